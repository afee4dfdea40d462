"""Headless batch run of BoneWatertight inside 3D Slicer.

Usage (the same flags, parameter options and exit codes as the ``bonewatertight`` command):
  Slicer --no-splash --no-main-window --python-script bonewatertight_batch.py -- \
      --ct CT.nrrd --seg Seg.seg.nrrd --label NAME_OR_ID --out bone.stl \
      [--h0 300 --spacing 0.5 ...] [--report report.json] [--ras]
  Slicer --no-main-window --python-script bonewatertight_batch.py -- \
      --ct CT.nrrd --seg Seg.seg.nrrd --label femur_left --label hip_left --out '{label}.stl' \
      [--all-labels] [--neighbours auto|none|LABEL,...]
  Slicer --no-main-window --python-script bonewatertight_batch.py -- --self-test

Several --label (or --all-labels) are reconstructed together, as the command does: every
other label of --seg is a neighbour by default (--neighbours), no surface enters another.

The extension installs this script as <Slicer extension folder>/lib/Slicer-X.Y/qt-scripted-modules/
Resources/Scripts/bonewatertight_batch.py (in a source checkout: Resources/Scripts/). It also
runs in PythonSlicer or any Python with the slicer-core wheel (no Slicer application needed).

Every run goes through the library's run service (BoneWatertightLib.app.run), with Slicer's own
Python, VTK and SimpleITK. Surfaces are written in LPS (default) or RAS (--ras) with the
coordinate system in the file (SPACE=LPS / SPACE=RAS, as 3D Slicer writes and reads them).
``--self-test`` builds a sphere phantom as MRML nodes, converts it with the MRML adapter
(BoneWatertightLib.mrml), writes the surface and reads it back with 3D Slicer's model reader to
check the radius in RAS; without open3d it installs it once with pip (BONEWATERTIGHT_TEST_INSTALL=0:
never) or skips with exit code 4.

Exit status (the table of BoneWatertightLib.errors):
  0    success
  1    internal error (a bug)
  2    bad input or usage
  3    reconstruction failed
  4    missing dependency (--self-test: skipped, open3d unavailable)
  5    an output could not be written, or another OS error
  6    partly done (several bones: those that passed are written, the others failed)
  130  cancelled
"""

import os
import sys
import tempfile

import slicer


def _ensureLibrary():
    """Make BoneWatertightLib importable: already importable when Slicer loaded the extension;
    else the folder two levels above this script's folder, which holds BoneWatertightLib both
    in a checkout (<root>/Resources/Scripts/) and as installed by the extension
    (<qt-scripted-modules>/Resources/Scripts/)."""
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
    options.add_removed_options(parser)
    parser.add_argument("-q", "--quiet", action="store_true", help="Print nothing but errors.")
    parser.add_argument("--self-test", action="store_true",
                        help="Run on a built-in phantom made of MRML nodes (no files needed).")
    options.add_parameter_options(parser)
    return parser


def _scene():
    """Slicer's scene; in PythonSlicer or with slicer-core, a new scene whose segmentations
    logic is registered first (it brings the segmentation converter rules)."""
    scene = getattr(slicer, "mrmlScene", None)
    if scene is not None:
        return scene
    scene = slicer.vtkMRMLScene()
    logic = slicer.vtkSlicerSegmentationsModuleLogic()
    logic.SetMRMLScene(scene)
    scene._boneWatertightSegmentationsLogic = logic  # kept alive with the scene
    return scene


def _volumeNode(scene, className, name, arrayKji, ijkToRas):
    import numpy as np
    import vtk
    from vtk.util import numpy_support

    node = scene.AddNewNodeByClass(className, name)
    image = vtk.vtkImageData()
    image.SetDimensions(arrayKji.shape[2], arrayKji.shape[1], arrayKji.shape[0])
    image.GetPointData().SetScalars(numpy_support.numpy_to_vtk(np.ascontiguousarray(arrayKji).ravel(), deep=True))
    node.SetAndObserveImageData(image)
    node.SetIJKToRASMatrix(slicer.util.vtkMatrixFromArray(ijkToRas))
    return node


def _phantom(scene):
    """A sphere of radius 10 mm (~1000 HU in 40 HU, blurred edge, 8 HU noise: a CT, not a
    label map) on an oblique grid, and a rough segment, as MRML nodes; returns (CT node,
    segmentation node, segment ID, centre RAS)."""
    import numpy as np

    dims = 40
    k, j, i = np.mgrid[0:dims, 0:dims, 0:dims]
    ijkToRas = np.array([[-0.9, 0.1, 0.0, 30.0], [-0.1, -0.9, 0.0, 20.0], [0.0, 0.0, 1.0, -15.0], [0, 0, 0, 1.0]])
    ras = np.stack([i, j, k, np.ones_like(i)], -1) @ ijkToRas.T
    centre = (ijkToRas @ np.array([19.5, 19.5, 19.5, 1.0]))[:3]
    r = np.linalg.norm(ras[..., :3] - centre, axis=-1)
    edge = 0.5 * (1.0 - np.tanh((r - 10.0) / 0.5))  # half maximum at the 10 mm radius
    noise = np.random.default_rng(3).normal(0.0, 8.0, r.shape)
    ct = _volumeNode(scene, "vtkMRMLScalarVolumeNode", "phantom CT",
                     np.round(40.0 + 960.0 * edge + noise).astype(np.int16), ijkToRas)
    lab = _volumeNode(scene, "vtkMRMLLabelMapVolumeNode", "rough", (r <= 8.5).astype(np.uint8), ijkToRas)
    seg = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", "Segmentation")
    slicer.vtkSlicerSegmentationsModuleLogic.ImportLabelmapToSegmentationNode(lab, seg)
    scene.RemoveNode(lab)
    return ct, seg, seg.GetSegmentation().GetNthSegmentID(0), centre


def _open3dForSelfTest(quiet):
    """None when open3d imports (installed once with pip if allowed), else why not."""
    from BoneWatertightLib.app.slicer_support import dependency_test_plan

    def importable():
        try:
            import open3d  # noqa: F401
        except (ImportError, OSError):
            return False
        return True

    plan = dependency_test_plan(importable())
    if plan == "run":
        return None
    if plan == "skip":
        return "not installed; installing is switched off"
    if not quiet:
        print("SELFTEST installing open3d with pip", flush=True)
    try:
        slicer.util.pip_install(["open3d>=0.18", "--upgrade-strategy", "only-if-needed",
                                 "--timeout", "60", "--retries", "1"])
    except Exception as exc:  # offline machine, no wheel for this platform, no Slicer app, ...
        return f"pip could not install it: {exc}"
    return None if importable() else "installed but it does not import"


def _selfTest(args, params, progress, transaction):
    """The phantom through the MRML adapter and the run service; returns (report, check) where
    check() reads the written file back once the transaction committed it."""
    import numpy as np

    from BoneWatertightLib import mrml
    from BoneWatertightLib.app import run

    ctNode, segNode, segmentId, centre = _phantom(_scene())
    ct = mrml.volume_to_sitk(ctNode)
    mask = mrml.segment_to_sitk_mask(segNode, segmentId, ctNode)
    out = args.out or os.path.join(tempfile.mkdtemp(prefix="bonewatertight_selftest_"), "sphere.stl")
    report = run.run_case(ct, mask, "phantom", out, params, coordinate_system="RAS" if args.ras else "LPS",
                          progress=progress, inputs={"self_test": True}, transaction=transaction)

    def check():
        # read back as 3D Slicer loads the file: the SPACE tag must put it where the CT is
        from vtk.util import numpy_support

        points = numpy_support.vtk_to_numpy(mrml.read_model_file(out).GetPolyData().GetPoints().GetData())
        error = float(np.abs(np.linalg.norm(points - centre, axis=1) - 10.0).max())
        print(f"SELFTEST max radial error {error:.3f} mm (read back with Slicer's model reader)", flush=True)
        return error <= 1.0
    return report, check


def _runFiles(args, params, progress, transaction):
    """The bonewatertight command's run of --ct / --seg / --label(s) (or --all-labels): the
    labels reconstructed together through the run service (run_joint), outputs staged in
    ``transaction``. Returns the run service's JointRun."""
    import time

    from BoneWatertightLib.app import cli, run
    from BoneWatertightLib.errors import InputError
    from BoneWatertightLib.io import images, segmentations

    t0 = time.perf_counter()
    ct = images.read_ct(args.ct, args.ct_series)
    labels, names = segmentations.read_label_image(args.seg)
    if args.all_labels:
        present = getattr(names, "present", None)
        targets = [v for v in sorted(names) if present is None or v in present]
        if not targets:
            raise InputError(f"{args.seg} holds no painted label.")
    else:
        targets = [segmentations.resolve_label(names, label) for label in args.label]
    for i, value in enumerate(targets):
        if value in targets[:i]:
            raise InputError(f"--label {args.label[targets.index(value)]} and --label {args.label[i]} "
                             f"are the same segment '{names.get(value, value)}'; give each bone once.")
    neighbours = cli.parse_neighbours(args.neighbours, names)
    readSeconds = time.perf_counter() - t0
    labelNames = {v: str(names.get(v, v)) for v in targets}
    outputs = {v: run.fill_template(args.out, labelNames[v]) for v in targets}
    if len(set(outputs.values())) != len(outputs):
        raise InputError("Two labels give the same output file name; use distinct labels.")
    pictures = None
    if args.picture:
        pictures = {}
        for v in targets:
            picture = run.fill_template(args.picture, labelNames[v])
            if len(targets) > 1 and "{label}" not in args.picture:
                picture = os.path.splitext(picture)[0] + f"_{run.safe_name(labelNames[v])}.png"
            pictures[v] = picture
    inputs = {"ct": os.path.abspath(args.ct), "seg": os.path.abspath(args.seg),
              "ct_size": list(ct.GetSize()), "ct_spacing": list(ct.GetSpacing())}
    return run.run_joint(ct, labels, targets, dict(names), outputs, params,
                         coordinate_system="RAS" if args.ras else "LPS", pictures=pictures,
                         intermediates_dir=args.save_intermediates, neighbours=neighbours,
                         progress=progress, inputs=inputs, read_seconds=readSeconds,
                         report_path=args.report, transaction=transaction)


def main(argv):
    parser = build_parser()
    from BoneWatertightLib import errors
    from BoneWatertightLib.app import options, run
    from BoneWatertightLib.io.files import OutputTransaction
    from BoneWatertightLib.report import case_summary_line, pair_summary_line

    try:
        args = parser.parse_args(argv)
        overrides = options.parameter_overrides(args)
        if args.self_test:
            overrides = {"spacing": 0.6, "h0": 500.0, "ht": 300.0, **overrides}
        if args.save_intermediates:
            overrides["keep_intermediates"] = True
        params = options.make_parameters(overrides)

        def progress(fraction, message):
            if not args.quiet:
                print(f"PROGRESS {fraction:.3f} {message}", flush=True)
            return True

        check = None
        if args.self_test:
            missing = _open3dForSelfTest(args.quiet)
            if missing:
                from BoneWatertightLib.app.slicer_support import dependency_skip_message

                print(dependency_skip_message(missing), flush=True)
                return errors.EXIT_DEPENDENCY
        else:
            from BoneWatertightLib.app import cli

            cli.check_single_args(args, parser)  # the command's own checks and messages
        # as the bonewatertight command: every output of the run (surfaces, pictures, report)
        # is committed together or not at all; SIGINT/SIGTERM/SIGHUP cancel (exit 130)
        pairs, failures = [], []
        with run.cancel_on_signals(), OutputTransaction() as tx:
            if args.self_test:
                report, check = _selfTest(args, params, progress, tx)
                reports = [report]
                if args.report:
                    run.write_reports(args.report, reports, tx)
            else:
                joint = _runFiles(args, params, progress, tx)
                reports, pairs, failures = joint.reports, joint.pairs, joint.failures
        codes = [errors.EXIT_OK]
        for name, exc in failures:  # a bone that failed did not stop the others
            print(f"error: {name + ': ' if len(reports) + len(failures) > 1 else ''}{errors.one_line(exc)}",
                  file=sys.stderr)
            code = errors.exit_code_for(exc)
            if code == errors.EXIT_INTERNAL:
                raise exc  # a bug: the traceback below
            codes.append(code)
        for report in reports:
            print("RESULT " + case_summary_line(report), flush=True)
        for pair in pairs:
            print("PAIR " + pair_summary_line(pair), flush=True)
        if check is not None and not check():
            return errors.EXIT_FAILED
        # as the command: partly done, or an input error outranking a failed reconstruction
        return errors.joint_exit_code(codes, len(reports))
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


def _exit(status):
    """Leave Slicer with ``status`` (slicer.util.exit needs the application); elsewhere sys.exit."""
    if getattr(slicer, "app", None) is not None:
        slicer.util.exit(status)
    else:
        sys.exit(status)


if __name__ == "__main__":
    _exit(main(sys.argv[1:]))
