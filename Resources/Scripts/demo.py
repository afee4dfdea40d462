"""Reconstruct the bundled sample bone and write surface, report and picture.

Usage: python Resources/Scripts/demo.py [OUTDIR] [--label NAME]

Input: Resources/SampleData/lumbar_spine_3mm (a 3 mm CT crop with TotalSegmentator labels).
Output in OUTDIR (default ``out``): surface.stl, surface.vtp (with the per-vertex
"DistanceToConstraints" array), report.json and surface.png. All coordinates are physical LPS
millimetres (as ITK); the files say so (STL header / VTP field data "SPACE=LPS").
Exit status: the codes of BoneWatertightLib.errors (0 success, 2 bad input, 3 reconstruction
failed, 4 missing dependency, 5 output/OS error, 130 cancelled, 1 internal error).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

from BoneWatertightLib import errors  # noqa: E402
from BoneWatertightLib.app import run as runner  # noqa: E402
from BoneWatertightLib.app.cli import ProgressBar  # noqa: E402
from BoneWatertightLib.io import images, segmentations  # noqa: E402
from BoneWatertightLib.params import Parameters  # noqa: E402
from BoneWatertightLib.report import CaseReport  # noqa: E402

SAMPLE = os.path.join(ROOT, "Resources", "SampleData", "lumbar_spine_3mm")
DEFAULT_LABEL = "vertebrae_L3"


def run(out_dir: str, label: str = DEFAULT_LABEL, quiet: bool = False) -> CaseReport:
    """Run the pipeline on the sample through the run service; returns the case report (also
    written to report.json)."""
    os.makedirs(out_dir, exist_ok=True)
    ct_path = os.path.join(SAMPLE, "ct.nrrd")
    seg_path = os.path.join(SAMPLE, "labels.nrrd")
    stl = os.path.join(out_dir, "surface.stl")
    vtp = os.path.join(out_dir, "surface.vtp")
    png = os.path.join(out_dir, "surface.png")
    report_path = os.path.join(out_dir, "report.json")

    t0 = time.perf_counter()
    ct = images.read_ct(ct_path)
    mask, name = segmentations.read_segment(seg_path, label)
    read_seconds = time.perf_counter() - t0
    # The sample is a 3 mm CT: partial volume lowers the cortex to ~500 HU and the vertebral
    # body to ~150-250 HU, below the paper's thin-slice H0 = 300. Like the panel's Auto button,
    # propose H0/HT from the HU histogram inside the segment, and close a little more (n = 3
    # voxels = 3 mm at the auto spacing) so the porous body shell becomes one closed region.
    from BoneWatertightLib.stages.autothreshold import propose_thresholds

    auto = propose_thresholds(ct, mask)
    params = Parameters(h0=float(auto["h0"]), ht=float(auto["ht"]), closing=3).validate()
    bar = ProgressBar(enabled=False if quiet else None)
    import numpy as np
    import SimpleITK as sitk

    segment_ml = (float(np.count_nonzero(sitk.GetArrayViewFromImage(mask)))
                  * float(np.prod(mask.GetSpacing())) / 1000.0)
    inputs = {"ct": ct_path, "seg": seg_path, "label": label,
              "ct_size": list(ct.GetSize()), "ct_spacing": list(ct.GetSpacing()),
              "segment_volume_ml": segment_ml, "auto_thresholds": auto}
    try:
        report = runner.run_case(ct, mask, name, stl, params, picture=png, also=[vtp],
                                 progress=bar, inputs=inputs, read_seconds=read_seconds)
    finally:
        bar.close()
    report.output.report = os.path.abspath(report_path)
    runner.write_report(report, report_path)
    return report


def summary(report: CaseReport) -> str:
    """The demo's summary block (README), read from the typed report."""
    out = report.output
    checks = report.checks
    dist = report.distance_to_constraints_mm
    flags = ", ".join(f"{key}={getattr(checks, key)}" for key in
                      ("closed", "edge_manifold", "vertex_manifold", "outward", "n_components",
                       "n_self_intersections", "n_degenerate"))
    lines = [
        f"bone:            {report.segment_name} "
        f"(sample {os.path.relpath(SAMPLE, ROOT)})",
        f"surface:         {out.n_vertices} vertices, {out.n_faces} triangles",
        f"checks:          {'ok' if checks.ok else 'FAILED'} ({flags})"
        + ("" if checks.ok else "; problems: " + "; ".join(map(str, checks.problems))),
        f"genus:           {checks.genus}",
    ]
    segment_ml = report.inputs.get("segment_volume_ml")
    if segment_ml:
        ratio = checks.volume / 1000.0 / segment_ml
        lines.append(f"volume:          {checks.volume / 1000.0:.1f} ml enclosed; the rough segment "
                     f"has {segment_ml:.1f} ml ({100 * ratio:.0f} %)")
        if not 0.5 <= ratio <= 1.5:
            # The checks prove topology, not accuracy: a bone surface that far from the
            # rough segment's volume has lost or invented large parts.
            lines.append("WARNING:         the surface volume differs a lot from the rough "
                         "segment's; look at the picture before using the surface.")
    if dist.n:
        lines.append(f"distance to constraints: mean {dist.mean:.2f} mm, "
                     f"p95 {dist.p95:.2f} mm, max {dist.max:.2f} mm")
    lines += [
        f"time:            {report.timings_s.total:.1f} s "
        f"(reconstruction {report.timings_s.reconstruct:.1f} s)",
        f"coordinates:     physical {out.coordinate_system} mm (as ITK; 3D Slicer reads the "
        "SPACE tag in the files)",
        f"surface:         {out.path}",
        f"                 {out.also[0]}",
        f"picture:         {out.picture or 'none (' + str(out.picture_error) + ')'}",
        f"report:          {out.report}",
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out_dir", nargs="?", default="out", help="output folder (default: out)")
    parser.add_argument("--label", default=DEFAULT_LABEL,
                        help=f"segment of the sample (default {DEFAULT_LABEL}; also "
                             "vertebrae_L4)")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        report = run(args.out_dir, args.label, args.quiet)
    except KeyboardInterrupt:
        sys.stderr.write("error: cancelled\n")
        return errors.EXIT_CANCELLED
    except Exception as exc:
        code = errors.exit_code_for(exc)
        if code == errors.EXIT_INTERNAL:
            raise
        sys.stderr.write(f"error: {errors.one_line(exc)}\n")
        return code
    print(summary(report), flush=True)
    return errors.EXIT_OK if report.checks.ok else errors.EXIT_FAILED


if __name__ == "__main__":
    sys.exit(main())
