"""Anatomical phantoms (Testing/anatomical.py): truths watertight and on their SDF's zero set,
joint spaces at least the requested gap, thin plates of the stated thickness that a 3 mm CT
blurs below the usual thresholds, CT geometry and HU, AI-style labels, seeds.

Two cases build without the shared data: ``sample_L3L4`` (the bundled 3 mm sample, real
shapes) and ``scapula_3mm`` (synthetic shoulder); the pelvis test needs ../shared/data and is
skipped without it.
"""

import time

import numpy as np
import pytest
import SimpleITK as sitk

import anatomical as A
from BoneWatertightLib.mesh.checks import check_surface
from metrics import TriangleLocator


@pytest.fixture(scope="module")
def sample():
    t = time.perf_counter()
    ph = A.make_anatomical("sample_L3L4", seed=0)
    print(f"\nsample_L3L4 made in {time.perf_counter() - t:.1f} s, peak {ph.info['peak_rss_mb']:.0f} MB")
    return ph


@pytest.fixture(scope="module")
def scapula():
    t = time.perf_counter()
    ph = A.make_anatomical("scapula_3mm", seed=0)
    print(f"\nscapula_3mm made in {time.perf_counter() - t:.1f} s, peak {ph.info['peak_rss_mb']:.0f} MB")
    return ph


def _cheap(seed):
    # The sample at a coarse model grid and a coarse CT: seconds, for the seed tests.
    return A.make_anatomical("sample_L3L4", seed=seed, model_grid=0.6, pixel=3.0)


# ---------------------------------------------------------------------------- truths

def test_truths_are_watertight_single_bones_with_the_smoothed_labels_genus(sample, scapula):
    for ph in (sample, scapula):
        assert set(ph.truths) == set(ph.names)
        for label, s in ph.truths.items():
            # self-intersections where they could hide: the scapula's sub-millimetre plates
            rep = check_surface(s.vertices, s.faces, check_self_intersections=ph is scapula)
            assert rep.ok, (ph.names[label], rep.problems)
            meta = ph.info["bones_info"][ph.names[label]]
            # Thinning and joint carving must not open holes (nor close the canal).
            assert rep.genus == meta["genus_smoothed_label"] == meta["genus"]
    # A vertebra has its canal; the scapula and the humerus none.
    assert all(ph_g == 1 for ph_g in (sample.info["bones_info"][n]["genus"] for n in ("L3", "L4")))
    assert scapula.info["bones_info"]["scapula_right"]["genus"] == 0


def test_truth_vertices_lie_on_the_zero_set_of_the_sdf(sample, scapula):
    for ph in (sample, scapula):
        for label, s in ph.truths.items():
            d = ph.sdf(label, s.vertices)
            assert np.abs(d).max() < 2e-3, ph.names[label]
            # and the SDF is a distance near the surface: 1 mm along the outward normal
            n = s.vertex_normals()
            out = ph.sdf(label, s.vertices[::50] + n[::50])
            inn = ph.sdf(label, s.vertices[::50] - 0.3 * n[::50])
            assert np.median(out) == pytest.approx(1.0, abs=0.15)
            assert np.median(inn) < 0


def test_the_truths_of_neighbours_are_at_least_the_joint_gap_apart(sample, scapula):
    for ph in (sample, scapula):
        by_name = {v: k for k, v in ph.names.items()}
        carved = [j for j in ph.info["joints"] if j["carved"]]
        assert carved, "the labels touch: every case has a joint"
        for j in carved:
            la, lb = by_name[j["a"]], by_name[j["b"]]
            a, b = ph.truths[la], ph.truths[lb]
            # exact point-to-triangle distances of the vertices that can be closest (within
            # g + 3 mm of the other bone by its SDF), both ways
            near_a = a.vertices[ph.sdf(lb, a.vertices) < j["gap_mm"] + 3.0]
            near_b = b.vertices[ph.sdf(la, b.vertices) < j["gap_mm"] + 3.0]
            d = min(TriangleLocator(b).query(near_a)[0].min(), TriangleLocator(a).query(near_b)[0].min())
            assert d >= 0.98 * j["gap_mm"], j
            assert d == pytest.approx(j["min_distance_mm"], abs=0.02)
            # ... and the gap is a joint space, not a chasm: the surfaces come within 2 g
            assert d < 2.0 * j["gap_mm"], j


def test_thin_plates_exist_with_the_stated_thickness(scapula):
    s = scapula.truths[72]
    p, inward, t, area = A.thickness_samples(s, n=20000, seed=3)
    wall = np.isfinite(t)
    # A scapular blade: a large part of the bone is a plate thinner than 2 mm.
    assert (t < 2.0).mean() > 0.25
    assert (t < 1.0).mean() > 0.05
    thin = t[wall & (t < 3.0)]
    lo, hi = A.KINDS["scapula"]["plate"]
    assert np.percentile(thin, 5) > 0.8 * lo
    assert lo <= np.median(thin) <= hi
    # the construction's target is met where the bone is fully thinned
    err = scapula.info["plates"]["scapula_right"]["plate_full_target_abs_err_mm_median_p95"]
    assert err[0] < 0.15 and err[1] < 0.5
    # the humerus has no plates
    _, _, th, _ = A.thickness_samples(scapula.truths[70], n=5000, seed=4)
    assert (th < 3.0).mean() < 0.01


def test_a_3mm_ct_blurs_sub_millimetre_plates_below_the_thresholds(scapula):
    fig = scapula.info["ct_figures"]
    plate = fig["scapula_right"]
    # The physical effect the phantoms exist for: a < 1 mm cortical plate at 1000-1800 HU in
    # a 3 mm voxel peaks at a few hundred HU, mostly below the paper's H0 = 300 HU ...
    assert plate["plate_0-1mm_n"] > 200
    assert plate["plate_0-1mm_frac_below_300HU"] > 0.5
    assert plate["plate_0-1mm_mid_HU_p10_p50_p90"][1] < 320
    # ... thicker plates a little more, while the thick cortex of the humerus stays bright.
    assert plate["plate_1-2mm_mid_HU_p10_p50_p90"][1] > plate["plate_0-1mm_mid_HU_p10_p50_p90"][1]
    assert fig["humerus_right"]["thick_cortex_peak_HU_p10_p50_p90"][1] > 550


# ---------------------------------------------------------------------------- CT and labels

def test_ct_geometry_and_hu(sample, scapula):
    for ph in (sample, scapula):
        ct = ph.ct
        info = ph.info
        assert ct.GetPixelID() == sitk.sitkInt16
        assert np.allclose(ct.GetSpacing(), [info["pixel"], info["pixel"], info["slice_spacing"]])
        assert list(ct.GetSize()) == info["ct_size"]
        D = np.array(ct.GetDirection()).reshape(3, 3)
        assert np.allclose(D @ D.T, np.eye(3), atol=1e-9)
        # every bone inside the field of view with a margin
        lo = np.array(ct.GetOrigin())
        idx = np.concatenate([(s.vertices - lo) @ D / np.array(ct.GetSpacing()) for s in ph.truths.values()])
        assert idx.min() > 1.0 and np.all(idx.max(axis=0) < np.array(ct.GetSize()) - 2.0)
        arr = sitk.GetArrayViewFromImage(ct)
        lab = sitk.GetArrayViewFromImage(ph.labels)
        far = (lab == 0) & (arr > -300)
        # muscle and organs at 30-60 HU, fat at -100: both in the body around the bones
        assert ((arr[far] > 20) & (arr[far] < 75)).mean() > 0.3
        assert ((arr[far] > -140) & (arr[far] < -60)).mean() > 0.005
        assert arr.max() < 2000 and arr.min() >= -1024
        noise = info["noise"]
        assert noise >= 10
    # the synthetic shoulder has air behind the back, fat under the skin, lung in front
    a = sitk.GetArrayViewFromImage(scapula.ct)
    assert (a < -700).mean() > 0.05 and ((a > -160) & (a < -50)).mean() > 0.005


def test_labels_are_ai_style_majority_votes_on_the_ct_grid(sample):
    lab = sample.labels
    ct = sample.ct
    assert lab.GetSize() == ct.GetSize() and np.allclose(lab.GetSpacing(), ct.GetSpacing())
    assert np.allclose(lab.GetOrigin(), ct.GetOrigin()) and np.allclose(lab.GetDirection(), ct.GetDirection())
    assert lab.GetPixelID() == sitk.sitkUInt8
    assert set(np.unique(sitk.GetArrayViewFromImage(lab))) == {0} | set(sample.names)
    # the coarse grid itself: every voxel is the majority of 27 points of the truth
    coarse = sample.labels_ai(on_ct_grid=False)
    assert np.allclose(coarse.GetSpacing(), [sample.info["label_grid"]] * 3)
    arr = sitk.GetArrayViewFromImage(coarse)
    rng = np.random.default_rng(0)
    sp = np.array(coarse.GetSpacing())
    D = np.array(coarse.GetDirection()).reshape(3, 3)
    labels = sorted(sample.names)
    # voxels near a surface (where the vote matters)
    idx = np.argwhere(arr >= 0)
    centres = np.array(coarse.GetOrigin()) + (idx[:, ::-1] * sp) @ D.T
    dist = np.min([np.abs(sample.sdf(k, centres)) for k in labels], axis=0)
    near = idx[dist < 0.6 * sp[0]]
    pick = near[rng.choice(len(near), size=min(300, len(near)), replace=False)]
    t = (np.arange(3) + 0.5) / 3 - 0.5
    off = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3) * sp
    for k, j, i in pick:
        c = np.array(coarse.GetOrigin()) + (np.array([i, j, k]) * sp) @ D.T
        pts = c + off @ D.T
        votes = [27 - sum(int((sample.sdf(v, pts) < 0).sum()) for v in labels)]
        votes += [int((sample.sdf(v, pts) < 0).sum()) for v in labels]
        expect = ([0] + labels)[int(np.argmax(votes))]
        assert arr[k, j, i] == expect
    # stair-stepped, not the truth: a 3 mm label of a vertebra differs from it by voxels
    for v in labels:
        m = sitk.GetArrayViewFromImage(lab) == v
        assert m.sum() > 1000


def test_steal_gives_part_of_one_bone_to_its_neighbour(sample):
    plain = sitk.GetArrayFromImage(sample.labels_ai(on_ct_grid=False))
    stolen = sitk.GetArrayFromImage(sample.labels_ai(steal_mm=("L4", "L3", 4.0), on_ct_grid=False))
    moved = (plain == 28) & (stolen == 29)
    assert moved.sum() > 10
    assert np.all(stolen[plain != 28] == plain[plain != 28])


def test_seeds_are_deterministic_and_different():
    a, b, c = _cheap(0), _cheap(0), _cheap(1)
    aa, bb, cc = (sitk.GetArrayViewFromImage(p.ct) for p in (a, b, c))
    assert np.array_equal(aa, bb)
    assert np.array_equal(sitk.GetArrayViewFromImage(a.labels), sitk.GetArrayViewFromImage(b.labels))
    for k in a.truths:
        assert np.array_equal(a.truths[k].vertices, b.truths[k].vertices)
    assert not np.array_equal(aa, cc)
    # held-out seeds change the shape (perturbation, plate thickness), not only the noise
    k = sorted(a.truths)[0]
    d = TriangleLocator(c.truths[k]).query(a.truths[k].vertices[::20])[0]
    assert 0.02 < np.median(d) < 1.0


def test_bad_parameters_and_missing_data_are_clear(monkeypatch):
    with pytest.raises(ValueError, match="Unknown anatomical case"):
        A.make_anatomical("nope")
    with pytest.raises(ValueError, match="Unknown anatomical phantom parameter"):
        A.make_truth("sample_L3L4", pixle=1.0)
    with pytest.raises(ValueError, match="model_grid"):
        A.make_truth("scapula_3mm", model_grid=0.55)  # 0.6 mm plates need h <= 0.5
    monkeypatch.setenv("BONEWATERTIGHT_DATA", "/nonexistent/shared/data")
    assert not A.data_available("pelvis")
    with pytest.raises(A.DataMissing, match="/nonexistent/shared/data"):
        A.make_anatomical("pelvis_3mm")


# ---------------------------------------------------------------------------- real shapes

@pytest.mark.skipif(not A.data_available("pelvis"), reason="needs ../shared/data (the 3 mm pelvis CT)")
def test_pelvis_hip_bone_gets_thin_iliac_plates_without_holes():
    ph = A.make_truth("pelvis_3mm", bones=("hip_right",))
    meta = ph.info["bones_info"]["hip_right"]
    assert meta["genus"] == meta["genus_smoothed_label"]
    s = ph.truths[78]
    p, inward, t, area = A.thickness_samples(s, n=20000, seed=5)
    # the 3 mm label's 6-12 mm wing became plates: part of the bone is < 2 mm thick now,
    # and the label's volume shrank accordingly
    assert (t < 2.0).mean() > 0.04
    assert (t < 1.2).mean() > 0.003
    assert 0.7 < meta["volume_ml"] / meta["label_ml"] < 0.95
    pl = ph.info["plates"]["hip_right"]
    assert pl["plate_full_target_abs_err_mm_median_p95"][0] < 0.25


# ---------------------------------------------------------------------------- the benchmark part

def test_benchmark_report_shows_results_refusals_and_baselines():
    import bench_anatomical as B

    d = {"mean": 0.4, "p95": 1.2, "max": 3.5}
    ok_bone = {"name": "hip_right", "label": 78, "ok": True, "distance": d, "bias_mm": 0.1, "volume_ratio": 0.93,
               "checks": {"ok": True, "genus": 2, "problems": []}, "truth_genus": 0, "truth_ml": 300.0,
               "frac_on_neighbour": 0.01, "warnings": ["tunnels"],
               "baselines": {"threshold_mc": {"ok": True, "distance": d, "bias_mm": 0.0, "volume_ratio": 1.2,
                                              "checks": {"ok": False, "genus": None}},
                             "segment": {"ok": False, "error": "empty surface"}}}
    refused = {"name": "sacrum", "label": 25, "ok": False, "truth_genus": 13, "truth_ml": 200.0,
               "refusal": "error: part of the bone is missing", "baselines": {}}
    info = {"pixel": 3.0, "slice_spacing": 3.0, "slice_thickness": 3.0, "psf_sigma": 0.6, "noise": 20,
            "label_grid": 3.0, "joints": [{"a": "hip_right", "b": "sacrum", "gap_mm": 1.5, "carved": True,
                                           "min_distance_mm": 1.6}],
            "plates": {"hip_right": {"whole_bone_area_frac_thinner_than_1mm": 0.01,
                                     "whole_bone_area_frac_thinner_than_2mm": 0.08}},
            "ct_figures": {"hip_right": {"plate_0-1mm_mid_HU_p10_p50_p90": [200, 250, 320]}}}
    res = {"pelvis_3mm": {"seed": 0, "build": {"seconds": 30.0, "peak_rss_mb": 1600}, "info": info,
                          "cli": {"exit_code": 3, "seconds": 100.0, "error_lines": ["error: sacrum: missing"]},
                          "bones": [ok_bone, refused], "figures": {}}}
    text = "\n".join(B.report_lines(res))
    assert "exit **3**" in text and "error: sacrum: missing" in text
    assert "| hip_right | 1.0 / 8.0 | 300.0 | product | 0.40 / 1.20 / 3.50 | +0.10 | 0.930 | 2 / 0 | pass" in text
    assert "**REFUSED**" in text and "part of the bone is missing" in text
    assert "FAILED: empty surface" in text and "1.5 mm (truths 1.60 mm apart)" in text
    assert B._error_lines("x\nerror: the CT is too small\nok") == ["error: the CT is too small"]
