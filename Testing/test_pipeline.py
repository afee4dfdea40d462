"""Per-stage known answers and end-to-end tests of BoneWatertightLib's pipeline (issue 5)."""

import numpy as np
import pytest
import SimpleITK as sitk

from BoneWatertightLib import errors
from BoneWatertightLib.mesh.checks import check_surface
from BoneWatertightLib.stages.deform import Deformer
from BoneWatertightLib.mesh import Surface, enclosed_volume, mean_edge_length
from BoneWatertightLib.params import Parameters
from BoneWatertightLib.pipeline import reconstruct
from BoneWatertightLib.stages.poisson import contour, poisson_surface, remesh
from BoneWatertightLib.stages.threshold import boundary_voxels, voxel_points
from BoneWatertightLib.stages.visible import hpr_visible, visible_points

from metrics import surface_distance, vertex_distances
from phantoms import make_phantom


def sphere_points(n, radius=10.0, seed=0):
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    return p * radius, p


def sphere_mesh(radius, h):
    """Closed sphere mesh by contouring a distance field (grid step h)."""
    n = int(np.ceil(2.6 * radius / h))
    g = (np.arange(n) - (n - 1) / 2) * h
    zz, yy, xx = np.meshgrid(g, g, g, indexing="ij")
    field = radius - np.sqrt(xx ** 2 + yy ** 2 + zz ** 2)
    return contour(field, (g[0], g[0], g[0]), h, 0.0, smooth_iterations=0)


# ----------------------------------------------------------------- visible points, eq. (1)

def test_hpr_sphere_seen_from_outside_gives_near_hemisphere():
    pts, dirs = sphere_points(20000)
    view = np.array([0.0, 0.0, 200.0])
    idx = hpr_visible(pts, view, log_radius=3.6)
    vis = np.zeros(len(pts), bool)
    vis[idx] = True
    # From 200 mm the visible cap ends where the tangent from the viewpoint touches: z > r^2/200.
    cap = pts[:, 2] > 10.0 ** 2 / 200.0 + 0.3
    far = pts[:, 2] < -0.5
    assert vis[cap].mean() > 0.97
    assert vis[far].sum() == 0


def test_visible_points_skip_inner_shell_and_interior_adds_nothing():
    # A hollow capsule (cortical shell around a cavity): inner-wall voxels must stay hidden,
    # and feeding all voxels instead of boundary voxels gives the same visible set.
    d = 0.5
    zz, yy, xx = np.meshgrid(np.arange(120) * d - 30, np.arange(70) * d - 17.5,
                             np.arange(70) * d - 17.5, indexing="ij")
    zc = np.clip(zz, -15, 15)
    r = np.sqrt(xx ** 2 + yy ** 2 + (zz - zc) ** 2)
    shell = (r < 8) & (r >= 6)
    boundary = voxel_points(boundary_voxels(shell), d)
    idx, info = visible_points(boundary, d)
    q = boundary - np.array([17.5, 17.5, 30.0])
    qz = np.clip(q[:, 2], -15, 15)
    radius = np.sqrt(q[:, 0] ** 2 + q[:, 1] ** 2 + (q[:, 2] - qz) ** 2)
    outer = radius > 7
    # both walls are there (else the checks below would hold for nothing)
    assert outer.sum() > 1000 and (~outer).sum() > 500
    sel = np.zeros(len(boundary), bool)
    sel[idx] = True
    assert sel[outer].mean() > 0.95
    assert sel[~outer].sum() == 0
    # Interior voxels add nothing: per view, the hull of all voxels has the same visible
    # boundary voxels and no interior voxel (measured on 6 PCA views, far viewpoints).
    all_vox = voxel_points(shell, d)
    centre = all_vox.mean(axis=0)
    for direction in np.vstack([np.eye(3), -np.eye(3)]):
        view = centre + direction * 20 * 20.0
        vb = {tuple(p) for p in np.round(boundary[hpr_visible(boundary, view, 3.6)] / d).astype(int)}
        va = {tuple(p) for p in np.round(all_vox[hpr_visible(all_vox, view, 3.6)] / d).astype(int)}
        assert len(va ^ vb) <= 0.01 * len(vb), (direction, len(va ^ vb), len(vb))


# ----------------------------------------------------------------- Poisson M0

def test_poisson_sphere_is_watertight_genus0_with_right_radius():
    pts, normals = sphere_points(8000, radius=10.0)
    raw = poisson_surface(pts, normals, depth=6)
    m0 = remesh(raw, edge_length=0.8)
    rep = check_surface(m0.vertices, m0.faces)
    assert rep.ok, rep.problems
    assert rep.genus == 0
    radius = np.linalg.norm(m0.vertices - m0.vertices.mean(0), axis=1)
    assert abs(radius.mean() - 10.0) < 0.25
    assert radius.std() < 0.15
    assert 0.6 < mean_edge_length(m0.vertices, m0.faces) < 1.0


# ----------------------------------------------------------------- deformation, Fig. 9

def test_fig9_sphere_deforms_outward_shell_by_shell():
    """Paper Fig. 9: a sphere of radius 100 deformed towards point shells of radius 100, 120,
    140, 160 reaches 120, 140, 160 after 1, 2, 3 directional steps - at the paper's search
    parameters (delta = 0.75 d*, radius 1.5 d*, the schema's defaults), with psi the point
    nearest to the search centre v_c (eq. (7)); the shells are about one d* apart."""
    from BoneWatertightLib.params import SCHEMA

    rng = np.random.default_rng(1)
    shells = []
    for r in (100, 120, 140, 160):
        p = rng.normal(size=(40000, 3))
        shells.append(r * p / np.linalg.norm(p, axis=1, keepdims=True))
    cloud = np.vstack(shells)
    mesh = sphere_mesh(100.0, 20.0)
    d_star = mean_edge_length(mesh.vertices, mesh.faces)
    assert 15.0 < d_star < 30.0
    offset, radius = SCHEMA["search_offset"].default, SCHEMA["search_radius"].default
    assert 0.5 <= offset <= 1.0 and 1.0 <= radius <= 3 ** 0.5  # the paper's ranges
    alpha, beta = 1.0, 1e-3
    deformer = Deformer(mesh.vertices, mesh.faces, cloud, lambda p: np.ones(len(p), bool), d_star,
                        iterations=3, search_offset=offset, search_radius=radius,
                        alpha=alpha, beta=beta)
    deformer.clean_v = deformer.v.copy()
    for j, expected in enumerate((120.0, 140.0, 160.0), start=1):
        # One directional iteration with the full step of the last iteration (c = psi - v).
        new, matched, _ = deformer.step(3, 3, alpha, beta)
        assert new is not None and matched.mean() > 0.95
        deformer.v = new
        radius_now = np.linalg.norm(new, axis=1)
        assert abs(np.median(radius_now) - expected) < 3.0, (expected, np.median(radius_now))
        assert radius_now.std() < 2.0
        assert check_surface(new, mesh.faces).ok


def test_search_takes_the_point_nearest_the_search_centre():
    """With psi nearest v (not v_c) M0 would stay pinned to its own points: here a vertex on a
    shell at 100 with the next shell 15 ahead moves to it."""
    rng = np.random.default_rng(2)
    shells = []
    for r in (100, 115):
        p = rng.normal(size=(30000, 3))
        shells.append(r * p / np.linalg.norm(p, axis=1, keepdims=True))
    mesh = sphere_mesh(100.0, 20.0)
    d_star = mean_edge_length(mesh.vertices, mesh.faces)
    deformer = Deformer(mesh.vertices, mesh.faces, np.vstack(shells), lambda p: np.ones(len(p), bool),
                        d_star, iterations=1)
    normals = -mesh.vertices / np.linalg.norm(mesh.vertices, axis=1, keepdims=True) * -1
    psi, matched, _ = deformer.match(mesh.vertices, normals)
    reach = np.linalg.norm(psi[matched], axis=1)
    assert matched.mean() > 0.95 and np.median(reach) > 112.0


# ----------------------------------------------------------------- end to end on phantoms

@pytest.fixture(scope="module")
def tiny():
    return make_phantom("tiny")


@pytest.fixture(scope="module")
def tiny_result(tiny):
    return reconstruct(tiny.ct, tiny.mask, Parameters(keep_intermediates=True))


def test_tiny_phantom_checks_accuracy_and_no_bridge(tiny, tiny_result):
    surf = tiny_result.surface
    rep = tiny_result.report
    assert rep.checks.ok and rep.checks.genus == 0
    assert rep.checks.n_components == 1
    d = surface_distance(surf, tiny.truth, n_samples=60000)
    # Measured: mean 0.14, p95 0.33, max 1.5 mm at 1 mm voxels (31 mm bone).
    assert d["mean"] < 0.3 and d["p95"] < 0.6 and d["max"] < 2.5, d
    # No bridge: the surface stays out of the neighbouring cup (gap 2 mm).
    dn = vertex_distances(surf.vertices, tiny.neighbour_truth)
    assert dn.min() > 0.3
    assert np.all(np.isfinite(tiny_result.distance_to_constraints))
    assert "DistanceToConstraints" in surf.point_data
    for key in ("P_H0", "P_HT", "visible_points", "constraints", "M0"):
        assert key in tiny_result.intermediates
    # the segment's genus, counted once for M0's fill and reused by the tunnel warning
    assert rep.plausibility.segment_genus == 0


SHARED_STAGES = ("import_open3d", "prepare", "filter", "thresholds", "ownership", "territories",
                 "refine_field", "contacts")


def _assert_spans_match_the_times(spans, times_of, total):
    """Every stage timed for a bone (or shared) has spans whose durations add up to that time,
    within the run, in order of start; the shared stages follow one another."""
    assert spans == sorted(spans, key=lambda s: (s["start_s"], s["end_s"]))
    assert all(0.0 <= s["start_s"] <= s["end_s"] <= total for s in spans)
    summed = {}
    for s in spans:
        key = (s["stage"], s["label"])
        summed[key] = summed.get(key, 0.0) + s["end_s"] - s["start_s"]
        assert (s["bone"] is None) == (s["label"] is None) == (s["stage"] in SHARED_STAGES)
    for (stage, label), seconds in summed.items():
        assert seconds == pytest.approx(getattr(times_of(label), stage), abs=1e-9), (stage, label)
    for label in {lab for _, lab in summed}:
        for stage, seconds in vars(times_of(label)).items():
            if stage != "total" and seconds > 0 and (label is None) == (stage in SHARED_STAGES):
                assert (stage, label) in summed, (stage, label)
    shared = [s for s in spans if s["label"] is None]
    assert all(a["end_s"] <= b["start_s"] for a, b in zip(shared, shared[1:]))


def test_stage_spans_add_up_to_the_stage_times(tiny_result):
    """report.stage_spans (when each timed stage ran, for the benchmark's per-stage memory)."""
    rep = tiny_result.report
    spans = rep.stage_spans
    assert {s["stage"] for s in spans} >= {"prepare", "poisson", "deform", "refine", "checks"}
    assert {s["label"] for s in spans} == {None, 1}
    _assert_spans_match_the_times(spans, lambda label: rep.timings, rep.timings.total)


def test_stage_spans_of_bones_run_together():
    """Two bones: the joint report has every span, each bone's report the shared ones and its
    own; the per-bone spans add up to each bone's own stage times."""
    from BoneWatertightLib.pipeline import reconstruct_many
    from test_child_run import NAMES, PARAMS, two_balls

    ct, labels, _ = two_balls()
    res = reconstruct_many(ct, labels, [1, 2], PARAMS, names=NAMES)
    joint = res.report
    by_label = {b.label: b.report.timings for b in res.bones}

    def times_of(label):
        return joint.timings if label is None else by_label[label]

    assert {s["label"] for s in joint.stage_spans} == {None, 1, 2}
    _assert_spans_match_the_times(joint.stage_spans, times_of, joint.timings.total)
    for b in res.bones:
        assert b.report.stage_spans == [s for s in joint.stage_spans if s["label"] in (None, b.label)]
        assert {s["bone"] for s in b.report.stage_spans} == {None, NAMES[b.label]}


def test_inputs_are_not_modified(tiny):
    ct_before = sitk.GetArrayFromImage(tiny.ct).copy()
    mask_before = sitk.GetArrayFromImage(tiny.mask).copy()
    reconstruct(tiny.ct, tiny.mask, Parameters(spacing=1.0, iterations=2))
    assert np.array_equal(sitk.GetArrayFromImage(tiny.ct), ct_before)
    assert np.array_equal(sitk.GetArrayFromImage(tiny.mask), mask_before)


def _moved(image, rotation, origin):
    out = sitk.Image(image)
    direction = rotation @ np.array(image.GetDirection()).reshape(3, 3)
    out.SetDirection(direction.ravel().tolist())
    out.SetOrigin(origin.tolist())
    return out


def test_oblique_direction_and_origin_move_the_surface_the_same_way(tiny, tiny_result):
    a = np.deg2rad(25.0)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]) @ \
        np.array([[1, 0, 0], [0, np.cos(0.4), -np.sin(0.4)], [0, np.sin(0.4), np.cos(0.4)]])
    new_origin = np.array([120.5, -43.25, 17.0])
    ct2 = _moved(tiny.ct, rot, new_origin)
    mask2 = _moved(tiny.mask, rot, new_origin + (np.array(tiny.mask.GetOrigin()) - np.array(tiny.ct.GetOrigin())) @ rot.T)
    res2 = reconstruct(ct2, mask2, Parameters())
    # The same voxels: map the first result's vertices through the same rigid motion.
    o1 = np.array(tiny.ct.GetOrigin())
    expected = (tiny_result.surface.vertices - o1) @ rot.T + new_origin
    got = res2.surface.vertices
    moved = Surface(expected, tiny_result.surface.faces)
    d = surface_distance(moved, res2.surface, n_samples=40000)
    # Measured: mean 0.004, p98 0.04, max 1.0 mm (9 of 5000 vertices beyond 0.5 mm). Not
    # bit-identical: nearest-neighbour resampling of the coarse segment onto the rotated CT grid
    # breaks a few ties differently (here: one soft-tissue island of the rough segment is left
    # out in one run only), and the thin-plate ridges of the 1 mm cortex (as thin as a voxel)
    # are found on differently resampled grids; both change a few vertices by about a voxel.
    assert d["mean"] < 0.03 and d["p98"] < 0.3 and d["max"] < 1.5, d
    v1 = enclosed_volume(tiny_result.surface.vertices, tiny_result.surface.faces)
    assert abs(enclosed_volume(got, res2.surface.faces) - v1) < 0.003 * v1
    assert res2.report.checks.ok


def test_progress_reports_and_cancel(tiny):
    seen = []

    def cb(fraction, message):
        seen.append(fraction)

    reconstruct(tiny.ct, tiny.mask, Parameters(spacing=1.0, iterations=1), progress=cb)
    assert seen[-1] == pytest.approx(1.0) and all(b >= a - 1e-9 for a, b in zip(seen, seen[1:]))

    def cancel(fraction, message):
        return fraction < 0.3

    with pytest.raises(errors.CancelledError):
        reconstruct(tiny.ct, tiny.mask, Parameters(spacing=1.0), progress=cancel)


# ----------------------------------------------------------------- SPEC §5 error paths

def _ball_ct(shape=(40, 40, 40), radius=8.0, spacing=1.0):
    z, y, x = np.indices(shape)
    c = (np.array(shape) - 1) / 2
    r = np.sqrt((x - c[2]) ** 2 + (y - c[1]) ** 2 + (z - c[0]) ** 2) * spacing
    arr = np.where(r < radius, 1200, 40).astype(np.int16)
    arr = arr + np.random.default_rng(0).normal(0, 5, shape).astype(np.int16)
    ct = sitk.GetImageFromArray(arr)
    ct.SetSpacing([spacing] * 3)
    mask = sitk.GetImageFromArray((r < radius - 1).astype(np.uint8))
    mask.CopyInformation(ct)
    return ct, mask


def test_error_thresholds_out_of_order():
    ct, mask = _ball_ct()
    with pytest.raises(errors.InputError, match="HT < H0"):
        reconstruct(ct, mask, Parameters(h0=100, ht=200))
    with pytest.raises(errors.InputError, match="theta_max"):
        reconstruct(ct, mask, Parameters(h0=300, theta_max=250))


def test_error_empty_segment_and_no_overlap():
    ct, mask = _ball_ct()
    empty = sitk.Image(mask.GetSize(), sitk.sitkUInt8)
    empty.CopyInformation(mask)
    with pytest.raises(errors.EmptySegmentError):
        reconstruct(ct, empty, Parameters())
    far = sitk.Image(mask)
    far.SetOrigin((500.0, 500.0, 500.0))
    with pytest.raises(errors.NoOverlapError):
        reconstruct(ct, far, Parameters())
    with pytest.raises(errors.EmptySegmentError):
        reconstruct(ct, None, Parameters())


def test_error_no_voxel_in_windows():
    ct, mask = _ball_ct()
    with pytest.raises(errors.ThresholdError, match="HT"):
        reconstruct(ct, mask, Parameters(ht=1500, h0=1800, theta_max=2500))
    # An H0 above every voxel: the segment's core still says bone, but the surface has no CT
    # edge and the plausibility gate refuses it (never a success).
    with pytest.raises((errors.PlausibilityError, errors.ReconstructionError)):
        reconstruct(ct, mask, Parameters(ht=1400, h0=1500, theta_max=2500))


def test_error_volume_types():
    ct, mask = _ball_ct()
    label = sitk.GetImageFromArray((sitk.GetArrayFromImage(ct) > 500).astype(np.uint8) * 3)
    with pytest.raises(errors.VolumeTypeError, match="label map"):
        reconstruct(label, mask, Parameters())
    rgb = sitk.Compose([ct, ct, ct])
    with pytest.raises(errors.VolumeTypeError, match="components"):
        reconstruct(rgb, mask, Parameters())
    two_d = sitk.GetImageFromArray(np.zeros((20, 20), np.int16))
    with pytest.raises(errors.VolumeTypeError, match="2-D"):
        reconstruct(two_d, mask, Parameters())


def test_error_segment_touching_border_and_memory_limit():
    ct, mask = _ball_ct()
    arr = sitk.GetArrayFromImage(mask)
    arr[0, 20, 20] = 1
    border = sitk.GetImageFromArray(arr)
    border.CopyInformation(mask)
    with pytest.raises(errors.BorderError, match="border"):
        reconstruct(ct, border, Parameters(at_border="error"))
    with pytest.raises(errors.MemoryLimitError, match="spacing of at least"):
        reconstruct(ct, mask, Parameters(spacing=0.05, max_memory_gb=0.5))


def test_error_unknown_parameter():
    with pytest.raises(errors.InputError, match="Unknown parameter"):
        Parameters().replace(not_a_parameter=1)


def test_a_bone_cut_into_two_pieces_by_the_image_boundary_is_refused_clearly():
    """A U-shaped bone whose arch lies outside the scan: inside the image it is two arms that
    join only beyond the field of view. One closed surface cannot hold them: the run must not
    return one arm as a success (it did: the untouched arm counted as an island)."""
    n, s = 56, 1.0
    z, y, x = np.mgrid[:n, :n, :n].astype(float) * s
    cx, cz = 28.0, 28.0
    r_major, r_minor = 14.0, 5.0
    # arch: a half torus around (cx, y=40, cz) in the x-y plane; arms down to y = 12
    ring = np.hypot(np.hypot(x - cx, y - 40.0) - r_major, z - cz) <= r_minor
    arch = ring & (y >= 40.0)
    arms = ((np.hypot(x - (cx - r_major), z - cz) <= r_minor)
            | (np.hypot(x - (cx + r_major), z - cz) <= r_minor)) & (y >= 12.0) & (y < 40.0)
    bone = (arch | arms) & (y <= 47.0)  # the image ends at y = 47: the arch's top is outside
    keep = slice(0, 48)
    hu = np.where(bone, 1300.0, 20.0)[:, keep, :]
    ct = sitk.GetImageFromArray(hu.astype(np.int16))
    ct = sitk.Cast(sitk.SmoothingRecursiveGaussian(sitk.Cast(ct, sitk.sitkFloat32), 0.6),
                   sitk.sitkInt16)
    mask = sitk.GetImageFromArray(bone[:, keep, :].astype(np.uint8))
    for img in (ct, mask):
        img.SetSpacing((s, s, s))
    with pytest.raises(errors.PlausibilityError, match=r"separate piece of bone that the surface "
                                                      r"does not reach"):
        reconstruct(ct, mask, Parameters(spacing=1.0, iterations=2, views=6))


def test_remesh_joins_a_process_of_the_bone_that_the_surface_missed():
    """M0 (a ball, r 8 mm) misses a rod of the bone's own solid reaching 10 mm beyond it (a
    thin process Poisson detached): the remesh joins it. The solid's partial-volume rim along
    the surface (1 mm, within the reach) and a speck not connected to the surface are not."""
    from BoneWatertightLib.stages.poisson import Fusion

    h = 0.5
    n = 64
    g = (np.arange(n) - (n - 1) / 2) * h          # -15.75 .. 15.75 mm, centred at 0
    zz, yy, xx = np.meshgrid(g, g, g, indexing="ij")
    r = np.sqrt(xx ** 2 + yy ** 2 + zz ** 2)
    rod = (np.hypot(xx, yy) <= 1.5) & (zz > 0) & (zz <= 15.0)
    speck = (np.sqrt((xx + 13) ** 2 + (yy + 13) ** 2 + zz ** 2) <= 1.5)
    solid = (r <= 9.0) | rod | speck
    ball = sphere_mesh(8.0, 0.5)
    fusion = Fusion(label_origin=np.array([g[0]] * 3), label_spacing=h, solid=solid,
                    solid_reach_mm=2.0)
    out = remesh(ball, 1.0, fusion=fusion)
    v = out.vertices
    assert fusion.info["joined_pieces"] == 1 and fusion.info["joined_bone_mm3"] > 40.0
    assert v[:, 2].max() > 12.0                            # most of the rod (its end smoothed)
    side = np.abs(v[:, 2]) < 2.0
    assert np.linalg.norm(v[side], axis=1).max() < 8.6     # no rim joined
    assert np.linalg.norm(v - [-13, -13, 0], axis=1).min() > 5.0  # no speck
    alone = remesh(ball, 1.0)
    assert alone.vertices[:, 2].max() < 8.6


def test_remesh_joins_a_thin_process_reaching_a_little_beyond_the_reach():
    """A rod 2 mm across reaching 5 mm beyond the ball's solid (r 9 mm; the reach 2.5 mm, the
    remesh grid ~0.8 mm): its part beyond the reach holds less than reach^3, which left the
    whole rod out (the last 5 mm of a 3 mm transverse process), and is joined. A bump as
    as thick but less than a grid step beyond the reach is not (the solid's rough rim)."""
    from BoneWatertightLib.stages.poisson import Fusion

    h = 0.5
    g = (np.arange(72) - 35.5) * h
    zz, yy, xx = np.meshgrid(g, g, g, indexing="ij")
    r = np.sqrt(xx ** 2 + yy ** 2 + zz ** 2)
    ball = sphere_mesh(8.0, 0.5)

    def run(extra):
        fusion = Fusion(label_origin=np.array([g[0]] * 3), label_spacing=h,
                        solid=(r <= 9.0) | extra, solid_reach_mm=2.5)
        return remesh(ball, 0.6, fusion=fusion), fusion.info

    out, info = run((np.hypot(xx, yy) <= 1.0) & (zz > 0) & (zz <= 13.0))
    assert info["joined_pieces"] == 1 and out.vertices[:, 2].max() > 12.0
    side = np.abs(out.vertices[:, 2]) < 2.0
    assert np.linalg.norm(out.vertices[side], axis=1).max() < 8.6   # no rim joined
    out, info = run((r <= 10.6) & (zz > 0.985 * r))                   # a cap ~4 mm across
    assert info["joined_pieces"] == 0 and out.vertices[:, 2].max() < 8.6


def test_remesh_joins_a_process_whose_thin_poisson_neck_the_smoothing_cuts():
    """Poisson made a ball (r 8 mm) with a process as a thread 2 mm across (12 mm long): the
    remesh grid (1.33 mm) holds the thread, but its smoothing cuts it, and the contour keeps
    only the ball. The thresholds' solid holds the process 3.2 mm across: measured against
    what the contour keeps, the process is missed by 9 mm and is joined (before, the thread
    counted as reaching it and the whole process was lost: a 3 mm transverse process)."""
    from BoneWatertightLib.stages.poisson import Fusion, contour

    hf = 0.2
    g = np.arange(-12, 20.01, hf)
    zz, yy, xx = np.meshgrid(g, g, g, indexing="ij")
    thread = np.minimum(1.0 - np.hypot(xx, yy), np.minimum(zz - 5.0, 17.0 - zz))
    field = np.maximum(8.0 - np.sqrt(xx ** 2 + yy ** 2 + zz ** 2), thread).astype(np.float32)
    poisson_like = contour(field, (g[0],) * 3, hf, 0.0, smooth_iterations=0, relax=False)
    assert poisson_like.vertices[:, 2].max() > 16.5
    h = 0.5
    gs = np.arange(-12, 20.01, h)
    zs, ys, xs = np.meshgrid(gs, gs, gs, indexing="ij")
    solid = ((np.sqrt(xs ** 2 + ys ** 2 + zs ** 2) <= 9.0)
             | ((np.hypot(xs, ys) <= 1.6) & (zs > 0) & (zs <= 17.0)))
    fusion = Fusion(label_origin=np.array([gs[0]] * 3), label_spacing=h, solid=solid,
                    solid_reach_mm=2.0)
    out = remesh(poisson_like, 1.0, fusion=fusion)
    assert fusion.info["joined_pieces"] == 1 and fusion.info["joined_bone_mm3"] > 60.0
    assert out.vertices[:, 2].max() > 15.0
    assert remesh(poisson_like, 1.0).vertices[:, 2].max() < 8.5   # without the solid: lost


def _ball_with_a_handle(n, h=0.5):
    """A ball's solid (r 8.5 mm, centred on a grid of n^3 steps h) with a handle above it (a bar
    6 mm beyond the ball on two posts: lace of a thin plate, not a process); the grid's (z, y,
    x) coordinates (mm) and its first node."""
    g = (np.arange(n) - (n - 1) / 2) * h
    zz, yy, xx = np.meshgrid(g, g, g, indexing="ij")
    post = (np.hypot(np.abs(xx) - 5.0, yy) <= 1.5) & (zz > 0) & (zz <= 14.0)
    bar = (np.hypot(yy, zz - 13.0) <= 1.5) & (np.abs(xx) <= 6.5)
    solid = (np.sqrt(xx ** 2 + yy ** 2 + zz ** 2) <= 8.5) | post | bar
    return solid, (zz, yy, xx), np.array([g[0]] * 3)


def test_remesh_drops_a_join_that_would_add_a_tunnel():
    """A handle of the solid would make a tunnel: the join is dropped and reported."""
    from BoneWatertightLib.stages.poisson import Fusion, surface_genus

    h = 0.5
    solid, _, origin = _ball_with_a_handle(64, h)
    fusion = Fusion(label_origin=origin, label_spacing=h, solid=solid, solid_reach_mm=2.0)
    out = remesh(sphere_mesh(8.0, 0.5), 1.0, fusion=fusion)
    assert surface_genus(out) == 0 and out.vertices[:, 2].max() < 9.0
    assert fusion.info["joined_pieces"] == 0 and fusion.info["join_dropped_mm3"] > 40.0


def test_remesh_joins_the_pieces_that_add_no_tunnel_and_drops_the_others():
    """Two missed pieces of the solid: a rod (a process, below the ball) and the handle above
    it: joined together they add a tunnel; one at a time
    the rod is joined and the handle alone is left out, each reported (before, one piece's
    tunnel dropped both: the 3 mm sacrum's tip, 10 mm)."""
    from BoneWatertightLib.stages.poisson import Fusion, surface_genus

    h = 0.5
    solid, (zz, yy, xx), origin = _ball_with_a_handle(72, h)
    solid |= (np.hypot(xx, yy) <= 1.5) & (zz < 0) & (zz >= -16.0)  # the rod
    fusion = Fusion(label_origin=origin, label_spacing=h, solid=solid, solid_reach_mm=2.0)
    out = remesh(sphere_mesh(8.0, 0.5), 1.0, fusion=fusion)
    info = fusion.info
    assert surface_genus(out) == 0
    assert out.vertices[:, 2].min() < -13.0 and out.vertices[:, 2].max() < 9.0
    assert info["joined_pieces"] == 1 and info["joined_bone_mm3"] > 40.0
    assert info["join_dropped_mm3"] > 40.0 and info["join_dropped_reach_mm"] > 3.0
    assert fusion.dropped_far[2] > 9.0 and fusion.joined_far[2] < -9.0


def _u_with_a_plate(ct_mm=3.0, fine=0.25):
    """A bone shaped as a U of thick bars (12 mm square, cortex 1.5 mm) in the x-y plane with a
    1.2 mm plate between its arms (the middle of an iliac wing or a scapular blade), imaged as
    a 3 mm CT (Gaussian PSF, block average, noise 15 HU), and an AI-style label of the U alone
    (majority on the CT grid): the plate's middle lies 30 mm from the label. Returns the CT, the
    label and the plate's centre (physical mm)."""
    from scipy import ndimage

    size, height, zc = 96.0, 36.0, 16.5                     # the plate on a CT slice's centre
    nx, nz = int(size / fine), int(height / fine)
    c = (np.arange(max(nx, nz)) + 0.5) * fine
    Z, Y, X = np.meshgrid(c[:nz], c[:nx], c[:nx], indexing="ij")
    bars = np.abs(Z - zc) <= 6.0
    u = bars & (Y >= 12) & (Y <= 84) & (((X >= 12) & (X <= 24)) | ((X >= 72) & (X <= 84)))
    u |= bars & (Y >= 12) & (Y <= 24) & (X >= 12) & (X <= 84)
    plate = (np.abs(Z - zc) <= 0.6) & (Y >= 12) & (Y <= 84) & (X >= 12) & (X <= 84) & ~u
    hu = np.full(u.shape, 40.0, np.float32)
    hu[u] = 300.0
    hu[u & ~ndimage.binary_erosion(u, iterations=int(1.5 / fine))] = 1400.0
    hu[plate] = 1400.0
    hu = ndimage.gaussian_filter(hu, sigma=(1.2 / fine, 0.6 / fine, 0.6 / fine))
    f = int(ct_mm / fine)
    blocks = (nz // f, f, nx // f, f, nx // f, f)
    ct = hu.reshape(blocks).mean(axis=(1, 3, 5))
    ct += np.random.default_rng(0).normal(0, 15, ct.shape)
    label = u.reshape(blocks).mean(axis=(1, 3, 5)) >= 0.5
    ct_img = sitk.GetImageFromArray(ct.astype(np.int16))
    ct_img.SetSpacing((ct_mm,) * 3)
    lab_img = sitk.GetImageFromArray(label.astype(np.uint8))
    lab_img.CopyInformation(ct_img)
    return ct_img, lab_img, np.array([48.0, 54.0, zc])


def test_a_plate_the_segment_missed_between_its_labelled_parts_is_closed_not_a_hole():
    """Issue 18: the CT shows a thin plate between the arms of the labelled part, the segment
    leaves it out (30 mm beyond the label, farther than the merge's reach): the surface holds
    the plate (no hole, genus 0 as the segment), the run is not refused for reaching beyond
    the segment, and the report says what was taken in."""
    from scipy.spatial import cKDTree

    ct, label, centre = _u_with_a_plate()
    res = reconstruct(ct, label, Parameters(spacing=1.0))
    rep = res.report
    assert rep.checks.genus == 0 and not rep.plausibility.problems
    # the surface passes within the plate's half thickness + a voxel of its centre
    assert cKDTree(res.surface.vertices).query(centre)[0] < 2.5
    plate = [f for f in rep.fallbacks if f.stage == "ownership" and "thin plate" in f.what]
    assert len(plate) == 1 and plate[0].count == 1
