"""The Slicer panel's live threshold preview: the two windows as a label map in the slice views.

The voxels and nodes are read and written through the MRML adapter (:mod:`..mrml`); this
module decides what to cache and thresholds the cached crop, and never imports ``slicer``.
"""

from __future__ import annotations

import numpy as np

from .. import mrml

# Labels of the preview label map and their colours (the panel's tooltip names them).
PREVIEW_TARGET_LABEL = 1   # [HT, H0): reached only by the target window
PREVIEW_INITIAL_LABEL = 2  # [H0, theta_max]: the initial window
PREVIEW_COLORS = {
    PREVIEW_TARGET_LABEL: ("green", "[HT, H0)", (0.20, 0.80, 0.20)),
    PREVIEW_INITIAL_LABEL: ("yellow", "[H0, theta max]", (1.00, 0.90, 0.10)),
}
PREVIEW_MARGIN_MM = 5.0


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

    def _build(self, volumeNode, segmentationNode, segmentIds, key) -> None:
        box = mrml.segments_box_on_volume(volumeNode, segmentationNode, segmentIds, self.margin_mm)
        values, ijk_to_ras = mrml.volume_crop(volumeNode, box)
        node = self._ensure_nodes()
        # writes go straight into the node's buffer
        self._labels = mrml.set_labelmap_buffer(node, values.shape, ijk_to_ras,
                                                volumeNode.GetTransformNodeID())
        self._values = values
        self._scratch = (np.empty(values.shape, bool), np.empty(values.shape, bool))
        self._key = key
        self.cacheBuilds += 1

    def _hidden(self, node):
        node.SetHideFromEditors(True)
        node.SetSaveWithScene(False)
        return node

    def _ensure_nodes(self):
        scene = self.scene
        if self.colorNode is None or self.colorNode.GetScene() is not scene:
            color = self._hidden(scene.AddNewNodeByClass(
                "vtkMRMLColorTableNode", scene.GenerateUniqueName(f"{self.name} colours")))
            color.SetTypeToUser()
            color.SetNumberOfColors(1 + max(PREVIEW_COLORS))
            color.SetColor(0, "background", 0.0, 0.0, 0.0, 0.0)
            for label, (_colour, window, rgb) in PREVIEW_COLORS.items():
                color.SetColor(label, window, *rgb, 1.0)
            self.colorNode = color
        if self.labelmapNode is None or self.labelmapNode.GetScene() is not scene:
            self.labelmapNode = self._hidden(scene.AddNewNodeByClass(
                "vtkMRMLLabelMapVolumeNode", scene.GenerateUniqueName(self.name)))
        display = self.labelmapNode.GetDisplayNode()
        if display is None:
            # slice views draw no volume that lacks a display node (AddNewNodeByClass creates
            # none); made here, not by CreateDefaultDisplayNodes, so it never refers to the
            # default label colours (label 1 blue, 2 peach)
            display = self._hidden(scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeDisplayNode"))
            self.labelmapNode.SetAndObserveDisplayNodeID(display.GetID())
        if display.GetColorNodeID() != self.colorNode.GetID():
            display.SetAndObserveColorNodeID(self.colorNode.GetID())
        return self.labelmapNode

    # -- the per-drag-step work

    def update(self, volumeNode, segmentationNode, segmentId, h0: float, ht: float,
               theta_max: float):
        """Show [HT, H0) and [H0, theta_max] around the segment (a segment ID, or a list of
        them: around all of them); returns the label map node."""
        key = mrml.inputs_state_key(volumeNode, segmentationNode, segmentId)
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
        mrml.mark_modified(self.labelmapNode)
        return self.labelmapNode

    def remove(self) -> None:
        """Take the label map, its display node and the colour table out of the scene."""
        for node in (self.labelmapNode, self.colorNode):
            mrml.remove_node(node)
        self.labelmapNode = self.colorNode = None
        self.invalidate()
