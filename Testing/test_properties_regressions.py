"""Regression tests of the crashes and gaps the property-based campaign found (issue 12), and
of the cross-parameter and memory limits. Each is a fixed, fast case."""

import os
import sys

import numpy as np
import pytest
import SimpleITK as sitk
from scipy import ndimage

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from test_properties_strategies import Obj, _phantomish_scene  # noqa: E402

from BoneWatertightLib import pipeline  # noqa: E402
from BoneWatertightLib.errors import (InputError, MemoryLimitError,  # noqa: E402
                                      ReconstructionError)
from BoneWatertightLib.mesh.surface import Surface  # noqa: E402
from BoneWatertightLib.params import Parameters  # noqa: E402
from BoneWatertightLib.pipeline import reconstruct, reconstruct_many  # noqa: E402
from BoneWatertightLib.stages import prepare  # noqa: E402
from BoneWatertightLib.stages.poisson import remesh  # noqa: E402

FAST = dict(iterations=3, poisson_depth=6, views=6)


def _box_surface(size):
    """A closed cube of edge ``size`` mm (12 triangles)."""
    v = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], float) * size
    f = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                  [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
    return Surface(v, f)


# ---------------------------------------------------------------------------- crashes found

def test_remesh_of_a_surface_smaller_than_the_edge_raises_reconstruction_error():
    """Found: a Poisson surface a few grid steps across smoothed away in the remesh; the empty
    M0 reached the deformation (ValueError: zero-size array to reduction operation)."""
    with pytest.raises(ReconstructionError, match="too small for that edge length"):
        remesh(_box_surface(0.5), edge_length=3.0)
    assert remesh(_box_surface(10.0), edge_length=1.0).n_faces > 100


def test_tiny_ct_with_a_long_edge_is_a_typed_error_not_a_crash():
    """The campaign's case: a 2 x 2 x 3 CT at 1 mm, a sheet of bone, edge_length 3 mm."""
    scene = _phantomish_scene(size=(2, 2, 3), spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0),
                              background="air", background_hu=-1000.0, noise=0.0,
                              objects=[Obj("sheet", np.zeros(3), np.array([1.31, 0.27, 0.24]),
                                           1245.0, 0.0, np.array([1.0, 0, 0]))], seed=0)
    # the cross-parameter limit says so before any work (not a failure deep in the pipeline)
    with pytest.raises(InputError, match="edge_length 3 mm is too long"):
        reconstruct(scene.ct(), scene.label_map(), Parameters(edge_length=3.0, **FAST))


@pytest.mark.parametrize("pixel, value", [("int16", -5), ("int64", 2 ** 32 + 1),
                                          ("int64", 2 ** 40)])
def test_label_values_uint32_cannot_hold_are_refused_not_cast(pixel, value):
    """Found: -5 (int16) or 2^32 + 1 (int64) were cast to uint32: -5 became 4294967291 ("no
    overlap"), 2^32 + 1 became label 1 (a silent substitute)."""
    scene = _phantomish_scene(label_pixel=pixel, labels=[value])
    ct, labels = scene.ct(), scene.label_map()
    with pytest.raises(InputError, match="labels must be 1 to 4294967295"):
        reconstruct_many(ct, labels, [value], Parameters(**FAST))
    if value == 2 ** 32 + 1:  # label 1 is also there: it must not be what is reconstructed
        arr = sitk.GetArrayFromImage(labels)
        arr[0, 0, 0] = 1
        two = sitk.GetImageFromArray(arr)
        two.CopyInformation(labels)
        with pytest.raises(InputError):
            reconstruct_many(ct, two, [1], Parameters(**FAST))


# ---------------------------------------------------------------------------- size limits

def test_spacing_too_coarse_for_the_bone_is_refused_before_the_work(monkeypatch):
    scene = _phantomish_scene()  # an 18 x 16 x 22 mm bone
    calls = []
    monkeypatch.setattr(pipeline, "hybrid_filter",
                        lambda *a, **k: calls.append(1) or pytest.fail("long work started"))
    with pytest.raises(InputError, match=r"spacing 5 mm is too coarse for segment .*at most "
                                         r"\d\.\d+ mm"):
        reconstruct(scene.ct(), scene.label_map(), Parameters(spacing=5.0, **FAST))
    assert calls == []


def test_edge_length_too_long_for_the_bone_names_one_that_fits():
    scene = _phantomish_scene()
    with pytest.raises(InputError, match=r"edge_length 5 mm is too long for segment .*at most "
                                         r"\d\.\d+ mm"):
        reconstruct(scene.ct(), scene.label_map(), Parameters(edge_length=5.0, **FAST))


def test_edge_length_too_short_for_the_memory_limit_is_refused():
    scene = _phantomish_scene(size=(60, 60, 50), objects=[Obj(
        "ellipsoid", np.array([30.0, 30.0, 30.0]), np.array([20.0, 18.0, 22.0]), 1200.0, 2.0,
        np.array([1.0, 0, 0]))])
    params = Parameters(spacing=1.0, edge_length=0.1, max_memory_gb=0.25, **FAST)
    prep = prepare.prepare_labels(scene.ct(), scene.label_map(), [1], spacing=params.spacing)
    problems = pipeline.size_problems(prep, params)
    assert isinstance(problems.get(1), MemoryLimitError), problems
    assert "edge_length 0.1 mm is too short" in str(problems[1])


def test_a_bone_too_small_fails_alone_with_keep_going():
    """A sliver label among good ones: with keep_going only that bone fails (as the CLI's
    --all-labels runs), without it the run is refused."""
    objects = [Obj("ellipsoid", np.array([13.0, 18.0, 18.0]), np.array([8.0, 9.0, 11.0]),
                   1200.0, 2.0, np.array([1.0, 0, 0])),
               Obj("box", np.array([31.0, 18.0, 18.0]), np.array([0.4, 4.0, 4.0]), 1200.0, 0.0,
                   np.array([1.0, 0, 0]))]
    scene = _phantomish_scene(size=(40, 36, 30), objects=objects, labels=[1, 2])
    ct, labels = scene.ct(), scene.label_map()
    params = Parameters(spacing=0.5, **FAST)
    with pytest.raises(InputError, match="too coarse for segment 2"):
        reconstruct_many(ct, labels, [1, 2], params)
    res = reconstruct_many(ct, labels, [1, 2], params, keep_going=True)
    assert res.bones[0].ok
    assert isinstance(res.bones[1].error, InputError)


# ---------------------------------------------------------------------------- memory limits

def test_element_limit_refuses_a_grid_whatever_the_memory_limit(monkeypatch):
    monkeypatch.setattr(prepare, "MAX_GRID_VOXELS", 1000)
    with pytest.raises(MemoryLimitError, match=r"M voxels \(at most 0 M\): use a spacing of at "
                                               r"least"):
        prepare.check_memory(np.array([20.0, 20.0, 20.0]), 0.5, 256.0)


@pytest.mark.parametrize("extent, spacing, gb", [((300.0, 250.0, 400.0), 0.3, 4.0),
                                                 ((160.0, 90.0, 60.0), 0.1, 0.25),
                                                 ((40.0, 30.0, 2000.0), 0.2, 1.0)])
def test_the_spacing_named_by_the_memory_error_fits(extent, spacing, gb):
    with pytest.raises(MemoryLimitError) as info:
        prepare.check_memory(np.array(extent), spacing, gb)
    fit = float(str(info.value).split("at least ")[1].split(" mm")[0])
    assert prepare.check_memory(np.array(extent), fit, gb) <= gb * 1024 ** 3


def test_memory_estimate_constants_are_the_measured_ones():
    """Testing/bench_memory.py measured up to 166 B per working-grid voxel all included (a
    vertebra with its neighbours, 3.2 M voxels: 504 MB); the constants keep a margin."""
    assert prepare.estimate_memory_bytes(np.array([150.0, 236.0, 88.0]), 1.0) \
        >= 1.25 * 504 * 2 ** 20
    assert prepare.BYTES_PER_VOXEL >= 120
    assert prepare.MEMORY_OVERHEAD_BYTES < 0.25 * 1024 ** 3  # max_memory_gb's minimum
    # the case: an 84 M-voxel grid grew past 3.3 GB; it must not fit 4 GB any more
    side = 84e6 ** (1 / 3) * 0.5
    with pytest.raises(MemoryLimitError):
        prepare.check_memory(np.array([side] * 3), 0.5, 4.0)


def test_poisson_warnings_do_not_reach_stderr(capfd):
    """Found: PoissonRecon printed pages of "[WARNING] ... getValue assumes leaf node" to the C
    stderr (past open3d's verbosity), so the command line's error was not one line."""
    objects = [Obj("ellipsoid", np.array([15.44, 21.27, 20.8]), np.array([6.9, 13.1, 7.15]),
                   1624.6, 1.04, np.array([1.0, 0, 0])),
               Obj("box", np.array([38.19, 21.27, 20.8]), np.array([9.91, 7.66, 12.16]), 1000.0,
                   2.0, np.array([1.0, 0, 0]))]
    scene = _phantomish_scene(size=(67, 22, 38), spacing=(0.845, 1.933, 1.095),
                              origin=(-67.7, -289.9, 110.3), background="body", noise=35.0,
                              objects=objects, labels=[208, 11], label_pixel="int16",
                              label_offset=1.0, seed=174116)
    params = Parameters(spacing=2.2231, iterations=3, views=6, poisson_depth=4, closing=4)
    capfd.readouterr()
    try:
        reconstruct_many(scene.ct(), scene.label_map(), [11], params, neighbours=[11])
    except (InputError, ReconstructionError):
        pass
    assert "WARNING" not in capfd.readouterr().err


# ---------------------------------------------------------------------------- automatic spacing

def test_auto_spacing_is_the_finest_measured_step_that_keeps_the_grid_small():
    """Issue 11's rule: 0.5 mm unless the working grid would pass AUTO_GRID_VOXELS, then the
    finest 0.01 mm step that fits, at most 1 mm."""
    lo, hi = prepare.AUTO_SPACING_RANGE_MM
    vertebra = np.array([60.0, 55.0, 45.0])
    assert prepare.auto_spacing(vertebra) == lo
    femur = np.array([113.0, 80.0, 175.0])  # the benchmark femur's crop
    d = prepare.auto_spacing(femur)
    assert lo < d < hi
    assert prepare.grid_voxels(femur, d) <= prepare.AUTO_GRID_VOXELS
    assert prepare.grid_voxels(femur, d - 0.01) > prepare.AUTO_GRID_VOXELS
    assert prepare.auto_spacing(np.array([400.0, 400.0, 900.0])) == hi
    # the estimate at the automatic spacing of a femur stays within the 2 GB
    assert prepare.estimate_memory_bytes(femur, d) <= 2 * 1024 ** 3
    # never finer than a quarter of the CT's coarsest spacing (a 3 mm CT: 0.75 mm), never
    # coarser than the range for that reason alone; fine CTs keep the rule above
    assert prepare.auto_spacing(vertebra, ct_spacing=(3.0, 3.0, 3.0)) == 0.75
    assert prepare.auto_spacing(vertebra, ct_spacing=(0.7, 0.7, 2.5)) == pytest.approx(0.62)
    assert prepare.auto_spacing(vertebra, ct_spacing=(5.0, 5.0, 8.0)) == hi
    assert prepare.auto_spacing(vertebra, ct_spacing=(0.6, 0.6, 1.0)) == lo
    assert prepare.auto_spacing(femur, ct_spacing=(0.6, 0.6, 1.0)) == d


def test_auto_spacing_always_fits_the_memory_limit_it_checks():
    """Issue 21: every bone of the 3 mm pelvis CT spans 330 x 219 x 345 mm; the rule's 1 mm
    would need 4.7 GB, which check_memory refuses at the default 4 GB. The automatic spacing
    is then the finest 0.01 mm step that fits, for any limit."""
    pelvis = np.array([330.0, 219.0, 345.0])
    assert prepare.auto_spacing(pelvis) == 1.0
    with pytest.raises(MemoryLimitError, match="at least 1.06 mm"):
        prepare.check_memory(pelvis, 1.0, 4.0)
    assert prepare.auto_spacing(pelvis, 4.0) == pytest.approx(1.06)
    for extent in (pelvis, np.array([60.0, 55.0, 45.0]), np.array([500.0, 400.0, 1200.0])):
        rule = prepare.auto_spacing(extent)
        for gb in (0.25, 1.0, 4.0, 16.0):
            d = prepare.auto_spacing(extent, gb)
            prepare.check_memory(extent, d, gb)  # never refused
            assert d >= rule
            if d > rule:  # and no finer step would have fitted
                with pytest.raises(MemoryLimitError):
                    prepare.check_memory(extent, round(d - 0.01, 2), gb)


def test_a_run_coarsens_the_automatic_spacing_to_its_memory_limit_and_says_so():
    # a bone of 60 x 56 x 64 mm: 0.5 mm would need about 0.7 GB
    scene = _phantomish_scene(size=(84, 80, 72), spacing=(1.0, 1.0, 1.0),
                              objects=[Obj("ellipsoid", np.array([42.0, 40.0, 36.0]),
                                           np.array([30.0, 28.0, 32.0]), 1200.0, 2.0,
                                           np.array([1.0, 0, 0]))])
    res = reconstruct(scene.ct(), scene.label_map(), Parameters(max_memory_gb=0.25, **FAST))
    d = res.report.input["resample_spacing_mm"]
    assert d > prepare.AUTO_SPACING_RANGE_MM[0]
    assert res.report.input["spacing_coarsened_for_memory_from_mm"] == \
        pytest.approx(prepare.AUTO_SPACING_RANGE_MM[0])
    said = [f for f in res.report.fallbacks if f.stage == "prepare"]
    assert len(said) == 1 and "max_memory_gb = 0.25" in said[0].what
    assert res.report.input["estimated_memory_gb"] <= 0.25


def test_auto_spacing_is_what_a_run_uses():
    scene = _phantomish_scene()
    res = reconstruct(scene.ct(), scene.label_map(), Parameters(**FAST))
    assert res.report.input["resample_spacing_mm"] == pytest.approx(prepare.AUTO_SPACING_RANGE_MM[0])


# ---------------------------------------------------------------------------- refinement grid

def test_refine_spacing_follows_the_ct_and_never_passes_the_working_grid():
    """The edge refinement's CT: per axis 2/3 of the CT's spacing on it, never coarser than
    the working grid, coarser when the field would be too big or not fit the memory left."""
    vertebra = np.array([60.0, 55.0, 45.0])
    steps = prepare.refine_spacing
    assert steps(vertebra, 0.5, (0.6, 0.6, 1.0)) == pytest.approx((0.4, 0.4, 0.5))
    assert steps(vertebra, 0.62, (0.7, 0.7, 2.5)) == pytest.approx((0.47, 0.47, 0.62))
    assert steps(vertebra, 0.75, (3.0, 3.0, 3.0)) == (0.75, 0.75, 0.75)
    assert steps(vertebra, 0.5, (0.1, 0.1, 0.1)) == (prepare.REFINE_GRID_MIN_MM,) * 3
    femur = np.array([113.0, 80.0, 175.0])
    r = prepare.refine_spacing(femur, 0.59, (0.6, 0.6, 1.0))  # the first steps that fit
    assert 0.4 <= r[0] == r[1] < 0.59 and r[2] == 0.59

    def voxels(st):
        return float(np.prod(np.ceil(femur / np.asarray(st)) + 1))

    assert voxels(r) <= prepare.REFINE_GRID_VOXELS
    assert voxels((r[0] - 0.01, r[1] - 0.01, r[2])) > prepare.REFINE_GRID_VOXELS \
        or r[0] == 0.4
    pelvis = np.array([330.0, 219.0, 345.0])  # too big for a field of its own: the working grid
    assert prepare.refine_spacing(pelvis, 1.0, (0.7, 0.7, 2.5)) == (1.0, 1.0, 1.0)
    tight = prepare.refine_spacing(femur, 0.59, (0.6, 0.6, 1.0), spare_bytes=40e6)
    assert r[0] < tight[0] <= 0.59
    assert voxels(tight) * prepare.REFINE_BYTES_PER_VOXEL <= 40e6 or tight[0] == 0.59


@pytest.mark.parametrize("cut", [False, True])
def test_refine_ct_is_the_working_grids_interpolation_on_a_finer_grid(cut):
    """At the nodes the two grids share, the refinement's CT holds the working grid's values:
    the same B-spline interpolation of the same crop (replicated past the border where the
    bone is cut), on an oblique CT."""
    rng = np.random.default_rng(3)
    shape = (24, 30, 28)
    arr = (ndimage.gaussian_filter(rng.normal(0.0, 300.0, shape), 1.5) * 5).astype(np.float32)
    lab = np.zeros(shape, np.uint8)
    lab[6:18, 8:22, 7:20] = 1
    if cut:
        lab[0:18, 8:22, 7:20] = 1  # touches the first slice: capped, the crop is padded
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    ct = sitk.GetImageFromArray(arr)
    ct.SetSpacing((0.9, 0.9, 1.2))
    ct.SetOrigin((-20.0, 14.0, 3.5))
    ct.SetDirection(q.ravel().tolist())
    labels = sitk.GetImageFromArray(lab)
    labels.CopyInformation(ct)
    prep = prepare.prepare_labels(ct, labels, [1], spacing=0.8)
    assert any(prep.pad[0]) == cut
    prep.refine_spacing = (0.4, 0.2, 0.8)  # x, y, z
    fine = prepare.refine_ct(prep)
    coarse = prep.ct
    assert fine.dtype == np.float32
    shared = fine[:, ::4, ::2]
    n = tuple(min(a, b) for a, b in zip(shared.shape, coarse.shape))
    assert fine.shape[0] == coarse.shape[0]
    assert abs(fine.shape[1] - 4 * coarse.shape[1]) <= 4
    assert np.abs(shared[:n[0], :n[1], :n[2]] - coarse[:n[0], :n[1], :n[2]]).max() < 1e-2
    prep.refine_spacing = (prep.grid.spacing,) * 3
    assert prepare.refine_ct(prep) is prep.ct


def test_a_run_on_a_fine_ct_refines_on_its_own_finer_grid():
    """A CT finer than the working grid: the refinement samples a field of its own (reported),
    finer across the pixels, the working step across the thick slices; the surface passes its
    checks and encloses the volume that the working grid's field gives (within 0.05 mm of
    mean thickness)."""
    from BoneWatertightLib.mesh.surface import enclosed_volume, surface_area

    scene = _phantomish_scene(size=(72, 72, 30), spacing=(0.5, 0.5, 1.2),
                              objects=[Obj("ellipsoid", np.array([18.0, 18.0, 18.0]),
                                           np.array([11.0, 9.0, 12.0]), 1200.0, 2.0,
                                           np.array([1.0, 0, 0]))])
    res = reconstruct(scene.ct(), scene.label_map(), Parameters(spacing=0.8, **FAST))
    assert res.report.input["refine_spacing_mm"] == pytest.approx([0.34, 0.34, 0.8])
    assert res.report.checks.ok
    plain = prepare.REFINE_GRID_VOXELS
    try:  # no room for a field of its own: the working grid's, as before
        prepare.REFINE_GRID_VOXELS = 1
        same = reconstruct(scene.ct(), scene.label_map(), Parameters(spacing=0.8, **FAST))
    finally:
        prepare.REFINE_GRID_VOXELS = plain
    assert same.report.input["refine_spacing_mm"] == [0.8, 0.8, 0.8]
    assert same.report.checks.ok
    a = enclosed_volume(res.surface.vertices, res.surface.faces)
    b = enclosed_volume(same.surface.vertices, same.surface.faces)
    assert not np.array_equal(res.surface.vertices, same.surface.vertices)
    assert abs(a - b) / surface_area(res.surface.vertices, res.surface.faces) < 0.05
