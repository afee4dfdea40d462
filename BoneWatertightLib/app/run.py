"""The run service: one case -> surface file(s), optional picture and intermediates, and a report.

Every front end goes through here and never through another: the command line
(:mod:`.cli`), the batch runner (:mod:`.batch`), ``Resources/Scripts/demo.py`` and the Slicer
batch script. Outputs are written only after the reconstruction succeeded, each one atomically
(:func:`BoneWatertightLib.io.files.atomic_path`); a failed case leaves no file behind.
"""

from __future__ import annotations

import os
import time
from typing import Optional, Sequence

import numpy as np

from .. import __version__
from ..errors import DependencyError, InputError, OutputError
from ..io import files as bwfiles
from ..io import images, meshes, segmentations
from ..params import Parameters
from ..report import (CaseReport, CaseTimes, DistanceSummary, OutputInfo, to_json)


def load_reconstruct():
    """The pipeline's entry function, or DependencyError when it cannot be imported."""
    try:
        from ..pipeline import reconstruct
    except ImportError as exc:
        if isinstance(exc, DependencyError):
            raise
        raise DependencyError(f"The reconstruction pipeline cannot be imported: {exc}") from exc
    return reconstruct


def safe_name(text: str) -> str:
    """``text`` reduced to characters that are safe in a file name."""
    keep = "".join(c if (c.isalnum() or c in "-_.") else "_" for c in str(text))
    return keep.strip("._") or "segment"


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


def run_case(ct, mask, segment_name: str, out: str, params: Parameters, *,
             coordinate_system: str = "LPS", picture: Optional[str] = None,
             intermediates_dir: Optional[str] = None, also: Sequence[str] = (),
             progress=None, inputs: Optional[dict] = None, read_seconds: float = 0.0,
             reconstruct=None) -> CaseReport:
    """Reconstruct one segment and write its outputs.

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

    Returns
    -------
    CaseReport
    """
    t_start = time.perf_counter()
    check_surface_path(out)
    for path in also:
        check_surface_path(path, "an extra output")
    reconstruct = reconstruct or load_reconstruct()
    t0 = time.perf_counter()
    result = reconstruct(ct, mask, params, progress)
    t_reconstruct = time.perf_counter() - t0
    surface = result.surface

    picture_path, picture_error, t_render = None, None, 0.0
    try:
        for path in (out, picture, *also):
            if path:
                bwfiles.ensure_folder(path)
        if picture:
            from . import render

            t1 = time.perf_counter()
            try:
                with bwfiles.atomic_path(picture) as tmp:
                    render.render_surface(surface, tmp, ct=ct, title=segment_name)
                picture_path = os.path.abspath(picture)
            except render.RenderUnavailable as exc:
                picture_error = str(exc)
            t_render = time.perf_counter() - t1
        t1 = time.perf_counter()
        written_intermediates = []
        if intermediates_dir and result.intermediates:
            written_intermediates = write_intermediates(result.intermediates, intermediates_dir,
                                                        segment_name, coordinate_system)
        meshes.write_surface(surface, out, coordinate_system)
        for path in also:
            meshes.write_surface(surface, path, coordinate_system)
        t_write = time.perf_counter() - t1
    except OSError as exc:
        if isinstance(exc, InputError):
            raise
        raise OutputError(f"Could not write the outputs: {exc}") from exc

    report = CaseReport(
        version=__version__,
        inputs=dict(inputs or {}, segment_name=segment_name),
        output=OutputInfo(
            path=os.path.abspath(out), format=bwfiles.extension(out),
            coordinate_system=coordinate_system, n_vertices=int(surface.n_vertices),
            n_faces=int(surface.n_faces), picture=picture_path, picture_error=picture_error,
            intermediates=written_intermediates, also=[os.path.abspath(p) for p in also]),
        coordinate_system=coordinate_system,
        checks=result.report.checks,
        distance_to_constraints_mm=DistanceSummary.of(result.distance_to_constraints),
        parameters=params.to_dict(),
        timings_s=CaseTimes(read=read_seconds, reconstruct=t_reconstruct, render=t_render,
                            write=t_write, stages=result.report.timings),
        pipeline=result.report,
    )
    report.timings_s.total = read_seconds + time.perf_counter() - t_start
    return report


def run_files(ct_path: str, seg_path: str, label, out: str, params: Parameters, *,
              ct_series: Optional[str] = None, case: Optional[str] = None,
              **kwargs) -> CaseReport:
    """Read the CT and one segment from files, then :func:`run_case`.

    ``out`` (and ``picture``, ``intermediates_dir`` in ``kwargs``) may hold ``{label}`` and
    ``{case}``; they are filled with the segment's name and ``case``.
    """
    t0 = time.perf_counter()
    ct = images.read_ct(ct_path, ct_series)
    mask, name = segmentations.read_segment(seg_path, label)
    read_seconds = time.perf_counter() - t0
    out = fill_template(out, name, case)
    for key in ("picture", "intermediates_dir"):
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
                        coordinate_system: str) -> list:
    """Points as .ply, surfaces as .vtp, images as .nrrd; returns the files written."""
    import SimpleITK as sitk

    from ..mesh.surface import Surface

    os.makedirs(folder, exist_ok=True)
    written = []
    prefix = safe_name(segment_name)
    for name, value in intermediates.items():
        base = os.path.join(folder, f"{prefix}_{safe_name(name)}")
        if isinstance(value, Surface):
            path = base + ".vtp"
            meshes.write_surface(value, path, coordinate_system)
        elif isinstance(value, np.ndarray) and value.ndim == 2 and value.shape[1] == 3:
            path = base + ".ply"
            meshes.write_points(value, path, coordinate_system)
        elif isinstance(value, sitk.Image):
            path = base + ".nrrd"
            with bwfiles.atomic_path(path) as tmp:
                sitk.WriteImage(value, tmp, True)
        else:
            continue
        written.append(os.path.abspath(path))
    return written


def write_report(report, path: str) -> str:
    """Write a report (or a list of them) as NaN-safe JSON, atomically; returns ``path``."""
    try:
        bwfiles.write_text(to_json(report), bwfiles.ensure_folder(path))
    except OSError as exc:
        if isinstance(exc, InputError):
            raise
        raise OutputError(f"Could not write the report {path}: {exc}") from exc
    return path


def write_reports(template: str, reports: list) -> None:
    """One JSON per report when ``template`` has ``{label}``, else one file (a list of
    surfaces when there are several)."""
    if "{label}" in template:
        for report in reports:
            write_report(report, fill_template(template, report.segment_name))
    elif len(reports) == 1:
        write_report(reports[0], template)
    elif reports:
        write_report({"tool": "BoneWatertight", "version": __version__, "surfaces": reports},
                     template)
