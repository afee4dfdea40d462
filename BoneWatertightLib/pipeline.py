"""The entry function: CT + rough segment -> checked watertight 2-manifold bone surface.

The only place that unpacks :class:`~BoneWatertightLib.params.Parameters`: each stage of
:mod:`BoneWatertightLib.stages` gets arrays and explicit keyword arguments. Inside the pipeline
volumes are (z, y, x) arrays on the isotropic working grid and points are (n, 3) x-y-z grid
millimetres; the result is mapped to physical LPS millimetres at the end.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import SimpleITK as sitk
from scipy import ndimage
from scipy.spatial import cKDTree

from . import __version__
from .errors import SurfaceCheckError
from .mesh.checks import check_surface
from .mesh.operators import sample_field
from .mesh.surface import Surface, enclosed_volume, mean_edge_length, surface_area
from .params import Parameters
from .progress import Progress, ProgressCallback
from .report import Counts, DistanceSummary, PipelineReport, Refinement, StageTimes, constants_of
from .stages import deform as _deform, filtering as _filtering, poisson as _poisson  # noqa: I100
from .stages import prepare as _prepare, refine as _refine, threshold as _threshold
from .stages import visible as _visible
from .stages.deform import Deformer
from .stages.filtering import hybrid_filter
from .stages.poisson import import_open3d, initial_surface, mask_normals
from .stages.prepare import prepare as prepare_inputs
from .stages.refine import refine_to_edges
from .stages.threshold import boundary_voxels, crossing_points, two_step_threshold, voxel_points
from .stages.visible import visible_points
from .mesh import checks as _checks, operators as _operators

# The filter's percentile is taken within this distance (mm) of the segment.
FILTER_REGION_MM = 3.0
# Smoothing (voxels) of the occupancy whose 0.5 level is the deformation's inside test.
OCCUPANCY_SIGMA_VOXELS = 0.7
OCCUPANCY_LEVEL = 0.5
# The CT that the edge refinement samples is smoothed by max(REFINE_SIGMA_MIN_VOXELS,
# REFINE_SIGMA_MM / d) voxels.
REFINE_SIGMA_MM = 0.4
REFINE_SIGMA_MIN_VOXELS = 0.5

# Overall progress fraction at the start of each stage.
STAGES = [("prepare", 0.0, 0.08), ("filter", 0.08, 0.14), ("threshold", 0.14, 0.30),
          ("visible", 0.30, 0.42), ("poisson", 0.42, 0.55), ("deform", 0.55, 0.88),
          ("refine", 0.88, 0.93), ("checks", 0.93, 1.0)]


@dataclass
class ReconstructionResult:
    """The checked surface (physical LPS mm), its per-vertex distance to the constraint points
    (mm, (n,) float64), the typed report and, on request, the intermediate results."""

    surface: Surface
    distance_to_constraints: np.ndarray
    report: PipelineReport
    intermediates: dict = field(default_factory=dict)


def _stage(progress: Progress, name: str) -> Progress:
    for n, a, b in STAGES:
        if n == name:
            sub = progress.stage(a, b)
            sub(0.0, name)
            return sub
    raise KeyError(name)


def reconstruct(ct: sitk.Image, mask: sitk.Image, params: Optional[Parameters] = None,
                progress: Optional[ProgressCallback] = None) -> ReconstructionResult:
    """Reconstruct bone k's surface.

    :param ct: CT volume in HU (SimpleITK image, any direction matrix). Not modified.
    :param mask: rough segment of bone k (non-zero = segment), any geometry. Not modified.
    :param params: pipeline parameters (paper defaults when None).
    :param progress: callback(fraction, message); returning False cancels (CancelledError).
    :return: result with the surface in physical LPS coordinates (mm), outward normals,
        per-vertex distance to the constraint points, a typed report and, when
        ``params.keep_intermediates``, the intermediate point sets and M0 (physical LPS).
    :raises InputError, SeparationError, ReconstructionError, SurfaceCheckError, CancelledError.
    """
    params = (params or Parameters()).validate()
    prog = Progress(progress)
    times = StageTimes()
    t_all = time.perf_counter()
    inter = {}

    # open3d first: a missing dependency must fail before minutes of work, and its one-off
    # import (~3 s) is reported apart from the Poisson stage.
    t0 = time.perf_counter()
    import_open3d()
    times.import_open3d = time.perf_counter() - t0

    t0 = time.perf_counter()
    prep = prepare_inputs(ct, mask, spacing=params.spacing, margin=params.margin,
                          max_memory_gb=params.max_memory_gb)
    grid, d = prep.grid, prep.grid.spacing
    times.prepare = time.perf_counter() - t0
    sub = _stage(prog, "filter")

    t0 = time.perf_counter()
    near_segment = ndimage.binary_dilation(prep.segment,
                                           iterations=max(1, int(round(FILTER_REGION_MM / d))))
    ct_f = hybrid_filter(prep.ct, d, sigma=params.sigma, rho=params.rho, region=near_segment)
    times.filter = time.perf_counter() - t0
    sub = _stage(prog, "threshold")

    t0 = time.perf_counter()
    thr = two_step_threshold(ct_f, prep.segment, d, h0=params.h0, ht=params.ht,
                             theta_max=params.theta_max, max_erosions=params.max_erosions,
                             opening=params.opening, closing=params.closing,
                             segment_dilation=params.segment_dilation, progress=sub)
    times.threshold = time.perf_counter() - t0

    t0 = time.perf_counter()
    surf_vox = boundary_voxels(thr.solid_h0)
    p_h0_surface = voxel_points(surf_vox, d)
    sub = _stage(prog, "visible")
    vis_idx, vis_info = visible_points(p_h0_surface, d, views=params.views,
                                       view_distance=params.view_distance,
                                       log_radius=params.log_radius, progress=sub)
    visible = p_h0_surface[vis_idx]
    # B* = S(P_H0) U (P_HT - P_H0); of P_HT - P_H0 only the outer boundary can be reached by
    # the directional search, and we place it sub-voxel where the CT crosses HT.
    b_ht = crossing_points(ct_f, thr.occupancy, params.ht, d)
    constraints = np.vstack([visible, b_ht])
    times.visible = time.perf_counter() - t0

    sub = _stage(prog, "poisson")
    t0 = time.perf_counter()
    edge = params.edge_length if params.edge_length is not None else d
    normals = mask_normals(thr.solid_h0, visible, d)
    m0, raw = initial_surface(visible, normals, params.poisson_depth, edge)
    times.poisson = time.perf_counter() - t0

    sub = _stage(prog, "deform")
    t0 = time.perf_counter()
    history = []
    if params.iterations > 0:
        occ_field = ndimage.gaussian_filter(thr.occupancy.astype(np.float32),
                                            sigma=OCCUPANCY_SIGMA_VOXELS)
        deformer = Deformer(m0.vertices, m0.faces, constraints,
                            lambda pts: sample_field(occ_field, pts, d) >= OCCUPANCY_LEVEL,
                            mean_edge_length(m0.vertices, m0.faces),
                            iterations=params.iterations, alpha=params.alpha, beta=params.beta,
                            search_radius=params.search_radius,
                            search_offset=params.search_offset)
        verts = deformer.run(progress=sub)
        history = deformer.history
    else:
        verts = m0.vertices.copy()
    times.deform = time.perf_counter() - t0
    faces = m0.faces

    sub = _stage(prog, "refine")
    t0 = time.perf_counter()
    refine_info = Refinement(applied=False)
    deformed = verts
    if params.refine_edges:
        ct_smooth = ndimage.gaussian_filter(
            prep.ct, sigma=max(REFINE_SIGMA_MIN_VOXELS, REFINE_SIGMA_MM / d), mode="nearest")
        verts, shift, frac_ok = refine_to_edges(deformed, faces, ct_smooth, d, params.ht,
                                                edge_level=params.edge_level)
        refine_info = Refinement(applied=True, fraction_with_edge=frac_ok,
                                 mean_shift_mm=float(shift.mean()),
                                 mean_abs_shift_mm=float(np.abs(shift).mean()))
    times.refine = time.perf_counter() - t0

    sub = _stage(prog, "checks")
    t0 = time.perf_counter()
    phys = grid.grid_to_physical(verts)
    if enclosed_volume(phys, faces) < 0:  # a reflecting direction matrix flips orientation
        faces = faces[:, ::-1].copy()
    report_checks = check_surface(phys, faces)
    times.checks = time.perf_counter() - t0
    if not report_checks.ok:
        raise SurfaceCheckError(
            "The reconstructed surface failed the watertight 2-manifold checks: "
            + "; ".join(report_checks.problems)
            + ". Try a finer resample spacing, more deformation stiffness (alpha), or fewer iterations.",
            report=report_checks)
    dist, _ = cKDTree(grid.grid_to_physical(constraints)).query(phys, workers=-1)
    surface = Surface(phys, faces, "LPS", {"DistanceToConstraints": dist})
    times.total = time.perf_counter() - t_all

    if params.keep_intermediates:
        inter = {
            "P_H0": grid.grid_to_physical(voxel_points(thr.w_h0, d)),
            "P_HT": grid.grid_to_physical(voxel_points(thr.w_ht & ~thr.w_h0, d)),
            "visible_points": grid.grid_to_physical(visible),
            "constraints": grid.grid_to_physical(constraints),
            "M0": Surface(grid.grid_to_physical(m0.vertices), m0.faces if enclosed_volume(
                grid.grid_to_physical(m0.vertices), m0.faces) > 0 else m0.faces[:, ::-1].copy()),
            "deformed": Surface(grid.grid_to_physical(deformed), faces),
        }
    report = PipelineReport(
        version=__version__,
        parameters=params.to_dict(),
        input=prep.info,
        timings=times,
        threshold=thr.info,
        counts=Counts(
            p_h0_surface_points=int(len(p_h0_surface)), visible_points=int(len(visible)),
            ht_boundary_points=int(len(b_ht)), constraint_points=int(len(constraints)),
            poisson_raw_vertices=int(raw.n_vertices), m0_vertices=int(m0.n_vertices),
            m0_faces=int(m0.n_faces), vertices=int(len(phys)), faces=int(len(faces))),
        visible=vis_info,
        deformation=history,
        refinement=refine_info,
        checks=report_checks,
        distance_to_constraints_mm=DistanceSummary.of(dist),
        mean_edge_length_mm=mean_edge_length(phys, faces),
        area_mm2=surface_area(phys, faces),
        volume_mm3=enclosed_volume(phys, faces),
        constants=pipeline_constants(),
    )
    prog(1.0, "done")
    return ReconstructionResult(surface=surface, distance_to_constraints=dist, report=report,
                                intermediates=inter)


def pipeline_constants() -> dict:
    """The fixed settings of the pipeline and its stages ({module: {NAME: value}})."""
    import sys

    return constants_of(sys.modules[__name__], _prepare, _filtering, _threshold, _visible,
                        _poisson, _deform, _refine, _operators, _checks)
