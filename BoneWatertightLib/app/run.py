"""The run service: one case -> surface file(s), optional picture and intermediates, and a report.

Every front end goes through here and never through another: the command line
(:mod:`.cli`), the batch runner (:mod:`.batch`), ``Resources/Scripts/demo.py`` and the Slicer
batch script. Outputs are written only after the reconstruction succeeded, as one output
transaction (:class:`BoneWatertightLib.io.files.OutputTransaction`): :func:`stage_outputs` is
the one place that stages the files of a case (surface, extra surfaces, intermediates,
picture, report) and :func:`case_transaction` the one that commits them, so they appear
together or not at all. A failure, Ctrl-C, SIGTERM or SIGHUP (see :func:`cancel_on_signals`)
removes every staged file and leaves earlier outputs as they were.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from .. import __version__
from ..errors import CancelledBySignal, DependencyError, InputError
from ..io import files as bwfiles
from ..io import images, meshes, segmentations
from ..params import Parameters
from ..report import (CaseReport, CaseTimes, DistanceSummary, OutputInfo, to_json)

# Signals that cancel a run like Ctrl-C does (SIGHUP: the terminal was closed).
CANCEL_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP")
                       if hasattr(signal, name))


_PIPELINE_MODULE = __package__.rsplit(".", 1)[0] + ".pipeline"
# While the pipeline and open3d are imported in a helper thread (seconds on first use), the
# progress callback is called at least this often (s): a panel keeps painting, Cancel is honoured.
IMPORT_TICK_S = 0.1
# The import's progress approaches its end with this time constant (s) (its length is unknown).
IMPORT_TIME_CONSTANT_S = 3.0


def tune_process_memory() -> bool:
    """Stop numpy asking the kernel for transparent huge pages for this process's arrays.

    For a process of its own (the command line, a batch worker, the Slicer panel's child run),
    never for a host application. The pipeline allocates and frees many temporary volumes of a
    few to a few hundred MB; with huge-page advice every fresh one is faulted in 2 MB pages
    that the kernel must find (``defrag=madvise`` compacts memory for them) and zero. Measured
    on the femur phantom, command line at the defaults, 2 cores: wall 24-29 s -> 18-20 s, kernel
    time 9-12 s -> 3-4 s, peak the same; the surface is vertex-identical. Returns True when the
    advice was turned off (numpy has the switch), False otherwise (nothing changes then).
    """
    for name in ("numpy._core.multiarray", "numpy.core.multiarray"):
        try:
            module = __import__(name, fromlist=["_set_madvise_hugepage"])
        except ImportError:
            continue
        switch = getattr(module, "_set_madvise_hugepage", None)
        if switch is not None:
            switch(False)
            return True
    return False


def configure_own_process() -> None:
    """Settings for a process of this package's own (the command line, a batch worker): numpy's
    huge-page advice off (:func:`tune_process_memory`), and several-bone runs may compute their
    Poisson surfaces in a helper process (:class:`..stages.poisson.PoissonHelper`)."""
    from ..threads import allow_helper_processes

    tune_process_memory()
    allow_helper_processes()


def _import_pipeline(with_open3d: bool):
    from .. import pipeline

    if with_open3d:
        from ..stages.poisson import import_open3d

        import_open3d()
    return pipeline


def load_pipeline(progress=None, start: float = 0.0, end: float = 0.0):
    """The pipeline module, or DependencyError when it (or open3d) cannot be imported.

    Without ``progress`` a plain import (open3d is imported by the pipeline's first stage).
    With it, the pipeline and open3d are imported in a helper thread while this thread calls
    ``progress(fraction in [start, end], "Loading open3d")`` every IMPORT_TICK_S, so a panel
    that runs in-process keeps painting and Cancel (``progress`` raising, e.g. CancelledError)
    is honoured; only imports happen in the thread. Should the threaded import fail for
    another reason than a missing package, it is retried on this thread.
    """
    if progress is not None:
        progress(start, "Loading open3d")
        if "open3d" not in sys.modules or _PIPELINE_MODULE not in sys.modules:
            failure = []

            def work():
                try:
                    _import_pipeline(True)
                except BaseException as exc:  # handed to this thread
                    failure.append(exc)

            # not a daemon: after a Cancel the import finishes in the background, and an
            # interpreter that exits meanwhile waits for it instead of tearing a half-loaded
            # extension down
            thread = threading.Thread(target=work, name="BoneWatertight import", daemon=False)
            t0 = time.monotonic()
            thread.start()
            while thread.is_alive():
                thread.join(IMPORT_TICK_S)
                if thread.is_alive():
                    elapsed = time.monotonic() - t0
                    progress(start + (end - start) * (1.0 - math.exp(-elapsed / IMPORT_TIME_CONSTANT_S)),
                             "Loading open3d")
            if failure and isinstance(failure[0], (ImportError, DependencyError)):
                raise _as_dependency_error(failure[0])
            # else, e.g. a library that insists on the main thread: imported below instead
    try:
        return _import_pipeline(progress is not None)
    except ImportError as exc:
        raise _as_dependency_error(exc) from exc


def _as_dependency_error(exc: BaseException) -> BaseException:
    if isinstance(exc, DependencyError) or not isinstance(exc, ImportError):
        return exc
    return DependencyError(f"The reconstruction pipeline cannot be imported: {exc}")


def load_reconstruct():
    """The pipeline's entry function, or DependencyError when it cannot be imported."""
    return load_pipeline().reconstruct


def safe_name(text: str) -> str:
    """``text`` as a part of a file name, one-to-one.

    Distinct segment names always give distinct file names: ``.`` and ``..`` become ``%2E``
    and ``%2E.``, ``femur left`` becomes ``femur%20left`` (see
    :func:`BoneWatertightLib.io.files.name_part`).
    """
    return bwfiles.name_part(text)


def fill_template(template: str, label: str, case: Optional[str] = None) -> str:
    """Replace ``{label}`` (and ``{case}``) in an output path template."""
    out = template.replace("{label}", safe_name(label))
    if case is not None:
        out = out.replace("{case}", safe_name(case))
    return out


def check_surface_path(path: str, what: str = "--out") -> None:
    """InputError unless ``path`` ends in a surface extension."""
    ext = bwfiles.extension(path)
    if ext not in meshes.SURFACE_EXTENSIONS:
        raise InputError(f"{what} must end in one of {', '.join(meshes.SURFACE_EXTENSIONS)}, "
                         f"not '{ext or path}'")


# ----------------------------------------------------------------------------------------
# signals

def _cancel_handler(signum, frame):
    """Cancel the run (raise CancelledBySignal), unless a commit is under way: then right
    after it (the files of a case are never half renamed)."""
    if bwfiles.defer_signal(signum):
        return
    raise CancelledBySignal(signum)


@contextlib.contextmanager
def cancel_on_signals(signals: Sequence[int] = CANCEL_SIGNALS):
    """Within the block, SIGINT, SIGTERM and SIGHUP raise :class:`CancelledBySignal`.

    That is a KeyboardInterrupt, so every output transaction under way is aborted (its staged
    files removed) and the front end exits with code 130. The previous handlers come back at
    the end. Outside the main thread (where Python cannot set handlers) it does nothing.
    """
    previous = {}
    try:
        for signum in signals:
            try:
                previous[signum] = signal.signal(signum, _cancel_handler)
            except (ValueError, OSError):  # not the main thread, or not settable
                pass
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


# ----------------------------------------------------------------------------------------
# one case

@contextlib.contextmanager
def case_transaction(transaction: Optional[bwfiles.OutputTransaction] = None):
    """The transaction the files of one case are staged into; commits them at the end.

    Without ``transaction`` a new one is committed when the block ends (every file appears
    at once) and aborted when it raises. With one (several cases committed together, e.g.
    the command line's repeated ``--label``), a failure discards only this case's files and
    the caller commits.
    """
    if transaction is None:
        with bwfiles.OutputTransaction() as tx:
            yield tx
        return
    mark = transaction.mark()
    try:
        yield transaction
    except BaseException:
        transaction.discard(mark)
        raise


@dataclass
class StagedOutputs:
    """What :func:`stage_outputs` staged (final paths) and how long it took."""

    picture: Optional[str] = None
    picture_error: Optional[str] = None
    intermediates: list = field(default_factory=list)
    render_seconds: float = 0.0
    write_seconds: float = 0.0


def stage_outputs(tx: bwfiles.OutputTransaction, result, ct, segment_name: str, out: str, *,
                  coordinate_system: str = "LPS", picture: Optional[str] = None,
                  intermediates_dir: Optional[str] = None,
                  also: Sequence[str] = ()) -> StagedOutputs:
    """Stage every file of one case into ``tx`` (nothing appears before ``tx`` commits).

    The surface (``out`` and ``also``), the intermediate results (into ``intermediates_dir``,
    when the result has them) and the picture. A picture that cannot be rendered offscreen
    is left out (``picture_error`` says why); every other failure raises (OutputError for an
    operating-system error, naming the file).
    """
    staged = StagedOutputs()
    t0 = time.perf_counter()
    for path in (out, *also):
        meshes.write_surface(result.surface, path, coordinate_system, transaction=tx)
    if intermediates_dir and result.intermediates:
        staged.intermediates = write_intermediates(result.intermediates, intermediates_dir,
                                                   segment_name, coordinate_system,
                                                   transaction=tx)
    staged.write_seconds = time.perf_counter() - t0
    if picture:
        from . import render

        t1 = time.perf_counter()
        mark = tx.mark()
        try:
            staged.picture = tx.write(picture, lambda tmp: render.render_surface(
                result.surface, tmp, ct=ct, title=segment_name))
        except render.RenderUnavailable as exc:
            tx.discard(mark)
            staged.picture_error = str(exc)
        staged.render_seconds = time.perf_counter() - t1
    return staged


def run_case(ct, mask, segment_name: str, out: str, params: Parameters, *,
             coordinate_system: str = "LPS", picture: Optional[str] = None,
             intermediates_dir: Optional[str] = None, also: Sequence[str] = (),
             progress=None, inputs: Optional[dict] = None, read_seconds: float = 0.0,
             reconstruct=None, report_path: Optional[str] = None,
             transaction: Optional[bwfiles.OutputTransaction] = None) -> CaseReport:
    """Reconstruct one segment and write its outputs, all together or none.

    Parameters
    ----------
    ct, mask : SimpleITK.Image
        The CT (HU) and the rough segment (non-zero inside), any geometry. Not modified.
    segment_name : str
        Name used in the report, the summary line and intermediate file names.
    out : str
        The surface file (.stl, .ply, .vtp, .vtk, .obj); its folder is created.
    params : Parameters
    coordinate_system : {"LPS", "RAS"}
        Coordinates written into the files (the files say which).
    picture : str, optional
        A PNG to render. When offscreen rendering is unavailable the run still succeeds:
        ``report.output.picture`` is None and ``picture_error`` says why.
    intermediates_dir : str, optional
        Folder for the intermediate point sets and surfaces (needs
        ``params.keep_intermediates``).
    also : sequence of str
        More surface files of the same result (e.g. a .vtp beside the .stl).
    progress : callable, optional
        ``progress(fraction, message)``; returning False cancels (CancelledError).
    inputs : dict, optional
        Description of the inputs for the report.
    read_seconds : float
        Time the caller spent reading the inputs (reported).
    reconstruct : callable, optional
        The pipeline entry (default :func:`BoneWatertightLib.pipeline.reconstruct`).
    report_path : str, optional
        The JSON report, written in the same transaction as the surface.
    transaction : OutputTransaction, optional
        Stage the files into this transaction instead of committing them here (the caller
        commits; on failure this case's files are discarded from it).

    Returns
    -------
    CaseReport

    Raises
    ------
    InputError, ReconstructionError, DependencyError, CancelledError
        From the pipeline (nothing is written).
    OutputError
        A file could not be written (nothing is written; earlier files are kept).
    """
    t_start = time.perf_counter()
    check_surface_path(out)
    for path in also:
        check_surface_path(path, "an extra output")
    reconstruct = reconstruct or load_reconstruct()
    t0 = time.perf_counter()
    result = reconstruct(ct, mask, params, progress)
    t_reconstruct = time.perf_counter() - t0

    with case_transaction(transaction) as tx:
        staged = stage_outputs(tx, result, ct, segment_name, out,
                               coordinate_system=coordinate_system, picture=picture,
                               intermediates_dir=intermediates_dir, also=also)
        report = _case_report(result, params, staged, out=out, also=also,
                              coordinate_system=coordinate_system,
                              inputs=dict(inputs or {}, segment_name=segment_name),
                              read_seconds=read_seconds, t_reconstruct=t_reconstruct,
                              t_start=t_start, report_path=report_path)
        if report_path:
            write_report(report, report_path, transaction=tx)
    return report


def _case_report(result, params: Parameters, staged: StagedOutputs, *, out: str, also,
                 coordinate_system: str, inputs: dict, read_seconds: float,
                 t_reconstruct: float, t_start: float, report_path: Optional[str],
                 pairs: Optional[list] = None) -> CaseReport:
    """The CaseReport of one bone whose files were staged (``staged``) into ``out``/``also``."""
    surface = result.surface
    report = CaseReport(
        version=__version__,
        inputs=inputs,
        output=OutputInfo(
            path=os.path.abspath(out), format=bwfiles.extension(out),
            coordinate_system=coordinate_system, n_vertices=int(surface.n_vertices),
            n_faces=int(surface.n_faces), picture=staged.picture,
            picture_error=staged.picture_error, intermediates=staged.intermediates,
            also=[os.path.abspath(p) for p in also],
            report=os.path.abspath(report_path) if report_path else None),
        coordinate_system=coordinate_system,
        checks=result.report.checks,
        distance_to_constraints_mm=DistanceSummary.of(result.distance_to_constraints),
        parameters=params.to_dict(),
        timings_s=CaseTimes(read=read_seconds, reconstruct=t_reconstruct,
                            render=staged.render_seconds, write=staged.write_seconds,
                            stages=result.report.timings),
        pipeline=result.report,
        pairs=list(pairs or []),
    )
    report.timings_s.total = read_seconds + time.perf_counter() - t_start
    return report


def load_reconstruct_many():
    """The several-bone pipeline entry, or DependencyError when it cannot be imported."""
    return load_pipeline().reconstruct_many


def reconstruct_joint(ct, labels, targets: Sequence[int], params: Parameters, progress=None, *,
                      names: Optional[dict] = None, neighbours="auto", keep_going: bool = False):
    """Reconstruct the bones ``targets`` of a label image together, in this process.

    The one call of the several-bone pipeline for every front end: :func:`run_joint` (the
    command line, hence also a child run of :class:`.child.ChildRun`, and the Slicer batch
    script) and the in-process run on MRML nodes (:func:`.nodes.run_many_on_nodes`). Arguments
    as :func:`BoneWatertightLib.pipeline.reconstruct_many`; returns its JointResult.
    DependencyError when the pipeline cannot be imported.
    """
    return load_reconstruct_many()(ct, labels, [int(t) for t in targets], params, progress,
                                   neighbours=neighbours, names=names, keep_going=keep_going)


@dataclass
class JointRun:
    """What :func:`run_joint` did: one CaseReport per bone that succeeded, one (name, error)
    per bone that failed, and the pair checks."""

    reports: list
    failures: list
    pairs: list
    joint: object = None


def run_joint(ct, labels, targets: Sequence[int], names: dict, outputs: dict,
              params: Parameters, *, coordinate_system: str = "LPS",
              pictures: Optional[dict] = None, intermediates_dir: Optional[str] = None,
              also: Optional[dict] = None, neighbours="auto", progress=None,
              inputs: Optional[dict] = None, read_seconds: float = 0.0,
              report_path: Optional[str] = None, keep_going: bool = True,
              transaction: Optional[bwfiles.OutputTransaction] = None) -> JointRun:
    """Reconstruct several bones of one label map together and write their outputs.

    Parameters
    ----------
    ct, labels : SimpleITK.Image
        The CT (HU) and the label map (0 background; every label a bone). Not modified.
    targets : sequence of int
        Label values to reconstruct.
    names : dict
        Label value -> name (reports, summary lines, ``{label}`` in file names).
    outputs : dict
        Label value -> surface file.
    params : Parameters
    coordinate_system : {"LPS", "RAS"}
    pictures, also : dict, optional
        Label value -> PNG to render / more surface files of that bone.
    intermediates_dir : str, optional
    neighbours : "auto", "none" or sequence of int
        The labels competing as neighbours (default: every other label).
    progress : callable, optional
    inputs : dict, optional
        Description of the inputs for the reports.
    read_seconds : float
    report_path : str, optional
        One JSON report (``{label}`` in it: one per bone), in the same transaction.
    keep_going : bool
        A bone that fails does not stop the others (its error is in ``failures``).
    transaction : OutputTransaction, optional
        Stage into this transaction (the caller commits) instead of committing here.

    Returns
    -------
    JointRun
    """
    t_start = time.perf_counter()
    for value in targets:
        check_surface_path(outputs[value])
        for path in (also or {}).get(value, ()):
            check_surface_path(path, "an extra output")
    t0 = time.perf_counter()
    joint = reconstruct_joint(ct, labels, targets, params, progress, names=names,
                              neighbours=neighbours, keep_going=keep_going)
    t_reconstruct = time.perf_counter() - t0
    reports, failures = [], []
    with case_transaction(transaction) as tx:
        for result in joint.bones:
            if not result.ok:
                failures.append((result.name, result.error))
                continue
            value = result.label
            staged = stage_outputs(tx, result, ct, result.name, outputs[value],
                                   coordinate_system=coordinate_system,
                                   picture=(pictures or {}).get(value),
                                   intermediates_dir=intermediates_dir,
                                   also=(also or {}).get(value, ()))
            report = _case_report(
                result, params, staged, out=outputs[value], also=(also or {}).get(value, ()),
                coordinate_system=coordinate_system,
                inputs=dict(inputs or {}, segment_name=result.name, label=value,
                            neighbours=joint.report.neighbours),
                read_seconds=read_seconds, t_reconstruct=t_reconstruct, t_start=t_start,
                report_path=report_path,
                pairs=[p for p in joint.pairs if result.name in (p.a, p.b)])
            reports.append(report)
        if report_path and reports:
            if "{label}" in report_path:
                for report in reports:
                    write_report(report, fill_template(report_path, report.segment_name), tx)
            elif len(reports) == 1 and not failures:
                write_report(reports[0], report_path, tx)
            else:
                write_report({"tool": "BoneWatertight", "surfaces": reports,
                              "failed": [{"segment": n, "error": str(e)} for n, e in failures],
                              "pairs": joint.pairs, "joint": joint.report}, report_path, tx)
    return JointRun(reports=reports, failures=failures, pairs=joint.pairs, joint=joint.report)


def run_files(ct_path: str, seg_path: str, label, out: str, params: Parameters, *,
              ct_series: Optional[str] = None, case: Optional[str] = None,
              **kwargs) -> CaseReport:
    """Read the CT and one segment from files, then :func:`run_case`.

    ``out`` (and ``picture``, ``intermediates_dir``, ``report_path`` in ``kwargs``) may hold
    ``{label}`` and ``{case}``; they are filled with the segment's name and ``case``.
    """
    t0 = time.perf_counter()
    ct = images.read_ct(ct_path, ct_series)
    mask, name = segmentations.read_segment(seg_path, label)
    read_seconds = time.perf_counter() - t0
    out = fill_template(out, name, case)
    for key in ("picture", "intermediates_dir", "report_path"):
        if kwargs.get(key):
            kwargs[key] = fill_template(kwargs[key], name, case)
    inputs = {"ct": os.path.abspath(ct_path), "seg": os.path.abspath(seg_path),
              "label": str(label), "ct_size": list(ct.GetSize()),
              "ct_spacing": list(ct.GetSpacing())}
    if case is not None:
        inputs["case"] = case
    inputs.update(kwargs.pop("inputs", None) or {})
    return run_case(ct, mask, name, out, params, inputs=inputs, read_seconds=read_seconds,
                    **kwargs)


def write_intermediates(intermediates: dict, folder: str, segment_name: str,
                        coordinate_system: str,
                        transaction: Optional[bwfiles.OutputTransaction] = None) -> list:
    """Points as .ply, surfaces as .vtp, images as .nrrd; returns the files (final paths).

    Staged into ``transaction`` when given, else written together in one transaction of
    their own.
    """
    if transaction is None:
        with bwfiles.OutputTransaction() as tx:
            return write_intermediates(intermediates, folder, segment_name, coordinate_system,
                                       transaction=tx)
    import SimpleITK as sitk

    from ..mesh.surface import Surface

    written = []
    prefix = safe_name(segment_name)
    for name, value in intermediates.items():
        base = os.path.join(folder, f"{prefix}_{safe_name(name)}")
        if isinstance(value, Surface):
            path = meshes.write_surface(value, base + ".vtp", coordinate_system,
                                        transaction=transaction)
        elif isinstance(value, np.ndarray) and value.ndim == 2 and value.shape[1] == 3:
            path = meshes.write_points(value, base + ".ply", coordinate_system,
                                       transaction=transaction)
        elif isinstance(value, sitk.Image):
            path = transaction.write(base + ".nrrd", lambda tmp, image=value: _write_image(
                image, tmp))
        else:
            continue
        written.append(os.path.abspath(path))
    return written


def _write_image(image, path: str) -> None:
    """sitk.WriteImage (compressed), its RuntimeError as the OSError it is."""
    import SimpleITK as sitk

    try:
        sitk.WriteImage(image, path, True)
    except RuntimeError as exc:
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        raise OSError(lines[-1] if lines else "SimpleITK could not write the image") from None


def write_report(report, path: str,
                 transaction: Optional[bwfiles.OutputTransaction] = None) -> str:
    """Write a report (or a list of them) as NaN-safe JSON, atomically; returns ``path``.

    Staged into ``transaction`` when given. OutputError (exit code 5) when it cannot be
    written.
    """
    bwfiles.write_text(to_json(report), path, transaction=transaction)
    return path


def write_reports(template: str, reports: list,
                  transaction: Optional[bwfiles.OutputTransaction] = None) -> None:
    """One JSON per report when ``template`` has ``{label}``, else one file (a list of
    surfaces when there are several). All in one transaction (``transaction`` or their own)."""
    if transaction is None:
        with bwfiles.OutputTransaction() as tx:
            write_reports(template, reports, tx)
        return
    if "{label}" in template:
        for report in reports:
            write_report(report, fill_template(template, report.segment_name), transaction)
    elif len(reports) == 1:
        write_report(reports[0], template, transaction)
    elif reports:
        write_report({"tool": "BoneWatertight", "version": __version__, "surfaces": reports},
                     template, transaction)
