"""Benchmarks of the Slicer-facing paths on slicer-core's real MRML classes (headless, no Qt).

  python Testing/bench_slicer.py preview   # live threshold preview on a 512 x 512 x 500 CT
  python Testing/bench_slicer.py progress  # longest gap between progress callbacks, femur phantom
  python Testing/bench_slicer.py           # both

``preview``: a 512 x 512 x 500 int16 CT (0.8 x 0.8 x 1.0 mm) with a femur-sized bone and its
rough segment (a coarse label map) as MRML nodes; BoneWatertightLib.app.preview.ThresholdPreview as the
panel uses it while a threshold slider is dragged: the first update (builds the crop cache), then
one update per drag step. Target: <= 50 ms per update.

``progress``: Testing/phantoms.py make_phantom("femur") as MRML nodes, nodes.run_on_nodes at the
library's defaults with a progress callback that records the time of every call, in a fresh
process (the open3d import is part of the run, as on a first Apply). Prints the longest gaps
between successive callbacks and the messages on both sides, i.e. where a frozen panel would be
(the Slicer panel paints and honours Cancel only inside the callback). Target: <= 0.5 s.

A benchmark, not a test: it prints figures and asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)


def _scene():
    import slicer

    scene = slicer.vtkMRMLScene()
    logic = slicer.vtkSlicerSegmentationsModuleLogic()
    logic.SetMRMLScene(scene)
    scene._bw_logic = logic
    return scene


def bench_preview(steps: int = 60) -> dict:
    import SimpleITK as sitk

    from BoneWatertightLib import mrml
    from BoneWatertightLib.app.preview import ThresholdPreview

    scene = _scene()
    size = (512, 512, 500)  # i, j, k
    spacing = np.array([0.8, 0.8, 1.0])
    t0 = time.perf_counter()
    k, j, i = np.ogrid[0:size[2], 0:size[1], 0:size[0]]
    x, y, z = (i - 256) * spacing[0], (j - 256) * spacing[1], k * spacing[2]
    ct = np.full((size[2], size[1], size[0]), -1000, np.int16)  # air
    body = (x / 180.0) ** 2 + (y / 150.0) ** 2 <= 1.0
    ct[np.broadcast_to(body, ct.shape)] = 40
    # a femur-sized bone: a 30 mm shaft from z = 30 to 470 mm, a 50 mm head and condyles
    shaft = (x - 60.0) ** 2 + (y + 10.0) ** 2 <= 15.0 ** 2
    bone = shaft & (z >= 30) & (z <= 470)
    head = (x - 60.0) ** 2 + (y + 10.0) ** 2 + (z - 450.0) ** 2 <= 25.0 ** 2
    condyles = ((x - 60.0) / 40.0) ** 2 + ((y + 10.0) / 30.0) ** 2 + ((z - 50.0) / 30.0) ** 2 <= 1.0
    bone = bone | head | condyles
    ct[bone] = 1200
    ct += np.random.default_rng(0).normal(0.0, 15.0, ct.shape).astype(np.int16)
    image = sitk.GetImageFromArray(ct)
    image.SetSpacing(spacing.tolist())
    volume = mrml.volume_node_from_sitk(scene, image, "CT 512x512x500")
    del ct
    # the rough segment on a 4 mm grid (as a quick manual or AI segmentation would be)
    fine = sitk.GetImageFromArray(bone.astype(np.uint8))
    fine.SetSpacing(spacing.tolist())
    del bone
    coarse_size = [int(s * sp / 4.0) for s, sp in zip(size, spacing)]
    mask = sitk.Resample(fine, coarse_size, sitk.Transform(), sitk.sitkNearestNeighbor,
                         [0.0, 0.0, 0.0], [4.0, 4.0, 4.0], np.eye(3).ravel().tolist(), 0, sitk.sitkUInt8)
    del fine
    segmentation, segmentId = mrml.segmentation_node_from_mask(scene, mask, segmentName="femur")
    build = time.perf_counter() - t0

    preview = ThresholdPreview(scene)
    t0 = time.perf_counter()
    preview.update(volume, segmentation, segmentId, 300.0, 150.0, 2500.0)
    first = time.perf_counter() - t0
    times = []
    for step in range(steps):  # a drag of H0 from 200 to 800 HU, then of HT
        h0 = 200.0 + 10.0 * step if step < steps // 2 else 400.0
        ht = 150.0 if step < steps // 2 else 50.0 + 10.0 * (step - steps // 2)
        t0 = time.perf_counter()
        preview.update(volume, segmentation, segmentId, h0, min(ht, h0 - 5.0), 2500.0)
        times.append(time.perf_counter() - t0)
    crop = preview.labelmapNode.GetImageData().GetDimensions()
    ms = 1000.0 * np.array(times)
    result = dict(volume=size, crop=crop, crop_voxels=int(np.prod(crop)), setup_s=build,
                  first_update_ms=1000.0 * first, median_ms=float(np.median(ms)),
                  p95_ms=float(np.percentile(ms, 95)), max_ms=float(ms.max()), steps=steps,
                  cache_builds=preview.cacheBuilds)
    print(f"preview: CT {size[0]}x{size[1]}x{size[2]} ({np.prod(size) / 1e6:.0f} M voxels), "
          f"crop around the segment {crop[0]}x{crop[1]}x{crop[2]} ({np.prod(crop) / 1e6:.1f} M voxels)")
    print(f"preview: first update (builds the crop cache) {result['first_update_ms']:.0f} ms; "
          f"per drag step over {steps} steps: median {result['median_ms']:.1f} ms, "
          f"p95 {result['p95_ms']:.1f} ms, max {result['max_ms']:.1f} ms "
          f"(target <= 50 ms; cache builds {preview.cacheBuilds})", flush=True)
    return result


def bench_progress(case: str = "femur", overrides: dict | None = None) -> dict:
    from phantoms import make_phantom

    t0 = time.perf_counter()
    phantom = make_phantom(case)
    from BoneWatertightLib import mrml
    from BoneWatertightLib.app import nodes

    scene = _scene()
    volume = mrml.volume_node_from_sitk(scene, phantom.ct, f"{case} CT")
    segmentation, segmentId = mrml.segmentation_node_from_mask(scene, phantom.mask, segmentName=case)
    setup = time.perf_counter() - t0
    open3d_loaded = "open3d" in sys.modules
    stamps = []

    def progress(fraction, message):
        stamps.append((time.perf_counter(), fraction, message))
        return True

    start = time.perf_counter()
    model, result = nodes.run_on_nodes(volume, segmentation, segmentId, params=overrides or None,
                                      progress=progress)
    end = time.perf_counter()
    times = [start] + [s[0] for s in stamps] + [end]
    labels = ["(start)"] + [f"{s[2] or '-'} @{100 * s[1]:.1f}%" for s in stamps] + ["(returned)"]
    gaps = np.diff(times)
    order = np.argsort(gaps)[::-1]
    print(f"progress: {case} phantom {phantom.ct.GetSize()} voxels, defaults"
          f"{' + ' + str(overrides) if overrides else ''}; open3d imported before the run: "
          f"{open3d_loaded}; setup {setup:.1f} s")
    print(f"progress: run {end - start:.1f} s, {len(stamps)} callbacks, first after "
          f"{(stamps[0][0] - start) if stamps else float('nan'):.3f} s, "
          f"longest gap {gaps.max():.2f} s (target <= 0.5 s)")
    for n in order[:8]:
        print(f"  gap {gaps[n]:6.2f} s  between  {labels[n]}  and  {labels[n + 1]}")
    # the adapter's own first phase (export, open3d import): up to its last report
    last_own = max((n for n, s in enumerate(stamps) if s[1] < nodes.PIPELINE_START), default=-1)
    own = gaps[:last_own + 1]
    if len(own):
        print(f"progress: first phase (mrml: CT/segment export, open3d import) "
              f"{times[last_own + 1] - start:.2f} s, {last_own + 1} callbacks, longest gap {own.max():.3f} s; "
              f"then the pipeline's first report comes after {gaps[last_own + 1]:.2f} s")
    stage_times = result.report.timings
    print("progress: pipeline stage times (s): " + ", ".join(
        f"{k} {v:.2f}" for k, v in vars(stage_times).items() if isinstance(v, float)), flush=True)
    return dict(run_s=end - start, callbacks=len(stamps), longest_gap_s=float(gaps.max()),
                longest_gap_between=(labels[order[0]], labels[order[0] + 1]))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("what", nargs="?", choices=("preview", "progress", "all"), default="all")
    parser.add_argument("--case", default="femur", help="phantom for 'progress' (default femur)")
    parser.add_argument("--spacing", type=float, help="override the resample spacing for 'progress'")
    args = parser.parse_args(argv)
    if args.what in ("preview", "all"):
        bench_preview()
    if args.what in ("progress", "all"):
        bench_progress(args.case, {"spacing": args.spacing} if args.spacing else None)


if __name__ == "__main__":
    main()
