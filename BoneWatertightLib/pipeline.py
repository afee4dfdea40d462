"""The entry function: CT + rough segment -> checked watertight 2-manifold bone surface."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import SimpleITK as sitk
from scipy import ndimage
from scipy.spatial import cKDTree

from . import __version__
from .checks import check_surface
from .deform import Deformer, sample_field
from .errors import SurfaceCheckError
from .filtering import hybrid_filter
from .mesh import Surface, enclosed_volume, mean_edge_length, surface_area
from .params import Parameters
from .poisson import import_open3d, initial_surface, mask_normals
from .prepare import prepare
from .progress import Progress, ProgressCallback
from .refine import refine_to_edges
from .threshold import boundary_voxels, crossing_points, two_step_threshold, voxel_points
from .visible import visible_points

# Overall progress fraction at the start of each stage.
STAGES = [("prepare", 0.0, 0.08), ("filter", 0.08, 0.14), ("threshold", 0.14, 0.30),
          ("visible", 0.30, 0.42), ("poisson", 0.42, 0.55), ("deform", 0.55, 0.88),
          ("refine", 0.88, 0.93), ("checks", 0.93, 1.0)]


@dataclass
class ReconstructionResult:
    surface: Surface
    distance_to_constraints: np.ndarray
    report: dict
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
        per-vertex distance to the constraint points, a JSON-serialisable report and, when
        ``params.keep_intermediates``, the intermediate point sets and M0 (physical LPS).
    :raises InputError, SeparationError, ReconstructionError, SurfaceCheckError, CancelledError.
    """
    params = (params or Parameters()).validate()
    prog = Progress(progress)
    times = {}
    t_all = time.perf_counter()
    inter = {}

    # open3d first: a missing dependency must fail before minutes of work, and its one-off
    # import (~3 s) is reported apart from the Poisson stage.
    t0 = time.perf_counter()
    import_open3d()
    times["import_open3d"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    prep = prepare(ct, mask, params)
    grid, d = prep.grid, prep.grid.spacing
    times["prepare"] = time.perf_counter() - t0
    sub = _stage(prog, "filter")

    t0 = time.perf_counter()
    near_segment = ndimage.binary_dilation(prep.segment, iterations=max(1, int(round(3.0 / d))))
    ct_f = hybrid_filter(prep.ct, d, params, region=near_segment)
    times["filter"] = time.perf_counter() - t0
    sub = _stage(prog, "threshold")

    t0 = time.perf_counter()
    thr = two_step_threshold(ct_f, prep.segment, d, params, progress=sub)
    times["threshold"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    surf_vox = boundary_voxels(thr.solid_h0)
    p_h0_surface = voxel_points(surf_vox, d)
    sub = _stage(prog, "visible")
    vis_idx, vis_info = visible_points(p_h0_surface, params, d, progress=sub)
    visible = p_h0_surface[vis_idx]
    # B* = S(P_H0) U (P_HT - P_H0); of P_HT - P_H0 only the outer boundary can be reached by
    # the directional search, and we place it sub-voxel where the CT crosses HT.
    b_ht = crossing_points(ct_f, thr.occupancy, params.ht, d)
    constraints = np.vstack([visible, b_ht])
    times["visible"] = time.perf_counter() - t0

    sub = _stage(prog, "poisson")
    t0 = time.perf_counter()
    edge = params.edge_length or d
    normals = mask_normals(thr.solid_h0, visible, d)
    m0, raw = initial_surface(visible, normals, params.poisson_depth, edge)
    times["poisson"] = time.perf_counter() - t0

    sub = _stage(prog, "deform")
    t0 = time.perf_counter()
    history = []
    if params.iterations > 0:
        occ_field = ndimage.gaussian_filter(thr.occupancy.astype(np.float32), sigma=0.7)
        deformer = Deformer(m0.vertices, m0.faces, constraints,
                            lambda pts: sample_field(occ_field, pts, d) >= 0.5,
                            params, mean_edge_length(m0.vertices, m0.faces))
        verts = deformer.run(progress=sub)
        history = deformer.history
    else:
        verts = m0.vertices.copy()
    times["deform"] = time.perf_counter() - t0
    faces = m0.faces

    sub = _stage(prog, "refine")
    t0 = time.perf_counter()
    refine_info = {"applied": False}
    deformed = verts
    if params.refine_edges:
        ct_smooth = ndimage.gaussian_filter(prep.ct, sigma=max(0.5, 0.4 / d), mode="nearest")
        verts, shift, frac_ok = refine_to_edges(deformed, faces, ct_smooth, d, params.ht,
                                                edge_level=params.edge_level)
        refine_info = {"applied": True, "fraction_with_edge": frac_ok,
                       "mean_shift_mm": float(shift.mean()),
                       "mean_abs_shift_mm": float(np.abs(shift).mean())}
    times["refine"] = time.perf_counter() - t0

    sub = _stage(prog, "checks")
    t0 = time.perf_counter()
    phys = grid.grid_to_physical(verts)
    if enclosed_volume(phys, faces) < 0:  # a reflecting direction matrix flips orientation
        faces = faces[:, ::-1].copy()
    report_checks = check_surface(phys, faces)
    times["checks"] = time.perf_counter() - t0
    if not report_checks.ok:
        raise SurfaceCheckError(
            "The reconstructed surface failed the watertight 2-manifold checks: "
            + "; ".join(report_checks.problems)
            + ". Try a finer resample spacing, more deformation stiffness (alpha), or fewer iterations.",
            report=report_checks)
    dist, _ = cKDTree(grid.grid_to_physical(constraints)).query(phys, workers=-1)
    surface = Surface(phys, faces, "LPS", {"DistanceToConstraints": dist})
    times["total"] = time.perf_counter() - t_all

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
    report = {
        "version": __version__,
        "coordinate_system": "LPS",
        "units": "mm",
        "parameters": params.to_dict(),
        "input": prep.info,
        "times_s": {k: round(v, 3) for k, v in times.items()},
        "threshold": thr.info,
        "counts": {
            "p_h0_surface_points": int(len(p_h0_surface)),
            "visible_points": int(len(visible)),
            "ht_boundary_points": int(len(b_ht)),
            "constraint_points": int(len(constraints)),
            "poisson_raw_vertices": int(raw.n_vertices),
            "m0_vertices": int(m0.n_vertices),
            "m0_faces": int(m0.n_faces),
            "vertices": int(len(phys)),
            "faces": int(len(faces)),
        },
        "visible": vis_info,
        "deformation": history,
        "refinement": refine_info,
        "mean_edge_length_mm": mean_edge_length(phys, faces),
        "area_mm2": surface_area(phys, faces),
        "volume_mm3": enclosed_volume(phys, faces),
        "checks": report_checks.to_dict(),
        "distance_to_constraints_mm": {
            "mean": float(dist.mean()), "p95": float(np.percentile(dist, 95)),
            "max": float(dist.max()),
        },
    }
    prog(1.0, "done")
    return ReconstructionResult(surface=surface, distance_to_constraints=dist, report=report,
                                intermediates=inter)
