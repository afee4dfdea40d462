"""Smoke test of the benchmark harness (Testing/benchmark.py): fast, no timing targets.

One cheap method on the tiny phantom in its own process, the report and results written; the
real-CT part skips cleanly without data; the worker turns a failure into a result; the pure
helpers (plane sections, tables, target verdicts) on small inputs.
"""

import json
import os

import numpy as np
import pytest

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
    text = (out / "REPORT.md").read_text(encoding="utf-8")
    assert "## 1. Phantoms, single bone" in text and "### `tiny`" in text
    # Several components: the threshold surface fails the checks, and the report says so.
    line = next(ln for ln in text.splitlines() if ln.startswith("| threshold + MC + smoothing |"))
    assert "**fail**" in line and "connected components" in line
    assert (out / "tiny" / "cdf.png").exists() and (out / "tiny" / "sections.png").exists()
    res = json.loads((out / "results.json").read_text(encoding="utf-8"))
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
    assert "no real CT" in (out / "REPORT.md").read_text(encoding="utf-8")


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


# ---------------------------------------------------------------------------- per-stage memory

def _sampled(spans, t, rss, peak, total):
    return {"t_s": t, "rss_mb": rss, "peak_mb": peak, "spans": spans, "total_s": total,
            "before_mb": 100.0, "period_s": 0.1, "exact": True}


def _span(stage, start, end, label=None):
    return {"stage": stage, "bone": None if label is None else f"b{label}", "label": label,
            "start_s": start, "end_s": end}


def test_stage_memory_gives_each_peak_to_the_stages_running_then():
    import bench_stages

    # samples every 0.1 s; sample i's peak is the peak over (t[i-1], t[i]]
    t = [round(0.1 * i, 1) for i in range(-1, 11)]  # -0.1 (the reset) .. 1.0
    rss = [200.0] * len(t)
    peak = [float("nan")] + [210.0] * (len(t) - 1)
    peak[t.index(0.5)] = 900.0  # a spike in (0.4, 0.5]: both bones' poisson, not bone 2's deform
    peak[t.index(0.9)] = 700.0  # a spike in (0.8, 0.9]: outside every stage
    rss[t.index(0.6)] = 450.0   # the RSS when bone 2's deform ends (0.55 -> sample 0.6)
    spans = [_span("prepare", 0.0, 0.2), _span("poisson", 0.2, 0.5, 1), _span("poisson", 0.25, 0.45, 2),
             _span("deform", 0.55, 0.6, 2), _span("checks", 0.6, 0.75, 1)]
    got = bench_stages.stage_memory(_sampled(spans, t, rss, peak, 1.0))
    st = got["stages"]
    assert list(st) == ["prepare", "poisson", "deform", "checks"]  # the pipeline's order
    assert st["poisson"]["seconds"] == pytest.approx(0.5)  # summed over the bones
    assert st["poisson"]["wall_s"] == pytest.approx(0.3)   # their union 0.2-0.5
    assert st["poisson"]["peak_mb"] == 900.0 and st["poisson"]["bones"] == 2
    assert st["deform"]["peak_mb"] == 210.0 and st["deform"]["end_mb"] == 450.0
    assert st["prepare"]["peak_mb"] == 210.0 and st["prepare"]["end_mb"] == 200.0
    out = got["outside"]  # 0.5-0.55 and 0.75-1.0
    assert out["seconds"] == pytest.approx(0.30) and out["gaps"] == 2 and out["peak_mb"] == 900.0
    assert got["total"]["peak_mb"] == 900.0 and got["total"]["seconds"] == 1.0
    assert got["max_sample_gap_s"] == pytest.approx(0.1)
    spans[-1] = _span("checks", 0.6, 0.95, 1)  # now over the 0.8-0.9 spike
    assert bench_stages.stage_memory(_sampled(spans, t, rss, peak, 1.0))["stages"]["checks"]["peak_mb"] == 700.0


def test_profile_prints_per_stage_time_and_memory_beside_slicer(tmp_path):
    """--profile --quick: the tiny phantom's run with its memory sampled; every stage the report
    timed has finite figures, peak >= end, the seconds of report.timings; the Slicer-style
    baseline and the whole CLI run beside it, in the same invocation."""
    out = tmp_path / "bench"
    rc = benchmark.main(["--cases", "none", "--profile", "--quick", "--out", str(out), "--timeout", "300"])
    assert rc == 0
    res = json.loads((out / "results.json").read_text(encoding="utf-8"))
    row = res["profile"]["runs"]["tiny"]
    assert row["ok"] and row["bones_ok"] == 1
    st = row["stage_table"]
    # (a loaded machine delays the sampler: its largest gap is no bound, only its peaks are exact)
    assert st["exact"] and st["samples"] > 50 and 0 < st["max_sample_gap_s"] < row["seconds"]
    timed = {k for k, v in row["timings"].items() if k not in ("total", "import_open3d") and v > 0}
    assert timed >= {"prepare", "filter", "ownership", "threshold", "visible", "poisson", "deform",
                     "refine", "checks", "plausibility"}
    assert timed <= set(st["stages"])
    for k, r in list(st["stages"].items()) + [("total", st["total"])]:
        for key in ("seconds", "wall_s", "peak_mb", "end_mb"):
            assert r[key] is not None and np.isfinite(r[key]), (k, key)
        assert r["peak_mb"] >= r["end_mb"] > 0, k
        assert r["seconds"] == pytest.approx(row["timings"][k], abs=1e-6), k
    assert st["total"]["peak_mb"] == max(r["peak_mb"] for r in [*st["stages"].values(), st["outside"]])
    assert row["peak_rss_mb"] >= st["total"]["peak_mb"] > st["rss_at_start_mb"] > 0
    # one bone: the stages follow one another, the rest of the run is outside them
    assert sum(r["seconds"] for r in st["stages"].values()) + st["outside"]["seconds"] == pytest.approx(
        row["timings"]["total"], abs=1e-6)
    assert row["slicer_default"]["ok"] and row["cli"]["exit_code"] == 0
    assert row["ratio_call_to_slicer"] == pytest.approx(row["seconds"] / row["slicer_default"]["seconds"])
    assert row["ratio_call_to_slicer"] > 1 and row["ratio_cli_to_slicer"] > 1
    text = (out / "profile" / "STAGES.md").read_text(encoding="utf-8")
    assert "| stage | s | % of total | wall s | peak MB | end MB |" in text
    assert all(f"| {k} |" in text for k in timed) and "| **total** |" in text
    assert "call / Slicer = **" in text and "CLI / Slicer = **" in text
    assert "## 5. Profile" in (out / "REPORT.md").read_text(encoding="utf-8")


def test_the_real_table_says_what_the_ownership_moved_between_labels():
    """The real runs' reference is each label as it was: a bone that took a neighbour's label
    part (or gave one) says so beside its name, or its distances would read as misses."""
    import bench_real

    taken = {"pipeline": {"ownership": {"segment_taken_ml": 6.04, "segment_given_ml": 0}}}
    given = {"pipeline": {"ownership": {"segment_taken_ml": 0, "segment_given_ml": 6.04}}}
    assert "+6.0 ml of a neighbour's label" in bench_real._moved_text(taken)
    assert "-6.0 ml of its label" in bench_real._moved_text(given)
    assert bench_real._moved_text({"pipeline": {"ownership": {}}}) == ""
    assert bench_real._moved_text({}) == ""
