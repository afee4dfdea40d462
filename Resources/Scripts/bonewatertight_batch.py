"""Headless batch run of BoneWatertight inside 3D Slicer.

Usage (the same flags, parameter options and exit codes as the ``bonewatertight`` command):
  Slicer --no-splash --no-main-window --python-script bonewatertight_batch.py -- \
      --ct CT.nrrd --seg Seg.seg.nrrd --label NAME_OR_ID --out bone.stl \
      [--preset femur|hip|vertebra] [--h0 300 --spacing 0.5 ...] [--report report.json] [--ras]
  Slicer --no-main-window --python-script bonewatertight_batch.py -- --self-test

Every run goes through the library's run service (BoneWatertightLib.app.run), with Slicer's own
Python, VTK and SimpleITK. ``--self-test`` builds a sphere phantom as MRML nodes, converts it
with the MRML adapter (BoneWatertightLib.mrml) and checks the radius. Exit status: the table of
BoneWatertightLib.errors (0 success, 2 bad input, 3 failed, 4 missing dependency, 5 output/OS
error, 130 cancelled, 1 internal error).
"""

import os
import sys
import tempfile

import slicer


def _ensureLibrary():
    """Make BoneWatertightLib importable: the module folder when Slicer loaded the extension,
    else the checkout this script lives in."""
    try:
        import BoneWatertightLib  # noqa: F401
    except ImportError:
        sys.path.append(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))


def build_parser():
    """The argument parser: the library's shared option builders plus --self-test."""
    _ensureLibrary()
    from BoneWatertightLib.app import options

    parser = options.Parser(prog="bonewatertight_batch.py", description=__doc__.split("\n")[0])
    options.add_io_options(parser)
    options.add_preset_option(parser)
    parser.add_argument("-q", "--quiet", action="store_true", help="Print nothing but errors.")
    parser.add_argument("--self-test", action="store_true",
                        help="Run on a built-in phantom made of MRML nodes (no files needed).")
    options.add_parameter_options(parser)
    return parser


def _phantom():
    """A sphere of radius 10 mm (~1000 HU in 40 HU) on an oblique grid, and a rough segment,
    as MRML nodes; returns (CT node, segmentation node, segment ID, centre RAS)."""
    import numpy as np

    dims = 40
    k, j, i = np.mgrid[0:dims, 0:dims, 0:dims]
    ijkToRas = np.array([[-0.9, 0.1, 0.0, 30.0], [-0.1, -0.9, 0.0, 20.0], [0.0, 0.0, 1.0, -15.0], [0, 0, 0, 1.0]])
    ras = np.stack([i, j, k, np.ones_like(i)], -1) @ ijkToRas.T
    centre = (ijkToRas @ np.array([19.5, 19.5, 19.5, 1.0]))[:3]
    r = np.linalg.norm(ras[..., :3] - centre, axis=-1)
    ct = slicer.util.addVolumeFromArray(np.where(r <= 10.0, 1000, 40).astype(np.int16), name="phantom CT")
    ct.SetIJKToRASMatrix(slicer.util.vtkMatrixFromArray(ijkToRas))
    lab = slicer.util.addVolumeFromArray((r <= 8.5).astype(np.uint8), name="rough",
                                         nodeClassName="vtkMRMLLabelMapVolumeNode")
    lab.SetIJKToRASMatrix(slicer.util.vtkMatrixFromArray(ijkToRas))
    seg = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLSegmentationNode", "Segmentation")
    slicer.modules.segmentations.logic().ImportLabelmapToSegmentationNode(lab, seg)
    slicer.mrmlScene.RemoveNode(lab)
    return ct, seg, seg.GetSegmentation().GetNthSegmentID(0), centre


def _selfTest(args, params, progress):
    import numpy as np

    from BoneWatertightLib import mrml
    from BoneWatertightLib.app import run

    ctNode, segNode, segmentId, centre = _phantom()
    ct = mrml.volume_to_sitk(ctNode)
    mask = mrml.segment_to_sitk_mask(segNode, segmentId, ctNode)
    out = args.out or os.path.join(tempfile.mkdtemp(prefix="bonewatertight_selftest_"), "sphere.stl")
    report = run.run_case(ct, mask, "phantom", out, params, coordinate_system="RAS" if args.ras else "LPS",
                          progress=progress, inputs={"self_test": True})
    from BoneWatertightLib.io import meshes

    points = meshes.read_surface(out, "RAS").vertices
    error = float(np.abs(np.linalg.norm(points - centre, axis=1) - 10.0).max())
    print(f"SELFTEST max radial error {error:.3f} mm", flush=True)
    return [report], error <= 1.0


def main(argv):
    parser = build_parser()
    from BoneWatertightLib import errors
    from BoneWatertightLib.app import options, run
    from BoneWatertightLib.report import case_summary_line

    try:
        args = parser.parse_args(argv)
        overrides = options.parameter_overrides(args)
        if args.self_test:
            overrides = {"spacing": 0.6, "h0": 500.0, "ht": 300.0, **overrides}
        if args.save_intermediates:
            overrides["keep_intermediates"] = True
        params = options.make_parameters(args.preset, overrides)

        def progress(fraction, message):
            if not args.quiet:
                print(f"PROGRESS {fraction:.3f} {message}", flush=True)
            return True

        ok = True
        if args.self_test:
            reports, ok = _selfTest(args, params, progress)
        else:
            missing = [f for f, v in (("--ct", args.ct), ("--seg", args.seg), ("--label", args.label),
                                      ("--out", args.out)) if not v]
            if missing:
                parser.error("missing " + ", ".join(missing) + " (or --self-test)")
            if len(args.label) > 1 and "{label}" not in args.out:
                parser.error("several labels need {label} in --out")
            reports = [run.run_files(args.ct, args.seg, label, args.out, params, ct_series=args.ct_series,
                                     coordinate_system="RAS" if args.ras else "LPS", picture=args.picture,
                                     intermediates_dir=args.save_intermediates, progress=progress,
                                     inputs={"preset": args.preset})
                       for label in args.label]
        for report in reports:
            print("RESULT " + case_summary_line(report), flush=True)
        if args.report:
            run.write_reports(args.report, reports)
        return errors.EXIT_OK if ok else errors.EXIT_FAILED
    except SystemExit as exc:  # --help
        return exc.code if isinstance(exc.code, int) else errors.EXIT_OK
    except KeyboardInterrupt:
        print("error: cancelled", file=sys.stderr)
        return errors.EXIT_CANCELLED
    except Exception as exc:  # one line for the user, the documented exit code
        code = errors.exit_code_for(exc)
        if code == errors.EXIT_INTERNAL:
            import traceback

            traceback.print_exc()
        print(f"error: {errors.one_line(exc)}", file=sys.stderr)
        return code


if __name__ == "__main__":
    slicer.util.exit(main(sys.argv[1:]))
