"""Stage 7 (addition to the paper): sub-voxel edge refinement.

The deformation makes the surface follow bone k's [HT, theta_max] region. On a blurred CT the HT
isosurface lies outside the true border (HT sits near the soft-tissue level of the edge ramp; with
2.5 mm slices that is ~1 mm out). Each vertex therefore samples the lightly smoothed CT along its
normal, finds the bone peak just inside and the valley just outside, and moves to where the profile
crosses half-way between them (the half-maximum edge, the usual cortical-edge criterion). The
displacements are smoothed over the mesh and bounded, so they cannot fold the surface; the caller
checks the result and keeps the unrefined surface if a check fails. ``refine_edges=False`` skips it.
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.sparse as sp
from scipy.interpolate import RegularGridInterpolator

from ..mesh.operators import (SAMPLE_CHUNK, SAMPLE_THREADS, laplacian, ring_mean, safe_update,
                              sample_field, solve_spd, vertex_normals)
from ..threads import cpu_threads, thread_map

# Largest move along the normal (mm), of the whole refinement (its passes together): beyond it
# an edge is no sub-voxel correction but the receding edge of a thin rim or process tip.
MAX_SHIFT_MM = 1.5
# Least peak - valley contrast (HU) for a profile to give an edge.
MIN_CONTRAST_HU = 150.0
# Weights of the regularised step: Laplacian smoothness and damping toward the current surface.
REFINE_ALPHA = 0.3
REFINE_BETA = 0.05
# Refinement passes (vertices held back get another chance once their neighbours moved).
REFINE_PASSES = 3
# Rounds of "verify, re-refine the vertices the exact check put back".
VERIFY_ROUNDS = 3
# Profile along the normal: from PROFILE_RANGE_MM[0] (inside) to [1] (outside), step in mm.
PROFILE_RANGE_MM = (-3.5, 2.5)
PROFILE_STEP_MM = 0.1
# The bone peak is searched up to this far outside the vertex (mm).
PEAK_REACH_MM = 0.5
# The valley is the minimum up to VALLEY_REACH_MM beyond the peak, and at least
# VALLEY_MIN_REACH_MM outside the vertex.
VALLEY_REACH_MM = 2.0
VALLEY_MIN_REACH_MM = 1.5
# A profile that rises above its edge level again after the first crossing (within the peak's
# reach) is anchored on that outer layer's peak instead, at most this many times.
REANCHOR_ROUNDS = 2
# ... when it rises at least this much (HU) above the dip after the crossing (noise on a flank
# that hovers at the level is no outer layer): half the least contrast of an edge.
REANCHOR_RISE_HU = 0.5 * MIN_CONTRAST_HU
# Value of profile samples outside the grid (air).
OUTSIDE_HU = -1000.0
# Automatic edge level (edge_level None): the blurred-slab model. A cortex of thickness w blurred
# by a Gaussian of width s peaks at q = 2 Phi(w / 2s) - 1 of the full contrast and crosses its
# true outer border at r(q) = (Phi(w / s) - 1/2) / q of its own peak: r = 1/2 for thick cortex
# (the half maximum), up to ~0.9 for cortex much thinner than the blur, whose half maximum lies
# outside the bone. The full contrast is the SLAB_REFERENCE_PERCENTILE of the bone's own
# profile contrasts (its thickest cortex); q is bounded below by SLAB_MIN_RATIO.
SLAB_REFERENCE_PERCENTILE = 90.0
SLAB_MIN_RATIO = 0.3
SLAB_LEVEL_RANGE = (0.5, 0.9)
# Behind a thin cortex the bone may be cancellous (a vertebral body, a process) rather than
# marrow: the profile then falls only part of the way within SLAB_INNER_MM inside its peak. The
# level for such a profile comes from the same model with an interior behind the cortex - a
# cortex of thickness w and contrast 1 over an interior of contrast b, blurred by a Gaussian of
# width s - sampled over SLAB_MODEL_SIGMA_MM x SLAB_MODEL_THICKNESS_MM x SLAB_MODEL_INTERIOR and
# measured as a profile is (peak, valley, the fall within SLAB_INNER_MM): the median level at the
# true border in each cell of (contrast ratio, fall). A little fall already means a thin cortex:
# on 3 mm slices a 0.7 mm cortex over cancellous bone falls by ~0.3 and crosses its border at
# ~0.87 of its peak (the half maximum lies ~0.8 mm outside it).
SLAB_INNER_MM = 2.0
SLAB_MODEL_SIGMA_MM = (0.5, 2.2, 18)           # blur widths (mm): fine to 3 mm slices
SLAB_MODEL_THICKNESS_MM = (0.1, 8.0, 30)       # cortex thickness (mm), log-spaced
SLAB_MODEL_INTERIOR = (-0.15, 0.5, 14)         # interior / cortical contrast: fat to dense
SLAB_MODEL_BINS = (15, 10)                     # cells of (contrast ratio, fall)
# A vertex whose shift differs from its 1-ring's mean by more than
# max(OUTLIER_MM, OUTLIER_VOXELS * spacing) gets no target.
OUTLIER_MM = 0.4
OUTLIER_VOXELS = 0.8
# Back-off rounds that take a step half-way back before putting vertices all the way back
# (:func:`..mesh.operators.safe_update`).
BACKOFF_HALVINGS = 3


def slab_edge_level(ratio, fall=1.0):
    """The blurred-slab model's edge level (see the module constants) for a profile whose
    contrast is ``ratio`` (array) of the full contrast and which falls by ``fall`` (array, a
    fraction of its contrast) inside its peak: about the half maximum for a step (no fall,
    full contrast), up to SLAB_LEVEL_RANGE[1] for a thin cortex."""
    q_axis, f_axis, table = _slab_level_table()
    q, f = np.broadcast_arrays(np.asarray(ratio, dtype=np.float64),
                               np.asarray(fall, dtype=np.float64))
    known = ~(np.isnan(q) | np.isnan(f))  # no level for a profile without a contrast
    q = np.clip(np.where(known, q, 1.0), q_axis[0], q_axis[-1])
    f = np.clip(np.where(known, f, 0.0), f_axis[0], f_axis[-1])
    level = RegularGridInterpolator((q_axis, f_axis), table)(
        np.stack([q.ravel(), f.ravel()], axis=-1)).reshape(q.shape)
    return np.where(known, np.clip(level, *SLAB_LEVEL_RANGE), np.nan)


@functools.lru_cache(maxsize=1)
def _slab_level_table():
    """(ratio axis (m,), fall axis (k,), level (m, k)): the median level at the true border of
    model profiles (see the module constants) by their contrast ratio and fall, each measured
    as :func:`sample_profiles` and :func:`contrast_reference` measure a profile (the valley
    within VALLEY_REACH_MM outside the peak, the fall within SLAB_INNER_MM inside it, the
    ratio to the contrast of a thick cortex at the same blur). Cells no model profile reaches
    take the nearest reached cell's level."""
    from scipy.special import ndtr

    x = np.arange(PROFILE_RANGE_MM[0], PROFILE_RANGE_MM[1] + 1e-9, PROFILE_STEP_MM)  # outward
    s = np.linspace(*SLAB_MODEL_SIGMA_MM)
    w = np.exp(np.linspace(np.log(SLAB_MODEL_THICKNESS_MM[0]), np.log(SLAB_MODEL_THICKNESS_MM[1]),
                           SLAB_MODEL_THICKNESS_MM[2]))
    b = np.linspace(*SLAB_MODEL_INTERIOR)
    S, W, B = (g.ravel()[:, None] for g in np.meshgrid(s, w, b, indexing="ij"))
    inner_edge = ndtr((-W - x[None, :]) / S)
    prof = B * inner_edge + ndtr(-x[None, :] / S) - inner_edge  # border at x = 0
    i_peak = np.argmax(prof[:, :int(np.count_nonzero(x <= PEAK_REACH_MM))], axis=1)
    peak = prof[np.arange(len(prof)), i_peak]
    valley, inner = _valley_and_inner(x, prof, i_peak, peak)
    contrast = peak - valley
    at_border = prof[:, int(np.argmin(np.abs(x)))]
    level = (at_border - valley) / contrast
    fall = np.clip((peak - inner) / contrast, 0.0, 1.0)
    thick = contrast.reshape(len(s), len(w), len(b))[:, -1, :].max(axis=1)  # per blur
    ratio = contrast / np.repeat(thick, len(w) * len(b))[:, None].ravel()
    nq, nf = SLAB_MODEL_BINS
    q_axis = np.linspace(SLAB_MIN_RATIO, 1.0, nq)
    f_axis = np.linspace(0.0, 1.0, nf)
    qi = np.clip(np.rint((ratio - q_axis[0]) / (q_axis[1] - q_axis[0])), 0, nq - 1).astype(int)
    fi = np.clip(np.rint(fall / (f_axis[1] - f_axis[0])), 0, nf - 1).astype(int)
    keep = (ratio >= q_axis[0] - 0.5 * (q_axis[1] - q_axis[0])) & (ratio <= 1.0) & (contrast > 0)
    table = np.full((nq, nf), np.nan)
    for cell in set(zip(qi[keep].tolist(), fi[keep].tolist())):
        m = keep & (qi == cell[0]) & (fi == cell[1])
        table[cell] = np.median(level[m])
    filled = np.argwhere(np.isfinite(table))
    for cell in np.argwhere(~np.isfinite(table)):
        near = filled[np.argmin(np.abs(filled - cell).sum(axis=1))]
        table[tuple(cell)] = table[tuple(near)]
    return q_axis, f_axis, table


def sample_profiles(vertices, faces, ct_smooth, spacing):
    """CT profiles along the vertex normals: (normals, t (k,), profiles (n, k), peak index,
    peak, valley, inner): inner is the lowest value within SLAB_INNER_MM inside the peak."""
    n = vertex_normals(vertices, faces)
    t = np.arange(PROFILE_RANGE_MM[0], PROFILE_RANGE_MM[1] + 1e-9, PROFILE_STEP_MM)
    # The sample points of a few thousand vertices at a time: all at once they took 64 MB
    # (43 700 vertices x 61 samples x 3 coordinates) at the run's peak of memory.
    rows = max(1, SAMPLE_CHUNK // len(t))

    def values(start):
        part = slice(start, start + rows)
        pts = vertices[part, None, :] + t[None, :, None] * n[part, None, :]
        return sample_field(ct_smooth, pts.reshape(-1, 3), spacing, order=1,
                            cval=OUTSIDE_HU).reshape(-1, len(t))

    prof = np.concatenate(thread_map(values, range(0, max(len(vertices), 1), rows),
                                     cpu_threads(SAMPLE_THREADS)))
    i_peak = np.argmax(prof[:, :int(np.count_nonzero(t <= PEAK_REACH_MM))], axis=1)
    peak = prof[np.arange(len(prof)), i_peak]
    valley, inner = _valley_and_inner(t, prof, i_peak, peak)
    return n, t, prof, i_peak, peak, valley, inner


def _valley_and_inner(t, prof, i_peak, peak):
    """(valley, inner) of profiles ``prof`` (n, k) whose peak is at ``i_peak`` (n,), see
    :func:`sample_profiles`."""
    # Valley: the lowest value within 2 mm outside the peak (stops before a neighbour's cortex).
    # The window always reaches 1.5 mm outside the vertex, so a flat interior (peak deep inside)
    # still sees the soft tissue; a neighbour's cortex beyond the gap never lowers the minimum.
    cols = np.arange(len(t))[None, :]
    reach = np.maximum(t[i_peak] + VALLEY_REACH_MM, VALLEY_MIN_REACH_MM)
    outside = (cols > i_peak[:, None]) & (t[None, :] <= reach[:, None])
    valley = np.min(np.where(outside, prof, np.inf), axis=1)
    behind = (cols < i_peak[:, None]) & (t[None, :] >= (t[i_peak] - SLAB_INNER_MM)[:, None])
    inner = np.min(np.where(behind, prof, np.inf), axis=1)
    inner = np.where(np.isfinite(inner), inner, peak)
    return valley, inner


def contrast_reference(vertices, faces, ct_smooth, spacing, ht, min_contrast=MIN_CONTRAST_HU,
                       profiles=None, peak_max=np.inf):
    """The bone's full cortical contrast (HU) for the blurred-slab model: the
    SLAB_REFERENCE_PERCENTILE of peak - valley over the vertices whose profile has an edge
    (and peaks at most ``peak_max``: metal is no cortex). ``profiles``:
    :func:`sample_profiles` of these vertices, when already sampled."""
    if profiles is None:
        profiles = sample_profiles(vertices, faces, ct_smooth, spacing)
    _, _, _, _, peak, valley, _ = profiles
    c = peak - valley
    ok = np.isfinite(valley) & (c >= min_contrast) & (peak >= ht) & (peak <= peak_max)
    return float(np.percentile(c[ok], SLAB_REFERENCE_PERCENTILE)) if ok.any() else np.nan


def full_contrast(own, shared):
    """The full cortical contrast a bone's edge level is measured against: its own
    :func:`contrast_reference`, or the run's shared one when that is larger (cortical bone has
    about one density: a bone whose cortex is thin everywhere, a rib or a thin shell, never
    shows the full contrast itself, and its half maximum lies outside it). NaN when neither
    is known."""
    vals = [v for v in (own, shared) if v is not None and np.isfinite(v)]
    return float(max(vals)) if vals else np.nan


def refine_to_edges(vertices, faces, ct_smooth, spacing, ht, *, edge_level=None,
                    max_shift=MAX_SHIFT_MM, min_contrast=MIN_CONTRAST_HU,
                    smoothness=REFINE_ALPHA, damping=REFINE_BETA, passes=REFINE_PASSES,
                    allowed=None, progress=None, plate_targets=None,
                    fallbacks=None, shared_reference=None, info=None, profiles=None):
    """Move each vertex along its normal to the CT profile's edge at ``edge_level``.

    Repeats :func:`refine_pass` (vertices held back by the back-off get another chance once
    their neighbours have moved); the result is verified free of flips and self-intersections
    against the input surface.

    Parameters
    ----------
    vertices : (n, 3) float64 array
        x-y-z grid millimetres; an outward, intersection-free closed surface.
    faces : (m, 3) int array
    ct_smooth : (z, y, x) float array
        The lightly smoothed CT (HU) on a grid from the working grid's first voxel.
    spacing : float or (x, y, z) floats
        That grid's step in mm (or per axis).
    ht : float
        HT in HU: a profile whose peak is below it gives no edge.
    edge_level : float or None
        Where between the outside valley (0) and the bone peak (1) the edge sits; None: per
        vertex by the blurred-slab model (:func:`slab_edge_level`), 0.5 at thick cortex.
    max_shift, min_contrast, smoothness, damping, passes
        See the module constants (smoothness and damping are the refinement's own Laplacian and
        damping weights, not the deformation's alpha and beta).
    allowed : callable, optional
        points (n, 3) -> bool: where a target may lie (another bone's side of a joint may
        not); targets elsewhere are dropped.
    progress : callable, optional
        progress(fraction, message) after each pass.
    plate_targets : callable, optional
        (vertices (n, 3), normals (n, 3)) -> (n,) shift along the normal (mm) onto a thin
        plate's face, NaN where none (:meth:`.plates.Plates.targets`): the target of the
        vertices whose profile shows no edge.
    fallbacks : BoneWatertightLib.report.FallbackLog, optional
        Notes every step that fell back (the automatic level, a pass or verification round
        whose result was discarded, vertices held at their verified position).
    shared_reference : float, optional
        The full cortical contrast (HU) of the bones reconstructed together (the largest of
        their :func:`contrast_reference`): the automatic level measures against it where it
        exceeds this bone's own (:func:`full_contrast`).
    info : dict, optional
        Filled with ``own_reference_hu`` and ``reference_hu`` (the contrast used).
    profiles : tuple, optional
        :func:`sample_profiles` of ``vertices``, when already sampled.

    Returns
    -------
    vertices : (n, 3) float64 array
    shift : (n,) float64 array
        Signed move along the input's vertex normals (mm, outward positive).
    fraction : float
        Fraction of vertices whose profile had an edge (last pass).
    found : (n,) bool array
        Which vertices' profiles had an edge (last pass).
    """
    v = vertices
    frac = 0.0
    found = np.zeros(len(vertices), bool)

    def note(what, count, unit, where=""):
        if fallbacks is not None:
            fallbacks.add("refine", what, count, unit, where)

    first = profiles if profiles is not None else sample_profiles(vertices, faces, ct_smooth,
                                                                  spacing)  # level's, pass 1's
    if edge_level is None:
        own = contrast_reference(vertices, faces, ct_smooth, spacing, ht, min_contrast,
                                 profiles=first)
        reference = full_contrast(own, shared_reference)
        if info is not None:
            info.update(own_reference_hu=own, reference_hu=reference)
        edge_level = 0.5 if not np.isfinite(reference) else ("slab", reference)
        if edge_level == 0.5:
            note("no profile has a cortical contrast for the automatic edge level: the half "
                 "maximum (0.5) is used", 1, "")
    L = laplacian(len(vertices), faces)
    ops = ((L.T @ L).tocsr(), (sp.identity(len(vertices), format="csr") - L).tocsr())
    for i in range(passes):
        v, _, found, ok = refine_pass(v, faces, ct_smooth, spacing, ht, max_shift, min_contrast,
                                      smoothness, damping, ops=ops, edge_level=edge_level,
                                      allowed=allowed, plate_targets=plate_targets,
                                      fallbacks=fallbacks, profiles=first if i == 0 else None,
                                      start=vertices)
        frac = float(found.mean())
        if progress:
            progress((i + 1) / (passes + VERIFY_ROUNDS), f"edge refinement {i + 1}/{passes}")
        if not ok:
            note("the flip back-off gave up: the later passes were skipped", passes - 1 - i,
                 "passes", f"pass {i + 1}")
            break
    # Passes check only for flips; the exact self-intersection test runs against the verified
    # input surface. Vertices it puts back get another pass (they would stand out as spikes
    # among refined neighbours), then the result is verified again; at most three rounds.
    clean = vertices
    for r in range(VERIFY_ROUNDS):
        if progress:
            progress((passes + r) / (passes + VERIFY_ROUNDS), "edge refinement: verifying")
        checked, ok, _ = safe_update(clean, v, faces, halvings=BACKOFF_HALVINGS)
        if not ok:
            note("the unrefined surface is kept: the refined one failed the self-intersection "
                 "check" if r == 0 else "a re-refinement failed the self-intersection check: "
                 "the surface verified before it is kept",
                 int(np.any(v != clean, axis=1).sum()), "vertices", f"round {r + 1}")
            v = clean
            break
        reverted = np.any(checked != v, axis=1)
        clean = v = checked
        if not reverted.any():
            break
        last_reverted = int(reverted.sum())
        v, _, _, ok = refine_pass(v, faces, ct_smooth, spacing, ht, max_shift, min_contrast,
                                  smoothness, damping, ops=ops, edge_level=edge_level,
                                  allowed=allowed, plate_targets=plate_targets,
                                  fallbacks=fallbacks, start=vertices)
        if not ok:
            note("the re-refinement of the vertices the check put back was reverted (the flip "
                 "back-off gave up)", int(reverted.sum()), "vertices", f"round {r + 1}")
            v = clean
            break
    else:
        note("vertices still put back by the self-intersection check after "
             f"{VERIFY_ROUNDS} rounds keep their verified position (the last re-refinement is "
             "not kept)", last_reverted, "vertices")
        v = clean
    n = vertex_normals(vertices, faces)
    return v, np.einsum("ij,ij->i", v - vertices, n), frac, found


def edge_crossings(vertices, faces, ct_smooth, spacing, ht, edge_level,
                   min_contrast=MIN_CONTRAST_HU, profiles=None, allowed=None):
    """Where each vertex's CT profile crosses its edge level.

    Parameters
    ----------
    vertices : (n, 3) float array
        x-y-z grid millimetres of a closed outward surface; ``faces`` (m, 3).
    ct_smooth, spacing, ht, min_contrast
        As :func:`refine_to_edges`.
    edge_level : float or ("slab", full contrast in HU)
        As :func:`refine_pass`.
    profiles : tuple, optional
        :func:`sample_profiles` of these vertices, when already sampled.
    allowed : callable, optional
        points (n, 3) -> bool, this bone's side of its joints (as :func:`refine_to_edges`):
        a layer beyond the dip whose peak lies elsewhere is a neighbour's cortex across a
        joint space, not this bone's outer layer, and anchors nothing.

    Returns
    -------
    normals : (n, 3) float array
    t_cross : (n,) float array
        Signed distance (mm, along the normal, outward positive) from the vertex to the edge.
    ok : (n,) bool array
        Whether the profile has an edge (peak at least HT and ``min_contrast`` above the valley
        outside it).
    contrast : (n,) float array
        Peak - valley (HU).
    """
    if profiles is None:
        profiles = sample_profiles(vertices, faces, ct_smooth, spacing)
    n, t, prof, i_peak, peak, valley, inner = profiles
    cols = np.arange(len(t))[None, :]
    rows = np.arange(len(prof))
    reach = int(np.count_nonzero(t <= PEAK_REACH_MM))
    for attempt in range(REANCHOR_ROUNDS + 1):
        with np.errstate(invalid="ignore", divide="ignore"):
            contrast = peak - valley
            if isinstance(edge_level, tuple):
                fraction = slab_edge_level(contrast / edge_level[1], (peak - inner) / contrast)
            else:
                fraction = edge_level
        level = valley + fraction * (peak - valley)
        below = (prof < level[:, None]) & (cols > i_peak[:, None])
        first = np.argmax(below, axis=1)
        has = below[rows, first]
        # Bone again above the level after the first crossing, within the peak's reach: the
        # brightest sample was a deeper cortex (the far wall of a thin shell such as a cup,
        # seen through its cancellous middle), and the crossing found is the dip inside the
        # bone. The edge is that of the outer layer: its peak anchors the profile instead.
        after = cols[:, :reach] > first[:, None]
        dip = np.minimum.accumulate(np.where(after, prof[:, :reach], np.inf), axis=1)
        again = has & (after & (prof[:, :reach] >= level[:, None])
                       & (prof[:, :reach] - dip >= REANCHOR_RISE_HU)).any(axis=1)
        if attempt == REANCHOR_ROUNDS or not again.any():
            break
        r = np.flatnonzero(again)
        outer = np.where(cols[:, :reach] > first[r, None], prof[r, :reach], -np.inf)
        i_new = np.argmax(outer, axis=1)
        if allowed is not None:
            mine = allowed(vertices[r] + t[i_new][:, None] * n[r])
            r, i_new = r[mine], i_new[mine]
            if not len(r):
                break
        i_peak, peak, valley, inner = (a.copy() for a in (i_peak, peak, valley, inner))
        i_peak[r] = i_new
        peak[r] = prof[r, i_new]
        valley[r], inner[r] = _valley_and_inner(t, prof[r], i_new, peak[r])
    k1 = np.maximum(first - 1, 0)
    g0 = prof[rows, k1]
    g1 = prof[rows, first]
    frac = np.clip((g0 - level) / np.maximum(g0 - g1, 1e-6), 0.0, 1.0)
    t_cross = t[k1] + frac * PROFILE_STEP_MM
    ok = has & np.isfinite(valley) & (contrast >= min_contrast) & (peak >= ht)
    return n, t_cross, ok, np.where(np.isfinite(contrast), contrast, 0.0)


def refine_pass(vertices, faces, ct_smooth, spacing, ht, max_shift=MAX_SHIFT_MM,
                min_contrast=MIN_CONTRAST_HU, smoothness=REFINE_ALPHA, damping=REFINE_BETA, ops=None,
                edge_level=None, allowed=None, plate_targets=None,
                fallbacks=None, profiles=None, start=None):
    """Return (new vertices, per-vertex shift along the normal, edge found (n,) bool, ok).

    The edge points are soft targets of one regularised Laplacian step (as in the deformation)
    followed by the local back-off, so the result never folds or self-intersects.
    ``edge_level``: a number in (0, 1), or ("slab", full contrast in HU) for the blurred-slab
    model's level per vertex; None: that model with the full contrast of these vertices
    (:func:`contrast_reference`). ``profiles``: :func:`sample_profiles` of ``vertices``, when
    already sampled. ``start``: (n, 3) vertices where the refinement started; the targets lie
    within ``max_shift`` of them along the normals (None: of ``vertices``)."""
    if profiles is None:
        profiles = sample_profiles(vertices, faces, ct_smooth, spacing)
    if edge_level is None:
        reference = contrast_reference(vertices, faces, ct_smooth, spacing, ht, min_contrast,
                                       profiles=profiles)
        edge_level = 0.5 if not np.isfinite(reference) else ("slab", reference)
    n, t_cross, ok, _ = edge_crossings(vertices, faces, ct_smooth, spacing, ht, edge_level,
                                       min_contrast, profiles=profiles, allowed=allowed)
    # The bound holds for the whole refinement: a pass's target lies within max_shift of where
    # the refinement started (``start``), not of where the last pass left the vertex.
    done = 0.0 if start is None else np.einsum("ij,ij->i", vertices - start, n)
    lo, hi = -max_shift - done, max_shift - done
    shift = np.where(ok, np.clip(t_cross, lo, hi), 0.0)
    w = ok.astype(np.float64)
    if plate_targets is not None:
        # No edge on the profile, but a plate thinner than the CT resolves: its model's face.
        plate = plate_targets(vertices, n)
        use = ~ok & np.isfinite(plate)
        shift = np.where(use, np.clip(np.nan_to_num(plate), lo, hi), shift)
        w[use] = 1.0
    if ops is None:
        L = laplacian(len(vertices), faces)
        ops = ((L.T @ L).tocsr(), (sp.identity(len(vertices), format="csr") - L).tocsr())
    LtL, avg = ops
    # A vertex whose edge disagrees with its neighbours' (noise, a pore at the surface, a
    # grazing profile) gets no target: the Laplacian term carries it with its neighbours.
    # Targets are compared where they lie, not by how far each vertex moves: a vertex that
    # stands out of its ring (a spike the deformation or a back-off left) keeps a target that
    # lies with its neighbours' targets. ``spike``: how much further it stands out along its
    # normal than its neighbours do (a process tip whose whole ring is as curved is no spike;
    # there the test stays that of the shifts).
    height = np.einsum("ij,ij->i", vertices - avg @ vertices, n)
    spike = height - avg @ height
    w[np.abs(shift + spike - ring_mean(avg, shift, w))
      > max(OUTLIER_MM, OUTLIER_VOXELS * float(np.max(spacing)))] = 0.0
    targets = vertices + shift[:, None] * n
    if allowed is not None:
        # never toward another bone's side of a joint
        w[~allowed(targets)] = 0.0
    A = (smoothness * LtL + sp.diags(w + damping)).tocsr()
    rhs = w[:, None] * targets + smoothness * (LtL @ vertices) + damping * vertices
    new = solve_spd(A, rhs, vertices, fallbacks, "refine")
    new, safe, _ = safe_update(vertices, new, faces, intersections=False,
                               halvings=BACKOFF_HALVINGS)
    moved = np.einsum("ij,ij->i", new - vertices, n)
    return new, moved, ok, safe
