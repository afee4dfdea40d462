"""Reconstruct the bundled sample bone and write surface, report and picture.

Usage: python Resources/Scripts/demo.py [OUTDIR] [--label NAME] [--preset NAME]

Input: Resources/SampleData/lumbar_spine_3mm (a 3 mm CT crop with TotalSegmentator labels).
Output in OUTDIR (default ``out``): surface.stl, surface.vtp (with the per-vertex
"DistanceToConstraints" array), report.json and surface.png. All coordinates are physical LPS
millimetres (as ITK); the files say so (STL header / VTP field data "SPACE=LPS").
Exit status: 0 success, otherwise the CLI's codes (2 bad input, 3 reconstruction failed,
4 missing dependency, 1 internal error).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

from BoneWatertightLib import cli  # noqa: E402
from BoneWatertightLib import io as bwio  # noqa: E402
from BoneWatertightLib.params import preset  # noqa: E402

SAMPLE = os.path.join(ROOT, "Resources", "SampleData", "lumbar_spine_3mm")
DEFAULT_LABEL = "vertebrae_L3"
DEFAULT_PRESET = "vertebra"


def run(out_dir: str, label: str = DEFAULT_LABEL, preset_name: str = DEFAULT_PRESET,
        quiet: bool = False) -> dict:
    """Run the pipeline on the sample; returns the report (also written to report.json)."""
    os.makedirs(out_dir, exist_ok=True)
    ct_path = os.path.join(SAMPLE, "ct.nrrd")
    seg_path = os.path.join(SAMPLE, "labels.nrrd")
    stl = os.path.join(out_dir, "surface.stl")
    vtp = os.path.join(out_dir, "surface.vtp")
    png = os.path.join(out_dir, "surface.png")
    report_path = os.path.join(out_dir, "report.json")

    t0 = time.perf_counter()
    ct = bwio.read_ct(ct_path)
    mask, name = bwio.read_segment(seg_path, label)
    # The sample is a 3 mm CT: partial volume lowers the cortex to ~500 HU and the vertebral
    # body to ~150-250 HU, below the paper's thin-slice H0 = 300. Like the panel's Auto button,
    # propose H0/HT from the HU histogram inside the segment, and close a little more (n = 3
    # voxels = 3 mm at the auto spacing) so the porous body shell becomes one closed region.
    from BoneWatertightLib.autothreshold import propose_thresholds

    auto = propose_thresholds(ct, mask)
    params = preset(preset_name, h0=float(auto["h0"]), ht=float(auto["ht"]), closing=3).validate()
    reconstruct = cli.load_reconstruct()
    captured = {}

    def keep_result(*args):
        # reconstruct_and_write returns the report only; keep the surface to write the VTP.
        captured["result"] = reconstruct(*args)
        return captured["result"]

    bar = cli.ProgressBar(enabled=False if quiet else None)
    import numpy as np
    import SimpleITK as sitk

    segment_ml = (float(np.count_nonzero(sitk.GetArrayViewFromImage(mask)))
                  * float(np.prod(mask.GetSpacing())) / 1000.0)
    inputs = {"ct": ct_path, "seg": seg_path, "label": label, "preset": preset_name,
              "ct_size": list(ct.GetSize()), "ct_spacing": list(ct.GetSpacing()),
              "segment_volume_ml": segment_ml, "auto_thresholds": auto}
    try:
        report = cli.reconstruct_and_write(ct, mask, name, stl, params, picture=png,
                                           progress=bar, inputs=inputs,
                                           reconstruct=keep_result)
    finally:
        bar.close()
    bwio.write_surface(captured["result"].surface, vtp, "LPS")
    report["output"]["also"] = [os.path.abspath(vtp)]
    report["timings_s"]["total"] = time.perf_counter() - t0
    bwio.write_text(cli.to_json(report), report_path)
    report["output"]["report"] = os.path.abspath(report_path)
    return report


def summary(report: dict) -> str:
    out = report["output"]
    checks = report.get("checks") or {}
    dist = report.get("distance_to_constraints_mm") or {}
    flags = ", ".join(f"{key}={checks.get(key)}" for key in
                      ("closed", "edge_manifold", "vertex_manifold", "outward", "n_components",
                       "n_self_intersections", "n_degenerate") if key in checks)
    lines = [
        f"bone:            {report['inputs'].get('segment_name')} "
        f"(sample {os.path.relpath(SAMPLE, ROOT)}, preset {report['inputs'].get('preset')})",
        f"surface:         {out['n_vertices']} vertices, {out['n_faces']} triangles",
        f"checks:          {'ok' if checks.get('ok') else 'FAILED'} ({flags})"
        + ("" if checks.get("ok")
           else "; problems: " + "; ".join(map(str, checks.get("problems", [])))),
        f"genus:           {checks.get('genus')}",
    ]
    volume = checks.get("volume")
    segment_ml = report["inputs"].get("segment_volume_ml")
    if isinstance(volume, (int, float)) and segment_ml:
        ratio = volume / 1000.0 / segment_ml
        lines.append(f"volume:          {volume / 1000.0:.1f} ml enclosed; the rough segment has "
                     f"{segment_ml:.1f} ml ({100 * ratio:.0f} %)")
        if not 0.5 <= ratio <= 1.5:
            # The checks prove topology, not accuracy: a bone surface that far from the
            # rough segment's volume has lost or invented large parts.
            lines.append("WARNING:         the surface volume differs a lot from the rough "
                         "segment's; look at the picture before using the surface.")
    if dist.get("n"):
        lines.append(f"distance to constraints: mean {dist['mean']:.2f} mm, "
                     f"p95 {dist['p95']:.2f} mm, max {dist['max']:.2f} mm")
    lines += [
        f"time:            {report['timings_s']['total']:.1f} s "
        f"(reconstruction {report['timings_s']['reconstruct']:.1f} s)",
        f"coordinates:     physical {out['coordinate_system']} mm (as ITK; 3D Slicer reads the "
        "SPACE tag in the files)",
        f"surface:         {out['path']}",
        f"                 {out['also'][0]}",
        f"picture:         {out['picture']}",
        f"report:          {out['report']}",
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out_dir", nargs="?", default="out", help="output folder (default: out)")
    parser.add_argument("--label", default=DEFAULT_LABEL,
                        help=f"segment of the sample (default {DEFAULT_LABEL}; also "
                             "vertebrae_L4)")
    parser.add_argument("--preset", default=DEFAULT_PRESET, help="parameter preset")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        report = run(args.out_dir, args.label, args.preset, args.quiet)
    except KeyboardInterrupt:
        sys.stderr.write("error: cancelled\n")
        return cli.EXIT_CANCELLED
    except Exception as exc:
        code = cli.exit_code_for(exc)
        if code == cli.EXIT_INTERNAL:
            raise
        sys.stderr.write(f"error: {cli.one_line(exc)}\n")
        return code
    print(summary(report), flush=True)
    return cli.EXIT_OK if (report.get("checks") or {}).get("ok") else cli.EXIT_FAILED


if __name__ == "__main__":
    sys.exit(main())
