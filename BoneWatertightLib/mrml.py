"""Adapter between MRML nodes (3D Slicer / slicer-core) and the pure library.

The only module of BoneWatertightLib that imports ``slicer``; it uses MRML/VTK classes only
(never qt, ctk, slicer.app or slicer.util), so it runs inside Slicer and, in CI, on the
``slicer-core`` wheel.

Coordinate conventions: MRML is RAS, SimpleITK images and the pipeline are LPS. The volume's
full IJK->RAS matrix (any direction, non-zero origin) and its parent transform (world frame)
are converted into the SimpleITK origin/spacing/direction; surfaces come back as RAS polydata.

Nothing here modifies an input node: voxels are copied, the segments are exported through
vtkOrientedImageData objects that never enter the scene, and the output model nodes (and the
segments written back) are only created or touched after the pipeline succeeded.

Several bones (SPEC §5b): :func:`run_many_on_nodes` exports the segments to reconstruct and
their neighbours (by default every other segment of the segmentation) into one label image
with a value per segment (:func:`segments_to_sitk_labels`; overlapping segments are refused,
named), reconstructs them together (``pipeline.reconstruct_many``) and, on success only, makes
one model per bone and, on request, writes the surfaces back as segments that share one label
map layer, so that no voxel belongs to two of them (:func:`prepare_segments_without_overlap`).
:func:`run_on_nodes` is the one-bone case (the other segments are its neighbours unless
``neighbours="none"``).

Besides the conversions: a run that reports progress from its first moment and is cancelled
when its scene closes (:func:`run_on_nodes`, :class:`RunGuard`, :class:`RunProgress`,
:func:`load_pipeline`), and the panel's live threshold preview on a cached crop
(:class:`ThresholdPreview`). The only thread used imports modules (open3d); MRML is touched
on the caller's thread alone.

The same joint run with the reconstruction in a child process, for a panel whose GUI thread
must stay free (issue 13): :func:`start_many_on_nodes` checks and exports on the caller's
thread and starts the child (:class:`BoneWatertightLib.app.child.ChildRun`, the project's
command line); the returned :class:`ChildNodesRun` is polled from a timer (never blocks) and
cancelled within a second, and the scene guard cancels it when the scene closes;
:func:`finish_many_on_nodes` stores the result with the same code as :func:`run_many_on_nodes`
(:func:`_store_many`).
"""

from __future__ import annotations

import math
import sys
import threading
import time
from dataclasses import dataclass, field
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


def _closed_surface_name() -> str:
    return slicer.vtkSegmentationConverter.GetClosedSurfaceRepresentationName()


def _labelmap_layers_world(segmentationNode, segmentIds, reference) -> list:
    """The label maps that hold ``segmentIds``, in world RAS: one ``(oriented labelmap, {segment
    ID: label value in it})`` per layer (segments sharing a labelmap are read once).

    A segmentation with a binary labelmap is read as it is (parent transform applied); one whose
    source is another representation (closed surface) is converted in a private copy directly
    on the CT grid, so the user's segmentation keeps its representations and conversion
    parameters untouched.
    """
    segmentation = segmentationNode.GetSegmentation()
    binary = _binary_labelmap_name()
    layers = {}
    if segmentation.ContainsRepresentation(binary):
        for segmentId in segmentIds:
            layers.setdefault(segmentation.GetLayerIndex(segmentId), []).append(segmentId)
        out = []
        for ids in layers.values():
            labelmap = slicer.vtkOrientedImageData()
            ok = slicer.vtkSlicerSegmentationsModuleLogic.GetSegmentBinaryLabelmapRepresentation(
                segmentationNode, ids[0], labelmap, True)
            if not ok:
                raise InputError(f"Could not read the label map of segment "
                                 f"'{segmentation.GetSegment(ids[0]).GetName()}'.")
            out.append((labelmap, {s: segmentation.GetSegment(s).GetLabelValue() for s in ids}))
        return out

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
    for segmentId in segmentIds:
        if not private.CopySegmentFromSegmentation(segmentation, segmentId):
            raise InputError(f"Segment '{segmentation.GetSegment(segmentId).GetName()}' could not be "
                             "read.")
    if not private.CreateRepresentation(binary):
        names = ", ".join(f"'{segmentation.GetSegment(s).GetName()}'" for s in segmentIds)
        raise InputError(f"Segment(s) {names} could not be converted to a label map.")
    for segmentId in segmentIds:
        layers.setdefault(private.GetLayerIndex(segmentId), []).append(segmentId)
    out = []
    for ids in layers.values():
        local = private.GetSegment(ids[0]).GetRepresentation(binary)
        labelmap = slicer.vtkOrientedImageData()
        labelmap.DeepCopy(local)
        labelmap.SetImageToWorldMatrix(_np_to_vtk_matrix(seg_to_world @ _oriented_image_matrix(local)))
        out.append((labelmap, {s: private.GetSegment(s).GetLabelValue() for s in ids}))
    return out


def _segment_labelmap_world(segmentationNode, segmentId: str, reference):
    """(oriented labelmap in world RAS, label value of the segment in it)."""
    (labelmap, values), = _labelmap_layers_world(segmentationNode, [segmentId], reference)
    return labelmap, values[segmentId]


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
    _check_segment(segmentationNode, segmentId)
    labels = segments_to_sitk_labels(segmentationNode, [segmentId], referenceVolumeNode)
    return sitk.Cast(sitk.NotEqual(labels.image, 0), sitk.sitkUInt8)


def _label_boxes(labelmap, labels) -> dict:
    """{label: [i0, i1, j0, j1, k0, k1]} IJK index range of the voxels == label in the label
    map (None for a label without voxels), all labels in one pass over the voxels."""
    from scipy import ndimage

    scalars = labelmap.GetPointData().GetScalars() if labelmap.GetPointData() is not None else None
    wanted = sorted({int(v) for v in labels})
    if scalars is None or not wanted or wanted[-1] <= 0:
        return {v: None for v in wanted}
    arr = _array_view(labelmap)
    if arr.dtype.kind not in "iu" or arr.dtype.itemsize > 4:
        arr = arr.astype(np.int32)
    found = ndimage.find_objects(arr, max_label=wanted[-1])
    extent = labelmap.GetExtent()
    boxes = {}
    for v in wanted:
        slices = found[v - 1] if v >= 1 else None
        if slices is None:
            boxes[v] = None
            continue
        k, j, i = slices
        boxes[v] = [i.start + extent[0], i.stop - 1 + extent[0], j.start + extent[2],
                    j.stop - 1 + extent[2], k.start + extent[4], k.stop - 1 + extent[4]]
    return boxes


def _label_index_box(labelmap, label):
    """(i0, i1, j0, j1, k0, k1) IJK index range of the voxels == label, or None if there are none."""
    return _label_boxes(labelmap, [label])[int(label)]


def _box_on_grid(box, labelmap, grid_to_world: np.ndarray, grid_extent, pad: int = 1,
                 margin_voxels=(0, 0, 0)):
    """Extent on a grid (IJK -> world matrix, extent) that holds the voxel box ``box`` of a
    label map (any rotation or spacing), grown by ``pad`` + ``margin_voxels`` (i, j, k) and
    clipped to ``grid_extent``. None for no box, False when the box misses the grid."""
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


def _segment_box_on_grid(labelmap, label, grid_to_world: np.ndarray, grid_extent, pad: int = 1,
                         margin_voxels=(0, 0, 0)):
    """Extent on a grid (IJK -> world matrix, extent) that holds every voxel of the segment.

    The segment's voxel box is mapped through both matrices (any rotation or spacing), grown
    by ``pad`` + ``margin_voxels`` (i, j, k) and clipped to ``grid_extent``. Returns None for
    an empty segment and False when the box misses the grid.
    """
    return _box_on_grid(_label_index_box(labelmap, label), labelmap, grid_to_world, grid_extent,
                        pad, margin_voxels)


def _union_box(boxes):
    boxes = [b for b in boxes if b]
    if not boxes:
        return None
    b = np.array(boxes)
    return [int(b[:, 0].min()), int(b[:, 1].max()), int(b[:, 2].min()), int(b[:, 3].max()),
            int(b[:, 4].min()), int(b[:, 5].max())]


def _boxes_meet(a, b, grow=(0, 0, 0)) -> bool:
    return all(a[2 * n] - grow[n] <= b[2 * n + 1] and b[2 * n] <= a[2 * n + 1] + grow[n]
               for n in range(3))


# ---------------------------------------------------------------------------------------
# several segments as one label map
# ---------------------------------------------------------------------------------------

# Neighbours farther than margin + segment_dilation + this from the bones to reconstruct are
# left out: the pipeline crops to the targets + margin + band, and the band is at most
# segment_dilation + 3 mm (segments beyond the crop cannot compete, and cannot block a run by
# overlapping each other far away).
NEIGHBOUR_REACH_SLACK_MM = 10.0


@dataclass
class SegmentLabels:
    """Segments of one segmentation as one label image on the CT grid.

    ``image``: uint8 (uint16, uint32 for more segments) SimpleITK image on the CT grid (LPS), 0 =
    background; ``values``: segment ID -> its label value (1, 2, ... in the order asked for);
    ``names``: label value -> segment name (made unique); ``skipped``: segment ID -> why it is not
    in the image (empty, outside the CT, beyond the neighbours' reach).
    """

    image: sitk.Image
    values: dict
    names: dict
    skipped: dict = field(default_factory=dict)

    def segmentId(self, value: int) -> str:
        return next(s for s, v in self.values.items() if v == value)


def _unique_names(segmentation, segmentIds) -> dict:
    names = [segmentation.GetSegment(s).GetName() or s for s in segmentIds]
    return {s: (n if names.count(n) == 1 else f"{n} ({s})") for s, n in zip(segmentIds, names)}


def _overlap_error(segmentationNode, overlaps: dict, names: dict, voxel_mm3: float) -> InputError:
    pairs = sorted(overlaps.items(), key=lambda item: -item[1])
    shown = "; ".join(f"'{names[a]}' and '{names[b]}' ({count} voxels, {count * voxel_mm3:.0f} mm³)"
                      for (a, b), count in pairs[:5])
    more = f" and {len(pairs) - 5} more pairs" if len(pairs) > 5 else ""
    return InputError(
        f"Segments of '{segmentationNode.GetName()}' overlap on the CT grid: {shown}{more}. A voxel can "
        "belong to one bone only. Remove the overlap (Segment Editor: Logical operators, or paint "
        "with 'Modify other segments: overwrite all'), or do not use the other segments as "
        "neighbours (panel: uncheck 'Other segments are neighbours'; logic: neighbours='none').")


def segments_to_sitk_labels(segmentationNode, segmentIds, referenceVolumeNode, *, required=None,
                            reach_mm: Optional[float] = None, progress=None) -> SegmentLabels:
    """Segments of a segmentation as one label image on the CT grid, a value per segment.

    :param segmentIds: segments to export, in the order their values are given (1, 2, ...).
    :param required: the segments that must be there (the bones to reconstruct; default all):
        empty -> EmptySegmentError, outside the CT -> NoOverlapError. Other segments that are
        empty or outside the CT are skipped (``skipped`` says why).
    :param reach_mm: when given, a segment that is not required and lies farther than this
        from the required ones is skipped as well.
    :param progress: ``progress(fraction in [0, 1], message)`` once per label map layer.
    :raises InputError: two segments overlap on the CT grid (the message names them).

    Each layer (segments sharing a label map) is resampled once, nearest neighbour, onto the
    part of the CT grid that its segments reach (any geometry, parent transforms applied).
    Nothing of the segmentation is modified.
    """
    segmentIds = list(segmentIds)
    required = list(segmentIds if required is None else required)
    for segmentId in segmentIds + required:
        _check_segment(segmentationNode, segmentId)
    if len(set(segmentIds)) != len(segmentIds):
        raise InputError("The same segment is asked for twice; give each segment once.")
    segmentation = segmentationNode.GetSegmentation()
    names = _unique_names(segmentation, segmentIds)
    reference = _reference_geometry(referenceVolumeNode)
    ijk_to_world = _oriented_image_matrix(reference)
    ref_extent = reference.GetExtent()
    layers = _labelmap_layers_world(segmentationNode, segmentIds, reference)

    # every segment's box on the CT grid (one pass over each layer's voxels)
    grid_box, skipped = {}, {}
    for labelmap, values in layers:
        boxes = _label_boxes(labelmap, values.values())
        for segmentId, label in values.items():
            grid_box[segmentId] = _box_on_grid(boxes[int(label)], labelmap, ijk_to_world, ref_extent)

    def missing(segmentId, box):
        name = names[segmentId]
        if box is None:
            return EmptySegmentError(f"Segment '{name}' is empty. Paint at least a rough outline of "
                                     "the bone into it (Segment Editor), then apply again.")
        return NoOverlapError(f"Segment '{name}' does not overlap volume "
                              f"'{referenceVolumeNode.GetName()}'. Select the CT the segment was "
                              "drawn on (or check the transforms of both nodes).")

    for segmentId in required:
        if not grid_box[segmentId]:
            raise missing(segmentId, grid_box[segmentId])
    for segmentId in segmentIds:
        if not grid_box[segmentId]:
            skipped[segmentId] = "empty" if grid_box[segmentId] is None else "outside the CT"
    if reach_mm is not None and required:
        spacing = np.linalg.norm(ijk_to_world[:3, :3], axis=0)
        grow = np.ceil(float(reach_mm) / spacing).astype(int)
        targets_box = _union_box(grid_box[s] for s in required)
        for segmentId in segmentIds:
            if segmentId not in required and segmentId not in skipped \
                    and not _boxes_meet(grid_box[segmentId], targets_box, grow):
                skipped[segmentId] = f"farther than {reach_mm:g} mm from the bones"

    kept = [s for s in segmentIds if s not in skipped]
    values = {s: n for n, s in enumerate(kept, 1)}
    dims = [ref_extent[2 * a + 1] - ref_extent[2 * a] + 1 for a in range(3)]
    # the smallest type: a full-grid image of a 512 x 512 x 500 CT is 131 MB in uint8
    dtype = np.uint8 if len(kept) < 2 ** 8 else np.uint16 if len(kept) < 2 ** 16 else np.uint32
    out = np.zeros((dims[2], dims[1], dims[0]), dtype=dtype)
    overlaps = {}
    for n, (labelmap, layer_values) in enumerate(layers):
        if progress is not None:
            progress(n / len(layers), "Reading the segments" if len(segmentIds) > 1 else "Reading the segment")
        mine = {s: int(v) for s, v in layer_values.items() if s in values}
        box = _union_box(grid_box[s] for s in mine)
        if box is None:
            continue
        crop = slicer.vtkOrientedImageData()
        crop.SetExtent(box)
        crop.SetImageToWorldMatrix(_np_to_vtk_matrix(ijk_to_world))
        resampled = slicer.vtkOrientedImageData()
        ok = slicer.vtkOrientedImageDataResample.ResampleOrientedImageToReferenceOrientedImage(
            labelmap, crop, resampled, False, False, None, 0)
        if not ok or resampled.GetPointData().GetScalars() is None:
            continue
        source = _array_view(resampled)
        lut = np.zeros(max(max(mine.values()), int(source.max(initial=0))) + 1, dtype=dtype)
        for segmentId, label in mine.items():
            if label > 0:
                lut[label] = values[segmentId]
        mapped = lut[np.clip(source, 0, len(lut) - 1).astype(np.intp)]
        e = resampled.GetExtent()
        region = out[e[4] - ref_extent[4]:e[5] - ref_extent[4] + 1,
                     e[2] - ref_extent[2]:e[3] - ref_extent[2] + 1,
                     e[0] - ref_extent[0]:e[1] - ref_extent[0] + 1]
        new = mapped != 0
        clash = new & (region != 0)
        if clash.any():
            pairs, counts = np.unique(np.stack([region[clash], mapped[clash]]), axis=1,
                                      return_counts=True)
            for (a, b), count in zip(pairs.T, counts):
                key = tuple(sorted((kept[int(a) - 1], kept[int(b) - 1]), key=segmentIds.index))
                overlaps[key] = overlaps.get(key, 0) + int(count)
            new &= ~clash
        region[new] = mapped[new]
    if overlaps:
        raise _overlap_error(segmentationNode, overlaps, names,
                             float(np.prod(np.linalg.norm(ijk_to_world[:3, :3], axis=0))))
    present = set(np.unique(out).tolist()) - {0}
    for segmentId in required:
        if values[segmentId] not in present:  # box on the grid, but no voxel centre inside
            raise missing(segmentId, False)
    for segmentId in kept:
        if values[segmentId] not in present:
            skipped[segmentId] = "outside the CT"
            del values[segmentId]
    image = _sitk_from_array(out, ijk_to_world, ref_extent[0::2])
    return SegmentLabels(image=image, values=values,
                         names={v: names[s] for s, v in values.items()}, skipped=skipped)


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


def segmentation_node_from_labels(scene, labels: sitk.Image, names: Optional[dict] = None,
                                  name: str = "Segmentation"):
    """A new segmentation node with one segment per non-zero label value of a label image (on
    its own grid; the segments share one label map, as Slicer imports a label map); returns
    ``(segmentationNode, {label value: segment ID})``. ``names``: label value -> segment name
    (default "Label <value>"). The scene's segmentations logic must be set up first."""
    values = [int(v) for v in np.unique(sitk.GetArrayViewFromImage(labels)) if v != 0]
    if not values:
        raise EmptySegmentError("The label map is empty: nothing to import.")
    labelmap = volume_node_from_sitk(scene, labels, "BoneWatertight import", "vtkMRMLLabelMapVolumeNode")
    segmentation = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", name)
    try:
        if not slicer.vtkSlicerSegmentationsModuleLogic.ImportLabelmapToSegmentationNode(labelmap, segmentation):
            raise InputError("The label map could not be imported into a segmentation.")
    finally:
        scene.RemoveNode(labelmap)
    s = segmentation.GetSegmentation()
    ids = {}
    for n in range(s.GetNumberOfSegments()):
        segmentId = s.GetNthSegmentID(n)
        value = int(s.GetSegment(segmentId).GetLabelValue())
        ids[value] = segmentId
        s.GetSegment(segmentId).SetName(str((names or {}).get(value, f"Label {value}")))
    return segmentation, ids


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


# Attributes of a model node made by a run: which segment it is the surface of, and (several
# bones) the joint report with the pair checks.
SOURCE_SEGMENT_ATTRIBUTE = "BoneWatertight.SourceSegment"
JOINT_REPORT_ATTRIBUTE = "BoneWatertight.JointReport"
# Tag of a segment written back by a run (value: the ID of the segment it was made from). Such a
# segment is a copy of its source, never one of the "other segments" that compete as neighbours.
SOURCE_SEGMENT_TAG = "BoneWatertight.SourceSegment"


@dataclass
class PreparedSegments:
    """Surfaces rasterised for writing back into a segmentation, without overlap.

    ``labelmap``: one vtkOrientedImageData in the segmentation's own frame with the value
    ``n`` for the n-th surface (one shared layer: no voxel can belong to two segments);
    ``polys``: the surfaces in the segmentation's frame (their closed-surface representation);
    ``resolvedVoxels``: voxels that the rasterisations of two surfaces both claimed (a joint
    narrower than a voxel), each given to the surface it lies deepest inside.
    """

    labelmap: object
    names: list
    polys: list
    resolvedVoxels: int = 0


def _check_write_back(segmentationNode):
    """(reference geometry string or "", segmentation -> world matrix); InputError when the
    surfaces could not be written back (checked before a run: it would fail at its end)."""
    geometry = segmentationNode.GetSegmentation().GetConversionParameter(
        slicer.vtkSegmentationConverter.GetReferenceImageGeometryParameterName())
    seg_to_world = _to_world_matrix(segmentationNode)
    if not geometry and seg_to_world is None:
        raise InputError(f"Segmentation '{segmentationNode.GetName()}' is under a non-linear transform "
                         "and has no reference geometry: harden its transform to write the surfaces "
                         "back as segments (or switch that option off).")
    return geometry, seg_to_world


def _write_back_geometry(segmentationNode, volumeNode) -> str:
    """Serialized geometry (segmentation frame) of the written-back label maps: the
    segmentation's reference geometry, else the CT grid."""
    geometry, seg_to_world = _check_write_back(segmentationNode)
    if geometry:
        return geometry
    reference = _reference_geometry(volumeNode)
    local = slicer.vtkOrientedImageData()
    local.SetExtent(reference.GetExtent())
    local.SetImageToWorldMatrix(_np_to_vtk_matrix(np.linalg.inv(seg_to_world) @ _oriented_image_matrix(reference)))
    return slicer.vtkSegmentationConverter.SerializeImageGeometry(local)


def _mask_on_grid(labelmap, label, grid_to_local: np.ndarray):
    """(bool (k, j, i) array, extent) of ``labelmap == label`` on a grid with the given
    IJK -> frame matrix (the label map's own voxels when it is that grid)."""
    box = _label_index_box(labelmap, label)
    if box is None:
        return None, None
    if np.allclose(_oriented_image_matrix(labelmap), grid_to_local, atol=1e-6):
        e = labelmap.GetExtent()
        arr = _array_view(labelmap)[box[4] - e[4]:box[5] - e[4] + 1, box[2] - e[2]:box[3] - e[2] + 1,
                                    box[0] - e[0]:box[1] - e[0] + 1]
        return arr == label, box
    big = 2 ** 30
    extent = _box_on_grid(box, labelmap, grid_to_local, [-big, big] * 3)
    ref = slicer.vtkOrientedImageData()
    ref.SetExtent(extent)
    ref.SetImageToWorldMatrix(_np_to_vtk_matrix(grid_to_local))
    out = slicer.vtkOrientedImageData()
    slicer.vtkOrientedImageDataResample.ResampleOrientedImageToReferenceOrientedImage(
        labelmap, ref, out, False, False, None, 0)
    return _array_view(out) == label, list(out.GetExtent())


def prepare_segments_without_overlap(segmentationNode, volumeNode, named_surfaces) -> PreparedSegments:
    """Rasterise surfaces (``[(name, Surface)]``, world) for the segmentation, without overlap.

    Each surface is converted by Slicer's own closed-surface -> label map rule with the
    segmentation's conversion parameters, in a private copy (on its reference geometry, else
    on the CT grid); the results go into one label map with a value per surface. Surfaces that
    do not overlap (the pipeline checks every pair) can still claim one voxel each at a joint
    narrower than a voxel: such a voxel goes to the surface whose inside it is deepest in
    (signed distance at the voxel centre). Nothing of the segmentation is modified.
    """
    segmentation = segmentationNode.GetSegmentation()
    binary, closed = _binary_labelmap_name(), _closed_surface_name()
    private = slicer.vtkSegmentation()
    private.SetSourceRepresentationName(closed)
    private.CopyConversionParameters(segmentation)
    private.SetConversionParameter(slicer.vtkSegmentationConverter.GetReferenceImageGeometryParameterName(),
                                   _write_back_geometry(segmentationNode, volumeNode))
    names, polys = [], []
    for n, (name, surface) in enumerate(named_surfaces):
        poly = _into_node_frame(segmentationNode, surface_to_polydata_ras(surface))
        segment = slicer.vtkSegment()
        segment.SetName(name)
        segment.AddRepresentation(closed, poly)
        if not private.AddSegment(segment, f"bone{n}"):
            raise InputError(f"The surface of {name} could not be prepared as a segment.")
        names.append(name)
        polys.append(poly)
    if not private.CreateRepresentation(binary):
        raise InputError("The surfaces could not be converted to label maps for the segmentation.")
    first = private.GetSegment("bone0").GetRepresentation(binary)
    grid = _oriented_image_matrix(first)
    masks = []
    for n in range(len(names)):
        segment = private.GetSegment(f"bone{n}")
        masks.append(_mask_on_grid(segment.GetRepresentation(binary), segment.GetLabelValue(), grid))
    boxes = [box for _, box in masks if box is not None]
    if not boxes:
        raise InputError("The surfaces are too small for the segmentation's label map geometry.")
    union = _union_box(boxes)
    shape = tuple(union[2 * a + 1] - union[2 * a] + 1 for a in (2, 1, 0))
    dtype = np.uint8 if len(names) < 256 else np.uint16
    merged = np.zeros(shape, dtype)
    claims = np.zeros(shape, np.uint16)

    def window(array, box):
        return array[box[4] - union[4]:box[5] - union[4] + 1, box[2] - union[2]:box[3] - union[2] + 1,
                     box[0] - union[0]:box[1] - union[0] + 1]

    for n, (mask, box) in enumerate(masks, 1):
        if mask is None:
            continue
        window(merged, box)[mask] = n
        window(claims, box)[mask] += 1
    contested = np.argwhere(claims > 1)
    if len(contested):
        distance = [None] * len(names)
        for k, j, i in contested:
            index = np.array([i + union[0], j + union[2], k + union[4], 1.0])
            centre = (grid @ index)[:3]
            best, best_d = 0, np.inf
            for n, (mask, box) in enumerate(masks, 1):
                if mask is None:
                    continue
                ii, jj, kk = index[:3].astype(int)
                if not (box[0] <= ii <= box[1] and box[2] <= jj <= box[3] and box[4] <= kk <= box[5]):
                    continue
                if not mask[kk - box[4], jj - box[2], ii - box[0]]:
                    continue
                if distance[n - 1] is None:
                    distance[n - 1] = vtk.vtkImplicitPolyDataDistance()
                    distance[n - 1].SetInput(polys[n - 1])
                d = distance[n - 1].EvaluateFunction(*centre)
                if d < best_d:
                    best, best_d = n, d
            merged[k, j, i] = best
    image = slicer.vtkOrientedImageData()
    image.SetExtent(union)
    image.SetImageToWorldMatrix(_np_to_vtk_matrix(grid))
    image.AllocateScalars(vtk.VTK_UNSIGNED_CHAR if dtype == np.uint8 else vtk.VTK_UNSIGNED_SHORT, 1)
    _array_view(image)[...] = merged
    return PreparedSegments(labelmap=image, names=names, polys=polys, resolvedVoxels=int(len(contested)))


def add_prepared_segments(segmentationNode, prepared: PreparedSegments, colors=None,
                          sources=None) -> list:
    """Add the prepared surfaces as new segments sharing one label map layer (so no voxel is in
    two of them), with their exact surfaces as closed-surface representation where the
    segmentation keeps one. ``colors``/``sources``: per surface, its colour and the ID of the
    segment it was made from (SOURCE_SEGMENT_TAG). Returns the new segment IDs; on failure
    nothing stays added."""
    segmentation = segmentationNode.GetSegmentation()
    added = []
    try:
        for n, (name, poly) in enumerate(zip(prepared.names, prepared.polys), 1):
            segment = slicer.vtkSegment()
            segment.SetName(name)
            if colors is not None and colors[n - 1] is not None:
                segment.SetColor(*colors[n - 1])
            if sources is not None and sources[n - 1]:
                segment.SetTag(SOURCE_SEGMENT_TAG, sources[n - 1])
            segment.AddRepresentation(_binary_labelmap_name(), prepared.labelmap)
            segment.AddRepresentation(_closed_surface_name(), poly)
            segment.SetLabelValue(n)
            segmentId = segmentation.GenerateUniqueSegmentID(name)
            if not segmentation.AddSegment(segment, segmentId):
                raise InputError(f"Could not add the surface as segment '{name}' to "
                                 f"'{segmentationNode.GetName()}'.")
            added.append(segmentId)
    except Exception:
        for segmentId in added:
            segmentation.RemoveSegment(segmentId)
        raise
    return added


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

    def __init__(self, scene, nodes=(), onCancel=None):
        self.scene = scene
        self.nodes = [n for n in nodes if n is not None]
        self.reason: Optional[str] = None
        # called once when the run is to be cancelled (a child process is stopped at once)
        self.onCancel = onCancel
        self._tags = []
        if scene is not None:
            self._tags = [scene.AddObserver(slicer.vtkMRMLScene.StartCloseEvent, self._onClose),
                          scene.AddObserver(slicer.vtkMRMLScene.NodeRemovedEvent, self._onNodeRemoved)]

    def _onClose(self, caller=None, event=None):
        if self.reason is None:
            self.reason = "The scene was closed during the run"
            self._notify()

    def _onNodeRemoved(self, caller=None, event=None):
        if self.reason is not None:
            return
        for node in self.nodes:
            if not self.scene.IsNodePresent(node):
                self.reason = f"'{node.GetName()}' was removed from the scene during the run"
                self._notify()
                return

    def _notify(self):
        if self.onCancel is not None:
            self.onCancel()

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


def export_joint_inputs(volumeNode, segmentationNode, segmentIds, neighbourIds, params: Parameters,
                        progress: Optional[RunProgress] = None):
    """(CT, SegmentLabels) for a joint run: the bones and their neighbours as one label image on
    the CT grid (neighbours out of the pipeline's reach are left out)."""
    if progress is not None:
        progress(EXPORT_VOLUME_START, "Reading the CT volume")
    ct = volume_to_sitk(volumeNode)
    message = "Reading the segment" if len(segmentIds) + len(neighbourIds) == 1 else "Reading the segments"
    if progress is not None:
        progress(EXPORT_SEGMENT_START, message)

    def layer(fraction, text):
        if progress is not None and fraction > 0:
            progress(EXPORT_SEGMENT_START + (IMPORT_START - EXPORT_SEGMENT_START) * fraction, text)

    labels = segments_to_sitk_labels(
        segmentationNode, list(segmentIds) + list(neighbourIds), volumeNode, required=segmentIds,
        reach_mm=params.margin + params.segment_dilation + NEIGHBOUR_REACH_SLACK_MM, progress=layer)
    return ct, labels


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


def bone_summary(bone) -> str:
    """One line per bone of a joint run: vertices, faces, checks, plausibility, cap, warnings."""
    report = bone.report
    text = summary_line(bone.name, report.checks, report.distance_to_constraints_mm, None,
                        bone.surface.n_vertices, bone.surface.n_faces)
    p = report.plausibility
    if p is not None:
        state = "plausible" if p.ok else "IMPLAUSIBLE"
        text += (f"; {state}: {100 * p.segment_inside_fraction:.0f} % of the segment inside, volume "
                 f"{p.volume_ratio:.2f} x the segment's, at most {p.max_excursion_mm:.1f} mm outside it")
    cap = report.cap or {}
    if cap.get("faces"):
        text += f"; cut by the scan: capped, {cap.get('area_mm2', 0.0):.0f} mm² of cap"
    n = len(report.warnings)
    text += f"; {n} warning{'s' if n != 1 else ''}" if n else ""
    return text


def pair_summary(pair) -> str:
    """One line per pair of bones: smallest gap, crossings, vertices inside the other."""
    gap = "no vertex within 2 mm of the other" if pair.min_gap_mm is None else \
        f"smallest gap {pair.min_gap_mm:.2f} mm"
    inside = pair.a_inside_b + pair.b_inside_a
    text = (f"{pair.a} / {pair.b}: {gap}, {pair.crossing_face_pairs} crossing face pairs, "
            f"{inside} vertices inside the other")
    if pair.contact_area_mm2:
        text += f", {pair.contact_area_mm2:.0f} mm² within 1 mm"
    return text


def summarize_joint(joint) -> list:
    """The lines of a joint run (panel result, logs): a header, one line per bone, one per pair
    of bones, then every warning (on_implausible = warn)."""
    report = joint.report
    n = len(joint.bones)
    header = f"{n} bone{'s' if n != 1 else ''} in {report.timings.total:.1f} s"
    header += "; neighbours: " + (", ".join(report.neighbours) if report.neighbours else "none")
    lines = [header] + [bone_summary(b) for b in joint.bones] + [pair_summary(p) for p in joint.pairs]
    lines += [f"warning: {w}" for b in joint.bones for w in b.report.warnings]
    return lines


@dataclass
class JointNodesResult:
    """What :func:`run_many_on_nodes` made: one model node per bone (``modelNodes[i]`` for
    ``segmentIds[i]``), the segments written back (``addedSegmentIds``, same order, empty unless
    asked for), the other segments handed to the pipeline as neighbours
    (``neighbourSegmentIds``; ``skippedSegments``: segment ID -> why one was not: empty, outside
    the CT, out of reach), the intermediate-result nodes, and the pipeline's JointResult."""

    modelNodes: list
    segmentIds: list
    result: object
    addedSegmentIds: list = field(default_factory=list)
    neighbourSegmentIds: list = field(default_factory=list)
    skippedSegments: dict = field(default_factory=dict)
    intermediateNodes: list = field(default_factory=list)

    @property
    def warnings(self) -> list:
        return [w for b in self.result.bones for w in b.report.warnings]

    def summaryLines(self) -> list:
        return summarize_joint(self.result)


def _per_segment(value, segmentIds, what: str) -> list:
    """A list aligned with ``segmentIds`` from None, a sequence of that length or a dict."""
    if value is None:
        return [None] * len(segmentIds)
    if isinstance(value, dict):
        unknown = set(value) - set(segmentIds)
        if unknown:
            raise InputError(f"{what} given for segment(s) not reconstructed: {', '.join(sorted(unknown))}.")
        return [value.get(s) for s in segmentIds]
    value = list(value)
    if len(value) != len(segmentIds):
        raise InputError(f"{len(value)} {what} for {len(segmentIds)} segments: give one per segment "
                         "(None: a new one).")
    return value


def _neighbour_ids(segmentationNode, segmentIds, neighbours) -> list:
    segmentation = segmentationNode.GetSegmentation()
    every = [segmentation.GetNthSegmentID(i) for i in range(segmentation.GetNumberOfSegments())]
    if neighbours in (None, "auto", True):
        # written back by an earlier run: a copy of its source segment, not another bone
        return [s for s in every if s not in segmentIds
                and not segmentation.GetSegment(s).HasTag(SOURCE_SEGMENT_TAG)]
    if neighbours in ("none", False):
        return []
    if isinstance(neighbours, str):
        raise InputError(f"neighbours must be 'auto', 'none' or a list of segment IDs, got '{neighbours}'.")
    chosen = list(neighbours)
    for segmentId in chosen:
        _check_segment(segmentationNode, segmentId)
    both = [s for s in chosen if s in segmentIds]
    if both:
        raise InputError(f"Segment(s) {', '.join(both)} are both reconstructed and neighbours: give "
                         "each segment one role.")
    return list(dict.fromkeys(chosen))


@dataclass
class _ManyRun:
    """What a joint run on nodes was asked for, checked before any work (shared by
    :func:`run_many_on_nodes` and :func:`start_many_on_nodes`)."""

    scene: object
    volumeNode: object
    segmentationNode: object
    segmentIds: list
    parameters: Parameters
    outputs: list
    names: list
    neighbourIds: list
    addAsSegments: bool
    showIntermediates: bool
    colorByDistance: bool

    @property
    def guardedNodes(self) -> tuple:
        """The nodes whose removal cancels the run: the inputs and the given output models."""
        return (self.volumeNode, self.segmentationNode, *[n for n in self.outputs if n is not None])


def _plan_many(volumeNode, segmentationNode, segmentIds, outputModelNodes, params, scene,
               neighbours, addAsSegments, showIntermediates, colorByDistance, modelNames) -> _ManyRun:
    """Every check of a joint run on nodes that needs no voxel (InputError before any work)."""
    parameters = _as_parameters(params)
    if showIntermediates and not parameters.keep_intermediates:
        parameters = parameters.replace(keep_intermediates=True)
    parameters.validate()
    if isinstance(segmentIds, str):
        segmentIds = [segmentIds]
    segmentIds = list(segmentIds or [])
    if scene is None:
        scene = (volumeNode.GetScene() if volumeNode is not None else None) or (
            segmentationNode.GetScene() if segmentationNode is not None else None)
    if scene is None:
        raise InputError("The input nodes are not in a scene.")
    if not segmentIds:
        _check_segment(segmentationNode, "")
    for segmentId in segmentIds:
        _check_segment(segmentationNode, segmentId)
    if len(set(segmentIds)) != len(segmentIds):
        raise InputError("The same segment is asked for twice; give each segment once.")
    outputs = _per_segment(outputModelNodes, segmentIds, "output models")
    for node in outputs:
        if node is not None and not node.IsA("vtkMRMLModelNode"):
            raise InputError("The output node must be a model node.")
    given = [n for n in outputs if n is not None]
    if len({n.GetID() or id(n) for n in given}) != len(given):
        raise InputError("The same output model is given for two segments; give each bone its own.")
    names = _per_segment(modelNames, segmentIds, "model names")
    neighbourIds = _neighbour_ids(segmentationNode, segmentIds, neighbours)
    if addAsSegments:
        _check_write_back(segmentationNode)
    return _ManyRun(scene=scene, volumeNode=volumeNode, segmentationNode=segmentationNode,
                    segmentIds=segmentIds, parameters=parameters, outputs=outputs, names=names,
                    neighbourIds=neighbourIds, addAsSegments=bool(addAsSegments),
                    showIntermediates=bool(showIntermediates), colorByDistance=bool(colorByDistance))


def _competing(plan: _ManyRun, labels: SegmentLabels) -> list:
    """The neighbour segments that made it into the label image (the others are empty, outside
    the CT or out of reach)."""
    return [s for s in plan.neighbourIds if s in labels.values]


def _pipeline_targets(plan: _ManyRun, labels: SegmentLabels) -> tuple:
    """(target label values, neighbours argument) of the pipeline call for this plan."""
    return ([labels.values[s] for s in plan.segmentIds],
            "auto" if _competing(plan, labels) else "none")


def _store_many(plan: _ManyRun, guard: RunGuard, joint, labels: SegmentLabels) -> JointNodesResult:
    """The success half of a joint run on nodes: ``joint`` (the pipeline's JointResult, or a
    child run's ChildJoint with the same attributes) into models, report attributes and, on
    request, segments and intermediate-result nodes."""
    guard.check()  # the scene may have closed after the last progress report
    segmentationNode = plan.segmentationNode
    segmentation = segmentationNode.GetSegmentation()
    segNames = [segmentation.GetSegment(s).GetName() or s for s in plan.segmentIds]
    surfaces = [_with_distances(b) for b in joint.bones]
    prepared = None
    if plan.addAsSegments:
        prepared = prepare_segments_without_overlap(
            segmentationNode, plan.volumeNode, [(f"{n} watertight", s) for n, s in zip(segNames, surfaces)])
        guard.check()
    out = JointNodesResult(modelNodes=[], segmentIds=list(plan.segmentIds), result=joint,
                           neighbourSegmentIds=_competing(plan, labels),
                           skippedSegments=dict(labels.skipped))
    _store_joint(plan.scene, out, segmentationNode, surfaces, plan.outputs, plan.names, segNames, prepared,
                 showIntermediates=plan.showIntermediates, colorByDistance=plan.colorByDistance)
    return out


def run_many_on_nodes(volumeNode, segmentationNode, segmentIds, outputModelNodes=None, params=None,
                      progress=None, scene=None, *, neighbours="auto", addAsSegments: bool = False,
                      showIntermediates: bool = False, colorByDistance: bool = False,
                      modelNames=None) -> JointNodesResult:
    """Reconstruct several bones of one segmentation together from MRML nodes (SPEC §5b).

    :param segmentIds: the segments to reconstruct (one model each, in this order).
    :param outputModelNodes: models to replace on success: None (new ones named
        "<segment> watertight"), a list aligned with ``segmentIds`` (None entries: new), or a
        dict segment ID -> model node.
    :param neighbours: "auto" (default: every other segment of the segmentation competes for
        the joints, and no surface enters it; segments written back by an earlier run are
        copies of their sources and left out), "none", or a list of segment IDs.
    :param addAsSegments: also write the surfaces into the segmentation as new segments
        "<segment> watertight", sharing one label map layer (no voxel in two of them).
    :param showIntermediates, colorByDistance: as :func:`run_on_nodes`.
    :param modelNames: names of new models (list aligned with segmentIds or dict).
    :return: :class:`JointNodesResult`.
    :raises InputError: bad inputs, overlapping segments (named). ReconstructionError and its
        subclasses (PlausibilityError, SurfaceCheckError) when a bone fails; CancelledError.

    The scene is only modified after every bone succeeded; a failed or cancelled run leaves it
    as it was (also should writing the results fail half-way: what was written is undone).
    Progress, Cancel and the scene-close guard as in :func:`run_on_nodes`. The same run in a
    child process (the GUI thread stays free): :func:`start_many_on_nodes` /
    :func:`finish_many_on_nodes`.
    """
    plan = _plan_many(volumeNode, segmentationNode, segmentIds, outputModelNodes, params, scene,
                      neighbours, addAsSegments, showIntermediates, colorByDistance, modelNames)
    with RunGuard(plan.scene, plan.guardedNodes) as guard:
        report = RunProgress(progress, guard)
        ct, labels = export_joint_inputs(volumeNode, segmentationNode, plan.segmentIds, plan.neighbourIds,
                                         plan.parameters, report)
        pipeline = load_pipeline(report)
        targets, competing = _pipeline_targets(plan, labels)
        joint = pipeline.reconstruct_many(ct, labels.image, targets, plan.parameters, report.pipeline(),
                                          neighbours=competing, names=labels.names)
        return _store_many(plan, guard, joint, labels)


# ---------------------------------------------------------------------------------------
# the same run in a child process (issue 13)
# ---------------------------------------------------------------------------------------

CHILD_STARTING_MESSAGE = "Starting the reconstruction process"


class ChildNodesRun:
    """A joint run on nodes whose reconstruction goes on in a child process
    (:class:`BoneWatertightLib.app.child.ChildRun`), made by :func:`start_many_on_nodes`.

    :meth:`poll` (from a GUI timer) never blocks: it returns ``(fraction, message, finished)``
    on the run's one [0, 1] scale (export, then the child's progress from PIPELINE_START on).
    :meth:`cancel` stops the child within a second. The scene guard (:class:`RunGuard`) stays
    on while the child runs: closing the scene, or removing an input or a given output model,
    cancels the child at once, and :func:`finish_many_on_nodes` then raises CancelledError.
    ``childRun`` is the ChildRun (its ``progress_log``, ``output``, ``command``).
    """

    def __init__(self, plan: _ManyRun, guard: RunGuard, labels: SegmentLabels, childRun):
        self.plan = plan
        self.guard = guard
        self.labels = labels
        self.childRun = childRun
        self.closed = False
        guard.onCancel = self.cancel

    def poll(self):
        from .app.child import PollResult

        if self.guard.reason is not None and not self.childRun.cancelled:
            self.childRun.cancel()
        state = self.childRun.poll()
        if self.childRun.proc is None or not self.childRun.progress_log:
            fraction = IMPORT_START
            message = state.message or CHILD_STARTING_MESSAGE
        else:
            fraction = PIPELINE_START + (1.0 - PIPELINE_START) * state.fraction
            message = state.message
        return PollResult(fraction, message, state.finished)

    @property
    def finished(self) -> bool:
        return self.childRun.finished

    def cancel(self) -> None:
        """Stop the child (returns within about a second); the run then ends cancelled."""
        self.childRun.cancel()

    def close(self) -> None:
        """Stop the child if it still runs, remove its files, stop observing the scene."""
        if not self.closed:
            self.closed = True
            try:
                self.childRun.close()
            finally:
                self.guard.onCancel = None
                self.guard.close()


def start_many_on_nodes(volumeNode, segmentationNode, segmentIds, outputModelNodes=None, params=None,
                        progress=None, scene=None, *, neighbours="auto", addAsSegments: bool = False,
                        showIntermediates: bool = False, colorByDistance: bool = False,
                        modelNames=None, python: Optional[str] = None, env: Optional[dict] = None,
                        tempRoot: Optional[str] = None) -> ChildNodesRun:
    """First half of :func:`run_many_on_nodes` with the reconstruction in a child process.

    Checks the inputs, exports the CT and the segments (on this thread: MRML is read here
    only; ``progress`` is called as in run_many_on_nodes during the export), starts the
    child (``python``: the interpreter, default
    :func:`BoneWatertightLib.app.child.find_python_slicer`; ``env``: its environment;
    ``tempRoot``: where its private folder goes) and returns at once with a
    :class:`ChildNodesRun`. Poll it from a timer; then :func:`finish_many_on_nodes`. The
    arguments and errors before the run are those of run_many_on_nodes; the scene is not
    touched.
    """
    from .app.child import ChildRun

    plan = _plan_many(volumeNode, segmentationNode, segmentIds, outputModelNodes, params, scene,
                      neighbours, addAsSegments, showIntermediates, colorByDistance, modelNames)
    guard = RunGuard(plan.scene, plan.guardedNodes)
    try:
        report = RunProgress(progress, guard)
        ct, labels = export_joint_inputs(volumeNode, segmentationNode, plan.segmentIds, plan.neighbourIds,
                                         plan.parameters, report)
        report(IMPORT_START, CHILD_STARTING_MESSAGE)
        targets, competing = _pipeline_targets(plan, labels)
        # the export made sure every target and neighbour in the label image has voxels
        child = ChildRun(ct, labels.image, targets, labels.names, plan.parameters, neighbours=competing,
                         python=python, env=env, temp_root=tempRoot, check_labels=False)
        child.start()
    except BaseException:
        guard.close()
        raise
    return ChildNodesRun(plan, guard, labels, child)


def finish_many_on_nodes(run: ChildNodesRun, timeout: Optional[float] = None) -> JointNodesResult:
    """Second half: wait for the child (at once when :meth:`ChildNodesRun.poll` said finished;
    ``timeout`` in s, else ChildRunError), then write the surfaces into the model nodes (and
    segments, intermediate nodes) exactly as :func:`run_many_on_nodes` does, and return its
    :class:`JointNodesResult` (``result`` is the child's ChildJoint: ``bones[i].report``,
    ``pairs``, ``report``, typed). The child's error is raised as the library's typed error
    (InputError, ReconstructionError, ...), CancelledError after a cancel, a closed scene or a
    removed node; the scene is then unchanged. The child's files and the scene observers are
    gone afterwards in every case."""
    try:
        run.guard.check()
        joint = run.childRun.result(timeout)
        return _store_many(run.plan, run.guard, joint, run.labels)
    except BaseException:
        if run.guard.reason is not None:
            run.childRun.cancel()
            run.guard.check()  # CancelledError naming why (the scene closed, a node was removed)
        raise
    finally:
        run.close()


def _with_distances(bone) -> Surface:
    surface = bone.surface
    if DISTANCE_ARRAY not in surface.point_data and bone.distance_to_constraints is not None:
        d = np.asarray(bone.distance_to_constraints, dtype=np.float64)
        if d.shape == (surface.n_vertices,):
            surface = surface.copy()
            surface.point_data[DISTANCE_ARRAY] = d
    return surface


class _SceneChanges:
    """What a successful run writes, undone if writing fails half-way: nodes it added, models
    it replaced (their mesh, report attributes and display settings), segments it added."""

    _DISPLAY = ("ScalarVisibility", "ActiveScalarName", "ColorNodeID", "ScalarRangeFlag", "ScalarRange")

    def __init__(self, scene, segmentationNode):
        self.scene = scene
        self.segmentationNode = segmentationNode
        self.added = []
        self.models = []
        self.segments = []

    def addNode(self, node):
        self.added.append(node)
        return node

    def replacingModel(self, node):
        display = node.GetDisplayNode()
        state = None if display is None else {k: getattr(display, "Get" + k)() for k in self._DISPLAY}
        attributes = {k: node.GetAttribute(k) for k in
                      (REPORT_ATTRIBUTE, JOINT_REPORT_ATTRIBUTE, SOURCE_SEGMENT_ATTRIBUTE)}
        self.models.append((node, node.GetPolyData(), display, state, attributes))

    def undo(self):
        segmentation = self.segmentationNode.GetSegmentation()
        for segmentId in self.segments:
            segmentation.RemoveSegment(segmentId)
        for node in reversed(self.added):
            if node.GetScene() is not None:
                display = node.GetDisplayNode() if node.IsA("vtkMRMLDisplayableNode") else None
                node.GetScene().RemoveNode(node)
                if display is not None and display.GetScene() is not None:
                    display.GetScene().RemoveNode(display)
        for node, poly, display, state, attributes in self.models:
            node.SetAndObservePolyData(poly)
            for key, value in attributes.items():
                if value is None:
                    node.RemoveAttribute(key)
                else:
                    node.SetAttribute(key, value)
            if display is not None:
                if node.GetDisplayNode() is not display:
                    created = node.GetDisplayNode()
                    node.SetAndObserveDisplayNodeID(display.GetID())
                    if created is not None and created.GetScene() is not None:
                        created.GetScene().RemoveNode(created)
                display.SetActiveScalar(state["ActiveScalarName"], vtk.vtkAssignAttribute.POINT_DATA)
                if display.GetColorNodeID() != state["ColorNodeID"]:  # "" stands for none
                    display.SetAndObserveColorNodeID(state["ColorNodeID"] or "")
                display.SetScalarRangeFlag(state["ScalarRangeFlag"])
                display.SetScalarRange(*state["ScalarRange"])
                display.SetScalarVisibility(state["ScalarVisibility"])
            elif node.GetDisplayNode() is not None:
                created = node.GetDisplayNode()
                node.SetAndObserveDisplayNodeID(None)
                if created.GetScene() is not None:
                    created.GetScene().RemoveNode(created)


def _store_joint(scene, out: JointNodesResult, segmentationNode, surfaces, outputs, names, segNames,
                 prepared, *, showIntermediates, colorByDistance):
    """Success: only now touch the scene (models, report attributes, segments, intermediates);
    should any of it fail, what was written is undone and the error propagates."""
    joint = out.result
    segmentation = segmentationNode.GetSegmentation()
    changes = _SceneChanges(scene, segmentationNode)
    jointJson = to_json(joint.report) if len(joint.bones) > 1 else None
    try:
        for segmentId, bone, surface, node, name, segName in zip(out.segmentIds, joint.bones, surfaces,
                                                                 outputs, names, segNames):
            color = segmentation.GetSegment(segmentId).GetColor()
            if node is None:
                node = changes.addNode(scene.AddNewNodeByClass(
                    "vtkMRMLModelNode", name or scene.GenerateUniqueName(f"{segName} watertight")))
                node.CreateDefaultDisplayNodes()
                if node.GetDisplayNode() is not None:
                    node.GetDisplayNode().SetColor(*color)
            else:
                changes.replacingModel(node)
            update_model_node(node, surface, colorByDistance=colorByDistance)
            node.SetAttribute(REPORT_ATTRIBUTE, to_json(bone.report))
            node.SetAttribute(SOURCE_SEGMENT_ATTRIBUTE, _source_key(segmentationNode, segmentId))
            if jointJson is not None:
                node.SetAttribute(JOINT_REPORT_ATTRIBUTE, jointJson)
            else:
                node.RemoveAttribute(JOINT_REPORT_ATTRIBUTE)
            out.modelNodes.append(node)
        if prepared is not None:
            colors = [segmentation.GetSegment(s).GetColor() for s in out.segmentIds]
            changes.segments = add_prepared_segments(segmentationNode, prepared, colors, out.segmentIds)
            out.addedSegmentIds = list(changes.segments)
        if showIntermediates:
            for bone, segName in zip(joint.bones, segNames):
                if getattr(bone, "intermediates", None):
                    nodes = add_intermediate_nodes(scene, bone.intermediates, prefix=f"BoneWatertight {segName}")
                    for node in nodes:
                        changes.addNode(node)
                    out.intermediateNodes += nodes
    except BaseException:
        changes.undo()
        out.modelNodes, out.addedSegmentIds, out.intermediateNodes = [], [], []
        raise


def _source_key(segmentationNode, segmentId) -> str:
    return f"{segmentationNode.GetID()}/{segmentId}"


def previous_output_models(scene, segmentationNode, segmentIds) -> dict:
    """{segment ID: model node} of the models an earlier run made from these segments (their
    SOURCE_SEGMENT_ATTRIBUTE), for a panel that replaces its previous results on a new run."""
    wanted = {_source_key(segmentationNode, s): s for s in segmentIds}
    found = {}
    for n in range(scene.GetNumberOfNodesByClass("vtkMRMLModelNode")):
        node = scene.GetNthNodeByClass(n, "vtkMRMLModelNode")
        segmentId = wanted.get(node.GetAttribute(SOURCE_SEGMENT_ATTRIBUTE) or "")
        if segmentId is not None and segmentId not in found:
            found[segmentId] = node
    return found


def run_on_nodes(volumeNode, segmentationNode, segmentId, outputModelNode=None, params=None,
                 progress=None, scene=None, *, addAsSegment: bool = False,
                 showIntermediates: bool = False, colorByDistance: bool = False,
                 modelName: Optional[str] = None, neighbours="auto"):
    """Reconstruct the watertight surface of one bone from MRML nodes.

    Returns ``(modelNode, result)`` (a ReconstructionResult). Every other segment of the
    segmentation is a neighbour by default (``neighbours="auto"``: they compete for the joint
    and the surface never enters them); ``neighbours="none"`` reconstructs the segment alone,
    a list of segment IDs uses those. The scene is only modified after the pipeline succeeded;
    any error (bad input, reconstruction failure, cancel) propagates with the scene unchanged.
    ``progress(fraction, message)`` is called from the first moment (CT and segment export,
    the open3d import) and throughout the pipeline; returning False cancels. Closing the
    scene, or removing an input or the output node, during the run cancels it
    (CancelledError) and nothing is written (:class:`RunGuard`).
    """
    _check_segment(segmentationNode, segmentId)
    out = run_many_on_nodes(volumeNode, segmentationNode, [segmentId], [outputModelNode], params,
                            progress, scene, neighbours=neighbours, addAsSegments=addAsSegment,
                            showIntermediates=showIntermediates, colorByDistance=colorByDistance,
                            modelNames=[modelName])
    return out.modelNodes[0], out.result.bones[0]


def segment_selection(segmentationNode, segmentIds=(), segmentId: str = "",
                      pickFirst: bool = False) -> list:
    """The segments a panel shows as chosen in ``segmentationNode``: the stored ``segmentIds``
    that exist in it (in their order), else the one ``segmentId`` of an older parameter node,
    else, when ``pickFirst`` (the segmentation was just chosen), its first segment, as the
    single-segment selector does; [] without a segmentation."""
    if segmentationNode is None:
        return []
    segmentation = segmentationNode.GetSegmentation()
    chosen = [s for s in dict.fromkeys(_segment_id_list(segmentIds)) if segmentation.GetSegment(s)]
    if chosen:
        return chosen
    if segmentId and segmentation.GetSegment(segmentId) is not None:
        return [segmentId]
    if pickFirst and segmentation.GetNumberOfSegments():
        return [segmentation.GetNthSegmentID(0)]
    return []


def _segments_mask(volumeNode, segmentationNode, segmentIds) -> sitk.Image:
    if isinstance(segmentIds, str):
        segmentIds = [segmentIds]
    labels = segments_to_sitk_labels(segmentationNode, list(segmentIds), volumeNode)
    return sitk.Cast(sitk.NotEqual(labels.image, 0), sitk.sitkUInt8)


def propose_thresholds(volumeNode, segmentationNode, segmentId, theta_max: float = 2500.0) -> dict:
    """H0/HT proposal from the HU histogram in and around the segment (or the union of several
    segments: a list of IDs), see autothreshold."""
    from .stages.autothreshold import propose_thresholds as _propose

    ct = volume_to_sitk(volumeNode)
    return _propose(ct, _segments_mask(volumeNode, segmentationNode, segmentId), theta_max=theta_max)


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


def _segment_id_list(segmentIds) -> list:
    """A segment ID or a sequence of them, as a list ([] for none)."""
    if not segmentIds:
        return []
    if isinstance(segmentIds, str):
        return [segmentIds]
    return [s for s in segmentIds if s]


def _preview_source_key(volumeNode, segmentationNode, segmentIds):
    """Changes whenever the voxels, the geometry or the segments that the preview's cached
    crop was made from change (MTimes are cheap to read: microseconds)."""
    image = volumeNode.GetImageData()
    key = [volumeNode.GetID(), volumeNode.GetMTime(), image.GetMTime() if image is not None else None,
           _transform_key(volumeNode)]
    ids = _segment_id_list(segmentIds)
    if segmentationNode is not None and ids:
        segmentation = segmentationNode.GetSegmentation()
        key += [segmentationNode.GetID(), segmentationNode.GetMTime(), segmentation.GetMTime(),
                _transform_key(segmentationNode)]
        for segmentId in ids:
            segment = segmentation.GetSegment(segmentId)
            source = (segment.GetRepresentation(segmentation.GetSourceRepresentationName())
                      if segment is not None else None)
            key += [segmentId, segment.GetMTime() if segment is not None else None,
                    source.GetMTime() if source is not None else None]
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

    def _crop_box(self, volumeNode, segmentationNode, segmentIds, image):
        """IJK extent of the volume (its own grid) to preview: the segments' box + margin."""
        extent = list(image.GetExtent())
        ids = _segment_id_list(segmentIds)
        if segmentationNode is None or not ids:
            return extent
        ijk_to_world = _ijk_to_world(volumeNode)
        if ijk_to_world is None:  # non-linear transform: the volume's IJK has no world box
            return extent
        for segmentId in ids:
            _check_segment(segmentationNode, segmentId)
        reference = slicer.vtkOrientedImageData()
        reference.SetExtent(extent)
        reference.SetImageToWorldMatrix(_np_to_vtk_matrix(ijk_to_world))
        spacing = np.linalg.norm(ijk_to_world[:3, :3], axis=0)
        margin = np.ceil(self.margin_mm / spacing).astype(int)
        boxes = []
        for labelmap, values in _labelmap_layers_world(segmentationNode, ids, reference):
            found = _label_boxes(labelmap, values.values())
            boxes += [_box_on_grid(found[int(v)], labelmap, ijk_to_world, extent, margin_voxels=margin)
                      for v in values.values()]
        if all(b is None for b in boxes):
            raise EmptySegmentError("The segment is empty: nothing to preview.")
        if not any(boxes):
            raise NoOverlapError("The segment does not overlap the volume: nothing to preview.")
        return _union_box(boxes)

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

    def update(self, volumeNode, segmentationNode, segmentId, h0: float, ht: float,
               theta_max: float):
        """Show [HT, H0) and [H0, theta_max] around the segment (a segment ID, or a list of
        them: around all of them); returns the label map node."""
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

