"""Pair mode of the phantom generator: label maps of both bones (rough and AI-style) on their
own grids, steal at the joint, and the joint cases' gaps."""

import time

import numpy as np
import pytest
import SimpleITK as sitk
from scipy import ndimage

from metrics import vertex_distances
from phantoms import (CASES, LABEL_CUP, LABEL_FEMUR, labels_ai, labels_rough, make_labels,
                      make_phantom, make_truth, resample_nearest)

JOINT_CASES = sorted(c for c in CASES if c.startswith("joint_"))


@pytest.fixture(scope="module")
def tiny():
    return make_phantom("tiny", seed=0)


@pytest.fixture(scope="module")
def joint():
    # Thick slices (2.5 mm, mask grid 1.6 x 1.6 x 5 mm), 1.2 mm gap, rotated grid.
    t = time.perf_counter()
    ph = make_phantom("joint_s25_g12", seed=0)
    print(f"\njoint_s25_g12: phantom made in {time.perf_counter() - t:.1f} s")
    return ph


def _centres(img, value):
    """Physical LPS centres (n, 3) of the voxels of img equal to value."""
    arr = sitk.GetArrayViewFromImage(img)
    idx = np.argwhere(arr == value)[:, ::-1].astype(float)  # (i, j, k)
    D = np.array(img.GetDirection()).reshape(3, 3)
    return np.array(img.GetOrigin()) + (idx * np.array(img.GetSpacing())) @ D.T


def _same_frame(img, ref):
    return np.allclose(np.array(img.GetDirection()), np.array(ref.GetDirection()), atol=1e-12)


@pytest.mark.parametrize("kind", ["rough", "ai"])
def test_label_maps_are_uint8_with_both_bones_in_the_phantoms_frame(tiny, joint, kind):
    for ph in (tiny, joint):
        lab = make_labels(ph, kind)
        assert lab.GetPixelID() == sitk.sitkUInt8 and lab.GetDimension() == 3
        arr = sitk.GetArrayViewFromImage(lab)
        assert set(np.unique(arr)) == {0, LABEL_FEMUR, LABEL_CUP}
        assert _same_frame(lab, ph.ct)
        # The labels sit where the bones are in physical space (any direction matrix).
        assert np.median(ph.bone_sdf(_centres(lab, LABEL_FEMUR))) < 0
        assert np.median(ph.cup_sdf(_centres(lab, LABEL_CUP))) < 0
    with pytest.raises(ValueError):
        make_labels(tiny, "nope")


def test_rough_labels_are_the_mask_plus_a_rough_cup(tiny, joint):
    for ph in (tiny, joint):
        lab = labels_rough(ph)
        assert lab.GetSize() == ph.mask.GetSize() and lab.GetSpacing() == ph.mask.GetSpacing()
        assert np.allclose(lab.GetOrigin(), ph.mask.GetOrigin(), atol=1e-9)
        arr = sitk.GetArrayFromImage(lab)
        mask = sitk.GetArrayFromImage(ph.mask)
        # Label 1 is exactly the femur's rough mask: the cup never took one of its voxels.
        np.testing.assert_array_equal(arr == LABEL_FEMUR, mask > 0)
        cup = arr == LABEL_CUP
        pts = _centres(lab, LABEL_CUP)
        d_cup, d_bone = ph.cup_sdf(pts), ph.bone_sdf(pts)
        sz = lab.GetSpacing()[2]
        # One piece (plus the island): the thin shell is not cut apart, even on 5 mm slices.
        comp, n = ndimage.label(cup)
        sizes = np.bincount(comp[cup])
        big = comp[cup] == np.argmax(sizes)
        print(f"\n{ph.info['case']}: cup label {cup.sum()} voxels, {n} components, "
              f"largest {big.mean():.3f}, centres inside the cup {(d_cup < 0).mean():.3f}")
        assert big.mean() > 0.97
        # On the cup: centres within half a slab (z spread) + the wobble of the truth, never
        # on the femur.
        assert (d_cup[big] < 0.5 * sz + 0.5).all()
        assert (d_cup[big] < 0.5).mean() > 0.75
        assert (d_bone > 0).all()
    # Deterministic.
    np.testing.assert_array_equal(sitk.GetArrayFromImage(labels_rough(tiny)),
                                  sitk.GetArrayFromImage(tiny.labels_rough()))


@pytest.mark.parametrize("grid_mm", [1.5, 2.0, 3.0])
def test_ai_labels_overlay_the_truth(joint, grid_mm):
    t = time.perf_counter()
    lab = labels_ai(joint, grid_mm=grid_mm)
    dt = time.perf_counter() - t
    assert lab.GetSpacing() == pytest.approx((grid_mm,) * 3)
    fem, cup = _centres(lab, LABEL_FEMUR), _centres(lab, LABEL_CUP)
    in_fem = (joint.bone_sdf(fem) < 0).mean()
    in_cup = (joint.cup_sdf(cup) < 0).mean()
    vox = grid_mm ** 3
    from BoneWatertightLib.mesh import enclosed_volume
    vf = enclosed_volume(joint.truth.vertices, joint.truth.faces)
    vc = enclosed_volume(joint.neighbour_truth.vertices, joint.neighbour_truth.faces)
    print(f"\nai labels {grid_mm} mm: {dt:.2f} s, {lab.GetSize()}, femur centres inside the femur "
          f"{in_fem:.3f}, cup centres inside the cup {in_cup:.3f}, volume femur "
          f"{len(fem) * vox / vf:.3f}, cup {len(cup) * vox / vc:.3f} of the truth")
    assert in_fem > 0.8 and in_cup > 0.8
    assert abs(len(fem) * vox / vf - 1) < 0.05
    assert abs(len(cup) * vox / vc - 1) < 0.15
    # Covers the CT's field of view.
    ct = joint.ct
    corners = [ct.TransformContinuousIndexToPhysicalPoint([float(v) for v in c])
               for c in np.array(np.meshgrid(*[[-0.5, s - 0.5] for s in ct.GetSize()])).reshape(3, -1).T]
    for c in corners:
        ci = np.array(lab.TransformPhysicalPointToContinuousIndex(c))
        assert (ci >= -0.5 - 1e-6).all() and (ci <= np.array(lab.GetSize()) - 0.5 + 1e-6).all()


def test_ai_labels_deterministic_and_seeded(tiny):
    a = labels_ai(tiny)
    b = tiny.labels_ai()
    np.testing.assert_array_equal(sitk.GetArrayFromImage(a), sitk.GetArrayFromImage(b))
    assert a.GetOrigin() == b.GetOrigin()
    c = labels_ai(tiny, seed=5)
    assert not np.allclose(a.GetOrigin(), c.GetOrigin())  # another phase of the coarse grid


def test_steal_moves_femur_voxels_to_the_cup_at_the_joint_only(joint):
    gap = joint.info["gap"]
    m = joint.info["_model"]
    base = labels_ai(joint, grid_mm=2.0)
    a0 = sitk.GetArrayFromImage(base)
    # steal_mm <= gap takes nothing (the femur is gap away from the cup).
    np.testing.assert_array_equal(sitk.GetArrayFromImage(labels_ai(joint, grid_mm=2.0, steal_mm=gap)), a0)
    steal = gap + 3.0
    st = labels_ai(joint, grid_mm=2.0, steal_mm=steal)
    assert st.GetOrigin() == base.GetOrigin() and st.GetSize() == base.GetSize()
    a1 = sitk.GetArrayFromImage(st)
    changed = a0 != a1
    assert changed.sum() > 20
    assert (a0[changed] == LABEL_FEMUR).all() and (a1[changed] == LABEL_CUP).all()
    idx = np.argwhere(changed)[:, ::-1].astype(float)
    D = np.array(st.GetDirection()).reshape(3, 3)
    pts = np.array(st.GetOrigin()) + (idx * np.array(st.GetSpacing())) @ D.T
    assert (joint.cup_sdf(pts) < steal).all()
    # Near the joint: in the head, on the cup's side (the cup reaches 0.2 of its radius past
    # the head's equator).
    q = m.to_local(pts) - m.head_c
    assert (np.linalg.norm(q, axis=1) < m.head_r + 1.0).all()
    assert ((q @ m.cup_axis) > -0.2 * m.cup_r_in - steal).all()
    assert (np.linalg.norm(q, axis=1) > m.head_r - (steal - gap) - 1.8).all()  # a cap only
    print(f"\nsteal {steal} mm: {int(changed.sum())} voxels femur -> cup")


def test_ai_labels_resampled_onto_the_ct(joint):
    lab = resample_nearest(labels_ai(joint, grid_mm=2.0), joint.ct)
    assert lab.GetSize() == joint.ct.GetSize() and lab.GetPixelID() == sitk.sitkUInt8
    assert np.allclose(lab.GetOrigin(), joint.ct.GetOrigin())
    fem = _centres(lab, LABEL_FEMUR)
    assert (joint.bone_sdf(fem) < 0).mean() > 0.8
    # Stair-stepped: no CT voxel centre labelled femur lies farther than a coarse voxel's
    # half-diagonal outside the femur.
    assert joint.bone_sdf(fem).max() < 0.5 * np.sqrt(3) * 2.0 + 0.1


def test_joint_cases_named_by_their_slices_and_gap():
    assert len(JOINT_CASES) >= 5
    rotated = 0
    for name in JOINT_CASES:
        cfg = CASES[name]
        s, g = name.split("_")[1:]
        assert float(s[1:]) / 10 == cfg["slice_spacing"] and float(g[1:]) / 10 == cfg["gap"]
        assert cfg["scale"] == 0.6 and 20 <= cfg["noise"] <= 25 and cfg["gap_exact"]
        rotated += any(cfg.get("direction_angles_deg", (0, 0, 0)))
    assert rotated >= 2
    assert {(1.5, 2.0), (2.0, 1.5), (2.5, 1.2), (3.0, 3.0), (1.0, 1.0)} <= \
        {(CASES[c]["slice_spacing"], CASES[c]["gap"]) for c in JOINT_CASES}


@pytest.mark.parametrize("name", JOINT_CASES)
def test_joint_case_gap_is_what_it_says(name):
    # The geometry of the case; a 0.5 mm truth grid (instead of 0.3) only to be quick: the
    # vertices lie on the analytic zero sets either way.
    truth, cup, info = make_truth(name, truth_grid=0.5)
    d = vertex_distances(cup.vertices, truth, signed=False)
    gap = CASES[name]["gap"]
    near = (d < gap + 0.05).mean()
    print(f"\n{name}: smallest distance between the truths {d.min():.4f} mm (gap {gap}); "
          f"{near:.2f} of the cup's vertices within gap + 0.05 mm")
    assert abs(d.min() - gap) < 0.1
    assert abs(info["gap_min_mm"] - gap) < 0.01
    assert near > 0.25  # the whole joint is that narrow, not just one point


def test_joint_case_truths_at_full_resolution(joint):
    d = vertex_distances(joint.neighbour_truth.vertices, joint.truth, signed=False)
    assert abs(d.min() - 1.2) < 0.1 and abs(joint.info["gap_min_mm"] - 1.2) < 0.01
    from BoneWatertightLib.mesh.checks import check_surface
    for s in (joint.truth, joint.neighbour_truth):
        rep = check_surface(s.vertices, s.faces)
        assert rep.ok and rep.genus == 0, rep.problems


def test_old_cases_keep_their_wider_joint(tiny):
    # Without gap_exact the cup's smooth clamp widens the joint by 0.075 cup thickness
    # (kept so that old figures stay comparable); gap_min_mm says by how much.
    m = tiny.info["_model"]
    assert tiny.info["gap_min_mm"] == pytest.approx(tiny.info["gap"] + 0.075 * m.cup_t, abs=0.01)
