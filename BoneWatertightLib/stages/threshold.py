"""Stage 3: two-step thresholding with morphology (paper §2.1) and the constraint points.

W_H0 = [H0, theta_max] and W_HT = [HT, theta_max]. Bone k is the part of W_H0 that the rough
segment points at. If W_H0 still joins bone k to a neighbour, we erode (6-connected, one voxel at
a time, at most m times) until the component under the segment no longer spills out of the
segment's region. The paper then dilates back m times and intersects with W_H0; plain dilation
would re-grow across the bridge it just cut, so we let bone k and its neighbours grow back
*competitively*: every W_H0 voxel within m voxels goes to the nearest eroded seed (ties to bone k).
The same competition, seeded by the H0 result, decides which W_HT voxels belong to bone k, which
keeps a cartilage-filled joint gap from becoming a bridge. Finally opening (l) and closing (n).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from ..errors import SeparationError, ThresholdError

SIX = ndimage.generate_binary_structure(3, 1)

# Closing of the rough segment (fills its missing chunks up to ~2x this), and its cap relative
# to the segment's largest extent for small bones whose neighbours sit closer.
REGION_CLOSE_MM = 10.0
REGION_CLOSE_FRACTION = 0.15
# Cap of segment_dilation relative to the segment's largest extent.
REGION_DILATE_FRACTION = 0.1
# Grid step (mm) on which the segment region is computed.
REGION_COARSE_MM = 2.0
# "Near the segment": the segment dilated by this much (mm).
SEGMENT_NEAR_MM = 1.5
# Erosion stops when the component under the segment keeps less than this fraction of itself.
DISSOLVE_FRACTION = 0.2
# Separated: at least this fraction of the component lies inside the segment's region.
SEPARATED_FRACTION = 0.85
# Below this fraction after the best erosion: SeparationError.
MIN_SEPARATED_FRACTION = 0.5
# A fragment is bone k when this fraction lies in the region and NEAR_FRACTION near the segment.
FRAGMENT_IN_REGION_FRACTION = 0.5
FRAGMENT_NEAR_FRACTION = 0.2
# An H0 piece that no seed reached joins bone k when this fraction of it is near the segment.
UNREACHED_NEAR_FRACTION = 0.5
# Competitive regrowth of the H0 mask: at least this many mm.
H0_REGROW_MM = 4.0
# HT voxels are assigned within this distance (mm, and at least as many voxels) of the H0 bone.
HT_GROW_MM = 3.0
# Ball radius (mm) of the closing that plugs pores before the cavities are filled.
SOLIDIFY_RADIUS_MM = 1.5


@dataclass
class ThresholdResult:
    w_h0: np.ndarray        # bool, bone k at [H0, theta_max] after morphology
    w_ht: np.ndarray        # bool, bone k at [HT, theta_max] after morphology
    occupancy: np.ndarray   # bool, filled bone k (inside / outside decisions)
    roi: np.ndarray         # bool, region the rough segment points at
    info: dict = field(default_factory=dict)
    solid_h0: np.ndarray = None  # bool, w_h0 with pores plugged and cavities filled


def _block_any(mask: np.ndarray, f: int) -> np.ndarray:
    if f == 1:
        return mask.copy()
    pad = [(0, (-s) % f) for s in mask.shape]
    m = np.pad(mask, pad)
    z, y, x = (s // f for s in m.shape)
    return m.reshape(z, f, y, f, x, f).any(axis=(1, 3, 5))


def segment_region(segment: np.ndarray, spacing: float, close_mm: float = REGION_CLOSE_MM,
                   dilate_mm: float = 3.0) -> np.ndarray:
    """Closed and dilated rough segment: fills its holes and missing chunks up to ~2*close_mm.

    Computed on a ~2 mm grid with distance maps, because a 6 mm closing at 0.5 mm is costly.

    Parameters
    ----------
    segment : (z, y, x) bool array
    spacing : float
        Voxel size in mm.
    close_mm, dilate_mm : float

    Returns
    -------
    (z, y, x) bool array
    """
    f = max(1, int(round(REGION_COARSE_MM / spacing)))
    cs = spacing * f
    coarse = _block_any(segment, f)
    pad = int(np.ceil((close_mm + dilate_mm) / cs)) + 2
    coarse = np.pad(coarse, pad)
    d_out = ndimage.distance_transform_edt(~coarse) * cs
    dilated = d_out <= close_mm
    d_in = ndimage.distance_transform_edt(dilated) * cs
    closed = (d_in > close_mm) | coarse
    closed = ndimage.binary_fill_holes(closed)
    d_closed = ndimage.distance_transform_edt(~closed) * cs
    region = d_closed <= dilate_mm
    region = region[pad:-pad, pad:-pad, pad:-pad]
    idx = [np.minimum(np.arange(s) // f, region.shape[a] - 1) for a, s in enumerate(segment.shape)]
    return region[np.ix_(*idx)]


def _components(mask: np.ndarray, roi: np.ndarray):
    lab, n = ndimage.label(mask, structure=SIX)
    size = np.bincount(lab.ravel(), minlength=n + 1)
    inroi = np.bincount(lab[roi], minlength=n + 1)
    size[0] = 0
    inroi[0] = 0
    return lab, n, size, inroi


def _competitive_assign(candidates: np.ndarray, bone_seed: np.ndarray, other_seed: np.ndarray,
                        max_steps: float) -> np.ndarray:
    """Voxels of ``candidates`` that bone_seed reaches before other_seed, growing both one
    6-connected voxel per step through the candidates (ties go to bone k), at most max_steps.

    A geodesic competition: cheaper than two distance maps, and a neighbour cannot claim voxels
    through a gap that only a straight line would cross."""
    own = bone_seed.copy()
    other = other_seed & ~own
    steps = int(max_steps) if np.isfinite(max_steps) else 10 ** 6
    for _ in range(steps):
        grow = ndimage.binary_dilation(own, structure=SIX) & candidates & ~own & ~other
        grow_other = ndimage.binary_dilation(other, structure=SIX) & candidates & ~own & ~other & ~grow
        if not grow.any() and not grow_other.any():
            break
        own |= grow
        other |= grow_other
    return own & candidates


def _keep_connected_to(mask: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    lab, n = ndimage.label(mask, structure=SIX)
    if n <= 1:
        return mask
    keep = np.zeros(n + 1, dtype=bool)
    keep[np.unique(lab[anchor & mask])] = True
    keep[0] = False
    return keep[lab]


def two_step_threshold(ct_f: np.ndarray, segment: np.ndarray, spacing: float, *,
                       h0: float = 300.0, ht: float = 150.0, theta_max: float = 2500.0,
                       max_erosions: int = 3, opening: int = 1, closing: int = 2,
                       segment_dilation: float = 3.0, progress=None) -> ThresholdResult:
    """Bone k's masks at [H0, theta_max] and [HT, theta_max], separated from its neighbours.

    Parameters
    ----------
    ct_f : (z, y, x) float array
        Filtered CT in HU on the isotropic working grid.
    segment : (z, y, x) bool array
        The rough segment on the same grid.
    spacing : float
        Voxel size d in mm.
    h0, ht, theta_max : float
        Threshold windows W_H0 = [h0, theta_max] and W_HT = [ht, theta_max] in HU.
    max_erosions : int
        m, the most erosions tried to separate bone k.
    opening, closing : int
        l and n, iterations of the final opening and closing.
    segment_dilation : float
        How far (mm) bone k may extend beyond the segment's closed region.
    progress : callable, optional
        ``progress(fraction, message)``.

    Returns
    -------
    ThresholdResult
        Boolean (z, y, x) masks on the working grid and an ``info`` dict for the report.
    """
    tmax = theta_max
    # Closing fills missing chunks of the rough segment up to ~2 x 10 mm, less for small bones
    # whose neighbours sit closer than that (0.15 x the segment's largest extent).
    nzs = np.nonzero(segment.any(axis=(1, 2)))[0], np.nonzero(segment.any(axis=(0, 2)))[0], \
        np.nonzero(segment.any(axis=(0, 1)))[0]
    extent = max((a.max() - a.min() + 1) for a in nzs) * spacing
    roi = segment_region(segment, spacing,
                         close_mm=min(REGION_CLOSE_MM, REGION_CLOSE_FRACTION * extent),
                         dilate_mm=min(segment_dilation, REGION_DILATE_FRACTION * extent))
    w0 = (ct_f >= h0) & (ct_f <= tmax)
    wt = (ct_f >= ht) & (ct_f <= tmax)
    seg_vals = ct_f[segment]
    if not wt[segment].any():
        raise ThresholdError(
            f"No voxel of the segment region lies in [HT, theta_max] = [{ht:g}, {tmax:g}] HU "
            f"(segment HU range {seg_vals.min():.0f} to {seg_vals.max():.0f}): lower HT or check "
            "that the volume is a CT in Hounsfield units.")
    if not w0[segment].any():
        raise ThresholdError(
            f"No voxel of the segment region lies in [H0, theta_max] = [{h0:g}, {tmax:g}] HU "
            f"(segment HU up to {seg_vals.max():.0f}): lower H0 (it must stay above HT).")
    if progress:
        progress(0.1, "thresholds")

    # Near the segment itself (no closing): a neighbour lies mostly outside this, while bone k's
    # parts that the rough segment missed still lie inside the closed region ``roi``.
    seg_near = ndimage.binary_dilation(segment, structure=SIX,
                                       iterations=max(1, int(round(SEGMENT_NEAR_MM / spacing))))
    eroded = w0
    stats = []
    levels = []
    chosen = None
    for e in range(0, max_erosions + 1):
        if e > 0:
            eroded = ndimage.binary_erosion(eroded, structure=SIX)
        lab, n, size, inroi = _components(eroded, roi)
        near = np.bincount(lab[seg_near], minlength=n + 1)
        near[0] = 0
        if n == 0 or near.max() == 0:
            break
        main = int(np.argmax(near))
        frac = inroi[main] / size[main]
        # Too much erosion dissolves thin or low-density bone (3 mm CT, vertebrae): stop before
        # the component under the segment loses most of itself.
        if levels and size[main] < DISSOLVE_FRACTION * levels[0][2][levels[0][5]]:
            stats.append({"erosions": e, "main_voxels": int(size[main]), "stopped": "bone dissolves"})
            break
        stats.append({"erosions": e, "components": int(n), "main_voxels": int(size[main]),
                      "main_fraction_in_region": float(frac)})
        levels.append((lab, n, size, inroi, near, main, frac))
        if progress:
            progress(0.1 + 0.3 * (e + 1) / (max_erosions + 1), f"erosion {e}")
        # Spilling out of the segment's region by less than 15 % is bone k's own surface near a
        # rough segment border, not a neighbour.
        if frac >= SEPARATED_FRACTION:
            chosen = len(levels) - 1
            break
    if not levels:
        raise ThresholdError("Nothing of the bone under the segment is in [H0, theta_max]: lower H0.")
    if chosen is None:
        # Not separated by erosion alone: take the level that separated best. The competition
        # below still stops at the neighbours' seeds outside the segment's region.
        chosen = int(np.argmax([lv[6] for lv in levels]))
    lab, n, size, inroi, near, main, frac = levels[chosen]
    separated_at = chosen
    if frac < MIN_SEPARATED_FRACTION:
        raise SeparationError(
            f"After {len(levels) - 1} erosions the bone under the segment is still joined to a "
            f"neighbour ({100 * (1 - frac):.0f} % of it lies outside the segment's region). Try: raise H0 "
            f"(now {h0:g} HU), raise max_erosions (now {max_erosions}), use a finer resample "
            "spacing, or draw the rough segment over more of the bone.")
    # Bone k: every piece mostly inside the segment's region (thin bone breaks into fragments).
    is_bone = ((inroi >= FRAGMENT_IN_REGION_FRACTION * size) & (near >= FRAGMENT_NEAR_FRACTION * size)
               & (size > 0))
    is_bone[main] = True
    is_bone[0] = False
    bone_seed = is_bone[lab]
    # Neighbours: the other pieces, and every H0 voxel outside the segment's region.
    other_seed = ((lab > 0) & ~bone_seed) | (w0 & ~roi)
    if progress:
        progress(0.5, "competitive dilation")
    w_h0 = _competitive_assign(w0, bone_seed, other_seed, max(separated_at + 1, H0_REGROW_MM / spacing))
    w_h0 = _keep_connected_to(w_h0, bone_seed)
    # H0 pieces that no seed reached (isolated fragments) belong to bone k when they lie in its
    # region and touch the segment.
    lab_u, n_u = ndimage.label(w0 & ~w_h0 & roi, structure=SIX)
    if n_u:
        sz = np.bincount(lab_u.ravel(), minlength=n_u + 1)
        nr = np.bincount(lab_u[seg_near], minlength=n_u + 1)
        touch_other = np.zeros(n_u + 1, dtype=bool)
        touch_other[np.unique(lab_u[ndimage.binary_dilation(other_seed, structure=SIX) & (lab_u > 0)])] = True
        add = (nr >= UNREACHED_NEAR_FRACTION * sz) & ~touch_other
        add[0] = False
        w_h0 |= add[lab_u]
    # The neighbours' H0 voxels: the rest of W_H0 in components that hold a neighbour seed.
    rest = w0 & ~w_h0
    lab_rest, n_rest = ndimage.label(rest, structure=SIX)
    has_seed = np.zeros(n_rest + 1, dtype=bool)
    has_seed[np.unique(lab_rest[other_seed & rest])] = True
    has_seed[0] = False
    neighbours_h0 = has_seed[lab_rest]
    # HT voxels of bone k: reached from bone k's H0 voxels before a neighbour's, within 3 mm.
    grow_vox = max(HT_GROW_MM, HT_GROW_MM / spacing)
    w_ht = _competitive_assign(wt, w_h0, neighbours_h0, grow_vox) | w_h0
    w_ht = _keep_connected_to(w_ht, w_h0)
    if progress:
        progress(0.75, "opening / closing")
    w_h0 = _open_close(w_h0, opening, closing)
    w_ht = _open_close(w_ht, opening, closing) | w_h0
    if not w_h0.any():
        raise ThresholdError(
            "Opening removed the whole bone at H0: lower the opening iterations (l) or H0.")
    # Solid versions: marrow and pores connect to the outside through the porous trabecular ends,
    # so a plain fill leaves them open and far views see the inner cortical wall through the
    # pores. A ~1.5 mm closing plugs the pores, then the fill makes the bone solid; only its
    # outer boundary feeds the visible-point extraction and the inside/outside decisions.
    solid_h0 = solidify(w_h0, spacing)
    occupancy = solidify(w_ht | solid_h0, spacing)
    info = {
        "erosions_used": int(separated_at),
        "erosion_steps": stats,
        "voxels_h0": int(w_h0.sum()),
        "voxels_ht": int(w_ht.sum()),
        "neighbour_voxels_h0": int(neighbours_h0.sum()),
    }
    if progress:
        progress(1.0, "thresholding done")
    return ThresholdResult(w_h0=w_h0, w_ht=w_ht, occupancy=occupancy, roi=roi, info=info,
                           solid_h0=solid_h0)


def _open_close(mask: np.ndarray, opening: int, closing: int) -> np.ndarray:
    # Paper: Open^l . Close^n (closing first fills pores, opening then removes spurs).
    out = mask
    if closing:
        pad = closing + 1
        out = np.pad(out, pad)
        out = ndimage.binary_closing(out, structure=SIX, iterations=closing)
        out = out[pad:-pad, pad:-pad, pad:-pad]
    if opening:
        opened = ndimage.binary_opening(out, structure=SIX, iterations=opening)
        # Opening must not cut the bone into pieces: keep what it removed where that happens.
        out = opened if opened.any() else out
    return out


def solidify(mask: np.ndarray, spacing: float, radius_mm: float = SOLIDIFY_RADIUS_MM) -> np.ndarray:
    """Closing with a ~radius_mm ball (18-connected steps), then hole filling."""
    steps = max(1, int(round(radius_mm / spacing)))
    struct = ndimage.generate_binary_structure(3, 2)
    pad = steps + 1
    out = np.pad(mask, pad)
    out = ndimage.binary_closing(out, structure=struct, iterations=steps)
    out = out[pad:-pad, pad:-pad, pad:-pad] | mask
    return ndimage.binary_fill_holes(out)


def boundary_voxels(mask: np.ndarray) -> np.ndarray:
    """Voxels of mask with at least one 6-neighbour outside it."""
    return mask & ~ndimage.binary_erosion(mask, structure=SIX, border_value=0)


def voxel_points(mask: np.ndarray, spacing: float) -> np.ndarray:
    """Voxel centres of a (z, y, x) mask as (k, 3) x-y-z points in grid millimetres."""
    idx = np.nonzero(mask)
    return np.stack([idx[2], idx[1], idx[0]], axis=1).astype(np.float64) * spacing


def crossing_points(values: np.ndarray, inside: np.ndarray, level: float, spacing: float) -> np.ndarray:
    """Sub-voxel points where the image crosses ``level`` between an inside and an outside voxel.

    Only grid edges that leave ``inside`` are used, so the points lie on bone k's outer boundary
    (the marching-cubes vertex positions of the HT isosurface restricted to bone k)."""
    pts = []
    for axis in range(3):
        for step in (1, -1):
            out_nb = np.roll(inside, -step, axis=axis)
            # np.roll wraps around; the working grid has a margin, so border voxels are outside.
            sl = [slice(None)] * 3
            sl[axis] = slice(-1, None) if step == 1 else slice(0, 1)
            out_nb[tuple(sl)] = True
            edge = inside & ~out_nb
            idx = np.nonzero(edge)
            if len(idx[0]) == 0:
                continue
            nb = list(idx)
            nb[axis] = nb[axis] + step
            f_in = values[idx]
            f_out = values[tuple(nb)]
            denom = f_in - f_out
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.where((f_in >= level) & (f_out < level) & (denom > 0),
                             (f_in - level) / denom, 0.5)
            t = np.clip(t, 0.0, 1.0)
            p = np.stack([idx[2], idx[1], idx[0]], axis=1).astype(np.float64)
            p[:, 2 - axis] += step * t
            pts.append(p * spacing)
    if not pts:
        return np.zeros((0, 3))
    return np.concatenate(pts)
