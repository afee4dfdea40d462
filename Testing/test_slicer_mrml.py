"""The Slicer-facing parts of BoneWatertightLib (the mrml adapter, app.nodes, app.preview) on
slicer-core's real MRML classes (no Qt, no mocks): the live threshold preview (cached crop, its colours, never saved), progress and
Cancel from the first second of a run, the scene-close / node-removal guard, the release of
the volume copy made under a non-linear transform, and the sitk <-> node conversions.

Issue 13, defects 2 (preview), 5 (colours), 8 (first-phase progress), 9 (scene close), 10 (leak).
"""

from __future__ import annotations

import gc
import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

slicer = pytest.importorskip("slicer")
vtk = pytest.importorskip("vtk")
from vtk.util import numpy_support as ns  # noqa: E402

from BoneWatertightLib import mrml  # noqa: E402
from BoneWatertightLib.app import nodes, run  # noqa: E402
from BoneWatertightLib.app.preview import (PREVIEW_COLORS, PREVIEW_INITIAL_LABEL,  # noqa: E402
                                           PREVIEW_TARGET_LABEL, ThresholdPreview)
from BoneWatertightLib.errors import CancelledError  # noqa: E402
from BoneWatertightLib.params import Parameters  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
UI_FILE = ROOT / "BoneWatertight" / "Resources" / "UI" / "BoneWatertight.ui"


@pytest.fixture()
def scene():
    sc = slicer.vtkMRMLScene()
    logic = slicer.vtkSlicerSegmentationsModuleLogic()  # converter rules: before any segmentation
    logic.SetMRMLScene(sc)
    sc._bw_logic = logic
    return sc


def _ct_image(size=(60, 50, 40), spacing=(0.8, 0.7, 1.2), centre_lps=(10.0, -20.0, 35.0),
              radius=9.0, angles=(0.2, -0.15, 0.3), seed=1):
    """An oblique int16 CT (LPS) with a blurred ball of ~1000 HU in 40 HU and noise."""
    cx, cy, cz = np.cos(angles)
    sx, sy, sz = np.sin(angles)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    direction = rz @ ry @ rx
    spacing = np.asarray(spacing, float)
    mid = (np.asarray(size, float) - 1) / 2
    origin = np.asarray(centre_lps) - direction @ (spacing * mid)
    k, j, i = np.meshgrid(*(np.arange(n) for n in size[::-1]), indexing="ij")
    idx = np.stack([i, j, k], -1).astype(float)
    lps = origin + (idx * spacing) @ direction.T
    r = np.linalg.norm(lps - centre_lps, axis=-1)
    edge = 0.5 * (1.0 - np.tanh((r - radius) / 0.6))
    hu = 40.0 + 960.0 * edge + np.random.default_rng(seed).normal(0, 8.0, r.shape)
    img = sitk.GetImageFromArray(np.round(hu).astype(np.int16))
    img.SetSpacing(spacing.tolist())
    img.SetOrigin(origin.tolist())
    img.SetDirection(direction.ravel().tolist())
    return img, np.asarray(centre_lps, float), radius


def _ball_mask(ct, centre_lps, radius):
    """A rough segment on a coarser, axis-aligned grid (another geometry than the CT)."""
    ref = sitk.Image([24, 24, 24], sitk.sitkUInt8)
    ref.SetSpacing([1.5, 1.5, 1.5])
    ref.SetOrigin((np.asarray(centre_lps) - 1.5 * 11.5).tolist())
    k, j, i = np.meshgrid(*(np.arange(24),) * 3, indexing="ij")
    lps = np.asarray(ref.GetOrigin()) + np.stack([i, j, k], -1) * 1.5
    arr = (np.linalg.norm(lps - centre_lps, axis=-1) <= radius).astype(np.uint8)
    mask = sitk.GetImageFromArray(arr)
    mask.CopyInformation(ref)
    return mask


def _nodes(scene, **kw):
    ct, centre, radius = _ct_image(**kw)
    volume = mrml.volume_node_from_sitk(scene, ct, "CT")
    seg, segId = mrml.segmentation_node_from_mask(scene, _ball_mask(ct, centre, radius - 1.5))
    return volume, seg, segId, ct, centre, radius


def _voxel_ras(node, ijk):
    m = vtk.vtkMatrix4x4()
    node.GetIJKToRASMatrix(m)
    a = np.array([[m.GetElement(r, c) for c in range(4)] for r in range(4)])
    ijk = np.asarray(ijk, float)
    return (np.c_[ijk, np.ones(len(ijk))] @ a.T)[:, :3]


def _node_ids(scene):
    return [scene.GetNthNode(i).GetID() for i in range(scene.GetNumberOfNodes())]


# ---------------------------------------------------------------------------------------
# sitk <-> nodes
# ---------------------------------------------------------------------------------------

def test_volume_node_from_sitk_round_trips(scene):
    ct, _, _ = _ct_image()
    back = mrml.volume_to_sitk(mrml.volume_node_from_sitk(scene, ct))
    assert np.allclose(back.GetOrigin(), ct.GetOrigin()) and np.allclose(back.GetSpacing(), ct.GetSpacing())
    assert np.allclose(back.GetDirection(), ct.GetDirection())
    assert np.array_equal(sitk.GetArrayViewFromImage(back), sitk.GetArrayViewFromImage(ct))


def test_segment_mask_equals_a_nearest_neighbour_resample(scene):
    """The mask is resampled only over the segment's box on the CT grid: the result is the
    same as resampling the whole grid."""
    volume, seg, segId, ct, centre, radius = _nodes(scene)
    mask = mrml.segment_to_sitk_mask(seg, segId, volume)
    expected = sitk.Resample(_ball_mask(ct, centre, radius - 1.5), ct, sitk.Transform(),
                             sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8)
    a, b = sitk.GetArrayViewFromImage(mask) > 0, sitk.GetArrayViewFromImage(expected) > 0
    assert a.sum() > 1000 and np.array_equal(a, b)


# ---------------------------------------------------------------------------------------
# defect 2 + 5: the preview
# ---------------------------------------------------------------------------------------

def test_preview_thresholds_a_crop_aligned_with_the_ct(scene):
    volume, seg, segId, ct, centre, radius = _nodes(scene, size=(100, 90, 60))
    preview = ThresholdPreview(scene, margin_mm=3.0)
    node = preview.update(volume, seg, segId, h0=600.0, ht=300.0, theta_max=2500.0)
    labels = mrml.array_view(node.GetImageData())
    full = sitk.GetArrayViewFromImage(ct)
    assert labels.size < full.size / 3, "the preview must be a crop around the segment"
    # the crop's voxel (0, 0, 0) is a voxel of the CT: find it and compare every label
    origin = _voxel_ras(node, [[0, 0, 0]])[0]
    m = vtk.vtkMatrix4x4()
    volume.GetRASToIJKMatrix(m)
    ijk0 = np.rint(np.array(m.MultiplyPoint([*origin, 1.0]))[:3]).astype(int)
    assert np.allclose(_voxel_ras(volume, [ijk0])[0], origin, atol=1e-6)
    i0, j0, k0 = ijk0
    nk, nj, ni = labels.shape
    values = full[k0:k0 + nk, j0:j0 + nj, i0:i0 + ni]
    expected = np.where((values >= 600) & (values <= 2500), 2, np.where(values >= 300, 1, 0))
    assert np.array_equal(labels, expected)
    assert (labels == 1).any() and (labels == 2).any()
    # the crop holds the whole segment plus the margin
    mask = sitk.GetArrayFromImage(mrml.segment_to_sitk_mask(seg, segId, volume)) > 0
    kk, jj, ii = np.nonzero(mask)
    assert kk.min() > k0 and jj.min() > j0 and ii.min() > i0
    assert kk.max() < k0 + nk - 1 and jj.max() < j0 + nj - 1 and ii.max() < i0 + ni - 1


def test_preview_reuses_its_crop_and_rebuilds_when_inputs_change(scene):
    volume, seg, segId, ct, centre, radius = _nodes(scene, size=(100, 90, 60))
    preview = ThresholdPreview(scene)
    node = preview.update(volume, seg, segId, 300.0, 150.0, 2500.0)
    image = node.GetImageData()
    for h0 in (310.0, 320.0, 500.0):  # drag steps: the crop is reused, only thresholded again
        assert preview.update(volume, seg, segId, h0, 150.0, 2500.0) is node
    assert preview.cacheBuilds == 1 and node.GetImageData() is image
    # voxels edited (as slicer.util.updateVolumeFromArray does): rebuilt from the new voxels
    arr = ns.vtk_to_numpy(volume.GetImageData().GetPointData().GetScalars())
    arr[:] = np.clip(arr, None, 400)
    volume.GetImageData().GetPointData().GetScalars().Modified()
    labels = mrml.array_view(preview.update(volume, seg, segId, 500.0, 150.0, 2500.0).GetImageData())
    assert preview.cacheBuilds == 2 and not (labels == 2).any() and (labels == 1).any()
    # the segment painted (its labelmap modified in place, as the Segment Editor does): rebuilt
    rep = seg.GetSegmentation().GetSegment(segId).GetRepresentation(
        slicer.vtkSegmentationConverter.GetBinaryLabelmapRepresentationName())
    rep.GetPointData().GetScalars().Modified()
    preview.update(volume, seg, segId, 500.0, 150.0, 2500.0)
    assert preview.cacheBuilds == 3
    # another (larger) segment: rebuilt, the crop follows the segment
    shape = labels.shape
    seg2, segId2 = mrml.segmentation_node_from_mask(scene, _ball_mask(ct, centre, radius + 3.0))
    labels = mrml.array_view(preview.update(volume, seg2, segId2, 500.0, 150.0, 2500.0).GetImageData())
    assert preview.cacheBuilds == 4 and all(a > b for a, b in zip(labels.shape, shape))
    # the volume moved by a linear transform: rebuilt (the segment's box on its grid moved);
    # the label map sits under the volume's transform
    tn = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode")
    shift = vtk.vtkMatrix4x4()
    shift.SetElement(0, 3, 4.0)
    tn.SetMatrixTransformToParent(shift)
    volume.SetAndObserveTransformNodeID(tn.GetID())
    node = preview.update(volume, seg2, segId2, 500.0, 150.0, 2500.0)
    assert preview.cacheBuilds == 5 and node.GetTransformNodeID() == tn.GetID()


def test_preview_colours_are_its_own_green_and_yellow_and_never_saved(scene):
    volume, seg, segId, *_ = _nodes(scene)
    preview = ThresholdPreview(scene)
    node = preview.update(volume, seg, segId, 300.0, 150.0, 2500.0)
    display = node.GetDisplayNode()
    assert display is not None and display.IsA("vtkMRMLLabelMapVolumeDisplayNode")
    colours = display.GetColorNode()
    assert colours is preview.colorNode and colours.GetScene() is scene
    rgba = [0.0] * 4
    colours.GetColor(PREVIEW_TARGET_LABEL, rgba)
    r, g, b, a = rgba
    assert g > 0.6 and r < 0.4 and b < 0.4 and a == 1.0, f"label 1 should be green, is {rgba}"
    colours.GetColor(PREVIEW_INITIAL_LABEL, rgba)
    r, g, b, a = rgba
    assert r > 0.8 and g > 0.8 and b < 0.3 and a == 1.0, f"label 2 should be yellow, is {rgba}"
    colours.GetColor(0, rgba)
    assert rgba[3] == 0.0  # outside both windows: transparent
    # the tooltip promises exactly these colours for these windows
    tooltip = UI_FILE.read_text(encoding="utf-8")
    windows = {PREVIEW_TARGET_LABEL: "[HT, H0)", PREVIEW_INITIAL_LABEL: "[H0, θmax]"}
    for label, (colour, _name, _rgb) in PREVIEW_COLORS.items():
        assert f"{colour}: {windows[label]}" in tooltip
    # nothing of the preview is saved with the scene
    for n in (node, display, colours):
        assert not n.GetSaveWithScene() and n.GetHideFromEditors()
    scene.SetSaveToXMLString(1)
    scene.Commit()
    xml = scene.GetSceneXMLString()
    assert volume.GetID() in xml
    for n in (node, display, colours):
        assert f'id="{n.GetID()}"' not in xml
    # remove() leaves nothing behind
    ids = set(_node_ids(scene))
    preview.remove()
    assert ids - set(_node_ids(scene)) == {node.GetID(), display.GetID(), colours.GetID()}


def test_preview_update_touches_only_the_crop(scene):
    """Each drag step thresholds the cached crop in place (the measurement of its time is
    Testing/bench_slicer.py; this checks that an update writes no more than the crop)."""
    volume, seg, segId, *_ = _nodes(scene, size=(200, 200, 160), spacing=(0.8, 0.8, 1.0))
    preview = ThresholdPreview(scene)
    node = preview.update(volume, seg, segId, 300.0, 150.0, 2500.0)
    image, scalars = node.GetImageData(), node.GetImageData().GetPointData().GetScalars()
    volume_mtime = volume.GetImageData().GetMTime()
    for h0 in range(300, 340, 4):
        assert preview.update(volume, seg, segId, float(h0), 150.0, 2500.0) is node
    # same buffer, written in place; the CT untouched; the crop a few % of the volume
    assert node.GetImageData() is image and image.GetPointData().GetScalars() is scalars
    assert volume.GetImageData().GetMTime() == volume_mtime and preview.cacheBuilds == 1
    assert image.GetNumberOfPoints() < 0.05 * volume.GetImageData().GetNumberOfPoints()


# ---------------------------------------------------------------------------------------
# defect 8: progress and Cancel from the first second
# ---------------------------------------------------------------------------------------

def test_run_reports_progress_before_any_work_and_cancel_there_leaves_the_scene(scene):
    volume, seg, segId, *_ = _nodes(scene)
    out = scene.AddNewNodeByClass("vtkMRMLModelNode", "previous")
    before = _node_ids(scene)
    calls = []

    def progress(fraction, message):
        calls.append((time.perf_counter(), fraction, message))
        return False  # Cancel at the very first report

    t0 = time.perf_counter()
    with pytest.raises(CancelledError):
        nodes.run_on_nodes(volume, seg, segId, outputModelNode=out, progress=progress)
    assert len(calls) == 1 and calls[0][1] == 0.0 and "CT" in calls[0][2]
    assert calls[0][0] - t0 < 1.0  # "progress from the first second"
    assert _node_ids(scene) == before and out.GetPolyData() is None


def test_run_progress_covers_export_import_and_pipeline_in_order(scene):
    volume, seg, segId, *_ = _nodes(scene)
    calls = []
    nodes.run_on_nodes(volume, seg, segId, params={"spacing": 0.8, "h0": 500.0, "ht": 300.0},
                      progress=lambda f, m: calls.append((f, m)) or True)
    fractions = [f for f, _ in calls]
    messages = [m for _, m in calls]
    assert messages[:3] == ["Reading the CT volume", "Reading the segment", "Loading open3d"]
    assert fractions == sorted(fractions) and fractions[-1] == pytest.approx(1.0)
    first_pipeline = max(i for i, m in enumerate(messages) if m == "Loading open3d") + 1
    assert all(f < nodes.PIPELINE_START for f in fractions[:first_pipeline])
    assert all(f >= nodes.PIPELINE_START for f in fractions[first_pipeline:])
    assert len(fractions) - first_pipeline > 5


def test_open3d_import_reports_progress_and_honours_cancel(tmp_path):
    """In a fresh interpreter (open3d not yet imported) the import runs in a helper thread
    while the progress callback keeps coming; Cancel is honoured within a tick."""
    script = textwrap.dedent(f"""
        import json, sys, time
        sys.path.insert(0, {str(ROOT)!r})
        from BoneWatertightLib.app import nodes, run
        from BoneWatertightLib.errors import CancelledError
        from BoneWatertightLib.stages import poisson
        assert "open3d" not in sys.modules and poisson._OPEN3D is None
        stamps = []
        def callback(fraction, message):
            stamps.append((time.perf_counter(), fraction, message))
            return len(stamps) < {{stop}}
        t0 = time.perf_counter()
        outcome = "done"
        try:
            run.load_pipeline(nodes.RunProgress(callback), nodes.IMPORT_START, nodes.PIPELINE_START)
        except CancelledError:
            outcome = "cancelled"
        t1 = time.perf_counter()
        print(json.dumps(dict(outcome=outcome, t0=t0, t1=t1, stamps=stamps,
                              imported=poisson._OPEN3D is not None)))
    """)
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    results = {}
    for stop in (10 ** 6, 3):
        path = tmp_path / f"probe_{stop}.py"
        path.write_text(script.replace("{stop}", str(stop)), encoding="utf-8")
        proc = subprocess.run([sys.executable, str(path)], capture_output=True, text=True, env=env,
                              timeout=300)
        assert proc.returncode == 0, proc.stderr
        results[stop] = json.loads(proc.stdout.strip().splitlines()[-1])
    full, cancelled = results[10 ** 6], results[3]
    assert full["outcome"] == "done" and full["imported"]
    times = [full["t0"]] + [s[0] for s in full["stamps"]] + [full["t1"]]
    gaps = np.diff(times)
    duration = full["t1"] - full["t0"]
    print(f"open3d import {duration:.2f} s, {len(full['stamps'])} reports, longest gap {gaps.max():.3f} s")
    # reports keep coming while the import runs (a tick every IMPORT_TICK_S, fewer while the
    # extension's shared library loads with the GIL held): not one report, then silence
    assert len(full["stamps"]) >= 1 + int(0.3 * duration / run.IMPORT_TICK_S)
    assert gaps.max() < max(1.0, 0.5 * duration)
    assert all(m == "Loading open3d" for _, _, m in full["stamps"])
    # Cancel at the third report: raised right there, without waiting for the import
    assert cancelled["outcome"] == "cancelled" and len(cancelled["stamps"]) == 3
    assert cancelled["t1"] - cancelled["stamps"][-1][0] < 0.5


# ---------------------------------------------------------------------------------------
# defect 9: the scene closes (or a node goes) during a run
# ---------------------------------------------------------------------------------------

def _segment_state(seg):
    s = seg.GetSegmentation()
    return [s.GetNthSegmentID(i) for i in range(s.GetNumberOfSegments())]


@pytest.mark.parametrize("when", ["export", "pipeline", "last"])
def test_scene_close_during_a_run_cancels_and_writes_nothing(scene, when):
    volume, seg, segId, *_ = _nodes(scene)
    segments = _segment_state(seg)
    calls = []

    def progress(fraction, message):
        calls.append(message)
        if not scene.GetNumberOfNodes():
            return True
        if (when == "export" and message == "Reading the segment") or \
                (when == "pipeline" and fraction > nodes.PIPELINE_START) or \
                (when == "last" and fraction >= 1.0):
            scene.Clear(0)  # File > Close Scene, processed while the run pumps events
        return True

    with pytest.raises(CancelledError, match="scene was closed"):
        nodes.run_on_nodes(volume, seg, segId, params={"spacing": 0.8, "h0": 500.0, "ht": 300.0},
                          progress=progress, addAsSegment=True, showIntermediates=True)
    assert scene.GetNumberOfNodes() == 0  # no model, no intermediates in the new scene
    assert _segment_state(seg) == segments  # nothing written into the removed segmentation
    if when == "last":
        assert calls[-1] == "done"  # the pipeline had finished; the result was still not stored


def test_removing_the_output_or_an_input_during_a_run_cancels(scene):
    volume, seg, segId, *_ = _nodes(scene)
    out = scene.AddNewNodeByClass("vtkMRMLModelNode", "previous")
    for victim in (out, seg):
        removed = []

        def progress(fraction, message):
            if message == "Loading open3d" and not removed:
                removed.append(victim.GetName())
                scene.RemoveNode(victim)
            return True

        with pytest.raises(CancelledError, match="was removed from the scene"):
            nodes.run_on_nodes(volume, seg, segId, outputModelNode=out, progress=progress,
                              params={"spacing": 0.8, "h0": 500.0, "ht": 300.0})
        assert out.GetPolyData() is None
        scene.AddNode(victim)


def test_run_guard_stops_observing_after_the_run(scene):
    volume, seg, segId, *_ = _nodes(scene)
    with nodes.RunGuard(scene, (volume,)) as guard:
        assert guard.reason is None
    scene.Clear(0)
    guard.check()  # closed after the run: not this run's business
    assert guard.reason is None


# ---------------------------------------------------------------------------------------
# defect 10: no leak under a non-linear transform
# ---------------------------------------------------------------------------------------

def _thin_plate_transform(scene):
    tn = scene.AddNewNodeByClass("vtkMRMLTransformNode", "warp")
    source, target = vtk.vtkPoints(), vtk.vtkPoints()
    for p in [(-60, -60, -30), (60, -60, -30), (-60, 60, -30), (-60, -60, 90), (60, 60, 90), (0, 0, 30)]:
        source.InsertNextPoint(p)
        target.InsertNextPoint(p[0] + 0.5 * (p[2] > 50), p[1], p[2] + 0.3 * (p[0] > 0))
    tps = vtk.vtkThinPlateSplineTransform()
    tps.SetSourceLandmarks(source)
    tps.SetTargetLandmarks(target)
    tps.SetBasisToR()
    tn.SetAndObserveTransformToParent(tps)
    assert not tn.IsTransformToWorldLinear()
    return tn


def test_volume_copy_under_a_non_linear_transform_is_released(scene):
    volume, seg, segId, ct, *_ = _nodes(scene)
    volume.SetAndObserveTransformNodeID(_thin_plate_transform(scene).GetID())
    image = mrml._hardened_oriented_image(volume)
    assert image.GetReferenceCount() == 1  # the caller's reference is the only one
    deleted = []
    image.AddObserver(vtk.vtkCommand.DeleteEvent, lambda *a: deleted.append(True))
    del image
    gc.collect()
    assert deleted, "the resampled copy of the volume outlived its last Python reference"
    # the conversions still work under the warp (and release their copies)
    hardened = mrml.volume_to_sitk(volume)
    assert hardened.GetSize() != (0, 0, 0)
    mask = mrml.segment_to_sitk_mask(seg, segId, volume)
    assert sitk.GetArrayViewFromImage(mask).sum() > 0


# ---------------------------------------------------------------------------------------
# Auto on extended-HU CT with metal (defect 7: the adapter's half; the clamp is tested in
# test_slicer_module.py)
# ---------------------------------------------------------------------------------------

def test_auto_on_metal_ct_proposes_values_the_schema_accepts(scene):
    """Metal in the bone (extended-HU scale) is left out of the estimate: the proposal keeps
    theta_max, stays in the schema's ranges and is not raised by the implant."""
    ct, centre, radius = _ct_image()
    clean = nodes.propose_thresholds(mrml.volume_node_from_sitk(scene, ct),
                                    *mrml.segmentation_node_from_mask(scene, _ball_mask(ct, centre, radius + 2.0)))
    arr = sitk.GetArrayFromImage(ct).astype(np.int32)
    arr[20:24, 22:28, 28:32] = 14000  # an implant inside the bone, extended-HU scale
    metal = sitk.GetImageFromArray(arr)
    metal.CopyInformation(ct)
    volume = mrml.volume_node_from_sitk(scene, metal)
    seg, segId = mrml.segmentation_node_from_mask(scene, _ball_mask(ct, centre, radius + 2.0))
    proposal = nodes.propose_thresholds(volume, seg, segId)
    Parameters(theta_max=float(proposal["theta_max"]), h0=float(proposal["h0"]),
               ht=float(proposal["ht"])).validate()
    assert abs(proposal["h0"] - clean["h0"]) <= 20