"""Automatic thresholds: H0 and HT per case, from the CT inside and around the segment(s).

Reading of the paper: H0 must select only reliable (cortical) bone and HT must reach the
blurred bone border, both above the surrounding soft tissue. Two tissue levels are measured on
the CT's own grid:

- the **soft-tissue level**: the median of the voxels in a shell just outside the segments
  (between half the segmentation's coarseness and SHELL_MM), within SOFT_TISSUE_WINDOW - fat is
  left out (it is below the window), so is other bone or contrast (above it);
- the **cortical level**: a high percentile of the bone-like voxels (at least BONE_ABOVE_SOFT
  above soft tissue, below METAL_HU: metal and its streaks would otherwise dominate) in a band
  around the segments' boundary, where the cortex is: up to max(coarseness, BAND_MIN_MM)
  inside (a generous segment) and one coarseness outside (a tight one). On thick slices
  partial volume lowers this level, and the thresholds follow.

HT and H0 are then fixed fractions of the contrast above soft tissue, with floors: HT at least
HT_MIN_ABOVE_SOFT above soft tissue (muscle, discs and cartilage lie up to ~100 HU above it), H0
at least H0_MIN_ABOVE_HT above HT. The fractions give a typical adult femur on thin slices
(soft tissue ~40 HU, cortex ~1300-1400 HU) the paper's HT = 150 and H0 = 300.
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk

from ..errors import EmptySegmentError, ThresholdError, VolumeTypeError
from ..mesh.distance import distance_inside, distance_outside
from .prepare import bbox_slices, on_grid_of

HT_FRACTION = 0.08
H0_FRACTION = 0.19
HT_MIN_ABOVE_SOFT = 100.0
H0_MIN_ABOVE_HT = 50.0
CORTEX_PERCENTILE = 90.0
SOFT_TISSUE_WINDOW = (-30.0, 250.0)
SHELL_MM = 4.0
METAL_HU = 2000.0
BONE_ABOVE_SOFT = 100.0
BAND_MIN_MM = 3.0
MIN_CONTRAST = 250.0
# Used when the shell has fewer voxels than this.
MIN_SHELL_VOXELS = 20
DEFAULT_SOFT_TISSUE = 40.0
# A CT stored without its rescale intercept holds HU + RAW_OFFSET_HU: at least RAW_MIN_SHIFTED
# of the shell around the segment in SOFT_TISSUE_WINDOW shifted by the offset, at most
# RAW_MAX_WINDOW_RATIO times as much in the window itself (raw air, ~24, falls in it), and the
# segment brighter than its shell (bone inside soft tissue; a segment of marrow inside its
# cortex is darker). Then the automatic thresholds are refused with that advice: they would
# take the soft tissue for bone (a femur phantom +1024 had been refused as fused with
# unlabelled bone, its "soft tissue" measured on the air at 27).
RAW_OFFSET_HU = 1024.0
RAW_MIN_SHIFTED = 0.5
RAW_MAX_WINDOW_RATIO = 0.25


def tissue_levels(ct: np.ndarray, inside: np.ndarray, labelled: np.ndarray,
                  spacing_xyz, coarseness: float, fallbacks=None,
                  check_units: bool = False) -> tuple:
    """(soft-tissue HU, cortical HU) on the CT's own grid.

    Parameters
    ----------
    ct : (z, y, x) float array (HU)
    inside : (z, y, x) bool array
        The segment(s) whose bone is measured.
    labelled : (z, y, x) bool array
        Every labelled voxel (other bones are not soft tissue).
    spacing_xyz : sequence of 3 floats
        The CT's spacing (x, y, z) in mm.
    coarseness : float
        The segmentation's coarseness (mm).
    fallbacks : BoneWatertightLib.report.FallbackLog, optional
        Notes a level measured on a wider region, or not measured at all (the default).
    check_units : bool
        Refuse (VolumeTypeError) a CT that looks stored without its rescale intercept
        (see RAW_OFFSET_HU): for the automatic thresholds, which would be wrong on it.
    """

    def note(what, count):
        if fallbacks is not None:
            fallbacks.add("thresholds", what, count, "voxels")

    sampling = tuple(float(v) for v in spacing_xyz[::-1])
    d_in = distance_inside(np.pad(inside, 1), sampling)[1:-1, 1:-1, 1:-1]
    d_out = distance_outside(inside, sampling)
    band = (inside & (d_in <= max(coarseness, BAND_MIN_MM) + 1e-6)) | \
        (~labelled & (d_out <= coarseness + 1e-6) & (d_out > 0))
    shell = ~inside & ~labelled & (d_out <= SHELL_MM) & (d_out > 0.5 * coarseness)
    lo, hi = SOFT_TISSUE_WINDOW
    s = ct[shell]
    if check_units:
        _check_not_raw(s, ct[inside])
    s = s[(s >= lo) & (s <= hi)]
    if s.size < MIN_SHELL_VOXELS:
        note(f"soft tissue: fewer than {MIN_SHELL_VOXELS} voxels in the shell around the "
             f"segments; measured within {2 * SHELL_MM:g} mm of them, labelled voxels included",
             s.size)
        s = ct[~inside & (d_out <= 2 * SHELL_MM)]
        s = s[(s >= lo) & (s <= hi)]
    soft = float(np.median(s)) if s.size >= MIN_SHELL_VOXELS else DEFAULT_SOFT_TISSUE
    if s.size < MIN_SHELL_VOXELS:
        note(f"soft tissue: too few voxels in the window there too; the default "
             f"{DEFAULT_SOFT_TISSUE:g} HU is used", s.size)
    v = ct[band]
    v = v[(v >= soft + BONE_ABOVE_SOFT) & (v < METAL_HU)]
    if v.size < MIN_SHELL_VOXELS:
        note(f"cortex: fewer than {MIN_SHELL_VOXELS} bone-like voxels at the segments' border; "
             "measured on every voxel of the segments", v.size)
        v = ct[inside]
    cortex = float(np.percentile(v, CORTEX_PERCENTILE))
    return soft, cortex


def _check_not_raw(shell_values: np.ndarray, inside_values: np.ndarray) -> None:
    """VolumeTypeError when the CT around the segment looks like raw scanner values, HU +
    RAW_OFFSET_HU (see the constants); ``shell_values``, ``inside_values``: the CT in the
    soft-tissue shell around the segment and in the segment."""
    lo, hi = SOFT_TISSUE_WINDOW
    if shell_values.size < MIN_SHELL_VOXELS or not inside_values.size:
        return
    in_window = float(np.mean((shell_values >= lo) & (shell_values <= hi)))
    shifted = float(np.mean((shell_values >= lo + RAW_OFFSET_HU)
                            & (shell_values <= hi + RAW_OFFSET_HU)))
    around, within = float(np.median(shell_values)), float(np.median(inside_values))
    if shifted >= RAW_MIN_SHIFTED and in_window <= RAW_MAX_WINDOW_RATIO * shifted \
            and within > around:
        raise VolumeTypeError(
            "The CT does not look like Hounsfield units: the tissue around the segment reads "
            f"about {around:.0f} ({100 * shifted:.0f} % of it {RAW_OFFSET_HU:.0f} above the "
            f"soft-tissue window, {lo:.0f} to {hi:.0f} HU, {100 * in_window:.0f} % in it) and the segment "
            f"about {within:.0f}. It looks stored without its rescale intercept (values = HU + "
            f"{RAW_OFFSET_HU:.0f}): convert it to HU (subtract {RAW_OFFSET_HU:.0f}; a DICOM "
            "series read by 3D Slicer or SimpleITK is converted), or give H0 and HT by hand.")


def thresholds_from_levels(soft: float, cortex: float, theta_max: float) -> dict:
    """{"h0", "ht", "soft_tissue", "cortex"}; ThresholdError when there is no bone contrast."""
    contrast = cortex - soft
    if contrast < MIN_CONTRAST:
        raise ThresholdError(
            f"No bone contrast at the segment's border: soft tissue ~{soft:.0f} HU, cortex "
            f"~{cortex:.0f} HU. Check that the segment covers a bone on this CT, or give H0 and "
            "HT by hand.")
    ht = soft + max(HT_FRACTION * contrast, HT_MIN_ABOVE_SOFT)
    h0 = max(soft + H0_FRACTION * contrast, ht + H0_MIN_ABOVE_HT)
    h0 = min(h0, theta_max - H0_MIN_ABOVE_HT)
    ht = min(ht, h0 - H0_MIN_ABOVE_HT)
    return {"h0": float(round(h0)), "ht": float(round(ht)), "soft_tissue": soft, "cortex": cortex}


def auto_thresholds(ct: np.ndarray, labels: np.ndarray, targets, spacing_xyz, coarseness: float,
                    theta_max: float = 2500.0, fallbacks=None) -> dict:
    """Thresholds for the targets of a label map (arrays on the CT's own grid, (z, y, x)).

    ``targets``: label values. Returns {"h0", "ht", "soft_tissue", "cortex"} in HU;
    ``fallbacks`` (a FallbackLog) notes tissue levels that were not measured as usual."""
    inside = np.isin(labels, list(targets))
    if not inside.any():
        raise EmptySegmentError("The segment is empty; thresholds cannot be proposed.")
    soft, cortex = tissue_levels(ct, inside, labels > 0, spacing_xyz, coarseness, fallbacks,
                                 check_units=True)
    return thresholds_from_levels(soft, cortex, theta_max)


def propose_thresholds(ct: sitk.Image, mask: sitk.Image, theta_max: float = 2500.0) -> dict:
    """Suggested ``{"h0", "ht", "theta_max", "soft_tissue", "cortex"}`` for one segment (the
    panel's Auto): the same estimate as the pipeline's automatic thresholds.

    ``mask`` is the segment (any grid, resampled nearest-neighbour onto the CT grid).
    Raises EmptySegmentError for an empty mask and ThresholdError without bone contrast.
    """
    on_ct = on_grid_of(sitk.Cast(mask != 0, sitk.sitkUInt8), ct)  # kept: the view below reads it
    arr = sitk.GetArrayViewFromImage(on_ct) > 0
    if not arr.any():
        raise EmptySegmentError("The segment is empty; thresholds cannot be proposed.")
    # Work on the segment's box + margin of the CT grid only.
    sp = np.array(ct.GetSpacing())
    box = bbox_slices(arr, np.ceil(2 * SHELL_MM / sp[::-1]).astype(int) + 1)
    values = sitk.GetArrayViewFromImage(ct)[box].astype(np.float64)
    coarse = float(max(max(mask.GetSpacing()), max(sp)))
    soft, cortex = tissue_levels(values, arr[box], arr[box], sp, coarse, check_units=True)
    out = thresholds_from_levels(soft, cortex, theta_max)
    out["theta_max"] = float(theta_max)
    return out
