"""A reconstruction in a child Python process that a GUI timer can poll (issue 13).

3D Slicer's panel runs the pipeline outside its own process, as Slicer's CLI modules do: single
library calls (B-spline resampling, open3d's Poisson, the exact self-intersection test, a sparse
solve) take seconds each and hold the interpreter, so no progress callback on the GUI thread
can keep the panel painting. :class:`ChildRun` takes inputs already exported to SimpleITK (CT,
label image, the label values to reconstruct, their neighbours, names, :class:`Parameters`),
writes them into a private temporary folder (NRRD) and starts the project's own command line,
``[python, "-m", "BoneWatertightLib", ..., "--progress-lines"]``
(:mod:`BoneWatertightLib.app.cli`: the same run service as ``bonewatertight``). The caller
polls it:

- :meth:`ChildRun.poll` never blocks (a reader thread puts the child's ``PROGRESS`` lines into a
  queue) and returns the newest ``(fraction, message)`` and whether the child has finished;
- :meth:`ChildRun.cancel` terminates the child (SIGTERM: the command line removes what it
  staged and exits with 130; SIGKILL after a short grace for a child inside a long C call) and
  returns within a second;
- :meth:`ChildRun.result` loads the surfaces (VTP, LPS) and the JSON report into a
  :class:`ChildJoint` (the attributes of the pipeline's ``JointResult``: ``bones``, ``pairs``,
  ``report``, with typed reports), or raises the library's typed error (the child's ``ERROR``
  line names the class; else the exit code of :mod:`BoneWatertightLib.errors` decides; the
  child's ``error:`` line is the message).

The temporary folder is removed in every case (result, cancel, close, garbage collection,
the interpreter's exit, which also kills a child still running); one that a killed application
left behind is removed by the next run (:func:`remove_stale_folders`), and a child whose
parent is gone stops at its next progress line (its output pipe is broken). The child's stdin
is closed, its stdout and stderr are one pipe read by the thread, its
environment has the library's folder on ``PYTHONPATH``. Qt-free: standard library, numpy,
SimpleITK and the library only, so it is tested in CI with ``sys.executable``; inside Slicer
the executable is ``PythonSlicer`` (:func:`find_python_slicer`).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import queue
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import typing
import weakref
from dataclasses import dataclass, field
from typing import NamedTuple, Optional, Sequence

from .. import errors as _errors
from ..errors import (EXIT_CANCELLED, EXIT_DEPENDENCY, EXIT_FAILED, EXIT_INPUT, EXIT_INTERNAL,
                      EXIT_OUTPUT, EXIT_PARTIAL, BoneWatertightError, CancelledError,
                      DependencyError, EmptySegmentError, InputError, OutputError, ReconstructionError)
from ..io import files as bwfiles
from ..params import SCHEMA, Parameters
# One bone of a child run is the pipeline's own result type.
from ..pipeline import ReconstructionResult as ChildBone

PROGRESS_PREFIX = "PROGRESS "
ERROR_PREFIX = "ERROR "
# After SIGTERM, the child has this long (s) to remove its staged files and say so (its ERROR
# line) before it is killed (a child inside a long C call acts on the signal only after it).
# Once it has said so, it is not waited for (the interpreter's own exit can take longer).
CANCEL_GRACE_S = 0.4
# A child that has exited while something still holds its output pipe (a grandchild) counts
# as finished after this long (s).
PIPE_LINGER_S = 2.0
# Lines of the child's other output kept (the end: the error and a traceback).
OUTPUT_LINES_KEPT = 400
# The private folders are named FOLDER_PREFIX<pid of the process that made it>-<random>; one
# left by a process that is gone (killed before it could clean up) and older than
# STALE_FOLDER_S is removed by the next run in the same place.
FOLDER_PREFIX = "BoneWatertight-"
STALE_FOLDER_S = 60.0
CANCELLED_MESSAGE = "Cancelled by the user; nothing was changed."

_EXIT_ERRORS = {EXIT_INPUT: InputError, EXIT_FAILED: ReconstructionError,
                EXIT_PARTIAL: ReconstructionError,
                EXIT_DEPENDENCY: DependencyError, EXIT_OUTPUT: OutputError,
                EXIT_CANCELLED: CancelledError}


class ChildRunError(BoneWatertightError):
    """The reconstruction process died, was killed, failed internally or left no result."""


# ----------------------------------------------------------------------------------------
# where things are


def library_root() -> str:
    """The folder that holds the ``BoneWatertightLib`` package (goes on the child's PYTHONPATH)."""
    return os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _executable_names(stem: str) -> list:
    return [stem + ".exe", stem] if os.name == "nt" else [stem]


def find_python_slicer(app_dir: Optional[str] = None) -> str:
    """The Python interpreter for the child: 3D Slicer's ``PythonSlicer`` when there is one.

    Looked for in ``app_dir`` (``slicer.app.applicationDirPath()``, Slicer's ``bin``), then on
    PATH (Slicer's launcher puts its ``bin`` there), then beside ``sys.executable``. Without
    one, ``sys.executable`` (a plain Python: CI, scripts), unless that is the Slicer
    application itself (it would open a second Slicer): then DependencyError.
    """
    folders = [app_dir] if app_dir else []
    for folder in folders:
        for name in _executable_names("PythonSlicer"):
            candidate = os.path.join(folder, name)
            if os.path.isfile(candidate):
                return candidate
    found = shutil.which("PythonSlicer")
    if found:
        return found
    here = os.path.dirname(os.path.abspath(sys.executable or ""))
    for name in _executable_names("PythonSlicer"):
        candidate = os.path.join(here, name)
        if os.path.isfile(candidate):
            return candidate
    executable = sys.executable or ""
    base = os.path.basename(executable).lower()
    if not executable or (base.startswith("slicer") and "python" not in base):
        raise DependencyError(
            "3D Slicer's PythonSlicer was not found (looked in "
            + ", ".join(f for f in [*folders, "PATH", here] if f)
            + "), so the reconstruction cannot run in its own process. Reinstall 3D Slicer, or "
            "run it in the application's process (logic process()/processMany()).")
    return executable


def _resolve_executable(python: str) -> str:
    if os.path.dirname(python):
        if os.path.isfile(python) and os.access(python, os.X_OK):
            return python
        raise DependencyError(f"The Python interpreter for the reconstruction process does not "
                              f"exist or cannot be run: {python}.")
    found = shutil.which(python)
    if not found:
        raise DependencyError(f"The Python interpreter for the reconstruction process was not "
                              f"found on PATH: {python}.")
    return found


# ----------------------------------------------------------------------------------------
# what a finished run gives


@dataclass
class ChildJoint:
    """A finished child run: the attributes of the pipeline's ``JointResult`` (``bones`` in the
    order of the targets, ``pairs``, ``report``) and the child's exit code, command line and
    output (other lines than PROGRESS/ERROR)."""

    bones: list
    pairs: list
    report: object
    returncode: int = 0
    command: list = field(default_factory=list)
    output: list = field(default_factory=list)


class PollResult(NamedTuple):
    """What :meth:`ChildRun.poll` returns."""

    fraction: float
    message: str
    finished: bool


# ----------------------------------------------------------------------------------------
# typed reports from their JSON


def _typed(cls, data):
    """A report dataclass from its plain form (:func:`BoneWatertightLib.report.to_plain`);
    nested dataclass fields are rebuilt from their annotations, unknown keys ignored."""
    if data is None or not isinstance(data, dict):
        return data
    from ..mesh.checks import SurfaceReport
    from ..report import PairReport
    from ..stages.plausibility import Plausibility

    special = {"checks": SurfaceReport, "plausibility": Plausibility}
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        value = data[f.name]
        kind = special.get(f.name) if f.name in special else hints.get(f.name)
        if f.name == "pairs" and isinstance(value, list):
            value = [_typed(PairReport, v) for v in value]
        elif isinstance(kind, type) and dataclasses.is_dataclass(kind):
            value = _typed(kind, value)
        kwargs[f.name] = value
    obj = cls(**kwargs)
    if cls.__name__ == "SurfaceReport":
        import numpy as np

        obj.self_intersection_pairs = np.asarray(obj.self_intersection_pairs or [],
                                                 dtype=np.int64).reshape(-1, 2)
    return obj


def pipeline_report_from_dict(data: dict):
    """:class:`BoneWatertightLib.report.PipelineReport` from its JSON form."""
    from ..report import PipelineReport

    return _typed(PipelineReport, data)


def joint_report_from_dict(data: dict):
    """:class:`BoneWatertightLib.report.JointReport` from its JSON form."""
    from ..report import JointReport

    return _typed(JointReport, data)


def _joint_report_of_one(case: dict, pipeline):
    """The JointReport of a one-bone run, whose JSON report is the bone's CaseReport: grid,
    thresholds and ownership from the bone's pipeline report, and its times (all of a
    one-bone run's time is its bone's)."""
    from ..report import JointReport

    return JointReport(version=pipeline.version, parameters=dict(pipeline.parameters),
                       input=dict(pipeline.input), thresholds=dict(pipeline.thresholds),
                       ownership=dict(pipeline.ownership), pairs=[],
                       timings=dataclasses.replace(pipeline.timings),
                       neighbours=list(case.get("inputs", {}).get("neighbours") or []),
                       coordinate_system=pipeline.coordinate_system, units=pipeline.units,
                       stage_spans=list(pipeline.stage_spans))


# ----------------------------------------------------------------------------------------
# the command line of a run


def parameter_arguments(params: Parameters) -> list:
    """Command-line options that give the child exactly ``params`` (every schema field; a
    float as its repr, which reads back bit for bit)."""
    args = []
    for name, spec in SCHEMA.items():
        value = getattr(params, name)
        flag = "--" + name.replace("_", "-")
        if spec.kind is bool:
            args.append(flag if value else "--no-" + name.replace("_", "-"))
        elif value is None:
            args += [flag, "auto"]
        else:
            args += [flag, repr(value) if isinstance(value, float) else str(value)]
    return args


def _error_class(name: str, code: int):
    cls = getattr(_errors, str(name), None)
    if isinstance(cls, type) and issubclass(cls, BoneWatertightError):
        return cls
    return _EXIT_ERRORS.get(code)


def _signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"


# ----------------------------------------------------------------------------------------
# the run


def remove_stale_folders(root: Optional[str] = None, now: Optional[float] = None) -> list:
    """Remove the private folders of runs whose process is gone (POSIX; same machine), older
    than STALE_FOLDER_S, in ``root`` (default the system's temporary folder); return them."""
    if os.name != "posix":
        return []
    root = root or tempfile.gettempdir()
    now = time.time() if now is None else now
    removed = []
    for name in bwfiles.list_names(root):
        pid = name[len(FOLDER_PREFIX):].split("-", 1)[0]
        if not name.startswith(FOLDER_PREFIX) or not pid.isdigit() or bwfiles.pid_alive(int(pid)):
            continue  # not a run's folder, or its process is alive (this one included)
        path = os.path.join(root, name)
        try:
            if now - os.lstat(path).st_mtime < STALE_FOLDER_S or not os.path.isdir(path):
                continue
        except OSError:
            continue
        shutil.rmtree(path, ignore_errors=True)
        removed.append(path)
    return removed


def _cleanup(state: dict) -> None:
    """Kill a child still running and remove the temporary folder (idempotent; also the
    finalizer when a ChildRun is dropped without result/cancel/close)."""
    proc = state.get("proc")
    if proc is not None and proc.poll() is None:
        _kill(proc)
    folder = state.pop("folder", None)
    if folder:
        shutil.rmtree(folder, ignore_errors=True)


def _kill(proc) -> None:
    try:
        if os.name == "posix":
            os.killpg(proc.pid, signal.SIGKILL)  # the child leads its own session
        else:
            proc.kill()
    except (ProcessLookupError, PermissionError, OSError):
        try:
            proc.kill()
        except OSError:
            pass


class ChildRun:
    """One reconstruction (one or several bones of a label image) in a child process.

    Parameters
    ----------
    ct, labels : SimpleITK.Image
        The CT (HU) and the label image (0 background, a value per segment), any geometry, as
        ``pipeline.reconstruct_many`` takes them. Not modified; written from a helper thread,
        so the caller must not change them until the run has started.
    targets : sequence of int
        Label values to reconstruct (one surface each, in this order).
    names : dict, optional
        Label value -> name (reports, messages, pair names); default ``str(value)``.
    params : Parameters, optional
    neighbours : "auto", "none" or sequence of int
        The labels that compete as neighbours (as ``reconstruct_many``).
    python : str, optional
        The interpreter to run (default :func:`find_python_slicer`).
    env : dict, optional
        The child's environment (default ``os.environ``); the library's folder is put first
        on its PYTHONPATH.
    temp_root : str, optional
        Where the private temporary folder is made (default the system's).
    grace_s : float
        How long :meth:`cancel` waits for the child to exit on SIGTERM before killing it.
    check_labels : bool
        Refuse targets and neighbours without a voxel in ``labels`` before the child starts
        (EmptySegmentError / InputError, as in-process), in the helper thread (about 2 s per
        100 M voxels). False when the caller made sure (the MRML export does).

    Use: ``run = ChildRun(...).start()``, then ``run.poll()`` from a timer until ``finished``,
    then ``run.result()`` (or ``run.cancel()``). ``with ChildRun(...) as run:`` cleans up.
    """

    def __init__(self, ct, labels, targets: Sequence[int], names: Optional[dict] = None,
                 params: Optional[Parameters] = None, *, neighbours="auto",
                 python: Optional[str] = None, env: Optional[dict] = None,
                 temp_root: Optional[str] = None, grace_s: float = CANCEL_GRACE_S,
                 check_labels: bool = True):
        self.ct = ct
        self.labels = labels
        self.targets = [int(t) for t in targets]
        self.names = {int(k): str(v) for k, v in (names or {}).items()}
        self.params = (params or Parameters()).validate()
        if isinstance(neighbours, str):
            if neighbours.lower() not in ("auto", "none"):
                raise InputError(f"neighbours must be 'auto', 'none' or label values, not "
                                 f"'{neighbours}'.")
            self.neighbours = neighbours.lower()
        else:
            self.neighbours = [int(v) for v in neighbours]
        if not self.targets:
            raise InputError("No label to reconstruct: give at least one label value.")
        if len(set(self.targets)) != len(self.targets):
            raise InputError("The same bone is asked for twice; give each label once.")
        self.python = python
        self.env = env
        self.temp_root = temp_root
        self.grace_s = float(grace_s)
        self.check_labels = bool(check_labels)
        self.command: list = []
        self.output: list = []          # the child's other lines (the last OUTPUT_LINES_KEPT)
        self.errors: list = []          # the child's ERROR lines, parsed
        self.progress_log: list = []    # (time.monotonic(), fraction, message) of every line
        self.started_at: Optional[float] = None
        self._queue: "queue.Queue" = queue.Queue()
        self._lock = threading.Lock()
        self._state: dict = {}
        self._finalizer = weakref.finalize(self, _cleanup, self._state)
        self._thread: Optional[threading.Thread] = None
        self._done = threading.Event()
        self._failure: Optional[BaseException] = None
        self._cancelled = False
        self._exit_seen: Optional[float] = None
        self._fraction = 0.0
        self._message = ""
        self._folder: Optional[str] = None
        self._paths: dict = {}

    # -- state

    @property
    def proc(self) -> Optional[subprocess.Popen]:
        return self._state.get("proc")

    @property
    def pid(self) -> Optional[int]:
        proc = self.proc
        return proc.pid if proc is not None else None

    @property
    def folder(self) -> Optional[str]:
        """The private temporary folder (None once removed)."""
        return self._state.get("folder")

    @property
    def returncode(self) -> Optional[int]:
        proc = self.proc
        return proc.returncode if proc is not None else None

    @property
    def cancelled(self) -> bool:
        return self._cancelled

    @property
    def finished(self) -> bool:
        if self._done.is_set():
            return True
        proc = self.proc
        if proc is not None and proc.poll() is not None:
            # exited, but something (a grandchild) may still hold the pipe open
            now = time.monotonic()
            if self._exit_seen is None:
                self._exit_seen = now
            return now - self._exit_seen > PIPE_LINGER_S
        return False

    # -- start

    def start(self) -> "ChildRun":
        """Make the temporary folder and start the helper thread, which writes the inputs,
        starts the child and reads its output. Returns at once (``self``).

        DependencyError at once when the interpreter cannot be found or run.
        """
        if self._thread is not None:
            raise RuntimeError("This ChildRun was already started.")
        if self._cancelled:
            raise CancelledError(CANCELLED_MESSAGE)
        python = _resolve_executable(self.python or find_python_slicer())
        self.python = python
        remove_stale_folders(self.temp_root)
        folder = tempfile.mkdtemp(prefix=f"{FOLDER_PREFIX}{os.getpid()}-", dir=self.temp_root)
        self._state["folder"] = folder
        self._folder = folder
        self._paths = {"ct": os.path.join(folder, "ct.nrrd"),
                       "labels": os.path.join(folder, "labels.nrrd"),
                       "names": os.path.join(folder, "labels.csv"),
                       "out": os.path.join(folder, "out", "bone_{label}.vtp"),
                       "report": os.path.join(folder, "out", "report.json"),
                       "intermediates": os.path.join(folder, "intermediates")}
        self.started_at = time.monotonic()
        self._message = "Writing the inputs of the reconstruction process"
        self._thread = threading.Thread(target=self._work, name="BoneWatertight child run",
                                        daemon=True)
        self._thread.start()
        return self

    def _arguments(self) -> list:
        p = self._paths
        args = [self.python, "-m", "BoneWatertightLib", "--ct", p["ct"], "--seg", p["labels"]]
        for value in self.targets:
            args += ["--label", str(value)]
        neighbours = (self.neighbours if isinstance(self.neighbours, str)
                      else ",".join(str(v) for v in self.neighbours) or "none")
        args += ["--neighbours", neighbours, "--out", p["out"], "--report", p["report"]]
        if self.params.keep_intermediates:
            args += ["--save-intermediates", p["intermediates"]]
        return args + parameter_arguments(self.params) + ["--progress-lines", "--verbose"]

    def _environment(self) -> dict:
        env = dict(os.environ if self.env is None else self.env)
        root = library_root()
        parts = [root] + [x for x in env.get("PYTHONPATH", "").split(os.pathsep) if x and x != root]
        env["PYTHONPATH"] = os.pathsep.join(parts)
        env["PYTHONUNBUFFERED"] = "1"
        env["PYTHONIOENCODING"] = "utf-8"
        return env

    def _check_labels(self) -> None:
        """The targets and neighbours have voxels in the label image (the command line would
        refuse them with a message naming the temporary file)."""
        import SimpleITK as sitk

        image = self.labels
        if image.GetPixelID() not in (sitk.sitkUInt8, sitk.sitkUInt16, sitk.sitkUInt32,
                                      sitk.sitkInt8, sitk.sitkInt16, sitk.sitkInt32):
            return  # other types: the command line checks them
        stats = sitk.LabelStatisticsImageFilter()
        stats.Execute(image, image)  # multi-threaded C++, the interpreter stays free
        present = {int(v) for v in stats.GetLabels()} - {0}
        listing = ", ".join(str(v) for v in sorted(present)[:20]) or "none (it is empty)"
        missing = [t for t in self.targets if t not in present]
        if missing:
            which = ", ".join(f"{self.names.get(t, t)} ({t})" if t in self.names else str(t)
                              for t in missing)
            raise EmptySegmentError(
                f"Segment {which} has no voxel in the label image (labels with voxels: "
                f"{listing}): paint the bone in it, or pick another segment.")
        if not isinstance(self.neighbours, str):
            absent = [v for v in self.neighbours if v not in present]
            if absent:
                raise InputError(
                    f"Neighbour label(s) {', '.join(map(str, absent))} have no voxel in the label "
                    f"image (labels with voxels: {listing}). Give existing labels, or "
                    "neighbours 'auto' (every other label) or 'none'.")

    def _write_inputs(self) -> None:
        import SimpleITK as sitk

        p = self._paths
        try:
            sitk.WriteImage(self.ct, p["ct"], False)
            sitk.WriteImage(self.labels, p["labels"], False)
            with open(p["names"], "w", newline="", encoding="utf-8") as f:
                writer = csv.writer(f)
                writer.writerow(["value", "name"])
                for value, name in sorted(self.names.items()):
                    if name.strip():
                        writer.writerow([value, name])
        except (OSError, RuntimeError) as exc:
            if self._cancelled:
                raise CancelledError(CANCELLED_MESSAGE) from None
            text = " ".join(str(exc).split())
            raise OutputError(f"The inputs of the reconstruction process could not be written "
                              f"into {self._folder}: {text}") from None

    def _work(self) -> None:
        try:
            if self.check_labels:
                self._check_labels()
            if self._cancelled:
                return
            self._write_inputs()
            self.ct = self.labels = None  # on disk now: the caller's memory back
            self.command = self._arguments()
            kwargs = dict(stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, cwd=self._folder, env=self._environment(),
                          close_fds=True)
            if os.name == "posix":
                kwargs["start_new_session"] = True
            else:
                kwargs["creationflags"] = (getattr(subprocess, "CREATE_NEW_PROCESS_GROUP", 0)
                                           | getattr(subprocess, "CREATE_NO_WINDOW", 0))
            with self._lock:
                if self._cancelled:
                    return
                try:
                    proc = subprocess.Popen(self.command, **kwargs)
                except OSError as exc:
                    raise DependencyError(f"The reconstruction process could not be started "
                                          f"({self.python}): {exc}") from None
                self._state["proc"] = proc
            self._queue.put((0.0, "Starting the reconstruction process"))
            self._read(proc)
            proc.wait()
        except BaseException as exc:  # handed to result()
            self._failure = exc
        finally:
            self._done.set()
            if self._cancelled:
                _cleanup(self._state)

    def _read(self, proc) -> None:
        for raw in iter(proc.stdout.readline, b""):
            line = raw.decode("utf-8", errors="replace").rstrip("\r\n")
            if line.startswith(PROGRESS_PREFIX):
                parts = line[len(PROGRESS_PREFIX):].split(" ", 1)
                try:
                    fraction = float(parts[0])
                except ValueError:
                    self._keep(line)
                    continue
                message = parts[1] if len(parts) > 1 else ""
                self.progress_log.append((time.monotonic(), fraction, message))
                self._queue.put((fraction, message))
            elif line.startswith(ERROR_PREFIX):
                try:
                    self.errors.append(json.loads(line[len(ERROR_PREFIX):]))
                except ValueError:
                    self._keep(line)
            else:
                self._keep(line)
        proc.stdout.close()

    def _keep(self, line: str) -> None:
        self.output.append(line)
        if len(self.output) > OUTPUT_LINES_KEPT:
            del self.output[:len(self.output) - OUTPUT_LINES_KEPT]

    # -- the caller's timer

    def poll(self) -> PollResult:
        """The newest (fraction, message) of the child and whether it has finished. Never
        blocks (reads a queue the helper thread fills)."""
        latest = None
        while True:
            try:
                latest = self._queue.get_nowait()
            except queue.Empty:
                break
        if latest is not None:
            self._fraction = max(self._fraction, latest[0])
            self._message = latest[1]
        return PollResult(self._fraction, self._message, self.finished)

    def wait(self, timeout: Optional[float] = None) -> bool:
        """Block until the child has finished (console use); True if it has."""
        if self._thread is None:
            raise RuntimeError("The ChildRun was not started.")
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self.finished:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return False
            self._done.wait(0.1 if left is None else min(0.1, left))
        return True

    def cancel(self, grace_s: Optional[float] = None) -> None:
        """Stop the run: SIGTERM (the command line removes its staged files, exit 130), then
        SIGKILL after ``grace_s``; waits for the child to be gone and removes the temporary
        folder. Returns within about a second; safe to call more than once."""
        grace = self.grace_s if grace_s is None else float(grace_s)
        with self._lock:
            self._cancelled = True
            proc = self.proc
        if proc is not None and proc.poll() is None:
            try:
                proc.terminate()
            except OSError:
                pass
            deadline = time.monotonic() + grace
            while proc.poll() is None and time.monotonic() < deadline and not any(
                    e.get("type") == "CancelledError" for e in self.errors):
                time.sleep(0.01)
            if proc.poll() is None:
                _kill(proc)
                try:
                    proc.wait(1.0)
                except subprocess.TimeoutExpired:
                    pass
        if proc is not None and os.name == "posix":
            try:  # whatever the child started, in its session
                os.killpg(proc.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError, OSError):
                pass
        if self._thread is not None:
            self._thread.join(0.3)
        _cleanup(self._state)

    def close(self) -> None:
        """Cancel if still running, and remove the temporary folder."""
        if self._thread is not None and not self.finished:
            self.cancel()
        _cleanup(self._state)

    def __enter__(self) -> "ChildRun":
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False

    # -- the result

    def result(self, timeout: Optional[float] = None) -> ChildJoint:
        """The finished run's surfaces and reports (blocks until the child has finished; pass
        ``timeout`` to give up: ChildRunError). Raises the run's typed error instead; the
        temporary folder is removed either way."""
        try:
            if self._thread is None:
                raise RuntimeError("The ChildRun was not started.")
            if not self._cancelled and not self.wait(timeout):
                self.cancel()
                raise ChildRunError(f"The reconstruction process did not finish within "
                                    f"{timeout:g} s; it was stopped.")
            return self._load()
        finally:
            _cleanup(self._state)

    def error(self) -> Optional[BaseException]:
        """The typed error of a finished run (None when it succeeded)."""
        if self._cancelled:
            return CancelledError(CANCELLED_MESSAGE)
        if self._failure is not None:
            return self._failure
        proc = self.proc
        if proc is None:
            return ChildRunError("The reconstruction process was never started.")
        code = proc.returncode
        if code is None:
            return None
        if code == 0:
            return None
        if self.errors:
            first = self.errors[0]
            cls = _error_class(first.get("type"), int(first.get("code", code)))
            message = self._readable(str(first.get("message") or ""))
            if cls is not None:
                return cls(message)
            return ChildRunError(f"internal error in the reconstruction process: "
                                 f"{first.get('type')}: {message}{self._tail()}")
        said = [self._readable(line[len("error: "):]) for line in self.output
                if line.startswith("error: ")]
        if code < 0:
            name = _signal_name(-code)
            hint = " (the system may have run out of memory)" if -code == getattr(
                signal, "SIGKILL", 9) else ""
            return ChildRunError(f"The reconstruction process was killed by {name}{hint}; "
                                 f"nothing was written.{self._tail()}")
        cls = _EXIT_ERRORS.get(code)
        if said and cls is not None:
            return cls(said[-1])
        if code == EXIT_INTERNAL:
            text = said[-1] if said else "no message"
            return ChildRunError(f"The reconstruction process failed: {text}{self._tail()}")
        return ChildRunError(f"The reconstruction process ended with exit code {code}"
                             + (f": {said[-1]}" if said else "") + f".{self._tail()}")

    def _readable(self, message: str) -> str:
        """A message of the command line with the temporary input files named for what they
        are (the user never saw those paths)."""
        for key, what in (("ct", "the CT (as exported)"), ("labels", "the label image (as exported)")):
            path = self._paths.get(key)
            if path:
                message = message.replace(path, what)
        return message

    def _tail(self, lines: int = 12) -> str:
        tail = [line for line in self.output[-lines:] if line.strip()]
        return ("\nLast output of the process:\n" + "\n".join(tail)) if tail else ""

    def _load(self) -> ChildJoint:
        exc = self.error()
        if exc is not None:
            raise exc
        from ..io import meshes

        path = self._paths["report"]
        try:
            with open(path, encoding="utf-8") as f:
                data = json.load(f)
        except (OSError, ValueError) as err:
            raise ChildRunError(f"The reconstruction process left no readable report "
                                f"({err}).{self._tail()}") from None
        if isinstance(data, dict) and "surfaces" in data:
            cases, pairs_data, joint_data = data["surfaces"], data.get("pairs") or [], data.get("joint")
        else:
            cases, pairs_data, joint_data = [data], data.get("pairs") or [], None
        by_label = {}
        for case in cases:
            pipeline = pipeline_report_from_dict(case["pipeline"])
            value = int(case.get("inputs", {}).get("label", pipeline.label))
            name = str(case.get("inputs", {}).get("segment_name", pipeline.name))
            surface = meshes.read_surface(case["output"]["path"], "LPS")
            intermediates = self._intermediates(case["output"].get("intermediates") or [], name)
            by_label[value] = ChildBone(
                surface=surface, distance_to_constraints=surface.point_data.get(
                    "DistanceToConstraints"), report=pipeline, intermediates=intermediates,
                label=value, name=name)
        missing = [t for t in self.targets if t not in by_label]
        if missing:
            raise ChildRunError(f"The reconstruction process reported no surface for label(s) "
                                f"{', '.join(map(str, missing))}.{self._tail()}")
        bones = [by_label[t] for t in self.targets]
        from ..report import PairReport

        pairs = [_typed(PairReport, p) for p in pairs_data]
        if joint_data is not None:
            joint = joint_report_from_dict(joint_data)
        else:
            joint = _joint_report_of_one(cases[0], bones[0].report)
        return ChildJoint(bones=bones, pairs=pairs, report=joint, returncode=self.returncode or 0,
                          command=list(self.command), output=list(self.output))

    def _intermediates(self, paths, name: str) -> dict:
        """{name: Surface or (n, 3) points} from the files ``--save-intermediates`` wrote."""
        if not paths:
            return {}
        import numpy as np

        from ..io import meshes

        prefix = bwfiles.name_part(name) + "_"
        out = {}
        for path in paths:
            base = os.path.basename(path)
            stem, ext = os.path.splitext(base)
            if not stem.startswith(prefix):
                continue
            key = bwfiles.name_from_part(stem[len(prefix):])
            if ext == ".vtp":
                out[key] = meshes.read_surface(path, "LPS")
            elif ext == ".ply":
                from .. import _vtk as vtk
                from .._vtk import numpy_support as ns

                reader = vtk.vtkPLYReader()
                reader.SetFileName(path)
                reader.Update()
                points = reader.GetOutput().GetPoints()
                arr = (ns.vtk_to_numpy(points.GetData()).astype(np.float64) if points is not None
                       else np.zeros((0, 3)))
                out[key] = arr  # written in LPS (the run's coordinate system)
        return out
