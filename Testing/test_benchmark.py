"""Smoke test of the benchmark harness (Testing/benchmark.py): fast, no timing targets.

One cheap method on the tiny phantom in its own process, the report and results written; the
real-CT part skips cleanly without data; the worker turns a failure into a result; the pure
helpers (plane sections, tables, target verdicts) on small inputs.
"""

import json
import os

import numpy as np

import bench_common
import bench_worker
import benchmark


def test_plane_segments_of_a_tetrahedron():
    v = np.array([[0.0, 0, 0], [2, 0, 0], [0, 2, 0], [0, 0, 2]])
    f = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    seg = bench_common.plane_segments(v, f, axis=2, level=1.0)
    assert seg.shape == (3, 2, 3)  # a triangle cross-section
    pts = seg.reshape(-1, 3)
    assert np.allclose(pts[:, 2], 1.0)
    assert np.allclose(pts[:, :2].min(axis=0), [0, 0]) and np.allclose(pts[:, :2].max(axis=0), [1, 1])


def test_harness_runs_and_reports(tmp_path):
    out = tmp_path / "bench"
    rc = benchmark.main(["--cases", "tiny", "--out", str(out), "--samples", "2000",
                         "--methods", "threshold_mc", "--timeout", "300"])
    assert rc == 0
    text = (out / "REPORT.md").read_text()
    assert "## 1. Phantoms, single bone" in text and "### `tiny`" in text
    # Several components: the threshold surface fails the checks, and the report says so.
    line = next(ln for ln in text.splitlines() if ln.startswith("| threshold + MC + smoothing |"))
    assert "**fail**" in line and "connected components" in line
    assert (out / "tiny" / "cdf.png").exists() and (out / "tiny" / "sections.png").exists()
    res = json.loads((out / "results.json").read_text())
    row = res["phantoms"]["tiny"]["rows"][0]
    assert row["method"] == "threshold_mc" and row["ok"]
    assert row["seconds"] > 0 and row["peak_rss_mb"] > row["base_rss_mb"] > 0
    assert 0 < row["distance"]["mean"] < row["distance"]["p95"] <= row["distance"]["max"]
    assert row["checks"]["ok"] is False and row["volume_ratio"] > 1  # fused with the cup


def test_real_part_skips_without_data(tmp_path):
    out = tmp_path / "bench"
    rc = benchmark.main(["--cases", "none", "--real", "--data", str(tmp_path / "absent"),
                         "--out", str(out)])
    assert rc == 0
    assert "no real CT" in (out / "REPORT.md").read_text()


def test_worker_reports_a_failure_as_a_result(tmp_path):
    res = bench_worker.run_isolated({"kind": "segment_surface", "labels": str(tmp_path / "no.nrrd"),
                                     "value": 1}, 120, str(tmp_path))
    assert res["ok"] is False and "RuntimeError" in res["error"]
    assert res["process_seconds"] > 0
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".pkl")]  # task files removed


def test_targets_state_verdicts():
    def row(method, mean, p95, mx, bias, vol=1.0, ok=True):
        d = {"mean": mean, "p95": p95, "max": mx, "b_to_a": {"frac_under_1": 1.0}}
        return {"method": method, "ok": True, "distance": d, "bias_mm": bias, "volume_ratio": vol,
                "checks": {"ok": ok, "problems": [], "genus": 0}}
    results = {"phantoms": {
        "femur": {"rows": [row("full", 0.15, 0.22, 0.7, 0.02), row("m0", 0.2, 0.3, 0.5, 0.0),
                           row("m0_deform", 0.2, 0.3, 0.9, 0.0)]},
        "osteo": {"rows": [row("full", 0.2, 0.3, 0.9, 0.1), row("m0", 0.3, 0.6, 1.5, -0.2),
                           row("m0_deform", 0.25, 0.4, 1.2, 0.0)]}}}
    got = {t[1][:30]: t[3] for t in benchmark.targets(results)}
    assert got["femur phantom, defaults: p95 ≤"] is True
    assert got["femur-sized phantom, 1 mm slic"] is True
    assert got["rough segments with holes stil"] is True
    assert got["the paper's deformation improv"] is True  # osteo 0.6 -> 0.4
    assert got["… and never raises the maximum"] is False  # femur 0.5 -> 0.9
    table = bench_common.md_table(["a", "b"], [[1, "x|y"]])
    assert table.splitlines()[2] == "| 1 | x/y |"
