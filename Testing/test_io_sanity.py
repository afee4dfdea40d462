"""Input sanity: non-finite CT voxels, NRRD/MetaImage headers that disagree with their data,
DICOM series made of several stacks, complex and one-component vector CTs."""

import gzip
import os
import sys

import numpy as np
import pytest
import SimpleITK as sitk

sys.path.insert(0, os.path.abspath(os.path.join(os.path.dirname(__file__), "..")))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from BoneWatertightLib.errors import InputError, VolumeTypeError  # noqa: E402
from BoneWatertightLib.io import check_finite, read_ct, read_segment  # noqa: E402
from test_io import small_ct, write_dicom_series  # noqa: E402


def float_ct(shape=(6, 7, 8)):
    array = np.random.default_rng(3).normal(0.0, 300.0, shape).astype(np.float32)
    image = sitk.GetImageFromArray(array)
    image.SetOrigin((10.0, 20.0, 30.0))
    image.SetSpacing((0.5, 0.5, 2.0))
    return image, array


# ---------------------------------------------------------------------------- non-finite voxels

def test_one_nan_voxel_is_refused_with_its_index(tmp_path):
    """Before: read silently; the pipeline then said 'segment HU range nan to nan'."""
    image, array = float_ct()
    array[5, 4, 3] = np.nan
    bad = sitk.GetImageFromArray(array)
    bad.CopyInformation(image)
    sitk.WriteImage(bad, str(tmp_path / "ct.nrrd"))
    with pytest.raises(InputError) as info:
        read_ct(str(tmp_path / "ct.nrrd"))
    text = str(info.value)
    assert "has 1 voxel that is not a number (1 NaN)" in text
    assert "voxel index (i, j, k) = (3, 4, 5)" in text
    assert "LPS (11.5, 22.0, 40.0) mm" in text and "-1000" in text


def test_nan_and_inf_are_counted(tmp_path):
    image, array = float_ct()
    array[0, 0, 2] = np.inf
    array[1, 2, 3] = np.nan
    array[4, 4, 4] = -np.inf
    bad = sitk.GetImageFromArray(array.astype(np.float64))
    sitk.WriteImage(bad, str(tmp_path / "ct.mha"))
    with pytest.raises(InputError, match=r"has 3 voxels that are not a number \(1 NaN, 2 "
                                         r"infinite\); the first at voxel index \(i, j, k\) = "
                                         r"\(2, 0, 0\)"):
        read_ct(str(tmp_path / "ct.mha"))


def test_finite_float_and_integer_cts_pass(tmp_path):
    image, _ = float_ct()
    check_finite(image)
    check_finite(small_ct())
    sitk.WriteImage(image, str(tmp_path / "ct.nrrd"))
    np.testing.assert_array_equal(sitk.GetArrayFromImage(read_ct(str(tmp_path / "ct.nrrd"))),
                                  sitk.GetArrayFromImage(image))


# ---------------------------------------------------------------------------- header vs data

def write_nrrd(path, header_slices, data_slices, encoding="raw", detached=False):
    data = np.arange(4 * 5 * data_slices, dtype=np.int16).reshape(data_slices, 5, 4) - 1000
    header = ("NRRD0004\ntype: short\ndimension: 3\nspace: left-posterior-superior\n"
              f"sizes: 4 5 {header_slices}\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n"
              "kinds: domain domain domain\nendian: little\n"
              f"encoding: {encoding}\nspace origin: (0,0,0)\n")
    payload = data.tobytes()
    if encoding == "gzip":
        payload = gzip.compress(payload)
    if detached:
        with open(str(path) + ".raw", "wb") as f:
            f.write(payload)
        with open(path, "w") as f:
            f.write(header + f"data file: {os.path.basename(str(path))}.raw\n")
    else:
        with open(path, "wb") as f:
            f.write((header + "\n").encode() + payload)
    return str(path)


LAYOUTS = [("raw", False, ".nrrd"), ("gzip", False, ".nrrd"), ("raw", True, ".nhdr"),
           ("gzip", True, ".nhdr")]


@pytest.mark.parametrize("encoding, detached, ext", LAYOUTS)
def test_header_promising_fewer_slices_than_the_data(tmp_path, encoding, detached, ext):
    """Before: SimpleITK read 3 of the 5 slices without a word."""
    path = write_nrrd(tmp_path / f"ct{ext}", 3, 5, encoding, detached)
    assert sitk.ReadImage(path).GetSize() == (4, 5, 3)  # what SimpleITK does on its own
    with pytest.raises(InputError, match=r"holds more data than its header says: the header "
                                         r"promises 4x5x3 voxels \(120 bytes, 3 slices\) but "
                                         r"the file holds 200 bytes \(5 slices\)"):
        read_ct(path)


@pytest.mark.parametrize("encoding, detached, ext", LAYOUTS)
def test_header_promising_more_slices_than_the_data(tmp_path, encoding, detached, ext):
    """Before: 'not an image format SimpleITK can read' with teem's fread message."""
    path = write_nrrd(tmp_path / f"ct{ext}", 5, 3, encoding, detached)
    with pytest.raises(InputError, match=r"is truncated: its header promises 4x5x5 voxels "
                                         r"\(200 bytes\) but it holds 120 bytes of data, 3 of 5 "
                                         "slices"):
        read_ct(path)


@pytest.mark.parametrize("encoding, detached, ext", LAYOUTS)
def test_matching_header_reads(tmp_path, encoding, detached, ext):
    path = write_nrrd(tmp_path / f"ct{ext}", 5, 5, encoding, detached)
    assert read_ct(path).GetSize() == (4, 5, 5)


def test_metaimage_header_against_data(tmp_path):
    for slices, data_slices in ((3, 5), (5, 3)):
        data = np.zeros((data_slices, 5, 4), np.int16) - 1000
        header = (f"ObjectType = Image\nNDims = 3\nDimSize = 4 5 {slices}\n"
                  "ElementType = MET_SHORT\nElementSpacing = 1 1 1\nBinaryData = True\n"
                  "BinaryDataByteOrderMSB = False\nElementDataFile = LOCAL\n")
        path = tmp_path / f"ct{slices}{data_slices}.mha"
        path.write_bytes(header.encode() + data.tobytes())
        match = "holds more data than its header" if slices < data_slices else "is truncated"
        with pytest.raises(InputError, match=match):
            read_ct(str(path))


def test_label_map_header_is_checked_too(tmp_path):
    labels = np.zeros((5, 5, 4), np.uint8)
    labels[:, 2, 2] = 1
    header = ("NRRD0004\ntype: unsigned char\ndimension: 3\nsizes: 4 5 4\n"
              "encoding: raw\n\n")
    path = tmp_path / "labels.nrrd"
    path.write_bytes(header.encode() + labels.tobytes())
    with pytest.raises(InputError, match="label map file .* holds more data than its header"):
        read_segment(str(path), 1)


@pytest.mark.parametrize("compress", [False, True])
@pytest.mark.parametrize("ext", [".nrrd", ".nhdr", ".mha", ".mhd"])
def test_files_simpleitk_writes_pass(tmp_path, ext, compress):
    image = small_ct()
    sitk.WriteImage(image, str(tmp_path / f"ct{ext}"), compress)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(read_ct(str(tmp_path / f"ct{ext}"))),
                                  sitk.GetArrayFromImage(image))


# ---------------------------------------------------------------------------- DICOM stacks

@pytest.mark.parametrize("second, message", [
    (dict(angles=(0, 0, 0)), r"mixes slices of 2 different orientations: 8 slices with "
                             r"row/column directions \(.*\) \(e.g. a000.dcm\); 8 slices with "
                             r"row/column directions \(1, 0, 0, 0, 1, 0\) \(e.g. b000.dcm\)"),
    (dict(spacing=(0.5, 0.5, 1.5)), r"mixes slices of 2 different pixel spacings: 8 slices with "
                                    r"pixel spacing \(row, column\) 0.9 x 0.8 mm .*0.5 x 0.5 mm"),
    (dict(size=(14, 10, 8)), r"mixes slices of 2 different image sizes: 8 slices with 12x10 "
                             r"pixels \(e.g. a000.dcm\); 8 slices with 14x10 pixels"),
    (dict(seed=1), r"has 8 slices at a position another slice already has \(e.g. a000.dcm and "
                   r"b000.dcm, both at"),
    (dict(origin=(-40.0, 25.0, 330.0)), r"has unevenly spaced slices: gaps from 1.5 to 8.53 mm "
                                        r"\(median 1.5 mm\); the gap between a007.dcm and "
                                        r"b000.dcm is 8.53 mm"),
])
def test_two_stacks_sharing_a_series_uid(tmp_path, second, message):
    """Before: orientation, spacing, duplicates and gaps were read silently as one volume with
    a wrong slice spacing (0.7 mm instead of 1.5 mm); different sizes gave ITK's raw
    'Size mismatch! The size of ... is [14, 10, 1]'."""
    folder = tmp_path / "dicom"
    write_dicom_series(small_ct(), str(folder), stem="a")
    write_dicom_series(small_ct(**second), str(folder), stem="b")
    with pytest.raises(InputError, match=message) as info:
        read_ct(str(folder))
    assert "move the files of each stack into a folder of their own" in str(info.value) \
        or "into a folder of its own" in str(info.value)


def test_one_stack_with_a_missing_slice(tmp_path):
    folder = tmp_path / "dicom"
    write_dicom_series(small_ct(), str(folder), stem="a")
    os.remove(folder / "a004.dcm")
    with pytest.raises(InputError, match="unevenly spaced slices: gaps from 1.5 to 3 mm.*a003.dcm "
                                         "and a005.dcm is 3 mm. Slices are missing"):
        read_ct(str(folder))


def test_dicom_warning_is_not_printed(tmp_path, capfd):
    folder = tmp_path / "dicom"
    write_dicom_series(small_ct(), str(folder), stem="a")
    write_dicom_series(small_ct(seed=1), str(folder), stem="b")
    with pytest.raises(InputError):
        read_ct(str(folder))
    assert "Non uniform sampling" not in capfd.readouterr().err
    assert sitk.ProcessObject.GetGlobalWarningDisplay()  # restored


# ---------------------------------------------------------------------------- pixel types

def test_complex_ct_is_refused(tmp_path):
    image = sitk.Image([6, 6, 6], sitk.sitkComplexFloat32)
    sitk.WriteImage(image, str(tmp_path / "c.nrrd"))
    with pytest.raises(VolumeTypeError, match="complex-valued image"):
        read_ct(str(tmp_path / "c.nrrd"))


def test_one_component_vector_ct_is_its_scalar(tmp_path):
    values = np.random.default_rng(2).integers(-1000, 2000, 5 * 6 * 7).astype(np.int16)
    header = ("NRRD0004\ntype: short\ndimension: 4\nspace: left-posterior-superior\n"
              "sizes: 1 7 6 5\nspace directions: none (0.7,0,0) (0,0.7,0) (0,0,2)\n"
              "kinds: vector domain domain domain\nendian: little\nencoding: raw\n"
              "space origin: (1,2,3)\n\n")
    path = tmp_path / "v.nrrd"
    path.write_bytes(header.encode() + values.tobytes())
    assert sitk.ReadImage(str(path)).GetPixelIDTypeAsString().startswith("vector")
    ct = read_ct(str(path))
    assert ct.GetPixelID() == sitk.sitkInt16 and ct.GetNumberOfComponentsPerPixel() == 1
    np.testing.assert_array_equal(sitk.GetArrayFromImage(ct).ravel(), values)
    assert ct.GetSpacing() == (0.7, 0.7, 2.0) and ct.GetOrigin() == (1.0, 2.0, 3.0)
