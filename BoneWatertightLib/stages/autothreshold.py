"""Propose the two threshold windows (H0, HT) from the HU histogram around a rough segment.

Reading of the paper: H0 must select only reliable (cortical) bone and HT must reach the
blurred bone border, both above the surrounding soft tissue. We measure two tissue levels:
the soft-tissue level (histogram mode of a shell just outside the segment) and the cortical
level (a high percentile inside the segment), and place HT and H0 at fixed fractions of the
contrast between them. The fractions are chosen so that a typical adult femur (soft tissue
~40 HU, cortex ~1400 HU) gets the paper's HT = 150 and H0 = 300.
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk

from ..errors import EmptySegmentError, ThresholdError

HT_FRACTION = 0.08
H0_FRACTION = 0.19
CORTEX_PERCENTILE = 95.0
SOFT_TISSUE_WINDOW = (-250.0, 250.0)
MIN_CONTRAST = 250.0


def _on_ct_grid(ct: sitk.Image, mask: sitk.Image) -> sitk.Image:
    same = (ct.GetSize() == mask.GetSize()
            and np.allclose(ct.GetOrigin(), mask.GetOrigin(), atol=1e-4)
            and np.allclose(ct.GetSpacing(), mask.GetSpacing(), atol=1e-6)
            and np.allclose(ct.GetDirection(), mask.GetDirection(), atol=1e-6))
    if same:
        return mask
    return sitk.Resample(mask, ct, sitk.Transform(), sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8)


def tissue_levels(ct_values_inside: np.ndarray, ct_values_shell: np.ndarray) -> tuple:
    """(soft-tissue HU, cortical HU) from the voxel values inside the segment and in a shell around it."""
    lo, hi = SOFT_TISSUE_WINDOW
    soft_vals = ct_values_shell[(ct_values_shell >= lo) & (ct_values_shell <= hi)]
    if soft_vals.size < 20:
        soft_vals = ct_values_inside[(ct_values_inside >= lo) & (ct_values_inside <= hi)]
    if soft_vals.size:
        # The mode (10 HU bins) is robust to the fat/muscle mixture and to bone in the shell.
        hist, edges = np.histogram(soft_vals, bins=np.arange(lo, hi + 10.0, 10.0))
        k = int(np.argmax(hist))
        soft = float(0.5 * (edges[k] + edges[k + 1]))
    else:
        soft = 40.0
    cortex = float(np.percentile(ct_values_inside, CORTEX_PERCENTILE))
    return soft, cortex


def propose_thresholds(ct: sitk.Image, mask: sitk.Image, theta_max: float = 2500.0,
                       shell_mm: float = 4.0) -> dict:
    """Suggested ``{"h0", "ht", "theta_max", "soft_tissue", "cortex"}`` in HU.

    ``mask`` is the rough segment (any grid, resampled nearest onto the CT grid).
    Raises EmptySegmentError for an empty mask and ThresholdError when the region shows no
    bone contrast.
    """
    mask = _on_ct_grid(ct, mask)
    m = sitk.GetArrayViewFromImage(mask) > 0
    if not m.any():
        raise EmptySegmentError("The segment is empty; thresholds cannot be proposed.")
    radius = [max(1, int(round(shell_mm / s))) for s in ct.GetSpacing()]
    dilated = sitk.GetArrayFromImage(
        sitk.BinaryDilate(sitk.Cast(mask > 0, sitk.sitkUInt8), radius, sitk.sitkBall)) > 0
    values = sitk.GetArrayViewFromImage(ct)
    inside = np.asarray(values[m], dtype=np.float64)
    shell = np.asarray(values[dilated & ~m], dtype=np.float64)
    soft, cortex = tissue_levels(inside, shell)
    contrast = cortex - soft
    if contrast < MIN_CONTRAST:
        raise ThresholdError(
            f"No bone contrast inside the segment: soft tissue ~{soft:.0f} HU, brightest 5% of the "
            f"segment ~{cortex:.0f} HU. Check that the segment covers the bone on this CT.")
    ht = soft + HT_FRACTION * contrast
    h0 = soft + H0_FRACTION * contrast
    top = max(float(theta_max), float(np.percentile(inside, 99.9)) + 1.0)
    # Keep the windows ordered and non-degenerate even for unusual contrasts.
    ht = float(np.clip(ht, soft + 50.0, top - 100.0))
    h0 = float(np.clip(h0, ht + 50.0, top - 50.0))
    return {"h0": round(h0), "ht": round(ht), "theta_max": round(top),
            "soft_tissue": soft, "cortex": cortex}
