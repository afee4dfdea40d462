"""Headless batch run of BoneWatertight inside 3D Slicer.

Usage:
  Slicer --no-splash --no-main-window --python-script bonewatertight_batch.py -- \
      --ct CT.nrrd --segmentation Seg.seg.nrrd [--segment NAME_OR_ID] --output bone.stl \
      [--preset femur|hip|vertebra] [--param h0=300 --param spacing=0.5 ...] [--report report.json]
      [--coordinate-system LPS|RAS]
  Slicer --no-main-window --python-script bonewatertight_batch.py -- --self-test

The logic is instantiated directly (not through getModuleLogic, which would build the widget).
Exit status: 0 success, 1 bad input / failed reconstruction, 2 usage error.
"""

import argparse
import json
import os
import sys
import traceback

import slicer


def _parse(argv):
    parser = argparse.ArgumentParser(prog="bonewatertight_batch.py", description=__doc__.split("\n")[0])
    parser.add_argument("--ct", help="CT volume file (NRRD, NIfTI, MHA, ...)")
    parser.add_argument("--segmentation", help="segmentation file (.seg.nrrd) or label map")
    parser.add_argument("--segment", default=None, help="segment name or ID (default: the first segment)")
    parser.add_argument("--output", help="output surface file (.stl, .ply, .obj, .vtk, .vtp)")
    parser.add_argument("--coordinate-system", choices=["LPS", "RAS"], default="LPS",
                        help="coordinate system written into the surface file (Slicer's default: LPS)")
    parser.add_argument("--preset", choices=["femur", "hip", "vertebra"], default=None)
    parser.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                        help="any BoneWatertightLib.params.Parameters field, repeatable")
    parser.add_argument("--report", default=None, help="write the JSON report here")
    parser.add_argument("--self-test", action="store_true", help="run on a built-in phantom (no files needed)")
    return parser.parse_args(argv)


def _value(text):
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return {"true": True, "false": False, "none": None}.get(text.lower(), text)


def _find_segment(segmentationNode, nameOrId):
    segmentation = segmentationNode.GetSegmentation()
    if nameOrId is None:
        if segmentation.GetNumberOfSegments() == 0:
            raise ValueError("The segmentation has no segment.")
        return segmentation.GetNthSegmentID(0)
    if segmentation.GetSegment(nameOrId) is not None:
        return nameOrId
    segmentId = segmentation.GetSegmentIdBySegmentName(nameOrId)
    if not segmentId:
        raise ValueError(f"No segment named or with ID '{nameOrId}'.")
    return segmentId


def _load_segmentation(path):
    if path.lower().endswith((".seg.nrrd", ".seg.nhdr")):
        return slicer.util.loadSegmentation(path)
    label = slicer.util.loadLabelVolume(path)
    seg = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLSegmentationNode", "Segmentation")
    slicer.modules.segmentations.logic().ImportLabelmapToSegmentationNode(label, seg)
    slicer.mrmlScene.RemoveNode(label)
    return seg


def _phantom():
    """A sphere of radius 10 mm (~1000 HU in 40 HU) on an oblique grid, and a rough segment."""
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
    return ct, seg, centre


def main(argv):
    args = _parse(argv)
    import BoneWatertight

    parameters = {}
    for item in args.param:
        if "=" not in item:
            print(f"--param expects NAME=VALUE, got '{item}'", file=sys.stderr)
            return 2
        name, text = item.split("=", 1)
        parameters[name.strip()] = _value(text.strip())

    if args.self_test:
        ct, seg, centre = _phantom()
        parameters.setdefault("spacing", 0.6)
        parameters.setdefault("h0", 500.0)
        parameters.setdefault("ht", 300.0)
    else:
        if not (args.ct and args.segmentation and args.output):
            print("--ct, --segmentation and --output are required (or --self-test).", file=sys.stderr)
            return 2
        ct = slicer.util.loadVolume(args.ct)
        seg = _load_segmentation(args.segmentation)
    segmentId = _find_segment(seg, args.segment)

    def progress(fraction, message):
        print(f"PROGRESS {fraction:.3f} {message}", flush=True)
        return True

    logic = BoneWatertight.BoneWatertightLogic()
    model, result = logic.process(ct, seg, segmentId, progressCallback=progress, preset=args.preset,
                                  returnResult=True, **parameters)
    from BoneWatertightLib import mrml

    print("RESULT " + mrml.summarize(result), flush=True)
    if args.self_test:
        import numpy as np

        points = slicer.util.arrayFromModelPoints(model)
        error = np.abs(np.linalg.norm(points - centre, axis=1) - 10.0).max()
        print(f"SELFTEST max radial error {error:.3f} mm", flush=True)
        if error > 1.0:
            return 1
    if args.output:
        storage = model.CreateDefaultStorageNode()
        storage.SetCoordinateSystem(slicer.vtkMRMLStorageNode.GetCoordinateSystemFromString(args.coordinate_system))
        storage.SetFileName(os.path.abspath(args.output))
        if not storage.WriteData(model):
            print(f"Could not write {args.output}", file=sys.stderr)
            return 1
        slicer.mrmlScene.RemoveNode(storage)
    if args.report:
        with open(args.report, "w") as f:
            json.dump(result.report, f, indent=2, default=str)
    return 0


if __name__ == "__main__":
    try:
        status = main(sys.argv[1:])
    except Exception as exc:  # report and exit non-zero instead of leaving Slicer running
        traceback.print_exc()
        print(f"ERROR {exc}", file=sys.stderr)
        status = 1
    slicer.util.exit(status)
