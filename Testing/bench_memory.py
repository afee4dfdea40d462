"""Peak memory of the pipeline against its estimate (``stages.prepare.estimate_memory_bytes``).

Each case runs in a process of its own: it reads the CT and the label map from files, imports
open3d, resets the kernel's peak-RSS counter (``/proc/self/clear_refs``) and runs
``reconstruct_many``; the peak RSS above the RSS just before the call is what the run needed
(the inputs the caller already holds are not part of it). The table compares it with the
estimate that ``prepare_labels`` checked against ``max_memory_gb`` (reported as
``estimated_memory_gb``): the ratio peak / estimate must stay below 1 for every case.

    .venv/bin/python Testing/bench_memory.py                 # phantoms + /work/shared/data
    .venv/bin/python Testing/bench_memory.py --quick         # three small cases
    .venv/bin/python Testing/bench_memory.py --json out.json

Linux only (/proc). Cases of ``../shared/data`` (or ``$BONEWATERTIGHT_DATA``) are included
when present.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
DATA = os.environ.get("BONEWATERTIGHT_DATA", os.path.join(os.path.dirname(ROOT), "shared", "data"))

# (name, source, targets, spacing): source "phantom:<case>" (label 1 = the rough mask, with
# "+cup" the rough cup as label 2) or a folder of DATA with its label map.
CASES = [
    ("tiny d=0.5", "phantom:tiny", [1], 0.5),
    ("tiny d=0.3", "phantom:tiny", [1], 0.3),
    ("easy d=1.0", "phantom:easy", [1], 1.0),
    ("easy d=0.5", "phantom:easy", [1], 0.5),
    ("easy d=0.35", "phantom:easy", [1], 0.35),
    ("hard d=0.5", "phantom:hard", [1], 0.5),
    ("oblique d=0.5", "phantom:oblique", [1], 0.5),
    ("femur d=0.5", "phantom:femur", [1], 0.5),
    ("femur d=0.4", "phantom:femur", [1], 0.4),
    ("joint femur+cup d=0.5", "phantom:joint_s15_g20+cup", [1, 2], 0.5),
    ("pelvis L3 d=0.5", "ts_example_ct_abdomen_pelvis_3mm", [29], 0.5),
    ("pelvis femur_right d=0.5", "ts_example_ct_abdomen_pelvis_3mm", [76], 0.5),
    ("pelvis hip_left d=0.75", "ts_example_ct_abdomen_pelvis_3mm", [77], 0.75),
    ("pelvis L3+L4+L5 d=0.75", "ts_example_ct_abdomen_pelvis_3mm", [27, 28, 29], 0.75),
    ("aorta T12 d=0.4", "ts_aorta_report_ct_cropped_1p5mm", [32], 0.4),
    ("20 slices T12 (cut) d=0.5", "ts_example_ct_dicom_20slices", [32], 0.5),
    ("20 slices humerus_right (cut) d=0.5", "ts_example_ct_dicom_20slices", [70], 0.5),
    # a 35 M-voxel CT without labels: bone (> 200 HU) in a 50 mm cube at the spine as label 1
    ("35 M-voxel CT, spine cube d=0.5", "itkelastix_ct_dicom_00:cube", [1], 0.5),
]
QUICK = ["tiny d=0.5", "easy d=1.0", "pelvis L3 d=0.5"]


def _status_kb(key: str) -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    raise KeyError(key)


def child(ct_path: str, labels_path: str, targets: list, spacing: float) -> dict:
    """Run one case in this process and return its figures."""
    import gc

    import numpy as np
    import SimpleITK as sitk

    sys.path.insert(0, ROOT)
    from BoneWatertightLib import pipeline
    from BoneWatertightLib.params import Parameters
    from BoneWatertightLib.pipeline import reconstruct_many
    from BoneWatertightLib.stages import prepare
    from BoneWatertightLib.stages.poisson import import_open3d

    ct = sitk.ReadImage(ct_path)
    labels = sitk.ReadImage(labels_path)
    phase = {}
    prepare_labels = pipeline.prepare_labels

    def measured_prepare(*args, **kwargs):  # the peak of the prepare stage (CT-grid arrays)
        out = prepare_labels(*args, **kwargs)
        phase["prepare_kb"] = _status_kb("VmHWM")
        return out

    pipeline.prepare_labels = measured_prepare
    import_open3d()
    import vtk  # noqa: F401
    gc.collect()
    rss0 = _status_kb("VmRSS")
    with open("/proc/self/clear_refs", "w") as fh:  # VmHWM := VmRSS
        fh.write("5")
    t0 = time.perf_counter()
    error = None
    info = {}
    try:
        res = reconstruct_many(ct, labels, targets, Parameters(spacing=spacing, max_memory_gb=256.0,
                                                               on_implausible="warn"),
                               keep_going=True)
        info = res.report.input
        failed = [type(b.error).__name__ for b in res.bones if b.error is not None]
        error = ", ".join(failed) or None
    except Exception as exc:  # noqa: BLE001 - reported
        error = f"{type(exc).__name__}: {exc}"
    seconds = time.perf_counter() - t0
    peak = _status_kb("VmHWM")
    grid = info.get("grid_size") or [0, 0, 0]
    return {"rss_before_mb": rss0 / 1024, "peak_mb": peak / 1024,
            "used_mb": (peak - rss0) / 1024,
            "prepare_used_mb": (phase.get("prepare_kb", rss0) - rss0) / 1024,
            "estimate_mb": info.get("estimated_memory_gb", float("nan")) * 1024,
            "grid_voxels": int(np.prod(grid)), "ct_voxels": int(np.prod(ct.GetSize())),
            "bytes_per_voxel_constant": prepare.BYTES_PER_VOXEL,
            "seconds": seconds, "error": error}


def _inputs(source: str, cache: str):
    """(ct path, labels path) of a case; phantoms are made once into ``cache``."""
    if source.endswith(":cube"):
        import numpy as np
        import SimpleITK as sitk

        ct_path = os.path.join(DATA, source.split(":")[0], "ct.nrrd")
        lab_path = os.path.join(cache, "cube_labels.nrrd")
        if not os.path.exists(lab_path):
            ct = sitk.ReadImage(ct_path)
            arr = sitk.GetArrayViewFromImage(ct)
            centre = np.array(arr.shape) // 2 + np.array([0, 55, 0])  # (z, y, x): the spine
            half = (25.0 / np.array(ct.GetSpacing()[::-1])).astype(int)
            lab = np.zeros(arr.shape, np.uint8)
            box = tuple(slice(c - h, c + h) for c, h in zip(centre, half))
            lab[box] = arr[box] > 200
            img = sitk.GetImageFromArray(lab)
            img.CopyInformation(ct)
            sitk.WriteImage(img, lab_path, True)
        return ct_path, lab_path
    if not source.startswith("phantom:"):
        folder = os.path.join(DATA, source)
        labels = [n for n in os.listdir(folder) if n.endswith("_labels.nrrd")]
        return os.path.join(folder, "ct.nrrd"), os.path.join(folder, labels[0])
    case = source.split(":", 1)[1]
    cup = case.endswith("+cup")
    case = case.replace("+cup", "")
    ct_path = os.path.join(cache, f"{case}_ct.nrrd")
    lab_path = os.path.join(cache, f"{case}_{'labels' if cup else 'mask'}.nrrd")
    if not (os.path.exists(ct_path) and os.path.exists(lab_path)):
        code = (
            "import sys, SimpleITK as sitk; sys.path.insert(0, %r); from phantoms import "
            "make_phantom, make_labels; p = make_phantom(%r); sitk.WriteImage(p.ct, %r, True); "
            "sitk.WriteImage(make_labels(p, 'rough') if %r else p.mask, %r, True)"
            % (HERE, case, ct_path, cup, lab_path))
        subprocess.run([sys.executable, "-c", code], check=True)
    return ct_path, lab_path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="three small cases only")
    ap.add_argument("--case", action="append", help="run only these cases (by name)")
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--cache", help="folder for the phantoms' files (default: a temporary one)")
    ap.add_argument("--child", nargs=4, metavar=("CT", "LABELS", "TARGETS", "SPACING"),
                    help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        ct, lab, targets, spacing = args.child
        print(json.dumps(child(ct, lab, [int(t) for t in targets.split(",")], float(spacing))))
        return 0
    names = args.case or (QUICK if args.quick else [c[0] for c in CASES])
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        cache = args.cache or tmp
        os.makedirs(cache, exist_ok=True)
        for name, source, targets, spacing in CASES:
            if name not in names:
                continue
            folder = os.path.join(DATA, source.split(":")[0])
            if not source.startswith("phantom:") and not os.path.isdir(folder):
                print(f"{name}: skipped ({source} not in {DATA})")
                continue
            ct, lab = _inputs(source, cache)
            out = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", ct, lab,
                                  ",".join(map(str, targets)), str(spacing)],
                                 capture_output=True, text=True)
            if out.returncode != 0:
                print(f"{name}: the child failed ({out.returncode}): {out.stderr[-2000:]}")
                rows.append({"case": name, "error": f"exit {out.returncode}"})
                continue
            row = dict(json.loads(out.stdout.strip().splitlines()[-1]), case=name)
            row["ratio"] = row["used_mb"] / row["estimate_mb"] if row["estimate_mb"] else None
            row["bytes_per_grid_voxel"] = row["used_mb"] * 2 ** 20 / max(row["grid_voxels"], 1)
            rows.append(row)
            print(f"{name:38s} grid {row['grid_voxels'] / 1e6:7.2f} M  CT {row['ct_voxels'] / 1e6:6.2f} M"
                  f"  used {row['used_mb']:7.0f} MB (prepare {row['prepare_used_mb']:5.0f})"
                  f"  estimate {row['estimate_mb']:7.0f} MB"
                  f"  ratio {row['ratio']:.2f}  {row['bytes_per_grid_voxel']:6.0f} B/voxel"
                  f"  {row['seconds']:5.1f} s{'  (' + row['error'] + ')' if row['error'] else ''}",
                  flush=True)
    good = [r for r in rows if r.get("ratio") is not None]
    if good:
        worst = max(good, key=lambda r: r["ratio"])
        print(f"\nhighest peak / estimate: {worst['ratio']:.2f} ({worst['case']}); "
              f"BYTES_PER_VOXEL = {good[0]['bytes_per_voxel_constant']}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)
    return 0 if all(r.get("ratio") is not None and r["ratio"] < 1.0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
