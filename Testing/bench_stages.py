"""Per-stage time and memory of one pipeline run (Testing/benchmark.py --profile).

The worker (Testing/bench_worker.py, task key ``stage_memory``) returns memory samples of its
own process taken every few milliseconds by a second process (VmRSS, and the exact peak since
the previous sample: VmHWM read and reset), in seconds from the start of the run, with the
report's ``stage_spans`` (when each timed stage of each bone ran). Here they are put together:

- **s**: the stage's seconds (its spans' durations: report.timings, summed over the bones);
- **wall s**: how long at least one bone was in the stage (the union of its spans);
- **peak MB**: the largest resident memory of the process while the stage ran: the largest
  sample peak over the sample intervals that overlap one of its spans. With bones on threads,
  the memory another bone holds at the same time counts too: a peak is attributed to every
  stage active then;
- **end MB**: the resident memory at the first sample at or after the stage's last span ended;
- **(outside the timed stages)**: the run's time outside every span (auto thresholds, the
  refinement's smoothed CT, the pair checks, the reports, ...), and the peak then;
- **total**: the run (report.timings.total), its peak and the resident memory at its end.

Nothing here is timed; everything is a pure function of the worker's result.
"""

from __future__ import annotations

import math
import os

import numpy as np

from bench_common import fmt

STAGE_ORDER = ["import_open3d", "prepare", "filter", "thresholds", "ownership", "threshold", "visible",
               "poisson", "territories", "refine_field", "deform", "refine", "contacts", "cap",
               "checks", "plausibility"]
OUTSIDE = "(outside the timed stages)"


def union(intervals):
    """The sorted, merged union of (start, end) intervals."""
    out = []
    for a, b in sorted(intervals):
        if out and a <= out[-1][1]:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return [(a, b) for a, b in out]


def complement(intervals, lo, hi):
    """The parts of [lo, hi] outside the (merged) intervals."""
    out, at = [], lo
    for a, b in union(intervals):
        if a > at:
            out.append((at, min(a, hi)))
        at = max(at, b)
    if at < hi:
        out.append((at, hi))
    return [(a, b) for a, b in out if b > a]


def stage_memory(mem: dict) -> dict:
    """Per-stage seconds, wall seconds, peak and end memory of one sampled run.

    Parameters
    ----------
    mem : dict
        The worker's ``stage_memory``: ``t_s`` (sample times, s from the run's start; sample 0
        is the reset before the call), ``rss_mb``, ``peak_mb`` (the peak over the interval
        (t[i-1], t[i]], NaN for sample 0), ``spans`` (report.stage_spans), ``total_s``,
        ``before_mb``, ``period_s``, ``exact``.

    Returns
    -------
    dict
        ``stages``: {stage: {seconds, wall_s, peak_mb, end_mb, spans, bones}} in the order of
        STAGE_ORDER (then any other stage); ``outside`` and ``total`` rows (same keys); and the
        sampling's figures (samples, period, largest gap between samples, exact peaks or not).
    """
    t = np.asarray(mem["t_s"], float)
    rss = np.asarray(mem["rss_mb"], float)
    peak = np.asarray(mem["peak_mb"], float)
    total = float(mem["total_s"])

    def peak_in(a, b):
        hit = np.flatnonzero((t[1:] >= a) & (t[:-1] <= b)) + 1
        return float(np.nanmax(peak[hit])) if len(hit) else float("nan")

    def rss_at(x):
        i = min(int(np.searchsorted(t, x, side="left")), len(t) - 1)
        return float(rss[i])

    groups = {}
    for s in mem["spans"]:
        groups.setdefault(s["stage"], []).append(s)
    order = [k for k in STAGE_ORDER if k in groups] + sorted(k for k in groups if k not in STAGE_ORDER)
    stages = {}
    for k in order:
        ss = groups[k]
        iv = [(s["start_s"], s["end_s"]) for s in ss]
        last = max(ss, key=lambda s: s["end_s"])
        stages[k] = {"seconds": sum(b - a for a, b in iv),
                     "wall_s": sum(b - a for a, b in union(iv)),
                     "peak_mb": max(peak_in(a, b) for a, b in iv),
                     "end_mb": rss_at(last["end_s"]),
                     "spans": len(ss), "bones": len({s.get("label") for s in ss})}
    gaps = complement([(s["start_s"], s["end_s"]) for s in mem["spans"]], 0.0, total)
    gap_peaks = [peak_in(a, b) for a, b in gaps]
    outside = {"seconds": sum(b - a for a, b in gaps), "wall_s": sum(b - a for a, b in gaps),
               "peak_mb": max(gap_peaks) if gap_peaks else float("nan"), "end_mb": float("nan"),
               "gaps": len(gaps),
               "longest_gap": max(gaps, key=lambda g: g[1] - g[0]) if gaps else None}
    whole = {"seconds": total, "wall_s": total, "peak_mb": peak_in(0.0, total),
             "end_mb": rss_at(total)}
    return {"stages": stages, "outside": outside, "total": whole,
            "rss_at_start_mb": rss_at(0.0), "before_call_peak_mb": mem.get("before_mb"),
            "samples": int(len(t)), "period_s": mem.get("period_s"),
            "max_sample_gap_s": float(np.diff(t).max()) if len(t) > 1 else float("nan"),
            "exact": bool(mem.get("exact"))}


def stage_table(row: dict, title: str) -> str:
    """The Markdown table of a profiled run (``row["stage_table"]`` from :func:`stage_memory`),
    with its title line and, when measured, the ratio to 3D Slicer's default closed surface."""
    st = (row or {}).get("stage_table")
    if not row or not row.get("ok") or not st:
        return f"(no per-stage table of {title}: {(row or {}).get('error')})"
    total = st["total"]["seconds"]
    head = (f"Per-stage time and memory, {title}: d = {row.get('spacing_mm')} mm, {row.get('faces')} "
            f"faces, {row.get('bones_ok')} bone(s) on {row.get('bone_threads')} thread(s); call "
            f"{fmt(row.get('seconds'), 1)} s, process peak {fmt(row.get('peak_rss_mb'), 0)} MB (VmHWM, "
            f"imports and inputs included), RSS before the call {fmt(row.get('base_rss_mb'), 0)} MB; "
            f"load average {row.get('load')} at its start; memory sampled every "
            f"{1e3 * (st.get('period_s') or 0):.0f} ms (largest gap {1e3 * st['max_sample_gap_s']:.0f} ms), "
            + ("exact peaks between samples (VmHWM reset)" if st.get("exact") else
               "RSS samples only (VmHWM reset refused: short peaks can be missed)") + ".")
    lines = [head, "", "| stage | s | % of total | wall s | peak MB | end MB |", "|---|---|---|---|---|---|"]

    def cells(name, r, bold=False):
        pct = 100.0 * r["seconds"] / total if total else float("nan")
        vals = [f"{r['seconds']:.2f}", f"{pct:.0f}" if math.isfinite(pct) else "-", f"{r['wall_s']:.2f}",
                fmt(r["peak_mb"], 0), fmt(r["end_mb"], 0)]
        if bold:
            name, vals = f"**{name}**", [f"**{v}**" for v in vals]
        return "| " + " | ".join([name] + vals) + " |"

    for k, r in st["stages"].items():
        lines.append(cells(k, r))
    lines.append(cells(OUTSIDE, st["outside"]))
    lines.append(cells("total", st["total"], bold=True))
    several = row.get("bones_ok", 1) > 1 or row.get("bone_threads", 1) > 1
    lines += ["", "s = the stage's seconds (report.timings" + (", summed over the bones" if several else "")
              + "); wall s = time at least one bone was in it; peak MB = the process's largest resident "
              "memory while the stage ran (a sample interval overlapping any of its spans"
              + ("; bones on threads: a peak counts for every stage active at the time" if several else "")
              + "); end MB = resident memory at the end of its last span; a stage shorter than a few "
              "sample periods carries the peak of the few ms around it. RSS at the run's start "
              f"{fmt(st.get('rss_at_start_mb'), 0)} MB."]
    sl = row.get("slicer_default") or {}
    if sl:
        text = (f"3D Slicer's default closed surface on the same input ({row.get('slicer_what')}: threshold "
                f"[150, 2500] HU on the CT's grid, islands touching the segment, flying edges + windowed "
                f"sinc), same run: " + (f"{fmt(sl.get('seconds'), 2)} s (fastest of "
                                        f"{len(sl.get('all_seconds') or [1])}), peak {fmt(sl.get('peak_rss_mb'), 0)} MB; "
                                        f"call / Slicer = **{fmt(row.get('ratio_call_to_slicer'), 1)} ×**"
                                        if sl.get("ok") else "FAILED: " + str(sl.get("error"))))
        cli = row.get("cli") or {}
        if cli:
            text += (f"; whole CLI run {fmt(cli.get('seconds'), 1)} s (exit {cli.get('exit_code')}, peak "
                     f"{fmt(cli.get('peak_rss_mb'), 0)} MB), CLI / Slicer = **{fmt(row.get('ratio_cli_to_slicer'), 1)} ×**")
        lines += ["", text + "."]
    return "\n".join(lines)


def figure(mem: dict, path: str, title: str) -> str:
    """RSS and the peak between samples against time, the stage spans below (one row per
    bone, the shared stages on top)."""
    from bench_common import plt

    p = plt()
    t = np.asarray(mem["t_s"])
    fig, (ax, bx) = p.subplots(2, 1, figsize=(11, 6), sharex=True, gridspec_kw={"height_ratios": [2, 1]})
    ax.plot(t, mem["rss_mb"], lw=0.8, label="RSS")
    ax.step(t, mem["peak_mb"], where="pre", lw=0.6, alpha=0.7, label="peak since the previous sample")
    ax.set_ylabel("MB")
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title(title)
    rows = [None] + sorted({s["label"] for s in mem["spans"] if s["label"] is not None})
    names = {s["label"]: s["bone"] for s in mem["spans"]}
    cmap = p.get_cmap("tab20")
    colour = {k: cmap(i % 20) for i, k in enumerate(STAGE_ORDER)}
    for s in mem["spans"]:
        y = rows.index(s["label"])
        bx.barh(y, s["end_s"] - s["start_s"], left=s["start_s"], height=0.8,
                color=colour.get(s["stage"], "grey"), edgecolor="none")
    bx.set_yticks(range(len(rows)))
    bx.set_yticklabels(["shared" if r is None else str(names[r]) for r in rows], fontsize=7)
    bx.invert_yaxis()
    bx.set_xlabel("s from the start of the run")
    handles = [p.Rectangle((0, 0), 1, 1, color=colour[k]) for k in STAGE_ORDER
               if any(s["stage"] == k for s in mem["spans"])]
    bx.legend(handles, [k for k in STAGE_ORDER if any(s["stage"] == k for s in mem["spans"])],
              fontsize=6, ncol=7, loc="upper center", bbox_to_anchor=(0.5, -0.35))
    fig.tight_layout()
    os.makedirs(os.path.dirname(path), exist_ok=True)
    fig.savefig(path, dpi=90)
    p.close(fig)
    return path
