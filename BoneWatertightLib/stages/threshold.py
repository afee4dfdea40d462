"""Stage 3b: the two-step threshold windows of one bone (paper §2.1) and its constraint points.

W_H0 = [H0, theta_max] and W_HT = [HT, theta_max], each restricted to the voxels that bone k
owns (:mod:`.ownership`: the segment as evidence, the neighbours as competitors) and joined by
k's core (what the segment clearly covers is bone whatever its HU). The paper separates bone k
from its neighbours by eroding W_H0 until they disconnect; here the competition of
:mod:`.ownership` separates them (by the CT's valley where the erosion cannot), and
:func:`erosions_to_separate` still measures whether the paper's erosion alone would have done
it (reported per bone). Then the paper's closing (n) and opening (l); pores are plugged and
cavities filled for the inside/outside decisions.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from ..mesh.distance import distance_inside, distance_outside
from .prepare import bbox_slices
from ..threads import cpu_threads, thread_map

SIX = ndimage.generate_binary_structure(3, 1)

# Grid step (mm) on which the segment region is computed.
REGION_COARSE_MM = 2.0
REGION_CLOSE_MM = 10.0
# Ball radius (mm) of the closing that plugs pores before the cavities are filled.
SOLIDIFY_RADIUS_MM = 1.5
# Parts of W_HT deeper than this (mm) beyond W_H0 are out of the deformation's reach: they join
# the Poisson input (low-density bone the segment covers: thin processes, vertebral bodies).
REACH_MM = 1.0
# Margin (mm) of a bone's working box around what it owns.
BOX_MARGIN_MM = 4.0


@dataclass
class BoneMasks:
    """The threshold masks of one bone, on its box ``box`` (slices of the working grid).

    Arrays are (z, y, x) bool on the box; ``origin`` is the box corner in grid millimetres
    (x, y, z). ``w_h0``/``w_ht``: the two windows of bone k after morphology; ``solid_h0``:
    W_H0 with pores plugged, cavities filled and the out-of-reach part of W_HT joined (the
    visible-point candidates come from W_H0's own boundary joined by ``far``, the part of the
    filled W_HT out of the deformation's reach of W_H0); ``occupancy``: the filled bone at HT.
    """

    box: tuple
    origin: np.ndarray
    w_h0: np.ndarray
    w_ht: np.ndarray
    solid_h0: np.ndarray
    occupancy: np.ndarray
    far: np.ndarray = None
    info: dict = field(default_factory=dict)


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
    d_out = distance_outside(coarse) * cs
    dilated = d_out <= close_mm
    d_in = distance_inside(dilated) * cs
    closed = (d_in > close_mm) | coarse
    closed = fill_holes(closed)
    d_closed = distance_outside(closed) * cs
    region = d_closed <= dilate_mm
    region = region[pad:-pad, pad:-pad, pad:-pad]
    idx = [np.minimum(np.arange(s) // f, region.shape[a] - 1) for a, s in enumerate(segment.shape)]
    return region[np.ix_(*idx)]




def bone_masks(ct: np.ndarray, owner: np.ndarray, cores: np.ndarray, labels: np.ndarray,
               k: int, spacing: float, *, h0: float, theta_max: float, coarseness: float,
               opening: int, closing: int, unsupported: np.ndarray = None,
               fallbacks=None, foreground: np.ndarray = None) -> BoneMasks:
    """W_H0, W_HT and their solid versions for bone k (label index ``k``).

    Parameters
    ----------
    ct : (z, y, x) float array
        The filtered CT (HU) on the working grid.
    owner, cores, labels : (z, y, x) uint arrays
        From :func:`.ownership.compute_ownership` and the label index map.
    k : int
        Label index of the bone.
    spacing : float
        Voxel size d in mm.
    h0, theta_max : float
        The initial window [H0, theta_max] (HU).
    coarseness : float
        The segmentation's coarseness (mm): inside k's label, gaps of the cortex up to about
        twice this are closed (partial volume breaks thin cortex on thick slices).
    opening, closing : int
        l and n of the paper.
    unsupported : (z, y, x) bool array, optional
        Parts of the labels that the CT shows to be soft tissue (:func:`.ownership.unsupported_parts`):
        the label-restricted closing does not fill them.
    foreground : (z, y, x) bool array, optional
        The bone evidence F of :func:`.ownership.compute_ownership`: with it, the closing also
        fills the label's voxels between bone k and its neighbours' bone outside F.
    fallbacks : BoneWatertightLib.report.FallbackLog, optional
        Notes an opening skipped because it would empty a window.
    """
    owned_all = owner == k
    core_all = cores == k
    lab_all = labels == k
    box = bbox_slices(owned_all | core_all | lab_all,
                      int(np.ceil(BOX_MARGIN_MM / spacing)) + max(opening, closing) + 2)
    owned, core, lab_k = owned_all[box], core_all[box], lab_all[box]
    ctb = ct[box]
    strong = (ctb >= h0) & (ctb <= theta_max)
    r = max(1, int(round(coarseness / spacing)))

    def close(mask):
        pad = r + 1
        return erode6(dilate6(np.pad(mask, pad), r), r)[pad:-pad, pad:-pad, pad:-pad]

    closed = close(owned | core)
    others = None if foreground is None else (owner[box] > 0) & (owner[box] != k)
    if others is not None and others.any():
        # Against the neighbours' bone too: where a joint's two cortices blur into one band
        # (no joint space seen) that the neighbour owns, the label's low-HU bone between its
        # core and that band lies between bone on both sides, not outside the bone (a sacrum
        # at the sacro-iliac joint on 2.5 mm slices) - but never bone evidence that nobody
        # owns (a joint space the CT shows is such evidence, kept out of every bone).
        closed |= close(owned | core | others) & ~foreground[box]
    trusted = lab_k if unsupported is None else lab_k & ~unsupported[box]
    owned = owned | (closed & trusted & (owner[box] == 0))
    w_h0, w_ht = _open_close_both(((owned & strong) | core, "W_H0"), (owned | core, "W_HT"),
                                  opening, closing, fallbacks)
    w_ht |= w_h0
    solid_h0 = solidify(w_h0, spacing)
    occupancy = solidify(w_ht | solid_h0, spacing)
    far = erode6(occupancy, max(1, int(round(REACH_MM / spacing))))
    solid_h0 |= far
    origin = np.array([s.start for s in box][::-1], dtype=np.float64) * spacing
    info = {"voxels_h0": int(w_h0.sum()), "voxels_ht": int(w_ht.sum()),
            "voxels_core": int(core.sum()), "voxels_out_of_reach": int((far & ~w_h0).sum())}
    return BoneMasks(box=box, origin=origin, w_h0=w_h0, w_ht=w_ht, solid_h0=solid_h0,
                     occupancy=occupancy, far=far, info=info)


def erosions_to_separate(ct: np.ndarray, owner: np.ndarray, k: int, spacing: float, *,
                         h0: float, theta_max: float, step_voxels: int,
                         max_erosions: int) -> "int | None":
    """The paper's separation test: how many erosions (each ``step_voxels`` working voxels,
    i.e. one voxel of the CT) of W_H0 disconnect bone k's owned H0 voxels from every other
    bone's; 0 when they are apart already, None when ``max_erosions`` do not separate them."""
    mine = owner == k
    if not mine.any():
        return None
    box = bbox_slices(mine, 2 * step_voxels * max_erosions + 2)
    ctb = ct[box]
    w = (ctb >= h0) & (ctb <= theta_max) & (owner[box] > 0)
    mine_b, others = mine[box] & w, w & ~mine[box]
    if not others.any():
        return 0
    for e in range(max_erosions + 1):
        if e:
            w = erode6(w, step_voxels)
        lab, _ = ndimage.label(w, structure=SIX)
        a = np.unique(lab[mine_b & w])
        b = np.unique(lab[others & w])
        a, b = a[a > 0], b[b > 0]
        if len(a) == 0:
            return None
        if not np.intersect1d(a, b).size:
            return e
    return None


def paste_box(entry: tuple, win: tuple):
    """A (box, mask) entry - slices of a grid and a bool mask on them - on the window ``win``
    (slices of the same grid): bool, the window's shape; None when they do not meet."""
    box, sub = entry
    inter = [slice(max(b.start, w.start), min(b.stop, w.stop)) for b, w in zip(box, win)]
    if any(i.start >= i.stop for i in inter):
        return None
    out = np.zeros(tuple(w.stop - w.start for w in win), bool)
    out[tuple(slice(i.start - w.start, i.stop - w.start) for i, w in zip(inter, win))] = \
        sub[tuple(slice(i.start - b.start, i.stop - b.start) for i, b in zip(inter, box))]
    return out


def dilate_cube(mask: np.ndarray, steps: int) -> np.ndarray:
    """``mask`` dilated by ``steps`` steps of the 3 x 3 x 3 cube, nothing beyond the border: a
    separable maximum over a cube of 2 ``steps`` + 1 voxels - the voxels of scipy's iterated
    binary dilation, at a cost that does not grow with ``steps``. (z, y, x) bool."""
    if steps <= 0:
        return mask.astype(bool, copy=True)
    return ndimage.maximum_filter(np.asarray(mask, bool).view(np.uint8), size=2 * int(steps) + 1,
                                  mode="constant", cval=0).astype(bool)


def _axis_halves(axis: int, ndim: int) -> tuple:
    """(the array without its first slice along ``axis``, without its last): index tuples."""
    hi = tuple(slice(1, None) if a == axis else slice(None) for a in range(ndim))
    lo = tuple(slice(None, -1) if a == axis else slice(None) for a in range(ndim))
    return hi, lo


def six_max(a: np.ndarray) -> np.ndarray:
    """The maximum of each voxel and its six face neighbours of a non-negative (z, y, x) array
    (0 beyond the edges): ``maximum_filter(a, footprint=SIX, mode="constant", cval=0)`` by
    shifted slices, measured 3 x faster (on a bool array: one 6-neighbour dilation). A new
    array."""
    out = a.copy()
    for axis in range(a.ndim):
        hi, lo = _axis_halves(axis, a.ndim)
        np.maximum(out[hi], a[lo], out=out[hi])
        np.maximum(out[lo], a[hi], out=out[lo])
    return out


def _line_step(mask: np.ndarray, axis: int, erode: bool) -> np.ndarray:
    """One step of a binary dilation (or erosion, the outside as background) of a bool array
    by the three voxels along ``axis``. A new array."""
    out = mask.copy()
    hi, lo = _axis_halves(axis, mask.ndim)
    op = np.logical_and if erode else np.logical_or
    op(out[hi], mask[lo], out=out[hi])
    op(out[lo], mask[hi], out=out[lo])
    if erode:
        out[tuple(0 if a == axis else slice(None) for a in range(mask.ndim))] = False
        out[tuple(-1 if a == axis else slice(None) for a in range(mask.ndim))] = False
    return out


def _morph(mask: np.ndarray, steps: int, erode: bool, planes: bool) -> np.ndarray:
    """``steps`` binary dilations (erosions) of a (z, y, x) bool array by the 6-neighbour
    cross, or with ``planes`` by the 18-neighbourhood (the union of the three axis planes'
    3 x 3 squares: a dilation by it is the OR of the squares', an erosion the AND, and each
    square's is two steps along its axes)."""
    out = np.array(mask, dtype=bool)
    for _ in range(int(steps)):
        if planes:
            parts = [_line_step(_line_step(out, a, erode), b, erode)
                     for a, b in ((0, 1), (0, 2), (1, 2))]
            out = (np.logical_and if erode else np.logical_or).reduce(parts)
        elif erode:
            prev = out
            out = _line_step(prev, 0, True)
            for axis in range(1, prev.ndim):
                out &= _line_step(prev, axis, True)
        else:
            out = six_max(out)
    return out


def dilate6(mask: np.ndarray, steps: int = 1) -> np.ndarray:
    """``mask`` dilated ``steps`` times by the 6-neighbour cross, nothing beyond the border:
    the voxels of ``scipy.ndimage.binary_dilation(mask, SIX, iterations=steps)`` (steps >= 1)
    by shifted slices (measured 10 x faster on a 300 x 200 x 200 box). A new (z, y, x) bool
    array."""
    return _morph(mask, steps, erode=False, planes=False)


def erode6(mask: np.ndarray, steps: int = 1) -> np.ndarray:
    """``mask`` eroded ``steps`` times by the 6-neighbour cross, the outside of the array as
    background: the voxels of ``scipy.ndimage.binary_erosion(mask, SIX, iterations=steps)``
    (steps >= 1), by shifted slices. A new (z, y, x) bool array."""
    return _morph(mask, steps, erode=True, planes=False)


def dilate18(mask: np.ndarray, steps: int = 1) -> np.ndarray:
    """As :func:`dilate6` with the 18-neighbourhood (``generate_binary_structure(3, 2)``)."""
    return _morph(mask, steps, erode=False, planes=True)


def erode18(mask: np.ndarray, steps: int = 1) -> np.ndarray:
    """As :func:`erode6` with the 18-neighbourhood (``generate_binary_structure(3, 2)``)."""
    return _morph(mask, steps, erode=True, planes=True)


def near(mask: np.ndarray, spacing: float, radius_mm: float, step_mm: float = 2.0) -> np.ndarray:
    """Voxels within about ``radius_mm`` of ``mask`` (never fewer: computed on a coarse grid
    of ``step_mm`` blocks, so it errs on the generous side by up to a block)."""
    f = max(1, int(round(step_mm / spacing)))
    coarse = _block_any(mask, f)
    steps = int(np.ceil(radius_mm / (f * spacing))) + 1
    grown = dilate_cube(coarse, steps)
    idx = [np.minimum(np.arange(s) // f, grown.shape[a] - 1) for a, s in enumerate(mask.shape)]
    return grown[np.ix_(*idx)]


def coarse_distance(mask: np.ndarray, spacing: float, step_mm: float = 1.0) -> tuple:
    """(distance map in mm to ``mask`` on a grid of about ``step_mm`` blocks, block factor f):
    voxel (z, y, x) of the full grid reads it at (z // f, y // f, x // f). Accurate to a block;
    for bounds of a few millimetres (not for sub-voxel work)."""
    f = max(1, int(round(step_mm / spacing)))
    coarse = _block_any(mask, f)
    return distance_outside(coarse) * (f * spacing), f


def _open_close(mask: np.ndarray, opening: int, closing: int, fallbacks=None,
                where: str = "") -> np.ndarray:
    # Paper: Open^l . Close^n (closing first fills pores, opening then removes spurs).
    out = mask
    if closing:
        pad = closing + 1
        out = np.pad(out, pad)
        out = erode6(dilate6(out, closing), closing)
        out = out[pad:-pad, pad:-pad, pad:-pad]
    if opening:
        opened = dilate6(erode6(out, opening), opening)
        # Opening must not empty the mask: then the closed mask is kept as it is.
        if not opened.any() and fallbacks is not None:
            fallbacks.add("threshold", f"opening ({opening}) would empty the mask: it is kept "
                          "unopened", int(out.sum()), "voxels", where)
        out = opened if opened.any() else out
    return out


def _open_close_both(first: tuple, second: tuple, opening: int, closing: int,
                     fallbacks=None) -> tuple:
    """:func:`_open_close` of two (mask, name) pairs at once on two threads (scipy's
    morphology releases the GIL; 0.48 -> 0.27 s on the femur phantom's box). Their fallbacks
    are noted in the order of the pairs, as one after the other would."""
    from ..report import FallbackLog

    logs = [FallbackLog(), FallbackLog()]

    def run(i):
        mask, where = (first, second)[i]
        return _open_close(mask, opening, closing, logs[i], where)

    out = tuple(thread_map(run, range(2), cpu_threads(2), "morphology"))
    if fallbacks is not None:
        for log in logs:
            for r in log:
                fallbacks.add(r.stage, r.what, r.count, r.unit, r.where)
    return out


def solidify(mask: np.ndarray, spacing: float, radius_mm: float = SOLIDIFY_RADIUS_MM) -> np.ndarray:
    """Closing with a ~radius_mm ball (18-connected steps), then hole filling."""
    steps = max(1, int(round(radius_mm / spacing)))
    pad = steps + 1
    out = erode18(dilate18(np.pad(mask, pad), steps), steps)
    out = out[pad:-pad, pad:-pad, pad:-pad] | mask
    return fill_holes(out)


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """``mask`` with every background component that does not touch the array's border filled
    (the same as :func:`scipy.ndimage.binary_fill_holes`, 6-connected background; one
    labelling instead of a dilation iterated to convergence, which is slow across a large
    hollow bone). A new (z, y, x) bool array."""
    background, n = ndimage.label(~mask)
    if n == 0:
        return np.ones(mask.shape, bool)
    outer = np.zeros(n + 1, bool)
    for axis in range(mask.ndim):
        for end in (0, -1):
            outer[np.take(background, end, axis=axis)] = True
    outer[0] = False
    return ~outer[background]


def boundary_voxels(mask: np.ndarray) -> np.ndarray:
    """Voxels of mask with at least one 6-neighbour outside it."""
    return mask & ~erode6(mask)


def voxel_points(mask: np.ndarray, spacing: float) -> np.ndarray:
    """Voxel centres of a (z, y, x) mask as (k, 3) x-y-z points in grid millimetres."""
    idx = np.nonzero(mask)
    return np.stack([idx[2], idx[1], idx[0]], axis=1).astype(np.float64) * spacing


def crossing_points(values: np.ndarray, inside: np.ndarray, level: float, spacing: float,
                    crossed: bool = False):
    """Sub-voxel points where the image crosses ``level`` between an inside and an outside voxel.

    Only grid edges that leave ``inside`` are used, so the points lie on bone k's outer boundary
    (the marching-cubes vertex positions of the HT isosurface restricted to bone k). An edge
    whose two voxels do not straddle ``level`` gets its midpoint (a fallback): with
    ``crossed``, returns (points (k, 3), (k,) bool: a crossing was found) instead of the
    points."""
    pts = []
    found = []
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
            crosses = (f_in >= level) & (f_out < level) & (denom > 0)
            found.append(crosses)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.where(crosses, (f_in - level) / denom, 0.5)
            t = np.clip(t, 0.0, 1.0)
            p = np.stack([idx[2], idx[1], idx[0]], axis=1).astype(np.float64)
            p[:, 2 - axis] += step * t
            pts.append(p * spacing)
    if not pts:
        return (np.zeros((0, 3)), np.zeros(0, bool)) if crossed else np.zeros((0, 3))
    return (np.concatenate(pts), np.concatenate(found)) if crossed else np.concatenate(pts)
