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


class _Done:
    """The result of work done at once (the interface of a Future that :func:`background`
    uses)."""

    def __init__(self, work, args):
        self._value = work(*args)

    def result(self):
        return self._value


class _Background:
    """``work(*args)`` on a thread of its own; :meth:`result` waits for it (and raises its
    exception)."""

    def __init__(self, work, args, name):
        import threading

        self._value = self._error = None

        def target():
            try:
                self._value = work(*args)
            except BaseException as exc:  # handed to the caller by result()
                self._error = exc

        self._thread = threading.Thread(target=target, name=name, daemon=True)
        self._thread.start()

    def result(self):
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._value


def background(work, *args, name: str = "bonewatertight-background"):
    """``work(*args)`` started on a thread while the caller goes on (with more than one CPU;
    with one, done at once); the returned object's ``result()`` gives its value."""
    if cpu_threads(2) <= 1:
        return _Done(work, args)
    return _Background(work, args, name)
