"""Synthetic phantoms: geometry, HU model, frames, reproducibility."""

import numpy as np
import pytest
import SimpleITK as sitk

from BoneWatertightLib.mesh.checks import check_surface
from BoneWatertightLib.mesh import enclosed_volume
from phantoms import CASES, make_phantom


@pytest.fixture(scope="module")
def tiny():
    return make_phantom("tiny", seed=0)


# Finer, noise-free variant with a wide gap, so HU can be read at known places.
CLEAN = dict(noise=0.0, pixel=0.6, slice_spacing=0.6, gap=3.0, scale=0.3, truth_grid=0.4)


@pytest.fixture(scope="module")
def clean():
    return make_phantom("tiny", seed=0, **CLEAN)


def _hu_at(img, physical_points):
    arr = sitk.GetArrayViewFromImage(img)
    out = []
    for p in physical_points:
        idx = img.TransformPhysicalPointToIndex([float(v) for v in p])
        out.append(float(arr[idx[2], idx[1], idx[0]]))
    return np.array(out)


def test_cases_listed():
    assert {"tiny", "easy", "femur", "hard", "lesion", "oblique"} <= set(CASES)


def test_truth_watertight(tiny):
    for surf in (tiny.truth, tiny.neighbour_truth):
        rep = check_surface(surf.vertices, surf.faces)
        assert rep.ok and rep.genus == 0, rep.problems
        assert rep.volume > 0


def test_truth_on_zero_set_and_volume(tiny):
    model = tiny.info["_model"]
    # Vertices lie on the analytic zero set.
    assert np.abs(tiny.bone_sdf(tiny.truth.vertices)).max() < 1e-5
    # Mesh volume == numeric volume of {sdf < 0} (voxel count on a 0.1 mm grid).
    lo, hi = model.bone_bbox()
    h = 0.1
    axes = [np.arange(lo[k], hi[k], h) + h / 2 for k in range(3)]
    inside = 0
    Y, X = np.meshgrid(axes[1], axes[0], indexing="ij")
    xy = np.column_stack([X.ravel(), Y.ravel()])
    for z in axes[2]:
        inside += int((model.bone_sdf(np.column_stack([xy, np.full(len(xy), z)])) < 0).sum())
    numeric = inside * h ** 3
    mesh_vol = enclosed_volume(tiny.truth.vertices, tiny.truth.faces)
    assert abs(mesh_vol - numeric) / numeric < 0.005, (mesh_vol, numeric)
    assert tiny.info["bone_length_mm"] == pytest.approx(32.6, abs=1.0)


def test_hu_in_the_right_places(clean):
    m = clean.info["_model"]
    to_phys = m.to_physical
    r, t = m.shaft[2], m.t_shaft
    cortex = to_phys(np.array([[r - t / 2, 0, 0], [0, -(r - t / 2), 0], [-(r - t / 2), 0, 0]]))
    marrow = to_phys(np.array([[0, 0, 0], [0, 0, 2.0]]))
    gap_pt = to_phys((m.head_c + m.cup_axis * (m.head_r + 0.5 * clean.info["gap"]))[None])
    lo, hi = m.bone_bbox()
    cx, cy, ax, ay = m.body
    depth = m.fat_mm + 1.2  # in the muscle layer, clear of the fat and of the bone
    soft = to_phys(np.array([[cx + ax * (1 - depth / min(ax, ay)), cy, 0.0]]))
    assert soft is not None and m.bone_sdf(m.to_local(soft))[0] > 3.0
    ct = clean.ct
    assert (_hu_at(ct, cortex) > 800).all()
    assert (np.abs(_hu_at(ct, marrow) - 50) < 60).all()
    assert 60 < _hu_at(ct, gap_pt)[0] < 300
    assert abs(_hu_at(ct, soft)[0] - 40) < 40
    arr = sitk.GetArrayViewFromImage(ct)
    assert arr[0, 0, 0] < -900  # air in the FOV corner
    assert arr.dtype == np.int16
    assert np.abs(np.array(ct.GetOrigin())).min() > 1  # non-zero origin


def test_mask_is_rough_but_on_the_bone(tiny):
    mask = tiny.mask
    assert mask.GetSpacing()[0] > tiny.ct.GetSpacing()[0] * 1.5  # a coarser grid
    arr = sitk.GetArrayFromImage(mask)
    idx = np.argwhere(arr > 0)[:, ::-1]
    pts = np.array([mask.TransformIndexToPhysicalPoint([int(v) for v in i]) for i in idx])
    model = tiny.info["_model"]
    d_bone = tiny.bone_sdf(pts)
    d_cup = model.cup_sdf(model.to_local(pts))
    assert (d_bone < 0.5).mean() > 0.6   # mostly on the bone (islands and wobble allowed)
    # The largest piece is the bone (the islands are elsewhere).
    from scipy import ndimage
    lab, n = ndimage.label(arr)
    assert n >= 2
    sizes = np.bincount(lab[arr > 0])
    big = lab[tuple(idx[:, ::-1].T)] == np.argmax(sizes)
    assert (d_bone[big] < 0.5).mean() > 0.95
    assert (d_cup > 0).all()              # never on the neighbour
    # Missing slab: some z range inside the shaft has no mask voxel.
    assert arr.any(axis=(1, 2)).sum() < arr.shape[0]


def test_oblique_is_the_same_object_moved(tiny):
    ang = (20.0, -10.0, 30.0)
    obl = make_phantom("tiny", seed=0, direction_angles_deg=ang)
    D = np.array(obl.ct.GetDirection()).reshape(3, 3)
    assert not np.allclose(D, np.eye(3))
    assert np.allclose(D.T @ D, np.eye(3))
    np.testing.assert_array_equal(sitk.GetArrayViewFromImage(obl.ct), sitk.GetArrayViewFromImage(tiny.ct))
    o = np.array(tiny.ct.GetOrigin())
    moved = (tiny.truth.vertices - o) @ D.T + o
    np.testing.assert_allclose(obl.truth.vertices, moved, atol=1e-6)
    # The truth sits at the same voxels in both images.
    v = tiny.truth.vertices[::500]
    for a, b in zip(v, obl.truth.vertices[::500]):
        ia = tiny.ct.TransformPhysicalPointToContinuousIndex(a.tolist())
        ib = obl.ct.TransformPhysicalPointToContinuousIndex(b.tolist())
        assert np.allclose(ia, ib, atol=1e-6)


def test_seed_reproducible(tiny):
    again = make_phantom("tiny", seed=0)
    np.testing.assert_array_equal(sitk.GetArrayViewFromImage(again.ct), sitk.GetArrayViewFromImage(tiny.ct))
    np.testing.assert_array_equal(sitk.GetArrayViewFromImage(again.mask), sitk.GetArrayViewFromImage(tiny.mask))
    other = make_phantom("tiny", seed=1)
    assert not np.array_equal(sitk.GetArrayViewFromImage(other.ct), sitk.GetArrayViewFromImage(tiny.ct))


def test_lesion_breaks_the_cortex(clean):
    base = clean
    les = make_phantom("tiny", seed=0, lesion=True, **CLEAN)
    m = les.info["_model"]
    c, r_l = m.lesion
    pt = m.to_physical(np.array([[0.0, m.shaft[2] - 0.5 * m.t_shaft, c[2]]]))
    assert _hu_at(base.ct, pt)[0] > 800
    assert _hu_at(les.ct, pt)[0] < 700
    np.testing.assert_allclose(les.truth.vertices, base.truth.vertices)


def test_unknown_case_and_parameter():
    with pytest.raises(ValueError):
        make_phantom("nope")
    with pytest.raises(ValueError):
        make_phantom("tiny", not_a_parameter=1)
