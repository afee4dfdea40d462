"""Checks of output surfaces: watertight, 2-manifold, oriented, no self-intersections (§4).

Every surface the library returns goes through :func:`check_surface` (or :func:`require_valid`,
which raises :class:`~BoneWatertightLib.errors.SurfaceCheckError`). Everything is vectorised
numpy/scipy so that a 200k-face surface is checked in about a second on one core.

Self-intersection policy: a pair of faces is reported when their interiors cross transversally,
or when they are coplanar and overlap with positive area (including two faces folded onto each
other across a shared edge). Contacts within the numeric tolerance (touching at a point or along a
segment without crossing) are not reported; degenerate faces are counted separately and excluded.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

from ..errors import SurfaceCheckError
from ..threads import cpu_threads, map_ahead

# Relative area below which a face counts as degenerate (times the squared mean edge length).
DEGENERATE_EPS = 1e-10
# Number of intersecting pairs kept in a report (the count is always complete).
MAX_STORED_PAIRS = 100
# Distance tolerance, relative to the size of the mesh's bounding box.
_REL_DIST_TOL = 1e-10
# Barycentric margin: a crossing point closer than this to a triangle's border is a contact.
_BARY_TOL = 1e-9
# Angle (rad) under which two faces sharing an edge are considered folded onto each other,
# and under which two directions in a plane are considered the same.
_ANGLE_TOL = 1e-7
# Candidate pairs handled per narrow-phase batch (bounds the memory of the broad phase and of
# the narrow phase's temporaries). Measured on a femur (87 k faces) and a hip bone (95 k):
# 2 M pairs per batch 0.30 / 0.31 s and 199 / 220 MB at the peak, 500 k 0.24 / 0.26 s and
# 114 / 120 MB (smaller batches stay in cache); the deformation's full checks set the run's
# peak memory.
_PAIR_BATCH = 500_000


@dataclass
class SurfaceReport:
    """Result of :func:`check_surface`. ``problems`` is empty exactly when ``ok``."""

    ok: bool
    problems: list = field(default_factory=list)
    n_vertices: int = 0
    n_faces: int = 0
    closed: bool = False
    edge_manifold: bool = False
    vertex_manifold: bool = False
    consistent_orientation: bool = False
    n_components: int = 0
    volume: float = 0.0
    outward: bool = False
    n_degenerate: int = 0
    n_self_intersections: int = 0
    self_intersection_pairs: np.ndarray = field(
        default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    genus: Optional[int] = None
    unreferenced_vertices: int = 0
    n_boundary_edges: int = 0
    n_nonmanifold_edges: int = 0
    n_nonmanifold_vertices: int = 0
    n_misoriented_edges: int = 0
    n_duplicate_faces: int = 0
    seconds: float = 0.0

    def to_dict(self) -> dict:
        """JSON-serialisable summary (plain Python types only)."""
        out = {}
        for key, value in self.__dict__.items():
            if isinstance(value, np.ndarray):
                value = value.tolist()
            elif isinstance(value, np.generic):
                value = value.item()
            elif isinstance(value, list):
                value = [str(v) for v in value]
            out[key] = value
        return out

    def summary(self) -> str:
        if self.ok:
            g = "" if self.genus is None else f", genus {self.genus}"
            return (f"watertight 2-manifold: {self.n_vertices} vertices, {self.n_faces} faces, "
                    f"volume {self.volume:.1f} mm^3{g}")
        return "; ".join(self.problems)


def check_surface(vertices, faces, *, expect_components: Optional[int] = 1,
                  check_self_intersections: bool = True) -> SurfaceReport:
    """Check a triangle mesh against SPEC §4 and return a :class:`SurfaceReport`.

    ``expect_components=None`` accepts any number of connected components.
    """
    t0 = time.perf_counter()
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    n, m = len(vertices), len(faces)
    rep = SurfaceReport(ok=False, n_vertices=n, n_faces=m)
    problems = rep.problems

    if m == 0:
        problems.append("the surface has no faces (empty result)")
        rep.seconds = time.perf_counter() - t0
        return rep
    if faces.min() < 0 or faces.max() >= n:
        problems.append(f"face indices outside 0..{n - 1} (corrupt mesh)")
        rep.seconds = time.perf_counter() - t0
        return rep
    used = np.zeros(n, dtype=bool)
    used[faces.ravel()] = True
    rep.unreferenced_vertices = int(n - used.sum())
    if not np.isfinite(vertices[used]).all():
        problems.append("vertex coordinates that are NaN or infinite (corrupt mesh)")
        rep.seconds = time.perf_counter() - t0
        return rep

    # Faces with a repeated index have no proper edges; they are reported as degenerate and
    # left out of the topology so that they do not also show up as holes.
    repeated = ((faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2])
                | (faces[:, 2] == faces[:, 0]))
    topo = faces[~repeated]
    _check_topology(rep, topo, n)

    # Geometry, recentred so that cross products do not lose digits to a far-away origin.
    centre = vertices[used].mean(axis=0)
    v = vertices - centre
    v0, v1, v2 = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    rep.volume = float(np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() / 6.0)
    rep.outward = bool(rep.volume > 0)
    edge_len = np.concatenate([np.linalg.norm(v1 - v0, axis=1), np.linalg.norm(v2 - v1, axis=1),
                               np.linalg.norm(v0 - v2, axis=1)])
    mean_edge = float(edge_len.mean())
    area = 0.5 * np.linalg.norm(np.cross(v1 - v0, v2 - v0), axis=1)
    degenerate = repeated | (area <= DEGENERATE_EPS * mean_edge ** 2)
    rep.n_duplicate_faces = _count_duplicate_faces(topo, n)
    rep.n_degenerate = int(degenerate.sum()) + rep.n_duplicate_faces

    if check_self_intersections:
        pairs = find_self_intersections(vertices, faces, exclude=degenerate)
        rep.n_self_intersections = int(len(pairs))
        rep.self_intersection_pairs = pairs[:MAX_STORED_PAIRS]

    # Problems, each saying what it means for the user.
    if rep.n_boundary_edges:
        problems.append(f"{rep.n_boundary_edges} boundary edges "
                        "(surface is not closed: it has holes)")
    if rep.n_nonmanifold_edges:
        problems.append(f"{rep.n_nonmanifold_edges} edges shared by more than 2 faces "
                        "(not edge-manifold)")
    if rep.n_nonmanifold_vertices:
        problems.append(f"{rep.n_nonmanifold_vertices} vertices whose faces do not form a "
                        "single fan (not vertex-manifold: parts of the surface touch at a "
                        "vertex)")
    if rep.n_misoriented_edges:
        problems.append(f"{rep.n_misoriented_edges} edges traversed in the same direction by both "
                        "faces (inconsistent orientation: some faces are flipped)")
    if expect_components is not None and rep.n_components != expect_components:
        problems.append(f"{rep.n_components} connected components, expected {expect_components} "
                        "(separate pieces of surface)")
    if rep.closed and rep.consistent_orientation and not rep.outward:
        problems.append(f"enclosed volume {rep.volume:.3g} mm^3 is not positive "
                        "(normals point inward)")
    if degenerate.any():
        problems.append(f"{int(degenerate.sum())} degenerate faces "
                        "(zero area or a repeated vertex)")
    if rep.n_duplicate_faces:
        problems.append(f"{rep.n_duplicate_faces} duplicate faces (same three vertices twice)")
    if rep.n_self_intersections:
        involved = int(np.count_nonzero(np.bincount(pairs.ravel())))
        problems.append(f"{rep.n_self_intersections} pairs of intersecting faces "
                        f"({involved} faces; the surface passes through itself)")
    rep.ok = not problems
    rep.seconds = time.perf_counter() - t0
    return rep


def require_valid(surface, what: str = "surface", **kw) -> SurfaceReport:
    """Check ``surface`` (anything with ``vertices`` and ``faces``) and raise if it fails.

    Raises :class:`SurfaceCheckError` whose message names ``what`` and every failed check;
    the report is attached as ``error.report``. Keyword arguments go to :func:`check_surface`.
    """
    report = check_surface(surface.vertices, surface.faces, **kw)
    if not report.ok:
        raise SurfaceCheckError(
            f"The {what} is not a valid watertight 2-manifold surface: "
            + "; ".join(report.problems) + ".", report=report)
    return report


# ---------------------------------------------------------------------------------------------
# Topology

def _count_duplicate_faces(faces: np.ndarray, n: int) -> int:
    """Faces whose vertex set already occurred (any order)."""
    if len(faces) < 2:
        return 0
    a = faces.min(axis=1)
    c = faces.max(axis=1)
    b = faces.sum(axis=1) - a - c
    if n < 2_000_000:  # n**3 fits in int64
        key = np.sort((a * n + b) * n + c)
        return int(np.count_nonzero(key[1:] == key[:-1]))
    return int(len(faces) - len(np.unique(np.stack([a, b, c], axis=1), axis=0)))


def _check_topology(rep: SurfaceReport, faces: np.ndarray, n: int) -> None:
    m = len(faces)
    if m == 0:
        return
    # Half-edges: half-edge 3f+k goes from corner 3f+k to corner 3f+(k+1)%3.
    start = faces.ravel()
    nxt = np.arange(3 * m).reshape(m, 3)[:, [1, 2, 0]].ravel()
    end = start[nxt]
    lo = np.minimum(start, end)
    hi = np.maximum(start, end)
    key = lo * n + hi
    order = np.argsort(key)
    skey = key[order]
    new = np.empty(len(skey), dtype=bool)
    new[0] = True
    new[1:] = skey[1:] != skey[:-1]
    group = np.cumsum(new) - 1
    counts = np.bincount(group)
    n_edges = len(counts)
    rep.n_boundary_edges = int((counts == 1).sum())
    rep.n_nonmanifold_edges = int((counts > 2).sum())
    rep.closed = rep.n_boundary_edges == 0
    rep.edge_manifold = rep.n_boundary_edges == 0 and rep.n_nonmanifold_edges == 0

    # Orientation: the two half-edges of a manifold edge must run in opposite directions
    # (on edges with more than two faces orientation is undefined; they are reported anyway).
    forward = np.bincount(group, weights=(start == lo)[order], minlength=n_edges)
    rep.n_misoriented_edges = int(((counts == 2) & (forward != 1)).sum())
    rep.consistent_orientation = rep.n_misoriented_edges == 0

    # Vertex fans: link the corners of one vertex in faces that share an edge through it;
    # a vertex is manifold when its corners form a single connected fan.
    corner_lo = np.where(start == lo, np.arange(3 * m), nxt)[order]
    corner_hi = np.where(start == lo, nxt, np.arange(3 * m))[order]
    same = ~new[1:]  # consecutive half-edges on the same undirected edge
    a = np.concatenate([corner_lo[:-1][same], corner_hi[:-1][same]])
    b = np.concatenate([corner_lo[1:][same], corner_hi[1:][same]])
    graph = sparse.coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(3 * m, 3 * m))
    n_fans, fan = csgraph.connected_components(graph, directed=False)
    fan_vertex = np.empty(n_fans, dtype=np.int64)
    fan_vertex[fan] = start
    fans_per_vertex = np.bincount(fan_vertex, minlength=n)
    rep.n_nonmanifold_vertices = int((fans_per_vertex > 1).sum())
    rep.vertex_manifold = rep.n_nonmanifold_vertices == 0

    # Components connected through shared vertices.
    uniq_lo = lo[order][new]
    uniq_hi = hi[order][new]
    vgraph = sparse.coo_matrix((np.ones(n_edges, dtype=np.int8), (uniq_lo, uniq_hi)), shape=(n, n))
    _, vlabel = csgraph.connected_components(vgraph, directed=False)
    face_used = np.zeros(n, dtype=bool)
    face_used[faces.ravel()] = True
    rep.n_components = int(np.count_nonzero(np.bincount(vlabel[face_used])))

    if (rep.edge_manifold and rep.vertex_manifold and rep.consistent_orientation
            and rep.n_components == 1):
        chi = int(face_used.sum()) - n_edges + m
        rep.genus = (2 - chi) // 2


# ---------------------------------------------------------------------------------------------
# Self-intersections

def find_self_intersections(vertices, faces, max_pairs: Optional[int] = None,
                            exclude: Optional[np.ndarray] = None,
                            only: Optional[np.ndarray] = None) -> np.ndarray:
    """Pairs of faces whose interiors intersect, as a (k, 2) int64 array (i < j, sorted).

    Broad phase: face bounding boxes binned into a uniform grid; each box pair is produced once
    (in the cell holding the low corner of the boxes' overlap). Narrow phase: exact vectorised
    tests that know about shared vertices and edges (see the module docstring for the policy).
    ``exclude`` (bool per face) leaves faces out, e.g. degenerate ones. ``only`` (bool per
    face): just the pairs with at least one of these faces (e.g. the faces a step moved, on a
    surface that was free of intersections before it); the others are tested only where they
    are near one of them.
    """
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    empty = np.zeros((0, 2), dtype=np.int64)
    keep = np.ones(len(faces), dtype=bool) if exclude is None else ~np.asarray(exclude, bool)
    if only is not None:
        only = np.asarray(only, bool) & keep
        if not only.any():
            return empty
        if only.sum() < NEAR_FACES_FRACTION * keep.sum():
            keep &= _near_faces(vertices, faces, only)
    face_ids = np.flatnonzero(keep)
    if len(face_ids) < 2:
        return empty
    f = faces[face_ids]
    used = np.zeros(len(vertices), dtype=bool)
    used[f.ravel()] = True
    v = vertices - vertices[used].mean(axis=0)
    # Visit faces in spatial order (coarse grid of centroids) so that the gathers of the
    # pair tests below hit memory that is close together.
    centroid = v[f].mean(axis=1)
    spread = centroid - centroid.min(axis=0)
    step = max(8.0 * float(np.linalg.norm(v[f[:, 1]] - v[f[:, 0]], axis=1).mean()),
               float(spread.max()) / 1e6, 1e-300)
    q = np.floor(spread / step).astype(np.int64)
    qd = q.max(axis=0) + 1
    spatial = np.argsort((q[:, 0] * qd[1] + q[:, 1]) * qd[2] + q[:, 2])
    face_ids = face_ids[spatial]
    f = f[spatial]
    tri = v[f]  # (m, 3 corners, 3 xyz)
    lo = tri.min(axis=1)
    hi = tri.max(axis=1)
    scale = float(np.abs(tri).max()) + float((hi - lo).max())
    dtol = _REL_DIST_TOL * max(scale, 1e-300)
    # Boxes grown by the tolerance so that no crossing pair is lost to round-off.
    lo = lo - dtol
    hi = hi + dtol

    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nlen = np.linalg.norm(normal, axis=1)
    unit = normal / np.maximum(nlen, 1e-300)[:, None]

    ctx = {
        "fc": [np.ascontiguousarray(f[:, a]) for a in range(3)],
        "corner": [[np.ascontiguousarray(tri[:, c, k]) for k in range(3)] for c in range(3)],
        "normal": [np.ascontiguousarray(unit[:, k]) for k in range(3)],
        "offset": np.einsum("ij,ij->i", unit, tri[:, 0]),
        "nlen": nlen,
        "tri": tri, "tri_flat": tri.reshape(-1, 3), "unit": unit, "dtol": dtol,
        "size": float((hi - lo).max()),
    }
    found = []
    total = 0
    # The narrow phase of the next batches on threads (numpy's loops release the GIL).
    tested = map_ahead(lambda ij: (*ij, _narrow_phase(ctx, *ij)), _candidate_pairs(lo, hi),
                       cpu_threads(CHECK_THREADS), "checks")
    for i, j, hit in tested:
        if hit.any():
            found.append(np.stack([i[hit], j[hit]], axis=1))
            total += int(hit.sum())
            if max_pairs is not None and total >= max_pairs:
                break
    if not found:
        return empty
    pairs = face_ids[np.concatenate(found)]
    if only is not None:
        pairs = pairs[only[pairs[:, 0]] | only[pairs[:, 1]]]
        if not len(pairs):
            return empty
    pairs = np.sort(pairs, axis=1)
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
    if max_pairs is not None:
        pairs = pairs[:max_pairs]
    return pairs


# Threads testing batches of candidate pairs at once.
CHECK_THREADS = 2


# find_self_intersections(only=...) prunes the faces far from ``only`` when these are fewer
# than this fraction of the faces (beyond it the pruning costs more than it saves).
NEAR_FACES_FRACTION = 0.25


def _near_faces(vertices: np.ndarray, faces: np.ndarray, only: np.ndarray) -> np.ndarray:
    """Bool per face: its bounding box may meet the box of a face of ``only`` (a centroid
    lies in its box, so two boxes that meet have centroids at most their two diagonals
    apart: on cells of that size, in the same or a neighbouring cell)."""
    tri = vertices[faces]
    centroid = tri.mean(axis=1)
    diag = np.linalg.norm(tri.max(axis=1) - tri.min(axis=1), axis=1)
    reach = 2.0 * float(diag.max()) * (1.0 + 1e-6) + 1e-9 * (1.0 + float(np.abs(tri).max()))
    cell = np.floor((centroid - centroid.min(axis=0)) / reach).astype(np.int64)
    dims = cell.max(axis=0) + 3  # a cell of margin on each side
    cell += 1
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    marked = np.unique(key[only])
    offsets = np.array([(a * dims[1] + b) * dims[2] + c
                        for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)])
    marked = np.unique((marked[:, None] + offsets[None, :]).ravel())
    return np.isin(key, marked) | only


def _candidate_pairs(lo: np.ndarray, hi: np.ndarray):
    """Yield batches (i, j) of face pairs whose boxes overlap, each pair exactly once."""
    m = len(lo)
    extent = hi - lo
    # A cell about the size of a typical face keeps cells sparse on a uniform mesh; very large
    # faces would cover many cells, so grow the cell until the cell list stays linear in m.
    cell = 1.5 * float(np.median(extent.max(axis=1)))
    origin = lo.min(axis=0)
    # Keep the grid below 2e6 cells per axis so that cell keys fit in int64.
    cell = max(cell, float(extent.max()) * 1e-6, float((hi.max(axis=0) - origin).max()) / 2e6,
               1e-300)
    for _ in range(60):
        clo = np.floor((lo - origin) / cell).astype(np.int64)
        chi = np.floor((hi - origin) / cell).astype(np.int64)
        span = chi - clo + 1
        count = span.prod(axis=1)
        if count.sum() <= 12 * m + 10000:
            break
        cell *= 1.5
    total = int(count.sum())
    owner = np.repeat(np.arange(m), count)
    local = np.arange(total) - np.repeat(np.cumsum(count) - count, count)
    sx = span[owner, 0]
    sy = span[owner, 1]
    lx = local % sx
    ly = (local // sx) % sy
    lz = local // (sx * sy)
    dims = chi.max(axis=0) + 1
    cell_key = (((clo[owner, 0] + lx) * dims[1] + clo[owner, 1] + ly) * dims[2]
                + clo[owner, 2] + lz)
    # Bit per axis: is this the face's first cell along that axis? A pair met in a cell is
    # kept only there where the cell is the low corner of the overlap of the two boxes, i.e.
    # along every axis the cell is the first cell of at least one of the two faces.
    low_corner = ((lx == 0) | ((ly == 0) << 1) | ((lz == 0) << 2)).astype(np.uint8)
    order = np.argsort(cell_key)
    cell_key = cell_key[order]
    owner = owner[order]
    low_corner = low_corner[order]
    # Entry p pairs with every later entry of its cell: group_end[p] - p - 1 partners.
    boundary = np.flatnonzero(cell_key[1:] != cell_key[:-1]) + 1
    ends = np.append(boundary, total)
    group_end = np.repeat(ends, np.diff(np.concatenate([[0], ends])))
    n_partners = group_end - np.arange(total) - 1
    cum = np.cumsum(n_partners)
    lo_t = [np.ascontiguousarray(lo[:, k]) for k in range(3)]
    hi_t = [np.ascontiguousarray(hi[:, k]) for k in range(3)]
    done = 0
    p0 = 0
    while p0 < total:
        # Entries [p0, p1) produce about _PAIR_BATCH pairs.
        p1 = int(np.searchsorted(cum, done + _PAIR_BATCH, side="right"))
        p1 = min(max(p1, p0 + 1), total)
        k = n_partners[p0:p1]
        n_pairs = int(k.sum())
        done = int(cum[p1 - 1])
        if n_pairs:
            first = np.repeat(np.arange(p0, p1), k)
            second = first + 1 + (np.arange(n_pairs) - np.repeat(np.cumsum(k) - k, k))
            keep = (low_corner[first] | low_corner[second]) == 7
            a = owner[first[keep]]
            b = owner[second[keep]]
            # Box overlap axis by axis on 1-D arrays (much faster than (k, 3) rows).
            for ax in range(3):
                ok = (lo_t[ax][a] <= hi_t[ax][b]) & (lo_t[ax][b] <= hi_t[ax][a])
                a = a[ok]
                b = b[ok]
            if len(a):
                yield a, b
        p0 = p1


def _narrow_phase(ctx, i, j):
    """Bool per candidate pair (i, j): do the two faces intersect (see policy)?"""
    fc, corner, normal, offset, dtol = (ctx["fc"], ctx["corner"], ctx["normal"], ctx["offset"],
                                        ctx["dtol"])
    # Shared corners, on 1-D index columns (cheap).
    fi = [fc[a][i] for a in range(3)]
    fj = [fc[b][j] for b in range(3)]
    n_shared = sum((fi[a] == fj[b]).astype(np.int8) for a in range(3) for b in range(3))

    # Signed distances of each triangle's corners to the other's plane. Most candidates are
    # neighbours on a smooth surface and are dismissed here without building any geometry.
    def dist(corner_of, plane_of):
        nx, ny, nz = (normal[k][plane_of] for k in range(3))
        off = offset[plane_of]
        return [nx * corner[c][0][corner_of] + ny * corner[c][1][corner_of]
                + nz * corner[c][2][corner_of] - off for c in range(3)]

    dQ = dist(j, i)  # corners of j against the plane of i
    dP = dist(i, j)
    pos_q = (dQ[0] > dtol) | (dQ[1] > dtol) | (dQ[2] > dtol)
    neg_q = (dQ[0] < -dtol) | (dQ[1] < -dtol) | (dQ[2] < -dtol)
    pos_p = (dP[0] > dtol) | (dP[1] > dtol) | (dP[2] > dtol)
    neg_p = (dP[0] < -dtol) | (dP[1] < -dtol) | (dP[2] < -dtol)
    straddle_q = pos_q & neg_q
    straddle_p = pos_p & neg_p
    flat_q = ~(pos_q | neg_q)  # j lies in the plane of i
    flat = flat_q | ~(pos_p | neg_p)
    hit = np.zeros(len(i), dtype=bool)

    # Transversal crossings (at most one shared vertex, not coplanar): the intersection
    # segment ends where an edge of one triangle crosses the interior of the other. Edges
    # through a shared vertex have an endpoint on the other plane and never qualify, so the
    # same test finds where the edge opposite a shared vertex pierces the other face.
    cross = np.flatnonzero(~flat & np.where(n_shared == 0, straddle_q & straddle_p,
                                            (n_shared == 1) & (straddle_q | straddle_p)))
    if len(cross):
        ci, cj = i[cross], j[cross]
        dq = [d[cross] for d in dQ]
        dp = [d[cross] for d in dP]
        h = np.zeros(len(cross), dtype=bool)
        for a in range(3):
            b = (a + 1) % 3
            h |= _edge_crosses_face(ctx, ci, a, b, dp[a], dp[b], cj, ~h)
            h |= _edge_crosses_face(ctx, cj, a, b, dq[a], dq[b], ci, ~h)
        # Faces that cross only through their edges (every end of the intersection segment
        # on an edge of both, as in mirror-symmetric meshes): their intervals on the line
        # where the planes meet overlap with positive length.
        rest = ~h & (n_shared[cross] == 0)
        if rest.any():
            h[rest] = _intervals_overlap(ctx, ci[rest], cj[rest], [d[rest] for d in dp],
                                         [d[rest] for d in dq])
        hit[cross] = h

    tri, unit = ctx["tri"], ctx["unit"]
    # Coplanar pairs with at most one common vertex: overlap of positive area.
    sel = np.flatnonzero(flat & (n_shared <= 1))
    if len(sel):
        ii, jj = i[sel], j[sel]
        # Work in the plane the other face lies in (matters when one face is tiny).
        plane = np.where(flat_q[sel][:, None], unit[ii], unit[jj])
        hit[sel] = _coplanar_overlap(tri[ii], tri[jj], plane, dtol)

    # Pairs sharing an edge: folded onto each other? The far corner must lie (almost) in the
    # other face's plane, within _ANGLE_TOL * size.
    fold_tol = max(dtol, _ANGLE_TOL * ctx["size"])
    near_q = np.maximum(np.maximum(np.abs(dQ[0]), np.abs(dQ[1])), np.abs(dQ[2])) <= fold_tol
    sel = np.flatnonzero((n_shared == 2) & near_q)
    if len(sel):
        fi_s = [x[sel] for x in fi]
        fj_s = [x[sel] for x in fj]
        # The unshared corner of each face: the one equal to none of the other's corners.
        cut_i = np.zeros(len(sel), dtype=np.int64)
        cut_j = np.zeros(len(sel), dtype=np.int64)
        for a in range(3):
            cut_i[(fi_s[a] != fj_s[0]) & (fi_s[a] != fj_s[1]) & (fi_s[a] != fj_s[2])] = a
            cut_j[(fj_s[a] != fi_s[0]) & (fj_s[a] != fi_s[1]) & (fj_s[a] != fi_s[2])] = a
        hit[sel] = _edge_sharing_pairs(ctx["tri_flat"], i[sel], j[sel], cut_i, cut_j,
                                       unit[i[sel]], dtol)
    # Three shared vertices: a duplicate face, counted with the degenerate faces.
    return hit


def _edge_crosses_face(ctx, f_edge, a, b, da, db, f_tri, todo):
    """Does edge (corner a -> corner b) of faces f_edge cross the interior of faces f_tri?

    ``da``, ``db``: signed distances of the edge's ends to the plane of f_tri. Only pairs where
    ``todo`` holds and the ends lie strictly on opposite sides are computed.
    """
    dtol = ctx["dtol"]
    out = np.zeros(len(f_edge), dtype=bool)
    idx = np.flatnonzero(todo & (((da > dtol) & (db < -dtol)) | ((da < -dtol) & (db > dtol))))
    if not len(idx):
        return out
    corner = ctx["corner"]
    fe, ft = f_edge[idx], f_tri[idx]
    t = da[idx] / (da[idx] - db[idx])
    x = [corner[a][k][fe] + (corner[b][k][fe] - corner[a][k][fe]) * t for k in range(3)]
    n = [ctx["normal"][k][ft] for k in range(3)]
    twice_area = ctx["nlen"][ft]
    # Barycentric coordinate of x for corner c: area of (x, c+1, c+2) over the face's area.
    inside = np.ones(len(idx), dtype=bool)
    for c in range(3):
        p = [corner[(c + 1) % 3][k][ft] - x[k] for k in range(3)]
        q = [corner[(c + 2) % 3][k][ft] - x[k] for k in range(3)]
        bary = ((p[1] * q[2] - p[2] * q[1]) * n[0] + (p[2] * q[0] - p[0] * q[2]) * n[1]
                + (p[0] * q[1] - p[1] * q[0]) * n[2]) / twice_area
        inside &= bary > _BARY_TOL
    out[idx] = inside
    return out


def _intervals_overlap(ctx, fi, fj, dp, dq):
    """Do non-coplanar faces fi and fj, each straddling the other's plane, share a segment of
    positive length? (The intervals they cut on the line where their planes meet overlap.)

    ``dp``: distances of fi's corners to fj's plane; ``dq``: fj's corners to fi's plane."""
    dtol = ctx["dtol"]
    unit = ctx["unit"]
    line = np.cross(unit[fi], unit[fj])
    line /= np.maximum(np.linalg.norm(line, axis=1, keepdims=True), 1e-300)
    tri = ctx["tri"]

    def interval(faces, dist):
        proj = [np.einsum("ij,ij->i", tri[faces, c], line) for c in range(3)]
        lo = np.full(len(faces), np.inf)
        hi = np.full(len(faces), -np.inf)
        for a in range(3):
            on = np.abs(dist[a]) <= dtol
            lo = np.where(on, np.minimum(lo, proj[a]), lo)
            hi = np.where(on, np.maximum(hi, proj[a]), hi)
            b = (a + 1) % 3
            cut = ((dist[a] > dtol) & (dist[b] < -dtol)) | ((dist[a] < -dtol) & (dist[b] > dtol))
            with np.errstate(divide="ignore", invalid="ignore"):
                t = dist[a] / (dist[a] - dist[b])
            x = proj[a] + (proj[b] - proj[a]) * t
            lo = np.where(cut, np.minimum(lo, x), lo)
            hi = np.where(cut, np.maximum(hi, x), hi)
        return lo, hi

    lo_p, hi_p = interval(fi, dp)
    lo_q, hi_q = interval(fj, dq)
    overlap = np.minimum(hi_p, hi_q) - np.maximum(lo_p, lo_q)
    return overlap > max(dtol, _BARY_TOL * ctx["size"])


def _coplanar_overlap(P, Q, n, dtol):
    """Positive-area overlap of coplanar triangles (separating-axis test in their plane).

    Two convex polygons have disjoint interiors exactly when the line through one of their
    edges separates them; "touching" (within dtol of the line) counts as separated, which also
    makes two faces side by side around a shared vertex separated.
    """
    alive = np.arange(len(P))  # pairs not yet separated; most go at the first edges
    for first in (True, False):
        for a in range(3):
            A, B = (P[alive], Q[alive]) if first else (Q[alive], P[alive])
            p = A[:, a]
            m = np.cross(n[alive], A[:, (a + 1) % 3] - p)  # in-plane normal of the edge
            m /= np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-300)
            m *= np.sign(np.einsum("ij,ij->i", m, A[:, (a + 2) % 3] - p))[:, None]
            separated = np.einsum("kij,kj->ki", B - p[:, None], m).max(axis=1) <= dtol
            alive = alive[~separated]
    out = np.zeros(len(P), dtype=bool)
    out[alive] = True
    return out


def _edge_sharing_pairs(tri_flat, ii, jj, cut_i, cut_j, nP, dtol):
    """Faces ii = (a, b, c) and jj = (b, a, d) sharing edge ab: folded onto each other?

    ``cut_i``, ``cut_j``: index of the unshared corner (c, d) in each face.
    """
    c = tri_flat[3 * ii + cut_i]
    a = tri_flat[3 * ii + (cut_i + 1) % 3]
    b = tri_flat[3 * ii + (cut_i + 2) % 3]
    d = tri_flat[3 * jj + cut_j]
    perp = np.cross(nP, b - a)
    perp /= np.maximum(np.linalg.norm(perp, axis=1, keepdims=True), 1e-300)
    side_c = np.sign(np.einsum("ij,ij->i", c - a, perp))
    w = np.einsum("ij,ij->i", d - a, perp) * side_c  # > 0: d on c's side of the edge
    h = np.abs(np.einsum("ij,ij->i", d - a, nP))    # height of d over the plane of ii
    return (w > dtol) & (h <= np.maximum(dtol, _ANGLE_TOL * w))
