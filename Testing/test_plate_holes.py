"""Tunnels of a surface through a thin plate the CT shows (stages.plates.holes_across_plates)
and their plugs as M0's occupancy (pipeline._mask_field).

A plate with a hole in its voxels: the CT either shows the plate across the hole (a faint
ridge: the surface's tunnel is not the bone's) or shows the hole too (soft tissue in it: a
foramen). Only the first is a hole through a plate; a hole over another bone's voxels is not
this bone's; a surface without tunnels is not searched.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from BoneWatertightLib import pipeline
from BoneWatertightLib.stages import plates

SOFT = 40.0
SHAPE = (40, 64, 64)  # z, y, x; 1 mm voxels


def _scene(plate_in_hole: bool, seed: int, hole_radius: float = 5.0):
    """(inside, ct): a 3 mm plate 44 x 44 mm, its voxels with a round hole; the CT (blurred
    1 mm, 20 HU of noise correlated over a voxel) with the plate 1 mm thick at 700 HU across the
    hole, or with the hole."""
    z, y, x = np.indices(SHAPE)
    plate = (z >= 18) & (z < 21) & (np.abs(y - 32) < 22) & (np.abs(x - 32) < 22)
    hole = (y - 32) ** 2 + (x - 32) ** 2 <= hole_radius ** 2
    inside = plate & ~hole
    ct = np.full(SHAPE, SOFT, np.float32)
    ct[plate] = 1200.0
    ct[plate & hole] = SOFT
    if plate_in_hole:
        ct[(z == 19) & hole] = 700.0
    ct = ndimage.gaussian_filter(ct, 1.0)
    # CT noise is correlated over about a voxel: white noise blurred, 20 HU.
    noise = ndimage.gaussian_filter(np.random.default_rng(seed).normal(0.0, 1.0, SHAPE), 1.0)
    ct += (20.0 * noise / noise.std()).astype(np.float32)
    return inside, ct


def _holes(inside, ct, exclude=None, genus=1):
    return plates.holes_across_plates(
        inside, ct, 1.0, native_spacing=(1.0, 1.0, 1.0), soft=SOFT, cortex=1200.0,
        max_contrast=150.0,
        exclude=np.zeros(SHAPE, bool) if exclude is None else exclude, surface_genus=genus)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_hole_through_a_plate_the_ct_shows_is_found(seed):
    inside, ct = _scene(True, seed)
    out = _holes(inside, ct)
    assert out["tunnels"] == 1
    plug = out["plugs"][0]
    # the plug lies in the hole, at the plate's level (x, y, z mm of the box)
    assert np.allclose(plug["centre"], (32.0, 32.0, 19.0), atol=1.5)
    assert plug["contrast_hu"] >= out["min_contrast_hu"] > 0
    assert plug["hu_median"] > SOFT + out["min_contrast_hu"]


@pytest.mark.parametrize("seed", [0, 1])
def test_a_foramen_is_no_hole_through_a_plate(seed):
    # The same hole with soft tissue in it: no crest of a plate spans it.
    inside, ct = _scene(False, seed)
    out = _holes(inside, ct)
    assert out["tunnels"] == 0 and out["plugs"] == [] and "mask" not in out


def test_a_hole_narrower_than_the_blur_is_not_judged():
    # 3 voxels across, blurred by 1 mm: the CT in it stands far above the soft tissue and
    # peaks across the plate whether or not a plate spans it.
    for plate_in_hole in (False, True):
        inside, ct = _scene(plate_in_hole, 0, hole_radius=1.0)
        z, y, x = np.indices(SHAPE)
        hole = ((y - 32) ** 2 + (x - 32) ** 2 <= 1.0) & (z == 19)
        assert ct[hole].mean() > SOFT + 300.0
        out = _holes(inside, ct)
        assert out["tunnels"] == 0 and out["other_plugs"] >= 1  # found, not judged a plate


def test_a_plate_over_another_bones_voxels_or_no_tunnel_is_not_searched():
    inside, ct = _scene(True, 0)
    z, y, x = np.indices(SHAPE)
    other = (z == 19) & ((y - 32) ** 2 + (x - 32) ** 2 <= 2)
    assert _holes(inside, ct, exclude=other)["tunnels"] == 0
    assert _holes(inside, ct, genus=0) == {"tunnels": 0, "plugs": [], "other_plugs": 0,
                                           "min_contrast_hu": None, "noise_hu": None}


def test_a_lid_over_a_pocket_is_no_plug_of_a_tunnel():
    # A foramen (the surface's real tunnel) and, beside it, a cup standing on the plate whose
    # mouth the CT closes with a faint plate: adding the lid raises the voxels' Euler
    # characteristic (a cavity, deeper than the lid's window) but closes no tunnel.
    inside, ct = _scene(False, 0)
    z, y, x = np.indices(SHAPE)
    ring = (z >= 21) & (z < 28) & (np.abs(y - 20) <= 5) & (np.abs(x - 20) <= 5) \
        & ~((np.abs(y - 20) <= 3) & (np.abs(x - 20) <= 3))
    lid = (z == 28) & (np.abs(y - 20) <= 5) & (np.abs(x - 20) <= 5)
    add = np.zeros(SHAPE, np.float32)
    add[ring] = 1200.0 - SOFT
    add[lid] = 700.0 - SOFT
    ct = ct + ndimage.gaussian_filter(add, 1.0)
    out = _holes(inside | ring, ct)
    assert out["tunnels"] == 0 and out["other_plugs"] >= 1


def test_a_plug_mask_becomes_an_occupancy_on_m0s_grid():
    # A plug on the working grid (1 mm) as the remeshing's occupancy (0.4 mm, shifted): 1
    # inside, 0 beyond a voxel from it, 0.5 on its boundary (half a voxel out from the last
    # voxel centre).
    mask = np.zeros((10, 12, 14), bool)
    mask[4:6, 3:9, 5:10] = True
    lo, h, shape = np.array([0.2, -0.6, 0.6]), 0.4, (30, 35, 40)
    field = pipeline._mask_field(mask, 1.0, shape, lo, h)
    zz, yy, xx = np.indices(shape)
    x, y, z = lo[0] + h * xx, lo[1] + h * yy, lo[2] + h * zz
    core = (z >= 4) & (z <= 5) & (y >= 3) & (y <= 8) & (x >= 5) & (x <= 9)
    assert np.allclose(field[core], 1.0)
    far = (z <= 2.9) | (z >= 7.1) | (y <= 1.9) | (y >= 10.1) | (x <= 3.9) | (x >= 11.1)
    assert np.all(field[far] == 0.0)
    # along x through the plug's middle: 0.5 half a voxel beyond its last voxel (x = 9.5)
    row = field[np.argmin(np.abs(lo[2] + h * np.arange(30) - 4.5)),
                np.argmin(np.abs(lo[1] + h * np.arange(35) - 5.0))]
    xs = lo[0] + h * np.arange(40)
    assert np.interp(9.5, xs, row) == pytest.approx(0.5, abs=0.02)
    assert np.interp(4.5, xs, row) == pytest.approx(0.5, abs=0.02)


# ------------------------------------------------------------------- thin processes of a segment

def _process_scene(rod_hu, around_hu=-80.0, seed=0):
    """A ball of thresholded bone (radius 10 voxels of 1 mm) whose segment goes on as a rod 3
    voxels across and 16 long beyond it (a tail the CT barely resolves): the CT is ``rod_hu``
    along the rod, ``around_hu`` around it, 20 HU of noise; smoothed as the pipeline does."""
    shape = (40, 40, 60)
    z, y, x = np.indices(shape)
    ball = (x - 20) ** 2 + (y - 20) ** 2 + (z - 20) ** 2 <= 100
    rod = (np.abs(y - 20) <= 1) & (np.abs(z - 20) <= 1) & (x >= 20) & (x <= 46)
    label = ball | rod
    ct = np.full(shape, around_hu, np.float32)
    ct[rod] = rod_hu
    ct[ball] = 700.0
    ct += np.random.default_rng(seed).normal(0.0, 20.0, shape).astype(np.float32)
    sm = ndimage.gaussian_filter(ct, 1.0)
    return label, ball, sm, rod & ~ball


def test_a_thin_process_of_the_segment_the_ct_shows_is_joined():
    """The rod reaches 16 mm beyond the bone (more than 2 c + 2 = 8 mm for c = 3) and stands
    well above the tissue around it, above the soft tissue's level: joined whole, from the bone
    to its tip; its record says how far it reaches and where its tip is."""
    label, ball, sm, rod = _process_scene(rod_hu=250.0)
    mask, records = plates.segment_processes(label, ball, sm, 1.0, reach_mm=8.0, margin_mm=3.0,
                                             soft=50.0, min_contrast=60.0)
    assert len(records) == 1 and records[0]["joined"], records
    assert records[0]["reach_mm"] == pytest.approx(16.0, abs=1.0)
    assert records[0]["at"][0] == pytest.approx(46.0, abs=1.0)
    assert (mask & rod).sum() >= 0.95 * rod.sum()
    assert not (mask & ~label).any()
    # the segment's voxels between the process and the bone are joined with it
    assert mask[20, 20, 31]


@pytest.mark.parametrize("rod_hu, around_hu", [(30.0, -80.0),    # a muscle's strand in fat
                                               (-80.0, 40.0)])  # a dark canal in soft tissue
def test_a_process_of_the_segment_the_ct_does_not_show_as_bone_is_not_joined(rod_hu, around_hu):
    """Below the soft tissue's level (a label leaking along a muscle), or darker than what is
    around it: no bone the CT shows, nothing joined (the plausibility's reach warning says the
    segment goes on beyond the surface)."""
    label, ball, sm, _ = _process_scene(rod_hu=rod_hu, around_hu=around_hu)
    mask, records = plates.segment_processes(label, ball, sm, 1.0, reach_mm=8.0, margin_mm=3.0,
                                             soft=50.0, min_contrast=60.0)
    assert len(records) == 1 and not records[0]["joined"] and not mask.any(), records


def test_a_thick_part_or_a_detached_piece_of_the_segment_is_no_process():
    """A block of the segment 9 voxels across beyond the bone (a bone's larger part beyond a
    gap, a separate piece), and the tail cut off from the bone by a gap in the segment, bright
    as they are: not joined."""
    label, ball, sm, rod = _process_scene(rod_hu=250.0)
    z, y, x = np.indices(label.shape)
    block = (np.abs(y - 20) <= 4) & (np.abs(z - 20) <= 4) & (x >= 36) & (x <= 50)
    sm = sm.copy()
    sm[block] = 250.0
    mask, records = plates.segment_processes(ball | block | rod, ball, sm, 1.0, reach_mm=8.0,
                                             margin_mm=3.0, soft=50.0, min_contrast=60.0)
    assert not mask.any() and len(records) == 1, records
    assert records[0]["across_mm"] > 6.0 and records[0]["attached"]
    cut = label & ~((x >= 31) & (x <= 36))
    _, _, sm, _ = _process_scene(rod_hu=250.0)
    mask, records = plates.segment_processes(cut, ball, sm, 1.0, reach_mm=8.0, margin_mm=3.0,
                                             soft=50.0, min_contrast=60.0)
    assert not mask.any() and len(records) == 1 and not records[0]["attached"], records


def test_a_generous_margin_is_no_process():
    """A segment 2 voxels wider than the bone all round (a coarse label's margin) reaches less
    far than the bound: nothing is examined."""
    label, ball, sm, _ = _process_scene(rod_hu=250.0)
    z, y, x = np.indices(label.shape)
    generous = (x - 20) ** 2 + (y - 20) ** 2 + (z - 20) ** 2 <= 144
    mask, records = plates.segment_processes(generous, ball, sm, 1.0, reach_mm=8.0,
                                             margin_mm=3.0, soft=50.0, min_contrast=60.0)
    assert records == [] and not mask.any()


def test_a_staircase_process_along_crumbs_of_bone_is_joined_solid_to_the_bone():
    """A coarse segment's oblique tail: blocks of 3 voxels (its own voxels) in a staircase,
    each touching the next only along an edge, along a faint rod the CT shows (500 HU, 2 voxels across, in fat)
    whose first 10 mm the thresholds hold as a chain of single voxels (crumbs, 26-connected to
    the bone). The process is found beyond the crumbs' end; what is joined carries it back
    along them to the bone with the segment's width (not a thread of crumbs, which the
    surface's smoothing cuts): every cross-section from
    the bone to the tip holds at least 6 voxels (the segment's 9), in one piece with the bone."""
    shape = (40, 40, 70)
    z, y, x = np.indices(shape)
    ball = (x - 20) ** 2 + (y - 20) ** 2 + (z - 20) ** 2 <= 100
    tail = np.zeros(shape, bool)
    for i in range(10):  # blocks at x 28-57, alternately at y 18-20 and 21-23
        y0 = 18 + 3 * (i % 2)
        tail[19:22, y0:y0 + 3, 28 + 3 * i:31 + 3 * i] = True
    label = ball | tail
    crumbs = np.zeros(shape, bool)
    crumbs[20, 20, 30:41] = True
    crumbs[20, 21, 30:41:2] = True
    bone = ball | crumbs
    ct = np.full(shape, -80.0, np.float32)
    ct[(np.abs(y - 20.5) <= 1.0) & (np.abs(z - 20) <= 1) & (x >= 28) & (x <= 57)] = 500.0
    ct[ball] = 700.0
    ct += np.random.default_rng(3).normal(0.0, 20.0, shape).astype(np.float32)
    sm = ndimage.gaussian_filter(ct, 1.0)
    mask, records = plates.segment_processes(label, bone, sm, 1.0, reach_mm=8.0, margin_mm=3.0,
                                             soft=50.0, min_contrast=60.0)
    assert any(r["joined"] for r in records), records
    joined = mask | bone
    pieces, _ = ndimage.label(joined, structure=np.ones((3, 3, 3), bool))
    one = pieces == pieces[20, 20, 20]
    assert one[20, 22, 56], "the tip is not joined to the bone"
    across = one[:, :, 31:57].sum(axis=(0, 1))
    assert across.min() >= 6, across
    assert not (mask & ~label).any()


def _tail_ct(rod_hu: float, seed: int = 0):
    """(CT, segment) as sitk images, 2 mm voxels: a ball of bone (cortex 2 mm at 1100 HU,
    250 HU inside, radius 13 mm) in fat (-80 HU) with a tail 1 mm across and 32 mm long at
    ``rod_hu`` (made on a 0.25 mm grid, blurred by a 0.6 mm PSF, averaged into the voxels:
    75-105 HU at 1100 HU, under HT), 15 HU of noise; the segment: the voxels a 2 mm tail and
    the ball cover by a fifth (an AI label on the CT's grid)."""
    import SimpleITK as sitk

    f, k = 0.25, 8
    n = (np.array([64, 48, 48]) / f).astype(int)  # x, y, z
    z, y, x = np.meshgrid(*[(np.arange(m) + 0.5) * f for m in n[::-1]], indexing="ij")
    r = np.sqrt((x - 20) ** 2 + (y - 24) ** 2 + (z - 24) ** 2)
    axis = np.hypot(y - 25, z - 25)
    hu = np.full(x.shape, -80.0, np.float32)
    hu[r <= 13] = 1100.0
    hu[r <= 11] = 250.0
    hu[(axis <= 0.5) & (x > 20) & (x <= 52)] = rod_hu
    hu = ndimage.gaussian_filter(hu, 0.6 / f)

    def voxels(a):
        return a.reshape(n[2] // k, k, n[1] // k, k, n[0] // k, k).mean(axis=(1, 3, 5))

    ct = voxels(hu) + np.random.default_rng(seed).normal(0.0, 15.0, (n // k)[::-1])
    label = voxels(((r <= 13) | (axis <= 1.0) & (x > 20) & (x <= 52)).astype(np.float32)) >= 0.2
    img = sitk.GetImageFromArray(ct.astype(np.float32))
    img.SetSpacing((2.0, 2.0, 2.0))
    seg = sitk.GetImageFromArray(label.astype(np.uint8))
    seg.CopyInformation(img)
    return img, seg


@pytest.mark.parametrize("seed", [0, 1])
def test_a_tail_under_ht_that_the_segment_covers_is_in_the_surface(seed):
    """End to end at the defaults: the tail (its tip at x = 52 mm) is in the surface, joined
    as a process of the segment (a threshold fallback says so), not cut off at the ball
    (x = 33 mm, where the surface stopped before); and it is not warned as a segment that
    reaches beyond the surface."""
    from BoneWatertightLib.params import Parameters

    ct, seg = _tail_ct(1100.0, seed)
    res = pipeline.reconstruct(ct, seg, Parameters())
    assert res.ok
    assert res.surface.vertices[:, 0].max() > 47.0
    assert any("thin processes of the segment" in f.what for f in res.report.fallbacks)
    assert not any("beyond the surface" in w for w in res.report.warnings), res.report.warnings


def test_a_tail_of_the_segment_over_soft_tissue_is_left_out_and_warned():
    """The same segment over a tail at soft tissue's density (a label leaking along a strand of
    muscle): not joined; the surface stops at the ball and the run says how far the segment
    reaches beyond it."""
    from BoneWatertightLib.params import Parameters

    ct, seg = _tail_ct(60.0)
    res = pipeline.reconstruct(ct, seg, Parameters())
    assert res.surface.vertices[:, 0].max() < 36.0
    assert not any("thin processes of the segment" in f.what for f in res.report.fallbacks)
    assert any("the segment reaches" in w and "beyond the surface" in w
               for w in res.report.warnings), res.report.warnings
