"""The Poisson helper process (stages.poisson.PoissonHelper): the same surfaces as in this
process, used only where the process allows helpers (the command line does), and a helper that
fails leaves the run to compute its surfaces itself, with a fallback in the report."""

import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from BoneWatertightLib import pipeline, threads  # noqa: E402
from BoneWatertightLib.stages import poisson  # noqa: E402


def _sphere_points(n=3000, radius=10.0, seed=0):
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return normals * radius + np.array([20.0, 25.0, 30.0]), normals


@pytest.fixture
def helpers_allowed():
    before = threads.helper_processes_allowed()
    threads.allow_helper_processes(True)
    yield
    threads.allow_helper_processes(before)


@pytest.fixture
def made(monkeypatch):
    """The PoissonHelpers the run makes (real ones), in order."""
    helpers = []
    real = poisson.PoissonHelper

    def spy():
        helpers.append(real())
        return helpers[-1]

    monkeypatch.setattr(poisson, "PoissonHelper", spy)
    return helpers


def test_the_helper_computes_the_surface_this_process_computes():
    points, normals = _sphere_points()
    here = poisson.poisson_surface(points, normals, 5)
    with poisson.PoissonHelper() as helper:
        there = poisson.poisson_surface(points, normals, 5, helper)
        assert helper.error is None
    assert np.array_equal(here.faces, there.faces)
    assert np.array_equal(here.vertices, there.vertices)


def test_a_helper_that_died_says_why_and_the_surface_is_made_here():
    points, normals = _sphere_points()
    helper = poisson.PoissonHelper()
    process = helper._process
    process.kill()
    process.join(10)
    assert helper.mesh(points, normals, 5) is None
    assert "stopped" in helper.error
    surface = poisson.poisson_surface(points, normals, 5, helper)  # falls back to this process
    assert np.array_equal(surface.faces, poisson.poisson_surface(points, normals, 5).faces)
    helper.close()  # again: harmless


def test_a_helper_that_never_answers_is_given_up(monkeypatch):
    # e.g. an interpreter that starts an application instead of the helper: alive, silent
    import multiprocessing

    points, normals = _sphere_points()
    monkeypatch.setattr(poisson, "HELPER_START_TIMEOUT_S", 1.0)
    helper = poisson.PoissonHelper()
    silent, keep = multiprocessing.Pipe()  # nobody writes to ``keep``
    helper._conn.close()
    helper._conn = silent
    assert helper.mesh(points, normals, 5) is None
    assert "did not answer within 1 s" in helper.error
    assert helper._process is None  # stopped
    keep.close()


def test_an_error_in_the_helper_is_the_error_of_this_process():
    # no points: open3d refuses them; the helper says so, and the same call here raises
    points, normals = np.zeros((0, 3)), np.zeros((0, 3))
    with poisson.PoissonHelper() as helper:
        with pytest.raises(RuntimeError, match="no normals"):
            poisson.poisson_surface(points, normals, 5, helper)
        assert helper.error.startswith("it failed: RuntimeError")


def test_the_library_starts_no_helper_unless_its_process_allows_it(monkeypatch):
    from test_child_run import NAMES, PARAMS, two_balls

    started = []
    monkeypatch.setattr(poisson, "PoissonHelper",
                        lambda: started.append(1) or pytest.fail("no helper expected"))
    threads.allow_helper_processes(False)
    ct, labels, _ = two_balls()
    res = pipeline.reconstruct_many(ct, labels, [1, 2], PARAMS, names=NAMES)
    assert not started
    assert res.report.input["poisson_process"] == "this"


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="bones run one at a time on one CPU")
def test_bones_together_get_the_same_surfaces_through_the_helper(helpers_allowed, made):
    from test_child_run import NAMES, PARAMS, two_balls

    ct, labels, _ = two_balls()
    through = pipeline.reconstruct_many(ct, labels, [1, 2], PARAMS, names=NAMES)
    assert len(made) == 1 and made[0].error is None
    assert made[0]._process is None  # stopped once the surfaces were made
    assert through.report.input["poisson_process"] == "helper"
    assert not [f for f in through.report.fallbacks if f.stage == "poisson"]
    threads.allow_helper_processes(False)
    here = pipeline.reconstruct_many(ct, labels, [1, 2], PARAMS, names=NAMES)
    for a, b in zip(through.bones, here.bones):
        assert np.array_equal(a.surface.faces, b.surface.faces)
        assert np.array_equal(a.surface.vertices, b.surface.vertices)


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="bones run one at a time on one CPU")
def test_a_failed_helper_is_a_fallback_in_the_report(helpers_allowed, monkeypatch):
    from test_child_run import NAMES, PARAMS, two_balls

    class Broken(poisson.PoissonHelper):
        def __init__(self):
            super().__init__()
            self._process.kill()

    monkeypatch.setattr(poisson, "PoissonHelper", Broken)
    ct, labels, _ = two_balls()
    res = pipeline.reconstruct_many(ct, labels, [1, 2], PARAMS, names=NAMES)
    assert all(b.ok for b in res.bones)
    assert res.report.input["poisson_process"] == "this"
    notes = [f for f in res.report.fallbacks if f.stage == "poisson"]
    assert len(notes) == 1 and "helper process failed" in notes[0].what


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="bones run one at a time on one CPU")
def test_no_helper_where_the_memory_limit_has_no_room_for_it(helpers_allowed, made,
                                                            monkeypatch):
    import dataclasses

    from test_child_run import NAMES, PARAMS, two_balls

    # the bones' budget is the limit less what the process holds: here no room for the helper
    monkeypatch.setattr(pipeline, "_held_bytes", lambda: 0.9 * 1024 ** 3)
    ct, labels, _ = two_balls()
    res = pipeline.reconstruct_many(ct, labels, [1, 2],
                                    dataclasses.replace(PARAMS, max_memory_gb=1.0), names=NAMES)
    assert all(b.ok for b in res.bones)
    assert not made
    assert res.report.input["poisson_process"] == "this"
