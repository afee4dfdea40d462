"""BoneWatertightLib.mrml on real MRML nodes from the slicer-core wheel (no Qt, no mocks).

Phantom: a sphere of radius R_MM (~1000 HU, smooth edge) in soft tissue (~40 HU), in a volume
with an oblique IJK->RAS (rotation + anisotropic spacing + non-zero origin). The rough segment
is built on a coarser, shifted, axis-aligned grid so its geometry differs from the CT's.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import SimpleITK as sitk

slicer = pytest.importorskip("slicer")
vtk = pytest.importorskip("vtk")
from vtk.util import numpy_support as ns  # noqa: E402

from BoneWatertightLib import mrml  # noqa: E402
from BoneWatertightLib.app import nodes, summaries  # noqa: E402
from BoneWatertightLib.errors import (  # noqa: E402
    CancelledError,
    EmptySegmentError,
    InputError,
    NoOverlapError,
    ThresholdError,
    VolumeTypeError,
)
from BoneWatertightLib.mesh import Surface  # noqa: E402

R_MM = 11.0
CENTER_RAS = np.array([12.0, -25.0, 140.0])
DIMS = (44, 40, 36)  # i, j, k
SPACING = (0.9, 1.0, 1.2)
# Accuracy bound of the reconstructed sphere (1 mm-class voxels): every vertex within
# MAX_RADIAL_ERROR_MM of the analytic surface, mean within MEAN_RADIAL_ERROR_MM.
MAX_RADIAL_ERROR_MM = 0.9
MEAN_RADIAL_ERROR_MM = 0.3


def _rotation(axis, angle_deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    a = math.radians(angle_deg)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K


def _matrix(lin, origin):
    m = np.eye(4)
    m[:3, :3] = lin
    m[:3, 3] = origin
    return m


def _vtk_matrix(a):
    m = vtk.vtkMatrix4x4()
    for r in range(4):
        for c in range(4):
            m.SetElement(r, c, float(a[r, c]))
    return m


def _image_from_array(arr_kji, vtk_type):
    img = vtk.vtkImageData()
    img.SetDimensions(arr_kji.shape[2], arr_kji.shape[1], arr_kji.shape[0])
    img.GetPointData().SetScalars(ns.numpy_to_vtk(np.ascontiguousarray(arr_kji).ravel(), deep=True,
                                                  array_type=vtk_type))
    return img


def _voxel_centres_ras(ijk_to_ras, dims):
    i, j, k = np.meshgrid(np.arange(dims[0]), np.arange(dims[1]), np.arange(dims[2]), indexing="ij")
    ijk = np.stack([i, j, k, np.ones_like(i)], axis=-1).reshape(-1, 4).astype(float)
    ras = ijk @ ijk_to_ras.T
    # reorder to (k, j, i)
    return ras[:, :3].reshape(dims[0], dims[1], dims[2], 3).transpose(2, 1, 0, 3)


CT_IJK_TO_RAS = _matrix(_rotation([1.0, 2.0, 0.5], 27.0) @ np.diag([-1.0, -1.0, 1.0]) @ np.diag(SPACING),
                        [0, 0, 0])
# put the phantom centre in the middle of the grid
_mid = np.array([(d - 1) / 2 for d in DIMS] + [1.0])
CT_IJK_TO_RAS[:3, 3] = CENTER_RAS - (CT_IJK_TO_RAS @ _mid)[:3]


def _phantom_hu(ras_kji):
    r = np.linalg.norm(ras_kji - CENTER_RAS, axis=-1)
    # smooth edge (sigma 0.6 mm): the half-maximum iso-surface is the sphere of radius R_MM
    edge = 0.5 * (1.0 - np.vectorize(math.erf)((r - R_MM) / (0.6 * math.sqrt(2.0))))
    rng = np.random.default_rng(7)
    return (40.0 + 960.0 * edge + rng.normal(0.0, 8.0, r.shape)).round().astype(np.int16)


@pytest.fixture()
def scene():
    sc = slicer.vtkMRMLScene()
    # converter rules are registered by the segmentations logic; it must see the scene first
    logic = slicer.vtkSlicerSegmentationsModuleLogic()
    logic.SetMRMLScene(sc)
    sc._bw_logic = logic  # keep alive
    return sc


def _add_ct(scene, name="CT"):
    node = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", name)
    hu = _phantom_hu(_voxel_centres_ras(CT_IJK_TO_RAS, DIMS))
    node.SetAndObserveImageData(_image_from_array(hu, vtk.VTK_SHORT))
    node.SetIJKToRASMatrix(_vtk_matrix(CT_IJK_TO_RAS))
    return node, hu


SEG_SPACING = 2.0
SEG_ORIGIN_SHIFT = np.array([0.7, -0.3, 0.45])


def _coarse_labelmap_matrix():
    return _matrix(np.diag([SEG_SPACING] * 3), CENTER_RAS - 16.0 + SEG_ORIGIN_SHIFT)


def _add_segmentation(scene, radius=R_MM - 1.5, centre=CENTER_RAS, name="Bone"):
    """Rough segment on a coarse (2 mm), shifted, axis-aligned grid, imported from a labelmap."""
    dims = (17, 17, 17)
    m = _coarse_labelmap_matrix()
    m = m.copy()
    m[:3, 3] += centre - CENTER_RAS
    ras = _voxel_centres_ras(m, dims)
    lab = (np.linalg.norm(ras - centre, axis=-1) <= radius).astype(np.uint8)
    labNode = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode", "rough")
    labNode.SetAndObserveImageData(_image_from_array(lab, vtk.VTK_UNSIGNED_CHAR))
    labNode.SetIJKToRASMatrix(_vtk_matrix(m))
    seg = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", "Segmentation")
    assert slicer.vtkSlicerSegmentationsModuleLogic.ImportLabelmapToSegmentationNode(labNode, seg)
    scene.RemoveNode(labNode)
    segId = seg.GetSegmentation().GetNthSegmentID(0)
    seg.GetSegmentation().GetSegment(segId).SetName(name)
    return seg, segId, lab, m


def _state(scene, volume, seg):
    """Everything a failed run must leave untouched."""
    ids = [scene.GetNthNode(i).GetID() for i in range(scene.GetNumberOfNodes())]
    vol_bytes = ns.vtk_to_numpy(volume.GetImageData().GetPointData().GetScalars()).tobytes()
    segmentation = seg.GetSegmentation()
    seg_ids = [segmentation.GetNthSegmentID(i) for i in range(segmentation.GetNumberOfSegments())]
    seg_bytes = []
    for sid in seg_ids:
        rep = segmentation.GetSegment(sid).GetRepresentation(
            slicer.vtkSegmentationConverter.GetBinaryLabelmapRepresentationName())
        seg_bytes.append(None if rep is None or rep.GetPointData().GetScalars() is None
                         else ns.vtk_to_numpy(rep.GetPointData().GetScalars()).tobytes())
    reps = []
    for sid in seg_ids:
        names = []
        segmentation.GetSegment(sid).GetContainedRepresentationNames(names)
        reps.append(sorted(names))
    m = vtk.vtkMatrix4x4()
    volume.GetIJKToRASMatrix(m)
    return dict(ids=ids, vol=vol_bytes, seg_ids=seg_ids, seg=seg_bytes, reps=reps,
                conv=segmentation.SerializeAllConversionParameters(),
                source=segmentation.GetSourceRepresentationName(),
                ijk_to_ras=[m.GetElement(r, c) for r in range(4) for c in range(4)],
                volume_transform=volume.GetTransformNodeID())


# ---------------------------------------------------------------------------------------
# volume_to_sitk
# ---------------------------------------------------------------------------------------

def test_volume_to_sitk_geometry_and_values(scene):
    node, hu = _add_ct(scene)
    img = mrml.volume_to_sitk(node)
    assert img.GetSize() == DIMS
    arr = sitk.GetArrayFromImage(img)
    assert np.array_equal(arr, hu)
    rng = np.random.default_rng(0)
    for _ in range(20):
        ijk = [int(rng.integers(0, d)) for d in DIMS]
        ras = (CT_IJK_TO_RAS @ np.array(ijk + [1.0]))[:3]
        lps = np.array(img.TransformIndexToPhysicalPoint(ijk))
        assert np.allclose(lps, [-ras[0], -ras[1], ras[2]], atol=1e-6)
        assert np.allclose(mrml.sitk_index_to_ras(img, ijk), ras, atol=1e-6)
    assert np.allclose(img.GetSpacing(), SPACING)


def test_volume_to_sitk_is_a_copy(scene):
    node, hu = _add_ct(scene)
    img = mrml.volume_to_sitk(node)
    img[0, 0, 0] = 1234
    view = sitk.GetArrayViewFromImage(img)
    assert view[0, 0, 0] == 1234
    assert ns.vtk_to_numpy(node.GetImageData().GetPointData().GetScalars())[0] == hu.ravel()[0]


def test_volume_to_sitk_applies_linear_parent_transform(scene):
    node, _ = _add_ct(scene)
    tn = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode")
    to_parent = _matrix(_rotation([0, 0, 1], 30.0), [5.0, -7.0, 11.0])
    tn.SetMatrixTransformToParent(_vtk_matrix(to_parent))
    node.SetAndObserveTransformNodeID(tn.GetID())
    img = mrml.volume_to_sitk(node)
    world = to_parent @ CT_IJK_TO_RAS
    for ijk in ([0, 0, 0], [43, 39, 35], [10, 20, 30]):
        ras = (world @ np.array(ijk + [1.0]))[:3]
        assert np.allclose(mrml.sitk_index_to_ras(img, ijk), ras, atol=1e-6)
    # the node itself keeps its transform (nothing hardened in place)
    assert node.GetTransformNodeID() == tn.GetID()


def test_volume_type_errors(scene):
    lab = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode", "labels")
    lab.SetAndObserveImageData(_image_from_array(np.zeros((4, 4, 4), np.uint8), vtk.VTK_UNSIGNED_CHAR))
    with pytest.raises(VolumeTypeError, match="label map"):
        mrml.volume_to_sitk(lab)
    rgb = scene.AddNewNodeByClass("vtkMRMLVectorVolumeNode", "rgb")
    im = vtk.vtkImageData()
    im.SetDimensions(4, 4, 4)
    im.AllocateScalars(vtk.VTK_UNSIGNED_CHAR, 3)
    rgb.SetAndObserveImageData(im)
    with pytest.raises(VolumeTypeError):
        mrml.volume_to_sitk(rgb)
    flat = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "flat")
    flat.SetAndObserveImageData(_image_from_array(np.zeros((1, 8, 8), np.int16), vtk.VTK_SHORT))
    with pytest.raises(VolumeTypeError, match="2-D"):
        mrml.volume_to_sitk(flat)
    with pytest.raises(InputError, match="No CT"):
        mrml.volume_to_sitk(None)


# ---------------------------------------------------------------------------------------
# segment_to_sitk_mask
# ---------------------------------------------------------------------------------------

def _expected_mask_on_ct(lab, lab_ijk_to_ras):
    """Nearest-neighbour lookup of the coarse labelmap at every CT voxel centre."""
    ras = _voxel_centres_ras(CT_IJK_TO_RAS, DIMS).reshape(-1, 3)
    ijk = (np.c_[ras, np.ones(len(ras))] @ np.linalg.inv(lab_ijk_to_ras).T)[:, :3]
    idx = np.floor(ijk + 0.5).astype(int)
    inside = np.all((idx >= 0) & (idx < np.array(lab.shape[::-1])), axis=1)
    out = np.zeros(len(ras), np.uint8)
    out[inside] = lab[idx[inside, 2], idx[inside, 1], idx[inside, 0]]
    frac = np.abs(ijk - np.round(ijk))  # distance of the sample to a rounding tie
    tie = np.any(np.abs(frac - 0.5) < 1e-3, axis=1)
    return out.reshape(DIMS[::-1]), tie.reshape(DIMS[::-1])


def test_segment_mask_lands_on_ct_grid(scene):
    ct, _ = _add_ct(scene)
    seg, segId, lab, m = _add_segmentation(scene)
    before = _state(scene, ct, seg)
    mask = mrml.segment_to_sitk_mask(seg, segId, ct)
    img = mrml.volume_to_sitk(ct)
    assert mask.GetSize() == img.GetSize()
    assert np.allclose(mask.GetOrigin(), img.GetOrigin())
    assert np.allclose(mask.GetDirection(), img.GetDirection())
    got = sitk.GetArrayFromImage(mask)
    want, tie = _expected_mask_on_ct(lab, m)
    assert got.sum() > 1000
    # identical except exactly at nearest-neighbour rounding ties
    assert np.array_equal(got[~tie], want[~tie])
    assert _state(scene, ct, seg) == before


def test_segment_mask_with_shared_labelmap_and_second_segment(scene):
    ct, _ = _add_ct(scene)
    seg, segId, lab, m = _add_segmentation(scene)
    # a second segment in the same layer with another label value must not leak into the mask
    other = slicer.vtkOrientedImageData()
    other.DeepCopy(seg.GetSegmentation().GetSegment(segId).GetRepresentation(
        slicer.vtkSegmentationConverter.GetBinaryLabelmapRepresentationName()))
    newId = seg.GetSegmentation().AddEmptySegment("other")
    a = ns.vtk_to_numpy(other.GetPointData().GetScalars())
    bone_voxels = a != 0
    a[:] = 0
    a[: a.size // 3] = 1  # the first planes of the bone's extent ...
    a[bone_voxels] = 0  # ... around, but not on, the bone
    other.Modified()
    assert slicer.vtkSlicerSegmentationsModuleLogic.SetBinaryLabelmapToSegment(other, seg, newId)
    shared = []
    seg.GetSegmentation().GetSegmentIDsSharingBinaryLabelmapRepresentation(segId, shared)
    assert newId in shared  # one labelmap, two label values
    mask_bone = sitk.GetArrayFromImage(mrml.segment_to_sitk_mask(seg, segId, ct))
    want, tie = _expected_mask_on_ct(lab, m)
    assert np.array_equal(mask_bone[~tie], want[~tie])
    mask_other = sitk.GetArrayFromImage(mrml.segment_to_sitk_mask(seg, newId, ct))
    assert mask_other.sum() > 100
    assert not np.any(mask_other & mask_bone)


def test_segment_mask_from_closed_surface_source(scene):
    ct, _ = _add_ct(scene)
    src = vtk.vtkSphereSource()
    src.SetCenter(*CENTER_RAS)
    src.SetRadius(R_MM)
    src.SetThetaResolution(48)
    src.SetPhiResolution(48)
    src.Update()
    seg = scene.AddNewNodeByClass("vtkMRMLSegmentationNode")
    seg.GetSegmentation().SetSourceRepresentationName(
        slicer.vtkSegmentationConverter.GetClosedSurfaceRepresentationName())
    segment = slicer.vtkSegment()
    segment.SetName("ball")
    segment.AddRepresentation(slicer.vtkSegmentationConverter.GetClosedSurfaceRepresentationName(),
                              src.GetOutput())
    seg.GetSegmentation().AddSegment(segment, "ball")
    conv = seg.GetSegmentation().SerializeAllConversionParameters()
    mask = mrml.segment_to_sitk_mask(seg, "ball", ct)
    voxel_volume = float(np.prod(SPACING))
    vol = sitk.GetArrayViewFromImage(mask).sum() * voxel_volume
    assert vol == pytest.approx(4 / 3 * math.pi * R_MM ** 3, rel=0.08)
    # no labelmap representation was added to the user's segmentation, parameters unchanged
    assert not seg.GetSegmentation().ContainsRepresentation(
        slicer.vtkSegmentationConverter.GetBinaryLabelmapRepresentationName())
    assert seg.GetSegmentation().SerializeAllConversionParameters() == conv


def test_segment_errors(scene):
    ct, _ = _add_ct(scene)
    seg, segId, _, _ = _add_segmentation(scene)
    with pytest.raises(InputError, match="does not exist"):
        mrml.segment_to_sitk_mask(seg, "nope", ct)
    emptyId = seg.GetSegmentation().AddEmptySegment("empty")
    with pytest.raises(EmptySegmentError):
        mrml.segment_to_sitk_mask(seg, emptyId, ct)
    far, farId, _, _ = _add_segmentation(scene, centre=CENTER_RAS + [0, 0, 200.0])
    with pytest.raises(NoOverlapError):
        mrml.segment_to_sitk_mask(far, farId, ct)


# ---------------------------------------------------------------------------------------
# outputs
# ---------------------------------------------------------------------------------------

def _octahedron_lps():
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float) * 5 + [1, 2, 3]
    f = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    return Surface(v, f, "LPS", {"DistanceToConstraints": np.linspace(0, 1, 6)})


def test_update_model_node_ras_normals_display(scene):
    surf = _octahedron_lps()
    node = scene.AddNewNodeByClass("vtkMRMLModelNode", "out")
    mrml.update_model_node(node, surf, colorByDistance=True)
    poly = node.GetPolyData()
    pts = ns.vtk_to_numpy(poly.GetPoints().GetData())
    assert np.allclose(pts, surf.vertices * [-1, -1, 1])
    normals = ns.vtk_to_numpy(poly.GetPointData().GetNormals())
    # outward normals in RAS: they point away from the centre
    assert np.all(np.einsum("ij,ij->i", normals, pts - pts.mean(axis=0)) > 0)
    assert poly.GetPointData().GetArray("DistanceToConstraints") is not None
    d = node.GetDisplayNode()
    assert d is not None and d.GetScalarVisibility() and d.GetActiveScalarName() == "DistanceToConstraints"


def test_add_surface_as_segment(scene):
    ct, _ = _add_ct(scene)
    seg, segId, _, _ = _add_segmentation(scene)
    conv = seg.GetSegmentation().SerializeAllConversionParameters()
    src = vtk.vtkSphereSource()
    src.SetRadius(6.0)
    src.SetCenter(*CENTER_RAS)
    src.SetThetaResolution(24)
    src.SetPhiResolution(24)
    src.Update()
    from BoneWatertightLib.mesh import from_polydata
    surf = from_polydata(src.GetOutput(), "RAS")
    newId = mrml.add_surface_as_segment(seg, surf, "Bone watertight")
    assert seg.GetSegmentation().GetNumberOfSegments() == 2
    mask = sitk.GetArrayFromImage(mrml.segment_to_sitk_mask(seg, newId, ct))
    assert mask.sum() * np.prod(SPACING) == pytest.approx(4 / 3 * math.pi * 6.0 ** 3, rel=0.25)
    assert seg.GetSegmentation().SerializeAllConversionParameters() == conv


# ---------------------------------------------------------------------------------------
# run_on_nodes: error paths leave the scene unchanged
# ---------------------------------------------------------------------------------------

def _previous_output(scene):
    node = scene.AddNewNodeByClass("vtkMRMLModelNode", "previous result")
    mrml.update_model_node(node, _octahedron_lps())
    return node, ns.vtk_to_numpy(node.GetPolyData().GetPoints().GetData()).tobytes()


@pytest.mark.parametrize("case", ["empty", "no_overlap", "thresholds", "labelmap_ct", "unknown_id", "no_volume"])
def test_run_on_nodes_input_errors_leave_scene_unchanged(scene, case):
    ct, _ = _add_ct(scene)
    seg, segId, _, _ = _add_segmentation(scene)
    emptyId = seg.GetSegmentation().AddEmptySegment("empty")
    far, farId, _, _ = _add_segmentation(scene, centre=CENTER_RAS + [0, 0, 200.0])
    lab = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode", "labels")
    lab.SetAndObserveImageData(_image_from_array(np.zeros((4, 4, 4), np.uint8), vtk.VTK_UNSIGNED_CHAR))
    out, out_bytes = _previous_output(scene)
    before = _state(scene, ct, seg)
    before_far = _state(scene, ct, far)
    kwargs = dict(volumeNode=ct, segmentationNode=seg, segmentId=segId, outputModelNode=out)
    expected = InputError
    if case == "empty":
        kwargs["segmentId"], expected = emptyId, EmptySegmentError
    elif case == "no_overlap":
        kwargs["segmentationNode"], kwargs["segmentId"], expected = far, farId, NoOverlapError
    elif case == "thresholds":
        kwargs["params"] = {"h0": 150.0, "ht": 300.0}
    elif case == "labelmap_ct":
        kwargs["volumeNode"], expected = lab, VolumeTypeError
    elif case == "unknown_id":
        kwargs["segmentId"] = "S_does_not_exist"
    elif case == "no_volume":
        kwargs["volumeNode"] = None
    with pytest.raises(expected) as info:
        nodes.run_on_nodes(**kwargs, addAsSegment=True, showIntermediates=True)
    assert len(str(info.value)) > 20  # a sentence, not a code
    assert _state(scene, ct, seg) == before
    assert _state(scene, ct, far) == before_far
    assert ns.vtk_to_numpy(out.GetPolyData().GetPoints().GetData()).tobytes() == out_bytes


def test_run_on_nodes_threshold_window_without_bone_leaves_scene_unchanged(scene):
    ct, _ = _add_ct(scene)
    seg, segId, _, _ = _add_segmentation(scene)
    before = _state(scene, ct, seg)
    # no voxel of the region reaches [H0, theta_max] (the phantom's maximum is ~1030 HU)
    with pytest.raises(ThresholdError):
        nodes.run_on_nodes(ct, seg, segId, params={"h0": 1800.0, "ht": 1700.0, "theta_max": 2500.0})
    assert _state(scene, ct, seg) == before


def test_run_on_nodes_cancel_leaves_scene_unchanged(scene):
    ct, _ = _add_ct(scene)
    seg, segId, _, _ = _add_segmentation(scene)
    out, out_bytes = _previous_output(scene)
    before = _state(scene, ct, seg)
    calls = []

    def progress(fraction, message):
        calls.append((fraction, message))
        return len(calls) < 3  # cancel at the third report

    with pytest.raises(CancelledError):
        nodes.run_on_nodes(ct, seg, segId, outputModelNode=out, progress=progress, addAsSegment=True)
    assert len(calls) == 3
    assert _state(scene, ct, seg) == before
    assert ns.vtk_to_numpy(out.GetPolyData().GetPoints().GetData()).tobytes() == out_bytes


# ---------------------------------------------------------------------------------------
# run_on_nodes: the real pipeline on the oblique phantom
# ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("refine_edges", [False, True])
def test_run_on_nodes_sphere_accuracy_in_ras(scene, refine_edges):
    ct, hu = _add_ct(scene)
    seg, segId, _, _ = _add_segmentation(scene)
    conv = seg.GetSegmentation().SerializeAllConversionParameters()
    n_nodes = scene.GetNumberOfNodes()
    fractions = []
    model, result = nodes.run_on_nodes(
        ct, seg, segId, params={"spacing": 0.6, "h0": 500.0, "ht": 300.0, "refine_edges": refine_edges},
        progress=lambda f, m: fractions.append(f) or True, addAsSegment=True, colorByDistance=True)
    assert model is not None and model.IsA("vtkMRMLModelNode")
    assert scene.GetNumberOfNodes() > n_nodes  # model (+ display node) added
    pts = ns.vtk_to_numpy(model.GetPolyData().GetPoints().GetData())
    radial = np.linalg.norm(pts - CENTER_RAS, axis=1) - R_MM
    # least-squares sphere: its centre tests the adapter's geometry (IJK->RAS, LPS<->RAS), its
    # radius the pipeline's accuracy
    A = np.c_[2 * pts, np.ones(len(pts))]
    sol = np.linalg.lstsq(A, (pts ** 2).sum(axis=1), rcond=None)[0]
    fit_centre, fit_radius = sol[:3], float(np.sqrt(sol[3] + sol[:3] @ sol[:3]))
    print(f"sphere phantom (refine_edges={refine_edges}): {len(pts)} vertices, fitted centre offset "
          f"{np.linalg.norm(fit_centre - CENTER_RAS):.3f} mm, fitted radius {fit_radius:.3f} (truth {R_MM}), "
          f"|r-R| mean {np.abs(radial).mean():.3f} mm, max {np.abs(radial).max():.3f} mm")
    assert np.linalg.norm(fit_centre - CENTER_RAS) < 0.1
    assert np.abs(radial).max() <= MAX_RADIAL_ERROR_MM
    assert np.abs(radial).mean() <= MEAN_RADIAL_ERROR_MM
    # closed: no boundary or non-manifold edges
    fe = vtk.vtkFeatureEdges()
    fe.SetInputData(model.GetPolyData())
    fe.BoundaryEdgesOn()
    fe.NonManifoldEdgesOn()
    fe.FeatureEdgesOff()
    fe.ManifoldEdgesOff()
    fe.Update()
    assert fe.GetOutput().GetNumberOfCells() == 0
    assert model.GetPolyData().GetPointData().GetNormals() is not None
    assert model.GetDisplayNode() is not None
    import json
    import re

    stored = json.loads(model.GetAttribute(mrml.REPORT_ATTRIBUTE))
    assert stored["timings"]["total"] == pytest.approx(result.report.timings.total)
    summary = summaries.summarize(result)
    assert re.search(rf", {result.report.timings.total:.1f} s", summary), summary
    assert "checks passed" in summary and f"{len(pts)} vertices" in summary
    assert fractions and fractions[-1] == pytest.approx(1.0, abs=0.05)
    # inputs untouched, new segment added with the user's conversion parameters intact
    assert np.array_equal(ns.vtk_to_numpy(ct.GetImageData().GetPointData().GetScalars()), hu.ravel())
    assert seg.GetSegmentation().GetNumberOfSegments() == 2
    assert seg.GetSegmentation().SerializeAllConversionParameters() == conv
