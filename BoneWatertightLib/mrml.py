"""Adapter between MRML nodes (3D Slicer / slicer-core) and the pure library.

The only module of BoneWatertightLib that imports ``slicer``; it uses MRML/VTK classes only
(never qt, ctk, slicer.app or slicer.util), so it runs inside Slicer and, in CI, on the
``slicer-core`` wheel.

Coordinate conventions: MRML is RAS, SimpleITK images and the pipeline are LPS. The volume's
full IJK->RAS matrix (any direction, non-zero origin) and its parent transform (world frame)
are converted into the SimpleITK origin/spacing/direction; surfaces come back as RAS polydata.

Nothing here modifies an input node: voxels are copied, the segment is exported through
vtkOrientedImageData objects that never enter the scene, and the output model node is only
created or touched after the pipeline succeeded.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import SimpleITK as sitk
import vtk
from vtk.util import numpy_support as ns

import slicer

from .errors import (
    EmptySegmentError,
    InputError,
    NoOverlapError,
    VolumeTypeError,
)
from .mesh.surface import Surface, to_polydata
from .params import Parameters
from .report import summary_line, to_json

_FLIP_XY = np.diag([-1.0, -1.0, 1.0])
DISTANCE_ARRAY = "DistanceToConstraints"
REPORT_ATTRIBUTE = "BoneWatertight.Report"


# ---------------------------------------------------------------------------------------
# geometry helpers
# ---------------------------------------------------------------------------------------

def _vtk_to_np_matrix(m: vtk.vtkMatrix4x4) -> np.ndarray:
    return np.array([[m.GetElement(r, c) for c in range(4)] for r in range(4)])


def _np_to_vtk_matrix(a: np.ndarray) -> vtk.vtkMatrix4x4:
    m = vtk.vtkMatrix4x4()
    for r in range(4):
        for c in range(4):
            m.SetElement(r, c, float(a[r, c]))
    return m


def _to_world_matrix(node) -> Optional[np.ndarray]:
    """4x4 node->world matrix; None when the parent transform chain is non-linear."""
    tn = node.GetParentTransformNode()
    if tn is None:
        return np.eye(4)
    if not tn.IsTransformToWorldLinear():
        return None
    m = vtk.vtkMatrix4x4()
    tn.GetMatrixTransformToWorld(m)
    return _vtk_to_np_matrix(m)


def _ijk_to_world(volumeNode) -> Optional[np.ndarray]:
    """IJK->world-RAS matrix of a volume node, or None if a non-linear transform applies."""
    world = _to_world_matrix(volumeNode)
    if world is None:
        return None
    m = vtk.vtkMatrix4x4()
    volumeNode.GetIJKToRASMatrix(m)
    return world @ _vtk_to_np_matrix(m)


def _hardened_oriented_image(volumeNode):
    """Voxel copy of the volume resampled into world space (used for non-linear transforms)."""
    image = slicer.vtkSlicerSegmentationsModuleLogic.CreateOrientedImageDataFromVolumeNode(volumeNode, None)
    if image is None:
        raise InputError(f"Could not apply the transform of volume '{volumeNode.GetName()}'; "
                         "harden the transform (Data module) and try again.")
    return image


def _oriented_image_matrix(image) -> np.ndarray:
    m = vtk.vtkMatrix4x4()
    image.GetImageToWorldMatrix(m)
    return _vtk_to_np_matrix(m)


def _array_from_image_data(image) -> np.ndarray:
    """(k, j, i) numpy *copy* of the scalars; never a view into the node's buffer."""
    dims = image.GetDimensions()
    scalars = image.GetPointData().GetScalars()
    arr = ns.vtk_to_numpy(scalars)
    return np.array(arr, copy=True).reshape(dims[2], dims[1], dims[0])


def _sitk_from_array(arr: np.ndarray, ijk_to_ras: np.ndarray, extent_start) -> sitk.Image:
    """SimpleITK image (LPS) from a (k, j, i) array and its IJK->RAS matrix.

    ``extent_start`` is the IJK index of arr[0, 0, 0] (MRML image extents may not start at 0).
    """
    lin = ijk_to_ras[:3, :3]
    spacing = np.linalg.norm(lin, axis=0)
    if np.any(spacing <= 0):
        raise VolumeTypeError("The volume has a zero voxel spacing; it is not a valid 3-D image.")
    direction_ras = lin / spacing
    # SimpleITK needs an orthonormal direction; a shear only arises from a sheared parent
    # transform, which must be hardened (resampled) by the user first.
    if not np.allclose(direction_ras.T @ direction_ras, np.eye(3), atol=1e-4):
        raise InputError("The volume's geometry is sheared (e.g. by a sheared parent transform). "
                         "Harden the transform with resampling, or remove it, and try again.")
    origin_ras = ijk_to_ras @ np.array([*extent_start, 1.0])
    image = sitk.GetImageFromArray(arr)
    image.SetSpacing([float(s) for s in spacing])
    image.SetOrigin([float(v) for v in (_FLIP_XY @ origin_ras[:3])])
    image.SetDirection([float(v) for v in (_FLIP_XY @ direction_ras).ravel()])
    return image


def sitk_index_to_ras(image: sitk.Image, ijk) -> np.ndarray:
    """RAS position of a (continuous) voxel index of an LPS SimpleITK image."""
    lps = np.array(image.TransformContinuousIndexToPhysicalPoint([float(v) for v in ijk]))
    return _FLIP_XY @ lps


# ---------------------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------------------

def _check_volume_node(volumeNode):
    if volumeNode is None:
        raise InputError("No CT volume selected. Select the CT volume of the bone.")
    if volumeNode.IsA("vtkMRMLLabelMapVolumeNode"):
        raise VolumeTypeError(
            f"'{volumeNode.GetName()}' is a label map volume, not a CT. Select the CT (HU) volume; "
            "put the rough bone mask into a segmentation (Segmentations module: import label map).")
    if volumeNode.IsA("vtkMRMLVectorVolumeNode") or not volumeNode.IsA("vtkMRMLScalarVolumeNode"):
        raise VolumeTypeError(
            f"'{volumeNode.GetName()}' is not a scalar volume (RGB/vector/tensor volumes cannot be used). "
            "Select a grey-value CT in HU.")
    image = volumeNode.GetImageData()
    if image is None or image.GetPointData() is None or image.GetPointData().GetScalars() is None:
        raise InputError(f"Volume '{volumeNode.GetName()}' has no voxel data.")
    if image.GetNumberOfScalarComponents() != 1:
        raise VolumeTypeError(
            f"Volume '{volumeNode.GetName()}' has {image.GetNumberOfScalarComponents()} components per "
            "voxel (RGB/4-D data). Select a single-component CT volume.")
    dims = image.GetDimensions()
    if min(dims) < 2:
        raise VolumeTypeError(
            f"Volume '{volumeNode.GetName()}' is 2-D ({dims[0]}x{dims[1]}x{dims[2]} voxels); "
            "a 3-D CT with at least 2 slices in every direction is needed.")
    return image


def volume_to_sitk(volumeNode) -> sitk.Image:
    """The CT volume node as a SimpleITK image in LPS world coordinates (voxels copied).

    The parent transform is applied: linear transforms exactly through the geometry, a
    non-linear one by resampling a copy into world space.
    """
    image = _check_volume_node(volumeNode)
    ijk_to_world = _ijk_to_world(volumeNode)
    if ijk_to_world is None:
        image = _hardened_oriented_image(volumeNode)
        ijk_to_world = _oriented_image_matrix(image)
    extent = image.GetExtent()
    return _sitk_from_array(_array_from_image_data(image), ijk_to_world, extent[0::2])


def _reference_geometry(volumeNode):
    """Geometry-only vtkOrientedImageData of the CT grid in world RAS."""
    image = _check_volume_node(volumeNode)
    ijk_to_world = _ijk_to_world(volumeNode)
    if ijk_to_world is None:
        image = _hardened_oriented_image(volumeNode)
        ijk_to_world = _oriented_image_matrix(image)
    ref = slicer.vtkOrientedImageData()
    ref.SetExtent(image.GetExtent())
    ref.SetImageToWorldMatrix(_np_to_vtk_matrix(ijk_to_world))
    return ref


def _binary_labelmap_name() -> str:
    return slicer.vtkSegmentationConverter.GetBinaryLabelmapRepresentationName()


def _segment_labelmap_world(segmentationNode, segmentId: str, reference):
    """(oriented labelmap in world RAS, label value of the segment in it)."""
    segmentation = segmentationNode.GetSegmentation()
    binary = _binary_labelmap_name()
    segment = segmentation.GetSegment(segmentId)
    if segmentation.ContainsRepresentation(binary):
        labelmap = slicer.vtkOrientedImageData()
        ok = slicer.vtkSlicerSegmentationsModuleLogic.GetSegmentBinaryLabelmapRepresentation(
            segmentationNode, segmentId, labelmap, True)
        if not ok:
            raise InputError(f"Could not read the label map of segment '{segment.GetName()}'.")
        return labelmap, segment.GetLabelValue()

    # Source is a closed surface (or another representation) without a labelmap. Convert a
    # private copy of the segment directly on the CT grid, so the user's segmentation keeps
    # its representations and conversion parameters untouched.
    seg_to_world = _to_world_matrix(segmentationNode)
    if seg_to_world is None:
        raise InputError(f"Segmentation '{segmentationNode.GetName()}' is under a non-linear transform; "
                         "harden the transform first.")
    local_ref = slicer.vtkOrientedImageData()
    local_ref.SetExtent(reference.GetExtent())
    local_ref.SetImageToWorldMatrix(_np_to_vtk_matrix(
        np.linalg.inv(seg_to_world) @ _oriented_image_matrix(reference)))
    private = slicer.vtkSegmentation()
    private.SetSourceRepresentationName(segmentation.GetSourceRepresentationName())
    private.CopyConversionParameters(segmentation)
    private.SetConversionParameter(
        slicer.vtkSegmentationConverter.GetReferenceImageGeometryParameterName(),
        slicer.vtkSegmentationConverter.SerializeImageGeometry(local_ref))
    if not private.CopySegmentFromSegmentation(segmentation, segmentId) or not private.CreateRepresentation(binary):
        raise InputError(f"Segment '{segment.GetName()}' could not be converted to a label map.")
    local = private.GetSegment(segmentId).GetRepresentation(binary)
    labelmap = slicer.vtkOrientedImageData()
    labelmap.DeepCopy(local)
    labelmap.SetImageToWorldMatrix(_np_to_vtk_matrix(seg_to_world @ _oriented_image_matrix(local)))
    return labelmap, private.GetSegment(segmentId).GetLabelValue()


def _check_segment(segmentationNode, segmentId):
    if segmentationNode is None:
        raise InputError("No segmentation selected. Select the segmentation holding the rough bone segment.")
    if not segmentId:
        raise InputError("No segment selected. Select the segment of the bone to reconstruct.")
    segment = segmentationNode.GetSegmentation().GetSegment(segmentId)
    if segment is None:
        raise InputError(f"Segment '{segmentId}' does not exist in segmentation "
                         f"'{segmentationNode.GetName()}'. Select an existing segment.")
    return segment


def segment_to_sitk_mask(segmentationNode, segmentId: str, referenceVolumeNode) -> sitk.Image:
    """The segment as a uint8 0/1 mask on the CT grid (same geometry as volume_to_sitk).

    Works whatever the segmentation's own geometry (cropped extent, oversampled, other
    origin/direction, shared labelmap, closed-surface source, linear parent transforms).
    """
    segment = _check_segment(segmentationNode, segmentId)
    reference = _reference_geometry(referenceVolumeNode)
    labelmap, label = _segment_labelmap_world(segmentationNode, segmentId, reference)
    scalars = labelmap.GetPointData().GetScalars()
    if scalars is None or not np.any(ns.vtk_to_numpy(scalars) == label):
        raise EmptySegmentError(f"Segment '{segment.GetName()}' is empty. Paint at least a rough "
                                "outline of the bone into it (Segment Editor), then apply again.")
    resampled = slicer.vtkOrientedImageData()
    ok = slicer.vtkOrientedImageDataResample.ResampleOrientedImageToReferenceOrientedImage(
        labelmap, reference, resampled, False, False, None, 0)
    if not ok or resampled.GetPointData().GetScalars() is None:
        raise NoOverlapError(f"Segment '{segment.GetName()}' and volume '{referenceVolumeNode.GetName()}' "
                             "do not overlap. Select the CT the segment was drawn on.")
    mask = (_array_from_image_data(resampled) == label).astype(np.uint8)
    if not mask.any():
        raise NoOverlapError(f"Segment '{segment.GetName()}' does not overlap volume "
                             f"'{referenceVolumeNode.GetName()}'. Select the CT the segment was drawn on "
                             "(or check the transforms of both nodes).")
    ijk_to_world = _oriented_image_matrix(reference)
    return _sitk_from_array(mask, ijk_to_world, reference.GetExtent()[0::2])


# ---------------------------------------------------------------------------------------
# outputs
# ---------------------------------------------------------------------------------------

def surface_to_polydata_ras(surface: Surface):
    """vtkPolyData in RAS with point normals and the surface's point-data arrays."""
    return to_polydata(surface.to_ras(), normals=True)


def _into_node_frame(node, poly):
    """World-RAS polydata expressed in the node's local frame (inverse of its parent transform)."""
    tn = node.GetParentTransformNode()
    if tn is None:
        return poly
    from_world = vtk.vtkGeneralTransform()
    tn.GetTransformFromWorld(from_world)
    f = vtk.vtkTransformPolyDataFilter()
    f.SetInputData(poly)
    f.SetTransform(from_world)
    f.Update()
    out = vtk.vtkPolyData()
    out.DeepCopy(f.GetOutput())
    return out


def update_model_node(modelNode, surface: Surface, colorByDistance: bool = False):
    """Put the surface into the model node (RAS, normals, point data); add a display node if missing."""
    poly = _into_node_frame(modelNode, surface_to_polydata_ras(surface))
    modelNode.SetAndObservePolyData(poly)
    if modelNode.GetDisplayNode() is None:
        modelNode.CreateDefaultDisplayNodes()
    display = modelNode.GetDisplayNode()
    if display is None:
        return modelNode
    distances = surface.point_data.get(DISTANCE_ARRAY)
    if colorByDistance and distances is not None and len(distances):
        display.SetActiveScalar(DISTANCE_ARRAY, vtk.vtkAssignAttribute.POINT_DATA)
        scene = modelNode.GetScene()
        # A diverging-free, perceptually ordered table if the scene has the default colours.
        for colorId in ("vtkMRMLColorTableNodeFileViridis.txt", "vtkMRMLColorTableNodeRainbow"):
            if scene is not None and scene.GetNodeByID(colorId) is not None:
                display.SetAndObserveColorNodeID(colorId)
                break
        display.SetScalarRangeFlag(display.UseManualScalarRange)
        display.SetScalarRange(0.0, float(max(np.max(distances), 1e-6)))
        display.SetScalarVisibility(True)
    else:
        display.SetScalarVisibility(False)
    return modelNode


def add_surface_as_segment(segmentationNode, surface: Surface, name: str) -> str:
    """Add the surface to the segmentation as a new segment; returns the new segment ID.

    The segment is given as a closed surface; the segmentation converts it to its own source
    representation with its own conversion parameters (which are not changed).
    """
    poly = _into_node_frame(segmentationNode, surface_to_polydata_ras(surface))
    segment = slicer.vtkSegment()
    segment.SetName(name)
    segment.AddRepresentation(slicer.vtkSegmentationConverter.GetClosedSurfaceRepresentationName(), poly)
    segmentation = segmentationNode.GetSegmentation()
    segmentId = segmentation.GenerateUniqueSegmentID(name)
    if not segmentation.AddSegment(segment, segmentId):
        raise InputError(f"Could not add the surface as segment '{name}' to '{segmentationNode.GetName()}'.")
    return segmentId


def _points_to_polydata_ras(points_lps: np.ndarray):
    pts = np.ascontiguousarray(np.asarray(points_lps, dtype=np.float64).reshape(-1, 3) @ _FLIP_XY)
    vpts = vtk.vtkPoints()
    vpts.SetData(ns.numpy_to_vtk(pts, deep=True))
    verts = vtk.vtkCellArray()
    ids = np.arange(len(pts), dtype=np.int64)
    conn = np.column_stack([np.ones_like(ids), ids]).ravel()
    verts.SetCells(len(pts), ns.numpy_to_vtkIdTypeArray(conn, deep=True))
    poly = vtk.vtkPolyData()
    poly.SetPoints(vpts)
    poly.SetVerts(verts)
    return poly


def add_intermediate_nodes(scene, intermediates: dict, prefix: str = "BoneWatertight") -> list:
    """One model node per intermediate result (point sets as vertex clouds, surfaces as meshes)."""
    nodes = []
    for name, value in intermediates.items():
        if isinstance(value, Surface):
            poly = surface_to_polydata_ras(value)
        else:
            arr = np.asarray(value)
            if arr.ndim != 2 or arr.shape[1] != 3:
                continue
            poly = _points_to_polydata_ras(arr)
        node = scene.AddNewNodeByClass("vtkMRMLModelNode", scene.GenerateUniqueName(f"{prefix} {name}"))
        node.SetAndObservePolyData(poly)
        node.CreateDefaultDisplayNodes()
        if node.GetDisplayNode() is not None and not isinstance(value, Surface):
            node.GetDisplayNode().SetPointSize(3.0)
            node.GetDisplayNode().SetRepresentation(0)  # points
        nodes.append(node)
    return nodes


# ---------------------------------------------------------------------------------------
# the one call
# ---------------------------------------------------------------------------------------

def _as_parameters(params) -> Parameters:
    if params is None:
        return Parameters()
    if isinstance(params, Parameters):
        return params
    if isinstance(params, dict):
        return Parameters().replace(**params)
    raise InputError(f"params must be a Parameters object or a dict, got {type(params).__name__}.")


def summarize(result, name: str = "") -> str:
    """The one summary line of a ReconstructionResult (panel result line, logs): vertices,
    faces, checks, distance to the constraint points and the pipeline's total time."""
    report = result.report
    return summary_line(name, report.checks, report.distance_to_constraints_mm,
                        report.timings.total, result.surface.n_vertices,
                        result.surface.n_faces)


def run_on_nodes(volumeNode, segmentationNode, segmentId, outputModelNode=None, params=None,
                 progress=None, scene=None, *, addAsSegment: bool = False,
                 showIntermediates: bool = False, colorByDistance: bool = False,
                 modelName: Optional[str] = None):
    """Reconstruct the watertight surface of one bone from MRML nodes.

    Returns ``(modelNode, result)``. The scene is only modified after the pipeline succeeded;
    any error (bad input, reconstruction failure, cancel) propagates with the scene unchanged.
    """
    parameters = _as_parameters(params)
    if showIntermediates and not parameters.keep_intermediates:
        parameters = parameters.replace(keep_intermediates=True)
    parameters.validate()
    if scene is None:
        scene = (volumeNode.GetScene() if volumeNode is not None else None) or (
            segmentationNode.GetScene() if segmentationNode is not None else None)
    if scene is None:
        raise InputError("The input nodes are not in a scene.")
    if outputModelNode is not None and not outputModelNode.IsA("vtkMRMLModelNode"):
        raise InputError("The output node must be a model node.")

    ct = volume_to_sitk(volumeNode)
    mask = segment_to_sitk_mask(segmentationNode, segmentId, volumeNode)
    from . import pipeline  # late: input errors are reported even where the pipeline's deps are missing

    result = pipeline.reconstruct(ct, mask, parameters, progress)

    # --- success: only now touch the scene
    if outputModelNode is None:
        segName = segmentationNode.GetSegmentation().GetSegment(segmentId).GetName()
        name = modelName or scene.GenerateUniqueName(f"{segName} watertight")
        outputModelNode = scene.AddNewNodeByClass("vtkMRMLModelNode", name)
    surface = result.surface
    if DISTANCE_ARRAY not in surface.point_data and result.distance_to_constraints is not None:
        d = np.asarray(result.distance_to_constraints, dtype=np.float64)
        if d.shape == (surface.n_vertices,):
            surface = surface.copy()
            surface.point_data[DISTANCE_ARRAY] = d
    update_model_node(outputModelNode, surface, colorByDistance=colorByDistance)
    outputModelNode.SetAttribute(REPORT_ATTRIBUTE, to_json(result.report))
    if addAsSegment:
        segName = segmentationNode.GetSegmentation().GetSegment(segmentId).GetName()
        add_surface_as_segment(segmentationNode, surface, f"{segName} watertight")
    if showIntermediates and getattr(result, "intermediates", None):
        add_intermediate_nodes(scene, result.intermediates)
    return outputModelNode, result


def propose_thresholds(volumeNode, segmentationNode, segmentId: str, theta_max: float = 2500.0) -> dict:
    """H0/HT proposal from the HU histogram in and around the segment (see autothreshold)."""
    from .stages.autothreshold import propose_thresholds as _propose

    ct = volume_to_sitk(volumeNode)
    mask = segment_to_sitk_mask(segmentationNode, segmentId, volumeNode)
    return _propose(ct, mask, theta_max=theta_max)


def threshold_preview_labelmap(volumeNode, segmentationNode, segmentId: str, h0: float, ht: float,
                               theta_max: float, labelmapNode=None, margin_mm: float = 5.0):
    """Fill a label map node (CT grid) with the two threshold windows for a live preview.

    Label 1 = [HT, H0) (reached only by the target threshold), 2 = [H0, theta_max]; restricted to
    the segment's bounding box plus a margin so neighbouring bones far away stay unlabelled.
    The label map node is created (hidden from editors) if not given; the caller removes it.
    """
    image = _check_volume_node(volumeNode)
    scene = volumeNode.GetScene()
    values = _array_from_image_data(image)
    window = np.zeros(values.shape, dtype=np.uint8)
    sel = values >= ht
    window[sel & (values < h0)] = 1
    window[(values >= h0) & (values <= theta_max)] = 2
    if segmentationNode is not None and segmentId:
        mask = sitk.GetArrayFromImage(segment_to_sitk_mask(segmentationNode, segmentId, volumeNode)) > 0
        nz = np.nonzero(mask)
        m = vtk.vtkMatrix4x4()
        volumeNode.GetIJKToRASMatrix(m)
        spacing = np.linalg.norm(_vtk_to_np_matrix(m)[:3, :3], axis=0)[::-1]  # (k, j, i)
        keep = np.zeros_like(window, dtype=bool)
        sl = tuple(slice(max(0, int(a.min() - margin_mm / s)), int(a.max() + margin_mm / s) + 1)
                   for a, s in zip(nz, spacing))
        keep[sl] = True
        window[~keep] = 0
    if labelmapNode is None:
        labelmapNode = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode",
                                               scene.GenerateUniqueName("BoneWatertight preview"))
        labelmapNode.SetHideFromEditors(True)
        labelmapNode.SetSaveWithScene(False)
        # slice views draw no volume that lacks a display node (AddNewNodeByClass creates none)
        labelmapNode.CreateDefaultDisplayNodes()
        if labelmapNode.GetDisplayNode() is not None:
            labelmapNode.GetDisplayNode().SetSaveWithScene(False)
    m = vtk.vtkMatrix4x4()
    volumeNode.GetIJKToRASMatrix(m)
    labelmapNode.SetIJKToRASMatrix(m)
    labelmapNode.SetAndObserveTransformNodeID(volumeNode.GetTransformNodeID())
    img = vtk.vtkImageData()
    img.SetExtent(image.GetExtent())
    vtk_arr = ns.numpy_to_vtk(window.ravel(), deep=True, array_type=vtk.VTK_UNSIGNED_CHAR)
    img.GetPointData().SetScalars(vtk_arr)
    labelmapNode.SetAndObserveImageData(img)
    return labelmapNode
