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

Directional search (§3.3, eq. (7)): a vertex inside the bone searches a ball of radius r around
v_c = v + n delta (outward), a vertex outside around v_c = v - n delta (inward), with
delta in [0.5, 1] d* and r in [1, sqrt(3)] d* (the paper's ranges); the match psi is the point
of B* in that ball nearest to v_c. (Nearest to v instead would pin M0: with r > delta the ball
holds v itself, and B* holds S(P_H0), the points M0 was fitted to.)

Control weights (§2.4): omega_i = 1 for matched vertices; a vertex that has become stationary
(moved less than STATIONARY_MOVE d*) gets omega = 1 too (psi = its match, or itself), and at the
stable stage - when progress stalls and alpha, beta are lowered - every vertex does. alpha and
beta halve when the mean step stalls. A step that flips any triangle is redone with a doubled
beta; if that fails, the previous iterate is kept.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ..mesh.operators import laplacian, ring_mean, safe_update, solve_spd, vertex_normals

# A match whose normal step differs from its 1-ring's mean by more than this many d* is noise.
SPIKE_TOLERANCE = 0.5
# Progress stalls when the mean move is below this many d*: alpha and beta halve...
STALL_MOVE = 0.05
# ...but never below this fraction of their start values.
MIN_WEIGHT_FRACTION = 0.2
# Extra full iterations while still moving after N iterations.
MAX_EXTRA_ITERATIONS = 4
# The exact self-intersection check runs every this many iterations (and on the last).
FULL_CHECK_EVERY = 3
# Global back-off attempts (beta doubled each time) before an iteration is rejected.
STEP_ATTEMPTS = 3
# A vertex that moved less than this many d* in an iteration is stationary (omega = 1).
STATIONARY_MOVE = 0.02


class Deformer:
    """Iterative Laplacian deformation of a closed mesh onto constraint points (eq. (15)).

    Parameters
    ----------
    vertices : (n, 3) float array
        M0's vertices, x-y-z grid millimetres.
    faces : (m, 3) int array
    constraints : (k, 3) float array
        B*, x-y-z grid millimetres.
    inside : callable
        ``inside(points (j, 3)) -> (j,) bool``: whether points lie inside the target bone
        (decides the search direction).
    edge_length : float
        d* in mm: the unit of ``search_radius`` and ``search_offset``.
    iterations : int
        N.
    alpha, beta : float
        Start weights of the smoothness and the step-damping (previous-iterate) terms.
    search_radius, search_offset : float
        Radius and centre offset |delta| of the directional search, in units of d*.
    fallbacks : BoneWatertightLib.report.FallbackLog, optional
        Notes the steps redone stiffer, a rejected iteration, the fall-back to the last
        verified iterate and CG solves stopped short.
    """

    def __init__(self, vertices, faces, constraints, inside, edge_length: float, *,
                 iterations: int = 8, alpha: float = 1.0, beta: float = 1.0,
                 search_radius: float = 1.5, search_offset: float = 0.75, fallbacks=None):
        self.v = np.array(vertices, dtype=np.float64)
        self.f = np.asarray(faces)
        self.tree = cKDTree(constraints)
        self.constraints = constraints
        self.inside = inside
        self.iterations = iterations
        self.alpha = alpha
        self.beta = beta
        self.search_radius = search_radius
        self.search_offset = search_offset
        self.d = edge_length
        n = len(self.v)
        L = laplacian(n, self.f)
        self.LtL = (L.T @ L).tocsr()
        self.avg = (sp.identity(n, format="csr") - L).tocsr()  # D^-1 A: 1-ring mean
        self.history = []
        self.last_step: dict = {}
        self.fallbacks = fallbacks

    def _note(self, what, count, unit, where=""):
        if self.fallbacks is not None and count:
            self.fallbacks.add("deform", what, count, unit, where)

    def match(self, v, normals):
        inside = self.inside(v)
        delta = self.search_offset * self.d
        radius = self.search_radius * self.d
        centre = v + np.where(inside[:, None], 1.0, -1.0) * normals * delta
        # psi: the point of B* in the search ball nearest to its centre v_c (eq. (7)).
        dist, idx = self.tree.query(centre, k=1, distance_upper_bound=radius, workers=-1)
        matched = np.isfinite(dist)
        psi = self.constraints[np.where(matched, idx, 0)]
        # Keep only the normal component of the match: neighbouring vertices matched to the same
        # voxel point would otherwise slide together and fold the triangles between them.
        along = np.einsum("ij,ij->i", psi - v, normals)
        # Noise points of B* (B_N in the paper) show up as matches far from the neighbours':
        # a vertex whose step differs from its 1-ring mean by more than half an edge is left
        # free this iteration, so it cannot grow a spike.
        nb = ring_mean(self.avg, along, matched.astype(np.float64))
        matched &= np.abs(along - nb) <= SPIKE_TOLERANCE * self.d
        psi = v + along[:, None] * normals
        psi[~matched] = v[~matched]
        return psi, matched, inside

    @staticmethod
    def control_weights(matched, stationary=None, stable: bool = False) -> np.ndarray:
        """omega (§2.4) as (n,) float: 1 for the matched vertices, for the stationary ones
        (moved less than STATIONARY_MOVE d* in the previous iteration) and, at the stable
        stage, for every vertex; 0 (free) otherwise."""
        control = np.array(matched, dtype=bool)
        if stationary is not None:
            control |= stationary
        if stable:
            control[:] = True
        return control.astype(np.float64)

    def solve(self, rhs, diag_extra, alpha, beta, x0):
        A = (alpha * self.LtL + sp.diags(diag_extra + beta)).tocsr()
        return solve_spd(A, rhs, x0, self.fallbacks, "deform")

    def step(self, j, total, alpha, beta, full_check=True, stationary=None, stable=False):
        """One iteration j of ``total``: ``(new vertices, matched, 0)``, or ``(None, matched,
        faces still bad)`` when no attempt gave a flip-free (with ``full_check``: also
        intersection-free) step. ``self.last_step`` says how many vertices were control
        vertices and how many attempts (beta doubled after each) it took."""
        v = self.v
        normals = vertex_normals(v, self.f)
        psi, matched, inside = self.match(v, normals)
        w = self.control_weights(matched, stationary, stable)
        c = (psi - v) / float(max(total - j + 1, 1))
        c[~matched] = 0.0
        psi = np.where(matched[:, None], psi, v)
        lap_rhs = self.LtL @ v
        rhs = w[:, None] * psi + alpha * (lap_rhs + w[:, None] * (v + c)) + beta * v
        diag_extra = w + alpha * w
        self.last_step = {"controlled": int(w.sum()), "attempts": 0}
        for attempt in range(STEP_ATTEMPTS):
            self.last_step["attempts"] = attempt + 1
            new = self.solve(rhs, diag_extra, alpha, beta, v)
            new, ok, bad = safe_update(v, new, self.f, intersections=False)
            if ok and full_check:
                # The exact self-intersection test costs ~1 s per 150k faces, so it runs every
                # few iterations against the last verified iterate (see run()).
                new, ok, bad = safe_update(self.clean_v, new, self.f)
                if ok:
                    self.clean_v = new
            if ok:
                self._note("a step that flipped triangles was redone stiffer (beta doubled)",
                           attempt, "retries")
                return new, matched, 0
            # Global back-off: a stiffer step (more weight on the previous iterate).
            rhs = rhs + beta * v
            beta = beta * 2.0
        return None, matched, bad

    def run(self, progress=None):
        """Deform; return the final (n, 3) vertices, verified free of flips and
        self-intersections. ``self.history`` gets one record per iteration."""
        alpha, beta = self.alpha, self.beta
        total = self.iterations
        self.clean_v = self.v.copy()
        extra = 0
        j = 1
        stationary = None
        stable = False
        while j <= total + extra:
            last = j >= total + extra
            new, matched, flipped = self.step(min(j, total), total, alpha, beta,
                                              full_check=last or j % FULL_CHECK_EVERY == 0,
                                              stationary=stationary, stable=stable)
            if new is None:
                self.history.append({"iteration": j, "rejected": True, "flipped": flipped,
                                     **self.last_step})
                self._note(f"iteration {j} still flipped triangles after {STEP_ATTEMPTS} "
                           "stiffer attempts: the deformation stopped at the iterate before it",
                           flipped, "faces")
                break
            move = np.linalg.norm(new - self.v, axis=1)
            self.v = new
            stationary = move < STATIONARY_MOVE * self.d
            rec = {"iteration": j, "alpha": alpha, "beta": beta, "matched": int(matched.sum()),
                   "stable": stable, **self.last_step,
                   "mean_move": float(move.mean()), "max_move": float(move.max())}
            self.history.append(rec)
            if progress:
                progress(min(j / max(total, 1), 1.0), f"deformation {j}/{total}")
            # Paper: when two iterations barely differ, lower alpha and beta so the proximity
            # term dominates and local detail comes out.
            if move.mean() < STALL_MOVE * self.d:
                alpha = max(alpha * 0.5, MIN_WEIGHT_FRACTION * self.alpha)
                beta = max(beta * 0.5, MIN_WEIGHT_FRACTION * self.beta)
                stable = True
            # Still moving after N iterations: a few more full steps (c = psi - v), at most 4.
            if j == total + extra and move.mean() > STALL_MOVE * self.d and extra < MAX_EXTRA_ITERATIONS:
                extra += 1
            j += 1
        if not np.array_equal(self.clean_v, self.v):
            last = self.v
            self.v, ok, _ = safe_update(self.clean_v, self.v, self.f)
            if not ok:
                self._note("the last iterates failed the self-intersection check: fell back "
                           "to the last verified iterate",
                           int(np.any(last != self.clean_v, axis=1).sum()), "vertices")
                self.v = self.clean_v
        return self.v
