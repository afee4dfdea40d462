"""Independent pieces of work on threads.

scipy.ndimage's filters and morphology, Qhull and numpy's loops release the GIL, so pieces of
work that do not depend on each other (bones, axes, slabs of a volume, two masks) run at once
on several CPUs. The results are those of running them one after the other.
"""

from __future__ import annotations

import os


def cpu_threads(cap: int) -> int:
    """Threads to use: one per CPU, at most ``cap`` (at least 1)."""
    return max(1, min(os.cpu_count() or 1, cap))


def thread_map(work, items, threads: int, name: str = "bonewatertight") -> list:
    """[work(x) for x in items], on up to ``threads`` threads (in order; the first exception
    is raised, as a loop would)."""
    items = list(items)
    if threads <= 1 or len(items) <= 1:
        return [work(x) for x in items]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(min(threads, len(items)), thread_name_prefix=name) as pool:
        return list(pool.map(work, items))


def map_ahead(work, items, threads: int, name: str = "bonewatertight"):
    """``work(x)`` for each of ``items`` (any iterable, consumed lazily), yielded in order; with
    ``threads`` > 1 the next items are worked on threads while the caller takes the results.
    The caller may stop early: at most the items ahead are wasted."""
    if threads <= 1:
        for x in items:
            yield work(x)
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(threads, thread_name_prefix=name) as pool:
        pending = []
        for x in items:
            pending.append(pool.submit(work, x))
            if len(pending) >= threads:
                yield pending.pop(0).result()
        while pending:
            yield pending.pop(0).result()


# Whether this process may start helper processes (a fresh Python interpreter through
# multiprocessing's spawn) for work that holds the GIL: only a process of its own says so (the
# command line, :func:`BoneWatertightLib.app.run.configure_own_process`); a host application's
# interpreter (3D Slicer's) may not be a Python that can be started so.
_HELPER_PROCESSES = False


def allow_helper_processes(allowed: bool = True) -> None:
    """Let this process start helper processes (see :class:`..stages.poisson.PoissonHelper`)."""
    global _HELPER_PROCESSES
    _HELPER_PROCESSES = bool(allowed)


def helper_processes_allowed() -> bool:
    return _HELPER_PROCESSES
