"""The fast primitives give the values of the slow, plain ones they replace (issue 19).

- ``prepare.bspline_resample``: the working grid's cubic B-spline interpolation, axis by axis,
  against SimpleITK's ``Resample`` with ``sitkBSpline`` on the same grid (oblique directions,
  anisotropic spacing, a single slice).
- ``distance.signed_distance``: one two-label transform against the difference of the two
  one-sided transforms (and against scipy's exact transform).
- ``operators.solve_spd``: the three columns' conjugate gradients iterated together, against
  scipy's ``cg`` column by column and a direct solve.
"""

import os

import numpy as np
import pytest
import SimpleITK as sitk
from scipy import ndimage

from BoneWatertightLib.mesh.distance import distance_inside, distance_outside, signed_distance
from BoneWatertightLib.stages import threshold
from BoneWatertightLib.stages.prepare import bspline_resample


def _oblique_direction(rng) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


@pytest.mark.parametrize("shape_zyx, spacing_xyz, d", [
    ((18, 40, 36), (0.7, 0.7, 2.5), 0.5),     # thick slices, finer grid
    ((9, 11, 13), (1.0, 1.0, 1.0), 0.6),      # isotropic
    ((30, 6, 25), (0.9, 3.0, 0.4), 0.45),     # every axis different
    ((1, 12, 10), (0.8, 0.8, 1.0), 0.5),      # a single slice
    ((16, 16, 16), (0.5, 0.5, 0.5), 1.3),     # a coarser grid than the CT
    ((18, 40, 36), (0.7, 0.7, 2.5), (0.9, 0.45, 0.3)),  # a step per axis (z, y, x)
])
def test_bspline_resample_matches_simpleitk(shape_zyx, spacing_xyz, d):
    rng = np.random.default_rng(sum(shape_zyx))
    arr = (ndimage.gaussian_filter(rng.normal(0.0, 400.0, shape_zyx), 1.0) * 4
           + rng.normal(0.0, 50.0, shape_zyx)).astype(np.float32)
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing(spacing_xyz)
    img.SetOrigin((12.5, -40.0, 7.25))
    img.SetDirection(_oblique_direction(rng).ravel().tolist())
    extent = [(n - 1) * s for n, s in zip(img.GetSize(), spacing_xyz)]
    step_xyz = [d] * 3 if np.isscalar(d) else list(d)[::-1]
    size = [int(np.floor(e / st + 1e-9)) + 1 for e, st in zip(extent, step_xyz)]
    ref = sitk.Image(size, sitk.sitkFloat32)
    ref.SetSpacing(step_xyz)
    ref.SetOrigin(img.GetOrigin())
    ref.SetDirection(img.GetDirection())
    want = sitk.GetArrayFromImage(sitk.Resample(img, ref, sitk.Transform(), sitk.sitkBSpline,
                                                -1000.0, sitk.sitkFloat32))
    got = bspline_resample(arr, spacing_xyz[::-1], d, tuple(reversed(size)))
    assert got.shape == want.shape and got.dtype == np.float32
    # float32 arithmetic on both sides; values span about +-1500
    assert np.abs(got - want).max() < 2e-3
    # the input is not modified, and a constant stays constant (the weights sum to 1)
    flat = bspline_resample(np.full(shape_zyx, 300.0, np.float32), spacing_xyz[::-1], d,
                            tuple(reversed(size)))
    assert np.allclose(flat, 300.0, atol=1e-3)


@pytest.mark.parametrize("sampling", [1.0, (0.7, 1.0, 1.3)])
def test_signed_distance_is_the_two_sided_difference(sampling):
    rng = np.random.default_rng(3)
    mask = ndimage.gaussian_filter(rng.random((30, 34, 38)), 2.0) > 0.5
    got = signed_distance(mask, sampling)
    want = distance_outside(mask, sampling) - distance_inside(mask, sampling)
    assert got.dtype == np.float32
    assert np.array_equal(got, want)
    exact = (ndimage.distance_transform_edt(~mask, sampling=sampling)
             - ndimage.distance_transform_edt(mask, sampling=sampling))
    assert np.abs(got - exact).max() < 1e-4
    assert (got[mask] < 0).all() and (got[~mask] > 0).all()


def test_signed_distance_of_an_empty_or_full_mask():
    empty = np.zeros((5, 6, 7), bool)
    full = np.ones((5, 6, 7), bool)
    assert np.array_equal(signed_distance(empty), distance_outside(empty) - distance_inside(empty))
    assert np.array_equal(signed_distance(full), distance_outside(full) - distance_inside(full))


def test_fill_holes_is_scipys_on_hollow_shapes_with_holes_at_the_border():
    from BoneWatertightLib.stages.threshold import fill_holes

    rng = np.random.default_rng(5)
    z, y, x = np.mgrid[:40, :36, :30]
    r = np.sqrt((y - 18) ** 2 + (x - 15) ** 2)
    shell = (r < 12) & (r > 8)                     # a tube: its bore opens at both ends
    closed = shell.copy()
    closed[10] |= r[0] < 12                         # plates close the bore: a cavity between
    closed[30] |= r[0] < 12
    noisy = closed ^ (rng.random(closed.shape) < 0.02)
    for m in (shell, closed, noisy, np.zeros((4, 5, 6), bool), np.ones((4, 5, 6), bool)):
        assert np.array_equal(fill_holes(m), ndimage.binary_fill_holes(m))
    assert fill_holes(closed)[20, 18, 15] and not closed[20, 18, 15]


def test_visible_points_with_hulls_ahead_on_threads_are_those_of_one_thread(monkeypatch):
    from BoneWatertightLib import threads
    from BoneWatertightLib.stages import visible

    # boundary voxels of a dented ellipsoid on a 0.5 mm lattice (views stop early on it)
    g = np.arange(-16.0, 16.01, 0.5)
    z, y, x = np.meshgrid(g, g, g, indexing="ij")
    inside = (x / 14) ** 2 + (y / 9) ** 2 + (z / 7) ** 2 <= 1.0
    inside &= ~(((x - 10) ** 2 + y ** 2 + (z - 5) ** 2) < 16)
    edge = inside & ~ndimage.binary_erosion(inside)
    points = np.argwhere(edge)[:, ::-1] * 0.5
    monkeypatch.setattr(visible, "HULL_THREADS", 1)
    one = visible.visible_points(points, 0.5, full=True)
    monkeypatch.setattr(visible, "HULL_THREADS", 2)
    monkeypatch.setattr(threads.os, "cpu_count", lambda: 2)
    two = visible.visible_points(points, 0.5, full=True)
    assert one[1]["views_used"] < 14  # the views stopped early: a hull ahead was not used
    assert np.array_equal(one[0], two[0]) and np.array_equal(one[2], two[2])
    assert one[1] == two[1]


def test_hybrid_filter_with_its_filters_on_threads_is_the_plain_sequence():
    from BoneWatertightLib.stages import filtering

    rng = np.random.default_rng(5)
    ct = (ndimage.gaussian_filter(rng.normal(0.0, 400.0, (30, 34, 28)), 2.0) * 6
          + rng.normal(0.0, 30.0, (30, 34, 28))).astype(np.float32)
    region = np.zeros(ct.shape, bool)
    region[5:25, 6:30, 4:20] = True
    out = filtering.hybrid_filter(ct, 0.6, sigma=0.5, rho=80.0, region=region)
    # the plain sequence: smooth, edge voxels above the region's 80th gradient percentile,
    # each moved half-way to the nearer of its 3x3x3 extremes
    smooth = ndimage.gaussian_filter(ct, 0.5 / 0.6, mode="nearest",
                                     truncate=filtering.GAUSSIAN_TRUNCATE)
    grad = ndimage.gaussian_gradient_magnitude(smooth, sigma=filtering.GRADIENT_SIGMA_VOXELS,
                                               mode="nearest")
    edge = grad > np.percentile(grad[region], 80.0)
    hi = ndimage.maximum_filter(smooth, size=3, mode="nearest")[edge]
    lo = ndimage.minimum_filter(smooth, size=3, mode="nearest")[edge]
    v = smooth[edge]
    expected = smooth.copy()
    expected[edge] = v + filtering.TOGGLE_WEIGHT * (np.where(hi - v < v - lo, hi, lo) - v)
    assert edge.any() and np.array_equal(out, expected)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_valley_filters_on_threads_equal_the_plain_filters(monkeypatch, threads):
    from BoneWatertightLib import threads as threads_module
    from BoneWatertightLib.stages import ownership

    monkeypatch.setattr(threads_module.os, "cpu_count", lambda: threads)
    rng = np.random.default_rng(threads)
    ct = (ndimage.gaussian_filter(rng.normal(0.0, 300.0, (41, 23, 30)), 1.2) * 5
          ).astype(np.float32)
    k = 2 * max(1, int(round(2.0 / 0.6))) + 1
    cube = ndimage.minimum_filter(ndimage.maximum_filter(ct, size=k, mode="nearest"),
                                  size=k, mode="nearest") - ct
    assert np.array_equal(ownership.valley_map(ct, 0.6, 2.0), cube)
    plain = np.zeros(ct.shape, np.float32)
    for axis in range(3):
        top = ndimage.minimum_filter1d(ndimage.maximum_filter1d(ct, k, axis=axis, mode="nearest"),
                                       k, axis=axis, mode="nearest") - ct
        np.maximum(plain, top, out=plain)
    assert np.array_equal(ownership.gap_valley(ct, 0.6, 2.0), plain)


@pytest.mark.parametrize("threads", [1, 2])
def test_sampling_in_chunks_on_threads_is_one_interpolation(monkeypatch, threads):
    from BoneWatertightLib import threads as threads_module
    from BoneWatertightLib.mesh import operators
    from BoneWatertightLib.stages import refine

    monkeypatch.setattr(threads_module.os, "cpu_count", lambda: threads)
    rng = np.random.default_rng(8)
    field = ndimage.gaussian_filter(rng.normal(0.0, 500.0, (30, 26, 34)), 1.5).astype(np.float32)
    points = rng.uniform(-2.0, 20.0, (5003, 3))  # some outside the grid (cval)
    plain = ndimage.map_coordinates(field, (points[:, ::-1] / 0.6).T, order=1,
                                    mode="constant", cval=-7.0)
    monkeypatch.setattr(operators, "SAMPLE_CHUNK", 1000)  # 6 chunks, the last one short
    assert np.array_equal(operators.sample_field(field, points, 0.6, cval=-7.0), plain)
    cubic = ndimage.map_coordinates(field, (points[:, ::-1] / 0.6).T, order=3, mode="constant")
    assert np.array_equal(operators.sample_field(field, points, 0.6, order=3), cubic)
    # a step per axis (x, y, z): x / 0.4, y / 0.5, z / 0.7 mm
    steps = np.array([0.4, 0.5, 0.7])
    aniso = ndimage.map_coordinates(field, (points / steps)[:, ::-1].T, order=1,
                                    mode="constant", cval=-7.0)
    assert np.array_equal(operators.sample_field(field, points, tuple(steps), cval=-7.0), aniso)

    # the refinement's profiles, a few vertices at a time: those of all vertices at once
    from vtkmodules.vtkFiltersSources import vtkSphereSource

    from BoneWatertightLib.mesh.surface import from_polydata

    src = vtkSphereSource()
    src.SetCenter(10.0, 8.0, 9.0)
    src.SetRadius(5.0)
    src.SetThetaResolution(40)
    src.SetPhiResolution(30)
    src.Update()
    sphere = from_polydata(src.GetOutput())
    monkeypatch.setattr(refine, "SAMPLE_CHUNK", 10**9)
    whole = refine.sample_profiles(sphere.vertices, sphere.faces, field, 0.6)
    monkeypatch.setattr(refine, "SAMPLE_CHUNK", 7 * 61 + 3)  # 7 vertices a chunk
    parts = refine.sample_profiles(sphere.vertices, sphere.faces, field, 0.6)
    assert whole[2].shape == (len(sphere.vertices), len(whole[1]))
    for a, b in zip(whole, parts):
        assert np.array_equal(a, b)


def test_free_memory_goes_back_to_the_system():
    import sys

    from BoneWatertightLib.memory import release_free_memory

    try:
        glibc = sys.platform.startswith("linux") and bool(os.confstr("CS_GNU_LIBC_VERSION"))
    except (AttributeError, ValueError, OSError):
        glibc = False
    assert release_free_memory() is glibc
    if not glibc or any(k.startswith("MALLOC_") for k in os.environ):
        return

    def resident_mb():
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6

    # A freed 1.6 MB block raises glibc's mmap threshold above it (as numpy's freed arrays do
    # in a run), so the 0.8 MB blocks below come from the heap, whose freed pages stay
    # resident until trimmed.
    raise_threshold = np.ones(200_000)
    del raise_threshold
    blocks = [np.ones(100_000) for _ in range(300)]  # 240 MB
    keep = blocks[-1]  # the heap's top stays in use: only a trim returns the pages below it
    del blocks
    before = resident_mb()
    assert release_free_memory()
    assert resident_mb() < before - 100.0
    assert keep.sum() == 100_000


@pytest.mark.parametrize("f", [2, 3, 7])
def test_block_majority_is_the_blocks_count(f):
    from BoneWatertightLib.stages.plausibility import _block_majority

    rng = np.random.default_rng(f)
    mask = ndimage.gaussian_filter(rng.random((23, 30, 17)), 1.0) > 0.5
    pad = [(0, (-s) % f) for s in mask.shape]
    m = np.pad(mask, pad).astype(np.int64)
    z, y, x = (s // f for s in m.shape)
    count = m.reshape(z, f, y, f, x, f).sum(axis=(1, 3, 5))
    out = _block_majority(mask, f)
    assert out.shape == count.shape and 0 < out.sum() < out.size
    assert np.array_equal(out, 2 * count >= f ** 3)


def test_solve_spd_three_columns_at_once_is_scipys_cg_per_column():
    """A mesh-Laplacian-like SPD system (regularised Laplacian of a random sparse graph), a
    warm start, and a zero right-hand side in one column: the joint iteration gives scipy's
    per-column CG iterates (to round-off) and the direct solution to CG's tolerance."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import cg, spsolve

    from BoneWatertightLib.mesh import operators

    rng = np.random.default_rng(4)
    n = 3000
    i = rng.integers(0, n, 12000)
    j = rng.integers(0, n, 12000)
    W = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)).tocsr()
    W = ((W + W.T) > 0).astype(np.float64)
    L = sp.diags(np.asarray(W.sum(axis=1)).ravel()) - W
    A = (L.T @ L + sp.diags(rng.uniform(0.05, 1.0, n))).tocsr()
    rhs = rng.normal(size=(n, 3))
    rhs[:, 1] = 0.0
    x0 = rng.normal(size=(n, 3))
    got = operators.solve_spd(A, rhs, x0)
    assert np.array_equal(got[:, 1], np.zeros(n))
    pre = sp.diags(1.0 / A.diagonal())
    exact = spsolve(A.tocsc(), rhs)
    for c in (0, 2):
        ref, info = cg(A, rhs[:, c], x0=x0[:, c], rtol=operators.CG_RTOL,
                       maxiter=operators.CG_MAX_ITERATIONS, M=pre)
        assert info == 0
        assert np.abs(got[:, c] - ref).max() <= 1e-9 * np.abs(ref).max()
        residual = np.linalg.norm(A @ got[:, c] - rhs[:, c])
        assert residual <= 1.01 * operators.CG_RTOL * np.linalg.norm(rhs[:, c])
        assert np.abs(got[:, c] - exact[:, c]).max() <= 1e-4 * np.abs(exact[:, c]).max()


@pytest.mark.parametrize("threads", [1, 2])
def test_unsupported_parts_on_slabs_and_shifted_slices_equal_the_plain_filters(monkeypatch,
                                                                              threads):
    """The support test's smoothing on slabs and its six-neighbour maximum by shifted slices
    give the plain filters' values and the same parts."""
    from BoneWatertightLib import threads as threads_module
    from BoneWatertightLib.stages import ownership

    monkeypatch.setattr(threads_module.os, "cpu_count", lambda: threads)
    rng = np.random.default_rng(5 + threads)
    parts, _ = ndimage.label(ndimage.gaussian_filter(rng.random((37, 21, 26)), 1.0) > 0.55,
                             structure=ownership.SIX)
    assert parts.max() > 3
    assert np.array_equal(threshold.six_max(parts), ndimage.maximum_filter(
        parts, footprint=ownership.SIX, mode="constant", cval=0))
    # A label with a false blob of soft tissue beside the bone (unsupported) and a marrow
    # inside its cortex (supported).
    ct = np.full((40, 30, 30), 40.0, np.float32)
    ct[8:32, 6:24, 6:24] = 900.0
    ct[12:28, 10:20, 10:20] = 30.0  # marrow, walled by cortex
    label = np.zeros(ct.shape, bool)
    label[8:32, 6:24, 6:24] = True
    label[14:20, 24:29, 12:18] = True  # false blob beside the bone
    core = ndimage.binary_erosion(label, iterations=2)
    core[14:20, 20:27, 12:18] = True
    sigma = max(1.0 / 0.5, 0.5)
    soft = ndimage.gaussian_filter(ct, sigma=sigma, mode="nearest") < 200.0
    assert np.array_equal(
        ownership._in_slabs(lambda p: ndimage.gaussian_filter(p, sigma=sigma, mode="nearest"),
                            ct, int(4.0 * sigma + 0.5)) < 200.0, soft)
    bad, pieces = ownership.unsupported_parts(ct, label, core, 0.5, level=200.0,
                                              smooth_mm=1.0)
    assert len(pieces) == 1 and bad[16, 27, 15] and not bad[20, 15, 15]



@pytest.mark.parametrize("seed", [0, 1, 2])
def test_distance_near_is_the_whole_transform_where_it_is_compared_with_its_reach(seed):
    """The joint fits' distances on the box of ``where`` grown by the reach: at the voxels of
    ``where`` within the reach they are the whole volume's transform, and compared with the
    reach they decide as it does; with ``where`` = ``mask``, at every voxel."""
    from BoneWatertightLib.stages.ownership import _distance_near

    rng = np.random.default_rng(seed)
    shape = (40, 50, 45)
    mask = ndimage.binary_dilation(rng.random(shape) > 0.9995, iterations=2)
    where = np.zeros(shape, bool)
    where[10:25, 5:30, 20:44] = rng.random((15, 25, 24)) > 0.7
    spacing, reach = 0.6, 2.5
    full = distance_outside(mask) * spacing
    near = _distance_near(mask, where, reach, spacing)
    close = where & (full <= reach)
    assert close.any() and (where & (full > reach)).any()
    np.testing.assert_array_equal(near[close], full[close])
    np.testing.assert_array_equal(near[where] <= reach, full[where] <= reach)
    assert np.isinf(near).any()  # it did not measure the whole volume
    own = _distance_near(mask, mask, reach, spacing)
    np.testing.assert_array_equal(own <= reach, full <= reach)
    np.testing.assert_array_equal(own[own <= reach], full[full <= reach])
    # nothing of the mask near where: infinitely far, as the whole transform says beyond reach
    far = np.zeros(shape, bool)
    far[0, 0, 0] = True
    empty = np.zeros(shape, bool)
    assert np.isinf(_distance_near(empty, far, reach, spacing)).all()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_plugs_grown_and_smoothed_on_their_box_equal_the_whole_grid(seed):
    # _fill_tunnels grows and smooths each plug on its box only: the values must be those of
    # the whole grid's dilation and Gaussian, bit for bit, also where a plug meets the border.
    from BoneWatertightLib.stages import poisson

    rng = np.random.default_rng(seed)
    shape = (23, 31, 27)
    within = rng.random(shape) < 0.7
    field = rng.random(shape).astype(np.float32)
    for corner in (False, True):
        plug = np.zeros(shape, bool)
        lo = [0, 0, 0] if corner else [int(rng.integers(3, 10)) for _ in shape]
        plug[lo[0]:lo[0] + 4, lo[1]:lo[1] + 6, lo[2]:lo[2] + 3] = rng.random((4, 6, 3)) < 0.6
        whole = ndimage.binary_dilation(plug, structure=np.ones((3, 3, 3), bool),
                                        iterations=2) & within
        assert np.array_equal(poisson._grown_into(plug, within, 2), whole)
        box = ndimage.find_objects(plug.astype(np.int32))[0]
        assert np.array_equal(poisson._grown_into(plug, within, 2, box=box), whole)
        ramp = ndimage.gaussian_filter(plug.astype(np.float32), sigma=poisson.REMESH_SMOOTH_SIGMA)
        expected = np.maximum(field, np.minimum(1.0, 2.0 * ramp))
        raised = field.copy()
        poisson._raise_to_ramp(raised, plug)
        assert np.array_equal(raised, expected)
    empty = np.zeros(shape, bool)
    assert not poisson._grown_into(empty, within, 2).any()
    same = field.copy()
    poisson._raise_to_ramp(same, empty)
    assert np.array_equal(same, field)


def _largest_genus(field):
    from BoneWatertightLib.stages import poisson

    return poisson.surface_genus(poisson.contour(field, (0.0, 0.0, 0.0), 1.0, 0.5, 0,
                                                 relax=False))


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_a_plug_told_apart_without_a_contour_never_hides_a_closed_tunnel(seed):
    # _fill_tunnels decides on its box whether a plug can close a tunnel and makes the whole
    # contour only then: on lace-like fields (dozens of tunnels) and random plugs, a plug it
    # rejects must never lower the genus of the largest piece of the whole contour.
    from BoneWatertightLib.stages import poisson

    rng = np.random.default_rng(seed)
    shape = (40, 44, 36)
    noise = ndimage.gaussian_filter(rng.random(shape).astype(np.float32), 2.0)
    field = np.clip((noise - noise.mean()) / (4 * noise.std()) + 0.5, 0, 1).astype(np.float32)
    field[[0, -1]] = field[:, [0, -1]] = field[:, :, [0, -1]] = 0.0
    before = _largest_genus(field)
    assert before >= 3  # lace: plugs can close something
    parts = ndimage.label(field >= 0.5)[0]
    seen = {"skipped": 0, "lowered": 0}
    for _ in range(60):
        add = np.zeros(shape, bool)
        c = [int(rng.integers(4, n - 4)) for n in shape]
        r = int(rng.integers(1, 4))
        add[c[0] - r:c[0] + r + 1, c[1] - r:c[1] + r + 1, c[2] - r:c[2] + r + 1] = True
        trial = field.copy()
        if rng.random() < 0.5:
            poisson._raise_to_ramp(trial, add)
        else:
            trial[add] = 1.0
        after = _largest_genus(trial)
        if not poisson._may_lower_genus(field, trial, 0.5, parts):
            seen["skipped"] += 1
            assert after >= before
        elif after < before:
            seen["lowered"] += 1
    assert seen["skipped"] >= 5 and seen["lowered"] >= 1, seen
    # a trial that changes no sign changes nothing
    assert not poisson._may_lower_genus(field, field.copy(), 0.5, parts)


@pytest.mark.parametrize("seed", [0, 1])
def test_raw_genus_is_the_genus_of_the_unsmoothed_contour(seed):
    # _fill_tunnels and remesh count tunnels with raw_genus (flying edges' largest piece, its
    # points not merged) instead of the unsmoothed contour: the same counts, lace or solid.
    from BoneWatertightLib.stages import poisson

    rng = np.random.default_rng(seed)
    noise = ndimage.gaussian_filter(rng.random((36, 40, 33)).astype(np.float32), 2.0)
    counts = set()
    for shift in (-0.1, 0.0, 0.1, 0.2):  # lace to solid
        field = np.clip((noise - noise.mean()) / (4 * noise.std()) + 0.5 + shift, 0, 1)
        field[[0, -1]] = field[:, [0, -1]] = field[:, :, [0, -1]] = 0.0
        counts.add(poisson.raw_genus(field))
        assert poisson.raw_genus(field) == _largest_genus(field)
    assert len(counts) >= 3
    assert poisson.raw_genus(np.zeros((5, 5, 5), np.float32)) == 0


def test_a_plug_of_a_hole_in_a_plate_is_contoured_and_a_bump_is_not():
    from BoneWatertightLib.stages import poisson

    field = np.zeros((20, 30, 30), np.float32)
    field[8:12, 3:27, 3:27] = 1.0
    field[8:12, 12:17, 12:17] = 0.0  # a hole through the plate: genus 1
    parts = ndimage.label(field >= 0.5)[0]
    plug = field.copy()
    plug[9:11, 12:17, 12:17] = 1.0
    assert _largest_genus(field) == 1 and _largest_genus(plug) == 0
    assert poisson._may_lower_genus(field, plug, 0.5, parts)
    bump = field.copy()
    bump[12:15, 5:9, 5:9] = 1.0
    assert _largest_genus(bump) == 1
    assert not poisson._may_lower_genus(field, bump, 0.5, parts)
    island = field.copy()
    island[14:17, 5:9, 5:9] = 1.0  # a piece of its own: left to the contour
    assert poisson._may_lower_genus(field, island, 0.5, parts)


def _torus_faces(n, m):
    """Faces (2 n m, 3) of an n x m torus grid (genus 1; vertex i * m + j)."""
    i, j = np.meshgrid(np.arange(n), np.arange(m), indexing="ij")
    a = i * m + j
    b = ((i + 1) % n) * m + j
    c = ((i + 1) % n) * m + (j + 1) % m
    d = i * m + (j + 1) % m
    return np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                           np.stack([a, c, d], -1).reshape(-1, 3)])


def test_surface_genus_counts_as_the_plain_euler_characteristic():
    # poisson.surface_genus counts vertices and edges on one sorted key array: the same
    # numbers as np.unique's, also on a surface with unused vertices or a non-manifold edge.
    from test_checks import icosphere

    from BoneWatertightLib.mesh import Surface
    from BoneWatertightLib.stages.poisson import surface_genus

    def plain(f):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        chi = len(np.unique(f)) - len(np.unique(edges, axis=0)) + len(f)
        return max(0, (2 - chi) // 2)

    v, f = icosphere(2)
    torus = _torus_faces(12, 7)
    two_tori = np.concatenate([torus, torus + 84])  # chi 0: (2 - chi) / 2 = 1
    shared_edge = np.concatenate([f, f[:2] + len(v)])  # two stray faces: an open piece
    unused = f + 5                                       # vertices 0-4 unused
    cases = {"sphere": (f, 0), "torus": (torus, 1), "two tori": (two_tori, 1),
             "open piece": (shared_edge, None), "unused": (unused, 0)}
    for name, (faces, expected) in cases.items():
        n = int(faces.max()) + 1
        got = surface_genus(Surface(np.zeros((n, 3)), faces))
        assert got == plain(faces), name
        if expected is not None:
            assert got == expected, name
    assert surface_genus(Surface(np.zeros((0, 3)), np.zeros((0, 3), np.int64))) == 0


@pytest.mark.parametrize("steps", [1, 2, 4])
def test_dilate_cube_is_the_iterated_binary_dilation(steps):
    # threshold.dilate_cube (a separable maximum) replaces scipy's iterated dilation by the
    # 3 x 3 x 3 cube: the same voxels, also at the border and for an empty mask.
    from BoneWatertightLib.stages.threshold import dilate_cube

    rng = np.random.default_rng(steps)
    mask = rng.random((17, 23, 19)) < 0.01
    mask[0, 0, 0] = mask[-1, 5, -1] = True
    for m in (mask, np.zeros_like(mask)):
        expected = ndimage.binary_dilation(m, structure=np.ones((3, 3, 3), bool),
                                           iterations=steps)
        assert np.array_equal(dilate_cube(m, steps), expected)


@pytest.mark.parametrize("shape", [(23, 17, 31), (1, 12, 9), (2, 2, 2)])
@pytest.mark.parametrize("steps", [1, 2, 3])
def test_six_neighbour_morphology_by_shifts_equals_scipys(shape, steps):
    """dilate6 / erode6 (shifted slices) and their compositions give scipy's iterated binary
    dilation, erosion, closing and opening with the 6-neighbour cross, dilate18 / erode18 its
    dilation and erosion with the 18-neighbourhood, the outside of the array as background - a
    slab one voxel thin and a box smaller than the steps included."""
    rng = np.random.default_rng(steps + len(shape) * sum(shape))
    mask = ndimage.gaussian_filter(rng.random(shape), 0.8) > 0.5
    six = threshold.SIX
    assert mask.any()
    assert np.array_equal(threshold.dilate6(mask, steps),
                          ndimage.binary_dilation(mask, six, iterations=steps))
    assert np.array_equal(threshold.erode6(mask, steps),
                          ndimage.binary_erosion(mask, six, iterations=steps))
    assert np.array_equal(threshold.erode6(threshold.dilate6(mask, steps), steps),
                          ndimage.binary_closing(mask, six, iterations=steps))
    assert np.array_equal(threshold.dilate6(threshold.erode6(mask, steps), steps),
                          ndimage.binary_opening(mask, six, iterations=steps))
    full = np.ones(shape, bool)
    assert np.array_equal(threshold.erode6(full, steps),
                          ndimage.binary_erosion(full, six, iterations=steps))
    eighteen = ndimage.generate_binary_structure(3, 2)
    assert np.array_equal(threshold.dilate18(mask, steps),
                          ndimage.binary_dilation(mask, eighteen, iterations=steps))
    assert np.array_equal(threshold.erode18(mask, steps),
                          ndimage.binary_erosion(mask, eighteen, iterations=steps))
    assert np.array_equal(threshold.erode18(full, steps),
                          ndimage.binary_erosion(full, eighteen, iterations=steps))
