"""Label values and segmentation headers: checked, never cast; the multi-label reader.

Covers :func:`read_segment` (a label value a label map cannot hold is refused instead of being
wrapped to another label), :func:`slicer_segments` (unusable ``.seg.nrrd`` header values are
named), :func:`read_label_image` and :func:`resolve_label` on tiny synthetic files and on the
real files of ``../shared/data`` (those skip when it is absent).
"""

import os
import sys

import numpy as np
import pytest
import SimpleITK as sitk

sys.path.insert(0, os.path.abspath(os.path.join(os.path.dirname(__file__), "..")))

from BoneWatertightLib.errors import EmptySegmentError, InputError, VolumeTypeError  # noqa: E402
from BoneWatertightLib.io import (LabelNames, read_label_image, read_segment,  # noqa: E402
                                  resolve_label)

DATA = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data"))
PELVIS = os.path.join(DATA, "ts_example_ct_abdomen_pelvis_3mm")
AORTA = os.path.join(DATA, "ts_aorta_report_ct_cropped_1p5mm")
SLAB = os.path.join(DATA, "ts_example_ct_dicom_20slices")


def needs_data(path):
    if not os.path.exists(path):
        pytest.skip("../shared/data is not present")
    return path


def label_map(path, array, origin=(1.0, 2.0, 3.0), spacing=(0.5, 0.6, 2.0)):
    image = sitk.GetImageFromArray(array)
    image.SetOrigin(origin)
    image.SetSpacing(spacing)
    sitk.WriteImage(image, str(path))
    return str(path)


def seg_nrrd(path, layers, header, spacing=(1.0, 1.0, 2.0), origin=(5.0, -3.0, 7.0),
             dtype=np.uint8):
    """A Slicer-style .seg.nrrd with the given ``Segment*`` header lines, as written."""
    data = np.stack(layers, axis=-1) if len(layers) > 1 else layers[0]
    nz, ny, nx = layers[0].shape
    ntype = {np.uint8: "unsigned char", np.uint16: "unsigned short"}[dtype]
    lines = ["NRRD0004", f"type: {ntype}", "endian: little"]
    if len(layers) > 1:
        lines += ["dimension: 4", "space: left-posterior-superior",
                  f"sizes: {len(layers)} {nx} {ny} {nz}",
                  f"space directions: none ({spacing[0]},0,0) (0,{spacing[1]},0) "
                  f"(0,0,{spacing[2]})", "kinds: list domain domain domain"]
    else:
        lines += ["dimension: 3", "space: left-posterior-superior", f"sizes: {nx} {ny} {nz}",
                  f"space directions: ({spacing[0]},0,0) (0,{spacing[1]},0) (0,0,{spacing[2]})",
                  "kinds: domain domain domain"]
    lines += ["encoding: raw", f"space origin: ({origin[0]},{origin[1]},{origin[2]})"]
    lines += list(header)
    with open(path, "wb") as f:
        f.write(("\n".join(lines) + "\n\n").encode())
        f.write(np.ascontiguousarray(data, dtype=dtype).tobytes())
    return str(path)


def segment_lines(i, sid, name, value=None, layer=None):
    lines = [f"Segment{i}_ID:={sid}", f"Segment{i}_Name:={name}"]
    if value is not None:
        lines.append(f"Segment{i}_LabelValue:={value}")
    if layer is not None:
        lines.append(f"Segment{i}_Layer:={layer}")
    return lines


@pytest.fixture()
def uint8_map(tmp_path):
    labels = np.zeros((4, 5, 6), np.uint8)
    labels[1:3, 1:3, 1:3] = 1
    labels[2:4, 3:5, 3:6] = 2
    return label_map(tmp_path / "labels.nrrd", labels), labels


# ---------------------------------------------------------------------------- label values

@pytest.mark.parametrize("label", [257, "256", 513, -1, 70000])
def test_label_beyond_the_pixel_type_is_refused_not_wrapped(uint8_map, label):
    """Before: 257 selected label 1 (257 mod 256) and 256 the background, exit 0."""
    path, _ = uint8_map
    message = (f"Label {int(label)} cannot be in the label map .*: its voxels are uint8 "
               r"\(0 to 255\)\. Labels present: 1, 2\.")
    with pytest.raises(InputError, match=message):
        read_segment(path, label)
    _, names = read_label_image(path)
    with pytest.raises(InputError, match=message):
        resolve_label(names, label)


def test_background_and_absent_labels(uint8_map):
    path, labels = uint8_map
    with pytest.raises(InputError, match="Label 0 is the background .* Labels present: 1, 2"):
        read_segment(path, 0)
    with pytest.raises(InputError, match="Label 7 is not in the label map .*labels present: 1, 2"):
        read_segment(path, 7)
    mask, name = read_segment(path, "2")
    assert name == "2"
    np.testing.assert_array_equal(sitk.GetArrayFromImage(mask), labels == 2)
    assert mask.GetOrigin() == (1.0, 2.0, 3.0) and mask.GetSpacing() == (0.5, 0.6, 2.0)


def test_wide_label_values_are_kept(tmp_path):
    labels = np.zeros((3, 4, 5), np.int32)
    labels[0, 0, :2] = 300
    labels[2, 3, 4] = 70000
    path = label_map(tmp_path / "wide.nrrd", labels)
    mask, name = read_segment(path, 70000)
    assert name == "70000" and int(sitk.GetArrayViewFromImage(mask).sum()) == 1
    image, names = read_label_image(path)
    assert image.GetPixelID() == sitk.sitkUInt32
    assert dict(names) == {300: "300", 70000: "70000"}
    np.testing.assert_array_equal(sitk.GetArrayFromImage(image), labels)
    # 300 on a uint8 map: refused; on this int32 map it is a label
    assert resolve_label(names, "300") == 300


def test_float_label_map_with_integers_and_with_nan(tmp_path):
    labels = np.zeros((3, 4, 5), np.float32)
    labels[1, 1:3, 1:3] = 5.0
    path = label_map(tmp_path / "float.nrrd", labels)
    image, names = read_label_image(path)
    assert image.GetPixelID() == sitk.sitkUInt16 and dict(names) == {5: "5"}
    labels[2, 3, 4] = np.nan
    path = label_map(tmp_path / "nan.nrrd", labels)
    with pytest.raises(InputError, match=r"1 voxel that is not a number \(1 NaN\).*\(4, 3, 2\)"):
        read_segment(path, 5)


def test_negative_labels_cannot_go_into_a_label_image(tmp_path):
    labels = np.zeros((3, 4, 5), np.int16)
    labels[0, 0, 0] = -4
    labels[1, 1, 1] = 3
    path = label_map(tmp_path / "neg.nrrd", labels)
    with pytest.raises(InputError, match="values from -4 to 3; labels must be 1 to"):
        read_label_image(path)
    # read_segment can still pick the positive one
    assert read_segment(path, 3)[1] == "3"


def test_label_names_table_and_a_broken_one(tmp_path):
    labels = np.zeros((3, 4, 5), np.uint8)
    labels[0] = 75
    labels[2] = 77
    path = label_map(tmp_path / "bones_labels.nrrd", labels)
    (tmp_path / "labels.csv").write_text("value,name,voxels\n75,femur_left,20\n76,femur_right,0\n"
                                         "77,hip_left,20\n")
    image, names = read_label_image(path)
    assert dict(names) == {75: "femur_left", 77: "hip_left"}
    assert names.table[76] == "femur_right"
    assert resolve_label(names, "HIP_LEFT") == 77
    with pytest.raises(InputError, match="Label 76 is not in the label map .*75, 77"):
        resolve_label(names, "femur_right")
    with pytest.raises(InputError, match="'tibia' is not a label value .*Names in the labels "
                                         "table: femur_left, femur_right, hip_left"):
        read_segment(path, "tibia")
    (tmp_path / "labels.csv").write_text("value,name\n75,femur_left\nseventy,hip\n")
    with pytest.raises(InputError, match="labels table beside it cannot be used: .*line 3 has "
                                         "value 'seventy'"):
        read_segment(path, "femur_left")
    assert read_segment(path, 75)[1] == "75"


def test_resolve_label_on_a_plain_dict():
    names = {3: "tibia", 4: "fibula"}
    assert resolve_label(names, "Fibula") == 4
    assert resolve_label(names, 3) == 3
    with pytest.raises(InputError, match="Label 5 is not in"):
        resolve_label(names, 5)
    with pytest.raises(InputError, match="No label given"):
        resolve_label(names, " ")


# ---------------------------------------------------------------------------- .seg.nrrd headers

def one_layer():
    layer = np.zeros((4, 5, 6), np.uint8)
    layer[1:3, 1:4, 1:3] = 7
    layer[3, 4, 5] = 9
    return layer


@pytest.mark.parametrize("value, message", [
    ("abc", "Segment0_LabelValue is 'abc', not an integer"),
    ("7.5", "Segment0_LabelValue is '7.5', not an integer"),
    ("nan", "Segment0_LabelValue is 'nan', not an integer"),
    ("", "Segment0_LabelValue is '', not an integer"),
    ("0", "Segment0_LabelValue of segment 'femur' is 0, which is the background"),
    ("300", r"Segment0_LabelValue of segment 'femur' is 300, but its voxels are uint8 \(0 to "
            r"255\)"),
])
def test_bad_label_value_in_the_header_names_the_key(tmp_path, value, message):
    """Before: int(float('abc')) raised a bare ValueError: 'error: internal error', exit 1."""
    path = seg_nrrd(tmp_path / "bad.seg.nrrd", [one_layer()],
                    segment_lines(0, "S1", "femur", value, 0)
                    + segment_lines(1, "S2", "noise", 9, 0))
    for read in (lambda: read_segment(path, "noise"), lambda: read_label_image(path)):
        with pytest.raises(InputError, match=message):
            read()


@pytest.mark.parametrize("layer, message", [
    ("x", "Segment1_Layer is 'x', not an integer"),
    ("3", r"Segment1_Layer is 3, but the file has 1 layer \(0 to 0\)"),
    ("-1", "Segment1_Layer is -1, but the file has 1 layer"),
    (None, r"Segment1_Layer is missing, so \(as in 3D Slicer\) the segment is in layer 1, but "
           "the file has 1 layer"),
])
def test_bad_or_missing_layer_names_the_key(tmp_path, layer, message):
    path = seg_nrrd(tmp_path / "layer.seg.nrrd", [one_layer()],
                    segment_lines(0, "S1", "femur", 7, 0)
                    + segment_lines(1, "S2", "noise", 9, layer))
    with pytest.raises(InputError, match=message):
        read_segment(path, "femur")
    with pytest.raises(InputError, match=message):
        read_label_image(path)


def test_missing_keys_take_slicers_defaults(tmp_path):
    """No LabelValue: 1; no Layer: the segment's index (3D Slicer's reader does the same)."""
    a = np.zeros((4, 5, 6), np.uint8)
    b = np.zeros_like(a)
    a[0:2] = 1
    b[2:4] = 1
    path = seg_nrrd(tmp_path / "old.seg.nrrd", [a, b],
                    segment_lines(0, "S1", "first") + segment_lines(1, "S2", "second"))
    np.testing.assert_array_equal(sitk.GetArrayFromImage(read_segment(path, "second")[0]), b)
    image, names = read_label_image(path)
    # both have label value 1 (in different layers): renumbered 1, 2 in file order
    assert dict(names) == {1: "first", 2: "second"}
    np.testing.assert_array_equal(sitk.GetArrayFromImage(image), a + 2 * b)


def test_two_segments_with_one_value_in_one_layer(tmp_path):
    path = seg_nrrd(tmp_path / "dup.seg.nrrd", [one_layer()],
                    segment_lines(0, "S1", "femur", 7, 0) + segment_lines(1, "S2", "tibia", 7, 0))
    with pytest.raises(InputError, match=r"'femur' \(Segment0\) and 'tibia' \(Segment1\) both "
                                         "have label value 7 in layer 0"):
        read_label_image(path)


# ---------------------------------------------------------------------------- read_label_image

def test_single_layer_segmentation_keeps_its_label_values(tmp_path):
    layer = one_layer()
    path = seg_nrrd(tmp_path / "tiny.seg.nrrd", [layer],
                    segment_lines(0, "Segment_1", "femur left", 7, 0)
                    + segment_lines(1, "Segment_2", "noise", 9, 0)
                    + segment_lines(2, "Segment_3", "unpainted", 11, 0))
    image, names = read_label_image(path)
    assert isinstance(names, LabelNames) and isinstance(names, dict)
    assert dict(names) == {7: "femur left", 9: "noise", 11: "unpainted"}
    assert names.present == {7, 9} and names.kind == "segmentation"
    assert names.ids == {7: "Segment_1", 9: "Segment_2", 11: "Segment_3"}
    assert image.GetPixelID() == sitk.sitkUInt16
    np.testing.assert_array_equal(sitk.GetArrayFromImage(image), layer)
    assert image.GetOrigin() == (5.0, -3.0, 7.0) and image.GetSpacing() == (1.0, 1.0, 2.0)
    for text in ("femur left", "Segment_1", "FEMUR LEFT", "7", 7):
        assert resolve_label(names, text) == 7
    with pytest.raises(InputError, match="Segment 'tibia' is not in .*Available \\(name / ID / "
                                         "label value\\): femur left / Segment_1 / 7; noise"):
        resolve_label(names, "tibia")
    with pytest.raises(EmptySegmentError, match="'unpainted'.*has no voxel"):
        resolve_label(names, "Segment_3")


def test_two_disjoint_layers_merge_into_one_label_image(tmp_path):
    a = np.zeros((4, 5, 6), np.uint8)
    b = np.zeros_like(a)
    a[0:2, :, :3] = 1
    a[0:2, :, 3:] = 2
    b[2:4, 1:4, 1:4] = 1
    path = seg_nrrd(tmp_path / "layers.seg.nrrd", [a, b],
                    segment_lines(0, "S_a", "bone a", 1, 0)
                    + segment_lines(1, "S_c", "bone c", 2, 0)
                    + segment_lines(2, "S_b", "bone b", 1, 1))
    image, names = read_label_image(path)
    assert dict(names) == {1: "bone a", 2: "bone c", 3: "bone b"}
    expected = np.where(a == 1, 1, 0) + np.where(a == 2, 2, 0) + np.where(b == 1, 3, 0)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(image), expected)
    assert image.GetOrigin() == (5.0, -3.0, 7.0) and image.GetSpacing() == (1.0, 1.0, 2.0)
    assert resolve_label(names, "S_b") == 3
    # label value 1 is in both layers: ambiguous, the message says to use the ID (as before)
    with pytest.raises(InputError, match="matches 2 segments.*segment ID"):
        resolve_label(names, "1")


def test_overlapping_segments_are_refused_with_their_names(tmp_path):
    a = np.zeros((4, 5, 6), np.uint8)
    b = np.zeros_like(a)
    a[1:3, 1:3, 1:3] = 1      # 8 voxels
    b[1:4, 2:4, 2:5] = 1      # shares 2 x 1 x 1 = 2 voxels with a
    path = seg_nrrd(tmp_path / "overlap.seg.nrrd", [a, b],
                    segment_lines(0, "S_a", "femur", 1, 0) + segment_lines(1, "S_b", "hip", 1, 1))
    with pytest.raises(InputError, match="Segments of .* overlap: 'femur' and 'hip' share 2 "
                                         "voxels.*Subtract.*Overwrite other segments"):
        read_label_image(path)
    # one segment alone is fine, even from an overlapping file
    mask, name = read_segment(path, "hip")
    np.testing.assert_array_equal(sitk.GetArrayFromImage(mask), b)


def test_four_d_scalar_segmentation_geometry(tmp_path):
    """A 4-D scalar NRRD (layer on the first axis, kind 'domain'): the layer axis is dropped
    from the geometry, not a spatial one."""
    data = np.zeros((4, 5, 3, 2), np.uint8)  # numpy (z, y, x, layer)
    data[0, 0, 0, 0] = 1
    data[3, 4, 2, 1] = 1
    header = ["NRRD0004", "type: unsigned char", "dimension: 4", "space dimension: 4",
              "sizes: 2 3 5 4", "space directions: (1,0,0,0) (0,0.5,0,0) (0,0,0.7,0) "
              "(0,0,0,2.5)", "kinds: domain domain domain domain", "encoding: raw",
              "space origin: (9,1,2,3)"] + segment_lines(0, "A", "a", 1, 0) \
        + segment_lines(1, "B", "b", 1, 1)
    path = tmp_path / "four.seg.nrrd"
    path.write_bytes(("\n".join(header) + "\n\n").encode() + data.tobytes())
    image, names = read_label_image(str(path))
    assert image.GetSize() == (3, 5, 4)
    assert image.GetSpacing() == (0.5, 0.7, 2.5) and image.GetOrigin() == (1.0, 2.0, 3.0)
    array = sitk.GetArrayFromImage(image)
    assert array[0, 0, 0] == 1 and array[3, 4, 2] == 2 and array.sum() == 3


def test_not_a_label_image(tmp_path):
    rgb = sitk.Image([4, 4, 4], sitk.sitkVectorUInt8, 3)
    sitk.WriteImage(rgb, str(tmp_path / "rgb.nrrd"))
    with pytest.raises(VolumeTypeError, match="not a 3-D label map"):
        read_label_image(str(tmp_path / "rgb.nrrd"))
    ct = sitk.GetImageFromArray(np.linspace(-1000, 1000, 60).reshape(3, 4, 5).astype(np.float32))
    sitk.WriteImage(ct, str(tmp_path / "ct.nrrd"))
    with pytest.raises(VolumeTypeError, match="non-integer values"):
        read_label_image(str(tmp_path / "ct.nrrd"))
    with pytest.raises(InputError, match="Segment file not found"):
        read_label_image(str(tmp_path / "none.nrrd"))
    with pytest.raises(InputError, match="not a folder"):
        read_label_image(str(tmp_path))


# ---------------------------------------------------------------------------- real files

def test_real_segmentation_equals_the_real_label_map():
    seg = needs_data(os.path.join(PELVIS, "bones.seg.nrrd"))
    image, names = read_label_image(seg)
    reference, ref_names = read_label_image(os.path.join(PELVIS, "bones_labels.nrrd"))
    assert len(names) == 25 and dict(names) == dict(ref_names)
    assert names.present == ref_names.present
    # The .seg.nrrd has its own cropped extent and origin: compare in physical space.
    on_grid = sitk.Resample(image, reference, sitk.Transform(), sitk.sitkNearestNeighbor, 0)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(on_grid),
                                  sitk.GetArrayFromImage(reference))
    assert resolve_label(names, "femur_left") == 75 == resolve_label(ref_names, "femur_left")
    assert int((sitk.GetArrayViewFromImage(image) == 75).sum()) == 4488  # labels.csv
    hip = next(s for s in names.segments if s["name"] == "hip_right")
    assert resolve_label(names, hip["id"]) == 78
    with pytest.raises(InputError, match="'tibia' is not in.*femur_left"):
        resolve_label(names, "tibia")
    with pytest.raises(InputError, match="Label 300 cannot be in the label map .*uint8"):
        resolve_label(ref_names, 300)


@pytest.mark.parametrize("folder, file, n", [(AORTA, "vertebra_T12.seg.nrrd", 1),
                                             (SLAB, "bones.seg.nrrd", None)])
def test_real_segmentations_agree_with_read_segment(folder, file, n):
    seg = needs_data(os.path.join(folder, file))
    image, names = read_label_image(seg)
    if n is not None:
        assert len(names) == n
    array = sitk.GetArrayViewFromImage(image)
    for value in sorted(names.present):
        mask, name = read_segment(seg, names[value])
        assert name == names[value]
        np.testing.assert_array_equal(sitk.GetArrayViewFromImage(mask), array == value)
