"""The synthetic chest phantom (Testing/chest_phantom.py) at a coarse size: bones present and
named, labels on the CT grid, truths apart by their joint gaps, HU where expected, deterministic
per seed."""

import os
import sys

import numpy as np
import pytest
import SimpleITK as sitk

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import chest_phantom as cp  # noqa: E402

SMALL = dict(shape=(102, 102, 60), spacing=(3.5, 3.5, 5.0), h=1.2, label_grid=2.0, measure_joints=False)


@pytest.fixture(scope="module")
def ph():
    return cp.make_chest(0, **SMALL)


def _by_name(ph):
    return {n: k for k, n in ph.names.items()}


def _voxel_centres(img):
    arr_shape = sitk.GetArrayViewFromImage(img).shape
    k, j, i = np.meshgrid(*[np.arange(n) for n in arr_shape], indexing="ij")
    idx = np.column_stack([i.ravel(), j.ravel(), k.ravel()]).astype(float)
    D = np.array(img.GetDirection()).reshape(3, 3)
    return np.array(img.GetOrigin()) + (idx * np.array(img.GetSpacing())) @ D.T


def test_bones_present_and_named(ph):
    expected = ({f"vertebrae_T{k}" for k in range(1, 13)} | {f"rib_{s}_{k}" for s in ("left", "right")
                                                            for k in range(1, 13)}
                | {"sternum"} | {f"{b}_{s}" for b in ("clavicula", "scapula", "humerus") for s in ("left", "right")})
    assert set(ph.names.values()) == expected
    assert sorted(ph.names) == list(range(1, 44))
    lab = sitk.GetArrayViewFromImage(ph.labels)
    present = set(np.unique(lab)) - {0}
    assert present == set(ph.names), f"labels missing from the label map: {set(ph.names) - present}"
    ranges = {"vertebra": (8, 45), "rib": (3, 25), "sternum": (25, 90), "clavicle": (10, 35),
              "scapula": (25, 100), "humerus": (60, 200)}
    for name, bi in ph.info["bones"].items():
        lo, hi = ranges[bi["kind"]]
        assert lo < bi["volume_ml"] < hi, (name, bi["volume_ml"])
        assert bi["components"] == 1, (name, bi["components"])
        s = ph.truths[bi["label"]]
        assert len(s.faces) > 500
    # the vertebrae keep their canal open (genus 1), the ribs are solid tubes (genus 0)
    bn = _by_name(ph)
    assert ph.info["bones"]["vertebrae_T6"]["genus"][0] == 1
    assert ph.info["bones"]["rib_left_6"]["genus"][0] == 0
    # shapes where they belong (LPS: x left, y posterior, z superior)
    c = {n: ph.truths[bn[n]].vertices.mean(axis=0) for n in ("vertebrae_T1", "vertebrae_T12", "sternum",
                                                               "humerus_left", "humerus_right", "rib_left_6")}
    assert c["vertebrae_T1"][2] - c["vertebrae_T12"][2] > 180.0
    assert c["sternum"][1] < c["vertebrae_T1"][1] - 80.0
    assert c["humerus_left"][0] - c["humerus_right"][0] > 250.0
    assert c["rib_left_6"][0] > c["vertebrae_T12"][0] + 40.0


def test_labels_on_ct_grid(ph):
    ct, lab = ph.ct, ph.labels
    assert ct.GetPixelID() == sitk.sitkInt16 and lab.GetPixelID() == sitk.sitkUInt8
    assert ct.GetSize() == lab.GetSize() == SMALL["shape"]
    assert np.allclose(ct.GetSpacing(), SMALL["spacing"]) and np.allclose(lab.GetSpacing(), ct.GetSpacing())
    assert np.allclose(ct.GetOrigin(), lab.GetOrigin()) and np.allclose(ct.GetDirection(), lab.GetDirection())
    assert np.linalg.norm(ct.GetOrigin()) > 500.0  # a scanner-like origin, not (0, 0, 0)
    # the AI labels agree with the truth: most labelled voxels lie in (or next to) their bone
    arr = sitk.GetArrayViewFromImage(lab).ravel()
    pts = _voxel_centres(lab)
    bn = _by_name(ph)
    for name in ("vertebrae_T6", "rib_left_4", "scapula_right", "humerus_left", "sternum"):
        sel = arr == bn[name]
        f = ph.sdf(bn[name], pts[sel])
        assert (f < 0.5 * max(SMALL["spacing"])).mean() > 0.9, name


def test_truths_apart_by_their_joint_gaps(ph):
    """Every pair of bones the generator found near each other ends at least its gap apart
    (exact distance of one truth's vertices to the other truth's triangles)."""
    joints = ph.info["joints"]
    kinds = {(j["a"], j["b"]) for j in joints}
    assert ("vertebrae_T6", "rib_left_6") in kinds and ("scapula_left", "humerus_left") in kinds
    assert ("sternum", "clavicula_right") in kinds and ("clavicula_left", "scapula_left") in kinds
    bn = _by_name(ph)
    worst = {}
    for j in joints:
        a, b = ph.truths[bn[j["a"]]], ph.truths[bn[j["b"]]]
        d = cp._mesh_gap(ph._frame, a, b, ph._fields[j["a"]], ph._fields[j["b"]])
        worst[(j["a"], j["b"])] = (d, j["gap_mm"])
        assert d >= j["gap_mm"] - 0.3, (j, d)
    # the designed joint spaces are tight, not just large: the costovertebral and glenohumeral
    # joints come within 1 mm of their gap
    assert worst[("vertebrae_T6", "rib_left_6")][0] < 1.5 + 1.0
    assert worst[("scapula_left", "humerus_left")][0] < 2.5 + 1.0


def test_hu_where_expected(ph):
    from scipy.ndimage import distance_transform_edt

    arr3 = sitk.GetArrayViewFromImage(ph.ct)
    arr = arr3.ravel().astype(float)
    lab = sitk.GetArrayViewFromImage(ph.labels)
    pts = _voxel_centres(ph.ct)
    anat = ph.info["_anatomy"]
    bg = cp._background(anat, pts - cp.P_ANAT, 0.5)
    # far from every bone: > 10 mm from the label map
    sp = np.array(ph.ct.GetSpacing())[::-1]
    far = distance_transform_edt(lab == 0, sampling=sp).ravel() > 10.0
    soft = far & (np.abs(bg - cp.SOFT_HU) < 1.0)
    lung = far & (np.abs(bg - cp.LUNG_HU) < 1.0)
    air = np.abs(bg - cp.AIR_HU) < 1.0
    fat = far & (np.abs(bg - cp.FAT_HU) < 1.0)
    for sel, want in ((soft, cp.SOFT_HU), (lung, cp.LUNG_HU), (air, cp.AIR_HU), (fat, cp.FAT_HU)):
        assert sel.sum() > 200
        assert abs(np.median(arr[sel]) - want) < 25.0, (want, np.median(arr[sel]))
    # noise ~ 20 HU in soft tissue
    assert 12.0 < np.std(arr[soft]) < 35.0
    # bone: the trabecular core of the vertebral bodies 150-300 HU; the humeral shaft's thick
    # cortex makes the brightest bone; nothing above the cortex's 1400 HU
    bn = _by_name(ph)
    labs = lab.ravel()
    core = []
    for k in range(1, 13):
        sel = np.flatnonzero(labs == bn[f"vertebrae_T{k}"])
        core.append(sel[ph.sdf(bn[f"vertebrae_T{k}"], pts[sel]) < -5.0])
    core = np.concatenate(core)
    assert len(core) > 100
    assert 150.0 < np.median(arr[core]) < 320.0
    hum = np.flatnonzero(labs == bn["humerus_left"])
    assert np.percentile(arr[hum], 99) > 700.0
    assert arr.max() < 1500.0
    # the lungs lie inside the rib cage: the bone-free lung voxels are medial to the ribs' outline
    ribs_x = max(np.abs(ph.truths[bn[f"rib_left_{k}"]].vertices[:, 0] - cp.P_ANAT[0]).max() for k in range(1, 13))
    assert np.percentile(np.abs(pts[lung, 0] - cp.P_ANAT[0]), 99.5) < ribs_x - 5.0


def test_deterministic_per_seed(ph):
    """Every random stream is seeded: the anatomy (sizes, positions), the fields, the HU fields
    and noise of the CT, the label grid's phase give the same result again; another seed
    changes the anatomy, the noise and the label grid."""
    frame = ph._frame
    a0, a0b, a1 = cp._build_anatomy(0), cp._build_anatomy(0), cp._build_anatomy(1)
    probe = np.random.default_rng(0).uniform(-150, 150, size=(20000, 3))
    for k in (0, 20, 40):
        assert np.array_equal(a0.bones[k].f0(probe), a0b.bones[k].f0(probe))
        assert not np.allclose(a0.bones[k].f0(probe), a1.bones[k].f0(probe))
    assert [b.name for b in a0.bones] == list(ph.names.values())
    # the fields of a few bones again, from the fresh anatomy, carved by the same neighbours
    by_name = {b.name: b for b in a0.bones}
    step = max(3.0, 2.0 * SMALL["h"])
    for name in ("vertebrae_T6", "rib_right_5", "scapula_right"):
        nbrs = [(by_name[j["b"] if j["a"] == name else j["a"]], j["gap_mm"]) for j in ph.info["joints"]
                if name in (j["a"], j["b"])]
        assert nbrs
        coarse = cp._coarse_fields(frame, [by_name[name]], step)
        fld = cp._make_field(frame, by_name[name], SMALL["h"], nbrs, coarse, step)
        ref = ph._fields[name]
        assert np.array_equal(fld.bmap, ref.bmap) and np.array_equal(fld.data, ref.data)
    # the CT of a few bones twice: the same HU fields and noise; another seed: other noise
    anat = ph.info["_anatomy"]
    sub = [b for b in anat.bones if b.name in ("vertebrae_T6", "humerus_left")]
    cts = [cp._form_ct(frame, anat, sub, ph._fields, SMALL["h"], 0.5, SMALL["spacing"][2], 20.0, s)[0]
           for s in (0, 0)]
    A, B = (sitk.GetArrayViewFromImage(c) for c in cts)
    assert np.array_equal(A, B)
    # the labels again from the same fields: identical
    lab2 = cp._labels_ai(frame, anat.bones, ph._fields, SMALL["label_grid"], 0, ph.ct)
    assert np.array_equal(sitk.GetArrayViewFromImage(lab2), sitk.GetArrayViewFromImage(ph.labels))
