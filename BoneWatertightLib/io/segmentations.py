"""Segments from a label map (value or name) or a 3D Slicer ``.seg.nrrd``.

- :func:`read_segment`: one segment as a uint8 mask (1 inside).
- :func:`read_label_image`: every segment as one label image (uint16 or uint32) and the names of
  its labels, for a run that needs a bone's neighbours as well.
- :func:`resolve_label`: a segment name, segment ID or label value -> the label value in that
  label image.

A label value is checked against the label map's pixel type and the labels it actually holds,
and is never cast: ``--label 257`` on a uint8 label map is refused, not wrapped to label 1. The
header of a ``.seg.nrrd`` is read as 3D Slicer reads it (``Segment<i>_LabelValue`` default 1,
``Segment<i>_Layer`` default ``i``), and a value that cannot be used is refused with a message
naming the key.
"""

from __future__ import annotations

import csv
import os
import re
from typing import Dict, List, Optional, Tuple, Union

import numpy as np
import SimpleITK as sitk

from ..errors import EmptySegmentError, InputError, VolumeTypeError
from .files import PathLike, extension as _extension
from .images import _read_image_file, _short_list, check_finite

# Values a label image from read_label_image can hold, by its pixel type.
UINT16_MAX = np.iinfo(np.uint16).max
UINT32_MAX = np.iinfo(np.uint32).max
# Overlapping segment pairs named in the message (the rest are counted).
OVERLAP_PAIRS_SHOWN = 5
# Voxels handled at once when counting or mapping labels (bounds the temporary arrays).
CHUNK_VOXELS = 1 << 22
# Value spans up to this are counted with a histogram, wider ones with a sort.
HISTOGRAM_SPAN = 1 << 24


class LabelNames(dict):
    """Label value -> name of the labels of one label image (a ``dict[int, str]``).

    Returned by :func:`read_label_image`; :func:`resolve_label` reads the attributes below,
    which a plain ``dict(names)`` copy drops.

    Attributes
    ----------
    path : str
        The file the labels were read from.
    kind : {"label map", "segmentation"}
    present : frozenset of int
        The values that have at least one voxel.
    pixel_type : str
        The file's pixel type (numpy name, e.g. ``"uint8"``).
    value_range : tuple of int
        The values that pixel type can hold, (lowest, highest).
    table : dict
        Label map: every value -> name of the labels table beside it (``labels.csv`` or
        ``<stem>.csv``), also for values the map does not hold. Empty for a segmentation.
    table_error : str
        Why a labels table beside the label map could not be used ("" when fine or absent).
    segments : list of dict
        Segmentation: one dict per segment in file order with ``index``, ``id``, ``name``,
        ``label_value`` and ``layer`` (as in the file) and ``value`` (its value here).
    """

    def __init__(self, names=(), *, path: str = "", kind: str = "label map",
                 present=(), pixel_type: str = "", value_range: Tuple[int, int] = (0, 0),
                 table: Optional[dict] = None, table_error: str = "",
                 segments: Optional[list] = None):
        super().__init__(names)
        self.path = path
        self.kind = kind
        self.present = frozenset(int(v) for v in present)
        self.pixel_type = pixel_type
        self.value_range = tuple(value_range)
        self.table = dict(table or {})
        self.table_error = table_error
        self.segments = list(segments or [])

    @property
    def ids(self) -> Dict[int, str]:
        """Value -> segment ID (segmentation; empty for a label map)."""
        return {s["value"]: s["id"] for s in self.segments}


# ----------------------------------------------------------------------------------------
# public API

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


def slicer_segments(image: sitk.Image, path: str = "the segmentation") -> list:
    """The segments described in a .seg.nrrd header, in file order.

    Each is a dict with ``index``, ``id``, ``name``, ``label_value`` (int) and ``layer`` (int),
    with 3D Slicer's defaults where a key is missing (label value 1, layer = the segment's
    index). Raises InputError naming the key when a value is not a usable integer (e.g.
    ``Segment0_LabelValue:=abc``), a label value is 0 or beyond what the file's pixel type
    holds, a layer does not exist, or two segments claim the same label value in one layer.
    """
    keys = set(image.GetMetaDataKeys())
    n_layers = _n_layers(image)
    low, high = _type_range(_pixel_dtype(image))
    segments = []
    i = 0
    while f"Segment{i}_ID" in keys:
        def get(field, default=None):
            key = f"Segment{i}_{field}"
            return image.GetMetaData(key).strip() if key in keys else default
        value = _header_int(get("LabelValue", "1"), f"Segment{i}_LabelValue", path)
        layer_text = get("Layer")
        layer = i if layer_text is None else _header_int(layer_text, f"Segment{i}_Layer", path)
        name = get("Name") or get("ID")
        if value == 0:
            raise InputError(f"{path} is damaged: Segment{i}_LabelValue of segment '{name}' is "
                             "0, which is the background. Re-save the segmentation in 3D "
                             "Slicer.")
        if not low <= value <= high:
            raise InputError(f"{path} is damaged: Segment{i}_LabelValue of segment '{name}' is "
                             f"{value}, but its voxels are {_pixel_dtype(image).name} "
                             f"({low} to {high}). Re-save the segmentation in 3D Slicer.")
        if not 0 <= layer < n_layers:
            why = (f"Segment{i}_Layer is missing, so (as in 3D Slicer) the segment is in layer "
                   f"{i}" if layer_text is None else f"Segment{i}_Layer is {layer}")
            raise InputError(f"{path} is damaged: {why}, but the file has {n_layers} "
                             f"layer{'s' if n_layers != 1 else ''} (0 to {n_layers - 1}), so "
                             f"segment '{name}' cannot be found. Re-save the segmentation in "
                             "3D Slicer.")
        segments.append({"index": i, "id": get("ID", ""), "name": name, "label_value": value,
                         "layer": layer})
        i += 1
    seen = {}
    for seg in segments:
        key = (seg["layer"], seg["label_value"])
        if key in seen:
            other = seen[key]
            raise InputError(
                f"{path} is damaged: segments '{other['name']}' (Segment{other['index']}) and "
                f"'{seg['name']}' (Segment{seg['index']}) both have label value "
                f"{seg['label_value']} in layer {seg['layer']}. Re-save the segmentation in "
                "3D Slicer.")
        seen[key] = seg
    return segments


def read_label_image(path: PathLike) -> Tuple[sitk.Image, LabelNames]:
    """Read every segment of a label map or a Slicer ``.seg.nrrd`` as one label image.

    Parameters
    ----------
    path : str or os.PathLike
        A label map (any integer image, or a float image holding integers; names from a
        ``<stem>.csv`` or ``labels.csv`` with columns value,name beside it, else
        ``str(value)``) or a 3D Slicer segmentation (``.seg.nrrd``, or a NRRD whose header has
        ``Segment0_ID``).

    Returns
    -------
    image : SimpleITK.Image
        The labels on the file's own grid (origin, spacing, direction as in the file), uint16
        when every value fits, else uint32; 0 is the background. A label map keeps its values.
        A segmentation's segments get distinct values: their ``LabelValue`` when those are
        distinct across layers, else 1, 2, ... in file order; several layers are merged.
    names : LabelNames
        Value -> name. Label map: every value present. Segmentation: every segment of the
        header (also those without voxels; ``names.present`` says which have voxels).

    Raises
    ------
    InputError
        The file is missing, a folder or unreadable; its header disagrees with its data; a
        ``.seg.nrrd`` header value is unusable (the message names the key); segments of
        different layers overlap (the message names them and says what to do); a label
        map holds negative values or values beyond uint32.
    VolumeTypeError
        Not a 3-D scalar label image (RGB, 2-D, 4-D, non-integer values).
    """
    path = _check_path(path)
    if is_slicer_segmentation(path):
        image = _read_image_file(path, "segmentation")
        return _merge_segmentation(image, path)
    image = _read_image_file(path, "label map")
    array = _label_map_array(image, path)
    names = _label_map_names(array, image, path)
    if names.present and (min(names.present) < 0 or max(names.present) > UINT32_MAX):
        raise InputError(f"The label map {path} holds values from {min(names.present)} to "
                         f"{max(names.present)}; labels must be 1 to {UINT32_MAX} (0 is the "
                         "background). Renumber the labels.")
    high = max(names.present, default=0)
    dtype = np.uint16 if high <= UINT16_MAX else np.uint32
    labels = sitk.GetImageFromArray(array.astype(dtype, copy=False))
    labels.CopyInformation(image)
    return labels, names


def resolve_label(names: Dict[int, str], label: Union[int, str]) -> int:
    """The value of one label of :func:`read_label_image`, from its name, ID or value.

    Parameters
    ----------
    names : LabelNames or dict
        From :func:`read_label_image` (a plain ``{value: name}`` dict also works: then
        ``label`` is a value among its keys or one of its names).
    label : int or str
        Label map: a label value, or a name of its labels table. Segmentation: a segment name
        (exact, then any case), a segment ID, or the label value written in the file.

    Returns
    -------
    int
        The label's value in the label image.

    Raises
    ------
    InputError
        No such label (the message lists the labels there), a value the pixel type cannot
        hold, the background 0, or a text that matches several segments.
    EmptySegmentError
        The label exists but has no voxel.
    """
    text = str(label).strip()
    if not text:
        raise InputError("No label given: pass a label value or a segment name.")
    if not isinstance(names, LabelNames):
        names = LabelNames(names, present=names.keys(), path="the label image",
                           table=dict(names))
    if names.kind == "segmentation":
        seg = _match_segment(names.segments, text, names.path)
        if seg["value"] not in names.present:
            raise _empty_segment(seg["name"], names.path)
        return seg["value"]
    return _label_map_value(names, text)


def read_segment(path: PathLike, label: Union[int, str]) -> Tuple[sitk.Image, str]:
    """Read one segment as a uint8 mask (1 inside) on the segment file's own grid.

    ``path`` is a label map (any integer image; ``label`` is a label value, or a name listed in
    a ``labels.csv`` / ``<file stem>.csv`` beside it with columns value,name) or a Slicer
    ``.seg.nrrd`` (``label`` is a segment name, segment ID or label value; its segments may
    overlap, each is read from its own layer). Returns (mask, segment name).

    Raises InputError when the label is not there (listing the labels that are), is a value
    the label map's pixel type cannot hold, or the file is unusable; EmptySegmentError when the
    segment has no voxel.
    """
    path = _check_path(path)
    if not str(label).strip():
        raise InputError("No label given: pass a label value or a segment name.")
    if is_slicer_segmentation(path):
        image = _read_image_file(path, "segmentation")
        segments = slicer_segments(image, path)
        if not segments:
            raise InputError(f"{path} holds no segment (no Segment0_ID in its header).")
        seg = _match_segment(segments, str(label).strip(), path)
        layer = _layer_arrays(image, path)[seg["layer"]]
        values = layer == seg["label_value"]
        name = seg["name"]
        if not values.any():
            raise _empty_segment(name, path)
    else:
        image = _read_image_file(path, "label map")
        array = _label_map_array(image, path)
        names = _label_map_names(array, image, path)
        value = _label_map_value(names, str(label).strip())
        values = array == value
        name = names[value]
    return _on_grid_of(values.astype(np.uint8), image), name


# ----------------------------------------------------------------------------------------
# label maps

def _check_path(path: PathLike) -> str:
    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputError(f"Segment file not found: {path}")
    if os.path.isdir(path):
        raise InputError(f"Segment must be a label-map file or a .seg.nrrd, not a folder: {path}")
    return path


def _label_map_array(image: sitk.Image, path: str) -> np.ndarray:
    """The (z, y, x) integer array of a label map (VolumeTypeError for anything else)."""
    if image.GetNumberOfComponentsPerPixel() > 1 or image.GetDimension() != 3:
        raise VolumeTypeError(
            f"{path} is not a 3-D label map ({image.GetDimension()}-D, "
            f"{image.GetNumberOfComponentsPerPixel()} components). Give a 3-D label map or a "
            "Slicer .seg.nrrd."
        )
    array = sitk.GetArrayViewFromImage(image)
    if array.dtype.kind == "c":
        raise VolumeTypeError(f"{path} is a complex-valued image, not a label map. Give a 3-D "
                              "label map or a Slicer .seg.nrrd.")
    if array.dtype.kind == "f":
        check_finite(image, f"The label map {path}")
        if not np.array_equal(array, np.round(array)):
            raise VolumeTypeError(
                f"{path} has non-integer values, so it looks like a CT rather than a label map. "
                "Give the label map (or a .seg.nrrd) as --seg."
            )
        if array.size and (array.min() < np.iinfo(np.int64).min
                           or array.max() > np.iinfo(np.int64).max):
            raise InputError(f"The label map {path} holds values beyond 64-bit integers.")
        array = array.astype(np.int64)
    return array


def _present_values(array: np.ndarray) -> np.ndarray:
    """Sorted distinct non-zero values of an integer array (in chunks: little memory)."""
    if array.size == 0:
        return np.zeros(0, np.int64)
    flat = array.reshape(-1)
    low, high = int(flat.min()), int(flat.max())
    chunks = (flat[i:i + CHUNK_VOXELS] for i in range(0, flat.size, CHUNK_VOXELS))
    if high - low < HISTOGRAM_SPAN:
        counts = np.zeros(high - low + 1, np.int64)
        for chunk in chunks:
            counts += np.bincount((chunk.astype(np.int64) - low), minlength=counts.size)
        values = np.flatnonzero(counts) + low
    else:
        values = np.unique(np.concatenate([np.unique(chunk) for chunk in chunks]))
    return values[values != 0].astype(np.int64)


def _label_map_names(array: np.ndarray, image: sitk.Image, path: str) -> LabelNames:
    present = [int(v) for v in _present_values(array)]
    table, table_error = _label_names_beside(path)
    dtype = _pixel_dtype(image)
    return LabelNames({v: table.get(v, str(v)) for v in present}, path=path, kind="label map",
                      present=present, pixel_type=dtype.name, value_range=_type_range(dtype),
                      table=table, table_error=table_error)


def _label_map_value(names: LabelNames, label: str) -> int:
    """The value ``label`` (value or table name) means in a label map, checked."""
    path = names.path
    present = sorted(names.present)
    listing = _short_list(present) if present else "none (the label map is empty)"
    if _is_int(label):
        value = int(label)
        low, high = names.value_range
        if names.pixel_type and not low <= value <= high:
            raise InputError(
                f"Label {value} cannot be in the label map {path}: its voxels are "
                f"{names.pixel_type} ({low} to {high}). Labels present: {listing}.")
        if value == 0:
            raise InputError(f"Label 0 is the background of the label map {path}, not a "
                             f"segment. Labels present: {listing}.")
    else:
        value = _value_of_name(names, label)
    if value not in names.present:
        if present:
            raise InputError(f"Label {value} is not in the label map {path}; labels present: "
                             f"{listing}.")
        raise EmptySegmentError(f"Label map {path} has no voxel with label {value} "
                                "(the label map is empty).")
    return value


def _value_of_name(names: LabelNames, label: str) -> int:
    by_name: Dict[str, List[int]] = {}
    source = names.table or dict(names)
    for value, name in source.items():
        by_name.setdefault(str(name).lower(), []).append(value)
    values = by_name.get(label.lower())
    if not values:
        present = sorted(names.present)
        if names.table:
            hint = f" Names in the labels table: {', '.join(names.table.values())}."
        elif names.table_error:
            hint = f" The labels table beside it cannot be used: {names.table_error}."
        else:
            hint = " A name can be used when a labels.csv (value,name) is beside the file."
        raise InputError(f"'{label}' is not a label value of the label map {names.path}; "
                         f"values present: {_short_list(present)}.{hint}")
    if len(values) > 1:
        raise InputError(f"'{label}' names {len(values)} labels ({_short_list(sorted(values))}) "
                         f"in the labels table of {names.path}; give the label value instead.")
    return values[0]


def _label_names_beside(path: str) -> Tuple[dict, str]:
    """(value -> name, problem) from labels.csv or <stem>.csv beside a label map.

    ``problem`` says why a table that is there could not be read ("" when fine or absent).
    """
    folder = os.path.dirname(os.path.abspath(path))
    stem = os.path.basename(path)[: -len(_extension(path))] if _extension(path) else path
    for candidate in (os.path.join(folder, stem + ".csv"), os.path.join(folder, "labels.csv")):
        if not os.path.isfile(candidate):
            continue
        try:
            with open(candidate, newline="", encoding="utf-8-sig") as f:
                rows = list(csv.DictReader(f))
            table = {}
            for number, row in enumerate(rows, start=2):
                value, name = (row.get("value") or "").strip(), (row.get("name") or "").strip()
                if not value and not name:
                    continue
                if not _is_int(value) or not name:
                    return {}, (f"{candidate} line {number} has value '{value}' and name "
                                f"'{name}' (columns value,name; value an integer)")
                table[int(value)] = name
            return table, ""
        except (OSError, UnicodeDecodeError, csv.Error) as exc:
            return {}, f"{candidate}: {exc}"
    return {}, ""


# ----------------------------------------------------------------------------------------
# Slicer segmentations

def _match_segment(segments: list, label: str, path: str) -> dict:
    """The one segment ``label`` names (name, ID, name in any case, label value)."""
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
    return matches[0]


def _empty_segment(name: str, path: str) -> EmptySegmentError:
    return EmptySegmentError(f"Segment '{name}' in {path} has no voxel. Pick a segment "
                             "that is painted, or paint this one first.")


def _merge_segmentation(image: sitk.Image, path: str) -> Tuple[sitk.Image, LabelNames]:
    segments = slicer_segments(image, path)
    if not segments:
        raise InputError(f"{path} holds no segment (no Segment0_ID in its header).")
    layers = _layer_arrays(image, path)
    file_values = [s["label_value"] for s in segments]
    renumber = len(set(file_values)) != len(file_values)
    for seg in segments:
        seg["value"] = seg["index"] + 1 if renumber else seg["label_value"]
    high = max(s["value"] for s in segments)
    dtype = np.uint16 if high <= UINT16_MAX else np.uint32
    merged = np.zeros(layers[0].shape, dtype)
    by_value = {s["value"]: s for s in segments}
    overlaps: Dict[Tuple[int, int], int] = {}
    flat_merged = merged.reshape(-1)
    for k, layer in enumerate(layers):
        mapping = {s["label_value"]: s["value"] for s in segments if s["layer"] == k}
        if not mapping:
            continue
        flat = layer.reshape(-1)
        for i in range(0, flat.size, CHUNK_VOXELS):
            mapped = _map_values(flat[i:i + CHUNK_VOXELS], mapping, dtype)
            target = flat_merged[i:i + CHUNK_VOXELS]
            clash = (mapped != 0) & (target != 0)
            if clash.any():
                pairs, counts = np.unique(np.stack([target[clash], mapped[clash]]), axis=1,
                                          return_counts=True)
                for (a, b), count in zip(pairs.T, counts):
                    key = (by_value[int(a)]["index"], by_value[int(b)]["index"])
                    overlaps[key] = overlaps.get(key, 0) + int(count)
            np.copyto(target, mapped, where=mapped != 0)
    if overlaps:
        raise _overlap_error(overlaps, segments, path)
    present = [int(v) for v in _present_values(merged)]
    labels = _on_grid_of(merged, image)
    dtype_in = _pixel_dtype(image)
    names = LabelNames({s["value"]: s["name"] for s in segments}, path=path,
                       kind="segmentation", present=present, pixel_type=dtype_in.name,
                       value_range=_type_range(dtype_in), segments=segments)
    return labels, names


def _overlap_error(overlaps: dict, segments: list, path: str) -> InputError:
    pairs = sorted(overlaps.items(), key=lambda item: -item[1])
    shown = "; ".join(f"'{segments[a]['name']}' and '{segments[b]['name']}' share {n} "
                      f"voxel{'s' if n != 1 else ''}" for (a, b), n in
                      pairs[:OVERLAP_PAIRS_SHOWN])
    more = (f" (and {len(pairs) - OVERLAP_PAIRS_SHOWN} more pairs)"
            if len(pairs) > OVERLAP_PAIRS_SHOWN else "")
    return InputError(
        f"Segments of {path} overlap: {shown}{more}. A voxel can belong to one bone only. In "
        "3D Slicer make them disjoint (Segment Editor: Logical operators > Subtract, or paint "
        "with Masking > 'Overwrite other segments'), save, and run again; or leave one of "
        "each pair out.")


def _n_layers(image: sitk.Image) -> int:
    ncomp = image.GetNumberOfComponentsPerPixel()
    if image.GetDimension() == 3:
        return ncomp
    if image.GetDimension() == 4 and ncomp == 1:
        return image.GetSize()[0]
    return 0


def _layer_arrays(image: sitk.Image, path: str) -> list:
    """The (z, y, x) label layers of a segmentation image.

    Slicer writes several layers as a 4-D NRRD whose first axis (kind "list") is the layer;
    ITK reads that as a vector image with one component per layer. A plain 4-D scalar image
    with the layer on its first axis is handled too.
    """
    ncomp = image.GetNumberOfComponentsPerPixel()
    array = sitk.GetArrayViewFromImage(image)
    if array.dtype.kind not in "iub":
        raise VolumeTypeError(f"{path} has {array.dtype.name} voxels; a segmentation holds "
                              "integer label values. Re-save it in 3D Slicer.")
    if image.GetDimension() == 3 and ncomp == 1:
        return [array]
    if image.GetDimension() == 3:
        return [array[..., k] for k in range(ncomp)]
    if image.GetDimension() == 4 and ncomp == 1:
        return [array[..., k] for k in range(array.shape[3])]
    raise VolumeTypeError(f"{path} is a {image.GetDimension()}-D image with {ncomp} "
                          "components; expected a 3-D segmentation.")


def _map_values(values: np.ndarray, mapping: dict, dtype) -> np.ndarray:
    """``values`` with each key of ``mapping`` replaced by its value, everything else 0."""
    out = np.zeros(values.shape, dtype)
    if values.dtype.kind == "u" and values.dtype.itemsize <= 2:
        table = np.zeros(np.iinfo(values.dtype).max + 1, dtype)
        for old, new in mapping.items():
            table[old] = new
        return table[values]
    for old, new in mapping.items():
        out[values == old] = new
    return out


def _on_grid_of(array: np.ndarray, image: sitk.Image) -> sitk.Image:
    """A 3-D image of the (z, y, x) ``array`` with the spatial geometry of ``image``.

    A 4-D scalar segmentation has its layer on the first ITK axis: the last three axes are
    the spatial ones.
    """
    out = sitk.GetImageFromArray(array)
    dim = image.GetDimension()
    axes = slice(1, 4) if dim == 4 else slice(0, 3)
    out.SetOrigin(image.GetOrigin()[axes])
    out.SetSpacing(image.GetSpacing()[axes])
    out.SetDirection(tuple(np.array(image.GetDirection()).reshape(dim, dim)[axes, axes].ravel()))
    return out


# ----------------------------------------------------------------------------------------
# small helpers

def _pixel_dtype(image: sitk.Image) -> np.dtype:
    """numpy dtype of one voxel component of ``image`` (without reading the voxels)."""
    ids = {sitk.sitkUInt8: np.uint8, sitk.sitkInt8: np.int8, sitk.sitkUInt16: np.uint16,
           sitk.sitkInt16: np.int16, sitk.sitkUInt32: np.uint32, sitk.sitkInt32: np.int32,
           sitk.sitkUInt64: np.uint64, sitk.sitkInt64: np.int64, sitk.sitkFloat32: np.float32,
           sitk.sitkFloat64: np.float64}
    vector = {sitk.sitkVectorUInt8: np.uint8, sitk.sitkVectorInt8: np.int8,
              sitk.sitkVectorUInt16: np.uint16, sitk.sitkVectorInt16: np.int16,
              sitk.sitkVectorUInt32: np.uint32, sitk.sitkVectorInt32: np.int32,
              sitk.sitkVectorUInt64: np.uint64, sitk.sitkVectorInt64: np.int64,
              sitk.sitkVectorFloat32: np.float32, sitk.sitkVectorFloat64: np.float64}
    pixel = image.GetPixelID()
    return np.dtype(ids.get(pixel) or vector.get(pixel) or np.float64)


def _type_range(dtype: np.dtype) -> Tuple[int, int]:
    """(lowest, highest) integer a voxel of ``dtype`` can hold (exact integers for floats)."""
    if dtype.kind in "iu":
        info = np.iinfo(dtype)
        return int(info.min), int(info.max)
    digits = np.finfo(dtype).nmant + 1
    return -(2 ** digits), 2 ** digits


def _header_int(text: str, key: str, path: str) -> int:
    """An integer header value (``7`` or ``7.0``), or InputError naming the key."""
    text = str(text).strip()
    try:
        number = float(text)
    except ValueError:
        number = float("nan")
    if not np.isfinite(number) or not number.is_integer():
        raise InputError(f"{path} is damaged: {key} is '{text}', not an integer. Re-save the "
                         "segmentation in 3D Slicer, or correct that line of its header.")
    return int(number)


def _is_int(text: str) -> bool:
    return re.fullmatch(r"[+-]?\d+", str(text).strip()) is not None
