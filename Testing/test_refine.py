"""The edge refinement's automatic level (the blurred-slab model, stages/refine.py)."""

import numpy as np
import pytest
from scipy import ndimage
from scipy.special import ndtr

from BoneWatertightLib.stages import refine
from test_pipeline import sphere_mesh


def test_slab_level_is_the_half_maximum_for_thick_cortex_and_rises_for_thin():
    assert refine.slab_edge_level(1.0) == pytest.approx(0.5, abs=0.03)
    # a slab with nothing behind it (fall 1), w = 2 s: its peak is 2 Phi(1) - 1 = 0.683 of the
    # contrast, its border at (Phi(2) - 1/2) / 0.683 = 0.698 of the peak (the profile's valley,
    # measured 2 mm outside the peak as a profile is, is a little above the soft tissue)
    q = 2 * ndtr(1.0) - 1
    assert refine.slab_edge_level(q) == pytest.approx((ndtr(2.0) - 0.5) / q, abs=0.03)
    levels = refine.slab_edge_level(np.linspace(0.3, 1.0, 15))
    assert np.all(np.diff(levels) <= 1e-12) and levels[0] <= refine.SLAB_LEVEL_RANGE[1]
    # a step (the profile does not fall behind its peak) keeps about the half maximum
    assert refine.slab_edge_level(q, fall=0.0) == pytest.approx(0.5, abs=0.03)
    # a thin cortex over cancellous bone falls part of the way: its border is much nearer the
    # slab's level than the half maximum (the level a linear blend of the two gave: 0.62)
    assert refine.slab_edge_level(0.3, fall=0.3) > 0.7
    assert np.all(np.diff(refine.slab_edge_level(0.4, np.linspace(0, 1, 11))) > -0.03)
    # a profile without a contrast (NaN) gets no level, as before (no edge there)
    assert np.isnan(refine.slab_edge_level(np.array([0.5, np.nan]), np.array([np.nan, 0.3]))).all()


def _half_thin_ball(radius=12.0, thin=0.8, d=0.25, blur=0.8, solid_top=True, cortex=1500.0,
                    marrow=-50.0):
    """A ball whose upper half (z > 0) is solid cortex (``cortex`` HU) and whose lower half is
    a cortex ``thin`` mm thick around ``marrow`` (HU; fat by default), in soft tissue (40 HU),
    blurred by a Gaussian of ``blur`` mm; without ``solid_top`` the cortex is thin everywhere."""
    n = int(2 * (radius + 6) / d)
    g = (np.arange(n) + 0.5) * d - (radius + 6)
    z, y, x = np.meshgrid(g, g, g, indexing="ij")
    r = np.sqrt(x * x + y * y + z * z)
    ct = np.full(r.shape, 40.0)
    ct[r <= radius] = marrow
    ct[(r <= radius) & (((z > 0) & solid_top) | (r > radius - thin))] = cortex
    ct = ndimage.gaussian_filter(ct, blur / d).astype(np.float32)
    return ct, d, radius + 6 - 0.5 * d  # grid millimetres = index * d


def test_auto_level_finds_the_border_of_thin_cortex_where_the_half_maximum_is_outside():
    ct, d, shift = _half_thin_ball()
    s = sphere_mesh(12.3, 0.6)
    v, f = s.vertices, s.faces
    v = v + shift
    results = {}
    for level in (0.5, None):
        out, _, frac, _ = refine.refine_to_edges(v, f, ct, d, ht=200.0, edge_level=level)
        p = out - shift
        err = np.linalg.norm(p, axis=1) - 12.0
        low = p[:, 2] < -3.0
        results[level] = (float(err[low].mean()), float(err[~low & (p[:, 2] > 3.0)].mean()))
        assert frac > 0.95
    thin_half, thick_half = results[0.5]
    thin_auto, thick_auto = results[None]
    # the half maximum of the blurred thin cortex lies outside the bone; the model corrects it
    assert thin_half > 0.15
    assert abs(thin_auto) < 0.5 * thin_half
    # where the cortex is thick both are the half maximum
    assert abs(thick_auto - thick_half) < 0.05
    assert abs(thick_auto) < 0.1


def test_auto_level_finds_the_border_of_thin_cortex_over_cancellous_bone_on_thick_slices():
    """A ball whose lower half is a 0.7 mm cortex (1250 HU) over cancellous bone (170 HU), its
    upper half solid cortex, blurred by 1.3 mm (a vertebral body on 3 mm slices): the profile
    falls only ~0.3 behind its peak, and the half maximum lies 0.8 mm outside the border. The
    level the model gives for such a fall finds the border (a blend of the half maximum and
    the slab's level by the fall left it 0.28 mm outside)."""
    ct, d, shift = _half_thin_ball(thin=0.7, blur=1.3, cortex=1250.0, marrow=170.0)
    s = sphere_mesh(12.3, 0.6)
    err = {}
    for level in (0.5, None):
        out, _, frac, _ = refine.refine_to_edges(s.vertices + shift, s.faces, ct, d, ht=200.0,
                                                 edge_level=level)
        p = out - shift
        err[level] = float((np.linalg.norm(p, axis=1) - 12.0)[p[:, 2] < -3.0].mean())
        assert frac > 0.95
    assert err[0.5] > 0.6
    assert abs(err[None]) < 0.15


def test_the_edge_is_the_outer_layers_not_a_dip_inside_a_shell():
    """A shell of two cortices (outer 11.2-12 mm, 1200 HU; inner 8.3-9.8 mm, 1500 HU) with
    cancellous bone between them (150 HU), blurred: the brightest sample inside a vertex near
    the outer surface is the inner cortex, and its first crossing of the level is the dip
    between them. The edge is the outer cortex's: there the profile rises to bone again."""
    d, radius = 0.25, 12.0
    n = int(2 * (radius + 6) / d)
    g = (np.arange(n) + 0.5) * d - (radius + 6)
    z, y, x = np.meshgrid(g, g, g, indexing="ij")
    r = np.sqrt(x * x + y * y + z * z)
    ct = np.full(r.shape, 40.0)
    ct[r <= radius] = 1200.0
    ct[r <= radius - 0.8] = 150.0
    ct[r <= 9.8] = 1500.0
    ct[r <= 8.3] = 100.0
    ct = ndimage.gaussian_filter(ct, 0.5 / d).astype(np.float32)
    shift = radius + 6 - 0.5 * d
    s = sphere_mesh(12.5, 0.6)
    v = s.vertices + shift
    _, t, ok, _ = refine.edge_crossings(v, s.faces, ct, d, 200.0, 0.5)
    assert ok.mean() > 0.95
    # at the outer border (r = 12, t = -0.5 from r = 12.5; the half maximum of a blurred thin
    # cortex lies a little outside it), not in the dip (r ~ 10.4, t ~ -2)
    assert -0.6 < np.median(t[ok]) < -0.15
    assert np.percentile(t[ok], 5) > -0.8


def test_a_bone_thin_everywhere_is_measured_against_the_runs_full_contrast():
    """Its own thickest cortex is thin too, so against its own contrast the model sees no
    thin cortex and keeps the half maximum, outside the bone; against the full contrast of a
    thick cortex in the same run (1500 - 40 HU blurred as a step: ~1460) it finds the
    border. The larger of the two is used; a smaller shared one changes nothing."""
    ct, d, shift = _half_thin_ball(thin=0.6, solid_top=False)
    s = sphere_mesh(12.3, 0.6)
    v = s.vertices + shift
    err = {}
    for key, shared in (("own", None), ("shared", 1460.0), ("smaller", 100.0)):
        info = {}
        out, _, frac, _ = refine.refine_to_edges(v, s.faces, ct, d, ht=200.0,
                                                 shared_reference=shared, info=info)
        err[key] = float((np.linalg.norm(out - shift, axis=1) - 12.0).mean())
        assert frac > 0.95
        if key == "shared":
            assert info["reference_hu"] == pytest.approx(1460.0)
            assert info["own_reference_hu"] < 1000.0
    assert err["own"] > 0.2
    assert abs(err["shared"]) < 0.5 * err["own"]
    assert err["smaller"] == pytest.approx(err["own"], abs=1e-9)
    assert refine.full_contrast(np.nan, None) != refine.full_contrast(np.nan, None)  # NaN
    assert refine.full_contrast(500.0, np.nan) == 500.0


def test_a_spike_of_the_surface_is_pulled_onto_the_edge_with_its_neighbours():
    """A vertex that stands 1 mm out of a sphere lying on a solid ball's edge: its own edge
    target is 1 mm inward, its neighbours' about 0, so its shift disagrees with theirs; but
    its target lies with theirs, and the refinement must take the spike out (before, the
    outlier test dropped its target and the Laplacian term kept the spike)."""
    ct, d, shift = _half_thin_ball(thin=12.0)
    s = sphere_mesh(12.0, 0.6)
    v, f = s.vertices.copy(), s.faces
    n = v / np.linalg.norm(v, axis=1, keepdims=True)
    tip = int(np.argmax(v[:, 0]))
    v[tip] += 1.0 * n[tip]
    out, _, _, _ = refine.refine_to_edges(v + shift, f, ct, d, ht=200.0, edge_level=None)
    err = np.linalg.norm(out - shift, axis=1) - 12.0
    assert abs(err[tip]) < 0.3, err[tip]
    assert np.percentile(np.abs(err), 99) < 0.15


def test_the_back_off_keeps_the_part_of_a_step_that_flips_nothing():
    """A vertex pushed past its neighbour flips triangles; half of that step does not. The
    plain back-off puts it all the way back; with halvings it keeps a part of the step, and
    no triangle is flipped either way."""
    from BoneWatertightLib.mesh.operators import face_normals, safe_update

    s = sphere_mesh(10.0, 1.0)
    v, f = s.vertices, s.faces
    k = 0
    first = f[np.flatnonzero((f == k).any(axis=1))[0]]
    j = int(first[first != k][0])  # a neighbour of k
    new = v.copy()
    new[k] = v[k] + 1.6 * (v[j] - v[k])
    before = face_normals(v, f)
    assert (np.einsum("ij,ij->i", before, face_normals(new, f)) < 0).any()
    for halvings in (0, refine.BACKOFF_HALVINGS):
        out, ok, _ = safe_update(v, new, f, intersections=False, halvings=halvings)
        assert ok
        assert (np.einsum("ij,ij->i", before, face_normals(out, f)) >= 0).all()
        moved = np.linalg.norm(out[k] - v[k]) / np.linalg.norm(new[k] - v[k])
        if halvings:
            assert 0.1 < moved < 1.0, moved
        else:
            assert moved == 0.0


def test_the_refinement_moves_no_vertex_farther_than_its_bound_in_all():
    """A sphere 3 mm outside a solid ball's edge: each pass may move a vertex by at most
    MAX_SHIFT_MM, and so may the whole refinement (before, three passes took it 3 mm: the
    thin rim of a cup on 2.5 mm slices, whose blurred edge recedes, was pulled 3.8 mm in)."""
    ct, d, shift = _half_thin_ball(thin=12.0)
    s = sphere_mesh(15.0, 0.6)
    out, moved, _, _ = refine.refine_to_edges(s.vertices + shift, s.faces, ct, d, ht=200.0,
                                               edge_level=None)
    r = np.linalg.norm(out - shift, axis=1)
    assert np.abs(moved).max() <= refine.MAX_SHIFT_MM + 0.05
    assert np.all(r > 15.0 - refine.MAX_SHIFT_MM - 0.05) and np.median(r) < 13.7
