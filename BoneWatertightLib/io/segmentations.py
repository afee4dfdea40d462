"""Reading one segment as a mask: from a label map (value or name) or a 3D Slicer ``.seg.nrrd``."""

from __future__ import annotations

import csv
import os
import re
from typing import Tuple, Union

import numpy as np
import SimpleITK as sitk

from ..errors import EmptySegmentError, InputError, VolumeTypeError
from .files import PathLike, extension as _extension
from .images import _read_image_file, _short_list

# ----------------------------------------------------------------------------------------
# segments

def is_slicer_segmentation(path: PathLike) -> bool:
    """True for a 3D Slicer segmentation file (``.seg.nrrd`` or NRRD with Segment* keys)."""
    path = os.fspath(path)
    if _extension(path) == ".seg.nrrd":
        return True
    if _extension(path) != ".nrrd" or not os.path.isfile(path):
        return False
    reader = sitk.ImageFileReader()
    reader.SetFileName(path)
    try:
        reader.ReadImageInformation()
    except RuntimeError:
        return False
    return reader.HasMetaDataKey("Segment0_ID")


def slicer_segments(image: sitk.Image) -> list:
    """The segments described in a .seg.nrrd header, in file order.

    Each is a dict with ``index``, ``id``, ``name``, ``label_value`` (int) and ``layer`` (int).
    """
    keys = set(image.GetMetaDataKeys())
    segments = []
    i = 0
    while f"Segment{i}_ID" in keys:
        def get(field, default=""):
            key = f"Segment{i}_{field}"
            return image.GetMetaData(key) if key in keys else default
        segments.append({
            "index": i,
            "id": get("ID"),
            "name": get("Name") or get("ID"),
            # Slicer files older than 4.11 have no LabelValue/Layer: one layer, value i + 1.
            "label_value": int(float(get("LabelValue", str(i + 1)))),
            "layer": int(float(get("Layer", "0"))),
        })
        i += 1
    return segments


def read_segment(path: PathLike, label: Union[int, str]) -> Tuple[sitk.Image, str]:
    """Read one segment as a uint8 mask (1 inside) on the segment file's own grid.

    ``path`` is a label map (any integer image; ``label`` is a label value, or a name listed in
    a ``labels.csv`` / ``<file stem>.csv`` beside it with columns value,name) or a Slicer
    ``.seg.nrrd`` (``label`` is a segment name, segment ID or label value).
    Returns (mask, segment name).
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputError(f"Segment file not found: {path}")
    if os.path.isdir(path):
        raise InputError(f"Segment must be a label-map file or a .seg.nrrd, not a folder: {path}")
    label = str(label).strip()
    if not label:
        raise InputError("No label given: pass a label value or a segment name.")
    if is_slicer_segmentation(path):
        image = _read_image_file(path, "segmentation")
        mask, name = _segment_from_slicer(image, label, path)
    else:
        image = _read_image_file(path, "label map")
        mask, name = _segment_from_label_map(image, label, path)
    if not np.any(sitk.GetArrayViewFromImage(mask)):
        raise EmptySegmentError(f"Segment '{name}' in {path} has no voxel. Pick a segment "
                                "that is painted, or paint this one first.")
    return mask, name


def _segment_from_slicer(image: sitk.Image, label: str, path: str) -> Tuple[sitk.Image, str]:
    segments = slicer_segments(image)
    if not segments:
        raise InputError(f"{path} holds no segment (no Segment0_ID in its header).")
    matches = ([s for s in segments if s["name"] == label]
               or [s for s in segments if s["id"] == label]
               or [s for s in segments if s["name"].lower() == label.lower()])
    if not matches and _is_int(label):
        matches = [s for s in segments if s["label_value"] == int(label)]
    if not matches:
        raise InputError(
            f"Segment '{label}' is not in {path}. Available (name / ID / label value): "
            + "; ".join(f"{s['name']} / {s['id']} / {s['label_value']}" for s in segments)
        )
    if len(matches) > 1:
        raise InputError(
            f"'{label}' matches {len(matches)} segments in {path} ("
            + ", ".join(f"{s['name']} ({s['id']})" for s in matches)
            + "). Use the segment ID to pick one."
        )
    seg = matches[0]
    layers = _layers(image, path)
    if not 0 <= seg["layer"] < len(layers):
        raise InputError(f"Segment '{seg['name']}' refers to layer {seg['layer']} but {path} "
                         f"has {len(layers)} layer(s); the file is damaged.")
    mask = sitk.Cast(sitk.Equal(layers[seg["layer"]], seg["label_value"]), sitk.sitkUInt8)
    return mask, seg["name"]


def _layers(image: sitk.Image, path: str) -> list:
    """The 3-D label layers of a segmentation image.

    Slicer writes several layers as a 4-D NRRD whose first axis (kind "list") is the layer;
    ITK reads that as a vector image with one component per layer. A plain 4-D scalar image
    with the layer on its first axis is handled too.
    """
    ncomp = image.GetNumberOfComponentsPerPixel()
    if image.GetDimension() == 3 and ncomp == 1:
        return [image]
    if image.GetDimension() == 3:
        return [sitk.VectorIndexSelectionCast(image, k) for k in range(ncomp)]
    if image.GetDimension() == 4 and ncomp == 1:
        array = sitk.GetArrayFromImage(image)  # (z, y, x, layer)
        spacing, origin = image.GetSpacing()[1:], image.GetOrigin()[1:]
        direction = np.array(image.GetDirection()).reshape(4, 4)[1:, 1:]
        layers = []
        for k in range(array.shape[3]):
            layer = sitk.GetImageFromArray(np.ascontiguousarray(array[..., k]))
            layer.SetSpacing(spacing)
            layer.SetOrigin(origin)
            layer.SetDirection(direction.ravel().tolist())
            layers.append(layer)
        return layers
    raise VolumeTypeError(f"{path} is a {image.GetDimension()}-D image with {ncomp} "
                          "components; expected a 3-D segmentation.")


def _segment_from_label_map(image: sitk.Image, label: str, path: str) -> Tuple[sitk.Image, str]:
    if image.GetNumberOfComponentsPerPixel() > 1 or image.GetDimension() != 3:
        raise VolumeTypeError(
            f"{path} is not a 3-D label map ({image.GetDimension()}-D, "
            f"{image.GetNumberOfComponentsPerPixel()} components). Give a 3-D label map or a "
            "Slicer .seg.nrrd."
        )
    array = sitk.GetArrayViewFromImage(image)
    if array.dtype.kind == "f":
        if not np.all(np.isfinite(array)) or not np.array_equal(array, np.round(array)):
            raise VolumeTypeError(
                f"{path} has non-integer values, so it looks like a CT rather than a label map. "
                "Give the label map (or a .seg.nrrd) as --seg."
            )
    names = _label_names_beside(path)
    if _is_int(label):
        value, name = int(label), names.get(int(label), str(int(label)))
    else:
        by_name = {n.lower(): v for v, n in names.items()}
        if label.lower() not in by_name:
            present = np.unique(array)
            hint = (f" Names in the labels table: {', '.join(names.values())}." if names else
                    " A name can be used when a labels.csv (value,name) is beside the file.")
            raise InputError(f"'{label}' is not a label value of the label map {path}; values "
                             f"present: {_short_list(present[present != 0])}.{hint}")
        value = by_name[label.lower()]
        name = names[value]
    mask = sitk.Cast(sitk.Equal(image, float(value)), sitk.sitkUInt8)
    if not np.any(sitk.GetArrayViewFromImage(mask)):
        present = np.unique(array)
        present = present[present != 0]
        if len(present) and value not in present:
            raise InputError(f"Label {value} is not in the label map {path}; labels present: "
                             f"{_short_list(present)}.")
        raise EmptySegmentError(f"Label map {path} has no voxel with label {value} "
                                "(the label map is empty).")
    return mask, name


def _label_names_beside(path: str) -> dict:
    """value -> name from labels.csv or <stem>.csv beside a label map (empty if none)."""
    folder = os.path.dirname(os.path.abspath(path))
    stem = os.path.basename(path)[: -len(_extension(path))] if _extension(path) else path
    for candidate in (os.path.join(folder, stem + ".csv"), os.path.join(folder, "labels.csv")):
        if os.path.isfile(candidate):
            try:
                with open(candidate, newline="", encoding="utf-8") as f:
                    rows = list(csv.DictReader(f))
                return {int(float(r["value"])): r["name"].strip() for r in rows
                        if r.get("value") not in (None, "") and r.get("name")}
            except (KeyError, ValueError, csv.Error):
                return {}
    return {}


def _is_int(text: str) -> bool:
    return re.fullmatch(r"[+-]?\d+", str(text).strip()) is not None


