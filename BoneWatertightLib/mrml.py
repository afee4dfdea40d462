"""Adapter between MRML nodes (3D Slicer / slicer-core) and the pure library.

The only module of BoneWatertightLib that imports ``slicer``; it uses MRML/VTK classes only
(never qt, ctk, slicer.app or slicer.util), so it runs inside Slicer and, in CI, on the
``slicer-core`` wheel. It converts and writes back; it runs nothing. Running a reconstruction
on nodes (in the application's process or in a child process), its scene guard and undo, the
summary lines and the panel's threshold preview are front-end work in :mod:`.app`
(:mod:`.app.nodes`, :mod:`.app.summaries`, :mod:`.app.preview`), which uses this module and
never imports ``slicer`` itself.

Coordinate conventions: MRML is RAS, SimpleITK images and the pipeline are LPS. The volume's
full IJK->RAS matrix (any direction, non-zero origin) and its parent transform (world frame)
are converted into the SimpleITK origin/spacing/direction; surfaces come back as RAS polydata.

Nothing here modifies an input node: voxels are copied, the segments are exported through
vtkOrientedImageData objects that never enter the scene.

- inputs: :func:`volume_to_sitk`, :func:`segment_to_sitk_mask` and, for several bones,
  :func:`segments_to_sitk_labels` (the segments and their neighbours as one label image on the
  CT grid, a value per segment; overlapping segments are refused, named);
  :func:`segments_box_on_volume` (the segments' box on the volume's own grid);
- outputs: :func:`update_model_node`, :func:`add_surface_as_segment`, the surfaces of a joint
  run written back as segments that share one label map layer, so that no voxel belongs to
  two of them (:func:`prepare_segments_without_overlap`, :func:`add_prepared_segments`),
  :func:`add_intermediate_nodes`, :func:`read_model_file`;
- nodes from images for tests and scripts: :func:`volume_node_from_sitk`,
  :func:`segmentation_node_from_mask`, :func:`segmentation_node_from_labels`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import SimpleITK as sitk
import vtk
from vtk.util import numpy_support as ns

import slicer

from .errors import EmptySegmentError, InputError, NoOverlapError, VolumeTypeError
from .mesh.surface import Surface, to_polydata

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


def array_view(image) -> np.ndarray:
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

def check_volume_node(volumeNode):
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
    image, ijk_to_world = _image_in_world(volumeNode)
    extent = image.GetExtent()
    # GetImageFromArray copies the buffer: one copy of the voxels, not two
    return _sitk_from_array(array_view(image), ijk_to_world, extent[0::2])


def _image_in_world(volumeNode):
    """(image, IJK->world-RAS matrix) of a checked volume node: its own image under a linear
    transform chain, else a copy resampled into world space."""
    image = check_volume_node(volumeNode)
    ijk_to_world = _ijk_to_world(volumeNode)
    if ijk_to_world is None:
        image = _hardened_oriented_image(volumeNode)
        ijk_to_world = _oriented_image_matrix(image)
    return image, ijk_to_world


def _reference_geometry(volumeNode):
    """Geometry-only vtkOrientedImageData of the CT grid in world RAS."""
    image, ijk_to_world = _image_in_world(volumeNode)
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


def check_segment(segmentationNode, segmentId):
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
    check_segment(segmentationNode, segmentId)
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
    arr = array_view(labelmap)
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
        check_segment(segmentationNode, segmentId)
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
        source = array_view(resampled)
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


def _segmentation_from_label_image(scene, labels: sitk.Image, name: str, what: str):
    """A new segmentation node with the label image imported as Slicer imports a label map
    volume (one segment per value, sharing one label map); the temporary label map node is
    removed again."""
    labelmap = volume_node_from_sitk(scene, labels, "BoneWatertight import", "vtkMRMLLabelMapVolumeNode")
    segmentation = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", name)
    try:
        if not slicer.vtkSlicerSegmentationsModuleLogic.ImportLabelmapToSegmentationNode(labelmap, segmentation):
            raise InputError(f"The {what} could not be imported into a segmentation.")
    finally:
        scene.RemoveNode(labelmap)
    return segmentation


def segmentation_node_from_mask(scene, mask: sitk.Image, name: str = "Segmentation",
                                segmentName: str = "bone"):
    """A new segmentation node with one segment (mask != 0) on the mask's own grid; returns
    ``(segmentationNode, segmentId)``. The scene's segmentations logic must be set up first
    (it registers the converter rules)."""
    binary = sitk.Cast(sitk.NotEqual(mask, 0), sitk.sitkUInt8)
    segmentation = _segmentation_from_label_image(scene, binary, name, "mask")
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
    segmentation = _segmentation_from_label_image(scene, labels, name, "label map")
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


def check_write_back(segmentationNode):
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
    geometry, seg_to_world = check_write_back(segmentationNode)
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
        arr = array_view(labelmap)[box[4] - e[4]:box[5] - e[4] + 1, box[2] - e[2]:box[3] - e[2] + 1,
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
    return array_view(out) == label, list(out.GetExtent())


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
    array_view(image)[...] = merged
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




def remove_node(node) -> None:
    """Take a node and its display node out of their scene (RemoveNode leaves a displayable
    node's display node behind, orphaned); nothing for a node outside any scene."""
    if node is None or node.GetScene() is None:
        return
    display = node.GetDisplayNode() if node.IsA("vtkMRMLDisplayableNode") else None
    node.GetScene().RemoveNode(node)
    if display is not None and display.GetScene() is not None:
        display.GetScene().RemoveNode(display)


# ---------------------------------------------------------------------------------------
# a crop of the volume around segments (the panel's threshold preview)
# ---------------------------------------------------------------------------------------

def segment_id_list(segmentIds) -> list:
    """A segment ID or a sequence of them, as a list ([] for none)."""
    if not segmentIds:
        return []
    if isinstance(segmentIds, str):
        return [segmentIds]
    return [s for s in segmentIds if s]


def segments_box_on_volume(volumeNode, segmentationNode, segmentIds, margin_mm: float) -> list:
    """IJK extent ``[i0, i1, j0, j1, k0, k1]`` of the volume's own grid that holds the
    segments' voxels, grown by ``margin_mm`` and clipped to the volume: the whole volume
    without segments, or under a non-linear transform (its IJK then has no world box).

    :raises EmptySegmentError: every segment is empty.
    :raises NoOverlapError: no segment overlaps the volume.
    """
    image = check_volume_node(volumeNode)
    extent = list(image.GetExtent())
    ids = segment_id_list(segmentIds)
    if segmentationNode is None or not ids:
        return extent
    ijk_to_world = _ijk_to_world(volumeNode)
    if ijk_to_world is None:
        return extent
    for segmentId in ids:
        check_segment(segmentationNode, segmentId)
    reference = slicer.vtkOrientedImageData()
    reference.SetExtent(extent)
    reference.SetImageToWorldMatrix(_np_to_vtk_matrix(ijk_to_world))
    spacing = np.linalg.norm(ijk_to_world[:3, :3], axis=0)
    margin = np.ceil(float(margin_mm) / spacing).astype(int)
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


def volume_crop(volumeNode, box) -> tuple:
    """``(voxels, ijk_to_ras)``: a copy of the volume's voxels in the IJK extent ``box``, (k, j,
    i), and the IJK->RAS matrix (4 x 4) of that crop as an image of its own (extent from 0)."""
    image = check_volume_node(volumeNode)
    full = image.GetExtent()
    voxels = np.ascontiguousarray(array_view(image)[box[4] - full[4]:box[5] - full[4] + 1,
                                                    box[2] - full[2]:box[3] - full[2] + 1,
                                                    box[0] - full[0]:box[1] - full[0] + 1])
    m = vtk.vtkMatrix4x4()
    volumeNode.GetIJKToRASMatrix(m)
    ijk_to_ras = _vtk_to_np_matrix(m)
    ijk_to_ras[:3, 3] = (ijk_to_ras @ np.array([box[0], box[2], box[4], 1.0]))[:3]
    return voxels, ijk_to_ras


def set_labelmap_buffer(labelmapNode, shape_kji, ijk_to_ras: np.ndarray, parentTransformId=None) -> np.ndarray:
    """Give a label map node a new zeroed uint8 image of ``shape_kji`` with that IJK->RAS
    matrix and parent transform; returns a writable (k, j, i) view of the node's buffer (write
    into it, then :func:`mark_modified`)."""
    labelmapNode.SetIJKToRASMatrix(_np_to_vtk_matrix(ijk_to_ras))
    labelmapNode.SetAndObserveTransformNodeID(parentTransformId)
    labels = vtk.vtkImageData()
    labels.SetDimensions(shape_kji[2], shape_kji[1], shape_kji[0])
    labels.AllocateScalars(vtk.VTK_UNSIGNED_CHAR, 1)
    labelmapNode.SetAndObserveImageData(labels)
    return array_view(labels)


def mark_modified(volumeNode) -> None:
    """Tell the views that the voxels of the node's image changed (written through a view)."""
    image = volumeNode.GetImageData()
    image.GetPointData().GetScalars().Modified()
    image.Modified()


def _world_frame_key(node):
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


def inputs_state_key(volumeNode, segmentationNode, segmentIds) -> tuple:
    """A key that changes whenever the volume's voxels or geometry, or the segments'
    voxels or geometry, change (MTimes are cheap to read: microseconds), for caches of a crop."""
    image = volumeNode.GetImageData()
    key = [volumeNode.GetID(), volumeNode.GetMTime(), image.GetMTime() if image is not None else None,
           _world_frame_key(volumeNode)]
    ids = segment_id_list(segmentIds)
    if segmentationNode is not None and ids:
        segmentation = segmentationNode.GetSegmentation()
        key += [segmentationNode.GetID(), segmentationNode.GetMTime(), segmentation.GetMTime(),
                _world_frame_key(segmentationNode)]
        for segmentId in ids:
            segment = segmentation.GetSegment(segmentId)
            source = (segment.GetRepresentation(segmentation.GetSourceRepresentationName())
                      if segment is not None else None)
            key += [segmentId, segment.GetMTime() if segment is not None else None,
                    source.GetMTime() if source is not None else None]
    return tuple(key)
