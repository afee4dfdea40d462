"""Reading CT volumes: any SimpleITK file format or a DICOM folder, validated as a scalar 3-D CT.

Images keep SimpleITK's conventions: physical LPS coordinates, ``GetArrayFromImage`` gives
(z, y, x) arrays.
"""

from __future__ import annotations

import os
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
    Raises InputError for a missing or unreadable input and VolumeTypeError for anything that
    is not a scalar 3-D grayscale volume.
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
    try:
        return reader.Execute()
    except RuntimeError as exc:
        raise InputError(f"Cannot read DICOM series {uid} in {folder}: "
                         f"{str(exc).strip().splitlines()[-1]}") from None


def _describe_series(found: dict) -> str:
    return "; ".join(f"{uid} ({len(files)} files)" for uid, files in
                     sorted(found.items(), key=lambda item: -len(item[1])))


def _validate_ct(image: sitk.Image, path: str) -> sitk.Image:
    ncomp = image.GetNumberOfComponentsPerPixel()
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
    return image


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


def _short_list(values, limit: int = 20) -> str:
    values = [int(v) if float(v).is_integer() else float(v) for v in values]
    text = ", ".join(str(v) for v in values[:limit])
    if len(values) > limit:
        text += f", ... ({len(values)} in all)"
    return text

