"""How long the panel's GUI thread is blocked by a run in a child process, and the longest
gap between progress reports with and without the child (issue 13).

One femur-sized phantom (``make_phantom("femur")``, the library's defaults), on slicer-core's
real MRML nodes as the panel has them (CT volume, segmentation with the rough segment):

1. child process, as the panel's Apply does (``nodes.start_many_on_nodes``, ``poll()`` every
   100 ms as its QTimer, ``nodes.finish_many_on_nodes``): every interval the calling thread is
   busy without a chance to paint (export: between its cooperative progress calls; each poll;
   the finish), and the longest gap between the child's progress lines (as received);
2. in this process (``nodes.run_many_on_nodes``, the logic's process()): the longest gap between
   progress callbacks, and the stage it falls in.

The two runs go one after the other (never together). Usage::

    python Testing/measure_child_run.py [--case femur] [--json out.json] [--only child|inprocess]
        [--set on_implausible=warn ...]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

POLL_INTERVAL_S = 0.1  # the panel's CHILD_POLL_INTERVAL_MS


def _stage_of(fraction: float, pipeline_start: float) -> str:
    """The pipeline stage (pipeline.STAGES) an overall fraction of an MRML run falls in."""
    from BoneWatertightLib.pipeline import STAGES

    if fraction < pipeline_start:
        return "export/import (adapter)"
    f = (fraction - pipeline_start) / (1.0 - pipeline_start)
    for name, a, b in STAGES:
        if a <= f < b or (b == 1.0 and f >= a):
            return name
    return "?"


def _longest_gap(stamps):
    """(seconds, index) of the longest gap between consecutive (t, fraction, message)."""
    best, where = 0.0, None
    for n in range(1, len(stamps)):
        gap = stamps[n][0] - stamps[n - 1][0]
        if gap > best:
            best, where = gap, n
    return best, where


def _nodes(case: str):
    import slicer

    from BoneWatertightLib import mrml
    from phantoms import make_phantom

    t0 = time.perf_counter()
    ph = make_phantom(case)
    scene = slicer.vtkMRMLScene()
    logic = slicer.vtkSlicerSegmentationsModuleLogic()
    logic.SetMRMLScene(scene)
    volume = mrml.volume_node_from_sitk(scene, ph.ct, "CT")
    seg, segmentId = mrml.segmentation_node_from_mask(scene, ph.mask, "Segmentation", "femur")
    info = {"case": case, "ct_size": list(ph.ct.GetSize()), "ct_spacing": list(ph.ct.GetSpacing()),
            "phantom_s": time.perf_counter() - t0}
    return scene, logic, volume, seg, segmentId, info


def measure_child(volume, seg, segmentId, params=None) -> dict:
    from BoneWatertightLib.app import nodes

    blocks = []  # (seconds, what)
    calls = []

    def progress(fraction, message):
        calls.append((time.perf_counter(), fraction, message))
        return True

    t_enter = time.perf_counter()
    run = nodes.start_many_on_nodes(volume, seg, [segmentId], None, params, progress=progress,
                                   python=sys.executable)
    t_return = time.perf_counter()
    marks = [t_enter] + [c[0] for c in calls] + [t_return]
    for n in range(1, len(marks)):
        what = calls[n - 1][2] if n - 1 < len(calls) else "start the child"
        blocks.append((marks[n] - marks[n - 1], f"export: until the call after '{what}'"
                       if n - 1 < len(calls) else "export: last call -> start returned"))
    start_total = t_return - t_enter
    polls = []
    while True:
        t0 = time.perf_counter()
        state = run.poll()
        polls.append(time.perf_counter() - t0)
        if state.finished:
            break
        time.sleep(POLL_INTERVAL_S)
    t0 = time.perf_counter()
    error = None
    try:
        summary = nodes.finish_many_on_nodes(run).summaryLines()
    except Exception as exc:  # the blocks and gaps up to the failure are still measured
        error, summary = f"{type(exc).__name__}: {exc}", []
    finish = time.perf_counter() - t0
    blocks.append((max(polls), "the longest poll()"))
    blocks.append((finish, "finish_many_on_nodes (surface, report, model node)"))
    log = run.childRun.progress_log
    gap, n = _longest_gap(log)
    first_line = log[0][0] - t_return if log else None
    longest = max(blocks)
    return {
        "gui_longest_block_s": longest[0], "gui_longest_block_at": longest[1],
        "export_and_start_s": start_total, "export_calls": len(calls),
        "polls": len(polls), "poll_max_ms": 1e3 * max(polls),
        "poll_mean_ms": 1e3 * sum(polls) / len(polls), "finish_s": finish,
        "child_lines": len(log), "child_longest_gap_s": gap,
        "child_longest_gap_between": [log[n - 1][2], log[n][2]] if n else None,
        "child_longest_gap_stage": _stage_of(nodes.PIPELINE_START + (1 - nodes.PIPELINE_START)
                                             * log[n - 1][1], nodes.PIPELINE_START) if n else None,
        "start_to_first_line_s": first_line,
        "child_run_s": (log[-1][0] - t_return) if log else None,
        "error": error, "summary": summary,
    }


def measure_in_process(volume, seg, segmentId, params=None) -> dict:
    from BoneWatertightLib.app import nodes

    calls = []

    def progress(fraction, message):
        calls.append((time.perf_counter(), fraction, message))
        return True

    t0 = time.perf_counter()
    error = None
    try:
        out = nodes.run_many_on_nodes(volume, seg, [segmentId], None, params, progress=progress)
        summary = out.summaryLines()
    except Exception as exc:  # the gaps up to the failure are still measured
        error, summary = f"{type(exc).__name__}: {exc}", []
    total = time.perf_counter() - t0
    stamps = [(t0, 0.0, "call")] + calls + [(t0 + total, 1.0, "returned")]
    gap, n = _longest_gap(stamps)
    gaps = sorted(((stamps[i][0] - stamps[i - 1][0], stamps[i - 1][2], stamps[i][2], stamps[i - 1][1])
                   for i in range(1, len(stamps))), reverse=True)[:5]
    return {
        "callbacks": len(calls), "run_s": total, "error": error,
        "longest_gap_s": gap, "longest_gap_between": [stamps[n - 1][2], stamps[n][2]],
        "longest_gap_stage": _stage_of(stamps[n - 1][1], nodes.PIPELINE_START),
        "top_gaps": [{"s": g, "after": a, "before": b, "stage": _stage_of(f, nodes.PIPELINE_START)}
                     for g, a, b, f in gaps],
        "summary": summary,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--case", default="femur")
    parser.add_argument("--json", help="write the figures here")
    parser.add_argument("--only", choices=("child", "inprocess"))
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="a parameter other than its default (e.g. on_implausible=warn)")
    args = parser.parse_args(argv)
    from BoneWatertightLib.params import SCHEMA, Parameters

    overrides = {}
    for item in args.set:
        name, _, value = item.partition("=")
        overrides[name] = SCHEMA[name].parse(value)
    params = Parameters().replace(**overrides).validate()
    scene, logic, volume, seg, segmentId, info = _nodes(args.case)
    info["parameters_changed"] = overrides
    result = {"input": info}
    if args.only != "inprocess":
        result["child"] = measure_child(volume, seg, segmentId, params)
        print(json.dumps({"child": result["child"]}, indent=2), flush=True)
        for n in range(scene.GetNumberOfNodes() - 1, -1, -1):  # drop the model: a clean second run
            node = scene.GetNthNode(n)
            if node.IsA("vtkMRMLModelNode"):
                scene.RemoveNode(node)
    if args.only != "child":
        result["in_process"] = measure_in_process(volume, seg, segmentId, params)
        print(json.dumps({"in_process": result["in_process"]}, indent=2), flush=True)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(result, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
