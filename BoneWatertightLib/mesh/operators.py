"""Mesh operators shared by the stages: normals, the uniform Laplacian, ring means, the SPD
solver, the flip/intersection back-off, field sampling and tangential relaxation.

Conventions: ``vertices`` are (n, 3) float64 x-y-z points in millimetres (grid millimetres
inside the pipeline, i.e. voxel index * spacing in x-y-z order); ``faces`` are (m, 3) int64
vertex indices, counter-clockwise seen from outside. Volumes sampled by :func:`sample_field`
are (z, y, x) numpy arrays on an isotropic grid of the given spacing whose voxel (0, 0, 0) is
at grid millimetre (0, 0, 0).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy import ndimage

from ..threads import cpu_threads, thread_map
from .checks import find_self_intersections

# Conjugate-gradient tolerance (relative residual) and iteration cap of solve_spd.
CG_RTOL = 1e-7
CG_MAX_ITERATIONS = 500
# Rounds of the local back-off in safe_update before it gives up.
BACKOFF_ROUNDS = 8
# Then up to this many rounds that also put back the 1-ring around the bad triangles' vertices
# (each round one ring more): reverting a vertex can make its moved neighbours cross instead,
# and on real CT that cascade outlasted the plain rounds, so a whole refinement was discarded
# for 15 faces.
BACKOFF_GROW_ROUNDS = 8
# Tangential relaxation of a fresh contour: iterations and step weight.
RELAX_ITERATIONS = 5
RELAX_WEIGHT = 0.5
# sample_field interpolates this many points at a time (the grid coordinates of a chunk take
# 24 bytes a point: 2.7 M profile samples at once took 190 MB), on up to SAMPLE_THREADS threads
# (map_coordinates releases the GIL: 0.55 -> 0.32 s for 2.7 M points on 2 CPUs).
SAMPLE_CHUNK = 1 << 19
SAMPLE_THREADS = 2


def face_normals(vertices: np.ndarray, faces: np.ndarray, normalize: bool = True) -> np.ndarray:
    """Face normals (m, 3); unit length, or twice the triangle area when ``normalize`` is False.

    Parameters
    ----------
    vertices : (n, 3) float64 array
    faces : (m, 3) int array
    normalize : bool
    """
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    n = np.cross(v1 - v0, v2 - v0)
    if normalize:
        length = np.linalg.norm(n, axis=1, keepdims=True)
        n = n / np.maximum(length, 1e-300)
    return n


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals, (n, 3) float64, outward for an outward surface."""
    fn = face_normals(vertices, faces, normalize=False)
    corners = np.asarray(faces).ravel()
    vn = np.empty_like(vertices)
    for c in range(3):  # bincount sums far faster than np.add.at
        vn[:, c] = np.bincount(corners, weights=np.repeat(fn[:, c], 3), minlength=len(vertices))
    length = np.linalg.norm(vn, axis=1, keepdims=True)
    return vn / np.maximum(length, 1e-300)


def laplacian(n: int, faces: np.ndarray) -> sp.csr_matrix:
    """Uniform Laplacian L = I - D^-1 A of the mesh graph (paper eq. (11)).

    Parameters
    ----------
    n : int
        Number of vertices.
    faces : (m, 3) int array

    Returns
    -------
    (n, n) scipy.sparse.csr_matrix
        ``L @ v`` is each vertex minus the mean of its 1-ring.
    """
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.sort(e, axis=1).astype(np.int64)
    # Unique edges through one int64 key per edge (np.unique on rows is several times slower).
    key = np.unique(e[:, 0] * n + e[:, 1])
    e = np.stack([key // n, key % n], axis=1)
    rows = np.concatenate([e[:, 0], e[:, 1]])
    cols = np.concatenate([e[:, 1], e[:, 0]])
    adj = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    deg = np.asarray(adj.sum(axis=1)).ravel()
    dinv = sp.diags(1.0 / np.maximum(deg, 1))
    return (sp.identity(n, format="csr") - dinv @ adj).tocsr()


def vertex_components(n: int, faces: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
    """Connected-component index of each of the ``n`` vertices, joined along the faces' edges
    ((n,) int); with ``keep`` ((n,) bool), only along edges whose two ends are kept (a vertex
    not kept is a component of its own)."""
    from scipy.sparse.csgraph import connected_components

    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    if keep is not None:
        edges = edges[keep[edges[:, 0]] & keep[edges[:, 1]]]
    graph = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def ring_mean(avg: sp.csr_matrix, values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted mean of ``values`` over each vertex's 1-ring; 0 where no neighbour has weight.

    Parameters
    ----------
    avg : (n, n) sparse matrix
        D^-1 A, the 1-ring averaging operator (``I - laplacian(n, faces)``).
    values, weights : (n,) float arrays
    """
    cnt = avg @ weights
    return np.where(cnt > 0, (avg @ (weights * values)) / np.maximum(cnt, 1e-12), 0.0)


def sample_field(field_zyx: np.ndarray, points_grid_mm: np.ndarray, spacing: float, order: int = 1,
                 cval: float = 0.0) -> np.ndarray:
    """Interpolate a volume at points.

    Parameters
    ----------
    field_zyx : (z, y, x) array
        Values on a grid of step ``spacing`` mm.
    points_grid_mm : (k, 3) float array
        x-y-z points in grid millimetres (voxel index * spacing).
    spacing : float or (x, y, z) floats
        Voxel size in mm (or per axis).
    order : int
        Spline order of :func:`scipy.ndimage.map_coordinates` (1 = trilinear).
    cval : float
        Value outside the grid.

    Returns
    -------
    (k,) array of the field's dtype
    """
    points_grid_mm = np.asarray(points_grid_mm)
    if not np.isscalar(spacing):
        spacing = np.asarray(spacing, dtype=np.float64)
    # In chunks for order 1 only: a higher order prefilters the whole field at every call.
    chunk = SAMPLE_CHUNK if order <= 1 else max(len(points_grid_mm), 1)

    def sample(start):
        coords = (points_grid_mm[start:start + chunk] / spacing)[:, ::-1].T
        return ndimage.map_coordinates(field_zyx, coords, order=order, mode="constant",
                                       cval=cval)

    starts = range(0, len(points_grid_mm), chunk)
    if len(starts) <= 1:
        return sample(0)
    return np.concatenate(thread_map(sample, starts, cpu_threads(SAMPLE_THREADS)))


def safe_update(old: np.ndarray, new: np.ndarray, faces: np.ndarray, rounds: int = BACKOFF_ROUNDS,
                intersections: bool = True, halvings: int = 0):
    """Local back-off: vertices of triangles that a step would flip (or, with ``intersections``,
    make intersect) keep their old position. ``old`` must be free of both.

    Parameters
    ----------
    old, new : (n, 3) float64 arrays
        Vertices before and after the step.
    faces : (m, 3) int array
    rounds : int
        Back-off rounds before giving up.
    intersections : bool
        Also run the exact self-intersection test (slower).
    halvings : int
        The first ``halvings`` rounds move those vertices half-way back instead of all the way:
        a sliver triangle that a step flips is often fine with part of the step, and a vertex
        put all the way back while its neighbours moved stands out of the surface as a spike.

    Returns
    -------
    vertices : (n, 3) float64 array
    ok : bool
        True when the returned vertices are free of flips (and intersections).
    bad_faces : int
        Faces still bad when giving up (0 when ``ok``).
    """
    new = new.copy()
    # Only faces with a moved vertex can flip (the back-off only shrinks that set).
    sub = np.flatnonzero(np.any(new != old, axis=1)[faces].any(axis=1))
    fn_before = face_normals(old, faces[sub])
    bad_faces = 0
    ring = 0
    # Vertices whose faces the exact test has not seen where they are now. ``old`` is free of
    # intersections, so only faces that moved can make one; after a test, every pair it did
    # not report is clean, and a pair can only start crossing when one of its faces moves
    # again (is put back): the next test needs just the faces of the vertices put back since.
    unseen = np.any(new != old, axis=1)
    for r in range(halvings + rounds + BACKOFF_GROW_ROUNDS):
        bad = np.zeros(len(faces), bool)
        bad[sub] = np.einsum("ij,ij->i", fn_before, face_normals(new, faces[sub])) < 0.0
        if not bad.any():
            if not intersections:
                return new, True, 0
            pairs = find_self_intersections(new, faces, only=unseen[faces].any(axis=1))
            if len(pairs) == 0:
                return new, True, 0
            unseen[:] = False
            bad[np.unique(pairs)] = True
        bad_faces = int(bad.sum())
        back = np.zeros(len(new), bool)
        back[faces[bad]] = True
        if r >= halvings + rounds:
            ring += 1
            for _ in range(ring):
                back[faces[back[faces].any(axis=1)]] = True
        unseen |= back & np.any(new != old, axis=1)
        new[back] = 0.5 * (old[back] + new[back]) if r < halvings else old[back]
    return new, False, bad_faces


def solve_spd(A, rhs: np.ndarray, x0: np.ndarray, fallbacks=None,
              stage: str = "solver") -> np.ndarray:
    """Solve A X = rhs for a symmetric positive definite A: Jacobi-preconditioned conjugate
    gradients, warm-started from ``x0``, the three columns iterated together.

    Each column follows its own CG recurrence and stops on its own when its residual falls
    below CG_RTOL x its right-hand side's norm (as three separate solves would); iterating them
    together turns three sparse products per step into one with three columns and shares the
    interpreter's work per step (the femur's solves: 1.32 s one column at a time, 0.34 s
    together).

    Parameters
    ----------
    A : (n, n) sparse matrix, symmetric positive definite
    rhs, x0 : (n, 3) float64 arrays
    fallbacks : BoneWatertightLib.report.FallbackLog, optional
        Notes each column that stopped short of CG_RTOL after CG_MAX_ITERATIONS steps (its last
        iterate is used), under ``stage``.

    Returns
    -------
    (n, 3) float64 array
    """
    A = sp.csr_matrix(A)
    inv_diag = (1.0 / A.diagonal())[:, None]
    b = np.asarray(rhs, dtype=np.float64)
    x = np.array(x0, dtype=np.float64, copy=True)
    tol = CG_RTOL * np.linalg.norm(b, axis=0)
    # A zero right-hand side has the solution zero (CG's relative test could never pass).
    x[:, tol == 0] = 0.0
    r = b - A @ x
    p = None
    rho_prev = None
    active = (np.linalg.norm(r, axis=0) >= tol) & (tol > 0)
    for _ in range(CG_MAX_ITERATIONS):
        if not active.any():
            break
        z = r * inv_diag
        rho = np.einsum("ij,ij->j", r, z)
        if p is None:
            p = z
        else:
            beta = np.where(active, rho / np.where(active, rho_prev, 1.0), 0.0)
            p = z + beta * p
        q = A @ p
        pq = np.einsum("ij,ij->j", p, q)
        # A column that has converged keeps its iterate: its step is zero.
        alpha = np.where(active, rho / np.where(active, pq, 1.0), 0.0)
        x += alpha * p
        r -= alpha * q
        rho_prev = rho
        active &= np.linalg.norm(r, axis=0) >= tol
    short = int(active.sum())
    if short and fallbacks is not None:
        fallbacks.add(stage, f"conjugate gradient stopped short of its tolerance {CG_RTOL:g} "
                      f"(at most {CG_MAX_ITERATIONS} iterations): its last iterate was used",
                      short, "solves")
    return x


def tangential_relax(vertices: np.ndarray, faces: np.ndarray, iterations: int = RELAX_ITERATIONS,
                     weight: float = RELAX_WEIGHT) -> np.ndarray:
    """Even out marching-cubes slivers: move each vertex toward its neighbours' centroid within
    its tangent plane, so the shape stays and the triangles become near-equilateral.

    Parameters
    ----------
    vertices : (n, 3) float64 array
    faces : (m, 3) int array
    iterations : int
    weight : float
        Fraction of the tangential step taken per iteration.

    Returns
    -------
    (n, 3) float64 array
    """
    L = laplacian(len(vertices), faces)
    v = vertices.copy()
    for _ in range(iterations):
        n = vertex_normals(v, faces)
        u = -(L @ v)  # centroid of the 1-ring minus v
        u -= np.einsum("ij,ij->i", u, n)[:, None] * n
        v += weight * u
    return v
