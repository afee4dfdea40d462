"""Stage 4b (ours): thin bone plates that the CT barely resolves.

A cortical plate thinner than the CT's resolution - an iliac wing, a scapular blade, a sacral
ala, a transverse process on 2.5-3 mm slices - is blurred into a faint *ridge*: a sheet-like
local maximum of the CT a few hundred HU above the soft tissue, often below H0 and HT, so the
two-step threshold and its opening cut it away and the surface gets a hole (or lace) where the
bone is. The ridge still says where the plate is, and how much bone it holds:

1. **Ridges**: on the CT smoothed at the scale of its own voxels, voxels where the Hessian has
   one strongly negative eigenvalue lambda_1 and two small ones (a bright sheet), whose
   sub-voxel maximum along lambda_1's eigenvector e (the plate's normal) lies within the voxel,
   and whose peak stands at least ``min_contrast`` above the local background on both sides.
2. **Thickness** (the blurred-slab model of cortical bone mapping): a blur preserves the bone
   mass across the plate, so its true thickness is w = integral of (CT - background) along e /
   (cortex - background) - independent of the point-spread function, which need not be known.
   Only plates thinner than the CT's resolution along e (its voxel extent in that direction)
   are kept: thicker bone is resolved and the thresholds and the edge refinement handle it.
3. **The model**: each ridge point stands for a slab of thickness t = max(w, t_min) centred on
   it (t_min: the thinnest slab the working grid and the remeshing resolve without holes). The
   slab joins the bone's masks (visible-point candidates, the deformation's inside test), is
   fused into the initial surface M0 (Poisson at depth 7 cannot resolve a plate of a few
   millimetres in a bone 20 cm long), and gives the edge refinement a target on the vertices
   where the CT profile shows no edge.
4. **Processes of the segment** (:func:`segment_processes`): a tail or a process tip thinner
   than the CT resolves is a faint bright *rod*, too narrow for a sheet's profile; where the
   segment goes on along it farther beyond the thresholded bone than a segment that coarse
   misplaces a border, and the CT there is above the soft tissue and brighter than the tissue
   around it, the segment's part joins the bone (label-only shape, reported as a fallback).

Points are (n, 3) x-y-z millimetres of the working grid; volumes (z, y, x) arrays.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .threshold import dilate6, dilate_cube

# Ridge scale: Gaussian sigma = max(working spacing, PLATE_SIGMA_FRACTION x the CT's finest
# spacing) - the scale of the blur the plate has already had.
PLATE_SIGMA_FRACTION = 0.25
# A sheet: the second Hessian eigenvalue is at most this fraction of the first (a tube has
# two equally negative eigenvalues, a blob three).
PLATE_SHEETNESS = 0.5
# The profile across the plate is read within +- PLATE_WINDOW x the CT's resolution along the
# normal (the blur of a thin plate spreads about that far).
PLATE_WINDOW = 1.5
# A plate is thinner than PLATE_MAX_RESOLUTION x the CT's resolution along its normal, and holds
# at least as much bone as a cortex PLATE_MIN_MM thick: a ridge with less mass under it is
# soft tissue's texture or noise (the thinnest cortical plates are 0.2-0.3 mm).
PLATE_MAX_RESOLUTION = 1.0
PLATE_MIN_MM = 0.15
# A ridge stands at least PLATE_NOISE_FACTOR x the noise of the smoothed CT above its local
# background (the noise measured in the soft tissue within SOFT_WINDOW_HU of its level).
PLATE_NOISE_FACTOR = 4.0
SOFT_WINDOW_HU = 60.0
# Ridge pieces of fewer than PLATE_MIN_POINTS points are noise.
PLATE_MIN_POINTS = 20
# Refinement targets: only where the vertex normal is within PLATE_MAX_ANGLE_DEG of the plate's
# and the vertex lies within t / 2 + PLATE_SNAP_MM of the ridge.
PLATE_MAX_ANGLE_DEG = 40.0
PLATE_SNAP_MM = 2.0
# t_min = PLATE_MIN_STEPS x the coarser of the working voxel and the remeshing grid step: a
# thinner slab has no grid point inside it somewhere and comes out as a hole.
PLATE_MIN_STEPS = 1.2


@dataclass
class Plates:
    """Thin plates of one bone.

    ``points`` (m, 3): sub-voxel ridge points (x-y-z mm of the working grid); ``normals``
    (m, 3): unit plate normals; ``thickness`` (m,): the estimated true thickness w (mm);
    ``model`` (m,): the slab thickness the surface is given, max(w, t_min) (mm);
    ``contrast`` (m,): ridge peak above the local background (HU); ``spacing``: the working
    grid's voxel size; ``info``: counts and figures for the report.
    """

    points: np.ndarray
    normals: np.ndarray
    thickness: np.ndarray
    model: np.ndarray
    contrast: np.ndarray
    spacing: float
    info: dict = field(default_factory=dict)
    _tree: object = field(default=None, repr=False)

    @property
    def n(self) -> int:
        return int(len(self.points))

    def subset(self, keep: np.ndarray) -> "Plates":
        """The plates of the points where ``keep`` (m,) is true."""
        return Plates(self.points[keep], self.normals[keep], self.thickness[keep],
                      self.model[keep], self.contrast[keep], self.spacing, dict(self.info))

    @property
    def tree(self):
        if self._tree is None:
            self._tree = cKDTree(self.points)
        return self._tree

    def offsets(self, points: np.ndarray, lateral_max: float):
        """For each point (k, 3): (index of the nearest ridge point or -1, signed distance
        along that point's normal, lateral distance), for ridge points within reach."""
        k = len(points)
        idx = np.full(k, -1, np.int64)
        along = np.zeros(k)
        lateral = np.full(k, np.inf)
        if not self.n or not k:
            return idx, along, lateral
        reach = 0.5 * float(self.model.max()) + PLATE_SNAP_MM + lateral_max
        dist, j = self.tree.query(points, distance_upper_bound=reach, workers=-1)
        ok = np.isfinite(dist)
        jj = j[ok]
        rel = points[ok] - self.points[jj]
        a = np.einsum("ij,ij->i", rel, self.normals[jj])
        lat = np.sqrt(np.maximum((rel * rel).sum(axis=1) - a * a, 0.0))
        idx[ok], along[ok], lateral[ok] = jj, a, lat
        return idx, along, lateral

    def mask(self, shape: tuple, origin: np.ndarray) -> np.ndarray:
        """The slabs as voxels of a box: (z, y, x) bool of ``shape`` whose voxel (0, 0, 0) is
        at ``origin`` (x-y-z mm)."""
        return self.field(shape, origin, self.spacing) >= 0.5

    def field(self, shape: tuple, origin, step: float) -> np.ndarray:
        """The slabs as a [0, 1] occupancy ramp on a grid of step ``step`` (z, y, x) of
        ``shape`` whose voxel (0, 0, 0) is at ``origin``: 1 inside a slab, 0 outside, linear
        over one step across its faces (so that its 0.5 level is the slab's face, sub-voxel)."""
        out = np.zeros(shape, np.float32)
        if not self.n:
            return out
        origin = np.asarray(origin, np.float64)
        near = np.zeros(shape, bool)
        ijk = np.rint((self.points - origin) / step).astype(np.int64)
        inside = np.all((ijk >= 0) & (ijk < np.array(shape[::-1])), axis=1)
        if not inside.any():
            return out
        ijk = ijk[inside]
        near[ijk[:, 2], ijk[:, 1], ijk[:, 0]] = True
        grow = int(np.ceil((0.5 * float(self.model.max()) + step) / step)) + 1
        near = dilate_cube(near, grow)
        zyx = np.argwhere(near)
        pts = zyx[:, ::-1] * step + origin
        j, along, lateral = self.offsets(pts, 0.0)
        ok = j >= 0
        half = 0.5 * self.model[np.maximum(j, 0)]
        # Lateral reach: ridge points are about one working voxel apart; beyond that the
        # point lies past the plate's rim.
        val = np.clip(0.5 + (half - np.abs(along)) / step, 0.0, 1.0)
        val[~ok | (lateral > 0.87 * max(self.spacing, step))] = 0.0
        out[zyx[:, 0], zyx[:, 1], zyx[:, 2]] = val
        return out

    def targets(self, vertices: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Shift (mm) along each vertex normal that puts the vertex on its plate's face, NaN
        where no plate is near or the normals disagree: (n,) float array."""
        shift = np.full(len(vertices), np.nan)
        j, along, lateral = self.offsets(vertices, 0.0)
        ok = (j >= 0) & (lateral <= 1.5 * self.spacing)
        if not ok.any():
            return shift
        jj = j[ok]
        side = np.where(along[ok] >= 0, 1.0, -1.0)
        cos = side * np.einsum("ij,ij->i", normals[ok], self.normals[jj])
        half = 0.5 * self.model[jj]
        good = (cos >= np.cos(np.radians(PLATE_MAX_ANGLE_DEG))) & \
            (np.abs(along[ok]) <= half + PLATE_SNAP_MM)
        s = (side * half - along[ok]) / np.maximum(cos, 1e-3) * side
        out = np.full(ok.sum(), np.nan)
        out[good] = s[good]
        shift[ok] = out
        return shift


def empty_plates(spacing: float) -> Plates:
    return Plates(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0),
                  spacing, {"points": 0})


def find_plates(ct: np.ndarray, region: np.ndarray, bone: np.ndarray, resolved: np.ndarray,
                spacing: float, *, native_spacing, soft: float, cortex: float,
                max_contrast: float, min_thickness: float, origin=(0.0, 0.0, 0.0),
                smoothed: np.ndarray = None) -> Plates:
    """Thin plates of one bone (see the module doc).

    Parameters
    ----------
    ct : (z, y, x) float array
        The CT (HU) resampled onto the working grid (not sharpened: the thickness comes from
        the bone mass under the profile), on the bone's box.
    region : (z, y, x) bool array
        Where the bone's plates may lie (its segment and band, not another bone's).
    bone : (z, y, x) bool array
        The bone's own evidence: a ridge piece that touches it is a plate of the bone.
    resolved : (z, y, x) bool array
        Where the thresholds already hold the bone at least ``min_thickness`` thick (no plate
        is sought there).
    spacing : float
        Working voxel size d (mm).
    native_spacing : sequence of 3 floats
        The CT's own spacing (x, y, z) in mm, in the working grid's axes.
    soft : float
        Soft-tissue level (HU).
    cortex : float
        Full cortical level (HU) of the bone (thick cortex).
    max_contrast : float
        The least peak height above the local background (HU) a ridge needs is
        PLATE_NOISE_FACTOR x the noise of the smoothed CT in the box's soft tissue, but never
        more than this.
    min_thickness : float
        t_min (mm): the thinnest slab the surface is given.
    origin : sequence of 3 floats
        x-y-z mm of the box's voxel (0, 0, 0) on the working grid (the points are returned in
        working-grid millimetres).
    smoothed : (z, y, x) float array, optional
        :func:`smooth_ct` of ``ct`` when already made (made here otherwise).

    Returns
    -------
    Plates
    """
    d = float(spacing)
    native = np.asarray(native_spacing, np.float64)
    if not region.any():
        return empty_plates(d)
    sigma_mm = ridge_sigma_mm(d, native)
    sm = smooth_ct(ct, d, native) if smoothed is None else smoothed
    noise = soft_tissue_noise(sm, region | bone, soft)
    min_contrast = min(max_contrast, PLATE_NOISE_FACTOR * noise)
    cand = region & (sm >= soft + min_contrast) & ~resolved
    cand[[0, -1], :, :] = False
    cand[:, [0, -1], :] = False
    cand[:, :, [0, -1]] = False
    cand &= _local_peaks(sm)
    idx = np.argwhere(cand)
    del cand
    found = [_ridges(sm, idx[a:a + CHUNK], d, native, cortex, min_contrast)
             for a in range(0, len(idx), CHUNK)]
    idx = np.concatenate([f[0] for f in found]) if found else np.zeros((0, 3), np.int64)
    if not len(idx):
        none = empty_plates(d)
        none.info["noise_hu"] = float(noise)
        return none
    pts, e, w, contrast = (np.concatenate([f[i] for f in found]) for i in range(1, 5))
    # Ridge pieces: kept when they touch the bone's evidence (a plate of the bone, not a
    # structure of the soft tissue beside it).
    lab = np.zeros(sm.shape, bool)
    lab[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    pieces, n_pieces = ndimage.label(lab, structure=np.ones((3, 3, 3), bool))
    piece = pieces[idx[:, 0], idx[:, 1], idx[:, 2]]
    size = np.bincount(piece, minlength=n_pieces + 1)
    near_bone = dilate_cube(bone, 2)
    touching = np.zeros(n_pieces + 1, bool)
    touching[np.unique(piece[near_bone[idx[:, 0], idx[:, 1], idx[:, 2]]])] = True
    good = touching[piece] & (size[piece] >= PLATE_MIN_POINTS)
    pts, e, w, contrast = pts[good], e[good], w[good], contrast[good]
    model = np.maximum(w, min_thickness)
    info = {"points": int(len(pts)), "area_mm2": float(len(pts) * d * d),
            "thickness_mm_median": float(np.median(w)) if len(w) else None,
            "thickness_mm_p10": float(np.percentile(w, 10)) if len(w) else None,
            "thickened_fraction": float((w < min_thickness).mean()) if len(w) else 0.0,
            "min_thickness_mm": float(min_thickness), "ridge_sigma_mm": float(sigma_mm),
            "min_contrast_hu": float(min_contrast), "noise_hu": float(noise),
            "cortex_hu": float(cortex)}
    return Plates(pts + np.asarray(origin, np.float64), e, w, model, contrast, d, info)


def _hessian_ridge(sm, idx, d):
    """Hessian eigenvalues (k, 3) ascending, the first eigenvector (k, 3) x-y-z and the
    Newton step along it (k,) (mm) of ``sm`` at voxels idx (k, 3) (z, y, x), by central
    differences."""
    z, y, x = idx.T

    def at(dz, dy, dx):
        return sm[z + dz, y + dy, x + dx].astype(np.float64)

    c0 = at(0, 0, 0)
    H = np.empty((len(idx), 3, 3))
    H[:, 0, 0] = at(0, 0, 1) - 2 * c0 + at(0, 0, -1)
    H[:, 1, 1] = at(0, 1, 0) - 2 * c0 + at(0, -1, 0)
    H[:, 2, 2] = at(1, 0, 0) - 2 * c0 + at(-1, 0, 0)
    H[:, 0, 1] = H[:, 1, 0] = 0.25 * (at(0, 1, 1) - at(0, 1, -1) - at(0, -1, 1) + at(0, -1, -1))
    H[:, 0, 2] = H[:, 2, 0] = 0.25 * (at(1, 0, 1) - at(1, 0, -1) - at(-1, 0, 1) + at(-1, 0, -1))
    H[:, 1, 2] = H[:, 2, 1] = 0.25 * (at(1, 1, 0) - at(1, -1, 0) - at(-1, 1, 0) + at(-1, -1, 0))
    H /= d * d
    g = 0.5 * np.stack([at(0, 0, 1) - at(0, 0, -1), at(0, 1, 0) - at(0, -1, 0),
                        at(1, 0, 0) - at(-1, 0, 0)], axis=1) / d
    lam, vec = np.linalg.eigh(H)
    e = vec[:, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = -np.einsum("ij,ij->i", g, e) / lam[:, 0]
    return lam, e, np.nan_to_num(delta, nan=np.inf)


def soft_tissue_noise(sm: np.ndarray, exclude: np.ndarray, soft: float) -> float:
    """Noise (HU, a robust standard deviation) of the smoothed CT ``sm`` in the soft tissue of
    its box: voxels within SOFT_WINDOW_HU of the soft-tissue level, away from ``exclude``
    (the bone and its region). Soft tissue's own texture counts as noise (an upper bound)."""
    away = ~dilate6(exclude, 2)
    v = sm[away & (np.abs(sm - soft) <= SOFT_WINDOW_HU)]
    if v.size < 100:
        return float(SOFT_WINDOW_HU / PLATE_NOISE_FACTOR)
    return float(1.4826 * np.median(np.abs(v - np.median(v))))


def ridge_sigma_mm(spacing: float, native_spacing) -> float:
    """The ridges' scale (mm): max(working spacing, PLATE_SIGMA_FRACTION x the CT's finest
    spacing) - the scale of the blur a plate has already had. ``native_spacing``: the CT's own
    spacing (x, y, z) in mm."""
    return max(float(spacing), PLATE_SIGMA_FRACTION * float(np.min(native_spacing)))


def smooth_ct(ct: np.ndarray, spacing: float, native_spacing) -> np.ndarray:
    """The CT (z, y, x) smoothed by a Gaussian at :func:`ridge_sigma_mm`, float32."""
    d = float(spacing)
    return ndimage.gaussian_filter(np.asarray(ct, np.float32),
                                   sigma=ridge_sigma_mm(d, native_spacing) / d, mode="nearest")


def _local_peaks(sm: np.ndarray) -> np.ndarray:
    """Voxels that are a local maximum of ``sm`` along at least one grid axis (bool): the
    cheap pre-selection of ridge voxels."""
    peak_any = np.zeros(sm.shape, bool)
    for axis in range(3):
        peak_any |= (sm >= np.roll(sm, 1, axis=axis)) & (sm >= np.roll(sm, -1, axis=axis))
    return peak_any


def _slab_thickness(prof: np.ndarray, il: np.ndarray, ir: np.ndarray, step: float,
                    cortex: float) -> tuple:
    """(background (k,), thickness (k,) mm) of profiles ``prof`` (k, n) sampled every ``step``
    mm across a plate, between their valleys at columns ``il`` and ``ir`` (k,): the background
    is the valleys' mean (soft tissue, fat, or marrow between two cortices), the bone mass what
    stands above it between them, as a thickness of ``cortex`` (the blurred-slab model)."""
    rows = np.arange(len(prof))
    bg = 0.5 * (prof[rows, il] + prof[rows, ir])
    cols = np.arange(prof.shape[1])[None, :]
    between = (cols >= il[:, None]) & (cols <= ir[:, None])
    mass = np.sum(np.where(between, np.clip(prof - bg[:, None], 0.0, None), 0.0), axis=1) * step
    return bg, mass / np.maximum(cortex - bg, 1.0)


# Candidate voxels are examined in chunks of this many (bounds the profiles' memory).
CHUNK = 100_000


def _ridges(sm, idx, d, native, cortex, min_contrast):
    """Of candidate voxels idx (k, 3) (z, y, x): the thin-plate ridge voxels, their
    sub-voxel points (x-y-z mm of the box), normals, thicknesses and contrasts."""
    none = (np.zeros((0, 3), np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0),
            np.zeros(0))
    if not len(idx):
        return none
    lam, e, delta = _hessian_ridge(sm, idx, d)
    l1, l2 = lam[:, 0], lam[:, 1]
    # (Within the voxel: the cube's half-extent along e, so every column across a plate has
    # a ridge voxel.)
    ridge = (l1 < 0) & (l2 > PLATE_SHEETNESS * l1) & \
        (np.abs(delta) <= 0.5 * d * np.abs(e).sum(axis=1))
    if not ridge.any():
        return none
    idx, e, delta = idx[ridge], e[ridge], delta[ridge]
    pts = idx[:, ::-1].astype(np.float64) * d + delta[:, None] * e
    # The CT's resolution along each plate normal: its voxel extent in that direction.
    res = np.sqrt(((e * native[None, :]) ** 2).sum(axis=1))
    window = PLATE_WINDOW * res
    step = 0.5 * d
    t = np.arange(-float(window.max()), float(window.max()) + 1e-9, step)
    samples = pts[:, None, :] + t[None, :, None] * e[:, None, :]
    # The smoothed CT: a blur keeps the bone mass under the profile and the smoothing keeps
    # noise from making a ridge of soft tissue.
    prof = ndimage.map_coordinates(sm, samples[..., ::-1].reshape(-1, 3).T / d, order=1,
                                   mode="nearest").reshape(len(pts), len(t))
    within = np.abs(t)[None, :] <= window[:, None]
    peak = np.max(np.where((np.abs(t) <= d)[None, :], prof, -np.inf), axis=1)
    il = np.argmin(np.where(within & (t[None, :] < 0), prof, np.inf), axis=1)
    ir = np.argmin(np.where(within & (t[None, :] > 0), prof, np.inf), axis=1)
    bg, w = _slab_thickness(prof, il, ir, step, cortex)
    contrast = peak - bg
    keep = (contrast >= min_contrast) & (w >= PLATE_MIN_MM) & (w < PLATE_MAX_RESOLUTION * res)
    return idx[keep], pts[keep], e[keep], w[keep], contrast[keep]


# Plates across a surface's holes are sought up to HOLE_REACH_MM from it (holes up to about
# twice that across).
HOLE_REACH_MM = 8.0


def holes_across_plates(inside: np.ndarray, ct: np.ndarray, spacing: float, *,
                        native_spacing, soft: float, cortex: float, max_contrast: float,
                        exclude: np.ndarray, surface_genus: int,
                        reach_mm: float = HOLE_REACH_MM, noise: float = None,
                        smoothed: np.ndarray = None) -> dict:
    """Tunnels of a surface through which the CT shows a thin plate, and their plugs.

    A hole through a plate the CT barely resolves (a wall of two voxels that the opening
    removed, a plate below the thresholds) has the plate's blurred ridge across it: across the
    plate the CT peaks in the hole and falls on both sides. A foramen, a canal or the blurred
    end of a slot is the opposite, a valley, however much its blur raises it above the soft
    tissue.

    1. The crests of bright sheets outside the surface and within ``reach_mm`` of it
       (:func:`_ridge_voxels`), grown by a voxel (a crest one voxel thin, met by the surface's
       rim); each piece that closes a tunnel of the surface's voxels (:func:`_tunnel_plugs`)
       is a plug. (A closing would not do: a ball closes a hole of radius r in a plate t thick
       only when larger than about r^2 / t.)
    2. A plug is a plate's when, across it (:func:`_across`), its median peak stands at least
       the contrast above the soft tissue and above the lower sides, holds bone at least
       PLATE_MIN_MM of cortex thick (less is soft tissue's texture, as for :func:`find_plates`),
       touches no ``exclude`` voxel, and the hole is wider than the CT's blur in its plane (its
       deepest voxel PLATE_WINDOW x that resolution from the surface: a narrower hole reads
       bright in the middle whether or not a plate spans it).
    3. Each plate's plug, largest first, is confirmed on the whole box: kept when the voxels
       with it have fewer tunnels (:func:`_tunnels`) than without it and than the surface
       itself (a pocket closed against the surface deeper than the plug's window, or a tunnel
       of the voxels alone, is not counted).

    Parameters
    ----------
    inside : (z, y, x) bool array
        The surface's inside on the working grid (a box of it).
    ct : (z, y, x) float array
        The CT (HU) on the same box of the working grid.
    spacing : float
        Working voxel size d (mm).
    native_spacing : sequence of 3 floats
        The CT's own spacing (x, y, z) in mm, in the working grid's axes.
    soft : float
        Soft-tissue level (HU).
    cortex : float
        Full cortical level (HU) of the bone: a plate holds at least PLATE_MIN_MM of it.
    max_contrast : float
        The contrast a plate needs is PLATE_NOISE_FACTOR x the noise of the smoothed CT in the
        box's soft tissue, but never more than this (HU).
    exclude : (z, y, x) bool array
        Where a plate of this bone cannot be (another bone's voxels, beyond the image).
    surface_genus : int
        The surface's own genus (its mesh's); 0: nothing is sought.
    reach_mm : float
        How far outside the surface a plate's crest is sought.
    noise : float, optional
        The smoothed CT's noise in the soft tissue (HU; :func:`soft_tissue_noise`, measured
        again when not given).
    smoothed : (z, y, x) float array, optional
        :func:`smooth_ct` of ``ct`` when already made (:func:`find_plates`' of the same box).

    Returns
    -------
    dict
        ``tunnels``: how many of the surface's tunnels go through a plate (0 when none);
        ``plugs``: their plugs, largest first - ``voxels``, ``centre`` (x, y, z mm of the
        box), ``hu_median`` (the CT on it), ``contrast_hu`` (its median peak over its sides),
        ``thickness_mm`` (the bone it holds, as cortex);
        ``other_plugs``: plugs of tunnels that are not a plate's; ``mask``: the plates' plugs,
        (z, y, x) bool like ``inside`` (only when there are some); ``min_contrast_hu``,
        ``noise_hu``.
    """
    from ..mesh.distance import distance_outside

    d = float(spacing)
    out = {"tunnels": 0, "plugs": [], "other_plugs": 0, "min_contrast_hu": None,
           "noise_hu": None}
    if surface_genus <= 0 or not inside.any():
        return out
    native = np.asarray(native_spacing, np.float64)
    sm = smooth_ct(ct, d, native) if smoothed is None else smoothed
    if noise is None:
        noise = soft_tissue_noise(sm, inside, soft)
    min_contrast = min(max_contrast, PLATE_NOISE_FACTOR * noise)
    out.update(min_contrast_hu=float(min_contrast), noise_hu=float(noise))
    depth = distance_outside(inside, d)
    cand = (sm >= soft + min_contrast) & ~inside & ~exclude & (depth <= reach_mm)
    for axis in range(3):
        cand[(slice(None),) * axis + ([0, -1],)] = False
    crest = np.zeros(inside.shape, bool)
    crest[tuple(_ridge_voxels(sm, cand, d, native, min_contrast).T)] = True
    del cand
    crest = dilate_cube(crest, 1) & ~inside & ~exclude
    found, masks = [], []
    for plug in _tunnel_plugs(inside, crest, depth <= 1.75 * d):
        idx = np.argwhere(plug)
        peak, contrast, thickness, plane = _across(sm, idx, d, native, cortex)
        wide = float(depth[plug].max()) >= PLATE_WINDOW * plane
        if wide and peak - soft >= min_contrast and contrast >= min_contrast \
                and thickness >= PLATE_MIN_MM:
            masks.append(plug)
            found.append({"voxels": int(len(idx)),
                          "centre": [float(c) for c in idx.mean(axis=0)[::-1] * d],
                          "hu_median": float(np.median(np.asarray(ct)[plug])),
                          "contrast_hu": float(contrast), "thickness_mm": float(thickness)})
        else:
            out["other_plugs"] += 1
    if not found:
        return out

    closed = inside.copy()
    tunnels = min(_tunnels(closed), int(surface_genus))
    kept = []
    for k in np.argsort([-p["voxels"] for p in found], kind="stable"):
        if tunnels <= 0:
            break
        g = _tunnels(closed | masks[k])
        if g < tunnels:
            closed |= masks[k]
            kept.append(found[k])
            out["tunnels"] += int(tunnels - g)
            tunnels = g
        else:
            out["other_plugs"] += 1
    out["plugs"] = kept
    if kept:
        out["mask"] = closed & ~inside
    return out


def _across(sm: np.ndarray, idx: np.ndarray, d: float, native: np.ndarray,
            cortex: float) -> tuple:
    """(peak, contrast, thickness, resolution in its plane) across a plug of voxels idx (k, 3)
    (z, y, x) of the smoothed CT ``sm``: along the plug's thinnest direction (its voxels'
    least principal axis; for a plug of fewer than four voxels, the Hessian's most negative
    direction at each), the peak within one voxel of each voxel, its height over the mean of
    the lowest values on either side within PLATE_WINDOW x the CT's resolution along that
    direction, and the bone it holds as a thickness of ``cortex`` (the blurred-slab model, as
    :func:`_ridges`) - medians over the plug's voxels; and the CT's resolution across the
    plug's plane (mm, the root mean square over its directions)."""
    pts = idx.astype(np.float64)
    if len(idx) >= 4:
        centred = pts - pts.mean(axis=0)
        normal = np.linalg.eigh(centred.T @ centred)[1][:, 0]      # z, y, x
        normals = np.repeat(normal[None, :], len(idx), axis=0)
    else:
        inner = np.all((idx > 0) & (idx < np.array(sm.shape) - 1), axis=1)
        if not inner.any():
            return -np.inf, -np.inf, 0.0, float(native.max())
        idx, pts = idx[inner], pts[inner]
        normals = _hessian_ridge(sm, idx, d)[1][:, ::-1]            # x-y-z -> z, y, x
    n2 = normals[:, ::-1] ** 2                                         # x, y, z
    res = float(np.median(np.sqrt((n2 * native[None, :] ** 2).sum(axis=1))))
    plane = float(np.median(np.sqrt(((1.0 - n2) * native[None, :] ** 2).sum(axis=1) / 2.0)))
    # (at least two voxels: the sides lie beyond the peak's voxel)
    window = max(PLATE_WINDOW * res, 2.0 * d)
    step = 0.5 * d
    t = np.arange(-window, window + 1e-9, step)
    samples = pts[:, None, :] + (t[None, :, None] / d) * normals[:, None, :]
    prof = ndimage.map_coordinates(sm, samples.reshape(-1, 3).T, order=1,
                                   mode="nearest").reshape(len(pts), len(t))
    peak = prof[:, np.abs(t) <= d].max(axis=1)
    il = np.argmin(np.where(t[None, :] < -d, prof, np.inf), axis=1)
    ir = np.argmin(np.where(t[None, :] > d, prof, np.inf), axis=1)
    bg, thickness = _slab_thickness(prof, il, ir, step, cortex)
    return (float(np.median(peak)), float(np.median(peak - bg)), float(np.median(thickness)),
            plane)


def _tunnel_plugs(occupancy: np.ndarray, adds: np.ndarray, near: np.ndarray) -> list:
    """The pieces of ``adds`` (z, y, x bool; 26-connected) that each close a tunnel of
    ``occupancy``: a piece touching it (``near``: the voxels 26-adjacent to it) whose addition
    alone raises the Euler characteristic (poisson.euler_number, counted with 26- or with
    6-connected voxels; additive, so counted on a window around the piece) by more than the
    cavities it encloses there (the characteristic counts components - tunnels + cavities: a
    piece that closes a pocket against the surface raises it too). Masks of the whole
    volume."""
    from .poisson import euler_number

    pieces, n = ndimage.label(adds, structure=np.ones((3, 3, 3), bool))
    if not n:
        return []
    # a piece of its own closes no tunnel (it adds a component)
    touching = np.zeros(n + 1, bool)
    touching[np.unique(pieces[near & adds])] = True
    found = []
    for i, box in enumerate(ndimage.find_objects(pieces), start=1):
        if box is None or not touching[i]:
            continue
        win = tuple(slice(max(0, b.start - 2), min(s, b.stop + 2))
                    for b, s in zip(box, occupancy.shape))
        piece = pieces[win] == i
        before = occupancy[win]
        after = before | piece
        for c in (26, 6):
            rise = euler_number(after, c) - euler_number(before, c)
            if rise > 0 and rise > _cavities(after, c) - _cavities(before, c):
                mask = np.zeros(occupancy.shape, bool)
                mask[win] = piece
                found.append(mask)
                break
    return found


def _tunnels(mask: np.ndarray) -> int:
    """Tunnels of the 26-connected voxels of ``mask`` (z, y, x bool), all its pieces together:
    components + cavities - Euler characteristic."""
    from .poisson import euler_number

    pieces = ndimage.label(mask, structure=np.ones((3, 3, 3), bool))[1]
    return int(pieces + _cavities(mask, 26) - euler_number(mask, 26))


def _cavities(mask: np.ndarray, connectivity: int) -> int:
    """Pieces of the complement of ``mask`` (z, y, x bool) that do not reach the array's faces
    (6-connected for 26-connected voxels, and 26- for 6-)."""
    structure = ndimage.generate_binary_structure(3, 1 if connectivity == 26 else 3)
    holes, n = ndimage.label(~mask, structure=structure)
    if not n:
        return 0
    faces = np.concatenate([holes[[0, -1]].ravel(), holes[:, [0, -1]].ravel(),
                            holes[:, :, [0, -1]].ravel()])
    return int(n - len(np.unique(faces[faces > 0])))


def _ridge_voxels(sm: np.ndarray, cand: np.ndarray, d: float, native: np.ndarray,
                  min_contrast: float) -> np.ndarray:
    """Of candidate voxels ``cand`` (z, y, x bool, not on the array's faces): those on a bright
    sheet's crest - one strongly negative Hessian eigenvalue (PLATE_SHEETNESS), the sub-voxel
    maximum along its eigenvector within the voxel - standing at least ``min_contrast`` above
    the lowest values on both sides within PLATE_WINDOW x the CT's resolution along it (as
    :func:`_ridges`, without the thickness bounds: any plate counts). (k, 3) z, y, x."""
    idx = np.argwhere(cand & _local_peaks(sm))
    kept = []
    for a in range(0, len(idx), CHUNK):
        part = idx[a:a + CHUNK]
        lam, e, delta = _hessian_ridge(sm, part, d)
        ok = (lam[:, 0] < 0) & (lam[:, 1] > PLATE_SHEETNESS * lam[:, 0]) & \
            (np.abs(delta) <= 0.5 * d * np.abs(e).sum(axis=1))
        part, e = part[ok], e[ok]
        if not len(part):
            continue
        res = np.sqrt(((e * native[None, :]) ** 2).sum(axis=1))
        window = np.maximum(PLATE_WINDOW * res, 2.0 * d)
        t = np.arange(-float(window.max()), float(window.max()) + 1e-9, 0.5 * d)
        samples = part[:, None, :].astype(np.float64) + (t[None, :, None] / d) * e[:, None, ::-1]
        prof = ndimage.map_coordinates(sm, samples.reshape(-1, 3).T, order=1,
                                       mode="nearest").reshape(len(part), len(t))
        within = np.abs(t)[None, :] <= window[:, None]
        centre = prof[:, np.argmin(np.abs(t))]
        left = np.where(within & (t[None, :] < -d), prof, np.inf).min(axis=1)
        right = np.where(within & (t[None, :] > d), prof, np.inf).min(axis=1)
        kept.append(part[centre - 0.5 * (left + right) >= min_contrast])
    return np.concatenate(kept) if kept else np.zeros((0, 3), np.int64)


# The tissue around a process of the segment: this many voxels beyond the segment (and the
# bone) around it.
PROCESS_SHELL_VOXELS = 2
# A process's ridge level: this percentile of the smoothed CT over its voxels.
PROCESS_PEAK_PERCENTILE = 90


def segment_processes(label: np.ndarray, bone: np.ndarray, sm: np.ndarray, spacing: float, *,
                      reach_mm: float, margin_mm: float, soft: float, min_contrast: float
                      ) -> tuple:
    """Thin processes of the segment beyond the thresholded bone that the CT shows as a faint
    bright structure: a tail, a process tip or a rib's end thinner than the CT resolves, whose
    blurred cortex stays below HT (the thresholds hold none or only crumbs of it), so the
    surface would stop short of it by up to its length.

    A part of the segment counts when it reaches farther than ``reach_mm`` from the main piece
    of ``bone`` (farther than a segment this coarse misplaces the bone's border; a generous
    margin does not), and the CT supports it: on the smoothed CT its ridge (the
    PROCESS_PEAK_PERCENTILE-th percentile of its voxels) is above the soft tissue's level
    ``soft``, and its mean stands at least ``min_contrast`` above the mean of the tissue just
    outside the segment around it; and it is a process: at most 2 ``margin_mm`` across in the
    segment (a bone's larger part beyond a gap is no process), and in one piece of the segment
    with the bone. A part of the segment into soft tissue (a leak along a muscle), fat or a
    dark canal is not joined. What is joined is the part beyond ``margin_mm`` of the bone (the
    segment's margin, where the bone's own surface decides) with the segment's voxels that
    join it to the bone, and its stem (:func:`_process_stems`: the segment along the crumbs of
    thresholded bone that the process goes on from, to where the segment widens).

    Parameters
    ----------
    label, bone : (z, y, x) bool arrays
        The bone's segment and its thresholded bone (filled) on a box of the working grid.
    sm : (z, y, x) float array
        The smoothed CT (HU) on the same box (:func:`smooth_ct`).
    spacing : float
        Working voxel size (mm).
    reach_mm, margin_mm : float
        How far a process reaches at least, and the segment's margin (mm).
    soft, min_contrast : float
        The soft-tissue level and the least contrast (HU).

    Returns
    -------
    (mask, records): the processes' voxels (z, y, x bool, same shape) and one dict each
    (``voxels``, ``reach_mm``, ``peak_hu``, ``contrast_hu``, ``at``: its farthest voxel, x-y-z
    mm of the box; where the CT supports it ``across_mm`` and ``attached``), joined or not
    (``joined``).
    """
    from ..mesh.distance import distance_inside, distance_outside

    d = float(spacing)
    out = np.zeros(label.shape, bool)
    pieces, n = ndimage.label(bone, structure=np.ones((3, 3, 3), bool))
    if not n:
        return out, []
    main = pieces == (int(np.argmax(np.bincount(pieces.ravel())[1:])) + 1)
    del pieces
    rest = label & ~bone
    if not rest.any():
        return out, []
    dist = distance_outside(main) * d
    beyond = rest & (dist > margin_mm)
    if not (beyond & (dist > reach_mm)).any():
        return out, []
    parts, _ = ndimage.label(beyond, structure=np.ones((3, 3, 3), bool))
    reaching = np.unique(parts[beyond & (dist > reach_mm)])
    records = []
    boxes = ndimage.find_objects(parts)
    depth = pieces = with_bone = along = None
    steps = int(np.ceil(margin_mm / d)) + 1  # back through the segment's margin to the bone
    for j in reaching[reaching > 0]:
        grow = max(PROCESS_SHELL_VOXELS, steps) + 1
        box = tuple(slice(max(s.start - grow, 0), min(s.stop + grow, n_)) for s, n_ in
                    zip(boxes[j - 1], label.shape))
        part = parts[box] == j
        shell = dilate_cube(part, PROCESS_SHELL_VOXELS) & ~label[box] & ~bone[box]
        vals = sm[box][part]
        # Its ridge: the segment is wider than a process thinner than the CT resolves, and its
        # voxels beside the ridge are the tissue around it.
        peak = float(np.percentile(vals, PROCESS_PEAK_PERCENTILE))
        contrast = float(vals.mean() - sm[box][shell].mean()) if shell.any() else 0.0
        at = np.argwhere(part)[np.argmax(dist[box][part])] + [s.start for s in box]
        rec = {"voxels": int(part.sum()), "reach_mm": float(dist[box][part].max()),
               "peak_hu": peak, "contrast_hu": contrast,
               "at": [float(v) for v in at[::-1] * d], "joined": False}
        records.append(rec)
        if not (peak > soft and contrast >= min_contrast):
            continue  # the CT does not show it as bone (the tests below cost more)
        if depth is None:
            # how deep in the segment: a process is at most about two of its voxels across
            depth = distance_inside(np.pad(label, 1))[1:-1, 1:-1, 1:-1] * d
            # attached: in a piece of the segment with the bone (crumbs of bone the thresholds
            # hold along a faint process split it into parts, each attached)
            pieces, _ = ndimage.label(label | main, structure=np.ones((3, 3, 3), bool))
            with_bone = np.unique(pieces[main])
            along = label & ~main
        rec["across_mm"] = float(2.0 * depth[box][part].max())
        rec["attached"] = bool(np.isin(pieces[box][part][0], with_bone))
        if rec["attached"] and rec["across_mm"] <= 2.0 * margin_mm:
            rec["joined"] = True
            # the segment's voxels that join it to the bone: grown back through the margin
            out[box] |= ndimage.binary_dilation(part, structure=np.ones((3, 3, 3), bool),
                                                iterations=steps, mask=along[box]) | part
    if out.any():
        out |= _process_stems(out, label, along, depth, margin_mm, steps,
                              int(np.ceil(reach_mm / d)))
    return out, records


def _process_stems(process: np.ndarray, label: np.ndarray, along: np.ndarray,
                   depth: np.ndarray, margin_mm: float, steps: int, reach: int) -> np.ndarray:
    """The segment's voxels that carry a joined process back to where the segment widens into
    the bone. Crumbs of thresholded bone along a faint process are 26-connected to the bone,
    so the segment around them lies within the margin of "the bone" and the process is joined
    only beyond their end: the surface would pinch to the crumbs there. Added: the segment
    within ``reach`` voxels of the process through voxels where it is a process all around
    (none within ``steps`` deeper in it than ``margin_mm``: a process is at most 2
    ``margin_mm`` across), and from there, as from the process, ``steps`` voxels back through
    the segment beside the bone (``along``) to the bone. (z, y, x) bool; ``depth``: the
    segment's depth (mm)."""
    idx = np.argwhere(process)
    grow = reach + 2 * steps
    lo = np.maximum(idx.min(0) - grow, 0)
    hi = np.minimum(idx.max(0) + grow + 1, process.shape)
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    cube = np.ones((3, 3, 3), bool)
    thin = label[box] & (ndimage.maximum_filter(depth[box], size=2 * steps + 1) <= margin_mm)
    stem = ndimage.binary_dilation(process[box], structure=cube, iterations=reach, mask=thin)
    out = np.zeros(process.shape, bool)
    out[box] = ndimage.binary_dilation(stem, structure=cube, iterations=steps,
                                       mask=along[box] | stem) & ~process[box]
    return out

