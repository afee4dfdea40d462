"""Stage 6: iterative Laplacian deformation of M0 onto the constraint points (paper §2.4, §3.3).

Energy (5): E = E_prox + alpha E_deformation + beta E_sharpness. Setting its gradient to zero gives
eq. (15); we keep the control weights in the proximity term (free vertices have no match, so
they must not be pulled):

    (W + alpha (L^T L + Omega^2) + beta I) V = W psi + alpha (L^T L V* + Omega^2 (V* + C)) + beta V*

with L = I - D^-1 A (uniform weights, eq. (11)), V* the previous iterate, W = Omega = diag(omega),
omega_i in {0, 1}, psi(v_i) the match found by the directional search and
c_i = (psi(v_i) - v_i) / (N - j + 1) (eq. (16)). The matrix is symmetric positive definite
(beta > 0), so each iteration is three conjugate-gradient solves, warm-started from the previous
iterate and preconditioned by the diagonal: omega changes every iteration, which rules out reusing
a factorisation, and warm-started CG converges in a few dozen products.

Directional search (§3.3): a vertex inside the bone searches a ball of radius r around
v + n delta (outward), a vertex outside around v - n delta (inward); the match is the point of
B* in that ball closest to v. alpha and beta halve when the mean step stalls. A step that flips
any triangle is redone with a doubled beta; if that fails, the previous iterate is kept.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy import ndimage
from scipy.sparse.linalg import cg
from scipy.spatial import cKDTree

from .checks import find_self_intersections
from .mesh import face_normals, vertex_normals
from .params import Parameters


def laplacian(n: int, faces: np.ndarray) -> sp.csr_matrix:
    """Uniform Laplacian L = I - D^-1 A of the mesh graph (eq. (11))."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.sort(e, axis=1)
    e = np.unique(e, axis=0)
    rows = np.concatenate([e[:, 0], e[:, 1]])
    cols = np.concatenate([e[:, 1], e[:, 0]])
    adj = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    deg = np.asarray(adj.sum(axis=1)).ravel()
    dinv = sp.diags(1.0 / np.maximum(deg, 1))
    return (sp.identity(n, format="csr") - dinv @ adj).tocsr()


def ring_mean(avg: sp.csr_matrix, values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted mean of ``values`` over each vertex's 1-ring (``avg`` = D^-1 A); 0 where no
    neighbour has weight."""
    cnt = avg @ weights
    return np.where(cnt > 0, (avg @ (weights * values)) / np.maximum(cnt, 1e-12), 0.0)


def sample_field(field_zyx: np.ndarray, points_grid_mm: np.ndarray, spacing: float, order: int = 1,
                 cval: float = 0.0) -> np.ndarray:
    coords = (points_grid_mm[:, ::-1] / spacing).T
    return ndimage.map_coordinates(field_zyx, coords, order=order, mode="constant", cval=cval)


def safe_update(old: np.ndarray, new: np.ndarray, faces: np.ndarray, rounds: int = 8,
                intersections: bool = True):
    """Local back-off: vertices of triangles that a step would flip (or, with ``intersections``,
    make intersect) keep their old position. ``old`` must be free of both.
    Returns (vertices, ok, number of bad faces)."""
    new = new.copy()
    fn_before = face_normals(old, faces)
    bad_faces = 0
    for _ in range(rounds):
        bad = np.einsum("ij,ij->i", fn_before, face_normals(new, faces)) < 0.0
        if not bad.any():
            if not intersections:
                return new, True, 0
            pairs = find_self_intersections(new, faces)
            if len(pairs) == 0:
                return new, True, 0
            bad[np.unique(pairs)] = True
        bad_faces = int(bad.sum())
        idx = np.unique(faces[bad])
        new[idx] = old[idx]
    return new, False, bad_faces


def solve_spd(A, rhs, x0):
    """Three CG solves (one per coordinate), Jacobi-preconditioned, warm-started."""
    precond = sp.diags(1.0 / A.diagonal())
    out = np.empty_like(x0)
    for c in range(3):
        out[:, c], _ = cg(A, rhs[:, c], x0=x0[:, c], rtol=1e-7, maxiter=500, M=precond)
    return out


class Deformer:
    def __init__(self, vertices, faces, constraints, inside, params: Parameters, edge_length: float):
        """``inside(points) -> bool array``: whether points lie inside the target bone (decides
        the search direction)."""
        self.v = np.array(vertices, dtype=np.float64)
        self.f = np.asarray(faces)
        self.tree = cKDTree(constraints)
        self.constraints = constraints
        self.inside = inside
        self.p = params
        self.d = edge_length
        n = len(self.v)
        L = laplacian(n, self.f)
        self.LtL = (L.T @ L).tocsr()
        self.avg = (sp.identity(n, format="csr") - L).tocsr()  # D^-1 A: 1-ring mean
        self.history = []

    def match(self, v, normals):
        inside = self.inside(v)
        delta = self.p.search_offset * self.d
        radius = self.p.search_radius * self.d
        centre = v + np.where(inside[:, None], 1.0, -1.0) * normals * delta
        # psi = of the constraint points within the search ball, the one nearest to v (eq. (7)
        # restricted to the directional search area). Measured on the phantoms: taking the one
        # nearest to v_c instead pushes the surface ~0.3 mm outward.
        k = 8
        dist, idx = self.tree.query(centre, k=k, distance_upper_bound=radius, workers=-1)
        valid = np.isfinite(dist)
        cand = self.constraints[np.where(valid, idx, 0)]  # (n, k, 3)
        dv = np.linalg.norm(cand - v[:, None, :], axis=2)
        dv[~valid] = np.inf
        best = np.argmin(dv, axis=1)
        rows = np.arange(len(v))
        matched = np.isfinite(dv[rows, best])
        psi = cand[rows, best]
        # Keep only the normal component of the match: neighbouring vertices matched to the same
        # voxel point would otherwise slide together and fold the triangles between them.
        along = np.einsum("ij,ij->i", psi - v, normals)
        # Noise points of B* (B_N in the paper) show up as matches far from the neighbours':
        # a vertex whose step differs from its 1-ring mean by more than half an edge is left
        # free this iteration, so it cannot grow a spike.
        nb = ring_mean(self.avg, along, matched.astype(np.float64))
        matched &= np.abs(along - nb) <= 0.5 * self.d
        psi = v + along[:, None] * normals
        psi[~matched] = v[~matched]
        return psi, matched, inside

    def solve(self, rhs, diag_extra, alpha, beta, x0):
        n = len(x0)
        A = (alpha * self.LtL + sp.diags(diag_extra + beta)).tocsr()
        return solve_spd(A, rhs, x0)

    def step(self, j, total, alpha, beta, full_check=True):
        v = self.v
        normals = vertex_normals(v, self.f)
        psi, matched, inside = self.match(v, normals)
        w = matched.astype(np.float64)
        c = (psi - v) / float(max(total - j + 1, 1))
        c[~matched] = 0.0
        lap_rhs = self.LtL @ v
        rhs = w[:, None] * psi + alpha * (lap_rhs + w[:, None] * (v + c)) + beta * v
        diag_extra = w + alpha * w
        for attempt in range(3):
            new = self.solve(rhs, diag_extra, alpha, beta, v)
            new, ok, bad = safe_update(v, new, self.f, intersections=False)
            if ok and full_check:
                # The exact self-intersection test costs ~1 s per 150k faces, so it runs every
                # few iterations against the last verified iterate (see run()).
                new, ok, bad = safe_update(self.clean_v, new, self.f)
                if ok:
                    self.clean_v = new
            if ok:
                return new, matched, 0
            # Global back-off: a stiffer step (more weight on the previous iterate).
            rhs = rhs + beta * v
            beta = beta * 2.0
        return None, matched, bad

    def run(self, progress=None):
        p = self.p
        alpha, beta = p.alpha, p.beta
        total = p.iterations
        self.clean_v = self.v.copy()
        extra = 0
        j = 1
        while j <= total + extra:
            last = j >= total + extra
            new, matched, flipped = self.step(min(j, total), total, alpha, beta,
                                              full_check=last or j % 3 == 0)
            if new is None:
                self.history.append({"iteration": j, "rejected": True, "flipped": flipped})
                break
            move = np.linalg.norm(new - self.v, axis=1)
            self.v = new
            rec = {"iteration": j, "alpha": alpha, "beta": beta, "matched": int(matched.sum()),
                   "mean_move": float(move.mean()), "max_move": float(move.max())}
            self.history.append(rec)
            if progress:
                progress(min(j / max(total, 1), 1.0), f"deformation {j}/{total}")
            # Paper: when two iterations barely differ, lower alpha and beta so the proximity
            # term dominates and local detail comes out.
            if move.mean() < 0.05 * self.d:
                alpha = max(alpha * 0.5, 0.2 * p.alpha)
                beta = max(beta * 0.5, 0.2 * p.beta)
            # Still moving after N iterations: a few more full steps (c = psi - v), at most 4.
            if j == total + extra and move.mean() > 0.05 * self.d and extra < 4:
                extra += 1
            j += 1
        if not np.array_equal(self.clean_v, self.v):
            self.v, ok, _ = safe_update(self.clean_v, self.v, self.f)
            if not ok:
                self.v = self.clean_v
        return self.v
