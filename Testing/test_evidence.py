"""Per-vertex evidence and confidence (issue 18): what the CT says under each vertex."""

import numpy as np
import pytest
import SimpleITK as sitk

from BoneWatertightLib.pipeline import reconstruct
from BoneWatertightLib.stages import evidence as E


def _ball(direction=(1, 0, 0, 0, 1, 0, 0, 0, 1), radius=8.0, blur=0.8):
    """A bone ball (1200 HU, blurred) in soft tissue (40 HU) and its segment."""
    shape = (44, 44, 44)
    z, y, x = np.indices(shape)
    c = (np.array(shape) - 1) / 2
    r = np.sqrt((x - c[2]) ** 2 + (y - c[1]) ** 2 + (z - c[0]) ** 2)
    from scipy import ndimage

    arr = ndimage.gaussian_filter(np.where(r < radius, 1200.0, 40.0), blur)
    arr = (arr + np.random.default_rng(0).normal(0, 5, shape)).astype(np.int16)
    ct = sitk.GetImageFromArray(arr)
    ct.SetDirection(direction)
    ct.SetOrigin((12.0, -30.0, 7.5))
    mask = sitk.GetImageFromArray((r < radius - 1).astype(np.uint8))
    mask.CopyInformation(ct)
    return ct, mask


@pytest.mark.parametrize("direction", [(1, 0, 0, 0, 1, 0, 0, 0, 1),
                                       (-1, 0, 0, 0, 1, 0, 0, 0, 1)])  # left-handed
def test_a_clear_ball_stands_on_edges(direction):
    ct, mask = _ball(direction)
    r = reconstruct(ct, mask)
    ev = r.surface.point_data["Evidence"]
    conf = r.surface.point_data["Confidence"]
    assert ev.shape == conf.shape == (r.surface.n_vertices,)
    assert conf.min() >= 0.0 and conf.max() <= 1.0
    summary = r.report.evidence
    # The whole surface is on the CT's edge, whichever way the grid is handed.
    assert summary["fraction"]["edge"] > 0.95, summary["fraction"]
    assert summary["fraction"]["label only"] < 0.05
    assert abs(sum(summary["area_mm2"].values()) - r.report.area_mm2) < 1e-3 * r.report.area_mm2
    assert summary["edge_offset_mm"]["p90"] < 0.5
    assert not any("no CT edge" in w for w in r.report.warnings)


def test_vertex_evidence_classes_on_a_synthetic_field():
    # A flat edge at x = 10 mm on a 0.5 mm grid; vertices on it, 3 mm off it, and on a cap.
    d = 0.5
    shape = (20, 20, 60)
    x = np.arange(shape[2]) * d
    ct = np.broadcast_to(np.where(x < 10.0, 1200.0, 40.0), shape).astype(np.float32)
    from scipy import ndimage

    ct = ndimage.gaussian_filter(ct, 1.0)
    # a small closed box surface around the edge: two triangles per side
    lo, hi = np.array([4.0, 3.0, 3.0]), np.array([10.0, 7.0, 7.0])
    corners = np.array([[lo[0] if i & 1 == 0 else hi[0], lo[1] if i & 2 == 0 else hi[1],
                         lo[2] if i & 4 == 0 else hi[2]] for i in range(8)])
    faces = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                      [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
    from BoneWatertightLib.mesh.surface import enclosed_volume

    if enclosed_volume(corners, faces) < 0:  # outward
        faces = faces[:, ::-1].copy()
    flags = np.zeros(len(faces), np.uint8)
    flags[[0, 1]] = 1  # the z = lo face is a cap
    ev, conf, summary = E.vertex_evidence(corners, faces, flags, ct_smooth=ct, spacing=d,
                                          ht=150.0, soft=40.0, min_contrast=50.0,
                                          resolution=2.0)
    on_cap = np.unique(faces[flags > 0])
    assert (ev[on_cap] == E.CAP).all() and (conf[on_cap] == 1.0).all()
    rest = np.setdiff1d(np.arange(8), on_cap)
    # the +x corners (x = 10) sit on the edge (within half the 2 mm CT spacing along their
    # corner normals); the -x ones (x = 4) are 6 mm inside: no edge
    at_edge = rest[corners[rest, 0] == hi[0]]
    inside = rest[corners[rest, 0] == lo[0]]
    assert (ev[at_edge] == E.EDGE).all() and (conf[at_edge] > 0.5).all()
    assert (ev[inside] == E.LABEL_ONLY).all() and (conf[inside] == 0.0).all()
    assert set(summary["area_mm2"]) == set(E.CLASSES)


def test_threshold_reach_is_the_border_the_ct_shows_that_ht_reaches():
    """The plausibility gate's measure: of the free surface whose profile shows the bone's
    edge, the area whose cortex reaches HT - all of it below the cortex, none above it (the
    edge still shown); caps and the vertices without an edge do not count."""
    d = 0.5
    shape = (20, 20, 60)
    x = np.arange(shape[2]) * d
    from scipy import ndimage

    ct = ndimage.gaussian_filter(
        np.broadcast_to(np.where(x < 10.0, 600.0, 40.0), shape).astype(np.float32), 1.0)
    corners = np.array([[4.0 if i & 1 == 0 else 10.0, 3.0 if i & 2 == 0 else 7.0,
                         3.0 if i & 4 == 0 else 7.0] for i in range(8)])
    faces = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                      [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
    from BoneWatertightLib.mesh.surface import enclosed_volume

    if enclosed_volume(corners, faces) < 0:
        faces = faces[:, ::-1].copy()
    flags = np.zeros(len(faces), np.uint8)
    flags[[0, 1]] = 1
    reach = {}
    for ht in (150.0, 700.0):
        _, _, summary = E.vertex_evidence(corners, faces, flags, ct_smooth=ct, spacing=d,
                                          ht=ht, soft=40.0, min_contrast=50.0, resolution=2.0)
        reach[ht] = summary["threshold_reach"]
    assert reach[150.0]["edge_area_mm2"] == reach[700.0]["edge_area_mm2"] > 0
    assert reach[150.0]["edge_area_mm2"] < reach[150.0]["free_area_mm2"]  # the -x side: none
    assert reach[150.0]["fraction"] == 1.0 and reach[700.0]["fraction"] == 0.0
    area = E.vertex_areas(corners, faces)
    on_cap = np.unique(faces[flags > 0])
    assert reach[150.0]["free_area_mm2"] == pytest.approx(area.sum() - area[on_cap].sum())
    _, _, summary = E.vertex_evidence(corners, faces, flags, ct_smooth=None, spacing=d, ht=150.0,
                                      soft=40.0, min_contrast=50.0)
    assert summary["threshold_reach"] is None


def test_the_label_only_warning_says_where_its_largest_patches_are():
    """Two caps of a sphere (radius 10 mm) stand on the segment alone: the warning gives the
    area and place of each (largest first), at a vertex of the patch near its middle; a patch
    under WARN_AREA_MM2 is not listed, and without ``where`` the warning is as before."""
    from test_checks import icosphere

    v, f = icosphere(level=4, radius=10.0)
    area = E.vertex_areas(v, f)
    big = v[:, 0] > 5.0            # cap of height 5 mm: 2 pi r h = 314 mm^2
    small = v[:, 0] < -8.0         # height 2 mm: 126 mm^2
    tiny = v[:, 2] > 9.7           # height 0.3 mm: 19 mm^2, not listed
    mask = big | small | tiny
    patches = E.label_only_patches(f, mask, area, v)
    assert len(patches) == 3
    assert patches[0]["area_mm2"] > patches[1]["area_mm2"] > patches[2]["area_mm2"]
    assert abs(patches[0]["area_mm2"] - 2 * np.pi * 10 * 5) < 20
    assert abs(patches[1]["area_mm2"] - 2 * np.pi * 10 * 2) < 15
    # each patch's vertex lies in it, near its middle (on the x axis)
    assert big[patches[0]["vertex"]] and v[patches[0]["vertex"], 0] > 9.5
    assert small[patches[1]["vertex"]] and v[patches[1]["vertex"], 0] < -9.5
    assert E.label_only_patches(f, np.zeros(len(v), bool), area, v) == []
    summary = {"area_mm2": {"label only": float(area[mask].sum())},
               "fraction": {"label only": float(area[mask].sum() / area.sum())},
               "label_only_patches": patches}
    [text] = E.evidence_warnings(
        "ball", summary, 1.6, where=lambda i: f"LPS ({v[i, 0]:.0f}, {v[i, 1]:.0f}, {v[i, 2]:.0f})")
    assert text.endswith("(point array Evidence = 3); the largest patches: 316 mm^2 near "
                         "LPS (10, 0, 0), 126 mm^2 near LPS (-10, 0, 0)")
    [plain] = E.evidence_warnings("ball", summary, 1.6)
    assert plain.endswith("(point array Evidence = 3)")
