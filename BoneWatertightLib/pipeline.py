"""The entry functions: CT + segment(s) -> checked, plausible watertight 2-manifold surfaces.

- :func:`reconstruct_many`: several bones of one segmentation *together*. Every other label
  of the segmentation is a neighbour: the bones compete for the voxels of their joints, and the
  surfaces are kept apart by ``min_gap`` (SPEC §5b).
- :func:`reconstruct`: one bone from a mask (the paper's case: a rough segment of bone k).

The only place that unpacks :class:`~BoneWatertightLib.params.Parameters`: each stage of
:mod:`BoneWatertightLib.stages` gets arrays and explicit keyword arguments. Volumes are (z, y, x)
arrays on the isotropic working grid, points (n, 3) x-y-z grid millimetres; results are mapped
to physical LPS millimetres at the end.

Stages: prepare (several labels, cut sides continued past the image) -> hybrid filter ->
automatic thresholds -> ownership (the segment as evidence, the neighbours as competitors, the
CT's joint valley) -> per bone: W_H0 / W_HT -> visible points (eq. 1) -> Poisson M0 -> the
territories between bones -> deformation (eq. 15) -> edge refinement -> joint gaps -> caps at
the image boundary -> checks (SPEC §4) -> plausibility against the segment -> pair checks.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np
import SimpleITK as sitk
from scipy import ndimage
from scipy.spatial import cKDTree

from . import __version__
from .errors import (BoneWatertightError, CancelledError, InputError, PlausibilityError,
                     ReconstructionError, SurfaceCheckError)
from .mesh import cap as _cap
from .mesh import checks as _checks, operators as _operators
from .mesh.cap import cap_plane
from .mesh.checks import check_surface
from .mesh.operators import sample_field
from .mesh.surface import Surface, enclosed_volume, mean_edge_length, surface_area
from .params import Parameters
from .progress import Progress, ProgressCallback
from .report import (Counts, DistanceSummary, JointReport, PairReport, PipelineReport,
                     Refinement, StageTimes, constants_of)
from .stages import autothreshold as _auto, contacts as _contacts, deform as _deform
from .stages import filtering as _filtering, ownership as _ownership, plausibility as _plaus
from .stages import plates as _plates, poisson as _poisson, prepare as _prepare
from .stages import refine as _refine
from .stages import threshold as _threshold, visible as _visible
from .stages.autothreshold import auto_thresholds
from .stages.deform import Deformer
from .stages.filtering import hybrid_filter
from .stages.ownership import compute_ownership
from .stages.poisson import import_open3d, initial_surface, mask_normals
from .stages.prepare import prepare_labels
from .stages.refine import refine_to_edges
from .stages.threshold import (bone_masks, boundary_voxels, crossing_points,
                               erosions_to_separate, voxel_points)
from .stages.visible import visible_points

# The filter's percentile is taken within this distance (mm) of the targets.
FILTER_REGION_MM = 3.0
# Smoothing (voxels) of the occupancy whose 0.5 level is the deformation's inside test.
OCCUPANCY_SIGMA_VOXELS = 0.7
OCCUPANCY_LEVEL = 0.5
# The CT that the edge refinement samples is smoothed by max(REFINE_SIGMA_MIN_VOXELS,
# REFINE_SIGMA_MM / d) voxels.
REFINE_SIGMA_MM = 0.4
REFINE_SIGMA_MIN_VOXELS = 0.5
# A bone reaches at most max(segment_dilation, BAND_COARSENESS x coarseness) beyond its label.
BAND_COARSENESS = 1.0
# Rounds of extra contact passes (each with one voxel more margin) while a pair still crosses.
CONTACT_RETRIES = 3
# HT crossings within this distance (mm) of W_H0 are left out of B* (see _bone_surface).
HT_BEYOND_H0_MM = 1.0
# A pair whose bone evidence touches over more than JOINT_WARN_MIN_MM2 with a joint space
# visible on less than JOINT_WARN_SEEN of it gets a warning: there the boundary between them
# follows the labels alone (a narrow joint on thick slices), and wrong labels move it.
JOINT_WARN_SEEN = 0.5
JOINT_WARN_MIN_MM2 = 25.0
# Vertices farther than this (mm) from every other bone's voxels are its free surface (where
# the edge refinement's support is measured).
FREE_SURFACE_MM = 2.0
# Cross-parameter limits, checked right after prepare: the smallest extent of each target's
# segment must span at least this many resample voxels d and this many edge lengths d*.
MIN_VOXELS_ACROSS = 4.0
MIN_EDGES_ACROSS = 4.0
# Bytes per voxel of M0's remeshing grid (step d* / REMESH_EDGE_RATIO over the bone's box):
# uint8 image and stencil, labels (int32), filled mask, smoothed float32 field, the contour
# (measured 40-49 B per voxel, mesh included).
REMESH_BYTES_PER_VOXEL = 64

# Overall progress fraction at the start and end of each stage.
STAGES = [("open3d", 0.0, 0.03), ("prepare", 0.03, 0.10), ("filter", 0.10, 0.14),
          ("thresholds", 0.14, 0.15), ("ownership", 0.15, 0.25), ("surfaces", 0.25, 0.50),
          ("territories", 0.50, 0.53), ("deform", 0.53, 0.78), ("contacts", 0.78, 0.86),
          ("checks", 0.86, 1.0)]


@dataclass
class ReconstructionResult:
    """One bone: the checked surface (physical LPS mm; cell array "Cap" on cap faces when the
    bone is cut by the image), its per-vertex distance to the constraint points (mm, (n,)),
    the typed report and, on request, the intermediate results."""

    surface: Surface
    distance_to_constraints: np.ndarray
    report: PipelineReport
    intermediates: dict = field(default_factory=dict)
    label: int = 0
    name: str = ""
    error: Optional[Exception] = None

    @property
    def ok(self) -> bool:
        return self.error is None


@dataclass
class JointResult:
    """Several bones reconstructed together: one result per target (in the order asked for),
    the pair checks and the shared report."""

    bones: list
    pairs: list
    report: JointReport


def _stage(progress: Progress, name: str) -> Progress:
    for n, a, b in STAGES:
        if n == name:
            sub = progress.stage(a, b)
            sub(0.0, name)
            return sub
    raise KeyError(name)


def reconstruct(ct: sitk.Image, mask: sitk.Image, params: Optional[Parameters] = None,
                progress: Optional[ProgressCallback] = None) -> ReconstructionResult:
    """Reconstruct one bone from a mask.

    :param ct: CT volume in HU (SimpleITK image, any direction matrix). Not modified.
    :param mask: segment of bone k (non-zero = segment), any geometry. Not modified.
    :param params: pipeline parameters (defaults when None).
    :param progress: callback(fraction, message); returning False cancels (CancelledError).
    :return: the bone's result (see :class:`ReconstructionResult`).
    :raises InputError, ReconstructionError, SurfaceCheckError, PlausibilityError,
        CancelledError.
    """
    if not isinstance(mask, sitk.Image):
        from .errors import EmptySegmentError
        raise EmptySegmentError("No segment was given: select the segment of the bone.")
    labels = sitk.Cast(sitk.NotEqual(mask, 0), sitk.sitkUInt8)
    result = reconstruct_many(ct, labels, [1], params, progress, neighbours="none",
                              names={1: "segment"})
    return result.bones[0]


def _select_neighbours(labels: np.ndarray, values: list, targets: list, neighbours) -> tuple:
    """The label index map with only the targets and the chosen neighbours (indices)."""
    if neighbours == "auto" or neighbours is None:
        return labels, [v for i, v in enumerate(values, 1) if i not in targets]
    if neighbours == "none":
        keep = list(targets)
    else:
        wanted = [int(v) for v in neighbours]
        absent = [v for v in wanted if v not in values]
        if absent:
            raise InputError(
                f"Neighbour label(s) {', '.join(map(str, absent))} are not in the segmentation "
                f"near the bone (labels there: {', '.join(map(str, values))}). Give existing "
                "labels, or neighbours 'auto' (every other label) or 'none'.")
        keep = list(targets) + [values.index(v) + 1 for v in wanted]
    lut = np.zeros(len(values) + 1, labels.dtype)
    for i in keep:
        lut[i] = i
    return lut[labels], [values[i - 1] for i in keep if i not in targets]


def reconstruct_many(ct: sitk.Image, labels: sitk.Image, targets: Sequence[int],
                     params: Optional[Parameters] = None,
                     progress: Optional[ProgressCallback] = None, *, neighbours="auto",
                     names: Optional[dict] = None, keep_going: bool = False) -> JointResult:
    """Reconstruct several bones of one segmentation together.

    Parameters
    ----------
    ct : SimpleITK.Image
        CT volume in HU, any orthonormal direction matrix. Not modified.
    labels : SimpleITK.Image
        Integer label map (0 = background), any geometry: every label is a bone. Not modified.
    targets : sequence of int
        Label values to reconstruct (each once).
    params : Parameters, optional
    progress : callable, optional
        callback(fraction, message); returning False cancels (CancelledError).
    neighbours : "auto", "none" or sequence of int
        Which other labels compete as neighbours: every other label (auto), none, or these.
    names : dict, optional
        Label value -> name, for reports and messages.
    keep_going : bool
        When a bone fails (its checks, its plausibility, its threshold windows), go on with the
        others: its result has ``error`` set and no surface (default: raise).

    Returns
    -------
    JointResult
        ``bones[i]`` for ``targets[i]``; ``pairs``: every pair of targets that succeeded,
        checked exactly.

    Raises
    ------
    InputError, ReconstructionError, SurfaceCheckError, PlausibilityError, CancelledError
    """
    params = (params or Parameters()).validate()
    names = dict(names or {})
    prog = Progress(progress)
    shared = StageTimes()
    t_all = time.perf_counter()

    # open3d first: a missing dependency fails before minutes of work.
    sub = _stage(prog, "open3d")
    t0 = time.perf_counter()
    import_open3d()
    shared.import_open3d = time.perf_counter() - t0

    sub = _stage(prog, "prepare")
    t0 = time.perf_counter()
    band_guess = max(params.segment_dilation, 3.0)
    prep = prepare_labels(ct, labels, targets, spacing=params.spacing, margin=params.margin,
                          band_mm=band_guess, max_memory_gb=params.max_memory_gb,
                          at_border=params.at_border, progress=sub)
    grid, d = prep.grid, prep.grid.spacing
    size_errors = size_problems(prep, params, names)
    if size_errors and not keep_going:
        raise next(iter(size_errors.values()))
    lab, neighbour_values = _select_neighbours(prep.labels, prep.values, prep.targets, neighbours)
    n = len(prep.values)
    c = prep.coarseness
    band = max(params.segment_dilation, BAND_COARSENESS * c)
    shared.prepare = time.perf_counter() - t0

    def name_of(k):
        v = prep.values[k - 1]
        return str(names.get(v, v))

    sub = _stage(prog, "filter")
    t0 = time.perf_counter()
    near = ndimage.binary_dilation(np.isin(lab, prep.targets),
                                   iterations=max(1, int(round(FILTER_REGION_MM / d))))
    ct_f = hybrid_filter(prep.ct, d, sigma=params.sigma, rho=params.rho, region=near)
    del near
    shared.filter = time.perf_counter() - t0

    sub = _stage(prog, "thresholds")
    nct, nlab, nsp = prep.native
    estimate = auto_thresholds(nct, nlab, [prep.values[t - 1] for t in prep.targets], nsp, c,
                               params.theta_max) if (params.h0 is None or params.ht is None) else None
    h0 = params.h0 if params.h0 is not None else estimate["h0"]
    ht = params.ht if params.ht is not None else estimate["ht"]
    if estimate is not None:
        # an explicit value must stay in order with the estimated one
        h0 = max(h0, ht + _auto.H0_MIN_ABOVE_HT) if params.h0 is None else h0
        ht = min(ht, h0 - _auto.H0_MIN_ABOVE_HT) if params.ht is None else ht
    params.check_thresholds(h0, ht)
    if estimate is not None:
        soft, cortex = estimate["soft_tissue"], estimate["cortex"]
    else:
        soft, cortex = _auto.tissue_levels(nct, np.isin(nlab, [prep.values[t - 1] for t in prep.targets]),
                                           nlab > 0, nsp, c)
    thresholds = {"h0": float(h0), "ht": float(ht), "theta_max": float(params.theta_max),
                  "h0_auto": params.h0 is None, "ht_auto": params.ht is None,
                  "soft_tissue_hu": float(soft), "cortex_hu": float(cortex)}
    failed = dict(size_errors)

    def fail(k, exc):
        if not keep_going or not isinstance(exc, BoneWatertightError) or isinstance(exc, CancelledError):
            raise exc
        failed[k] = exc

    for t in prep.targets:
        seg = lab == t
        window = (ct_f[seg] >= ht) & (ct_f[seg] <= params.theta_max)
        if not window.any():
            fail(t, _threshold_error(name_of(t), ht, params.theta_max, ct_f[seg]))

    sub = _stage(prog, "ownership")
    t0 = time.perf_counter()
    own = compute_ownership(ct_f, lab, n, d, h0=h0, ht=ht, theta_max=params.theta_max,
                            soft=soft, contrast=max(cortex - soft, 1.0), coarseness=c,
                            band_mm=band, progress=sub)
    shared.ownership = time.perf_counter() - t0

    # --- per bone: windows, visible points, M0
    sub = _stage(prog, "surfaces")
    bones = {}
    step_voxels = max(1, int(round(min(prep.ct_spacing) / d)))
    for i, k in enumerate(prep.targets):
        if k in failed:
            continue
        part = sub.stage(i / len(prep.targets), (i + 1) / len(prep.targets))
        try:
            bones[k] = _bone_surface(prep, ct_f, own, lab, k, h0, ht, c, params, part,
                                     name_of(k), step_voxels, levels=(soft, cortex))
        except Exception as exc:  # noqa: BLE001 - fail() re-raises unless keep_going
            fail(k, exc)

    # --- territories: the midway surfaces between bones (from the M0s)
    sub = _stage(prog, "territories")
    t0 = time.perf_counter()
    fixed = _fixed_masks(own, lab, prep.targets, n)
    terr = {}
    if len(bones) > 1 or fixed:
        terr = _contacts.territories({k: (b["m0"].vertices, b["m0"].faces) for k, b in bones.items()},
                                     fixed, lab.shape, d)
    shared.territories = time.perf_counter() - t0

    # --- per bone: deformation and edge refinement (never toward another bone's side)
    sub = _stage(prog, "deform")
    ct_smooth = None
    if params.refine_edges:
        ct_smooth = ndimage.gaussian_filter(
            prep.ct, sigma=max(REFINE_SIGMA_MIN_VOXELS, REFINE_SIGMA_MM / d), mode="nearest")
    for i, k in enumerate(prep.targets):
        if k not in bones:
            continue
        part = sub.stage(i / len(prep.targets), (i + 1) / len(prep.targets))
        allowed = _contacts.allowed_test(terr.get(k), d, params.min_gap)
        _shape_bone(bones[k], ct_smooth, ht, params, d, allowed, part)

    # --- joint gaps from the final surfaces
    sub = _stage(prog, "contacts")
    t0 = time.perf_counter()
    if terr and any(v is not None for v in terr.values()):
        surfaces = {k: [b["vertices"], b["faces"]] for k, b in bones.items()}
        history = _contacts.resolve_contacts(surfaces, fixed, lab.shape, d, params.min_gap,
                                             progress=sub.stage(0.0, 0.6))
        # The fields are voxel-accurate; the exact test decides. Pairs that still cross get
        # more passes with a wider margin.
        for extra in range(1, CONTACT_RETRIES + 1):
            crossing = _crossing_pairs(surfaces)
            if not crossing:
                break
            involved = {k for pair in crossing for k in pair}
            sub_surfaces = {k: surfaces[k] for k in involved}
            others = dict(fixed)
            for k in surfaces:
                if k not in involved:
                    others[f"bone{k}"] = _contacts.voxelize(surfaces[k][0], surfaces[k][1],
                                                            lab.shape, d)
            history += _contacts.resolve_contacts(sub_surfaces, others, lab.shape, d,
                                                  params.min_gap + extra * d,
                                                  progress=sub.stage(0.6, 1.0))
        else:
            # Still crossing after the field passes: a sub-voxel sliver; moved apart exactly.
            crossing = _crossing_pairs(surfaces)
            for a, b in crossing:
                va, vb, _ = _contacts.push_apart_exact(surfaces[a][0], surfaces[a][1],
                                                      surfaces[b][0], surfaces[b][1], d)
                surfaces[a][0], surfaces[b][0] = va, vb
        for k, b in bones.items():
            b["vertices"] = surfaces[k][0]
            b["contacts"] = {"passes": [{"moved": rec[k][0], "still_closer_than_gap": rec[k][1]}
                                        for rec in history if k in rec]}
    shared.contacts = time.perf_counter() - t0

    # --- per bone: caps, checks, plausibility, report
    sub = _stage(prog, "checks")
    results = []
    for i, k in enumerate(prep.targets):
        part = sub.stage(i / (len(prep.targets) + 1), (i + 1) / (len(prep.targets) + 1))
        if k in bones:
            try:
                results.append(_finish_bone(prep, own, lab, k, bones[k], params, band,
                                            name_of(k), part, thresholds))
                continue
            except Exception as exc:  # noqa: BLE001 - fail() re-raises unless keep_going
                fail(k, exc)
        results.append(ReconstructionResult(surface=None, distance_to_constraints=None,
                                            report=None, label=int(prep.values[k - 1]),
                                            name=name_of(k), error=failed[k]))

    # --- every pair, exactly
    pairs = []
    contact_of = {(cc["a"], cc["b"]): cc for cc in own.contacts}
    by_k = dict(zip(prep.targets, results))
    good = [k for k in prep.targets if by_k[k].ok]
    for i, a in enumerate(good):
        for b in good[i + 1:]:
            ra, rb = by_k[a], by_k[b]
            rep = _contacts.pair_report(ra.surface.vertices, ra.surface.faces,
                                        rb.surface.vertices, rb.surface.faces)
            joint = contact_of.get((min(a, b), max(a, b)))
            pairs.append(PairReport(a=name_of(a), b=name_of(b), **rep,
                                    joint_contact_mm2=float(joint["contact_area_mm2"]) if joint else 0.0,
                                    joint_valley_seen_fraction=(float(joint["valley_seen_fraction"])
                                                                if joint else None)))
    for p in pairs:
        seen = p.joint_valley_seen_fraction
        if seen is not None and seen < JOINT_WARN_SEEN and p.joint_contact_mm2 > JOINT_WARN_MIN_MM2:
            p.warnings.append(
                f"{p.a} | {p.b}: the CT shows a joint space on only {100 * seen:.0f} % of their "
                f"{p.joint_contact_mm2:.0f} mm^2 contact; elsewhere the boundary between them "
                "follows the segments' labels (a narrow joint on thick slices, or no joint space "
                "at all): check both surfaces at the joint")
            for r in (by_k[k] for k in good):
                if r.name in (p.a, p.b):
                    r.report.warnings.append(p.warnings[-1])
    # The same for a bone and a neighbour label that is not reconstructed in this run.
    for cc in own.contacts:
        for k, other in ((cc["a"], cc["b"]), (cc["b"], cc["a"])):
            seen = cc.get("valley_seen_fraction")
            if (k in good and other not in prep.targets and other < own.other and seen is not None
                    and seen < JOINT_WARN_SEEN and cc["contact_area_mm2"] > JOINT_WARN_MIN_MM2):
                by_k[k].report.warnings.append(
                    f"{name_of(k)} | {name_of(other)} (neighbour): the CT shows a joint space on "
                    f"only {100 * seen:.0f} % of their {cc['contact_area_mm2']:.0f} mm^2 contact; "
                    "elsewhere the boundary follows the segments' labels: check the surface at "
                    "the joint")
    bad = [p for p in pairs if not p.ok]
    if bad:
        text = "; ".join(f"{p.a} and {p.b}: {p.crossing_face_pairs} crossing face pairs, "
                         f"{p.a_inside_b + p.b_inside_a} vertices inside the other" for p in bad)
        raise ReconstructionError(
            f"The surfaces of neighbouring bones interpenetrate ({text}). Check the labels at the "
            "joint, or use a finer resample spacing.")
    shared.total = time.perf_counter() - t_all
    for r in results:
        if not r.ok:
            continue
        r.report.timings.import_open3d = shared.import_open3d
        r.report.timings.prepare = shared.prepare
        r.report.timings.filter = shared.filter
        r.report.timings.ownership = shared.ownership
        r.report.timings.territories = shared.territories
        r.report.timings.contacts = shared.contacts
        r.report.timings.total = shared.total
    report = JointReport(
        version=__version__, parameters=params.to_dict(), input=prep.info, thresholds=thresholds,
        ownership=dict(own.info, contacts=[dict(cc, a=_pair_name(cc["a"], own, name_of),
                                                b=_pair_name(cc["b"], own, name_of))
                                           for cc in own.contacts]),
        pairs=pairs, timings=shared, neighbours=[str(names.get(v, v)) for v in neighbour_values])
    prog(1.0, "done")
    return JointResult(bones=results, pairs=pairs, report=report)


def size_problems(prep, params: Parameters, names: Optional[dict] = None) -> dict:
    """Cross-parameter limits, checked before the long work: {target index: error} for each
    target whose segment's smallest extent on the working grid spans fewer than
    MIN_VOXELS_ACROSS voxels d (InputError) or MIN_EDGES_ACROSS edge lengths d* (InputError),
    or whose M0 remeshing grid (step d* / REMESH_EDGE_RATIO over its box grown by the band)
    would exceed ``max_memory_gb`` or the element limit (MemoryLimitError)."""
    from .errors import MemoryLimitError

    d = prep.grid.spacing
    edge = params.edge_length if params.edge_length is not None else d
    h = edge / _poisson.REMESH_EDGE_RATIO
    band = max(params.segment_dilation, BAND_COARSENESS * prep.coarseness)
    limit = params.max_memory_gb * 1024 ** 3
    problems = {}
    for k in prep.targets:
        value = prep.values[k - 1]
        name = str((names or {}).get(value, value))
        box = _threshold.bbox_slices(prep.labels == k, 0)
        extent = np.array([(s.stop - s.start) * d for s in box][::-1])
        smallest = float(extent.min())
        dims = " x ".join(f"{v:.1f}" for v in extent)
        remesh = float(np.prod(np.ceil((extent + 2 * band) / h)
                               + 2 * _poisson.REMESH_PAD_STEPS + 1))
        over = max(remesh * REMESH_BYTES_PER_VOXEL / limit, remesh / _prepare.MAX_GRID_VOXELS)
        if d * MIN_VOXELS_ACROSS > smallest:
            problems[k] = InputError(
                f"The resample spacing {d:g} mm is too coarse for segment {name}: its smallest "
                f"extent is {smallest:.1f} mm (box {dims} mm), fewer than "
                f"{MIN_VOXELS_ACROSS:g} voxels. Use a spacing of at most "
                f"{np.floor(smallest / MIN_VOXELS_ACROSS * 100) / 100:g} mm, or check the "
                "segment.")
        elif edge * MIN_EDGES_ACROSS > smallest:
            problems[k] = InputError(
                f"edge_length {edge:g} mm is too long for segment {name}: its smallest extent "
                f"is {smallest:.1f} mm (box {dims} mm), fewer than {MIN_EDGES_ACROSS:g} edges. "
                f"Use an edge_length of at most "
                f"{np.floor(smallest / MIN_EDGES_ACROSS * 100) / 100:g} mm (or auto).")
        elif over > 1.0:
            problems[k] = MemoryLimitError(
                f"edge_length {edge:g} mm is too short for segment {name} (box {dims} mm): "
                f"remeshing its surface needs a grid of {remesh / 1e6:.0f} M voxels, about "
                f"{remesh * REMESH_BYTES_PER_VOXEL / 1024 ** 3:.1f} GB (limit "
                f"{params.max_memory_gb:g} GB). Use an edge_length of at least "
                f"{np.ceil(edge * over ** (1 / 3) * 100) / 100:g} mm (or auto), or raise "
                "max_memory_gb.")
    return problems


def _crossing_pairs(surfaces: dict) -> list:
    """The pairs (a, b) of {key: [vertices, faces]} whose faces cross (exact test)."""
    keys = list(surfaces)
    return [(a, b) for i, a in enumerate(keys) for b in keys[i + 1:]
            if _contacts.pair_report(surfaces[a][0], surfaces[a][1], surfaces[b][0],
                                     surfaces[b][1])["crossing_face_pairs"]]


def _component_volumes(vertices, faces) -> list:
    """Enclosed volume (mm^3) of each connected piece of a surface, largest first."""
    import scipy.sparse as sps
    from scipy.sparse.csgraph import connected_components

    n = len(vertices)
    rows = np.concatenate([faces[:, 0], faces[:, 1]])
    cols = np.concatenate([faces[:, 1], faces[:, 2]])
    graph = sps.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    face_comp = comp[faces[:, 0]]
    vols = [abs(enclosed_volume(vertices, faces[face_comp == c])) for c in np.unique(face_comp)]
    return sorted(vols, reverse=True)


def _pair_name(k, own, name_of):
    return "unlabelled bone" if k >= own.other else name_of(k)


def _threshold_error(name, ht, theta_max, vals):
    from .errors import ThresholdError

    lo = float(np.min(vals)) if len(vals) else float("nan")
    hi = float(np.max(vals)) if len(vals) else float("nan")
    if hi < ht:
        # Nothing inside the segment is bone-like at all: the segment is off the bone.
        what = "air" if hi < -200 else "fat" if hi < -30 else "soft tissue"
        return ThresholdError(
            f"Segment {name} covers no bone on this CT: its HU range is {lo:.0f} to {hi:.0f} "
            f"({what}), all below HT = {ht:g} HU. Check that the segment belongs to this CT and "
            "lies on the bone (a misplaced or wrong segment), or lower HT if the bone is this "
            "faint.")
    return ThresholdError(
        f"No voxel of segment {name} lies in [HT, theta_max] = [{ht:g}, {theta_max:g}] HU "
        f"(the segment's HU range is {lo:.0f} to {hi:.0f}): lower HT (or leave it on auto), or "
        "check that the volume is a CT in Hounsfield units.")


def _fixed_masks(own, lab, targets, n) -> dict:
    """Owned voxels of the bones that are not reconstructed (neighbours, unlabelled bone)."""
    fixed = {}
    others = [i for i in range(1, n + 1) if i not in targets and (lab == i).any()]
    if others:
        m = np.isin(own.owner, others)
        if m.any():
            fixed["neighbours"] = m
    m = own.owner >= own.other
    if m.any():
        fixed["unlabelled"] = m
    return fixed


def _bone_plates(prep, own, masks, k, ht, levels, edge):
    """Thin plates of bone k (:mod:`.stages.plates`) on its box, and the box's plate mask."""
    d = prep.grid.spacing
    soft, cortex = levels
    sl, reg = own.regions[k]
    region = np.zeros(prep.labels.shape, bool)
    region[sl] = reg
    box = masks.box
    # Inside or right along the segment (within half its coarseness), not another bone's.
    along = ndimage.binary_dilation(
        prep.labels[box] == k, structure=_threshold.SIX,
        iterations=max(1, int(round(0.5 * prep.coarseness / d))))
    region = region[box] & along & ((own.owner[box] == 0) | (own.owner[box] == k))
    # A ridge as high as the label level always counts; fainter ones where the noise allows.
    max_contrast = _ownership.LABEL_LEVEL_FRACTION * (ht - soft)
    t_min = _plates.PLATE_MIN_STEPS * max(d, edge / _poisson.REMESH_EDGE_RATIO)
    resolved = ndimage.binary_erosion(masks.occupancy, structure=_threshold.SIX,
                                      iterations=max(1, int(round(0.5 * t_min / d))))
    plates = _plates.find_plates(
        prep.ct[box], region, masks.w_ht, resolved, d, native_spacing=prep.ct_spacing,
        soft=soft, cortex=cortex, max_contrast=max_contrast, min_thickness=t_min,
        origin=masks.origin)
    shape = masks.w_ht.shape
    return plates, plates.mask(shape, masks.origin) if plates.n else np.zeros(shape, bool)


def _bone_surface(prep, ct_f, own, lab, k, h0, ht, c, params, progress, name, step_voxels,
                  levels):
    """Threshold windows, thin plates, visible points and M0 of bone k (grid mm)."""
    d = prep.grid.spacing
    times = StageTimes()
    t0 = time.perf_counter()
    masks = bone_masks(ct_f, own.owner, own.cores, lab, k, d, h0=h0, theta_max=params.theta_max,
                       coarseness=c, opening=params.opening, closing=params.closing,
                       unsupported=own.unsupported)
    separation = erosions_to_separate(ct_f, own.owner, k, d, h0=h0, theta_max=params.theta_max,
                                      step_voxels=step_voxels, max_erosions=params.max_erosions)
    edge = params.edge_length if params.edge_length is not None else d
    # Plates thinner than the CT resolves join the bone as slabs of the model's thickness: in
    # the visible-point candidates, the deformation's inside test and M0 (fused below).
    plates, plate_mask = _bone_plates(prep, own, masks, k, ht, levels, edge)
    if plates.n:
        masks.w_ht |= plate_mask
        masks.far |= plate_mask & ~masks.w_h0
        masks.solid_h0 |= plate_mask
        masks.occupancy |= plate_mask
        masks.info["voxels_plate"] = int(plate_mask.sum())
    times.threshold = time.perf_counter() - t0
    progress(0.2, f"{name}: visible points")
    t0 = time.perf_counter()
    origin = masks.origin
    # The hyper-spherical mapping sees W_H0's own boundary (inner walls of cavities and pores
    # included: eq. (1) hides them), joined by the low-density bone out of reach of W_H0.
    candidates = voxel_points(boundary_voxels(masks.w_h0 | masks.far), d)
    if len(candidates) < 10:
        raise ReconstructionError(
            f"Almost nothing of {name} is in the threshold windows ({len(candidates)} boundary "
            "points): lower H0/HT or leave them on auto, and check the segment.")
    vis_idx, vis_info, every = visible_points(candidates, d, views=params.views,
                                              view_distance=params.view_distance,
                                              log_radius=params.log_radius,
                                              progress=progress.stage(0.2, 0.5), full=True)
    visible = candidates[vis_idx]       # Poisson's input: the thinned visible points
    visible_all = candidates[every]     # S(P_H0) for the deformation: all of them
    # B* = S(P_H0) U (P_HT - P_H0); of P_HT - P_H0 only the outer boundary can be reached by
    # the directional search, placed sub-voxel where the CT crosses HT.
    b_ht = crossing_points(ct_f[masks.box], masks.occupancy, ht, d)
    # Of P_HT - P_H0 the deformation needs the bone that W_H0 misses (low-density bone, a
    # cortex below H0): HT crossings more than HT_BEYOND_H0_MM beyond W_H0. Nearer ones are the
    # partial-volume foot of dense cortex, which would only pull the surface outward.
    if len(b_ht):
        from .mesh.distance import distance_outside

        gap_to_h0 = distance_outside(masks.w_h0) * d
        b_ht = b_ht[sample_field(gap_to_h0, b_ht, d) > HT_BEYOND_H0_MM]
    times.visible = time.perf_counter() - t0
    progress(0.5, f"{name}: Poisson surface M0")
    t0 = time.perf_counter()
    normals = mask_normals(masks.solid_h0, visible, d)
    # M0 joins what Poisson at depth <= 7 cannot resolve (a plate of a few voxels in a long
    # bone) and, where it then has tunnels its segment does not have, the segment (grid mm
    # relative to the box corner).
    trusted = (lab[masks.box] == k) & ((own.owner[masks.box] == 0) | (own.owner[masks.box] == k))
    if own.unsupported is not None:
        trusted &= ~own.unsupported[masks.box]
    fusion = _poisson.Fusion(label=trusted, label_origin=np.zeros(3), label_spacing=d,
                             genus=_plaus.segment_genus(trusted, d), close_mm=(c,))
    if plates.n:
        fusion.plates = lambda shape, lo, h: plates.field(shape, np.asarray(lo) + origin, h)
        fusion.plates_box = (plates.points.min(axis=0) - origin,
                             plates.points.max(axis=0) - origin)
    m0, raw = initial_surface(visible, normals, params.poisson_depth, edge, fusion=fusion)
    m0 = Surface(m0.vertices + origin, m0.faces)
    times.poisson = time.perf_counter() - t0
    progress(1.0, f"{name}: M0 done")
    others = (own.owner[masks.box] > 0) & (own.owner[masks.box] != k)
    others_distance = None
    if others.any():
        dist, f = _threshold.coarse_distance(others, d)
        idx = [np.minimum(np.arange(n) // f, dist.shape[a] - 1) for a, n in enumerate(others.shape)]
        others_distance = dist[np.ix_(*idx)].astype(np.float32)
    return {"masks": masks, "m0": m0, "raw_vertices": raw.n_vertices,
            "others_distance": others_distance,
            "visible": visible + origin, "visible_all": visible_all + origin,
            "b_ht": b_ht + origin, "n_candidates": len(candidates),
            "vis_info": vis_info, "times": times, "separation": separation,
            "vertices": m0.vertices.copy(), "faces": m0.faces, "history": [],
            "plates": plates, "fusion": fusion,
            "refinement": Refinement(applied=False), "contacts": {}}


def _shape_bone(b, ct_smooth, ht, params, d, allowed, progress):
    """Deformation (paper eq. 15) and edge refinement (ours), in place on ``b``."""
    masks, m0 = b["masks"], b["m0"]
    origin = masks.origin
    t0 = time.perf_counter()
    constraints = np.vstack([b["visible_all"], b["b_ht"]])
    if allowed is not None:
        constraints = constraints[allowed(constraints)]
    b["constraints"] = constraints
    verts = m0.vertices.copy()
    if params.iterations > 0 and len(constraints):
        occ = ndimage.gaussian_filter(masks.occupancy.astype(np.float32), sigma=OCCUPANCY_SIGMA_VOXELS)
        deformer = Deformer(m0.vertices - origin, m0.faces, constraints - origin,
                            lambda p: sample_field(occ, p, d) >= OCCUPANCY_LEVEL,
                            mean_edge_length(m0.vertices, m0.faces),
                            iterations=params.iterations, alpha=params.alpha, beta=params.beta,
                            search_radius=params.search_radius,
                            search_offset=params.search_offset)
        verts = deformer.run(progress=progress.stage(0.0, 0.6)) + origin
        b["history"] = deformer.history
    b["times"].deform = time.perf_counter() - t0
    b["deformed"] = verts
    t0 = time.perf_counter()
    if params.refine_edges:
        before = verts
        plates = b["plates"]
        verts, shift, frac, found = refine_to_edges(
            verts, b["faces"], ct_smooth, d, ht, edge_level=params.edge_level, allowed=allowed,
            progress=progress.stage(0.6, 1.0), plate_targets=plates.targets if plates.n else None)
        # Edge support on the free surface: where the bone touches another one (no joint space
        # on the CT) no edge is expected.
        free = np.ones(len(verts), bool)
        if b.get("others_distance") is not None:
            free = sample_field(b["others_distance"], before - origin, d, cval=1e3) > FREE_SURFACE_MM
        support = float(found[free].mean()) if free.any() else float(found.mean())
        b["refinement"] = Refinement(applied=True, fraction_with_edge=support,
                                     mean_shift_mm=float(shift.mean()),
                                     mean_abs_shift_mm=float(np.abs(shift).mean()))
    b["times"].refine = time.perf_counter() - t0
    b["vertices"] = verts


def _finish_bone(prep, own, lab, k, b, params, band, name, progress, thresholds):
    grid, d = prep.grid, prep.grid.spacing
    times = b["times"]
    verts, faces = b["vertices"], b["faces"]
    t0 = time.perf_counter()
    flags = np.zeros(len(faces), np.uint8)
    cap_area = 0.0
    planes = prep.caps.get(k, [])
    for plane in planes:
        verts, faces, flags, area = cap_plane(verts, faces, flags, plane.axis, plane.side,
                                              plane.position, mean_edge_length(verts, faces))
        cap_area += area
    times.cap = time.perf_counter() - t0
    progress(0.3, f"{name}: checks")
    t0 = time.perf_counter()
    phys = grid.grid_to_physical(verts)
    if enclosed_volume(phys, faces) < 0:  # a reflecting direction matrix flips orientation
        faces = faces[:, ::-1].copy()
    checks = check_surface(phys, faces)
    times.checks = time.perf_counter() - t0
    if not checks.ok and planes and checks.n_components > 1:
        pieces = _component_volumes(phys, faces)
        raise SurfaceCheckError(
            f"{name} is cut by the image boundary into {len(pieces)} separate pieces inside the "
            f"image ({', '.join(f'{v / 1000:.1f}' for v in pieces)} ml): they join outside the "
            "field of view, so one closed surface cannot hold them. Use a CT that contains more "
            "of the bone, or split the segment into one segment per piece.", report=checks)
    if not checks.ok:
        raise SurfaceCheckError(
            f"The surface of {name} failed the watertight 2-manifold checks: "
            + "; ".join(checks.problems)
            + ". Try a finer resample spacing, more deformation stiffness (alpha), or fewer "
            "iterations.", report=checks)
    progress(0.6, f"{name}: plausibility")
    t0 = time.perf_counter()
    seg_all = lab == k
    box = _threshold.bbox_slices(seg_all | (own.owner == k), int(np.ceil((band + 3 * d) / d)) + 2)
    corner = np.array([s.start for s in box][::-1], dtype=np.float64) * d
    inside = _contacts.voxelize(verts - corner, faces, tuple(s.stop - s.start for s in box), d)
    lab_b = lab[box]
    cores_b = own.cores[box]
    frac = b["refinement"].fraction_with_edge
    plaus = _plaus.measure(
        inside, verts - corner, seg_all[box], (lab_b > 0) & (lab_b != k),
        (cores_b > 0) & (cores_b != k), _plaus.image_mask(box, planes, d), d,
        volume_mm3=enclosed_volume(phys, faces), coarseness=prep.coarseness, band_mm=band,
        edge_support=float("nan") if frac is None else frac, owned=own.owner[box] == k,
        unsupported=None if own.unsupported is None else own.unsupported[box],
        unsupported_pieces=len(own.info.get("unsupported", {}).get(k, [])))
    _plaus.gate(plaus, coarseness=prep.coarseness, band_mm=band, name=name)
    times.plausibility = time.perf_counter() - t0
    warnings = []
    if plaus.problems:
        if params.on_implausible == "fail":
            raise PlausibilityError(
                "The surface is watertight but not plausible: " + "; ".join(plaus.problems)
                + ". (on_implausible = warn returns it with these warnings.)", report=plaus)
        warnings = list(plaus.problems)
    warnings += plaus.warnings
    plaus.segment_genus = _plaus.segment_genus(seg_all[box] & _plaus.image_mask(box, planes, d), d)
    warnings += _plaus.tunnel_warning(name, checks.genus, plaus.segment_genus)
    constraints = b["constraints"]
    dist, _ = cKDTree(grid.grid_to_physical(constraints)).query(phys, workers=-1) \
        if len(constraints) else (np.zeros(len(phys)), None)
    surface = Surface(phys, faces, "LPS", {"DistanceToConstraints": dist},
                      {"Cap": flags} if planes else {})
    masks = b["masks"]
    inter = {}
    if params.keep_intermediates:
        o = masks.origin
        m0p = grid.grid_to_physical(b["m0"].vertices)
        inter = {
            "P_H0": grid.grid_to_physical(voxel_points(masks.w_h0, d) + o),
            "P_HT": grid.grid_to_physical(voxel_points(masks.w_ht & ~masks.w_h0, d) + o),
            "visible_points": grid.grid_to_physical(b["visible"]),
            "constraints": grid.grid_to_physical(constraints),
            "M0": Surface(m0p, b["m0"].faces if enclosed_volume(m0p, b["m0"].faces) > 0
                          else b["m0"].faces[:, ::-1].copy()),
            "deformed": Surface(grid.grid_to_physical(b["deformed"]), b["faces"]),
        }
    sep = b["separation"]
    report = PipelineReport(
        version=__version__, parameters=params.to_dict(), input=prep.info, timings=times,
        threshold=dict(masks.info, h0=thresholds["h0"], ht=thresholds["ht"],
                       plates=b["plates"].info, fusion=dict(b["fusion"].info)),
        counts=Counts(p_h0_surface_points=int(b["n_candidates"]),
                      visible_points=int(len(b["visible"])), ht_boundary_points=int(len(b["b_ht"])),
                      constraint_points=int(len(constraints)),
                      poisson_raw_vertices=int(b["raw_vertices"]),
                      m0_vertices=int(b["m0"].n_vertices), m0_faces=int(b["m0"].n_faces),
                      vertices=int(len(phys)), faces=int(len(faces))),
        visible=b["vis_info"], deformation=b["history"], refinement=b["refinement"],
        checks=checks, distance_to_constraints_mm=DistanceSummary.of(dist),
        mean_edge_length_mm=mean_edge_length(phys, faces), area_mm2=surface_area(phys, faces),
        volume_mm3=enclosed_volume(phys, faces), constants=pipeline_constants(),
        label=int(prep.values[k - 1]), name=name, thresholds=dict(thresholds),
        ownership={"core_depth_mm": own.info["core_depth_mm"].get(k),
                   "owned_voxels": int((own.owner == k).sum())},
        separation={"erosions_to_separate": sep,
                    "by": ("threshold" if sep == 0 else f"erosion ({sep} CT voxels)" if sep
                           else "competition at the CT's valley and the labels")},
        cap={"planes": [p.to_dict() for p in planes], "area_mm2": cap_area,
             "faces": int(flags.sum())},
        contacts=b["contacts"], plausibility=plaus, warnings=warnings)
    progress(1.0, f"{name}: done")
    return ReconstructionResult(surface=surface, distance_to_constraints=dist, report=report,
                                intermediates=inter, label=int(prep.values[k - 1]), name=name)


def pipeline_constants() -> dict:
    """The fixed settings of the pipeline and its stages ({module: {NAME: value}})."""
    import sys

    return constants_of(sys.modules[__name__], _prepare, _filtering, _auto, _ownership,
                        _threshold, _plates, _visible, _poisson, _deform, _refine, _contacts, _plaus,
                        _cap, _operators, _checks)
