"""Every fallback of a stage is recorded in the typed report (issue 20): each one forced here,
at the stage and through the pipeline into the report, its JSON and the summary line."""

import numpy as np
import pytest
import SimpleITK as sitk

from BoneWatertightLib.mesh import cap, operators
from BoneWatertightLib.mesh.checks import check_surface
from BoneWatertightLib.mesh.surface import mean_edge_length
from BoneWatertightLib.params import Parameters
from BoneWatertightLib.report import Fallback, FallbackLog, fallbacks_text, shape_text, to_plain
from BoneWatertightLib.stages import autothreshold, contacts, deform, refine, threshold

from test_checks import icosphere
from test_joint_stages import _edge
from test_pipeline import sphere_mesh

FAST = dict(spacing=1.0, iterations=2, views=6)


def _only(log, stage, text):
    """The one record of ``log`` at ``stage`` whose text has ``text``."""
    found = [r for r in log if r.stage == stage and text in r.what]
    assert len(found) == 1, [r.text() for r in log]
    return found[0]


def _failing_exact_check(real):
    """safe_update whose exact self-intersection check never passes (flips still checked)."""
    def fake(old, new, faces, rounds=operators.BACKOFF_ROUNDS, intersections=True, halvings=0):
        if intersections:
            return old.copy(), False, 7
        return real(old, new, faces, rounds=rounds, intersections=False, halvings=halvings)
    return fake


# ---------------------------------------------------------------------------------- the log

def test_the_log_merges_the_same_fallback_and_the_summary_counts_kinds():
    log = FallbackLog()
    log.add("deform", "redone stiffer", 1, "retries")
    log.add("deform", "redone stiffer", 2, "retries")
    log.add("cap", "smaller snap", 1, "retries", "plane k high")
    assert [(r.stage, r.count) for r in log] == [("deform", 3), ("cap", 1)]
    text = fallbacks_text(log)
    assert text.startswith("fallbacks: 2 (deform: redone stiffer, 3 retries; cap (plane k high)")
    assert fallbacks_text([]) == ""
    assert to_plain(Fallback("refine", "kept", 5, "vertices")) == {
        "stage": "refine", "what": "kept", "count": 5, "unit": "vertices", "where": ""}


# ---------------------------------------------------------------------------------- solver

def test_conjugate_gradient_stopped_short_is_recorded(monkeypatch):
    import scipy.sparse as sp

    monkeypatch.setattr(operators, "CG_MAX_ITERATIONS", 1)
    n = 50
    A = (sp.diags([-1.0, 2.05, -1.0], [-1, 0, 1], shape=(n, n))).tocsr()
    rhs = np.random.default_rng(0).normal(size=(n, 3))
    log = FallbackLog()
    operators.solve_spd(A, rhs, np.zeros((n, 3)), log, "refine")
    r = _only(log, "refine", "conjugate gradient")
    assert (r.count, r.unit) == (3, "solves")
    monkeypatch.setattr(operators, "CG_MAX_ITERATIONS", 500)
    quiet = FallbackLog()
    operators.solve_spd(A, rhs, np.zeros((n, 3)), quiet)
    assert len(quiet) == 0


# ---------------------------------------------------------------------------------- deformation

def test_deformation_falls_back_to_its_last_verified_iterate(monkeypatch):
    rng = np.random.default_rng(1)
    p = rng.normal(size=(40000, 3))
    shell = 120.0 * p / np.linalg.norm(p, axis=1, keepdims=True)
    mesh = sphere_mesh(100.0, 20.0)
    d_star = mean_edge_length(mesh.vertices, mesh.faces)
    monkeypatch.setattr(deform, "safe_update", _failing_exact_check(deform.safe_update))
    log = FallbackLog()
    deformer = deform.Deformer(mesh.vertices, mesh.faces, shell, lambda q: np.ones(len(q), bool),
                               d_star, iterations=4, beta=1e-3, fallbacks=log)
    out = deformer.run()
    # every exact check fails: iteration 3 (the first checked) is rejected, and the two
    # unchecked iterates before it are given up for M0, the last verified one
    assert np.array_equal(out, mesh.vertices)
    assert deformer.history[-1]["rejected"]
    _only(log, "deform", "iteration 3 still flipped")
    back = _only(log, "deform", "last verified iterate")
    assert back.unit == "vertices" and back.count == len(mesh.vertices)


# ---------------------------------------------------------------------------------- refinement

def _ball_ct(d=0.5, radius=10.0):
    n = int(2 * (radius + 6) / d)
    g = (np.arange(n) + 0.5) * d - (radius + 6)
    z, y, x = np.meshgrid(g, g, g, indexing="ij")
    ct = np.where(np.sqrt(x * x + y * y + z * z) <= radius, 1300.0, 40.0)
    from scipy import ndimage

    return ndimage.gaussian_filter(ct, 0.8 / d).astype(np.float32), radius + 6 - 0.5 * d


def test_a_refinement_that_fails_its_check_keeps_the_unrefined_surface(monkeypatch):
    ct, shift = _ball_ct()
    s = sphere_mesh(10.6, 1.0)
    v = s.vertices + shift
    monkeypatch.setattr(refine, "safe_update", _failing_exact_check(refine.safe_update))
    log = FallbackLog()
    out, moved, _, _ = refine.refine_to_edges(v, s.faces, ct, 0.5, 200.0, edge_level=0.5,
                                              fallbacks=log)
    assert np.array_equal(out, v) and not moved.any()
    r = _only(log, "refine", "unrefined surface is kept")
    assert (r.count, r.unit, r.where) == (len(v), "vertices", "round 1")


def test_the_automatic_edge_level_without_contrast_is_recorded():
    ct = np.full((30, 30, 30), 40.0, np.float32)
    s = sphere_mesh(5.0, 1.0)
    log = FallbackLog()
    refine.refine_to_edges(s.vertices + 7.5, s.faces, ct, 0.5, 200.0, fallbacks=log)
    _only(log, "refine", "half maximum (0.5) is used")


# ---------------------------------------------------------------------------------- thresholds

def test_the_default_soft_tissue_level_is_recorded():
    # a bone in air: no voxel around it is in the soft-tissue window
    z, y, x = np.indices((30, 30, 30))
    inside = (x - 15) ** 2 + (y - 15) ** 2 + (z - 15) ** 2 <= 64
    ct = np.where(inside, 1200.0, -1000.0)
    log = FallbackLog()
    soft, _ = autothreshold.tissue_levels(ct, inside, inside, (1.0, 1.0, 1.0), 1.0, log)
    assert soft == autothreshold.DEFAULT_SOFT_TISSUE
    _only(log, "thresholds", "measured within")
    _only(log, "thresholds", f"the default {autothreshold.DEFAULT_SOFT_TISSUE:g} HU is used")


def test_a_missing_crossing_is_flagged():
    values = np.full((5, 5, 5), 0.0)
    inside = np.zeros((5, 5, 5), bool)
    inside[2, 2, 2] = True
    values[2, 2, 2] = 100.0
    values[2, 2, 3] = 200.0  # above the level: no crossing toward +x
    points, crossed = threshold.crossing_points(values, inside, 50.0, 1.0, crossed=True)
    assert len(points) == 6 and crossed.sum() == 5
    assert points[~crossed][0] == pytest.approx([2.5, 2.0, 2.0])
    assert len(threshold.crossing_points(values, inside, 50.0, 1.0)) == 6


def test_an_opening_that_would_empty_the_mask_is_recorded():
    mask = np.zeros((9, 9, 9), bool)
    mask[4, 4, 3:6] = True  # a rod one voxel thick: opening removes all of it
    log = FallbackLog()
    out = threshold._open_close(mask, 1, 0, log, "W_H0")
    assert np.array_equal(out, mask)
    r = _only(log, "threshold", "would empty the mask")
    assert (r.count, r.where) == (3, "W_H0")


def test_the_two_windows_opened_at_once_note_their_fallbacks_in_order():
    rod = np.zeros((9, 9, 9), bool)
    rod[4, 4, 3:6] = True  # opening removes all of it: kept unopened, noted
    block = np.zeros((9, 9, 9), bool)
    block[2:7, 2:7, 2:7] = True
    for first, second, expected in ((rod, block, ["W_H0"]), (block, rod, ["W_HT"]),
                                    (rod, rod, ["W_H0", "W_HT"])):
        log = FallbackLog()
        a, b = threshold._open_close_both((first, "W_H0"), (second, "W_HT"), 1, 1, log)
        assert np.array_equal(a, threshold._open_close(first, 1, 1))
        assert np.array_equal(b, threshold._open_close(second, 1, 1))
        assert [r.where for r in log] == expected


# ---------------------------------------------------------------------------------- caps

def test_cap_retries_and_the_contour_triangulator_are_recorded(monkeypatch):
    v, f = icosphere(level=4, radius=10.0)
    flags = np.zeros(len(f), np.uint8)
    # the first cap would cross the surface near the plane: cut again with a smaller snap
    answers = iter([True])
    real = cap._crosses_near_plane
    monkeypatch.setattr(cap, "_crosses_near_plane", lambda *a: next(answers, False))
    log = FallbackLog()
    cap.cap_plane(v, f, flags, 2, +1, 4.0, _edge(v, f), log)
    r = _only(log, "cap", "smaller snap distance")
    assert (r.count, r.where) == (1, "plane k high") and "would cross the surface" in r.what
    monkeypatch.setattr(cap, "_crosses_near_plane", real)

    def lost_edge(*args):
        raise cap.CapError("a cut edge is not an edge of the cap triangulation")

    monkeypatch.setattr(cap, "triangulate_region", lost_edge)
    log = FallbackLog()
    v3, f3, _, _ = cap.cap_plane(v, f, flags, 2, +1, 4.0, _edge(v, f), log)
    assert check_surface(v3, f3).ok
    _only(log, "cap", "contour triangulator")


def test_a_cap_that_fails_on_the_border_is_cut_a_sliver_inside_and_recorded(monkeypatch):
    v, f = icosphere(level=4, radius=10.0)
    flags = np.zeros(len(f), np.uint8)
    edge = _edge(v, f)
    # every snap distance fails on the border plane itself (a surface nearly tangent to it)
    answers = iter([True] * len(cap.SNAP_FRACTIONS))
    monkeypatch.setattr(cap, "_crosses_near_plane", lambda *a: next(answers, False))
    log = FallbackLog()
    v2, f2, fl2, area = cap.cap_plane(v, f, flags, 2, +1, 4.0, edge, log)
    assert check_surface(v2, f2).ok and area > 0
    r = _only(log, "cap", "inside the image border")
    assert r.where == "plane k high" and r.count == len(cap.SNAP_FRACTIONS)
    shifted = 4.0 - cap.PLANE_SHIFTS[1] * edge
    assert f"{cap.PLANE_SHIFTS[1] * edge:.2f} mm" in r.what
    assert np.allclose(v2[np.unique(f2[fl2 == 1]), 2], shifted)  # the cap lies on the new plane
    assert v2[:, 2].max() <= shifted + 1e-9


# ---------------------------------------------------------------------------------- contacts

def _two_overlapping_spheres():
    a = list(icosphere(level=3, radius=8.0, centre=(20.0, 20.0, 21.0)))
    b = list(icosphere(level=3, radius=8.0, centre=(20.0, 20.0, 36.0)))  # 1 mm overlap
    return {1: a, 2: b}


def test_a_contact_pass_failing_its_check_is_discarded_and_counted(monkeypatch):
    monkeypatch.setattr(contacts, "safe_update", _failing_exact_check(contacts.safe_update))
    surfaces = _two_overlapping_spheres()
    before = {k: s[0].copy() for k, s in surfaces.items()}
    history = contacts.resolve_contacts(surfaces, {}, (40, 40, 60), 1.0, 0.3, passes=1)
    for k in (1, 2):
        moved, beyond, discarded, relaxed = history[0][k]
        assert moved > 0 and discarded == moved and beyond > 0 and relaxed == 0
        assert np.array_equal(surfaces[k][0], before[k])


def test_the_contact_retries_and_the_exact_push_apart_are_recorded(monkeypatch):
    from BoneWatertightLib import pipeline
    from BoneWatertightLib.progress import Progress

    # the field passes do nothing: the pair still crosses, gets the wider passes, then the
    # exact push-apart (the last resort)
    monkeypatch.setattr(pipeline._contacts, "resolve_contacts", lambda *a, **k: [])
    surfaces = _two_overlapping_spheres()
    logs = {1: FallbackLog(), 2: FallbackLog()}
    pipeline._resolve_with_retries(surfaces, {}, (40, 40, 60), 1.0, 0.3, Progress(), logs,
                                   {1: "a", 2: "b"})
    for k, other in ((1, "b"), (2, "a")):
        more = _only(logs[k], "contacts", "wider margin")
        assert (more.count, more.unit, more.where) == (pipeline.CONTACT_RETRIES, "passes",
                                                       f"with {other}")
        exact = _only(logs[k], "contacts", "moved apart exactly")
        assert exact.count > 0 and exact.unit == "vertices"
    rep = contacts.pair_report(surfaces[1][0], surfaces[1][1], surfaces[2][0], surfaces[2][1])
    assert rep["crossing_face_pairs"] == 0


# ---------------------------------------------------------------------------------- the report

def test_fallbacks_reach_the_bone_and_joint_reports_json_and_summary(monkeypatch):
    """Through the pipeline: a refinement discarded (Refinement.applied is False, not the
    claim that it ran) and the automatic thresholds' default soft tissue (shared: in the joint
    report and in every bone's)."""
    from BoneWatertightLib.pipeline import reconstruct_many
    from phantoms import make_phantom

    ph = make_phantom("tiny")
    monkeypatch.setattr(refine, "safe_update", _failing_exact_check(refine.safe_update))
    monkeypatch.setattr(autothreshold, "MIN_SHELL_VOXELS", 10 ** 9)
    labels = sitk.Cast(ph.mask != 0, sitk.sitkUInt8)
    joint = reconstruct_many(ph.ct, labels, [1], Parameters(**FAST, on_implausible="warn"))
    (bone,) = joint.bones
    rep = bone.report
    assert rep.refinement.applied is False
    _only(rep.fallbacks, "refine", "unrefined surface is kept")
    shared = _only(joint.report.fallbacks, "thresholds", "default")
    assert shared in rep.fallbacks
    assert rep.thresholds["soft_tissue_hu"] == autothreshold.DEFAULT_SOFT_TISSUE
    plain = to_plain(rep)["fallbacks"]
    assert any(f["stage"] == "refine" and f["unit"] == "vertices" for f in plain)
    assert any(f["stage"] == "thresholds" for f in to_plain(joint.report)["fallbacks"])
    text = shape_text(rep)
    assert f"fallbacks: {len(rep.fallbacks)} (" in text and "unrefined surface is kept" in text


def test_bone_left_out_of_m0_is_warned_where_the_surface_stops_short_of_it():
    """M0 leaves out missed bone whose joining adds a tunnel (poisson.remesh: fusion.dropped_far,
    join_dropped_mm3). Where that bone lies farther than LEFT_OUT_WARN_MM outside the finished
    surface (a sacrum's tip cut off by 15 mm on the 3 mm held-out pelvis), the bone says so,
    with where; nearer, inside the surface or beyond a cap plane (the image's border), it does
    not. An oblique grid: the place is given in LPS."""
    from BoneWatertightLib.pipeline import LEFT_OUT_WARN_MM, _left_out_warning
    from BoneWatertightLib.stages.poisson import Fusion
    from BoneWatertightLib.stages.prepare import Grid

    c, s = np.cos(0.4), np.sin(0.4)
    direction = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    grid = Grid(origin=np.array([10.0, -20.0, 5.0]), direction=direction, spacing=0.5,
                shape_zyx=(80, 80, 80))
    box_origin = np.array([4.0, 6.0, 8.0])            # the bone's box on the grid (x, y, z mm)
    centre = np.array([20.0, 20.0, 20.0])             # the surface's centre, box frame
    verts, faces = icosphere(level=3, radius=10.0, centre=centre)
    phys = grid.grid_to_physical(verts + box_origin)
    fusion = Fusion(info={"join_dropped_mm3": 1140.0, "join_dropped_reach_mm": 15.0})
    for outside, warned in ((15.0, True), (LEFT_OUT_WARN_MM - 1.0, False), (-5.0, False)):
        fusion.dropped_far = centre + np.array([0.0, 0.0, 10.0 + outside])
        out = _left_out_warning("sacrum", fusion, grid, box_origin, phys, faces)
        assert bool(out) == warned, (outside, out)
        if warned:
            p = grid.grid_to_physical((fusion.dropped_far + box_origin)[None, :])[0]
            assert "1.14 ml" in out[0] and "up to 15.0 mm outside" in out[0]
            assert f"LPS ({p[0]:.0f}, {p[1]:.0f}, {p[2]:.0f})" in out[0]
    # beyond a cap plane (the image's border, continued by the grid) nothing is warned
    from BoneWatertightLib.stages.prepare import CapPlane

    fusion.dropped_far = centre + np.array([0.0, 0.0, 25.0])
    at_z = fusion.dropped_far[2] + box_origin[2]
    assert _left_out_warning("sacrum", fusion, grid, box_origin, phys, faces,
                             [CapPlane(2, +1, at_z + 1.0)])
    assert _left_out_warning("sacrum", fusion, grid, box_origin, phys, faces,
                             [CapPlane(2, +1, at_z - 1.0)]) == []
    fusion.dropped_far = None
    assert _left_out_warning("sacrum", fusion, grid, box_origin, phys, faces) == []


def test_summary_line_gives_the_segments_tunnels_where_the_surface_has_fewer_or_more():
    """A sacrum whose foramina the surface closed (genus 10 against its segment's 14 on a
    held-out 0.7 x 2.5 mm pelvis) said only "genus 10": the line now gives both counts where
    they differ, and the plain count where they agree or the segment's is unknown."""
    from BoneWatertightLib.report import DistanceSummary, summary_line

    v, f = icosphere(2)
    checks = check_surface(v, f)
    assert checks.ok and checks.genus == 0
    dist = DistanceSummary.of([0.1, 0.2])

    def line(segment_genus):
        return summary_line("sacrum", checks, dist, 1.0, len(v), len(f),
                            segment_genus=segment_genus)

    assert "genus 0: the segment has 4 at its resolution" in line(4)
    for same in (0, None):
        text = line(same)
        assert "genus 0)" in text and "the segment has" not in text
