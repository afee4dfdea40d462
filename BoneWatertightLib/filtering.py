"""Stage 2: the hybrid filter of paper §2.1 (Gaussian + rho-percentile gradient filter).

How we read the paper (it gives no formula): the filter must (a) suppress noise, (b) sharpen bone
borders and (c) fill small holes before thresholding.

(a) A Gaussian of sigma (mm) smooths the noise.
(b) Edge voxels are the voxels whose gradient magnitude lies above the rho-th percentile of the
    gradient magnitudes in the bone's neighbourhood (the "rho-percentile gradient" part). Each edge voxel is
    pushed toward the nearer of its local 3x3x3 extremes (a toggle-contrast step, weight 0.5). A
    toggle keeps the mid-level (half-maximum) position of an edge and steepens the ramp around it,
    so thresholds far from mid-level (HT = 150 between soft tissue and cortex) land closer to the
    true border. rho = 100 switches sharpening off.
(c) Small holes (pores of one or two voxels) are filled by the closing of the threshold stage,
    not here: a grey-level fill would also fill the joint gap.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .params import Parameters


def hybrid_filter(ct: np.ndarray, spacing: float, params: Parameters,
                  region: np.ndarray | None = None) -> np.ndarray:
    """Filtered copy of ``ct`` (float32, z-y-x). ``region`` limits where percentiles are taken."""
    sigma_mm = params.sigma if params.sigma > 0 else 0.5 * spacing
    out = ndimage.gaussian_filter(ct.astype(np.float32, copy=False), sigma=sigma_mm / spacing,
                                  mode="nearest", truncate=3.0)
    if params.rho >= 100:
        return out
    grad = ndimage.gaussian_gradient_magnitude(out, sigma=1.0, mode="nearest")
    if region is not None and region.any():
        level = np.percentile(grad[region], params.rho)
    else:
        level = np.percentile(grad, params.rho)
    edge = grad > level
    if not edge.any():
        return out
    local_max = ndimage.maximum_filter(out, size=3, mode="nearest")
    local_min = ndimage.minimum_filter(out, size=3, mode="nearest")
    v = out[edge]
    hi = local_max[edge]
    lo = local_min[edge]
    target = np.where(hi - v < v - lo, hi, lo)
    out[edge] = v + 0.5 * (target - v)
    return out
