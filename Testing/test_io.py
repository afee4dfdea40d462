"""File input/output: CT (files and DICOM folders), segments, surfaces with SPACE tags."""

import os
import sys

import numpy as np
import pytest
import SimpleITK as sitk

sys.path.insert(0, os.path.abspath(os.path.join(os.path.dirname(__file__), "..")))

from BoneWatertightLib import io as bwio  # noqa: E402
from BoneWatertightLib.io import meshes  # noqa: E402
from BoneWatertightLib.errors import EmptySegmentError, InputError, VolumeTypeError  # noqa: E402
from BoneWatertightLib.mesh import enclosed_volume, from_polydata  # noqa: E402

DATA = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data"))
PELVIS = os.path.join(DATA, "ts_example_ct_abdomen_pelvis_3mm")
AORTA = os.path.join(DATA, "ts_aorta_report_ct_cropped_1p5mm")


# ---------------------------------------------------------------------------- helpers

def rotation(ax, ay, az):
    ax, ay, az = np.radians([ax, ay, az])
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def small_ct(size=(12, 10, 8), spacing=(0.8, 0.9, 1.5), origin=(-40.0, 25.0, 310.0),
             angles=(10, -15, 25), seed=0):
    rng = np.random.default_rng(seed)
    array = rng.integers(-1000, 1500, size=size[::-1]).astype(np.int16)
    image = sitk.GetImageFromArray(array)
    image.SetSpacing(spacing)
    image.SetOrigin(origin)
    image.SetDirection(rotation(*angles).ravel().tolist())
    return image


def write_dicom_series(image, folder, series_uid="1.2.826.0.1.3680043.2.1125.1.1", stem="s"):
    """Write a 3-D int16 image as a DICOM CT series (one file per slice), oblique allowed."""
    os.makedirs(folder, exist_ok=True)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    d = np.array(image.GetDirection()).reshape(3, 3)
    orientation = "\\".join(f"{v:.10f}" for v in (*d[:, 0], *d[:, 1]))
    for k in range(image.GetSize()[2]):
        sl = image[:, :, k]
        position = image.TransformIndexToPhysicalPoint((0, 0, k))
        tags = {
            "0008|0060": "CT",
            "0008|0016": "1.2.840.10008.5.1.4.1.1.2",
            "0020|000d": "1.2.826.0.1.3680043.2.1125.1",
            "0020|000e": series_uid,
            "0020|0037": orientation,
            "0020|0032": "\\".join(f"{v:.10f}" for v in position),
            "0020|0013": str(k + 1),
            "0008|0018": f"{series_uid}.{k + 1}",
            "0028|1052": "0", "0028|1053": "1", "0028|1054": "HU",
            "0018|0050": f"{image.GetSpacing()[2]:.6f}",
        }
        for key, value in tags.items():
            sl.SetMetaData(key, value)
        writer.SetFileName(os.path.join(folder, f"{stem}{k:03d}.dcm"))
        writer.Execute(sl)


def sphere_surface(center=(10.0, -20.0, 30.0), radius=5.0):
    import vtk

    src = vtk.vtkSphereSource()
    src.SetCenter(*center)
    src.SetRadius(radius)
    src.SetThetaResolution(16)
    src.SetPhiResolution(10)
    src.Update()
    surface = from_polydata(src.GetOutput())
    surface.point_data = {"DistanceToConstraints": np.linspace(0.0, 2.0, surface.n_vertices)}
    return surface


def corner_set(surface, decimals=3):
    """Triangles as sets of rounded corner coordinates: independent of vertex numbering."""
    tri = np.round(surface.vertices[surface.faces], decimals)
    return {tuple(sorted(map(tuple, t))) for t in tri}


def raw_points(path):
    """Vertices as stored in the file, ignoring any SPACE tag."""
    import vtk

    ext = bwio.extension(path)
    reader = {".stl": vtk.vtkSTLReader, ".ply": vtk.vtkPLYReader, ".obj": vtk.vtkOBJReader,
              ".vtp": vtk.vtkXMLPolyDataReader, ".vtk": vtk.vtkPolyDataReader}[ext]()
    reader.SetFileName(path)
    reader.Update()
    return from_polydata(reader.GetOutput())


def write_seg_nrrd(path, layers, segments, spacing=(1.0, 1.0, 2.0), origin=(5.0, -3.0, 7.0)):
    """A Slicer-style .seg.nrrd: layers (list of (z, y, x) uint8), Segment{i}_* header keys."""
    data = np.stack(layers, axis=-1) if len(layers) > 1 else layers[0]
    nz, ny, nx = layers[0].shape
    lines = ["NRRD0004", "type: unsigned char"]
    if len(layers) > 1:
        lines += ["dimension: 4", "space: left-posterior-superior",
                  f"sizes: {len(layers)} {nx} {ny} {nz}",
                  f"space directions: none ({spacing[0]},0,0) (0,{spacing[1]},0) "
                  f"(0,0,{spacing[2]})",
                  "kinds: list domain domain domain"]
    else:
        lines += ["dimension: 3", "space: left-posterior-superior", f"sizes: {nx} {ny} {nz}",
                  f"space directions: ({spacing[0]},0,0) (0,{spacing[1]},0) (0,0,{spacing[2]})",
                  "kinds: domain domain domain"]
    lines += ["encoding: raw", f"space origin: ({origin[0]},{origin[1]},{origin[2]})"]
    for i, (sid, name, value, layer) in enumerate(segments):
        lines += [f"Segment{i}_ID:={sid}", f"Segment{i}_Name:={name}",
                  f"Segment{i}_LabelValue:={value}", f"Segment{i}_Layer:={layer}"]
    with open(path, "wb") as f:
        f.write(("\n".join(lines) + "\n\n").encode())
        f.write(np.ascontiguousarray(data, dtype=np.uint8).tobytes())


# ---------------------------------------------------------------------------- surfaces

@pytest.mark.parametrize("ext", bwio.SURFACE_EXTENSIONS)
@pytest.mark.parametrize("system", ["LPS", "RAS"])
def test_surface_round_trip(tmp_path, ext, system):
    surface = sphere_surface()
    path = str(tmp_path / f"bone{ext}")
    bwio.write_surface(surface, path, system)
    back = bwio.read_surface(path)
    assert back.coordinate_system == "LPS"
    assert back.n_faces == surface.n_faces
    assert back.n_vertices == surface.n_vertices
    assert corner_set(back) == corner_set(surface)
    # orientation survives: the volume stays positive and equal
    assert enclosed_volume(back.vertices, back.faces) == pytest.approx(
        enclosed_volume(surface.vertices, surface.faces), rel=1e-5)
    if ext == ".vtp":
        import vtk

        reader = vtk.vtkXMLPolyDataReader()
        reader.SetFileName(path)
        reader.Update()
        assert reader.GetOutput().GetFieldData().GetAbstractArray("SPACE").GetValue(0) == system
    else:
        with open(path, "rb") as f:
            head = f.read(4096)
        assert f"SPACE={system}".encode() in head
    if ext in (".vtp", ".vtk"):
        np.testing.assert_allclose(back.point_data["DistanceToConstraints"],
                                   surface.point_data["DistanceToConstraints"])
    ras = bwio.read_surface(path, "RAS")
    assert ras.coordinate_system == "RAS"
    np.testing.assert_allclose(ras.vertices[:, :2], -back.vertices[:, :2])
    np.testing.assert_allclose(ras.vertices[:, 2], back.vertices[:, 2])


@pytest.mark.parametrize("ext", bwio.SURFACE_EXTENSIONS)
def test_ras_file_is_lps_with_x_y_negated(tmp_path, ext):
    surface = sphere_surface()
    lps, ras = str(tmp_path / f"a{ext}"), str(tmp_path / f"b{ext}")
    bwio.write_surface(surface, lps, "LPS")
    bwio.write_surface(surface, ras, "RAS")
    a, b = raw_points(lps), raw_points(ras)
    np.testing.assert_allclose(b.vertices[:, :2], -a.vertices[:, :2], atol=1e-6)
    np.testing.assert_allclose(b.vertices[:, 2], a.vertices[:, 2], atol=1e-6)


def test_ras_surface_written_as_lps(tmp_path):
    """A surface held in RAS is converted, not relabelled."""
    lps = sphere_surface()
    path = str(tmp_path / "x.vtp")
    bwio.write_surface(lps.to_ras(), path, "LPS")
    np.testing.assert_allclose(raw_points(path).vertices, lps.vertices)


def test_untagged_file_is_read_as_lps(tmp_path):
    import vtk

    from BoneWatertightLib.mesh import to_polydata

    surface = sphere_surface()
    path = str(tmp_path / "plain.stl")
    writer = vtk.vtkSTLWriter()
    writer.SetInputData(to_polydata(surface))
    writer.SetFileName(path)
    writer.Write()
    back = bwio.read_surface(path)
    assert back.coordinate_system == "LPS"
    assert corner_set(back) == corner_set(surface)


@pytest.mark.parametrize("ext", bwio.SURFACE_EXTENSIONS)
def test_slicer_reads_our_files_in_place(tmp_path, ext):
    """3D Slicer's own model storage node (slicer-core) finds the tag and places the model."""
    slicer = pytest.importorskip("slicer")
    surface = sphere_surface(center=(10.0, -20.0, 30.0))
    for system in ("LPS", "RAS"):
        path = str(tmp_path / f"m_{system}{ext}")
        bwio.write_surface(surface, path, system)
        scene = slicer.vtkMRMLScene()
        node = scene.AddNewNodeByClass("vtkMRMLModelNode")
        storage = scene.AddNewNodeByClass("vtkMRMLModelStorageNode")
        storage.SetFileName(path)
        assert storage.ReadData(node)
        poly = node.GetPolyData()
        pts = np.array([poly.GetPoint(i) for i in range(poly.GetNumberOfPoints())])
        # Slicer works in RAS: the LPS centre (10, -20, 30) is (-10, 20, 30) there.
        np.testing.assert_allclose(pts.mean(axis=0), [-10.0, 20.0, 30.0], atol=0.05)


def test_unsupported_extension_writes_nothing(tmp_path):
    with pytest.raises(InputError, match="Unsupported surface file type"):
        bwio.write_surface(sphere_surface(), str(tmp_path / "bone.xyz"))
    assert os.listdir(tmp_path) == []


def test_failed_write_leaves_previous_file_and_no_temp(tmp_path, monkeypatch):
    path = tmp_path / "bone.stl"
    path.write_bytes(b"previous result")

    def broken(poly, tmp, system):
        with open(tmp, "wb") as f:
            f.write(b"half a file")
        raise OSError("disk full")

    monkeypatch.setitem(meshes._WRITERS, ".stl", broken)
    with pytest.raises(OSError, match="disk full"):
        bwio.write_surface(sphere_surface(), str(path))
    assert path.read_bytes() == b"previous result"
    assert sorted(os.listdir(tmp_path)) == ["bone.stl"]


def test_interrupted_write_leaves_nothing(tmp_path, monkeypatch):
    def interrupted(poly, tmp, system):
        with open(tmp, "wb") as f:
            f.write(b"half")
        raise KeyboardInterrupt

    monkeypatch.setitem(meshes._WRITERS, ".ply", interrupted)
    with pytest.raises(KeyboardInterrupt):
        bwio.write_surface(sphere_surface(), str(tmp_path / "bone.ply"))
    assert os.listdir(tmp_path) == []


def test_write_points_round_trip(tmp_path):
    pts = np.random.default_rng(1).normal(size=(50, 3)) * 10
    for ext in (".ply", ".vtp"):
        path = str(tmp_path / f"p{ext}")
        bwio.write_points(pts, path, "RAS")
        raw = raw_points(path)
        np.testing.assert_allclose(raw.vertices[:, :2], -pts[:, :2], atol=1e-5)
        np.testing.assert_allclose(raw.vertices[:, 2], pts[:, 2], atol=1e-5)


# ---------------------------------------------------------------------------- CT

def test_read_ct_nrrd_keeps_geometry(tmp_path):
    image = small_ct()
    path = str(tmp_path / "ct.nrrd")
    sitk.WriteImage(image, path)
    back = bwio.read_ct(path)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(back), sitk.GetArrayFromImage(image))
    np.testing.assert_allclose(back.GetDirection(), image.GetDirection(), atol=1e-9)
    np.testing.assert_allclose(back.GetOrigin(), image.GetOrigin())


def test_dicom_folder_equals_nrrd(tmp_path):
    image = small_ct()
    nrrd = str(tmp_path / "ct.nrrd")
    sitk.WriteImage(image, nrrd)
    folder = str(tmp_path / "dicom")
    write_dicom_series(image, folder)
    a, b = bwio.read_ct(nrrd), bwio.read_ct(folder)
    assert a.GetSize() == b.GetSize()
    np.testing.assert_array_equal(sitk.GetArrayFromImage(b).astype(np.int32),
                                  sitk.GetArrayFromImage(a).astype(np.int32))
    np.testing.assert_allclose(b.GetSpacing(), a.GetSpacing(), atol=1e-4)
    np.testing.assert_allclose(b.GetOrigin(), a.GetOrigin(), atol=1e-4)
    np.testing.assert_allclose(b.GetDirection(), a.GetDirection(), atol=1e-6)


def test_dicom_folder_with_two_series(tmp_path):
    folder = str(tmp_path / "dicom")
    write_dicom_series(small_ct(), folder, series_uid="1.2.3.4.1", stem="a")
    write_dicom_series(small_ct(size=(12, 10, 3), seed=2), folder, series_uid="1.2.3.4.2",
                       stem="b")
    with pytest.raises(InputError, match=r"2 DICOM series.*1\.2\.3\.4\.1 \(8 files\).*"
                                         r"1\.2\.3\.4\.2 \(3 files\).*--ct-series"):
        bwio.read_ct(folder)
    assert bwio.read_ct(folder, series="1.2.3.4.2").GetSize() == (12, 10, 3)
    with pytest.raises(InputError, match="is not in"):
        bwio.read_ct(folder, series="9.9")


def test_read_ct_missing_and_empty_folder(tmp_path):
    with pytest.raises(InputError, match="CT not found"):
        bwio.read_ct(str(tmp_path / "nope.nrrd"))
    with pytest.raises(InputError, match="No DICOM series"):
        bwio.read_ct(str(tmp_path))
    bad = tmp_path / "bad.nrrd"
    bad.write_text("not an image")
    with pytest.raises(InputError, match="Cannot read the CT"):
        bwio.read_ct(str(bad))


def test_read_ct_rejects_non_ct(tmp_path):
    rgb = sitk.Image([8, 8, 8], sitk.sitkVectorUInt8, 3)
    sitk.WriteImage(rgb, str(tmp_path / "rgb.nrrd"))
    with pytest.raises(VolumeTypeError, match="3-component"):
        bwio.read_ct(str(tmp_path / "rgb.nrrd"))

    flat = sitk.GetImageFromArray(np.full((16, 16), -500, np.int16))
    sitk.WriteImage(flat, str(tmp_path / "flat.nrrd"))
    with pytest.raises(VolumeTypeError, match="2-D"):
        bwio.read_ct(str(tmp_path / "flat.nrrd"))

    four = sitk.GetImageFromArray(np.full((3, 4, 5, 6), -500, np.int16), isVector=False)
    sitk.WriteImage(four, str(tmp_path / "four.nii.gz"))
    with pytest.raises(VolumeTypeError, match="4-D"):
        bwio.read_ct(str(tmp_path / "four.nii.gz"))

    labels = np.zeros((8, 9, 10), np.uint8)
    labels[2:5, 2:5, 2:5] = 3
    sitk.WriteImage(sitk.GetImageFromArray(labels), str(tmp_path / "labels.nrrd"))
    with pytest.raises(VolumeTypeError, match="label map.*--seg"):
        bwio.read_ct(str(tmp_path / "labels.nrrd"))


def test_real_ct_and_label_map_as_ct():
    path = os.path.join(PELVIS, "ct.nrrd")
    if not os.path.exists(path):
        pytest.skip("../shared/data not present")
    ct = bwio.read_ct(path)
    assert ct.GetSize() == (122, 101, 112)
    # 25 bone labels + background: a label map given as --ct is refused.
    with pytest.raises(VolumeTypeError, match="label map"):
        bwio.read_ct(os.path.join(PELVIS, "bones_labels.nrrd"))


# ---------------------------------------------------------------------------- segments

def test_tiny_seg_nrrd_single_layer(tmp_path):
    layer = np.zeros((4, 5, 6), np.uint8)
    layer[1:3, 1:4, 1:3] = 7
    layer[0, 0, 0] = 9
    path = str(tmp_path / "tiny.seg.nrrd")
    write_seg_nrrd(path, [layer], [("Segment_1", "femur left", 7, 0),
                                   ("Segment_2", "noise", 9, 0),
                                   ("Segment_3", "unpainted", 11, 0)])
    for label in ("femur left", "Segment_1", "7", 7, "FEMUR LEFT"):
        mask, name = bwio.read_segment(path, label)
        assert name == "femur left"
        assert mask.GetPixelID() == sitk.sitkUInt8
        np.testing.assert_array_equal(sitk.GetArrayFromImage(mask), layer == 7)
        assert mask.GetOrigin() == (5.0, -3.0, 7.0)
        assert mask.GetSpacing() == (1.0, 1.0, 2.0)
    with pytest.raises(InputError, match="'tibia' is not in.*femur left / Segment_1 / 7.*noise"):
        bwio.read_segment(path, "tibia")
    with pytest.raises(EmptySegmentError, match="'unpainted'.*no voxel"):
        bwio.read_segment(path, "unpainted")


def test_tiny_seg_nrrd_two_layers(tmp_path):
    a = np.zeros((4, 5, 6), np.uint8)
    b = np.zeros_like(a)
    a[1:3, 1:3, 1:3] = 1
    b[1:4, 2:4, 2:5] = 1  # overlaps a: that is why Slicer put it in a second layer
    path = str(tmp_path / "layers.seg.nrrd")
    write_seg_nrrd(path, [a, b], [("S_a", "bone a", 1, 0), ("S_b", "bone b", 1, 1)])
    mask, name = bwio.read_segment(path, "bone b")
    assert name == "bone b"
    np.testing.assert_array_equal(sitk.GetArrayFromImage(mask), b == 1)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(bwio.read_segment(path, "S_a")[0]),
                                  a == 1)
    assert mask.GetOrigin() == (5.0, -3.0, 7.0)
    # label value 1 is in both layers: ambiguous, the message says to use the ID
    with pytest.raises(InputError, match="matches 2 segments.*segment ID"):
        bwio.read_segment(path, "1")


def test_label_map_by_value_and_by_name(tmp_path):
    labels = np.zeros((6, 7, 8), np.int16)
    labels[1:3, 1:3, 1:3] = 75
    labels[3:5, 3:6, 3:6] = 76
    image = sitk.GetImageFromArray(labels)
    image.SetOrigin((1.0, 2.0, 3.0))
    path = str(tmp_path / "bones_labels.nrrd")
    sitk.WriteImage(image, path)
    mask, name = bwio.read_segment(path, 76)
    assert name == "76"
    np.testing.assert_array_equal(sitk.GetArrayFromImage(mask), labels == 76)
    assert mask.GetOrigin() == (1.0, 2.0, 3.0)
    with pytest.raises(InputError, match="values present: 75, 76.*labels.csv"):
        bwio.read_segment(path, "femur_left")
    with pytest.raises(InputError, match="Label 80 is not in.*75, 76"):
        bwio.read_segment(path, "80")
    (tmp_path / "labels.csv").write_text("value,name\n75,femur_left\n76,femur_right\n")
    mask, name = bwio.read_segment(path, "femur_left")
    assert name == "femur_left"
    np.testing.assert_array_equal(sitk.GetArrayFromImage(mask), labels == 75)
    assert bwio.read_segment(path, "76")[1] == "femur_right"


def test_empty_label_map_and_missing_file(tmp_path):
    path = str(tmp_path / "empty.nrrd")
    sitk.WriteImage(sitk.Image([5, 5, 5], sitk.sitkUInt8), path)
    with pytest.raises(EmptySegmentError, match="empty"):
        bwio.read_segment(path, 1)
    with pytest.raises(InputError, match="Segment file not found"):
        bwio.read_segment(str(tmp_path / "none.nrrd"), 1)


@pytest.mark.parametrize("label", ["femur_left", "75"])
def test_real_seg_nrrd_matches_label_map(label):
    seg = os.path.join(PELVIS, "bones.seg.nrrd")
    if not os.path.exists(seg):
        pytest.skip("../shared/data not present")
    mask, name = bwio.read_segment(seg, label)
    assert name == "femur_left"
    labels = sitk.ReadImage(os.path.join(PELVIS, "bones_labels.nrrd"))
    # The .seg.nrrd has its own cropped extent and origin: compare in physical space.
    on_grid = sitk.Resample(mask, labels, sitk.Transform(), sitk.sitkNearestNeighbor, 0)
    expected = sitk.GetArrayFromImage(labels) == 75
    np.testing.assert_array_equal(sitk.GetArrayFromImage(on_grid).astype(bool), expected)
    assert expected.sum() == 4488  # labels.csv


def test_real_seg_nrrd_by_id_and_unknown():
    seg = os.path.join(PELVIS, "bones.seg.nrrd")
    if not os.path.exists(seg):
        pytest.skip("../shared/data not present")
    image = sitk.ReadImage(seg)
    segments = bwio.slicer_segments(image)
    hip = next(s for s in segments if s["name"] == "hip_right")
    mask, name = bwio.read_segment(seg, hip["id"])
    assert name == "hip_right"
    assert int(sitk.GetArrayViewFromImage(mask).sum()) == 13048
    with pytest.raises(InputError, match="'tibia' is not in.*femur_left"):
        bwio.read_segment(seg, "tibia")


def test_real_vertebra_seg_nrrd():
    seg = os.path.join(AORTA, "vertebra_T12.seg.nrrd")
    if not os.path.exists(seg):
        pytest.skip("../shared/data not present")
    mask, name = bwio.read_segment(seg, "vertebrae_T12")
    assert name == "vertebrae_T12"
    assert int(sitk.GetArrayViewFromImage(mask).sum()) == 9617
    assert bwio.read_segment(seg, "32")[1] == "vertebrae_T12"
