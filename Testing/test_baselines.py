"""The plain alternatives run on the tiny phantom and return sensible surfaces."""

import numpy as np
import pytest

import baselines
from BoneWatertightLib.mesh.checks import check_surface
from BoneWatertightLib.mesh import enclosed_volume
from BoneWatertightLib.params import preset
from metrics import surface_distance
from phantoms import make_phantom


@pytest.fixture(scope="module")
def tiny():
    return make_phantom("tiny", seed=0)


@pytest.fixture(scope="module")
def params():
    return preset("femur", spacing=0.5)


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
    raw = (prep.ct >= params.ht) & (prep.ct <= params.theta_max)
    assert m.sum() > 0 and m.sum() <= raw.sum()
    assert not (m & ~raw).any()
