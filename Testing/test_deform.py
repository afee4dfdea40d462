"""Deformer.run() (paper §2.4, stages/deform.py) on small meshes: the control-weight rules, the
halving of alpha and beta once progress stalls (the stable stage), the extra iterations, the
back-off of a step that would fold the mesh, and the fallback to the last verified iterate.

The mesh is a sphere of radius 10 mm (edge d* ~0.9 mm); the constraint points lie on a sphere
of radius 11 (all of it, or only its upper part), or on the mesh's own sphere (no progress:
the stable stage at once).
"""

import numpy as np
import pytest

from BoneWatertightLib.mesh import mean_edge_length
from BoneWatertightLib.mesh.checks import check_surface
from BoneWatertightLib.stages import deform
from BoneWatertightLib.stages.deform import Deformer

from test_pipeline import sphere_mesh


@pytest.fixture(scope="module")
def sphere():
    mesh = sphere_mesh(10.0, 1.0)
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(60000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return mesh, mean_edge_length(mesh.vertices, mesh.faces), directions


def _deformer(sphere, radius=11.0, upper_only=False, **kwargs):
    mesh, d, directions = sphere
    points = radius * directions
    if upper_only:
        points = points[directions[:, 2] > 0.3]
    return Deformer(mesh.vertices, mesh.faces, points,
                    lambda p: np.linalg.norm(p, axis=1) < radius, d, **kwargs)


class _Spy:
    """Records what run() hands to every step (stationary, stable) and the vertices before."""

    def __init__(self, deformer):
        self.deformer = deformer
        self.calls = []
        self._step = deformer.step
        deformer.step = self

    def __call__(self, j, total, alpha, beta, full_check=True, stationary=None, stable=False):
        self.calls.append(dict(before=self.deformer.v.copy(), alpha=alpha, beta=beta,
                               stationary=None if stationary is None else stationary.copy(),
                               stable=stable))
        return self._step(j, total, alpha, beta, full_check=full_check, stationary=stationary,
                          stable=stable)


# ---------------------------------------------------------------------------------------
# the control weights

def test_control_weights_rule():
    matched = np.array([True, False, False, False])
    stationary = np.array([False, True, False, False])
    assert Deformer.control_weights(matched).tolist() == [1, 0, 0, 0]
    assert Deformer.control_weights(matched, stationary).tolist() == [1, 1, 0, 0]
    assert Deformer.control_weights(matched, stationary, stable=True).tolist() == [1, 1, 1, 1]


def test_run_updates_the_control_weights_as_the_paper(sphere):
    """Constraints on the upper part only: iteration 1 controls the matched vertices alone;
    from then on also those that moved less than STATIONARY_MOVE d* in the iteration before;
    once progress stalls (the stable stage) every vertex. The unmatched lower part, free,
    is not pulled to the points."""
    df = _deformer(sphere, upper_only=True, iterations=6)
    spy = _Spy(df)
    v = df.run()
    d, n = df.d, len(v)
    history = [h for h in df.history if not h.get("rejected")]
    assert len(history) == len(spy.calls) >= 6
    assert spy.calls[0]["stationary"] is None and not spy.calls[0]["stable"]
    assert history[0]["controlled"] == history[0]["matched"] < n
    for k in range(1, len(spy.calls)):
        moved = np.linalg.norm(spy.calls[k]["before"] - spy.calls[k - 1]["before"], axis=1)
        expected = moved < deform.STATIONARY_MOVE * d
        assert np.array_equal(spy.calls[k]["stationary"], expected), k
        assert spy.calls[k]["stable"] == any(h["mean_move"] < deform.STALL_MOVE * d
                                             for h in history[:k]), k
        if spy.calls[k]["stable"]:
            assert history[k]["controlled"] == n
        else:
            assert history[k]["matched"] < history[k]["controlled"] < n  # the stationary joined
    assert any(c["stable"] for c in spy.calls)  # this case reaches the stable stage
    radius = np.linalg.norm(v, axis=1)
    assert np.median(radius[v[:, 2] > 6]) == pytest.approx(11.0, abs=0.05)
    assert np.median(radius[v[:, 2] < -6]) == pytest.approx(10.0, abs=0.05)
    assert check_surface(v, df.f).ok


# ---------------------------------------------------------------------------------------
# alpha and beta, extra iterations

def _check_weight_schedule(df):
    history = [h for h in df.history if not h.get("rejected")]
    stalled = False
    for prev, rec in zip(history, history[1:]):
        stalled |= prev["mean_move"] < deform.STALL_MOVE * df.d
        for key, start in (("alpha", df.alpha), ("beta", df.beta)):
            if prev["mean_move"] < deform.STALL_MOVE * df.d:
                expected = max(0.5 * prev[key], deform.MIN_WEIGHT_FRACTION * start)
            else:
                expected = prev[key]
            assert rec[key] == pytest.approx(expected), (key, rec["iteration"])
        assert rec["stable"] == stalled
    return history


def test_alpha_and_beta_halve_at_the_stable_stage_down_to_their_floor(sphere):
    """Points on the mesh's own sphere: no progress from the first iteration, so alpha and
    beta halve after every iteration until MIN_WEIGHT_FRACTION of their start values."""
    df = _deformer(sphere, radius=10.0, iterations=6, alpha=1.0, beta=0.8)
    df.run()
    history = _check_weight_schedule(df)
    assert [h["alpha"] for h in history] == pytest.approx([1.0, 0.5, 0.25, 0.2, 0.2, 0.2])
    assert [h["beta"] for h in history] == pytest.approx([0.8, 0.4, 0.2, 0.16, 0.16, 0.16])
    assert [h["stable"] for h in history] == [False] + [True] * 5


def test_weights_stay_while_the_mesh_moves_and_extra_iterations_follow(sphere):
    """Points 1 mm out: while the mean move exceeds STALL_MOVE d* alpha and beta keep their
    start values; still moving after N = 2 iterations, up to MAX_EXTRA_ITERATIONS full steps
    follow, and the sphere reaches the points."""
    df = _deformer(sphere, iterations=2)
    v = df.run()
    history = _check_weight_schedule(df)
    assert history[0]["mean_move"] > deform.STALL_MOVE * df.d
    assert history[0]["alpha"] == history[1]["alpha"] == 1.0
    assert 2 < len(history) <= 2 + deform.MAX_EXTRA_ITERATIONS
    assert np.median(np.linalg.norm(v, axis=1)) == pytest.approx(11.0, abs=0.05)


# ---------------------------------------------------------------------------------------
# back-off and fallback

def test_a_step_that_folds_the_mesh_is_backed_off_locally(sphere):
    """A solve that pushes one vertex through the sphere (its triangles flip, the surface
    intersects itself): the step keeps that vertex where it was, the rest moves, and the
    result is a valid surface."""
    df = _deformer(sphere, iterations=4)
    df.clean_v = df.v.copy()
    solve = df.solve
    k = int(np.argmax(df.v[:, 2]))

    def folding(*args):
        new = solve(*args)
        new[k] = -new[k]
        return new

    df.solve = folding
    new, matched, bad = df.step(1, 4, 1.0, 1.0)
    assert new is not None and bad == 0
    assert np.array_equal(new[k], df.v[k])
    moved = np.linalg.norm(new - df.v, axis=1) > 0.1 * df.d
    assert moved.mean() > 0.9
    assert check_surface(new, df.f).ok


class _Verdicts:
    """deform.safe_update, whose answer is overridden to 'not ok' on the calls listed."""

    def __init__(self, monkeypatch, reject):
        self.calls = []
        self.reject = reject
        self.real = deform.safe_update
        monkeypatch.setattr(deform, "safe_update", self)

    def __call__(self, old, new, faces, *args, **kwargs):
        out, ok, bad = self.real(old, new, faces, *args, **kwargs)
        exact = kwargs.get("intersections", True)
        self.calls.append(exact)
        if self.reject(len(self.calls), exact):
            return out, False, max(bad, 1)
        return out, ok, bad


def test_a_rejected_attempt_is_redone_with_doubled_beta(sphere, monkeypatch):
    """The first attempt rejected: the step accepted is the one solved with beta doubled
    (the same system as a step started with 2 beta)."""
    reference = _deformer(sphere, iterations=4)
    reference.clean_v = reference.v.copy()
    expected, _, _ = reference.step(1, 4, 1.0, 2.0)
    df = _deformer(sphere, iterations=4)
    df.clean_v = df.v.copy()
    _Verdicts(monkeypatch, lambda n, exact: n == 1)
    new, _, bad = df.step(1, 4, 1.0, 1.0)
    assert df.last_step["attempts"] == 2 and bad == 0
    np.testing.assert_allclose(new, expected, atol=1e-6)


def test_an_iteration_no_attempt_saves_is_rejected_and_the_mesh_kept(sphere, monkeypatch):
    df = _deformer(sphere, iterations=4)
    m0 = df.v.copy()
    _Verdicts(monkeypatch, lambda n, exact: True)
    v = df.run()
    assert df.history == [{"iteration": 1, "rejected": True, "flipped": 1,
                           "controlled": len(m0), "attempts": deform.STEP_ATTEMPTS}]
    assert np.array_equal(v, m0)


@pytest.mark.parametrize("final_check_passes", [True, False])
def test_unverified_iterates_fall_back_to_the_last_verified_one(sphere, monkeypatch,
                                                                final_check_passes):
    """Iteration 1 passes the cheap flip test only (the exact self-intersection test runs
    every FULL_CHECK_EVERY iterations); iteration 2 is rejected. run() then checks iteration
    1 exactly: kept when it passes, else the last verified vertices (M0) come back."""
    assert deform.FULL_CHECK_EVERY > 2
    df = _deformer(sphere, iterations=4)
    m0 = df.v.copy()
    verdicts = _Verdicts(monkeypatch, lambda n, exact: 2 <= n <= 1 + deform.STEP_ATTEMPTS
                         or (exact and not final_check_passes))
    v = df.run()
    assert [h.get("rejected", False) for h in df.history] == [False, True]
    assert verdicts.calls == [False] * (1 + deform.STEP_ATTEMPTS) + [True]
    if final_check_passes:
        assert np.median(np.linalg.norm(v, axis=1)) > np.median(np.linalg.norm(m0, axis=1)) + 0.1
    else:
        assert np.array_equal(v, m0)
