"""The CT outranks the segment where it is unambiguous (issue 18): soft-tissue parts of a label
with no bone around them are no bone; marrow and low-density bone inside a cortex stay bone."""

import numpy as np
import pytest
import SimpleITK as sitk

from BoneWatertightLib.errors import ThresholdError
from BoneWatertightLib.pipeline import reconstruct
from BoneWatertightLib.stages.ownership import compute_ownership, unsupported_parts

D = 0.5  # mm


def _ball(shape, centre_mm, r_mm):
    z, y, x = np.indices(shape) * D
    c = np.asarray(centre_mm)
    return (x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 <= r_mm ** 2


def _scene(marrow_hu=40.0):
    """A hollow bone ball (cortex 2 mm, 1200 HU; marrow inside) in soft tissue (40 HU), and its
    label: the ball plus a 4 mm false blob stuck to it from outside."""
    shape = (72, 72, 96)
    centre = (20.0, 18.0, 18.0)
    outer = _ball(shape, centre, 10.0)
    inner = _ball(shape, centre, 8.0)
    ct = np.full(shape, 40.0, np.float32)
    ct[outer] = 1200.0
    ct[inner] = marrow_hu
    rng = np.random.default_rng(0)
    ct += rng.normal(0.0, 15.0, shape).astype(np.float32)
    blob_centre = (20.0 + 10.0 + 3.0, 18.0, 18.0)
    blob = _ball(shape, blob_centre, 4.0)
    label = outer | blob
    return ct, label, inner, blob & ~outer


def test_blob_unsupported_marrow_supported():
    ct, label, marrow, blob = _scene()
    from BoneWatertightLib.mesh.distance import distance_inside

    depth = distance_inside(np.pad(label, 1))[1:-1, 1:-1, 1:-1] * D
    core = depth > 1.5
    bad, pieces = unsupported_parts(ct, label, core, D, level=95.0)
    assert len(pieces) == 1
    assert pieces[0]["support"] < 0.5
    # most of the blob is left out, none of the marrow
    assert bad[blob].mean() > 0.8
    assert not bad[marrow].any()
    assert not bad[~label].any()


def test_low_density_inside_cortex_is_kept():
    # Marrow at fat-free soft-tissue HU and at 'osteoporotic' 70 HU: both inside their cortex.
    for marrow_hu in (40.0, 70.0):
        ct, label, marrow, blob = _scene(marrow_hu)
        label = label & ~blob
        from BoneWatertightLib.mesh.distance import distance_inside

        depth = distance_inside(np.pad(label, 1))[1:-1, 1:-1, 1:-1] * D
        bad, pieces = unsupported_parts(ct, label, depth > 1.5, D, level=95.0)
        assert pieces == [] and not bad.any()


def test_ownership_drops_the_blob_core():
    ct, label, marrow, blob = _scene()
    labels = label.astype(np.uint16)
    own = compute_ownership(ct, labels, 1, D, h0=300.0, ht=150.0, theta_max=2500.0,
                            soft=40.0, contrast=1160.0, coarseness=1.0, band_mm=3.0)
    assert own.unsupported[blob].mean() > 0.8
    assert not (own.cores[blob & own.unsupported] > 0).any()
    # the marrow stays core (bone whatever its HU)
    assert (own.cores[marrow] == 1).mean() > 0.5
    # nothing of the blob is owned beyond the CT's own bone evidence
    assert (own.owner[blob] == 1).mean() < 0.1
    info = own.info["unsupported"][1]
    assert len(info) == 1 and info[0]["voxels"] > 0


def _image(arr, spacing=(1.0, 1.0, 1.0)):
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing(spacing)
    img.SetOrigin((-10.0, 5.0, 3.0))
    return img


@pytest.mark.parametrize("background", [40.0, -1000.0])
def test_segment_without_bone_is_refused(background):
    # A label over soft tissue or air: a clear input error naming what the CT shows there.
    rng = np.random.default_rng(1)
    arr = (background + rng.normal(0.0, 10.0, (40, 40, 40))).astype(np.int16)
    arr[5:15, 5:15, 5:15] = 1200  # some bone elsewhere
    z, y, x = np.indices(arr.shape)
    mask = ((x - 28) ** 2 + (y - 28) ** 2 + (z - 28) ** 2 <= 36).astype(np.uint8)
    with pytest.raises(ThresholdError) as err:
        reconstruct(_image(arr), _image(mask))
    text = str(err.value)
    assert "covers" in text and "bone" in text


def test_low_density_bone_between_the_core_and_a_neighbours_band_is_the_bones():
    """A joint whose two cortices blur into one bright band on thick slices (a sacrum at the
    sacro-iliac joint): the neighbour owns the band, and bone k's label between its core and
    the band holds low-HU trabecular bone outside every bone's evidence. It lies between bone
    on both sides, so it is k's (before, k's surface stopped at its core, a dent as deep as the
    core's margin). Where the band is bone evidence nobody owns (a joint space the CT shows),
    or without the evidence given, nothing is filled."""
    from BoneWatertightLib.stages.threshold import bone_masks

    shape = (24, 24, 40)
    labels = np.zeros(shape, np.uint16)
    labels[4:20, 4:20, 4:22] = 1            # bone k = 1, its label up to x = 21
    labels[4:20, 4:20, 22:34] = 2           # the neighbour
    owner = np.zeros(shape, np.uint16)
    cores = np.zeros(shape, np.uint16)
    cores[6:18, 6:18, 6:15] = 1             # k's core stops 7 voxels short of its label's end
    owner[cores == 1] = 1
    owner[4:20, 4:20, 20:34] = 2            # the blurred band (and the neighbour) owned by 2
    ct = np.full(shape, 60.0, np.float32)   # trabecular bone at soft-tissue HU
    ct[owner == 2] = 700.0
    fg = owner > 0
    kw = dict(h0=400.0, theta_max=3000.0, coarseness=3.0, opening=0, closing=0)
    mid = (12, 12, 17)                      # between k's core and the band, in k's label

    def at(masks, index):
        i = tuple(np.asarray(index) - [s.start for s in masks.box])
        return bool(masks.w_ht[i])

    filled = bone_masks(ct, owner, cores, labels, 1, 1.0, foreground=fg, **kw)
    assert at(filled, mid) and at(filled, (12, 12, 19))
    assert not at(filled, (12, 12, 20))     # the neighbour's band stays the neighbour's
    assert not at(bone_masks(ct, owner, cores, labels, 1, 1.0, **kw), mid)
    seen = fg.copy()
    seen[4:20, 4:20, 15:20] = True          # the gap is bone evidence nobody owns
    assert not at(bone_masks(ct, owner, cores, labels, 1, 1.0, foreground=seen, **kw), mid)
