"""Stage 8 (several bones): keep neighbouring surfaces apart, then prove it.

Each bone's surface must stay on its side of every joint with at least ``min_gap`` between
surfaces. A bone's *territory* is where it is nearer than any other bone: with signed distance
fields S_k (negative inside k, from k's surface voxelised on the working grid) the midway surface
between bones k and j is S_k = S_j, and phi_k = (S_k - min_j S_j) / 2 is (to voxel accuracy) the
signed distance of a point to it, negative on k's side. Bones that are not reconstructed
(neighbours given as labels, unlabelled bone) enter with the voxels they own.

- :func:`territories` builds phi_k from the M0 surfaces; the deformation and the edge
  refinement never target points beyond phi_k = -min_gap / 2 (:func:`allowed_test`).
- :func:`resolve_contacts` then moves every vertex still beyond it back (:func:`enforce`: soft
  targets of a regularised Laplacian solve, verified free of flips and self-intersections),
  from the current surfaces, a few passes.
- :func:`pair_report` checks every pair exactly: faces of one crossing faces of the other (the
  library's exact triangle test on the merged pair), vertices of one inside the other, and the
  smallest vertex-to-surface gap. A pair that fails is an error of the run.

Arrays: (z, y, x) grids; points (n, 3) x-y-z grid millimetres.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy import ndimage
from scipy.spatial import cKDTree

from ..mesh.checks import find_self_intersections
from ..mesh.operators import laplacian, safe_update, sample_field, vertex_normals
from ..mesh.surface import Surface, inside_mask, to_polydata
from .threshold import bbox_slices, near, paste_box
from ..mesh.distance import signed_distance as signed_distance_map
from ..threads import thread_map

# Box margin (mm) of the signed distance fields.
SDF_PAD_MM = 6.0
# Vertices are moved to this far (x d) beyond -min_gap / 2: the fields are voxel-accurate.
TARGET_MARGIN_VOXELS = 0.3
# Regularised solve of the enforcement: smoothness weight, weight of vertices not moved.
ENFORCE_SMOOTHNESS = 0.3
ENFORCE_FREE_WEIGHT = 0.05
ENFORCE_ROUNDS = 12
# Rings of neighbours around the offending vertices that move with them.
ENFORCE_RINGS = 6
# Rings around a vertex whose move keeps being backed off that are relaxed (see enforce).
ENFORCE_RELAX_RINGS = 2
# Passes of the contact resolution (each from the current surfaces).
CONTACT_PASSES = 3
# Beyond a field's box no other bone is near: phi reads -FAR there (always on the bone's side).
FAR = 1e3
# Exact gap (keep_gap_exact): each vertex closer than the gap to the other surface moves away
# from its nearest point there by GAP_SHARE of its shortfall + GAP_EXTRA_MM (both surfaces move,
# so a little over half), at
# most GAP_ROUNDS times; candidates lie within the gap + GAP_SEARCH_MM of the other's vertices
# (more than an edge: the nearest point of a triangle can be far from its corners).
GAP_SHARE = 0.6
GAP_EXTRA_MM = 0.01
GAP_ROUNDS = 6
GAP_SEARCH_MM = 2.0


def voxelize(vertices: np.ndarray, faces: np.ndarray, shape: tuple, spacing: float) -> np.ndarray:
    """Voxel centres of a (z, y, x) grid of ``spacing`` inside a closed surface (grid mm)."""
    return inside_mask(Surface(vertices, faces), shape, spacing)


def signed_distance(mask: np.ndarray, box: tuple, spacing: float) -> np.ndarray:
    """Signed distance (mm, negative inside) of ``mask`` within ``box`` (float32)."""
    sub = mask[box]
    return (signed_distance_map(sub) * spacing).astype(np.float32)


def territories(surfaces: dict, fixed: dict, shape: tuple, spacing: float, *,
                only=None, cache: dict | None = None, threads: int = 1) -> dict:
    """phi per reconstructed bone from ``surfaces`` ({key: (vertices, faces)} grid mm) and the
    owned voxels of the bones that are not reconstructed (``fixed``: {key: bool mask}).

    phi is computed only where another bone comes within SDF_PAD_MM (a box around the joint),
    so a long bone pays for its joints, not for its length; and each bone is worked in a window
    around it, so n bones cost n windows, not n^2 whole grids. None: no other bone is near.
    ``only``: the keys whose phi is wanted (default: all of ``surfaces``). ``cache``: a dict
    kept between calls; a surface whose vertex array is the same object as at the last call is
    not voxelised again. ``threads``: bones worked at once (the same fields with any number)."""
    masks = _territory_masks(surfaces, fixed, shape, spacing, cache, threads)
    keys = list(surfaces if only is None else only)
    return dict(zip(keys, thread_map(lambda k: _phi(k, masks, shape, spacing), keys, threads,
                                     "contacts")))


def _territory_masks(surfaces: dict, fixed: dict, shape: tuple, spacing: float,
                     cache: dict | None, threads: int) -> dict:
    """{key: (box, mask)}: each surface voxelised around itself (cached by vertex array, see
    :func:`territories`) and each fixed bone's owned voxels in their box."""
    todo = []
    masks = {}
    for k, (v, f) in surfaces.items():
        hit = cache.get(k) if cache is not None else None
        if hit is not None and hit[0] is v:
            masks[k] = hit[1]
        else:
            todo.append(k)
    done = thread_map(lambda k: _voxelize_local(surfaces[k][0], surfaces[k][1], shape, spacing),
                      todo, threads, "contacts")
    for k, entry in zip(todo, done):
        masks[k] = entry
        if cache is not None:
            cache[k] = (surfaces[k][0], entry)
    for k, m in fixed.items():
        if m is not None and m.any():
            box = bbox_slices(m, 0)
            masks[k] = (box, m[box])
    return masks


def _phi(k, masks: dict, shape: tuple, spacing: float):
    """Bone k's entry of :func:`territories`: (x-y-z origin of its box in grid mm, phi
    (z, y, x) float32), or None where no other bone comes near."""
    pad = int(np.ceil(SDF_PAD_MM / spacing)) + 2
    box_k, sub_k = masks[k]
    if not sub_k.any():
        return None
    win = _window(box_k, shape, spacing, pad)
    mine = paste_box(masks[k], win)
    zone = near(mine, spacing, SDF_PAD_MM)
    others = [paste_box(m, win) for j, m in masks.items() if j != k]
    others = [m for m in others if m is not None]
    close = [m & zone for m in others]
    if not any(c.any() for c in close):
        return None
    union = np.zeros(mine.shape, bool)
    for c in close:
        union |= c
    box = bbox_slices(union, pad)
    own = signed_distance(mine, box, spacing)
    # The nearest other bone's signed distance, as that of the near bones' union: the same
    # outside them (the distance to the nearest one); inside one, the depth in the union
    # (deeper only where two others touch, far inside them). One transform instead of one per
    # neighbour.
    near_others = np.zeros(mine.shape, bool)
    for m, c in zip(others, close):
        if c.any():
            near_others |= m
    nearest = signed_distance(near_others, box, spacing)
    start = np.array([w.start + b.start for w, b in zip(win, box)][::-1], dtype=np.float64)
    return start * spacing, ((own - nearest) * 0.5).astype(np.float32)


def _voxelize_local(vertices: np.ndarray, faces: np.ndarray, shape: tuple,
                    spacing: float) -> tuple:
    """(box, mask): :func:`voxelize` on the grid's part around the surface (box: z, y, x
    slices; outside it no voxel centre is inside)."""
    lo = np.maximum(np.floor(vertices.min(axis=0) / spacing).astype(int) - 1, 0)
    hi = np.minimum(np.ceil(vertices.max(axis=0) / spacing).astype(int) + 2, np.array(shape[::-1]))
    hi = np.maximum(hi, lo + 1)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo[::-1], hi[::-1]))
    sub = inside_mask(Surface(vertices - lo * spacing, faces),
                      tuple(int(b - a) for a, b in zip(lo[::-1], hi[::-1])), spacing)
    return box, sub


def _window(box: tuple, shape: tuple, spacing: float, pad: int) -> tuple:
    """The part of the grid (z, y, x slices) where :func:`territories` works for a bone whose
    mask lies in ``box``: wide enough for :func:`near`'s reach of SDF_PAD_MM plus ``pad``, its
    start on a block of :func:`near`'s coarse grid (the same zone as on the whole grid)."""
    f = max(1, int(round(2.0 / spacing)))  # near()'s block (its step_mm = 2.0)
    reach = (int(np.ceil(SDF_PAD_MM / (f * spacing))) + 2) * f + pad
    win = []
    for b, n in zip(box, shape):
        a = max(0, b.start - reach)
        a -= a % f
        win.append(slice(a, min(n, b.stop + reach)))
    return tuple(win)


def allowed_test(phi_entry, spacing: float, min_gap: float):
    """points (n, 3) grid mm -> bool: on this bone's side, at least min_gap / 2 from the
    midway surface; None when no other bone is near."""
    if phi_entry is None:
        return None
    origin, phi = phi_entry
    limit = -0.5 * min_gap - TARGET_MARGIN_VOXELS * spacing
    return lambda p: sample_field(phi, np.asarray(p) - origin, spacing, cval=-FAR) <= limit


def _ring_patch(adjacency, seeds: np.ndarray, rings: int) -> np.ndarray:
    patch = seeds.copy()
    for _ in range(rings):
        patch |= (adjacency @ patch.astype(np.float64)) > 0
    return patch


def _adjacency(n: int, faces: np.ndarray):
    """(n, n) csr matrix, 1 where two vertices share an edge (and on the diagonal)."""
    return (abs(laplacian(n, faces)) > 0).astype(np.float64).tocsr()


def _halfway_to_ring_mean(v: np.ndarray, adjacency, ring: np.ndarray) -> np.ndarray:
    """``v`` with the vertices of ``ring`` ((n,) bool) moved halfway to the mean of their
    one-ring (themselves included: ``adjacency`` from :func:`_adjacency`); unchecked."""
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    mean = (adjacency @ v) / np.maximum(degree, 1)[:, None]
    out = v.copy()
    out[ring] = 0.5 * (v[ring] + mean[ring])
    return out


def enforce(vertices: np.ndarray, faces: np.ndarray, phi_entry, spacing: float, gap: float,
            rounds: int = ENFORCE_ROUNDS, pinned: np.ndarray | None = None,
            operators: dict | None = None):
    """Move vertices with phi > -gap / 2 back along -grad phi; returns (vertices, number still
    beyond, number moved, number of moves discarded, number of vertices relaxed).

    Each round solves a regularised Laplacian system on the offending vertices and a few rings
    around them (the rest of the surface is fixed), so the neighbourhood follows smoothly; the
    rounds are checked for flipped faces, the result once exactly for self-intersections.
    When that check cannot be met the input is kept: every move is discarded (the fourth
    value counts them). ``pinned`` ((n,) bool): vertices that never move (a cap's).
    ``operators``: a dict kept between calls on the same ``faces`` (the mesh's Laplacian
    matrices, built once)."""
    if phi_entry is None:
        return vertices, 0, 0, 0, 0
    from scipy.sparse.linalg import spsolve

    origin, phi = phi_entry
    v = np.asarray(vertices, dtype=np.float64) - origin
    start = v.copy()
    target = -0.5 * gap - TARGET_MARGIN_VOXELS * spacing
    value = sample_field(phi, v, spacing, cval=-FAR)
    free = np.ones(len(v), bool) if pinned is None else ~np.asarray(pinned, bool)
    if not ((value > target) & free).any():
        return vertices, 0, 0, 0, 0
    grads = [ndimage.sobel(phi, axis=a) / (8.0 * spacing) for a in (2, 1, 0)]
    if operators is None or operators.get("faces") is not faces:
        L = laplacian(len(v), faces)
        built = {"faces": faces, "LtL": (L.T @ L).tocsr(),
                 "adjacency": (abs(L) > 0).astype(np.float64).tocsr()}
        if operators is not None:
            operators.update(built)
        operators = built
    LtL, adjacency = operators["LtL"], operators["adjacency"]
    moved = np.zeros(len(v), bool)
    relaxed_any = np.zeros(len(v), bool)
    stiffness = ENFORCE_SMOOTHNESS
    for r in range(rounds):
        value = sample_field(phi, v, spacing, cval=-FAR)
        bad = (value > target) & free
        if not bad.any():
            break
        moved |= bad
        g = np.stack([sample_field(gi, v[bad], spacing) for gi in grads], axis=1)
        g /= np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-6)
        goal = v.copy()
        goal[bad] = v[bad] - (value[bad] - target + 0.1 * spacing)[:, None] * g
        patch = _ring_patch(adjacency, bad, ENFORCE_RINGS) & free
        idx = np.flatnonzero(patch)
        rest = np.flatnonzero(~patch)
        w = np.where(bad, 1.0, ENFORCE_FREE_WEIGHT)
        A = (stiffness * LtL + sp.diags(w)).tocsr()
        rhs = w[:, None] * goal + stiffness * (LtL @ v)
        A_pp = A[idx][:, idx].tocsc()
        rhs_p = rhs[idx] - A[idx][:, rest] @ v[rest]
        new = v.copy()
        new[idx] = spsolve(A_pp, rhs_p)  # one factorisation for the three columns
        new, ok, _ = safe_update(v, new, faces, intersections=False)
        if not ok:
            new = v
        stuck = bad & np.all(new == v, axis=1)
        if stuck.any():
            # A move that would flip a face is backed off, round after round, at a fold or a
            # spike of the surface: relax the neighbourhood halfway to the mean of each vertex's
            # one-ring (itself included; a spike into the other bone comes back on its own
            # side), so the next round can move it.
            ring = _ring_patch(adjacency, stuck, ENFORCE_RELAX_RINGS) & free
            relaxed, ok, _ = safe_update(new, _halfway_to_ring_mean(new, adjacency, ring), faces,
                                         intersections=False)
            if ok:
                relaxed_any |= np.any(relaxed != new, axis=1)
                new = relaxed
        if np.array_equal(new, v):
            stiffness *= 2.0  # stuck: let the neighbourhood move more as a whole
        v = new
    checked, ok, _ = safe_update(start, v, faces, intersections=True)
    # safe_update gives up after its rounds: then keep the verified input
    v = checked if ok else start
    beyond = int((sample_field(phi, v, spacing, cval=-FAR) > -0.5 * gap).sum())
    return (v + origin, beyond, int(moved.sum()), 0 if ok else int(moved.sum()),
            int(relaxed_any.sum()) if ok else 0)


def resolve_contacts(surfaces: dict, fixed: dict, shape: tuple, spacing: float, min_gap: float,
                     passes: int = CONTACT_PASSES, progress=None,
                     pinned: dict | None = None, active=None,
                     cache: dict | None = None, threads: int = 1) -> list:
    """Keep the surfaces (dict key -> [vertices, faces], updated in place) apart by min_gap.

    ``pinned``: key -> (n,) bool of vertices that never move. ``active``: the keys that may
    move (default all; the others only hold their place). ``cache``: a dict kept between
    calls on the same surfaces (voxelised surfaces, Laplacians). ``threads``: bones worked at
    once within a pass (each bone's field is made from the surfaces as the pass found them,
    so the result does not depend on it). Returns one record per pass:
    {key: (moved, still beyond, moves discarded by the self-intersection check, vertices
    relaxed where moves kept flipping faces)}.

    A pass after the first works only on the bones that were still beyond their midway surface:
    the others stay within theirs, since the moves only take surfaces back into their own
    side, which moves every midway surface away from the bones that did not move. (The exact
    crossing test after the passes decides in any case.)"""
    history = []
    cache = {} if cache is None else cache
    masks = cache.setdefault("masks", {})
    operators = cache.setdefault("operators", {})
    active = list(surfaces) if active is None else list(active)
    for p in range(passes):
        fields = _territory_masks({k: (v, f) for k, (v, f) in surfaces.items()}, fixed, shape,
                                  spacing, masks, threads)
        for k in active:
            operators.setdefault(k, {})

        def work(k):
            entry = _phi(k, fields, shape, spacing)
            if entry is None:
                return None
            v, f = surfaces[k]
            # half a voxel more: the fields are voxelised
            return enforce(v, f, entry, spacing, min_gap + 0.5 * spacing,
                           pinned=(pinned or {}).get(k), operators=operators[k])

        record = {}
        for k, out in zip(active, thread_map(work, active, threads, "contacts")):
            if out is None:
                continue
            v2, beyond, moved, discarded, relaxed = out
            surfaces[k][0] = v2
            record[k] = (moved, beyond, discarded, relaxed)
        history.append(record)
        if progress:
            progress((p + 1) / passes, f"joint gaps, pass {p + 1}")
        active = [k for k, rec in record.items() if rec[1] > 0]
        if not active:
            break
    return history


# Last resort after the voxel-field passes (a sub-voxel sliver of one surface through the
# other): at most EXACT_ROUNDS rounds that move the vertices of the crossing faces of both
# surfaces inward along their normals by EXACT_STEP_VOXELS x the grid spacing.
EXACT_ROUNDS = 12
EXACT_STEP_VOXELS = 0.25


def push_apart_exact(va, fa, vb, fb, spacing: float, rounds: int = EXACT_ROUNDS):
    """Move the vertices of faces of one surface that cross the other inward (both surfaces),
    each step checked for flips and self-intersections, until no face of one crosses the other.

    Returns (va, vb, ok): ok when no crossing is left."""
    va = np.array(va, dtype=np.float64)
    vb = np.array(vb, dtype=np.float64)
    step = EXACT_STEP_VOXELS * spacing
    for _ in range(rounds):
        pairs = find_self_intersections(np.vstack([va, vb]), np.vstack([fa, fb + len(va)]))
        cross = pairs[(pairs[:, 0] < len(fa)) != (pairs[:, 1] < len(fa))] if len(pairs) else pairs
        if len(cross) == 0:
            return va, vb, True
        faces_a = np.unique(cross[cross < len(fa)])
        faces_b = np.unique(cross[cross >= len(fa)]) - len(fa)
        out = []
        for v, f, bad in ((va, fa, faces_a), (vb, fb, faces_b)):
            idx = np.unique(f[bad])
            new = v.copy()
            new[idx] -= step * vertex_normals(v, f)[idx]
            new, _, _ = safe_update(v, new, f, intersections=True)
            out.append(new)
        va, vb = out
    pairs = find_self_intersections(np.vstack([va, vb]), np.vstack([fa, fb + len(va)]))
    ok = not len(pairs) or not ((pairs[:, 0] < len(fa)) != (pairs[:, 1] < len(fa))).any()
    return va, vb, ok


def keep_gap_exact(va, fa, vb, fb, gap: float, rounds: int = GAP_ROUNDS):
    """Move the vertices of each surface that lie closer than ``gap`` to the other away from
    their nearest point on it, by a share of the shortfall measured exactly (point to
    triangle), each step checked for flips and self-intersections, until no vertex of one is
    closer than ``gap`` to the other or ``rounds`` are used. A vertex whose move would flip a
    face (the tip of a spike or fold) has its one-ring relaxed halfway to its mean instead;
    where neither can move, the corners of the other surface's nearest face move away from it
    in the next round (found at a cup's rim: 0.16 mm left of min_gap 0.2).
    The voxel-accurate fields of :func:`resolve_contacts` leave pairs up to a voxel closer
    than ``gap``; this closes the rest. The surfaces must not cross.

    Returns (va, vb, moved vertices of a, moved vertices of b, smallest gap left mm or None
    where no vertex of one is within ``gap`` + GAP_SEARCH_MM of the other)."""
    va = np.array(va, dtype=np.float64)
    vb = np.array(vb, dtype=np.float64)
    start_a, start_b = va.copy(), vb.copy()
    adjacency = {}  # built once per surface, when a vertex first gets stuck
    pushes = {0: None, 1: None}  # moves of one surface's vertices asked by the other's stuck ones
    smallest = None
    for r in range(rounds + 1):
        near = [_close_vertices(va, vb, fb, gap), _close_vertices(vb, va, fa, gap)]
        found = np.concatenate([d for d, _, _ in near])
        smallest = float(found.min()) if len(found) else None
        if r == rounds or smallest is None or smallest >= gap:
            break
        out, asked = [], {0: None, 1: None}
        for side, v, f, (d, idx, away) in ((0, va, fa, near[0]), (1, vb, fb, near[1])):
            short = d < gap
            if not short.any() and pushes[side] is None:
                out.append(v)
                continue
            new = v.copy()
            step = GAP_SHARE * (gap - d[short]) + GAP_EXTRA_MM
            new[idx[short]] += step[:, None] * away[short]
            if pushes[side] is not None:
                new[pushes[side][0]] += pushes[side][1]
            new, _, _ = safe_update(v, new, f, intersections=True)
            stuck = idx[short][np.all(new[idx[short]] == v[idx[short]], axis=1)]
            if len(stuck):
                # The tip of a spike or fold: relax its one-ring halfway to the ring's mean.
                if side not in adjacency:
                    adjacency[side] = _adjacency(len(v), f)
                mark = np.zeros(len(v), bool)
                mark[stuck] = True
                ring = _ring_patch(adjacency[side], mark, 1)
                relaxed, ok, _ = safe_update(new, _halfway_to_ring_mean(new, adjacency[side], ring),
                                             f, intersections=True)
                if ok:
                    new = relaxed
                still = np.all(new[stuck] == v[stuck], axis=1)
                if still.any():
                    # Neither it nor its ring can move (a vertex at a rim or fold whose every
                    # move crosses its own surface): the other surface's nearest face moves
                    # away from it instead, in the next round.
                    sel = np.isin(idx, stuck[still]) & short
                    asked[1 - side] = _nearest_face_moves(
                        v[idx[sel]], -away[sel], GAP_SHARE * (gap - d[sel]) + GAP_EXTRA_MM,
                        (vb, fb) if side == 0 else (va, fa))
            out.append(new)
        va, vb = out
        pushes = asked
    moved_a = int(np.any(va != start_a, axis=1).sum())
    moved_b = int(np.any(vb != start_b, axis=1).sum())
    return va, vb, moved_a, moved_b, smallest


def _nearest_face_moves(points, directions, steps, other):
    """(vertex indices (m,), moves (m, 3)) of the surface ``other`` = (vertices, faces) that
    take the corners of its face nearest each of ``points`` (k, 3) by ``steps`` (k,) along
    ``directions`` (k, 3, unit); a corner of several such faces takes the largest move."""
    ov, of = other
    moves = {}
    for cell, u, step in zip(_closest_faces(points, ov, of)[0], directions, steps):
        for k in of[cell]:
            m = step * u
            if int(k) not in moves or np.dot(m, m) > np.dot(moves[int(k)], moves[int(k)]):
                moves[int(k)] = m
    ids = np.fromiter(moves, dtype=np.int64, count=len(moves))
    return ids, np.array([moves[int(k)] for k in ids]).reshape(-1, 3)


def _closest_faces(points, v, f) -> tuple:
    """(face index (k,) int, exact distance (k,) mm) of the face of the surface (v, f) nearest
    each of ``points`` (k, 3)."""
    from .. import _vtk as vtk

    loc = vtk.vtkCellLocator()
    loc.SetDataSet(to_polydata(Surface(v, f), normals=False))
    loc.BuildLocator()
    ids = np.empty(len(points), np.int64)
    d = np.empty(len(points))
    closest = [0.0, 0.0, 0.0]
    cell, sub, dist2 = vtk.reference(0), vtk.reference(0), vtk.reference(0.0)
    for i, p in enumerate(points):
        loc.FindClosestPoint(p, closest, cell, sub, dist2)
        ids[i] = int(cell)
        d[i] = float(dist2) ** 0.5
    return ids, d


def _close_vertices(v, other_v, other_f, gap: float):
    """The vertices of ``v`` within ``gap`` + GAP_SEARCH_MM of the vertices of the other
    surface: (their exact distance to its triangles (mm), their indices, and for those closer
    than ``gap`` the unit direction away from their nearest point on it (else 0))."""
    from .. import _vtk as vtk
    from .._vtk import numpy_support as ns

    empty = (np.zeros(0), np.zeros(0, np.int64), np.zeros((0, 3)))
    if not len(v) or not len(other_v):
        return empty
    near_v, _ = cKDTree(other_v).query(v, distance_upper_bound=gap + GAP_SEARCH_MM)
    idx = np.flatnonzero(np.isfinite(near_v))
    if not len(idx):
        return empty
    dist = vtk.vtkImplicitPolyDataDistance()
    dist.SetInput(to_polydata(Surface(other_v, other_f), normals=False))
    values = vtk.vtkDoubleArray()
    dist.FunctionValue(ns.numpy_to_vtk(np.ascontiguousarray(v[idx]), deep=True), values)
    d = np.abs(ns.vtk_to_numpy(values)).astype(np.float64)
    away = np.zeros((len(idx), 3))
    closest = [0.0, 0.0, 0.0]
    for j in np.flatnonzero(d < gap):
        p = v[idx[j]]
        dist.EvaluateFunctionAndGetClosestPoint(p, closest)
        u = p - np.asarray(closest)
        length = np.linalg.norm(u)
        if length > 1e-9:
            away[j] = u / length
    return d, idx, away


def _face_ids_meeting(v: np.ndarray, f: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The indices (m,) of the faces of (v, f) whose bounding boxes meet the box [lo, hi]
    (x-y-z mm)."""
    tri = v[f]
    keep = np.all(tri.min(axis=1) <= hi, axis=1) & np.all(tri.max(axis=1) >= lo, axis=1)
    return np.flatnonzero(keep)


def crossing_faces(va, fa, vb, fb) -> tuple:
    """The faces of two surfaces that cross each other (exact test): two (k,) int arrays, the
    face of a and the face of b of each crossing pair (vertices in any common frame, mm)."""
    va = np.asarray(va, dtype=np.float64)
    vb = np.asarray(vb, dtype=np.float64)
    fa = np.asarray(fa, dtype=np.int64)
    fb = np.asarray(fb, dtype=np.int64)
    lo = np.maximum(va.min(axis=0), vb.min(axis=0)) - 2.0
    hi = np.minimum(va.max(axis=0), vb.max(axis=0)) + 2.0
    none = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if np.any(hi < lo):
        return none
    # Faces of one can cross faces of the other only where their boxes overlap: the exact
    # test runs on the faces whose own boxes meet that region (a long bone pays for its joint).
    ia = _face_ids_meeting(va, fa, lo, hi)
    ib = _face_ids_meeting(vb, fb, lo, hi)
    if not (len(ia) and len(ib)):
        return none
    merged = np.vstack([va, vb])
    mf = np.vstack([fa[ia], fb[ib] + len(va)])
    pairs = find_self_intersections(merged, mf)
    if not len(pairs):
        return none
    cross = (pairs[:, 0] < len(ia)) != (pairs[:, 1] < len(ia))
    pairs = np.sort(pairs[cross], axis=1)  # (face of a, face of b) in the merged order
    return ia[pairs[:, 0]], ib[pairs[:, 1] - len(ia)]


def pair_report(va, fa, vb, fb, crossing_only: bool = False) -> dict:
    """Exact check of two surfaces (vertices in any common frame, mm).

    Returns ``crossing_face_pairs`` (faces of one crossing faces of the other), ``a_inside_b``
    / ``b_inside_a`` (vertices of one inside the other), ``min_gap_mm`` (smallest distance of a
    vertex of one to the other surface) and ``contact_area_mm2`` (area of a's faces within
    1 mm of b). With ``crossing_only`` only the first is measured (the others stay 0 / None)."""
    from .. import _vtk as vtk

    va = np.asarray(va, dtype=np.float64)
    vb = np.asarray(vb, dtype=np.float64)
    lo = np.maximum(va.min(axis=0), vb.min(axis=0)) - 2.0
    hi = np.minimum(va.max(axis=0), vb.max(axis=0)) + 2.0
    out = {"crossing_face_pairs": 0, "a_inside_b": 0, "b_inside_a": 0,
           "min_gap_mm": None, "contact_area_mm2": 0.0}
    if np.any(hi < lo):
        return out
    out["crossing_face_pairs"] = len(crossing_faces(va, fa, vb, fb)[0])
    if crossing_only:
        return out

    def distances(points, v, f):
        return _closest_faces(points, v, f)[1]

    def inside(points, v, f):
        if len(points) == 0:
            return np.zeros(0, bool)
        pts = vtk.vtkPoints()
        from .._vtk import numpy_support as ns
        pts.SetData(ns.numpy_to_vtk(np.ascontiguousarray(points), deep=True))
        poly = vtk.vtkPolyData()
        poly.SetPoints(pts)
        sel = vtk.vtkSelectEnclosedPoints()
        sel.SetInputData(poly)
        sel.SetSurfaceData(to_polydata(Surface(v, f), normals=False))
        sel.SetTolerance(1e-9)
        sel.Update()
        arr = sel.GetOutput().GetPointData().GetArray("SelectedPoints")
        return ns.vtk_to_numpy(arr).astype(bool)

    near_a = np.all((va >= lo) & (va <= hi), axis=1)
    near_b = np.all((vb >= lo) & (vb <= hi), axis=1)
    if near_a.any() and near_b.any():
        # candidates within 3 mm of the other's vertices
        tb = cKDTree(vb[near_b])
        da, _ = tb.query(va[near_a], distance_upper_bound=3.0)
        ta = cKDTree(va[near_a])
        db, _ = ta.query(vb[near_b], distance_upper_bound=3.0)
        ia = np.flatnonzero(near_a)[np.isfinite(da)]
        ib = np.flatnonzero(near_b)[np.isfinite(db)]
        gaps = []
        if len(ia):
            gaps.append(distances(va[ia], vb, fb))
            out["a_inside_b"] = int(inside(va[ia], vb, fb).sum())
        if len(ib):
            gaps.append(distances(vb[ib], va, fa))
            out["b_inside_a"] = int(inside(vb[ib], va, fa).sum())
        if gaps:
            g = np.concatenate(gaps)
            out["min_gap_mm"] = float(g.min())
            if len(ia):
                close = np.zeros(len(va), bool)
                close[ia[gaps[0] < 1.0]] = True
                tri_close = close[fa].all(axis=1)
                e1 = va[fa[tri_close, 1]] - va[fa[tri_close, 0]]
                e2 = va[fa[tri_close, 2]] - va[fa[tri_close, 0]]
                out["contact_area_mm2"] = float(0.5 * np.linalg.norm(np.cross(e1, e2), axis=1).sum())
    return out
