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

Besides the conversions: a run that reports progress from its first moment and is cancelled
when its scene closes (:func:`run_on_nodes`, :class:`RunGuard`, :class:`RunProgress`,
:func:`load_pipeline`), and the panel's live threshold preview on a cached crop
(:class:`ThresholdPreview`). The only thread used imports modules (open3d); MRML is touched
on the caller's thread alone.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from typing import Optional

import numpy as np
import SimpleITK as sitk
import vtk
from vtk.util import numpy_support as ns

import slicer

from .errors import (
    CancelledError,
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
    """Voxel copy of the volume resampled into world space (used for non-linear transforms).

    CreateOrientedImageDataFromVolumeNode hands its caller the reference that New() made
    (the C++ caller must Take() it) and its declaration does not say so to VTK's Python
    wrapping, which adds a reference of its own: without the UnRegister below every call
    leaked a full copy of the volume. Afterwards the Python object holds the only reference.
    """
    image = slicer.vtkSlicerSegmentationsModuleLogic.CreateOrientedImageDataFromVolumeNode(volumeNode, None)
    if image is None:
        raise InputError(f"Could not apply the transform of volume '{volumeNode.GetName()}'; "
                         "harden the transform (Data module) and try again.")
    image.UnRegister(None)
    return image


def _oriented_image_matrix(image) -> np.ndarray:
    m = vtk.vtkMatrix4x4()
    image.GetImageToWorldMatrix(m)
    return _vtk_to_np_matrix(m)


def _array_view(image) -> np.ndarray:
    """(k, j, i) numpy *view* of the scalars. Never written through for an input node's
    image: what leaves this module is copied (sitk.GetImageFromArray copies)."""
    dims = image.GetDimensions()
    return ns.vtk_to_numpy(image.GetPointData().GetScalars()).reshape(dims[2], dims[1], dims[0])


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
    # GetImageFromArray copies the buffer: one copy of the voxels, not two
    return _sitk_from_array(_array_view(image), ijk_to_world, extent[0::2])


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
    ijk_to_world = _oriented_image_matrix(reference)
    ref_extent = reference.GetExtent()
    box = _segment_box_on_grid(labelmap, label, ijk_to_world, ref_extent)
    if box is None:
        raise EmptySegmentError(f"Segment '{segment.GetName()}' is empty. Paint at least a rough "
                                "outline of the bone into it (Segment Editor), then apply again.")
    no_overlap = NoOverlapError(f"Segment '{segment.GetName()}' does not overlap volume "
                                f"'{referenceVolumeNode.GetName()}'. Select the CT the segment was drawn "
                                "on (or check the transforms of both nodes).")
    if box is False:
        raise no_overlap
    # Resample only onto the part of the CT grid that the segment can reach (a full-grid
    # nearest-neighbour resample of a 512x512x500 CT took ~1.5 s); the rest stays 0.
    crop = slicer.vtkOrientedImageData()
    crop.SetExtent(box)
    crop.SetImageToWorldMatrix(_np_to_vtk_matrix(ijk_to_world))
    resampled = slicer.vtkOrientedImageData()
    ok = slicer.vtkOrientedImageDataResample.ResampleOrientedImageToReferenceOrientedImage(
        labelmap, crop, resampled, False, False, None, 0)
    if not ok or resampled.GetPointData().GetScalars() is None:
        raise no_overlap
    dims = [ref_extent[2 * a + 1] - ref_extent[2 * a] + 1 for a in range(3)]
    mask = np.zeros((dims[2], dims[1], dims[0]), dtype=np.uint8)
    e = resampled.GetExtent()
    mask[e[4] - ref_extent[4]:e[5] - ref_extent[4] + 1,
         e[2] - ref_extent[2]:e[3] - ref_extent[2] + 1,
         e[0] - ref_extent[0]:e[1] - ref_extent[0] + 1] = _array_view(resampled) == label
    if not mask.any():
        raise no_overlap
    return _sitk_from_array(mask, ijk_to_world, ref_extent[0::2])


def _label_index_box(labelmap, label):
    """(i0, i1, j0, j1, k0, k1) IJK index range of the voxels == label, or None if there are none."""
    scalars = labelmap.GetPointData().GetScalars() if labelmap.GetPointData() is not None else None
    if scalars is None:
        return None
    inside = _array_view(labelmap) == label
    box = []
    for axis in (2, 1, 0):  # i, j, k: the numpy axes are (k, j, i)
        others = tuple(a for a in range(3) if a != axis)
        hit = np.flatnonzero(inside.any(axis=others))
        if hit.size == 0:
            return None
        box += [int(hit[0]), int(hit[-1])]
    extent = labelmap.GetExtent()
    return [box[n] + extent[2 * (n // 2)] for n in range(6)]


def _segment_box_on_grid(labelmap, label, grid_to_world: np.ndarray, grid_extent, pad: int = 1,
                         margin_voxels=(0, 0, 0)):
    """Extent on a grid (IJK -> world matrix, extent) that holds every voxel of the segment.

    The segment's voxel box is mapped through both matrices (any rotation or spacing), grown
    by ``pad`` + ``margin_voxels`` (i, j, k) and clipped to ``grid_extent``. Returns None for
    an empty segment and False when the box misses the grid.
    """
    box = _label_index_box(labelmap, label)
    if box is None:
        return None
    corners = np.array([[i, j, k, 1.0] for i in (box[0] - 0.5, box[1] + 0.5)
                        for j in (box[2] - 0.5, box[3] + 0.5) for k in (box[4] - 0.5, box[5] + 0.5)])
    on_grid = (np.linalg.inv(grid_to_world) @ _oriented_image_matrix(labelmap) @ corners.T).T[:, :3]
    lo = np.floor(on_grid.min(axis=0)).astype(int) - pad - np.asarray(margin_voxels, int)
    hi = np.ceil(on_grid.max(axis=0)).astype(int) + pad + np.asarray(margin_voxels, int)
    out = []
    for a in range(3):
        a0, a1 = max(lo[a], grid_extent[2 * a]), min(hi[a], grid_extent[2 * a + 1])
        if a0 > a1:
            return False
        out += [int(a0), int(a1)]
    return out


def volume_node_from_sitk(scene, image: sitk.Image, name: str = "CT",
                          className: str = "vtkMRMLScalarVolumeNode"):
    """A new volume node (RAS) holding a copy of a SimpleITK image (LPS): the inverse of
    :func:`volume_to_sitk` (phantoms, tests and scripts that start from files)."""
    if image.GetDimension() != 3 or image.GetNumberOfComponentsPerPixel() != 1:
        raise VolumeTypeError("Only single-component 3-D images can become volume nodes.")
    lin = _FLIP_XY @ np.array(image.GetDirection(), float).reshape(3, 3) @ np.diag(image.GetSpacing())
    ijk_to_ras = np.eye(4)
    ijk_to_ras[:3, :3] = lin
    ijk_to_ras[:3, 3] = _FLIP_XY @ np.array(image.GetOrigin(), float)
    arr = sitk.GetArrayFromImage(image)
    data = vtk.vtkImageData()
    data.SetDimensions(arr.shape[2], arr.shape[1], arr.shape[0])
    data.GetPointData().SetScalars(ns.numpy_to_vtk(np.ascontiguousarray(arr).ravel(), deep=True))
    node = scene.AddNewNodeByClass(className, name)
    node.SetAndObserveImageData(data)
    node.SetIJKToRASMatrix(_np_to_vtk_matrix(ijk_to_ras))
    return node


def segmentation_node_from_mask(scene, mask: sitk.Image, name: str = "Segmentation",
                                segmentName: str = "bone"):
    """A new segmentation node with one segment (mask != 0) on the mask's own grid; returns
    ``(segmentationNode, segmentId)``. The scene's segmentations logic must be set up first
    (it registers the converter rules)."""
    binary = sitk.Cast(sitk.NotEqual(mask, 0), sitk.sitkUInt8)
    labelmap = volume_node_from_sitk(scene, binary, "BoneWatertight import", "vtkMRMLLabelMapVolumeNode")
    segmentation = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", name)
    try:
        if not slicer.vtkSlicerSegmentationsModuleLogic.ImportLabelmapToSegmentationNode(labelmap, segmentation):
            raise InputError("The mask could not be imported into a segmentation.")
    finally:
        scene.RemoveNode(labelmap)
    segmentId = segmentation.GetSegmentation().GetNthSegmentID(0)
    if segmentId is None:
        scene.RemoveNode(segmentation)
        raise EmptySegmentError("The mask is empty: nothing to import.")
    segmentation.GetSegmentation().GetSegment(segmentId).SetName(segmentName)
    return segmentation, segmentId


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


def read_model_file(path: str, modelNode=None):
    """Read a surface file the way 3D Slicer loads it (vtkMRMLModelStorageNode: the SPACE tag
    of the file decides LPS or RAS; none means LPS). Returns the model node (RAS); a new node
    outside any scene unless ``modelNode`` is given."""
    storage = slicer.vtkMRMLModelStorageNode()
    storage.SetFileName(str(path))
    if modelNode is None:
        modelNode = slicer.vtkMRMLModelNode()
    if not storage.ReadData(modelNode) or modelNode.GetPolyData() is None:
        raise InputError(f"3D Slicer's model reader could not read {path}.")
    return modelNode


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
# a responsive run: progress from the first second, cancel, scene-close guard
# ---------------------------------------------------------------------------------------

# Overall progress fraction where each step of the adapter's own first phase starts; the
# pipeline's [0, 1] is mapped onto [PIPELINE_START, 1].
EXPORT_VOLUME_START = 0.0
EXPORT_SEGMENT_START = 0.01
IMPORT_START = 0.02
PIPELINE_START = 0.04
# While open3d (and the pipeline's modules) are imported in a helper thread, the progress
# callback is called at least this often (s): the panel keeps painting, Cancel is honoured.
IMPORT_TICK_S = 0.1
# The import's progress approaches its end with this time constant (s) (its length is unknown).
IMPORT_TIME_CONSTANT_S = 3.0


class RunGuard:
    """Cancels a run whose scene closes or whose nodes leave the scene (SPEC 5: never write
    into a closed scene or a removed node).

    Observes the scene's StartCloseEvent and NodeRemovedEvent while the run lasts; the run's
    progress calls :meth:`check`, and the adapter checks once more before it touches the
    scene. Use as a context manager (observers are removed on exit).
    """

    def __init__(self, scene, nodes=()):
        self.scene = scene
        self.nodes = [n for n in nodes if n is not None]
        self.reason: Optional[str] = None
        self._tags = []
        if scene is not None:
            self._tags = [scene.AddObserver(slicer.vtkMRMLScene.StartCloseEvent, self._onClose),
                          scene.AddObserver(slicer.vtkMRMLScene.NodeRemovedEvent, self._onNodeRemoved)]

    def _onClose(self, caller=None, event=None):
        if self.reason is None:
            self.reason = "The scene was closed during the run"

    def _onNodeRemoved(self, caller=None, event=None):
        if self.reason is not None:
            return
        for node in self.nodes:
            if not self.scene.IsNodePresent(node):
                self.reason = f"'{node.GetName()}' was removed from the scene during the run"
                return

    def check(self) -> None:
        """CancelledError if the scene closed or a node of the run was removed."""
        if self.reason is not None:
            raise CancelledError(f"{self.reason}; nothing was written.")

    def close(self) -> None:
        for tag in self._tags:
            self.scene.RemoveObserver(tag)
        self._tags = []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class RunProgress:
    """The progress callback of one MRML run: the adapter's first phase (export, imports),
    then the pipeline's, on one [0, 1] scale; checks the :class:`RunGuard` at every call.

    ``callback(fraction, message)`` returning False cancels (CancelledError), as in the library.
    """

    def __init__(self, callback=None, guard: Optional[RunGuard] = None,
                 pipeline_start: float = PIPELINE_START):
        self.callback = callback
        self.guard = guard
        self.pipeline_start = pipeline_start

    def __call__(self, fraction: float, message: str = "") -> None:
        if self.guard is not None:
            self.guard.check()
        if self.callback is not None and self.callback(fraction, message) is False:
            raise CancelledError("Cancelled by the user; nothing was changed.")

    def pipeline(self):
        """The callback to hand to ``pipeline.reconstruct`` (its [0, 1] mapped onto ours)."""
        start = self.pipeline_start

        def report(fraction, message=""):
            if self.guard is not None:
                self.guard.check()
            if self.callback is None:
                return True
            return self.callback(start + (1.0 - start) * fraction, message)
        return report


def load_pipeline(progress: Optional[RunProgress] = None, start: float = IMPORT_START,
                  end: float = PIPELINE_START):
    """Import the pipeline and open3d (seconds on first use) while reporting progress.

    The import runs in a helper thread; this (the main) thread calls ``progress`` every
    IMPORT_TICK_S, so the panel keeps painting and Cancel is honoured. Only imports happen in
    the thread (no MRML, no Qt). Should the threaded import fail for another reason than a
    missing package, it is retried here. Returns the pipeline module; DependencyError when
    open3d is missing.
    """
    if progress is not None:
        progress(start, "Loading open3d")
    if "open3d" in sys.modules and f"{__package__}.pipeline" in sys.modules:
        return sys.modules[f"{__package__}.pipeline"]
    failure = []

    def work():
        try:
            from . import pipeline
            from .stages.poisson import import_open3d
            import_open3d()
            del pipeline
        except BaseException as exc:  # handed to the main thread
            failure.append(exc)

    # not a daemon: after a Cancel the import finishes in the background, and an interpreter
    # that exits meanwhile waits for it instead of tearing a half-loaded extension down
    thread = threading.Thread(target=work, name="BoneWatertight import", daemon=False)
    t0 = time.monotonic()
    thread.start()
    while thread.is_alive():
        thread.join(IMPORT_TICK_S)
        if thread.is_alive() and progress is not None:
            elapsed = time.monotonic() - t0
            progress(start + (end - start) * (1.0 - math.exp(-elapsed / IMPORT_TIME_CONSTANT_S)),
                     "Loading open3d")
    from .errors import DependencyError

    if failure and not isinstance(failure[0], (ImportError, DependencyError)):
        failure.clear()  # e.g. a library that insists on the main thread: import here instead
    if failure:
        raise failure[0]
    from . import pipeline
    from .stages.poisson import import_open3d
    import_open3d()
    return pipeline


def export_inputs(volumeNode, segmentationNode, segmentId, progress: Optional[RunProgress] = None):
    """(CT, mask) as SimpleITK images in LPS for one segment, reporting progress per step."""
    if progress is not None:
        progress(EXPORT_VOLUME_START, "Reading the CT volume")
    ct = volume_to_sitk(volumeNode)
    if progress is not None:
        progress(EXPORT_SEGMENT_START, "Reading the segment")
    mask = segment_to_sitk_mask(segmentationNode, segmentId, volumeNode)
    return ct, mask


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
    ``progress(fraction, message)`` is called from the first moment (CT and segment export,
    the open3d import) and throughout the pipeline; returning False cancels. Closing the
    scene, or removing an input or the output node, during the run cancels it
    (CancelledError) and nothing is written (:class:`RunGuard`).
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

    with RunGuard(scene, (volumeNode, segmentationNode, outputModelNode)) as guard:
        report = RunProgress(progress, guard)
        ct, mask = export_inputs(volumeNode, segmentationNode, segmentId, report)
        # late: input errors are reported even where the pipeline's deps are missing
        pipeline = load_pipeline(report)
        result = pipeline.reconstruct(ct, mask, parameters, report.pipeline())
        guard.check()  # the scene may have closed after the last progress report
        return _store_result(scene, result, segmentationNode, segmentId, outputModelNode,
                             addAsSegment=addAsSegment, showIntermediates=showIntermediates,
                             colorByDistance=colorByDistance, modelName=modelName)


def _store_result(scene, result, segmentationNode, segmentId, outputModelNode, *,
                  addAsSegment, showIntermediates, colorByDistance, modelName):
    """Success: only now touch the scene (model, report attribute, segment, intermediates)."""
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


# ---------------------------------------------------------------------------------------
# live threshold preview
# ---------------------------------------------------------------------------------------

# Labels of the preview label map and their colours (the panel's tooltip names them).
PREVIEW_TARGET_LABEL = 1   # [HT, H0): reached only by the target window
PREVIEW_INITIAL_LABEL = 2  # [H0, theta_max]: the initial window
PREVIEW_COLORS = {
    PREVIEW_TARGET_LABEL: ("green", "[HT, H0)", (0.20, 0.80, 0.20)),
    PREVIEW_INITIAL_LABEL: ("yellow", "[H0, theta max]", (1.00, 0.90, 0.10)),
}
PREVIEW_MARGIN_MM = 5.0


def _transform_key(node):
    """What the node's world frame depends on: its world matrix, or the MTimes of a
    non-linear parent chain."""
    world = _to_world_matrix(node)
    if world is not None:
        return tuple(np.round(world.ravel(), 9))
    key, tn = [], node.GetParentTransformNode()
    while tn is not None:
        key += [tn.GetID(), tn.GetMTime(), tn.GetTransformToParent().GetMTime()]
        tn = tn.GetParentTransformNode()
    return tuple(key)


def _preview_source_key(volumeNode, segmentationNode, segmentId):
    """Changes whenever the voxels, the geometry or the segment that the preview's cached
    crop was made from change (MTimes are cheap to read: microseconds)."""
    image = volumeNode.GetImageData()
    key = [volumeNode.GetID(), volumeNode.GetMTime(), image.GetMTime() if image is not None else None,
           _transform_key(volumeNode)]
    if segmentationNode is not None and segmentId:
        segmentation = segmentationNode.GetSegmentation()
        segment = segmentation.GetSegment(segmentId)
        source = (segment.GetRepresentation(segmentation.GetSourceRepresentationName())
                  if segment is not None else None)
        key += [segmentationNode.GetID(), segmentId, segmentationNode.GetMTime(),
                segmentation.GetMTime(), segment.GetMTime() if segment is not None else None,
                source.GetMTime() if source is not None else None, _transform_key(segmentationNode)]
    return tuple(key)


class ThresholdPreview:
    """Live preview of the two threshold windows as a label map in the slice views.

    The voxels of the CT around the segment (its box plus ``margin_mm``, on the CT's own grid)
    are copied once into a cache; each :meth:`update` only thresholds that crop in place into
    the label map's buffer (a few ms for a femur-sized box, see Testing/bench_slicer.py). The
    cache is rebuilt when the volume, its geometry or the segment change. Label
    PREVIEW_TARGET_LABEL = [HT, H0) is green, PREVIEW_INITIAL_LABEL = [H0, theta_max] yellow,
    from a colour table of its own. The label map, its display node and the colour table are
    hidden from editors and never saved with the scene; :meth:`remove` takes them out.
    """

    def __init__(self, scene, margin_mm: float = PREVIEW_MARGIN_MM, name: str = "BoneWatertight preview"):
        self.scene = scene
        self.margin_mm = float(margin_mm)
        self.name = name
        self.labelmapNode = None
        self.colorNode = None
        self.cacheBuilds = 0
        self._key = None
        self._values = None
        self._labels = None
        self._scratch = None

    # -- cache

    def invalidate(self) -> None:
        self._key = None
        self._values = self._labels = self._scratch = None

    def _crop_box(self, volumeNode, segmentationNode, segmentId, image):
        """IJK extent of the volume (its own grid) to preview: the segment's box + margin."""
        extent = list(image.GetExtent())
        if segmentationNode is None or not segmentId:
            return extent
        ijk_to_world = _ijk_to_world(volumeNode)
        if ijk_to_world is None:  # non-linear transform: the volume's IJK has no world box
            return extent
        _check_segment(segmentationNode, segmentId)
        reference = slicer.vtkOrientedImageData()
        reference.SetExtent(extent)
        reference.SetImageToWorldMatrix(_np_to_vtk_matrix(ijk_to_world))
        labelmap, label = _segment_labelmap_world(segmentationNode, segmentId, reference)
        spacing = np.linalg.norm(ijk_to_world[:3, :3], axis=0)
        margin = np.ceil(self.margin_mm / spacing).astype(int)
        box = _segment_box_on_grid(labelmap, label, ijk_to_world, extent, margin_voxels=margin)
        if box is None:
            raise EmptySegmentError("The segment is empty: nothing to preview.")
        if box is False:
            raise NoOverlapError("The segment does not overlap the volume: nothing to preview.")
        return box

    def _build(self, volumeNode, segmentationNode, segmentId, key) -> None:
        image = _check_volume_node(volumeNode)
        box = self._crop_box(volumeNode, segmentationNode, segmentId, image)
        full = image.GetExtent()
        view = _array_view(image)
        values = np.ascontiguousarray(view[box[4] - full[4]:box[5] - full[4] + 1,
                                           box[2] - full[2]:box[3] - full[2] + 1,
                                           box[0] - full[0]:box[1] - full[0] + 1])
        node = self._ensure_nodes()
        # the crop's own image (extent from 0) with the volume's matrix shifted to its corner
        m = vtk.vtkMatrix4x4()
        volumeNode.GetIJKToRASMatrix(m)
        ijk_to_ras = _vtk_to_np_matrix(m)
        ijk_to_ras[:3, 3] = (ijk_to_ras @ np.array([box[0], box[2], box[4], 1.0]))[:3]
        node.SetIJKToRASMatrix(_np_to_vtk_matrix(ijk_to_ras))
        node.SetAndObserveTransformNodeID(volumeNode.GetTransformNodeID())
        labels = vtk.vtkImageData()
        labels.SetDimensions(values.shape[2], values.shape[1], values.shape[0])
        labels.AllocateScalars(vtk.VTK_UNSIGNED_CHAR, 1)
        node.SetAndObserveImageData(labels)
        self._values = values
        self._labels = _array_view(labels)  # writes go straight into the node's buffer
        self._scratch = (np.empty(values.shape, bool), np.empty(values.shape, bool))
        self._key = key
        self.cacheBuilds += 1

    def _ensure_nodes(self):
        scene = self.scene
        if self.colorNode is None or self.colorNode.GetScene() is not scene:
            color = slicer.vtkMRMLColorTableNode()
            color.SetName(scene.GenerateUniqueName(f"{self.name} colours"))
            color.SetTypeToUser()
            color.SetNumberOfColors(1 + max(PREVIEW_COLORS))
            color.SetColor(0, "background", 0.0, 0.0, 0.0, 0.0)
            for label, (_colour, window, rgb) in PREVIEW_COLORS.items():
                color.SetColor(label, window, *rgb, 1.0)
            color.SetHideFromEditors(True)
            color.SetSaveWithScene(False)
            scene.AddNode(color)
            self.colorNode = color
        if self.labelmapNode is None or self.labelmapNode.GetScene() is not scene:
            node = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode", scene.GenerateUniqueName(self.name))
            node.SetHideFromEditors(True)
            node.SetSaveWithScene(False)
            self.labelmapNode = node
        display = self.labelmapNode.GetDisplayNode()
        if display is None:
            # slice views draw no volume that lacks a display node (AddNewNodeByClass creates
            # none); made here, not by CreateDefaultDisplayNodes, so it never refers to the
            # default label colours (label 1 blue, 2 peach)
            display = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeDisplayNode")
            display.SetHideFromEditors(True)
            display.SetSaveWithScene(False)
            self.labelmapNode.SetAndObserveDisplayNodeID(display.GetID())
        if display.GetColorNodeID() != self.colorNode.GetID():
            display.SetAndObserveColorNodeID(self.colorNode.GetID())
        return self.labelmapNode

    # -- the per-drag-step work

    def update(self, volumeNode, segmentationNode, segmentId: str, h0: float, ht: float,
               theta_max: float):
        """Show [HT, H0) and [H0, theta_max] around the segment; returns the label map node."""
        key = _preview_source_key(volumeNode, segmentationNode, segmentId)
        if key != self._key or self.labelmapNode is None or self.labelmapNode.GetScene() is not self.scene:
            self._build(volumeNode, segmentationNode, segmentId, key)
        v, labels = self._values, self._labels
        below_top, initial = self._scratch
        target = labels.view(bool)
        np.less_equal(v, theta_max, out=below_top)
        np.greater_equal(v, ht, out=target)
        np.logical_and(target, below_top, out=target)        # [HT, theta_max] -> 1
        np.greater_equal(v, h0, out=initial)
        np.logical_and(initial, below_top, out=initial)      # [H0, theta_max]
        np.add(labels, initial.view(np.uint8), out=labels)   # -> 2
        image = self.labelmapNode.GetImageData()
        image.GetPointData().GetScalars().Modified()
        image.Modified()
        return self.labelmapNode

    def remove(self) -> None:
        """Take the label map, its display node and the colour table out of the scene."""
        for node in (self.labelmapNode, self.colorNode):
            if node is None or node.GetScene() is None:
                continue
            display = node.GetDisplayNode() if node.IsA("vtkMRMLDisplayableNode") else None
            node.GetScene().RemoveNode(node)
            if display is not None and display.GetScene() is not None:
                display.GetScene().RemoveNode(display)  # RemoveNode leaves it orphaned
        self.labelmapNode = self.colorNode = None
        self.invalidate()

