"""The plain alternatives run on the tiny phantom and return sensible surfaces."""

import numpy as np
import pytest

import baselines
from BoneWatertightLib.mesh.checks import check_surface
from BoneWatertightLib.mesh import enclosed_volume
from BoneWatertightLib.params import Parameters
from metrics import surface_distance
from phantoms import make_phantom


@pytest.fixture(scope="module")
def tiny():
    return make_phantom("tiny", seed=0)


@pytest.fixture(scope="module")
def params():
    return Parameters(spacing=0.5)


@pytest.mark.parametrize("name", sorted(baselines.METHODS))
def test_baseline_runs(tiny, params, name):
    s = baselines.METHODS[name](tiny.ct, tiny.mask, params)
    assert s.n_faces > 1000 and s.coordinate_system == "LPS"
    assert enclosed_volume(s.vertices, s.faces) > 0
    # In physical space, around the true bone (the cup may be included at this resolution).
    truth_vol = enclosed_volume(tiny.truth.vertices, tiny.truth.faces)
    assert 0.5 * truth_vol < enclosed_volume(s.vertices, s.faces) < 4.0 * truth_vol
    d = surface_distance(tiny.truth, s, n_samples=5000)
    # Most of the true surface has a method surface within a CT voxel (HT = 150 HU lies
    # outside the half-maximum edge, so plain thresholding is biased outward by ~0.6 mm).
    assert d["a_to_b"]["median"] < 1.0


def test_closing_wrap_is_closed_and_threshold_is_not_one_piece(tiny, params):
    wrap = baselines.closing_wrap(tiny.ct, tiny.mask, params, gap_mm=2.0)
    rep = check_surface(wrap.vertices, wrap.faces, check_self_intersections=False)
    assert rep.closed and rep.edge_manifold, rep.problems
    # Plain thresholding keeps the inner surfaces (marrow cavity): several components.
    mc = baselines.threshold_marching_cubes(tiny.ct, tiny.mask, params)
    rep = check_surface(mc.vertices, mc.faces, expect_components=None, check_self_intersections=False)
    assert rep.n_components > 1


def test_threshold_mask_keeps_only_touching_components(tiny, params):
    prep = baselines._prepared(tiny.ct, tiny.mask, params)
    m = baselines.threshold_mask(prep, params)
    ht = baselines.PAPER_HT if params.ht is None else params.ht
    raw = (prep.ct >= ht) & (prep.ct <= params.theta_max)
    assert m.sum() > 0 and m.sum() <= raw.sum()
    assert not (m & ~raw).any()


# ----------------------------------------------------------------- the segment itself

def _ball_labels(value=3, r=10.0, spacing=(0.9, 1.1, 2.0), left_handed=False):
    """A ball of radius r as label `value` on a rotated anisotropic grid; returns (image,
    centre in physical LPS, label voxel volume)."""
    import SimpleITK as sitk

    n = [int(30 / s) for s in spacing]
    D = np.array([[0.36, 0.48, -0.8], [-0.8, 0.6, 0.0], [0.48, 0.64, 0.6]])  # a rotation
    if left_handed:
        D[:, 2] *= -1
    img = sitk.Image(n, sitk.sitkUInt8)
    img.SetSpacing(spacing)
    img.SetDirection(D.ravel().tolist())
    img.SetOrigin((-50.0, 20.0, 100.0))
    c = np.array(img.TransformContinuousIndexToPhysicalPoint([(k - 1) / 2 for k in n]))
    arr = np.zeros(n[::-1], np.uint8)
    idx = np.argwhere(arr == 0)[:, ::-1]
    pts = np.array(img.GetOrigin()) + (idx * np.array(spacing)) @ D.T
    arr.ravel()[np.linalg.norm(pts - c, axis=1) < r] = value
    arr[0, 0, 0] = 1  # another label, ignored
    lab = sitk.GetImageFromArray(arr)
    lab.CopyInformation(img)
    return lab, c, float((arr == value).sum() * np.prod(spacing))


@pytest.mark.parametrize("left_handed", [False, True])
def test_segment_closed_surface_ball_in_physical_space(left_handed):
    lab, c, vox_vol = _ball_labels(left_handed=left_handed)
    for smoothing in (0.5, 0.0):
        s = baselines.segment_closed_surface(lab, 3, smoothing=smoothing)
        assert s.coordinate_system == "LPS" and s.n_faces > 1000
        rep = check_surface(s.vertices, s.faces)
        vol = enclosed_volume(s.vertices, s.faces)
        r = np.linalg.norm(s.vertices - c, axis=1)
        print(f"\nball, smoothing {smoothing}: checks ok {rep.ok} {rep.problems}, volume "
              f"{vol / vox_vol:.3f} of the label's voxels, radius {r.min():.2f}-{r.max():.2f}")
        assert rep.closed and rep.edge_manifold and rep.n_components == 1
        assert vol > 0 and abs(vol / vox_vol - 1) < 0.03
        # Around the ball in physical space (stair steps up to a voxel's half-diagonal).
        assert 10.0 - 1.2 < r.min() and r.max() < 10.0 + 1.2
    assert baselines.segment_closed_surface(lab, 7).n_faces == 0  # absent label


def test_segment_closed_surface_of_phantom_labels():
    from phantoms import labels_ai

    import SimpleITK as sitk
    ph = make_phantom("tiny", seed=0)
    lab = labels_ai(ph, grid_mm=1.0)
    arr = sitk.GetArrayViewFromImage(lab)
    for value, truth in ((1, ph.truth), (2, ph.neighbour_truth)):
        s = baselines.segment_closed_surface(lab, value)
        rep = check_surface(s.vertices, s.faces, expect_components=None)
        vol = enclosed_volume(s.vertices, s.faces)
        vox_vol = float((arr == value).sum())
        d = surface_distance(truth, s, n_samples=5000)
        print(f"\nlabel {value}: ok {rep.ok} closed {rep.closed} edge-manifold {rep.edge_manifold} "
              f"vertex-manifold {rep.vertex_manifold} components {rep.n_components} self-intersections "
              f"{rep.n_self_intersections} genus {rep.genus}; volume {vol / vox_vol:.3f} of the label's "
              f"voxels; to the truth mean {d['mean']:.2f} p95 {d['p95']:.2f} max {d['max']:.2f} mm")
        assert rep.closed and rep.edge_manifold
        # Slicer's smoothing shrinks a thin, curved label a little.
        assert 0.9 < vol / vox_vol < 1.02
        assert d["mean"] < 0.3 and d["p95"] < 0.6


def test_segment_closed_surface_needs_nothing_of_the_pipeline(monkeypatch):
    import sys

    # As if the pipeline's preparation and parameters were being rewritten (not importable).
    monkeypatch.setitem(sys.modules, "BoneWatertightLib.stages.prepare", None)
    monkeypatch.setitem(sys.modules, "BoneWatertightLib.params", None)
    lab, _, vox_vol = _ball_labels()
    s = baselines.segment_closed_surface(lab, 3)
    assert abs(enclosed_volume(s.vertices, s.faces) / vox_vol - 1) < 0.03
