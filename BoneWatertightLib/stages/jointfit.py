"""A smooth joint surface fitted to the part of a joint space the CT shows (issue 18).

Where thick slices run along a joint (the pole of a femoral head on 2.5 mm slices) the CT shows
no joint space: the two cortices blur into one bright band, and the ownership's flooding and
joint cut can only follow the labels there - a label a few mm wrong puts the split a few mm
wrong. Elsewhere on the same contact the joint space is seen. A joint's articular surfaces are
smooth, so the seen part predicts the hidden part: this module fits a plane or a sphere to the
mid-surface points of the seen joint space and says, for any point, on which side of the fitted
surface it lies and whether it lies within the fitted surface's support (the part of the
surface that the seen points surround, so the fit interpolates over a hidden patch and never
extrapolates beyond the seen joint).

Points are (n, 3) arrays in mm, in any Cartesian frame (the caller's voxel-index order times
the spacing).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

# A fit is trusted when its robust RMS distance to the seen mid-surface points is at most this
# many voxels (the mid-surface voxels are on the grid: a perfect fit leaves about 0.3 voxel).
# A ball joint seen over a good part of its ball (a determined sphere, see
# JointSurface.determined) may leave this many voxels of the CT where the CT is coarser than the
# grid (the size of a voxel of the same volume): the two bones' borders, between which the
# mid-surface lies, are located no better than the CT resolves them, and across a ball every
# direction is a normal. A plane or a shallow patch is a guess at the joint's shape and must
# follow the seen joint space to the grid's voxel (a disc's plane carried beside it cuts the
# facets of two vertebrae).
FIT_MAX_RMS_VOXELS = 0.75
# At least this many mid-surface points, spread over at least this many mm (both directions
# of the fitted surface), or the fit is not tried.
FIT_MIN_POINTS = 60
FIT_MIN_EXTENT_MM = 8.0
# ... and it must explain at least this fraction of them (the rest: trimmed as outliers).
FIT_MIN_INLIERS = 0.8
# The sphere is chosen over the plane when it leaves at most this fraction of the plane's RMS,
# and only with a radius below SPHERE_MAX_RADIUS_EXTENTS x the points' extent (beyond that it
# is a plane for the points' purposes).
SPHERE_RMS_GAIN = 0.75
SPHERE_MAX_RADIUS_EXTENTS = 5.0
# A sphere is carried over the whole contact only when its points span at least this many
# radii (see JointSurface.determined).
SPHERE_MIN_EXTENT_RADII = 1.0
# Robust fitting: points farther than this many RMS (at least one voxel) are dropped and the
# fit repeated, this many rounds.
TRIM_RMS = 2.5
TRIM_ROUNDS = 3
# A determined sphere is carried beyond its seen points, so it must predict them: fitted to the
# seen points outside each of this many sectors (of angle about their centroid, along the
# surface), the points of that sector lie within the fit's own RMS limit of it. A ball joint's
# seen ring passes (the hips of 3 mm pelvis phantoms and of the real 3 mm CT: worst sector
# 1.1-2.05 mm RMS against 2.25; the 2.5 mm-slice joint phantoms 0.3-0.5) - but not with 3 mm
# of the femur labelled hip (3.47 mm: the labels' split instead, p95 / max within 0.11 mm); a
# sacro-iliac joint, curved but no ball, that a sphere fits to 1.44 mm, does not (2.6-6.9 mm:
# carried over its contact it put the sacrum 7.5 mm into the hip bone).
SPHERE_CHECK_SECTORS = 4
# The support is the convex hull of the seen points' projections; for a sphere, points whose
# direction from the centre is more than this far round from the points' mean direction
# (cosine) are not projected (a seen part beyond a hemisphere adds no hidden patch inside).
SPHERE_MIN_COS = 0.15


@dataclass
class JointSurface:
    """A plane or sphere and its support. ``kind`` "plane": ``centre`` is a point on it and
    ``normal`` its unit normal; "sphere": ``centre`` and ``radius``. ``sign`` orients
    :meth:`signed` (negative on bone a's side); ``rms`` (mm) and ``n_points`` describe the fit.
    ``frame`` (2, 3) and ``axis`` (3,) span the projection of the support; ``hull`` is the
    scipy ConvexHull of the projected seen points."""

    kind: str
    centre: np.ndarray
    radius: float
    normal: np.ndarray
    rms: float
    n_points: int
    sign: float = 1.0
    frame: Optional[np.ndarray] = None
    axis: Optional[np.ndarray] = None
    hull: object = None

    points: Optional[np.ndarray] = None
    extent: float = 0.0   # the points' largest extent along the surface (mm)

    @property
    def determined(self) -> bool:
        """A sphere's curvature is determined by its points when they span at least
        SPHERE_MIN_EXTENT_RADII radii (a cap of about 30 degrees or more): then it may be
        carried over the whole contact; a flatter patch only near itself."""
        return self.kind == "sphere" and self.extent >= SPHERE_MIN_EXTENT_RADII * self.radius

    def build_support(self, towards: Optional[np.ndarray] = None) -> bool:
        """Make the support: the hull of the fitted points' projections. A sphere's points are
        projected about the direction ``towards`` (from the centre, (3,); default their mean
        direction): the caller passes the direction of the hidden part of the contact, so that
        a hidden patch that the seen points surround lies inside the hull. False when too few
        points project or they span no area."""
        from scipy.spatial import ConvexHull, QhullError

        if self.kind == "sphere":
            if towards is None:
                u = self.points - self.centre
                towards = (u / np.linalg.norm(u, axis=1, keepdims=True)).mean(axis=0)
            nrm = np.linalg.norm(towards)
            if not nrm > 1e-6:
                return False
            self.axis = np.asarray(towards, float) / nrm
        else:
            self.axis = self.normal
        self.frame = _frame(self.axis)
        q, ok = self.project(self.points)
        if ok.sum() < FIT_MIN_POINTS:
            return False
        try:
            self.hull = ConvexHull(q[ok])
        except QhullError:
            return False
        return True

    def distance(self, p: np.ndarray) -> np.ndarray:
        """Signed distance (mm) of points (n, 3) to the surface, unoriented: outside the
        sphere / on the normal's side of the plane positive."""
        if self.kind == "sphere":
            return np.linalg.norm(p - self.centre, axis=1) - self.radius
        return (p - self.centre) @ self.normal

    def signed(self, p: np.ndarray) -> np.ndarray:
        """Signed distance (mm), negative on bone a's side (see ``sign``)."""
        return self.sign * self.distance(p)

    def project(self, p: np.ndarray) -> tuple:
        """(2-D coordinates (n, 2) of the points in the support's projection, valid (n,) bool)."""
        if self.kind == "sphere":
            u = p - self.centre
            u = u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-9)
            c = u @ self.axis
            ok = c > SPHERE_MIN_COS
            q = (u @ self.frame.T) / np.maximum(c, SPHERE_MIN_COS)[:, None]  # gnomonic
            return q, ok
        q = (p - self.centre) @ self.frame.T
        return q, np.ones(len(p), bool)

    def supported(self, p: np.ndarray, margin_mm: float = 0.0) -> np.ndarray:
        """True (n,) where the point's projection lies inside the seen points' hull, or within
        ``margin_mm`` of a seen point's projection (measured on the surface: a sphere's
        gnomonic coordinates times its radius)."""
        q, ok = self.project(p)
        inside = np.zeros(len(p), bool)
        if ok.any():
            # Inside every edge of the hull (unit normals, offsets in the projection's units),
            # up to round-off: as a triangulation's point location but with a cost that does
            # not depend on where the walk starts (Delaunay.find_simplex took 0.01-1.9 s on the
            # same 25 000 points of a vertebra pair, most of them outside the hull).
            eq = self.hull.equations
            tol = 1e-9 * (1.0 + float(np.abs(self.hull.points).max()))
            inside[ok] = (q[ok] @ eq[:, :2].T + eq[:, 2]).max(axis=1) <= tol
            todo = ok & ~inside
            if margin_mm > 0 and todo.any():
                from scipy.spatial import cKDTree

                scale = self.radius if self.kind == "sphere" else 1.0
                dist, _ = cKDTree(self.hull.points).query(q[todo], distance_upper_bound=
                                                          margin_mm / scale)
                inside[todo] = np.isfinite(dist)
        return inside


def _plane(p: np.ndarray) -> tuple:
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    n = vt[2]
    return c, n, np.abs((p - c) @ n)


def _sphere(p: np.ndarray) -> Optional[tuple]:
    # Algebraic fit |p|^2 = 2 c.p + k, then Gauss-Newton on the geometric distance.
    a = np.column_stack([2.0 * p, np.ones(len(p))])
    sol, *_ = np.linalg.lstsq(a, (p ** 2).sum(axis=1), rcond=None)
    c = sol[:3]
    r2 = sol[3] + c @ c
    if not np.isfinite(r2) or r2 <= 0:
        return None
    r = float(np.sqrt(r2))
    for _ in range(5):
        d = p - c
        dist = np.linalg.norm(d, axis=1)
        u = d / np.maximum(dist, 1e-9)[:, None]
        jac = np.column_stack([-u, -np.ones(len(p))])
        step, *_ = np.linalg.lstsq(jac, -(dist - r), rcond=None)
        c = c + step[:3]
        r = r + float(step[3])
        if not np.isfinite(r) or r <= 0:
            return None
    return c, r, np.abs(np.linalg.norm(p - c, axis=1) - r)


def _plane_distance(res: tuple, p: np.ndarray) -> np.ndarray:
    """Unsigned distances (n,) of points to the plane (centre, normal, _) of :func:`_plane`."""
    return np.abs((p - res[0]) @ res[1])


def _sphere_distance(res: tuple, p: np.ndarray) -> np.ndarray:
    """Unsigned distances (n,) of points to the sphere (centre, radius, _) of :func:`_sphere`."""
    return np.abs(np.linalg.norm(p - res[0], axis=1) - res[1])


def _robust(fit, distance, p: np.ndarray, voxel: float):
    """``fit`` (:func:`_plane` / :func:`_sphere`) of the points, trimmed of those farther than
    TRIM_RMS x its RMS (at least a voxel; ``distance`` measures them) for TRIM_ROUNDS rounds:
    (fit result, RMS of the kept points, (n,) bool kept), or None."""
    keep = np.ones(len(p), bool)
    for _ in range(TRIM_ROUNDS):
        if keep.sum() < FIT_MIN_POINTS:
            return None
        res = fit(p[keep])
        if res is None:
            return None
        rms = float(np.sqrt(np.mean(res[-1] ** 2)))
        new = distance(res, p) <= max(TRIM_RMS * rms, voxel)
        if (new == keep).all():
            return res, rms, keep
        keep = new
    if keep.sum() < FIT_MIN_POINTS:
        return None
    res = fit(p[keep])
    if res is None:
        return None
    return res, float(np.sqrt(np.mean(res[-1] ** 2))), keep


def _frame(axis: np.ndarray) -> np.ndarray:
    t = np.eye(3)[int(np.argmin(np.abs(axis)))]
    e1 = np.cross(axis, t)
    e1 /= np.linalg.norm(e1)
    return np.vstack([e1, np.cross(axis, e1)])


def _held_out_rms(p: np.ndarray, q: np.ndarray, voxel: float) -> float:
    """The largest RMS distance of the points (n, 3) of one of SPHERE_CHECK_SECTORS angular
    sectors (of their 2-D coordinates q (n, 2) about the centroid) to the sphere fitted to the
    others (inf when that fit fails); sectors with too few points on either side are skipped."""
    ang = np.arctan2(q[:, 1] - q[:, 1].mean(), q[:, 0] - q[:, 0].mean())
    sector = np.minimum(((ang + np.pi) / (2 * np.pi) * SPHERE_CHECK_SECTORS).astype(int),
                        SPHERE_CHECK_SECTORS - 1)
    worst = 0.0
    for k in range(SPHERE_CHECK_SECTORS):
        held = sector == k
        if held.sum() < 5 or (~held).sum() < FIT_MIN_POINTS:
            continue
        fit = _robust(_sphere, _sphere_distance, p[~held], voxel)
        if fit is None:
            return float("inf")
        d = _sphere_distance(fit[0], p[held])
        worst = max(worst, float(np.sqrt(np.mean(d ** 2))))
    return worst


def fit_joint_surface(points: np.ndarray, voxel: float, resolution: float = 0.0,
                      reasons: Optional[list] = None) -> Optional[JointSurface]:
    """Fit a plane or a sphere to the mid-surface points of a seen joint space.

    Parameters
    ----------
    points : (n, 3) float array
        Mid-surface points of the seen joint space (mm).
    voxel : float
        The grid's voxel size (mm): the scale of the points' own scatter.
    resolution : float
        The size (mm) of a cube of the CT's voxel volume: where it is coarser than the grid,
        the scale of a determined sphere's scatter instead (see FIT_MAX_RMS_VOXELS).
    reasons : list, optional
        Gets one sentence when no fit is returned: why.

    Returns
    -------
    JointSurface or None
        The simpler model that explains the points (a sphere only when it explains them
        clearly better than the plane), or None when the points are too few, too local, or
        neither model fits within FIT_MAX_RMS_VOXELS voxels (an irregular joint: the caller
        keeps what the labels say). ``sign`` is +1; orient it with the bones' sides.
    """
    def refuse(why):
        if reasons is not None:
            reasons.append(why)
        return None

    p = np.asarray(points, float)
    if len(p) < FIT_MIN_POINTS:
        return refuse(f"fewer than {FIT_MIN_POINTS} points of seen joint space")
    c0, n0, _ = _plane(p)
    q0 = (p - c0) @ _frame(n0).T
    extent = q0.max(axis=0) - q0.min(axis=0)
    if extent.min() < FIT_MIN_EXTENT_MM:
        return refuse(f"the seen joint space spans less than {FIT_MIN_EXTENT_MM:g} mm")
    plane = _robust(_plane, _plane_distance, p, voxel)
    sphere = _robust(_sphere, _sphere_distance, p, voxel)
    chosen = None
    if sphere is not None and plane is not None:
        (c, r, _), rms_s, keep_s = sphere
        if rms_s <= SPHERE_RMS_GAIN * plane[1] and r <= SPHERE_MAX_RADIUS_EXTENTS * extent.max():
            chosen = ("sphere", sphere)
    if chosen is None and plane is not None:
        chosen = ("plane", plane)
    if chosen is None:
        return refuse("neither a plane nor a sphere could be fitted")
    limit = FIT_MAX_RMS_VOXELS * voxel
    if chosen[0] == "sphere" and extent.max() >= SPHERE_MIN_EXTENT_RADII * chosen[1][0][1]:
        limit = FIT_MAX_RMS_VOXELS * max(voxel, resolution)
    if chosen[1][1] > limit:
        return refuse(f"irregular: the best {chosen[0]} leaves an RMS of {chosen[1][1]:.2f} mm "
                      f"(at most {limit:.2f} mm)")
    kind, (res, rms, keep) = chosen
    if keep.mean() < FIT_MIN_INLIERS:
        return refuse(f"the {kind} explains only {keep.mean():.0%} of the seen joint space")
    if kind == "sphere" and extent.max() >= SPHERE_MIN_EXTENT_RADII * res[1]:
        worst = _held_out_rms(p, q0, voxel)
        if worst > limit:
            return refuse(f"no ball: the sphere fitted to the rest of the seen joint space misses "
                          f"one of its {SPHERE_CHECK_SECTORS} sectors by {worst:.2f} mm RMS "
                          f"(at most {limit:.2f} mm)")
    pts = p[keep]
    if kind == "sphere":
        c, r, _ = res
        surf = JointSurface("sphere", c, float(r), np.zeros(3), rms, int(keep.sum()))
    else:
        c, n, _ = res
        surf = JointSurface("plane", c, float("inf"), n, rms, int(keep.sum()))
    surf.points = pts
    surf.extent = float(extent.max())
    return surf if surf.build_support() else refuse("no support could be built for the fit")
