"""BoneWatertightLib.stages.autothreshold: H0/HT proposal from the HU histogram around the segment."""

import numpy as np
import pytest
import SimpleITK as sitk

from BoneWatertightLib.stages.autothreshold import auto_thresholds, propose_thresholds, tissue_levels
from BoneWatertightLib.errors import EmptySegmentError, ThresholdError


def _phantom(soft=40.0, cortex=1400.0, marrow=100.0, noise=15.0, seed=1, blur_mm=0.0):
    """Tube bone: cortical shell (r 6-9 mm) around marrow, in soft tissue; 0.8 mm voxels;
    ``blur_mm``: a Gaussian blur of the HU (the scanner's point spread) before the noise.
    Returns (ct, mask, r): r is each voxel's distance (mm) from the tube's axis, (z, y, x)."""
    n = 48
    z, y, x = np.mgrid[0:n, 0:n, 0:n].astype(float) * 0.8
    r = np.hypot(x - n * 0.4, y - n * 0.4)
    hu = np.full(r.shape, soft)
    hu[r <= 9.0] = cortex
    hu[r <= 6.0] = marrow
    if blur_mm:
        from scipy import ndimage

        hu = ndimage.gaussian_filter(hu, blur_mm / 0.8)
    hu += np.random.default_rng(seed).normal(0, noise, hu.shape)
    ct = sitk.GetImageFromArray(hu.astype(np.int16))
    ct.SetSpacing((0.8, 0.8, 0.8))
    ct.SetOrigin((-10.0, 5.0, 3.0))
    mask = sitk.GetImageFromArray((r <= 8.0).astype(np.uint8))  # rough, a bit too small
    mask.CopyInformation(ct)
    return ct, mask, r


def test_tissue_levels_are_measured_and_the_windows_separate_the_tissues():
    """What the thresholds are for (module docstring): the measured levels are the phantom's
    own; no soft-tissue voxel (noise included) reaches HT; W_H0 holds every cortex voxel and
    no marrow voxel; on a blurred edge both windows reach beyond the half maximum, so W_HT
    (the target) is the larger one and holds the whole bone."""
    ct, mask, r = _phantom(blur_mm=0.6)
    p = propose_thresholds(ct, mask)
    assert p["soft_tissue"] == pytest.approx(40, abs=10)
    assert p["cortex"] == pytest.approx(1400, abs=60)
    hu = sitk.GetArrayFromImage(ct).astype(float)
    soft, cortex, marrow = hu[r >= 11.0], hu[(r >= 7.0) & (r <= 8.0)], hu[r <= 4.0]
    assert soft.max() < p["ht"]
    assert cortex.min() >= p["h0"] and marrow.max() < p["h0"]
    assert p["ht"] < p["h0"] < 0.5 * (p["soft_tissue"] + p["cortex"])
    edge = (r > 9.0) & (r < 10.5)  # the blurred outer border's tail
    assert (edge & (hu >= p["ht"])).sum() > 1.2 * (edge & (hu >= p["h0"])).sum()
    assert (hu[(r >= 6.0) & (r <= 9.0)] >= p["ht"]).all()  # W_HT holds the whole cortex
    assert p["ht"] < p["h0"] < p["theta_max"]


def test_thresholds_scale_with_contrast():
    low = propose_thresholds(*_phantom(cortex=700.0)[:2])
    high = propose_thresholds(*_phantom(cortex=1800.0)[:2])
    assert low["h0"] < high["h0"] and low["ht"] < high["ht"]
    assert low["ht"] >= low["soft_tissue"] + 50


def test_mask_on_another_grid_is_resampled():
    ct, mask, _ = _phantom()
    coarse = sitk.Resample(mask, [24, 24, 24], sitk.Transform(), sitk.sitkNearestNeighbor, ct.GetOrigin(),
                           (1.6, 1.6, 1.6), ct.GetDirection(), 0, sitk.sitkUInt8)
    a = propose_thresholds(ct, mask)
    b = propose_thresholds(ct, coarse)
    assert abs(a["h0"] - b["h0"]) <= 25 and abs(a["ht"] - b["ht"]) <= 15


def test_errors():
    ct, mask, _ = _phantom()
    with pytest.raises(EmptySegmentError):
        propose_thresholds(ct, mask * 0)
    flat, _, _ = _phantom(cortex=40.0, marrow=40.0)
    with pytest.raises(ThresholdError, match="No bone contrast"):
        propose_thresholds(flat, mask)


def _tube_arrays(soft=40.0, cortex=1400.0, fat_shell=False, metal=False, thick_slices=False):
    """(ct, labels) (z, y, x) arrays: a cortical tube (label 1) and a second bone (label 2)."""
    n = 48
    z, y, x = np.mgrid[0:n, 0:n, 0:n].astype(float)
    r = np.hypot(x - 20, y - 24)
    hu = np.full(r.shape, soft)
    if fat_shell:
        hu[(r > 11) & (r < 14)] = -100.0  # fat around the bone
    hu[r <= 9.0] = cortex
    hu[r <= 6.0] = 150.0
    if metal:
        hu[10:30, 22:26, 18:22] = 3500.0  # an implant in the bone
    r2 = np.hypot(x - 40, y - 24)
    hu[r2 <= 4.0] = 900.0  # the neighbour
    if thick_slices:
        from scipy import ndimage
        hu = ndimage.uniform_filter1d(hu, 4, axis=1)  # partial volume
    labels = np.zeros(r.shape, np.uint16)
    labels[r <= 9.0] = 1
    labels[r2 <= 4.0] = 2
    return hu, labels


def test_fat_and_other_bones_are_not_soft_tissue():
    hu, labels = _tube_arrays(fat_shell=True)
    soft, cortex = tissue_levels(hu, labels == 1, labels > 0, (1.0, 1.0, 1.0), 1.0)
    assert soft == pytest.approx(40, abs=5)
    assert cortex == pytest.approx(1400, abs=5)


def test_metal_does_not_raise_the_thresholds():
    clean = auto_thresholds(*_tube_arrays(), [1], (1.0, 1.0, 1.0), 1.0)
    metal = auto_thresholds(*_tube_arrays(metal=True), [1], (1.0, 1.0, 1.0), 1.0)
    assert metal["cortex"] == pytest.approx(clean["cortex"], abs=30)
    assert abs(metal["h0"] - clean["h0"]) <= 10 and metal["h0"] < 400


def test_partial_volume_lowers_the_thresholds_with_floors():
    thin = auto_thresholds(*_tube_arrays(), [1], (1.0, 1.0, 1.0), 1.0)
    thick = auto_thresholds(*_tube_arrays(cortex=500.0, thick_slices=True), [1], (1.0, 1.0, 3.0), 3.0)
    assert thick["h0"] < thin["h0"]
    assert thick["ht"] >= thick["soft_tissue"] + 100 - 1  # never at the soft-tissue level
    assert thick["h0"] >= thick["ht"] + 50 - 1


def test_a_ct_stored_without_its_rescale_intercept_is_named():
    """HU + 1024 (raw scanner values): the automatic thresholds would take the soft tissue
    (~1064) for bone; they are refused with the advice to convert. The same CT in HU, a segment
    of the marrow inside its cortex (its shell is bone, brighter than the segment) and the
    levels asked for with thresholds given by hand (no check) are not refused."""
    from BoneWatertightLib.errors import VolumeTypeError

    ct, mask, r = _phantom()
    raw = sitk.Cast(ct, sitk.sitkFloat32) + 1024.0
    with pytest.raises(VolumeTypeError, match="rescale intercept.*subtract 1024"):
        propose_thresholds(raw, mask)
    arr = sitk.GetArrayFromImage(raw)
    inside = sitk.GetArrayFromImage(mask) > 0
    with pytest.raises(VolumeTypeError):
        auto_thresholds(arr, inside.astype(np.uint8), [1], (0.8, 0.8, 0.8), 0.8)
    tissue_levels(arr, inside, inside, (0.8, 0.8, 0.8), 0.8)  # by hand: measured, not refused
    propose_thresholds(ct, mask)
    marrow = sitk.GetImageFromArray((r <= 5.0).astype(np.uint8))
    marrow.CopyInformation(ct)
    try:
        propose_thresholds(ct, marrow)
    except ThresholdError:
        pass  # no bone contrast around a marrow segment is another matter
