"""Pictures (BoneWatertightLib.app.render, VTK offscreen) and the bundled-sample demo
(Resources/Scripts/demo.py)."""

import json
import os
import struct
import subprocess
import sys
import time

import numpy as np
import pytest
import SimpleITK as sitk

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, ROOT)

from BoneWatertightLib.app import render  # noqa: E402
from BoneWatertightLib.errors import InputError  # noqa: E402
from BoneWatertightLib.mesh import Surface  # noqa: E402

SAMPLE = os.path.join(ROOT, "Resources", "SampleData", "lumbar_spine_3mm")


def rotation(axis, angle_deg):
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    a = np.radians(angle_deg)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k


def uv_sphere(centre, radius, n_theta=48, n_phi=24):
    """Closed sphere mesh with outward CCW faces (poles + rings)."""
    rings = []
    for i in range(1, n_phi):
        phi = np.pi * i / n_phi
        t = 2 * np.pi * np.arange(n_theta) / n_theta
        rings.append(np.stack([np.sin(phi) * np.cos(t), np.sin(phi) * np.sin(t),
                               np.full(n_theta, np.cos(phi))], axis=1))
    v = np.vstack([[[0, 0, 1]], *rings, [[0, 0, -1]]]) * radius + centre
    faces = []
    south = len(v) - 1
    for j in range(n_theta):
        faces.append([0, 1 + j, 1 + (j + 1) % n_theta])
    for i in range(n_phi - 2):
        a0, b0 = 1 + i * n_theta, 1 + (i + 1) * n_theta
        for j in range(n_theta):
            j1 = (j + 1) % n_theta
            faces.append([a0 + j, b0 + j, b0 + j1])
            faces.append([a0 + j, b0 + j1, a0 + j1])
    last = 1 + (n_phi - 2) * n_theta
    for j in range(n_theta):
        faces.append([last + j, south, last + (j + 1) % n_theta])
    return Surface(v, np.array(faces))


def oblique_ct(radius=12.0, spacing=(1.0, 1.2, 1.5), size=(48, 42, 36)):
    """A ball of bone in an oblique, shifted, anisotropic CT; returns (ct, centre LPS)."""
    direction = rotation([1, 2, 3], 25.0) @ np.diag([-1.0, -1.0, 1.0])
    origin = np.array([31.0, -17.0, 102.0])
    centre_idx = (np.array(size) - 1) / 2.0 + np.array([0.3, -0.4, 0.2])
    centre = origin + direction @ (centre_idx * np.array(spacing))
    k, j, i = np.mgrid[:size[2], :size[1], :size[0]]
    idx = np.stack([i, j, k], axis=-1).astype(float)
    phys = origin + (idx * np.array(spacing)) @ direction.T
    r = np.linalg.norm(phys - centre, axis=-1)
    ct = sitk.GetImageFromArray(np.where(r < radius, 1200, 30).astype(np.int16))
    ct.SetSpacing(spacing)
    ct.SetOrigin(tuple(origin))
    ct.SetDirection(tuple(direction.ravel()))
    return ct, centre


def png_size(path):
    with open(path, "rb") as f:
        head = f.read(24)
    assert head[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG file"
    return struct.unpack(">II", head[16:24])


def test_orientation_of_sphere_mesh():
    s = uv_sphere(np.zeros(3), 10.0)
    from BoneWatertightLib.mesh import enclosed_volume

    assert enclosed_volume(s.vertices, s.faces) > 0.9 * 4 / 3 * np.pi * 1000


def test_render_surface_with_ct_writes_png(tmp_path):
    ct, centre = oblique_ct()
    surface = uv_sphere(centre, 12.0)
    surface.point_data["DistanceToConstraints"] = np.abs(surface.vertices[:, 2] - centre[2])
    out = tmp_path / "sphere.png"
    returned = render.render_surface(surface, str(out), ct=ct, title="sphere")
    assert returned == str(out)
    width, height = png_size(out)
    assert 800 <= width <= 2500 and 600 <= height <= 2000
    assert out.stat().st_size > 20_000
    # Without the CT: one row only, so a smaller picture.
    out2 = tmp_path / "sphere_views.png"
    render.render_surface(surface, str(out2), scalars=None)
    w2, h2 = png_size(out2)
    assert h2 < height


def test_render_accepts_ras_and_explicit_scalars(tmp_path):
    ct, centre = oblique_ct()
    surface = uv_sphere(centre, 12.0).to_ras()
    values = np.linspace(0.0, 2.0, surface.n_vertices)
    render.render_surface(surface, str(tmp_path / "ras.png"), ct=ct, scalars=values,
                          scalar_label="distance to truth")
    with pytest.raises(InputError):
        render.render_surface(surface, str(tmp_path / "bad.png"), scalars=values[:-1])
    with pytest.raises(InputError):
        render.render_surface(surface, str(tmp_path / "bad.png"), scalars="NoSuchArray")


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_section_through_centre_lies_on_radius(axis):
    """Triangles cut by a CT index plane through the centre give points at the radius,
    in physical space and in the picture's (mm) slice coordinates, for an oblique CT."""
    radius = 12.0
    ct, centre = oblique_ct(radius)
    surface = uv_sphere(centre, radius, n_theta=96, n_phi=48)
    centre_idx = render.physical_to_index(ct, centre[None])[0]
    assert np.allclose(render.index_to_physical(ct, centre_idx[None])[0], centre)
    idx = render.physical_to_index(ct, surface.vertices)
    seg = render.plane_section(idx, surface.faces, axis, centre_idx[axis])
    assert len(seg) > 50
    assert np.allclose(seg[..., axis], centre_idx[axis])
    phys = render.index_to_physical(ct, seg.reshape(-1, 3))
    dist = np.linalg.norm(phys - centre, axis=1)
    # Chords of a 96 x 48 sphere lie at most ~0.1 mm inside it.
    assert np.all(dist < radius + 1e-6) and np.all(dist > radius - 0.15)
    # Picture coordinates: an isometry of the plane, whatever the flips.
    frame = render._SliceFrame(ct, axis, int(round(centre_idx[axis])))
    disp = frame.display(seg.reshape(-1, 3))
    disp_centre = frame.display(centre_idx[None])[0]
    assert np.allclose(np.linalg.norm(disp - disp_centre, axis=1), dist, atol=1e-9)
    # Closed contour: every end point is shared by exactly two segments.
    keys = np.round(seg.reshape(-1, 3), 9)
    _, counts = np.unique(keys, axis=0, return_counts=True)
    assert np.all(counts == 2)


def test_surface_section_matches_plane_at_nearest_slice():
    radius = 12.0
    ct, centre = oblique_ct(radius)
    surface = uv_sphere(centre, radius, n_theta=96, n_phi=48)
    k = int(round(render.physical_to_index(ct, centre[None])[0][2]))
    seg = render.surface_section(ct, surface, 2, k)
    idx = render.physical_to_index(ct, seg.reshape(-1, 3))
    assert np.allclose(idx[:, 2], k)
    # The plane is off-centre by < half a voxel: the contour radius follows Pythagoras.
    plane_point = render.index_to_physical(ct, np.array([[0.0, 0.0, k]]))[0]
    normal = np.array(ct.GetDirection()).reshape(3, 3)[:, 2]
    offset = abs((centre - plane_point) @ normal)
    in_plane = np.linalg.norm(np.cross(seg.reshape(-1, 3) - centre, normal), axis=1)
    assert np.allclose(in_plane, np.sqrt(radius ** 2 - offset ** 2), atol=0.15)


def test_index_mapping_matches_simpleitk():
    ct, _ = oblique_ct()
    points = np.random.default_rng(1).uniform(-40, 40, (20, 3)) + np.array(ct.GetOrigin())
    ours = render.physical_to_index(ct, points)
    theirs = np.array([ct.TransformPhysicalPointToContinuousIndex(tuple(p)) for p in points])
    assert np.allclose(ours, theirs)
    assert np.allclose(render.index_to_physical(ct, ours), points)


# A sagittally acquired CT: image axes i -> S, j -> A, k -> L, so slices need transposing.
PERMUTED = (0.0, 0.0, 1.0, 0.0, -1.0, 0.0, 1.0, 0.0, 0.0)


@pytest.mark.parametrize("direction", [None, PERMUTED])
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_slice_image_and_contour_share_pixel_coordinates(axis, direction):
    """A marker voxel drawn by imshow must sit where display() puts its index."""
    ct, _ = oblique_ct()
    if direction is not None:
        ct.SetDirection(direction)
    array = sitk.GetArrayFromImage(ct)
    marker = np.array([7, 30, 22])  # i, j, k
    array[marker[2], marker[1], marker[0]] = 3000
    frame = render._SliceFrame(ct, axis, marker[axis])
    image = frame.image(array)
    x, y = frame.display(marker[None].astype(float))[0]
    ext = frame.extent()
    col = int(round((x - ext[0]) / (ext[1] - ext[0]) * image.shape[1] - 0.5))
    row = int(round((y - ext[2]) / (ext[3] - ext[2]) * image.shape[0] - 0.5))
    assert image[row, col] == 3000
    assert (image == 3000).sum() == 1
    if direction is not None:
        # Still radiological: the k (left) axis runs to the right in axial/coronal slices.
        expected = {0: "axial", 1: "coronal", 2: "sagittal"}[axis]
        assert frame.name == expected
        if axis != 2:
            step = frame.display(np.array([marker, marker + [0, 0, 1]], dtype=float))
            assert step[1, 0] > step[0, 0]


def test_slice_orientation_is_radiological():
    """With the usual NIfTI-from-RAS direction diag(-1,-1,1) the axial slice shows the
    patient's left on the right and anterior up."""
    ct, _ = oblique_ct()
    ct.SetDirection((-1, 0, 0, 0, -1, 0, 0, 0, 1))
    frame = render._SliceFrame(ct, 2, 10)
    assert frame.name == "axial"
    lo = frame.display(np.array([[0.0, 0.0, 10.0]]))[0]
    # Index (0, 0) is the most right-anterior corner in LPS (x, y grow with -i, -j).
    more_left = frame.display(np.array([[-5.0, 0.0, 10.0]]))[0]
    more_anterior = frame.display(np.array([[0.0, 5.0, 10.0]]))[0]
    assert more_left[0] > lo[0]           # -i = +L goes right
    assert more_anterior[1] > lo[1]       # +j = -P = anterior goes up


def test_render_cross_sections(tmp_path):
    ct, centre = oblique_ct()
    a = uv_sphere(centre, 12.0)
    b = uv_sphere(centre + 1.0, 10.0)
    out = tmp_path / "cross.png"
    render.render_cross_sections(ct, {"method A": a, "method B": b}, str(out), title="two")
    width, height = png_size(out)
    assert width > 600 and height > 300
    with pytest.raises(InputError):
        render.render_cross_sections(ct, {}, str(tmp_path / "none.png"))


def _read_png(path):
    """(h, w, 3) uint8 pixels of a PNG, top row first."""
    import vtk
    from vtk.util import numpy_support as ns

    reader = vtk.vtkPNGReader()
    reader.SetFileName(str(path))
    reader.Update()
    image = reader.GetOutput()
    w, h, _ = image.GetDimensions()
    pixels = ns.vtk_to_numpy(image.GetPointData().GetScalars()).reshape(h, w, -1)[..., :3]
    return pixels[::-1]


def test_rendered_picture_shows_the_shaded_coloured_surface_and_the_sections(tmp_path):
    """Not a blank image: the bone covers a good part of each view, is shaded (brightness
    varies), its colour follows the distance map (dark violet to yellow), and the CT sections
    show grey CT with the red cross-section over it."""
    ct, centre = oblique_ct()
    surface = uv_sphere(centre, 12.0, n_theta=96, n_phi=48)
    # 0 at the bottom, 2 mm at the top: both ends of the colour map are on the picture
    surface.point_data["DistanceToConstraints"] = (surface.vertices[:, 2] - centre[2] + 12.0) / 12.0
    out = tmp_path / "sphere.png"
    render.render_surface(surface, str(out), ct=ct, title="sphere")
    pixels = _read_png(out).astype(np.int32)
    h, w, _ = pixels.shape
    top = render.TITLE_PX
    panel = render.PANEL_PX
    view = pixels[top:top + panel, :panel]
    background_like = (np.abs(view - view[5:15, 5:15].reshape(-1, 3).mean(axis=0)).sum(axis=2) < 40)
    grey = (view.max(axis=2) - view.min(axis=2)) < 12
    bone = ~background_like & ~grey
    assert 0.15 < bone.mean() < 0.8, bone.mean()
    colours = view[bone]
    # viridis ends: violet (blue > green) and yellow (red and green high, blue low)
    assert ((colours[:, 2] > colours[:, 1] + 20) & (colours[:, 0] < 120)).sum() > 500
    assert ((colours[:, 0] > 150) & (colours[:, 1] > 150) & (colours[:, 2] < 110)).sum() > 500
    brightness = colours.sum(axis=1)
    assert brightness.std() > 40  # lit and shaded, not flat
    section = pixels[top + panel:, :panel]
    red = (section[..., 0] > 180) & (section[..., 1] < 110) & (section[..., 2] < 110)
    assert red.sum() > 300
    ct_grey = (np.abs(section[..., 0] - section[..., 1]) < 4) & (section[..., 0] > 30)
    assert ct_grey.mean() > 0.2
    assert w == 3 * panel + render.COLORBAR_PX and h == top + 2 * panel


def test_offscreen_unavailable_run_still_succeeds(tmp_path):
    """Forced unavailability (BONEWATERTIGHT_OFFSCREEN=0): the surface and the report are
    written, the picture is null with the reason, and the summary line says so."""
    from test_cli import FAST, sphere_ct

    ct, mask = sphere_ct()
    sitk.WriteImage(ct, str(tmp_path / "ct.nrrd"))
    sitk.WriteImage(mask, str(tmp_path / "mask.nrrd"))
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["BONEWATERTIGHT_OFFSCREEN"] = "0"
    proc = subprocess.run(
        [sys.executable, "-m", "BoneWatertightLib", "--ct", str(tmp_path / "ct.nrrd"),
         "--seg", str(tmp_path / "mask.nrrd"), "--label", "1", "--out", str(tmp_path / "b.stl"),
         "--picture", str(tmp_path / "b.png"), "--report", str(tmp_path / "r.json")]
        + [a for a in FAST if a != "-q"], cwd=ROOT, env=env, capture_output=True, text=True,
        encoding="utf-8", timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "b.stl").exists() and not (tmp_path / "b.png").exists()
    report = json.loads((tmp_path / "r.json").read_text(encoding="utf-8"))
    assert report["output"]["picture"] is None
    assert "BONEWATERTIGHT_OFFSCREEN=0" in report["output"]["picture_error"]
    assert "no picture: offscreen rendering is switched off" in proc.stdout
    assert render.offscreen_status()[0], "this machine renders offscreen (EGL), see setup_env.sh"


def test_bundled_sample_geometry():
    ct = sitk.ReadImage(os.path.join(SAMPLE, "ct.nrrd"))
    labels = sitk.ReadImage(os.path.join(SAMPLE, "labels.nrrd"))
    assert ct.GetPixelID() == sitk.sitkInt16 and labels.GetPixelID() == sitk.sitkUInt8
    assert ct.GetSize() == labels.GetSize()
    assert np.allclose(ct.GetOrigin(), labels.GetOrigin())
    assert np.allclose(ct.GetDirection(), (-1, 0, 0, 0, -1, 0, 0, 0, 1))
    assert set(np.unique(sitk.GetArrayViewFromImage(labels))) == {0, 28, 29}
    total = sum(os.path.getsize(os.path.join(SAMPLE, f)) for f in os.listdir(SAMPLE))
    assert total < 300_000


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "out"
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, os.path.join(ROOT, "Resources", "Scripts", "demo.py"),
                           str(out), "-q"], capture_output=True, text=True, timeout=900)
    return out, proc, time.perf_counter() - t0


def test_demo_runs_on_bundled_sample(demo_run):
    out, proc, seconds = demo_run
    # No wall-clock target here (the machine may be busy): the demo's time is the benchmark's
    # figure; the subprocess timeout only catches a hang.
    assert proc.returncode == 0, proc.stderr
    for name in ("surface.stl", "surface.vtp", "surface.png", "report.json"):
        assert (out / name).stat().st_size > 0, name
    report = json.loads((out / "report.json").read_text())
    assert report["checks"]["ok"] is True
    assert report["coordinate_system"] == "LPS"
    assert report["output"]["n_faces"] > 100
    assert "checks:          ok" in proc.stdout
    assert "distance to constraints" in proc.stdout
    with open(out / "surface.stl", "rb") as f:
        assert b"SPACE=LPS" in f.read(80)
    png_size(out / "surface.png")


def test_demo_surface_volume_agrees_with_segment(demo_run):
    """The checks prove a valid topology, not a right shape: the surface of the sample
    vertebra must enclose roughly the volume of its (automatic, 3 mm) rough segment."""
    out, proc, _ = demo_run
    assert proc.returncode == 0, proc.stderr
    report = json.loads((out / "report.json").read_text())
    enclosed_ml = report["checks"]["volume"] / 1000.0
    segment_ml = report["inputs"]["segment_volume_ml"]
    assert 0.5 * segment_ml < enclosed_ml < 1.5 * segment_ml, (enclosed_ml, segment_ml)
