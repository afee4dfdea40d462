"""Smoke test of the benchmark harness (one fast method on the tiny phantom)."""

import os

import numpy as np

import benchmark


def test_plane_segments_of_a_tetrahedron():
    v = np.array([[0.0, 0, 0], [2, 0, 0], [0, 2, 0], [0, 0, 2]])
    f = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    seg = benchmark._plane_segments(v, f, axis=2, level=1.0)
    assert seg.shape == (3, 2, 2)  # a triangle cross-section
    pts = seg.reshape(-1, 2)
    assert np.allclose(pts.min(axis=0), [0, 0]) and np.allclose(pts.max(axis=0), [1, 1])


def test_harness_runs_and_reports(tmp_path):
    out = tmp_path / "bench"
    rc = benchmark.main(["--cases", "tiny", "--out", str(out), "--samples", "2000",
                         "--methods", "threshold_mc", "--timeout", "300"])
    assert rc == 0
    text = (out / "REPORT.md").read_text()
    assert "| threshold_mc | NO |" in text  # several components: not watertight
    assert os.path.exists(out / "tiny" / "cdf.png") and os.path.exists(out / "tiny" / "sections.png")
    assert (out / "results.json").exists()
