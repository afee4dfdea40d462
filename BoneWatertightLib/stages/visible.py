"""Stage 4: visible surface points by hyper-spherical mapping (paper §2.2, eq. (1)).

For a viewpoint O every point p is flipped about a sphere of radius R centred on O:
    p* = X + 2 (R - |X|) X / |X|,   X = p - O.
A point is visible from O when its image is a vertex of the convex hull of {p*} U {O}. The hull
is computed with Qhull (scipy.spatial.ConvexHull).

R is relative: the points are first scaled so that the farthest one is at distance 1 from O,
and R = 10**log_radius in those units (paper: 10^3.5 - 10^3.8). The result is then independent of
the bone's size and of the units.

Viewpoints: the 6 directions +/- of the principal axes of the points (PCA), then the 8 diagonals and
the 12 edge directions of that frame, each at ``view_distance`` times the bounding radius from the
centroid. Views are added until ``views`` are used or the union stops growing (< 0.5 %).
Only boundary voxels are fed to the hull: interior voxels are hidden behind them (measured in the
tests: the visible set is the same).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from ..threads import cpu_threads, map_ahead

# Most points fed to the hull (the surface voxels are thinned on a lattice beyond this).
MAX_HULL_POINTS = 60000
# Views stop once two successive views each add fewer than this fraction of new points
# (checked from the 6th view on).
MIN_VIEW_GAIN = 0.005
MIN_VIEWS_BEFORE_STOP = 6
# Isolated-point cleaning: a visible point needs this many visible neighbours within
# CLEAN_RADIUS_VOXELS voxels (a surface patch has ~12).
CLEAN_MIN_NEIGHBOURS = 4
CLEAN_RADIUS_VOXELS = 2.01
# Hulls computed at once (one per CPU, at most this many).
HULL_THREADS = 2


def hpr_visible(points: np.ndarray, viewpoint: np.ndarray, log_radius: float) -> np.ndarray:
    """Indices of points visible from viewpoint (spherical flip + convex hull, eq. (1)).

    Parameters
    ----------
    points : (n, 3) float array
        x-y-z points (any length unit; the flip is scale-free).
    viewpoint : (3,) float array
        O, in the same frame.
    log_radius : float
        R = 10**log_radius times the farthest point's distance from O.

    Returns
    -------
    (k,) int array of indices into ``points``
    """
    x = points - viewpoint
    norm = np.linalg.norm(x, axis=1)
    scale = norm.max()
    if scale <= 0:
        return np.arange(len(points))
    x = x / scale
    norm = norm / scale
    norm = np.maximum(norm, 1e-12)
    radius = 10.0 ** log_radius
    flipped = x + 2.0 * (radius - norm)[:, None] * (x / norm[:, None])
    hull = ConvexHull(np.vstack([flipped, np.zeros((1, 3))]))
    vis = hull.vertices
    return vis[vis < len(points)]


def _hulls(points: np.ndarray, viewpoints: list, log_radius: float):
    """:func:`hpr_visible` of each viewpoint, in order, as a generator; with several CPUs the
    next views are computed ahead on threads (Qhull releases the GIL: 12 femur views 1.1 ->
    0.6 s on two threads). The caller may stop early: at most the views ahead are wasted."""
    return map_ahead(lambda vp: hpr_visible(points, vp, log_radius), viewpoints,
                     cpu_threads(HULL_THREADS), "hpr")


def view_directions(points: np.ndarray) -> np.ndarray:
    """Unit view directions: PCA axes +/- first, then diagonals and edge directions."""
    centred = points - points.mean(axis=0)
    cov = centred.T @ centred / max(len(points) - 1, 1)
    _, vecs = np.linalg.eigh(cov)
    axes = vecs[:, ::-1].T  # principal axis first
    dirs = []
    for a in axes:
        dirs += [a, -a]
    for s in np.array([[1, 1, 1], [-1, -1, -1], [1, -1, -1], [-1, 1, 1],
                       [-1, 1, -1], [1, -1, 1], [-1, -1, 1], [1, 1, -1]], dtype=float):
        dirs.append(s @ axes / np.sqrt(3))
    for i, j in ((0, 1), (0, 2), (1, 2)):
        for si, sj in ((1, 1), (-1, -1), (1, -1), (-1, 1)):
            dirs.append((si * axes[i] + sj * axes[j]) / np.sqrt(2))
    return np.array(dirs)


def thin_points(points: np.ndarray, spacing: float, max_points: int = MAX_HULL_POINTS) -> np.ndarray:
    """Indices of a lattice-strided subset with at most ~max_points (surface voxels thin out as
    stride^2). Poisson at depth 7 needs far fewer points than a 0.5 mm surface has, and the
    HT boundary points keep the deformation's constraints dense."""
    if len(points) <= max_points:
        return np.arange(len(points))
    idx = np.rint(points / spacing).astype(np.int64)
    for stride in range(2, 12):
        # Two of three lattice coordinates on the stride: slanted faces keep points too.
        keep = np.flatnonzero(np.sum(idx % stride == 0, axis=1) >= 2)
        if len(keep) <= max_points:
            break
    return keep


def visible_points(points: np.ndarray, spacing: float, *, views: int = 14,
                   view_distance: float = 20.0, log_radius: float = 3.6,
                   progress=None, full: bool = False) -> tuple:
    """Union of the points visible from the viewpoints, cleaned of isolated border noise.

    Parameters
    ----------
    points : (n, 3) float array
        Boundary-voxel centres, x-y-z grid millimetres.
    spacing : float
        Voxel size in mm (lattice of ``points``).
    views : int
        Most viewpoints used (PCA axes first, see :func:`view_directions`).
    view_distance : float
        Viewpoint distance from the centroid, in bounding radii.
    log_radius : float
        Flip radius exponent, see :func:`hpr_visible`.
    progress : callable, optional
    full : bool
        Also return the indices of every candidate that is visible (HPR runs on a thinned
        lattice of at most MAX_HULL_POINTS; each candidate takes its nearest tested point's
        verdict).

    Returns
    -------
    indices : (k,) int array into ``points``
        The visible points of the thinned lattice.
    info : dict
        Per-view counts for the report.
    every : (j,) int array into ``points``
        Only with ``full``: every visible candidate.
    """
    sub = thin_points(points, spacing)
    all_points, points = points, points[sub]
    centroid = points.mean(axis=0)
    bound = np.linalg.norm(points - centroid, axis=1).max()
    dirs = view_directions(points)
    seen = np.zeros(len(points), dtype=bool)
    per_view = []
    small_gain = 0
    viewpoints = [centroid + direction * view_distance * bound for direction in dirs[:views]]
    for k, idx in enumerate(_hulls(points, viewpoints, log_radius)):
        before = int(seen.sum())
        seen[idx] = True
        gain = int(seen.sum()) - before
        per_view.append({"view": k, "visible": int(len(idx)), "new": gain})
        if progress:
            progress((k + 1) / views, f"view {k + 1}")
        if k >= MIN_VIEWS_BEFORE_STOP - 1:
            small_gain = small_gain + 1 if gain < MIN_VIEW_GAIN * seen.sum() else 0
            if small_gain >= 2:
                break
    vis = np.flatnonzero(seen)
    # Patch borders (grazing rays) pick up isolated points of inner layers: keep points with
    # enough visible neighbours within 2 voxels (a surface patch has ~12 of them).
    tree = cKDTree(points[vis])
    radius = CLEAN_RADIUS_VOXELS * spacing * max(1.0, np.sqrt(len(all_points) / max(len(points), 1)))
    counts = tree.query_ball_point(points[vis], r=radius, return_length=True, workers=-1)
    kept = vis[counts >= CLEAN_MIN_NEIGHBOURS]
    clean = sub[kept]
    info = {"views_used": len(per_view), "per_view": per_view, "candidates": int(len(points)),
            "visible_raw": int(len(vis)),
            "visible": int(len(clean)), "removed_isolated": int(len(vis) - len(clean))}
    if not full:
        return clean, info
    # Every candidate takes the visibility of its nearest tested point (the thinning keeps a
    # lattice of them): the deformation gets all of S(P_H0), Poisson the thinned copy.
    if len(sub) == len(all_points):
        return clean, info, clean
    flag = np.zeros(len(points), bool)
    flag[kept] = True
    dist, nearest = cKDTree(points).query(all_points, workers=-1)
    reach = np.sqrt(3.0) * spacing * max(1.0, np.sqrt(len(all_points) / max(len(points), 1)))
    every = np.flatnonzero(flag[nearest] & (dist <= reach))
    info["visible_full"] = int(len(every))
    return clean, info, every
