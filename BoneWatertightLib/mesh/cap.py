"""Close a bone cut by the scan's field of view with a flat cap exactly at the image boundary.

The pipeline reconstructs a cut bone on a grid that continues past the image boundary (CT and
labels replicated there), so the surface crosses the boundary plane cleanly. :func:`cap_plane`
clips it by the plane (every triangle split exactly where its edges cross) and closes each cut
loop by a planar triangulation: interior points on a hexagonal lattice plus Delaunay, keeping
every loop edge (with VTK's contour triangulator as the fallback), so the result is closed and
2-manifold again. The cap's faces are flagged, as 3D Slicer closes a padded segmentation.

Coordinates: (n, 3) x-y-z points in any frame in which the plane is axis-aligned (the
pipeline's grid millimetres).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay, cKDTree

from ..errors import ReconstructionError

# Vertices closer than this (x the mean edge length) to the plane are moved off it first, so
# no clipped triangle is a sliver. Where two sheets of the surface lie closer than that to each
# other, the move can make the cut outline cross itself, or the surface near the plane cross
# itself or the cap: then the next, smaller fraction is tried (found on a rib cage cut by a
# 20-slice CT and on a proximal femur cut by a 3 mm pelvis CT).
SNAP_FRACTIONS = (0.2, 0.1, 0.05, 0.02)
SNAP_FRACTION = SNAP_FRACTIONS[0]
# When every snap distance fails on the plane itself, the cut is made again this far (x the
# edge length) inside the image: a surface nearly tangent to the border plane (a vertebra's
# end plate on the slab's first slice) cuts it in many small loops close together, and a
# slightly different plane cuts it cleanly (found on T12 of the 20-slice slab: the border
# failed, 0.1 and 0.25 edge lengths inside did not).
PLANE_SHIFTS = (0.0, 0.1, 0.25, 0.5)
# Interior cap points keep this distance (x the edge length, and x each loop edge's length)
# from the loop: outside every loop edge's diametral circle, so Delaunay keeps the loop edges.
INTERIOR_MARGIN = 0.6


class CapError(ReconstructionError):
    """A cut outline that could not be closed."""


def clip_by_plane(vertices: np.ndarray, faces: np.ndarray, flags: np.ndarray, axis: int,
                  side: int, position: float, snap: float):
    """Keep the part of a closed surface with ``(x[axis] - position) * side <= 0``.

    Returns ``(vertices, faces, flags, loop_edges)``: loop_edges (k, 2) are the new boundary's
    directed edges (as half-edges of the kept faces), all on the plane.
    """
    v = np.array(vertices, dtype=np.float64)
    h = (v[:, axis] - position) * side
    near = np.abs(h) < snap
    if near.any():
        sign = np.where(h[near] >= 0, 1.0, -1.0)
        v[near, axis] = position + side * sign * snap
        h[near] = sign * snap
    out = h > 0
    fo = out[faces]
    n_out = fo.sum(axis=1)
    keep = faces[n_out == 0]
    keep_flags = flags[n_out == 0]
    # One new vertex per cut edge, shared by the two faces of that edge.
    cut_faces = np.flatnonzero((n_out > 0) & (n_out < 3))
    edge_ids = {}
    new_points = []

    def cut(a, b):
        key = (a, b) if a < b else (b, a)
        idx = edge_ids.get(key)
        if idx is None:
            t = h[a] / (h[a] - h[b])
            p = v[a] + t * (v[b] - v[a])
            p[axis] = position
            idx = len(v) + len(new_points)
            new_points.append(p)
            edge_ids[key] = idx
        return idx

    tris, tflags, loop = [], [], []
    for fi in cut_faces:
        f = faces[fi]
        o = fo[fi]
        if n_out[fi] == 1:
            k = int(np.flatnonzero(o)[0])
            a, b, c = int(f[k]), int(f[(k + 1) % 3]), int(f[(k + 2) % 3])  # a outside
            pab, pca = cut(a, b), cut(c, a)
            tris += [(pab, b, c), (pab, c, pca)]
            tflags += [flags[fi], flags[fi]]
            loop.append((pca, pab))
        else:
            k = int(np.flatnonzero(~o)[0])
            a, b, c = int(f[k]), int(f[(k + 1) % 3]), int(f[(k + 2) % 3])  # a inside
            pab, pca = cut(a, b), cut(c, a)
            tris.append((a, pab, pca))
            tflags.append(flags[fi])
            loop.append((pab, pca))
    allv = np.vstack([v] + ([np.array(new_points)] if new_points else []))
    allf = np.vstack([keep] + ([np.array(tris, dtype=np.int64)] if tris else []))
    allflags = np.concatenate([keep_flags, np.array(tflags, dtype=flags.dtype)])
    used, inv = np.unique(allf, return_inverse=True)
    remap = np.full(len(allv), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    loop = remap[np.array(loop, dtype=np.int64)] if loop else np.zeros((0, 2), np.int64)
    return allv[used], inv.reshape(-1, 3), allflags, loop


def _loops(edges: np.ndarray) -> list:
    nxt = {}
    for a, b in edges:
        if int(a) in nxt:
            raise CapError("The cut through the image boundary is not a set of simple loops.")
        nxt[int(a)] = int(b)
    loops, seen = [], set()
    for start in list(nxt):
        if start in seen:
            continue
        cur, loop = start, []
        while cur not in seen:
            seen.add(cur)
            loop.append(cur)
            if cur not in nxt:
                raise CapError("The cut through the image boundary is not closed.")
            cur = nxt[cur]
        if cur != start:
            raise CapError("Two cut loops through the image boundary share a vertex.")
        loops.append(loop)
    return loops


def _inside_loops(p: np.ndarray, polys: list) -> np.ndarray:
    """Even-odd rule over all loops: (m, 2) points, list of (k, 2) polygons."""
    inside = np.zeros(len(p), dtype=bool)
    for poly in polys:
        a, b = poly, np.roll(poly, -1, axis=0)
        for (x1, y1), (x2, y2) in zip(a, b):
            cross = (y1 > p[:, 1]) != (y2 > p[:, 1])
            with np.errstate(divide="ignore", invalid="ignore"):
                xi = x1 + (p[:, 1] - y1) * (x2 - x1) / (y2 - y1)
            inside ^= cross & (p[:, 0] < xi)
    return inside


def triangulate_region(points2d: np.ndarray, loops: list, spacing: float):
    """Triangles filling the region the loops bound, with interior points on a hexagonal
    lattice of ``spacing``; every loop edge is a triangle edge.

    Returns (interior points (m, 2), triangles (k, 3) indexing points2d then the interior
    points). Raises CapError when a loop edge would be lost (the caller falls back)."""
    polys = [points2d[lp] for lp in loops]
    lo = points2d.min(axis=0) - spacing
    hi = points2d.max(axis=0) + spacing
    rows = []
    for i, y in enumerate(np.arange(lo[1], hi[1], spacing * np.sqrt(3) / 2)):
        xs = np.arange(lo[0] + (0.5 * spacing if i % 2 else 0.0), hi[0], spacing)
        rows.append(np.column_stack([xs, np.full(len(xs), y)]))
    cand = np.vstack(rows) if rows else np.zeros((0, 2))
    if len(cand):
        cand = cand[_inside_loops(cand, polys)]
    if len(cand):
        a = np.vstack(polys)
        b = np.vstack([np.roll(p, -1, axis=0) for p in polys])
        seg_len = np.linalg.norm(b - a, axis=1)
        tree = cKDTree(0.5 * (a + b))
        reach = INTERIOR_MARGIN * max(spacing, float(seg_len.max())) + 0.5 * float(seg_len.max())
        keep = np.ones(len(cand), dtype=bool)
        for i, idx in enumerate(tree.query_ball_point(cand, r=reach)):
            if not idx:
                continue
            ab = b[idx] - a[idx]
            t = np.clip(np.einsum("ij,ij->i", cand[i] - a[idx], ab)
                        / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-30), 0.0, 1.0)
            dist = np.linalg.norm(a[idx] + t[:, None] * ab - cand[i], axis=1)
            keep[i] = np.all(dist > INTERIOR_MARGIN * np.maximum(spacing, seg_len[idx]))
        cand = cand[keep]
    allp = np.vstack([points2d, cand])
    tri = Delaunay(allp).simplices
    tri = tri[_inside_loops(allp[tri].mean(axis=1), polys)]
    have = set()
    for t in tri:
        for k in range(3):
            a_, b_ = int(t[k]), int(t[(k + 1) % 3])
            have.add((min(a_, b_), max(a_, b_)))
    for lp in loops:
        for a_, b_ in zip(lp, lp[1:] + lp[:1]):
            if (min(a_, b_), max(a_, b_)) not in have:
                raise CapError("a cut edge is not an edge of the cap triangulation")
    e1 = allp[tri[:, 1]] - allp[tri[:, 0]]
    e2 = allp[tri[:, 2]] - allp[tri[:, 0]]
    if (0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) <= 1e-9 * spacing ** 2).any():
        raise CapError("a cap triangle would be degenerate")
    return cand, tri


def _loops_cross(points2d: np.ndarray, loops: list) -> bool:
    """Whether two edges of the loops (not sharing a vertex) properly cross."""
    segs = np.array([(a, b) for lp in loops for a, b in zip(lp, lp[1:] + lp[:1])], dtype=np.int64)
    a, b = points2d[segs[:, 0]], points2d[segs[:, 1]]
    half = 0.5 * np.linalg.norm(b - a, axis=1)
    tree = cKDTree(0.5 * (a + b))
    for i, j in tree.query_pairs(r=2.0 * float(half.max()) + 1e-12, output_type="ndarray"):
        if np.intersect1d(segs[i], segs[j]).size:
            continue
        p, q, r, s_ = a[i], b[i], a[j], b[j]

        def orient(u, v, w):
            return (v[0] - u[0]) * (w[1] - u[1]) - (v[1] - u[1]) * (w[0] - u[0])

        if orient(p, q, r) * orient(p, q, s_) < 0 and orient(r, s_, p) * orient(r, s_, q) < 0:
            return True
    return False


def _triangulate_contours(points2d: np.ndarray, loops: list):
    """Fallback: VTK's contour triangulator (no interior points; holes by orientation)."""
    from .. import _vtk as vtk
    from .._vtk import numpy_support as ns

    pts = vtk.vtkPoints()
    pts.SetData(ns.numpy_to_vtk(np.column_stack([points2d, np.zeros(len(points2d))]), deep=True))
    lines = vtk.vtkCellArray()
    for lp in loops:
        for a, b in zip(lp, lp[1:] + lp[:1]):
            lines.InsertNextCell(2)
            lines.InsertCellPoint(a)
            lines.InsertCellPoint(b)
    poly = vtk.vtkPolyData()
    poly.SetPoints(pts)
    poly.SetLines(lines)
    areas = []
    for lp in loops:
        q = points2d[lp]
        areas.append(0.5 * np.sum(q[:, 0] * np.roll(q[:, 1], -1) - np.roll(q[:, 0], -1) * q[:, 1]))
    sign = 1.0 if areas[int(np.argmax(np.abs(areas)))] > 0 else -1.0
    out = vtk.vtkCellArray()
    ok = vtk.vtkContourTriangulator.TriangulateContours(poly, 0, poly.GetNumberOfLines(), out,
                                                        (0.0, 0.0, sign))
    conn = ns.vtk_to_numpy(out.GetConnectivityArray()) if out.GetNumberOfCells() else np.zeros(0)
    if not ok or len(conn) == 0 or len(conn) % 3:
        raise CapError("The outline where the bone leaves the image could not be triangulated.")
    return np.zeros((0, 2)), conn.reshape(-1, 3).astype(np.int64)


def cap_plane(vertices: np.ndarray, faces: np.ndarray, flags: np.ndarray, axis: int, side: int,
              position: float, edge_length: float, fallbacks=None):
    """Clip a closed surface at an axis-aligned plane and close the cut with a flat cap.

    Parameters
    ----------
    vertices : (n, 3) float array
        x-y-z coordinates of a closed, outward-oriented surface.
    faces : (m, 3) int array
    flags : (m,) uint8 array
        Per-face cap flag (1 = cap face), carried through the clip.
    axis : int
        0, 1 or 2: the plane is ``x[axis] = position``.
    side : int
        -1 or +1: the part kept is ``(x[axis] - position) * side <= 0`` (the image's side).
    position : float
    edge_length : float
        Mean edge length of the surface (snap distance and cap point spacing).
    fallbacks : BoneWatertightLib.report.FallbackLog, optional
        Notes a cut made again with a smaller snap distance, and a cap closed by VTK's
        contour triangulator.

    Returns
    -------
    vertices, faces, flags, area
        The capped surface and the cap's area (0 when the surface does not cross the plane).
    """
    uv = [a for a in range(3) if a != axis]
    error = None
    where = f"plane {'ijk'[axis]} {'low' if side < 0 else 'high'}"

    def note(what, count, unit):
        if fallbacks is not None:
            fallbacks.add("cap", what, count, unit, where)

    attempts = [(shift, fraction) for shift in PLANE_SHIFTS for fraction in SNAP_FRACTIONS]
    for attempt, (shift, fraction) in enumerate(attempts):
        # a shift moves the plane into the image (the part kept shrinks by a sliver)
        at = position - side * shift * edge_length
        v, f, fl, loop_edges = clip_by_plane(vertices, faces, flags, axis, side, at,
                                             fraction * edge_length)
        if len(loop_edges) == 0:
            return v, f, fl, 0.0
        try:
            loops = _loops(loop_edges)
            ids = np.unique(np.concatenate(loops))
            local = {int(g): i for i, g in enumerate(ids)}
            p2 = v[ids][:, uv]
            lloops = [[local[int(g)] for g in lp] for lp in loops]
            if _loops_cross(p2, lloops):
                raise CapError("The outline where the bone leaves the image crosses itself.")
            try:
                extra, tri = triangulate_region(p2, lloops, edge_length)
                contours = False
            except CapError:
                extra, tri = _triangulate_contours(p2, lloops)
                contours = True
            capped = _close(v, f, fl, ids, extra, tri, axis, side, at, uv)
            if _crosses_near_plane(capped[0], capped[1], axis, at, edge_length):
                raise CapError("The cap at the image boundary would cross the surface there.")
            if contours:
                note("the lattice triangulation lost a cut edge: VTK's contour triangulator "
                     "(no interior points) closed the cap", len(tri), "faces")
            if shift:
                note(f"cut {shift * edge_length:.2f} mm inside the image border (every snap "
                     f"distance failed on the border itself) after: {error}", attempt,
                     "retries")
            elif attempt:
                note(f"cut again with a smaller snap distance ({fraction:g} x the edge length) "
                     f"after: {error}", attempt, "retries")
            return capped
        except CapError as exc:
            error = exc
    raise error


def _crosses_near_plane(v, f, axis, position, edge_length) -> bool:
    """Whether faces within a few edge lengths of the plane (the only ones the clip, the snap
    and the cap change) intersect each other."""
    from .checks import find_self_intersections

    near = np.abs(v[:, axis] - position) <= 3.0 * edge_length
    sub = f[near[f].any(axis=1)]
    return len(sub) > 0 and len(find_self_intersections(v, sub)) > 0


def _close(v, f, fl, ids, extra, tri, axis, side, position, uv):
    """The clipped surface closed by the cap triangles ``tri`` (indexing ``ids`` then the
    interior points ``extra``): (vertices, faces, flags, cap area)."""
    new_ids = np.concatenate([ids, len(v) + np.arange(len(extra))])
    extra3 = np.zeros((len(extra), 3))
    extra3[:, uv] = extra
    extra3[:, axis] = position
    v = np.vstack([v, extra3])
    cap_faces = new_ids[tri]
    normal = np.cross(v[cap_faces[:, 1]] - v[cap_faces[:, 0]], v[cap_faces[:, 2]] - v[cap_faces[:, 0]])
    flip = normal[:, axis] * side < 0
    cap_faces[flip] = cap_faces[flip][:, ::-1]
    area = float(0.5 * np.linalg.norm(normal, axis=1).sum())
    f = np.vstack([f, cap_faces])
    fl = np.concatenate([fl, np.ones(len(cap_faces), dtype=fl.dtype)])
    return v, f, fl, area
