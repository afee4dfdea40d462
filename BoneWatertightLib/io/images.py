"""Reading CT volumes: any SimpleITK file format or a DICOM folder, validated as a scalar 3-D CT.

Images keep SimpleITK's conventions: physical LPS coordinates, ``GetArrayFromImage`` gives
(z, y, x) arrays.

Before SimpleITK reads a NRRD or MetaImage file, the size its header promises is compared with
the data the file holds (:func:`check_payload_size`): SimpleITK silently reads a volume cut
short when the header promises fewer slices than the data holds. A DICOM series is checked to
be one stack (one orientation, image size and pixel spacing; distinct, evenly spaced slice
positions) and a CT to have only finite voxels (:func:`check_finite`).
"""

from __future__ import annotations

import os
import zlib
from typing import Optional

import numpy as np
import SimpleITK as sitk

from ..errors import InputError, VolumeTypeError
from .files import PathLike

# Integer volumes with no negative value and fewer distinct values than LABEL_MAP_FEW are label
# maps, not CT. Up to LABEL_MAP_MANY values they are label maps when 0 (background) is the most
# frequent value: multi-organ label maps (TotalSegmentator: up to 117 classes) look like that,
# while a noisy CT crop without air can have ~100 distinct values but is never mostly exact 0.
LABEL_MAP_FEW = 16
LABEL_MAP_MANY = 256


# ----------------------------------------------------------------------------------------
# CT volumes

def dicom_series(folder: PathLike) -> dict:
    """Series instance UID -> sorted file names of every DICOM series directly in ``folder``."""
    folder = os.fspath(folder)
    reader = sitk.ImageSeriesReader()
    series = {}
    for uid in reader.GetGDCMSeriesIDs(folder) or ():
        series[uid] = list(reader.GetGDCMSeriesFileNames(folder, uid))
    return series


def read_ct(path: PathLike, series: Optional[str] = None) -> sitk.Image:
    """Read a CT volume (HU) from any SimpleITK file or a DICOM folder.

    ``series`` picks one series instance UID when a DICOM folder holds several; without it
    such a folder is refused (naming the series) rather than guessing which one is the CT.

    Raises
    ------
    InputError
        A missing or unreadable input; a file whose header disagrees with its data size; a
        DICOM series made of several stacks (mixed orientations, image sizes or pixel
        spacings, duplicate or unevenly spaced slice positions); voxels that are NaN or
        infinite (their count and the first one's index).
    VolumeTypeError
        Anything that is not a scalar 3-D grayscale volume (a label map, RGB, complex, 2-D,
        4-D).
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputError(f"CT not found: {path}")
    if os.path.isdir(path):
        image = _read_dicom_folder(path, series)
    else:
        image = _read_image_file(path, "CT")
    return _validate_ct(image, path)


def _read_image_file(path: str, what: str) -> sitk.Image:
    check_payload_size(path, what)
    try:
        return sitk.ReadImage(path)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        detail = next((line for line in first if "ERROR" in line or "Could not" in line), "")
        raise InputError(
            f"Cannot read the {what} file {path}: not an image format SimpleITK can read "
            f"(NRRD, NIfTI, MHA, ...). {detail}".strip()
        ) from None


def _read_dicom_folder(folder: str, series: Optional[str]) -> sitk.Image:
    found = dicom_series(folder)
    if not found:
        raise InputError(
            f"No DICOM series found in folder {folder}. Give the folder that directly holds the "
            "slice files of one CT series, or a volume file (NRRD, NIfTI, MHA)."
        )
    if series is not None:
        if series not in found:
            raise InputError(f"DICOM series {series} is not in {folder}. Series there: "
                             + _describe_series(found))
        uid = series
    elif len(found) > 1:
        raise InputError(
            f"Folder {folder} holds {len(found)} DICOM series: {_describe_series(found)}. "
            "Choose one with --ct-series UID (or move its files to a folder of their own)."
        )
    else:
        uid = next(iter(found))
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(found[uid])
    reader.MetaDataDictionaryArrayUpdateOn()
    # ITK's own "non uniform sampling" warning goes to stderr; the stack check below says
    # what is wrong instead.
    warnings = sitk.ProcessObject.GetGlobalWarningDisplay()
    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    try:
        image = reader.Execute()
    except RuntimeError as exc:
        # Usually slices of different sizes; say which, rather than ITK's raw sizes.
        _check_dicom_stack(uid, folder, found[uid], [_dicom_tags(f) for f in found[uid]])
        raise InputError(f"Cannot read DICOM series {uid} in {folder}: "
                         f"{str(exc).strip().splitlines()[-1]}") from None
    finally:
        sitk.ProcessObject.SetGlobalWarningDisplay(warnings)
    tags = [{key: reader.GetMetaData(k, key) for key in _DICOM_KEYS
             if reader.HasMetaDataKey(k, key)} for k in range(len(found[uid]))]
    _check_dicom_stack(uid, folder, found[uid], tags)
    return image


# DICOM tags of one slice that must agree within one stack.
_ORIENTATION, _POSITION, _PIXEL_SPACING = "0020|0037", "0020|0032", "0028|0030"
_ROWS, _COLUMNS = "0028|0010", "0028|0011"
_DICOM_KEYS = (_ORIENTATION, _POSITION, _PIXEL_SPACING, _ROWS, _COLUMNS)
# Two slices closer than this (mm, along the slice normal) are at the same position.
DICOM_SAME_POSITION_MM = 0.01
# Slice gaps may differ by this fraction of the median gap (rounding in the headers).
DICOM_GAP_TOLERANCE = 0.1


def _dicom_tags(path: str) -> dict:
    reader = sitk.ImageFileReader()
    reader.SetFileName(path)
    try:
        reader.ReadImageInformation()
    except RuntimeError:
        return {}
    return {key: reader.GetMetaData(key) for key in _DICOM_KEYS if reader.HasMetaDataKey(key)}


def _numbers(text: str) -> Optional[tuple]:
    try:
        return tuple(float(v) for v in str(text).replace("\\", " ").split())
    except ValueError:
        return None


def _check_dicom_stack(uid: str, folder: str, files: list, tags: list) -> None:
    """InputError unless the slices of one series form one evenly spaced stack."""
    names = [os.path.basename(f) for f in files]
    where = f"DICOM series {uid} in {folder}"
    fix = ("One series UID holds several stacks here (e.g. two reconstructions or "
           "acquisitions); move the files of each stack into a folder of their own and give "
           "that folder as --ct.")

    def groups(key, describe, rounding):
        found = {}
        for name, tag in zip(names, tags):
            values = _numbers(tag.get(key, ""))
            if values is None or not values:
                continue
            found.setdefault(tuple(round(v / rounding) * rounding for v in values), []).append(
                name)
        if len(found) > 1:
            parts = [f"{len(members)} slices with {describe(value)} (e.g. {members[0]})"
                     for value, members in sorted(found.items(), key=lambda kv: -len(kv[1]))]
            raise InputError(f"{where} mixes slices of {len(found)} different "
                             f"{key_names[key]}: " + "; ".join(parts) + f". {fix}")

    key_names = {_ORIENTATION: "orientations", _ROWS: "image sizes",
                 _PIXEL_SPACING: "pixel spacings"}
    sizes = [(tag.get(_ROWS, "").strip(), tag.get(_COLUMNS, "").strip()) for tag in tags]
    for tag, (rows, cols) in zip(tags, sizes):
        if rows and cols:
            tag[_ROWS] = f"{cols} {rows}"
    groups(_ROWS, lambda v: "x".join(str(int(x)) for x in v) + " pixels", 1.0)
    groups(_ORIENTATION, lambda v: "row/column directions (" + ", ".join(f"{x:g}" for x in v)
           + ")", 1e-4)
    groups(_PIXEL_SPACING, lambda v: "pixel spacing (row, column) "
           + " x ".join(f"{x:g}" for x in v) + " mm", 1e-4)

    orientation = _numbers(tags[0].get(_ORIENTATION, "")) if tags else None
    positions = [_numbers(tag.get(_POSITION, "")) for tag in tags]
    if (orientation is None or len(orientation) != 6 or len(files) < 2
            or any(p is None or len(p) != 3 for p in positions)):
        return  # no geometry in the headers: nothing more to check
    normal = np.cross(orientation[:3], orientation[3:])
    depth = np.array(positions) @ normal
    order = np.argsort(depth, kind="stable")
    gaps = np.diff(depth[order])
    same = np.flatnonzero(gaps < DICOM_SAME_POSITION_MM)
    if same.size:
        a, b = names[order[same[0]]], names[order[same[0] + 1]]
        raise InputError(
            f"{where} has {same.size} slice{'s' if same.size > 1 else ''} at a position another "
            f"slice already has (e.g. {a} and {b}, both at {depth[order[same[0]]]:.2f} mm along "
            f"the slice normal): duplicated files or a second stack. {fix}")
    median = float(np.median(gaps))
    if gaps.max() - gaps.min() > DICOM_GAP_TOLERANCE * median:
        k = int(np.argmax(np.abs(gaps - median)))
        raise InputError(
            f"{where} has unevenly spaced slices: gaps from {gaps.min():.3g} to "
            f"{gaps.max():.3g} mm (median {median:.3g} mm); the gap between "
            f"{names[order[k]]} and {names[order[k + 1]]} is {gaps[k]:.3g} mm. Slices are "
            "missing, or two stacks share the series UID. Add the missing slices, or move "
            "each stack into a folder of its own.")


def _describe_series(found: dict) -> str:
    return "; ".join(f"{uid} ({len(files)} files)" for uid, files in
                     sorted(found.items(), key=lambda item: -len(item[1])))


def _validate_ct(image: sitk.Image, path: str) -> sitk.Image:
    ncomp = image.GetNumberOfComponentsPerPixel()
    if image.GetPixelID() in (sitk.sitkComplexFloat32, sitk.sitkComplexFloat64):
        raise VolumeTypeError(
            f"{path} is a complex-valued image (e.g. k-space or a Fourier transform), not a CT. "
            "Give the grayscale CT volume in Hounsfield units.")
    if ncomp == 1 and image.GetPixelIDTypeAsString().startswith("vector"):
        # A one-component vector image holds exactly a scalar image.
        image = sitk.VectorIndexSelectionCast(image, 0)
    if ncomp > 1:
        raise VolumeTypeError(
            f"{path} is a {ncomp}-component (RGB or vector) image, not a CT. Give the grayscale "
            "CT volume in Hounsfield units."
        )
    dim = image.GetDimension()
    if dim == 4:
        if image.GetSize()[3] != 1:
            raise VolumeTypeError(
                f"{path} is a 4-D image ({'x'.join(map(str, image.GetSize()))}), e.g. a time "
                "series. Extract the one 3-D CT frame you want and give that."
            )
        image = _drop_last_axis(image)
        dim = 3
    if dim != 3 or min(image.GetSize()) < 2:
        raise VolumeTypeError(
            f"{path} is a 2-D image ({'x'.join(map(str, image.GetSize()))}); a 3-D CT volume "
            "is needed. For DICOM, give the folder holding all slices of the series."
        )
    if _looks_like_label_map(image):
        values = np.unique(sitk.GetArrayViewFromImage(image))
        raise VolumeTypeError(
            f"{path} looks like a label map (integer values {_short_list(values)}), not a CT. "
            "Give the CT volume as --ct and the label map as --seg."
        )
    check_finite(image, f"The CT {path}")
    return image


def check_finite(image: sitk.Image, what: str = "The CT") -> None:
    """InputError when ``image`` has NaN or infinite voxels: how many, and the first one.

    Integer images are finite by construction and cost nothing. ``what`` starts the message
    (e.g. "The CT ct.nrrd").
    """
    if image.GetPixelID() not in (sitk.sitkFloat32, sitk.sitkFloat64, sitk.sitkVectorFloat32,
                                  sitk.sitkVectorFloat64):
        return
    array = sitk.GetArrayViewFromImage(image)
    bad = ~np.isfinite(array)
    count = int(np.count_nonzero(bad))
    if count == 0:
        return
    n_nan = int(np.count_nonzero(np.isnan(array)))
    flat = int(np.flatnonzero(bad.ravel())[0])
    zyx = np.unravel_index(flat, array.shape)
    index = tuple(int(v) for v in zyx[:image.GetDimension()][::-1])
    point = image.TransformIndexToPhysicalPoint(index)
    kinds = ", ".join(part for part in (f"{n_nan} NaN" if n_nan else "",
                                        f"{count - n_nan} infinite" if count > n_nan else "")
                      if part)
    raise InputError(
        f"{what} has {count} voxel{'s' if count > 1 else ''} that {'are' if count > 1 else 'is'}"
        f" not a number ({kinds}); the first at voxel index (i, j, k) = {index}, LPS "
        f"({', '.join(f'{v:.1f}' for v in point)}) mm. Replace them with a value in HU (e.g. "
        "-1000 for air outside the scanned field) where the volume was made, or crop them away.")


def _looks_like_label_map(image: sitk.Image) -> bool:
    if image.GetPixelID() not in (sitk.sitkUInt8, sitk.sitkInt8, sitk.sitkUInt16,
                                  sitk.sitkInt16, sitk.sitkUInt32, sitk.sitkInt32,
                                  sitk.sitkUInt64, sitk.sitkInt64):
        return False
    stats = sitk.MinimumMaximumImageFilter()
    stats.Execute(image)
    # CT in HU has air near -1000: a negative minimum settles it without a full np.unique.
    if stats.GetMinimum() < 0:
        return False
    if stats.GetMaximum() - stats.GetMinimum() > 10000:
        return False
    values, counts = np.unique(sitk.GetArrayViewFromImage(image), return_counts=True)
    if len(values) < LABEL_MAP_FEW:
        return True
    return len(values) <= LABEL_MAP_MANY and values[np.argmax(counts)] == 0


def _drop_last_axis(image: sitk.Image) -> sitk.Image:
    size = list(image.GetSize())
    size[3] = 0
    return sitk.Extract(image, size, [0, 0, 0, 0])


# ----------------------------------------------------------------------------------------
# header size against data size

# Bytes per voxel of the NRRD types (every spelling the format allows) and MetaImage types.
_NRRD_TYPES = {}
for _size, _names in (
        (1, "signed char, int8, int8_t, uchar, unsigned char, uint8, uint8_t"),
        (2, "short, short int, signed short, signed short int, int16, int16_t, ushort, "
            "unsigned short, unsigned short int, uint16, uint16_t"),
        (4, "int, signed int, int32, int32_t, uint, unsigned int, uint32, uint32_t, float"),
        (8, "longlong, long long, long long int, signed long long, signed long long int, "
            "int64, int64_t, ulonglong, unsigned long long, unsigned long long int, uint64, "
            "uint64_t, double")):
    _NRRD_TYPES.update({name.strip(): _size for name in _names.split(",")})
_MET_TYPES = {"MET_CHAR": 1, "MET_UCHAR": 1, "MET_SHORT": 2, "MET_USHORT": 2, "MET_INT": 4,
              "MET_UINT": 4, "MET_LONG_LONG": 8, "MET_ULONG_LONG": 8, "MET_FLOAT": 4,
              "MET_DOUBLE": 8}
# Most header bytes read when looking for the end of a header.
_HEADER_LIMIT = 1 << 20


def check_payload_size(path: str, what: str = "image") -> None:
    """InputError when a NRRD or MetaImage header promises more or fewer voxels than the data.

    SimpleITK reads a file whose header promises fewer slices than its data holds without a
    word (the volume is silently cut short), and one that promises more with a low-level
    message. Checked: NRRD (``.nrrd`` and detached ``.nhdr``) with raw or gzip encoding and
    MetaImage (``.mha``/``.mhd``) without compression, each with a single data file. Other
    encodings and layouts are left to SimpleITK.
    """
    low = path.lower()
    try:
        if low.endswith((".nrrd", ".nhdr")):
            found = _nrrd_payload(path)
        elif low.endswith((".mha", ".mhd")):
            found = _metaimage_payload(path)
        else:
            return
    except (OSError, ValueError, zlib.error):
        return  # unreadable here: SimpleITK will say why
    if found is None:
        return
    sizes, voxel_bytes, actual = found
    expected = int(np.prod(sizes, dtype=np.int64)) * voxel_bytes
    if actual == expected:
        return
    dims = "x".join(str(n) for n in sizes)
    slice_bytes = int(np.prod(sizes[:-1], dtype=np.int64)) * voxel_bytes
    held = actual / slice_bytes if slice_bytes else 0.0
    held_text = f"{held:.0f}" if float(held).is_integer() else f"{held:.2f}"
    if actual < expected:
        raise InputError(
            f"The {what} file {path} is truncated: its header promises {dims} voxels "
            f"({expected} bytes) but it holds {actual} bytes of data, {held_text} of "
            f"{sizes[-1]} slices (an interrupted copy or download?). Copy or export the "
            "volume again.")
    raise InputError(
        f"The {what} file {path} holds more data than its header says: the header promises "
        f"{dims} voxels ({expected} bytes, {sizes[-1]} slices) but the file holds {actual} "
        f"bytes ({held_text} slices), so the volume would be read cut short. Fix the sizes "
        "in the header to match the data, or export the volume again.")


def _header_lines(path: str):
    """(lines, offset of the data) of a text header that ends at its first empty line."""
    with open(path, "rb") as f:
        head = f.read(_HEADER_LIMIT)
    lines, offset = [], 0
    for raw in head.splitlines(keepends=True):
        offset += len(raw)
        line = raw.decode("latin-1").rstrip("\r\n")
        if not line:
            return lines, offset
        lines.append(line)
    return lines, (offset if len(head) < _HEADER_LIMIT else None)


def _nrrd_payload(path: str):
    """(sizes, bytes per voxel, bytes of data) of a NRRD file, or None when not checked."""
    lines, offset = _header_lines(path)
    if not lines or not lines[0].startswith("NRRD"):
        return None
    fields = {}
    for line in lines[1:]:
        if line.startswith("#") or ":=" in line or ":" not in line:
            continue
        key, value = line.split(":", 1)
        fields[key.strip().lower().replace(" ", "")] = value.strip()
    sizes = [int(v) for v in fields.get("sizes", "").split()]
    voxel_bytes = _NRRD_TYPES.get(fields.get("type", "").lower())
    encoding = fields.get("encoding", "").lower()
    skips = (fields.get("lineskip", "0"), fields.get("byteskip", "0"))
    if not sizes or voxel_bytes is None or encoding not in ("raw", "gzip", "gz") \
            or any(v.strip() != "0" for v in skips):
        return None
    data_file = fields.get("datafile")
    if data_file is not None:
        if data_file.upper().startswith("LIST") or len(data_file.split()) > 1 or "%" in data_file:
            return None  # several data files
        data_path = os.path.join(os.path.dirname(os.path.abspath(path)), data_file)
        start = 0
    elif offset is None:
        return None
    else:
        data_path, start = path, offset
    if encoding == "raw":
        return sizes, voxel_bytes, os.path.getsize(data_path) - start
    return sizes, voxel_bytes, _gzip_size(data_path, start, voxel_bytes * int(np.prod(sizes)))


def _gzip_size(path: str, start: int, expected: int) -> int:
    """Uncompressed size of the gzip data from ``start`` to the end of ``path``."""
    with open(path, "rb") as f:
        f.seek(0, os.SEEK_END)
        end = f.tell()
        if end - start >= 18:
            f.seek(end - 4)
            # The last member's ISIZE (size mod 2**32): the common single-member case.
            if int.from_bytes(f.read(4), "little") == expected % (1 << 32):
                return expected
        f.seek(start)
        total = 0
        stream = zlib.decompressobj(wbits=31)
        for chunk in iter(lambda: f.read(1 << 22), b""):
            while chunk:
                total += len(stream.decompress(chunk))
                if not stream.eof:
                    break
                # A further gzip member may follow.
                chunk, stream = stream.unused_data, zlib.decompressobj(wbits=31)
        return total


def _metaimage_payload(path: str):
    """(sizes, bytes per voxel, bytes of data) of a MetaImage file, or None when not checked."""
    with open(path, "rb") as f:
        head = f.read(_HEADER_LIMIT)
    fields, offset = {}, None
    position = 0
    for raw in head.splitlines(keepends=True):
        position += len(raw)
        line = raw.decode("latin-1").strip()
        if "=" not in line:
            continue
        key, value = (part.strip() for part in line.split("=", 1))
        fields[key] = value
        if key == "ElementDataFile":
            offset = position
            break
    if offset is None or fields.get("CompressedData", "False").lower() == "true":
        return None
    sizes = [int(v) for v in fields.get("DimSize", "").split()]
    voxel_bytes = _MET_TYPES.get(fields.get("ElementType", ""))
    if not sizes or voxel_bytes is None or fields.get("HeaderSize", "0") != "0":
        return None
    voxel_bytes *= int(fields.get("ElementNumberOfChannels", "1"))
    data_file = fields["ElementDataFile"]
    if data_file == "LOCAL":
        return sizes, voxel_bytes, os.path.getsize(path) - offset
    if data_file.upper().startswith("LIST") or len(data_file.split()) > 1 or "%" in data_file:
        return None
    data_path = os.path.join(os.path.dirname(os.path.abspath(path)), data_file)
    return sizes, voxel_bytes, os.path.getsize(data_path)


def _short_list(values, limit: int = 20) -> str:
    values = [int(v) if float(v).is_integer() else float(v) for v in values]
    text = ", ".join(str(v) for v in values[:limit])
    if len(values) > limit:
        text += f", ... ({len(values)} in all)"
    return text

