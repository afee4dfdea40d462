"""One benchmark method in its own fresh process (used by Testing/benchmark.py).

    python Testing/bench_worker.py TASK.pkl RESULT.pkl

The parent (:func:`run_isolated`) writes a task (plain types only), starts this script with
the same interpreter, waits (with a timeout) and reads the result. This module imports only
the standard library at the top, so the child's own start-up is what the task needs and
nothing of the parent (no re-import of the benchmark's __main__).

Measured in the child, for every kind of task:

- ``seconds``: wall time around the call only (imports and reading the inputs excluded),
  except for ``kind == "cli"``, where the clock starts before the command line's module is
  imported (the whole CLI run: imports, reading, reconstruction, writing);
- ``peak_rss_mb``: the process's peak resident set (VmHWM of /proc/self/status; not
  ru_maxrss, which on Linux carries the parent's RSS across exec);
- ``base_rss_mb``: the RSS just before the call (interpreter, libraries, inputs).

Task kinds (keys besides ``kind``):

- ``reconstruct``: ``ct``, ``mask``, ``params`` -> pipeline.reconstruct (one bone).
- ``many``: ``ct``, ``labels``, ``targets``, ``neighbours``, ``names``, ``params`` ->
  pipeline.reconstruct_many(..., keep_going=True).
- ``baseline``: ``ct``, ``mask``, ``method`` (a key of baselines.METHODS), ``params``,
  optional ``pad_air`` (voxels of air added around the CT, zeros around the mask: lets the
  baselines, which refuse segments touching the CT border, close a cut bone at the image
  boundary as a padded segment does in 3D Slicer).
- ``segment_surface``: ``labels``, ``value`` -> baselines.segment_closed_surface.
- ``slicer_default``: ``ct``, ``mask``, ``ht``, ``theta_max`` -> 3D Slicer's default closed
  surface on the CT's own grid: threshold [ht, theta_max], keep the islands touching the
  segment, discrete flying edges + windowed sinc (baselines.segment_closed_surface).
- ``cli``: ``argv``, ``log`` -> BoneWatertightLib.app.cli.main(argv), stdout/stderr to ``log``.

Every kind runs with the command line's process settings (numpy's transparent-huge-page advice
off, several-bone runs' Poisson in a helper process:
BoneWatertightLib.app.run.configure_own_process).

``cprofile: true`` runs the call under cProfile and returns the top functions.

``stage_memory: true`` (kinds ``reconstruct`` and ``many``, Linux) samples the process's memory
during the call from a second process (``bench_worker.py --sample PID PERIOD``, so the samples
never wait for the GIL that a long C call of the pipeline holds): every MEMORY_PERIOD_S it reads
VmRSS and VmHWM of /proc/PID/status and resets VmHWM (``echo 5 > /proc/PID/clear_refs``), so
each sample holds the exact peak resident memory since the previous one, short spikes included.
The result's ``stage_memory`` holds the samples in seconds from the start of the pipeline's run
(the zero of report.timings.total and of report.stage_spans, placed at the end of the call
minus timings.total: after taking its total the pipeline only builds its report), for
bench_stages.stage_memory. ``peak_rss_mb`` is then the largest of VmHWM before the call and every
sample's peak (VmHWM itself was reset).
"""

from __future__ import annotations

import os
import pickle
import sys
import time
import traceback

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
# Seconds between two memory samples of a ``stage_memory`` task.
MEMORY_PERIOD_S = 0.005


def _status_mb(key: str) -> float:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def _vm_mb(text: bytes, key: bytes) -> float:
    """The value (MB) of a ``Key:  N kB`` line of /proc/PID/status text; NaN where absent."""
    i = text.find(key)
    if i < 0:
        return float("nan")
    return float(text[i + len(key) + 1:text.index(b"kB", i)]) / 1024.0


def sample_memory(pid: int, period: float, stdin=None, stdout=None) -> None:
    """The sampler process's loop: one line ``ready <VmHWM before> <exact>`` once VmHWM was
    reset, then a sample every ``period`` s until stdin closes, then the samples (pickle).

    Sample i: CLOCK_MONOTONIC seconds, VmRSS then and the peak since sample i - 1 (VmHWM read,
    then reset; with ``exact`` False, where the reset is refused, only the RSS is sampled and
    the peak is the larger RSS of the interval's two ends). The /proc files stay open (one
    read and one write per sample)."""
    import select

    stdin = stdin or sys.stdin
    stdout = stdout or sys.stdout.buffer
    clock = time.CLOCK_MONOTONIC
    status = os.open(f"/proc/{pid}/status", os.O_RDONLY)
    try:
        clear = os.open(f"/proc/{pid}/clear_refs", os.O_WRONLY)
    except OSError:
        clear = None

    def read():
        text = os.pread(status, 8192, 0)
        return _vm_mb(text, b"VmRSS:"), _vm_mb(text, b"VmHWM:")

    def reset():
        try:
            os.write(clear, b"5")
            return True
        except OSError:
            return False

    _, before = read()
    exact = clear is not None and reset()
    t, rss, peak = [time.clock_gettime(clock)], [read()[0]], [float("nan")]
    stdout.write(f"ready {before!r} {int(exact)}\n".encode())
    stdout.flush()
    done = False
    while not done:
        done = bool(select.select([stdin], [], [], period)[0])
        now = time.clock_gettime(clock)
        r, h = read()
        if exact:
            reset()
        else:
            h = max(r, rss[-1])
        t.append(now)
        rss.append(r)
        peak.append(h)
    pickle.dump({"t": t, "rss_mb": rss, "peak_mb": peak, "exact": exact, "period_s": period},
                stdout, protocol=pickle.HIGHEST_PROTOCOL)
    stdout.flush()


class MemorySampler:
    """The sampler process of :func:`sample_memory`, watching this process."""

    def __init__(self, period: float = MEMORY_PERIOD_S):
        self.period = period
        self.proc = None
        self.before_mb = float("nan")
        self.exact = False

    def start(self) -> "MemorySampler":
        import subprocess

        self.proc = subprocess.Popen(
            [sys.executable, os.path.abspath(__file__), "--sample", str(os.getpid()),
             repr(self.period)], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        word, before, exact = self.proc.stdout.readline().decode().split()
        if word != "ready":
            raise RuntimeError(f"memory sampler: {word} {before}")
        self.before_mb, self.exact = float(before), exact == "1"
        return self

    def stop(self) -> dict:
        self.proc.stdin.close()  # the sampler takes one last sample and answers
        data = pickle.loads(self.proc.stdout.read())
        self.proc.wait()
        data["before_mb"] = self.before_mb
        return data


def _surface_out(surface, name="", label=0):
    import numpy as np

    cell = getattr(surface, "cell_data", None) or {}
    cap = cell.get("Cap")
    return {"name": name, "label": label, "ok": True, "error": None,
            "vertices": np.asarray(surface.vertices, np.float64),
            "faces": np.asarray(surface.faces, np.int64),
            "cap": None if cap is None else np.asarray(cap, np.uint8)}


def _pad_air(ct, mask, pad):
    import SimpleITK as sitk

    ct = sitk.ConstantPad(ct, [pad] * 3, [pad] * 3, -1000.0)
    mask = sitk.ConstantPad(sitk.Cast(mask != 0, sitk.sitkUInt8), [pad] * 3, [pad] * 3, 0)
    return ct, mask


def _slicer_default(ct, mask, ht, theta_max):
    """Threshold segment on the CT's grid, islands touching the segment, closed surface."""
    import numpy as np
    import SimpleITK as sitk
    from scipy import ndimage

    import baselines

    seg = sitk.Resample(mask, ct, sitk.Transform(), sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8)
    a = sitk.GetArrayViewFromImage(ct)
    m = (a >= ht) & (a <= theta_max)
    lab, n = ndimage.label(m)
    hit = np.unique(lab[(sitk.GetArrayViewFromImage(seg) > 0) & m])
    keep = np.isin(lab, hit[hit > 0])
    img = sitk.GetImageFromArray(keep.astype(np.uint8))
    img.CopyInformation(ct)
    return baselines.segment_closed_surface(img, 1)


def _call(task):
    """(function of no arguments doing the measured work, how to turn its value into bones)."""
    kind = task["kind"]
    if kind == "cli":
        def run_cli():
            from BoneWatertightLib.app import cli
            log = task.get("log")
            if log:
                with open(log, "w") as fh:
                    old = os.dup(1), os.dup(2)
                    sys.stdout.flush()
                    sys.stderr.flush()
                    os.dup2(fh.fileno(), 1)
                    os.dup2(fh.fileno(), 2)
                    try:
                        return cli.main(list(task["argv"]))
                    finally:
                        sys.stdout.flush()
                        sys.stderr.flush()
                        os.dup2(old[0], 1)
                        os.dup2(old[1], 2)
            return cli.main(list(task["argv"]))
        return run_cli, lambda rc: {"exit_code": rc, "bones": []}

    import SimpleITK as sitk

    from BoneWatertightLib.params import Parameters

    params = Parameters(**task.get("params", {}))
    if kind in ("reconstruct", "many"):
        from BoneWatertightLib import pipeline
        from BoneWatertightLib.report import to_plain
        from BoneWatertightLib.stages.poisson import import_open3d
        import_open3d()  # before the clock (the pipeline's own import_open3d is then ~0 s)
        ct = sitk.ReadImage(task["ct"])
        if kind == "reconstruct":
            mask = sitk.ReadImage(task["mask"])

            def conv(res):
                b = _surface_out(res.surface, res.name, res.label)
                b["report"] = to_plain(res.report)
                return {"bones": [b], "pairs": []}
            return (lambda: pipeline.reconstruct(ct, mask, params)), conv
        labels = sitk.ReadImage(task["labels"])
        names = {int(k): v for k, v in (task.get("names") or {}).items()}

        def conv(res):
            bones = []
            for r in res.bones:
                if r.ok:
                    b = _surface_out(r.surface, r.name, r.label)
                    b["report"] = to_plain(r.report)
                else:
                    b = {"name": r.name, "label": r.label, "ok": False,
                         "error": f"{type(r.error).__name__}: {r.error}"}
                bones.append(b)
            return {"bones": bones, "pairs": [to_plain(p) for p in res.pairs],
                    "joint": {"timings": to_plain(res.report.timings),
                              "stage_spans": to_plain(res.report.stage_spans),
                              "thresholds": to_plain(res.report.thresholds),
                              "neighbours": to_plain(res.report.neighbours),
                              "input": to_plain(res.report.input)}}
        neighbours = task.get("neighbours", "auto")
        return (lambda: pipeline.reconstruct_many(ct, labels, list(task["targets"]), params,
                                                  neighbours=neighbours, names=names,
                                                  keep_going=True)), conv

    import baselines
    import vtk  # noqa: F401

    if kind == "segment_surface":
        labels = sitk.ReadImage(task["labels"])
        return (lambda: baselines.segment_closed_surface(labels, int(task["value"]))), \
            lambda s: {"bones": [_surface_out(s)]}
    ct = sitk.ReadImage(task["ct"])
    mask = sitk.ReadImage(task["mask"])
    if task.get("pad_air"):
        ct, mask = _pad_air(ct, mask, int(task["pad_air"]))
    if kind == "baseline":
        import open3d  # noqa: F401  (direct_poisson's import, before the clock)
        fn = baselines.METHODS[task["method"]]
        return (lambda: fn(ct, mask, params)), lambda s: {"bones": [_surface_out(s)]}
    if kind == "slicer_default":
        return (lambda: _slicer_default(ct, mask, float(task["ht"]), float(task["theta_max"]))), \
            lambda s: {"bones": [_surface_out(s)]}
    raise ValueError(f"unknown task kind {kind!r}")


def run_task(task: dict) -> dict:
    for p in (ROOT, HERE):
        if p not in sys.path:
            sys.path.insert(0, p)
    out = {"kind": task["kind"], "ok": False}
    t_cli = time.perf_counter()
    sampler = None
    try:
        fn, conv = _call(task)
        out["base_rss_mb"] = _status_mb("VmRSS")
        if task.get("stage_memory"):
            if task["kind"] not in ("reconstruct", "many"):
                raise ValueError("stage_memory: only for kinds reconstruct and many")
            sampler = MemorySampler().start()
        prof = None
        if task.get("cprofile"):
            import cProfile
            prof = cProfile.Profile()
            prof.enable()
        t0 = t_cli if task["kind"] == "cli" else time.perf_counter()
        value = fn()
        t_end = time.perf_counter()
        out["seconds"] = t_end - t0
        if sampler is not None:
            # the call's end on the sampler's clock
            end_mono = time.clock_gettime(time.CLOCK_MONOTONIC) - (time.perf_counter() - t_end)
            mem = sampler.stop()
            sampler = None
        if prof is not None:
            prof.disable()
            import io
            import pstats
            s = io.StringIO()
            st = pstats.Stats(prof, stream=s)
            st.sort_stats("cumulative").print_stats("BoneWatertightLib", 45)
            s2 = io.StringIO()
            pstats.Stats(prof, stream=s2).sort_stats("tottime").print_stats(25)
            out["profile_cumulative"] = s.getvalue()
            out["profile_tottime"] = s2.getvalue()
        out["peak_rss_mb"] = _status_mb("VmHWM")
        out.update(conv(value))
        if task.get("stage_memory"):
            out["stage_memory"] = _aligned(mem, end_mono, out)
            out["peak_rss_mb"] = max(out["peak_rss_mb"], mem["before_mb"],
                                     max(p for p in mem["peak_mb"][1:]))
        out["ok"] = True
    except BaseException as exc:  # noqa: BLE001 - a failed method is a result
        out["error"] = f"{type(exc).__name__}: {exc}"
        out["error_type"] = type(exc).__name__
        out["traceback"] = traceback.format_exc(limit=8)
        out["peak_rss_mb"] = _status_mb("VmHWM")
        if sampler is not None:
            sampler.stop()
    return out


def _aligned(mem: dict, end_mono: float, out: dict) -> dict:
    """The samples in seconds from the start of the pipeline's run, with its stage spans."""
    joint = out.get("joint")
    rep = joint if joint is not None else out["bones"][0]["report"]
    total = rep["timings"]["total"]
    origin = end_mono - total
    return {"t_s": [t - origin for t in mem["t"]], "rss_mb": mem["rss_mb"],
            "peak_mb": mem["peak_mb"], "exact": mem["exact"], "period_s": mem["period_s"],
            "before_mb": mem["before_mb"], "total_s": total,
            "spans": list(rep.get("stage_spans") or [])}


def run_isolated(task: dict, timeout: float, workdir: str) -> dict:
    """Run one task in a fresh child process; returns its result (never raises)."""
    import subprocess
    import tempfile

    os.makedirs(workdir, exist_ok=True)
    fd, tpath = tempfile.mkstemp(prefix="task_", suffix=".pkl", dir=workdir)
    with os.fdopen(fd, "wb") as fh:
        pickle.dump(task, fh)
    rpath = tpath[:-4] + "_result.pkl"
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, os.path.abspath(__file__), tpath, rpath],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        output, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()  # the child this call started, by its pid
        proc.communicate()
        _unlink(tpath, rpath)
        return {"kind": task["kind"], "ok": False, "error": f"timeout after {timeout:.0f} s",
                "process_seconds": time.perf_counter() - t0}
    wall = time.perf_counter() - t0
    try:
        with open(rpath, "rb") as fh:
            res = pickle.load(fh)
    except (OSError, EOFError, pickle.UnpicklingError):
        tail = output.decode(errors="replace")[-1500:]
        res = {"kind": task["kind"], "ok": False,
               "error": f"worker died (exit code {proc.returncode}): {tail.strip()[-300:]}"}
    res["process_seconds"] = wall
    _unlink(tpath, rpath)
    return res


def _unlink(*paths):
    for p in paths:
        try:
            os.unlink(p)
        except OSError:
            pass


if __name__ == "__main__":
    if sys.argv[1] == "--sample":
        sample_memory(int(sys.argv[2]), float(sys.argv[3]))
        sys.exit(0)
    with open(sys.argv[1], "rb") as fh:
        _task = pickle.load(fh)
    # the command line's process settings for every kind: the call, the command line and the
    # baselines are timed alike.
    if ROOT not in sys.path:
        sys.path.insert(0, ROOT)
    from BoneWatertightLib.app.run import configure_own_process

    configure_own_process()
    _res = run_task(_task)
    with open(sys.argv[2], "wb") as fh:
        pickle.dump(_res, fh, protocol=pickle.HIGHEST_PROTOCOL)
