"""Property-based tests of the library (issue 12): whatever the images, masks, label maps, grids
and parameters, ``reconstruct`` / ``reconstruct_many`` return surfaces that pass every check,
or raise a typed library error; never another exception, never a hang, never a modified input.
An invalid case raises the error its inputs call for (``expected_error``: invalid parameters ->
InputError, a CT that is no CT -> VolumeTypeError, an empty segment -> EmptySegmentError, a
segment outside the CT -> NoOverlapError, ...); bone-like scenes with valid parameters succeed
at a stated rate, and hand-made valid cases succeed.

Strategies and the harness are in ``test_properties_strategies.py``; the command line has
``test_properties_cli.py``. CI runs a fixed, derandomized set (``BW_HYPOTHESIS_PROFILE=ci``,
the default); a campaign by hand::

    BW_HYPOTHESIS_PROFILE=campaign BW_CAMPAIGN_FACTOR=10 BW_PROPERTY_LOG=/tmp/campaign.jsonl \\
        .venv/bin/python -m pytest Testing/test_properties.py Testing/test_properties_cli.py -q
    .venv/bin/python Testing/test_properties_strategies.py /tmp/campaign.jsonl
"""

import os
import sys

import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import example, given, note
from hypothesis import strategies as st

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from test_properties_strategies import (FAST_BASE, SCHEMA, Obj, _phantomish_scene,  # noqa: E402
                                        any_scenes, bone_scenes, examples, expected_error,
                                        expected_error_many, invalid_value, parameter_sets,
                                        run_case, valid_value)

from BoneWatertightLib.errors import InputError, MemoryLimitError  # noqa: E402
from BoneWatertightLib.params import Parameters  # noqa: E402
from BoneWatertightLib.pipeline import reconstruct, reconstruct_many  # noqa: E402
from BoneWatertightLib.stages import prepare as prepare_stage  # noqa: E402


@pytest.fixture(scope="module", autouse=True)
def _open3d_loaded():
    # open3d's import (seconds) is not part of any example's time.
    from BoneWatertightLib.stages.poisson import import_open3d

    import_open3d()


# ---------------------------------------------------------------------------- parameters

@st.composite
def one_parameter(draw):
    name = draw(st.sampled_from(sorted(SCHEMA)))
    spec = SCHEMA[name]
    good = draw(st.booleans())
    value = draw(valid_value(spec) if good else invalid_value(spec))
    return name, value, good


@given(one_parameter())
@examples(300)
def test_every_invalid_value_is_refused_naming_the_parameter(case):
    """validate(): an invalid value of any parameter -> InputError naming it; a valid one is
    accepted (the other parameters at their defaults)."""
    name, value, good = case
    params = Parameters(**{name: value})
    if good:
        if name in ("h0", "ht") and value is not None:
            # a single threshold is compared with the default theta_max only
            try:
                params.validate()
            except InputError as exc:
                assert "Thresholds out of order" in str(exc)
            return
        params.validate()
        return
    with pytest.raises(InputError) as info:
        params.validate()
    assert name in str(info.value)


@given(parameter_sets(invalid_rate=0.3, base={}))
@examples(200)
def test_parameter_sets_validate_or_raise_input_error(drawn):
    overrides, valid = drawn
    note(repr(overrides))
    params = Parameters(**overrides)
    try:
        params.validate()
    except InputError:
        return
    except Exception as exc:  # pragma: no cover - the property
        raise AssertionError(f"validate() raised {type(exc).__name__}: {exc}") from exc
    assert valid, f"invalid values accepted: {overrides}"


# ---------------------------------------------------------------------------- one bone

@st.composite
def single_cases(draw):
    spacing = draw(st.one_of(st.none(), st.none(), st.floats(0.3, 5.0),
                             st.sampled_from([0.3, 0.5, 1.0, 2.0]),
                             st.floats(0.05, 0.3)))
    scene = draw(any_scenes(work_spacing=spacing if spacing else None))
    overrides, valid = draw(parameter_sets(invalid_rate=0.05))
    if spacing is not None:
        overrides["spacing"] = spacing
        if spacing < 0.3:  # keep the example small: refused unless tiny
            overrides["max_memory_gb"] = 0.25
    return scene, overrides


@given(single_cases())
@example((_phantomish_scene(), dict(FAST_BASE)))
@example((_phantomish_scene(segment="voxel"), dict(FAST_BASE)))
@example((_phantomish_scene(segment="border"), dict(FAST_BASE)))
@example((_phantomish_scene(background="flat", background_hu=0.0, objects=[], labels=[],
                            segment="random"), {}))
@examples(24)
def test_reconstruct_valid_surface_or_typed_error(case):
    scene, overrides = case
    ct, mask = scene.ct(), scene.label_map()
    params = Parameters(**overrides)
    describe = {"scene": scene.describe(), "params": {k: repr(v) for k, v in overrides.items()}}
    note(repr(describe))
    run_case("reconstruct", describe, lambda progress: reconstruct(ct, mask, params, progress),
             [ct, mask], params, expect=expected_error(ct, mask, overrides))


# Bone-like scenes (bone_scenes: a cortical object well inside the CT, labelled, any grid,
# direction and pixel type) with valid parameters: at least this fraction must give a surface.
# Measured (FAST_BASE), 48 random scenes: 21 (44 %) at main 1920262, 25 (52 %) before issue
# 18; the CI draw 12 of 12. Nearly every failure is a PlausibilityError ("n % of what the
# segment clearly covers is outside the surface"), 23 of 26 with a label 0.5-2 mm larger than
# an object of 3-6 mm semi-axes. A campaign list below the rate is a finding (the plausibility
# gate refusing valid cases), not noise to retry.
BONE_SCENE_SUCCESS_RATE = 1 / 3


@given(st.lists(bone_scenes(max_objects=1), min_size=12, max_size=12))
@examples(1)
def test_bone_like_scenes_with_valid_parameters_succeed_at_the_stated_rate(scenes):
    """A pipeline that refused everything would pass the typed-error property: valid,
    bone-like inputs must give surfaces at the stated rate (each then passes every check),
    and what fails fails in the reconstruction, never as bad input. A scene the rules of
    expected_error refuse (a noise-free CT with so few values that it is a label map) must
    raise that error and is not counted."""
    outcomes = []
    for scene in scenes:
        ct, mask = scene.ct(), scene.label_map()
        params = Parameters(**FAST_BASE)
        expect = expected_error(ct, mask, FAST_BASE)
        outcome = run_case("bone scenes", {"scene": scene.describe()},
                           lambda progress: reconstruct(ct, mask, params, progress),
                           [ct, mask], params, expect=expect)
        if expect is None:
            outcomes.append(outcome)
    note(repr(outcomes))
    assert len(outcomes) >= 6, outcomes
    assert outcomes.count("ok") >= BONE_SCENE_SUCCESS_RATE * len(outcomes), outcomes
    assert not {"InputError", "VolumeTypeError", "EmptySegmentError", "NoOverlapError"} & set(outcomes)


_OBLIQUE = np.array([[0.36, 0.48, -0.8], [-0.8, 0.6, 0.0], [0.48, 0.64, 0.6]])


@pytest.mark.parametrize("scene", [
    _phantomish_scene(),
    _phantomish_scene(label_grid="coarse", extra={"factor": 2.0}),  # a coarse (AI-like) label
    _phantomish_scene(direction=_OBLIQUE, pixel="float32"),
], ids=["plain", "coarse-label", "oblique-float"])
def test_hand_made_valid_cases_succeed(scene):
    ct, mask = scene.ct(), scene.label_map()
    params = Parameters(**FAST_BASE)
    run_case("valid", {"scene": scene.describe()},
             lambda progress: reconstruct(ct, mask, params, progress), [ct, mask], params,
             expect="ok")


def _inputs(scene, ct_is_label_map=False):
    labels = scene.label_map()
    return (labels if ct_is_label_map else scene.ct()), labels


_SHEAR = np.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("inputs, overrides, expect", [
    (_inputs(_phantomish_scene()), dict(FAST_BASE, h0=100.0, ht=300.0), "InputError"),
    (_inputs(_phantomish_scene()), dict(FAST_BASE, poisson_depth=99), "InputError"),
    (_inputs(_phantomish_scene(direction=_SHEAR)), dict(FAST_BASE), "VolumeTypeError"),
    (_inputs(_phantomish_scene(size=(36, 36, 1))), dict(FAST_BASE), "VolumeTypeError"),
    (_inputs(_phantomish_scene(), ct_is_label_map=True), dict(FAST_BASE), "VolumeTypeError"),
    (_inputs(_phantomish_scene(segment="empty")), dict(FAST_BASE), "EmptySegmentError"),
    (_inputs(_phantomish_scene(label_grid="far", label_offset=1e4)), dict(FAST_BASE),
     "NoOverlapError"),
], ids=["thresholds-order", "out-of-range", "sheared", "one-slice", "label-map-as-ct", "empty",
        "outside"])
def test_each_invalid_case_raises_its_error(inputs, overrides, expect):
    """One hand-made case per rule of expected_error, so that each rule is exercised (and the
    rule itself is checked against the library's answer)."""
    ct, mask = inputs
    assert expected_error(ct, mask, overrides) == expect
    params = Parameters(**overrides)
    run_case("invalid", {"expect": expect},
             lambda progress: reconstruct(ct, mask, params, progress), [ct, mask], params,
             expect=expect)


# ---------------------------------------------------------------------------- several bones

@st.composite
def many_cases(draw):
    spacing = draw(st.one_of(st.none(), st.floats(0.4, 3.0)))
    scene = draw(any_scenes(work_spacing=spacing, max_objects=3))
    overrides, _ = draw(parameter_sets(invalid_rate=0.05))
    if spacing is not None:
        overrides["spacing"] = spacing
    present = [v for v in scene.labels if v]
    pool = present + [draw(st.integers(0, 70000))]
    targets = draw(st.lists(st.sampled_from(pool), min_size=1, max_size=3))
    if draw(st.booleans()):
        targets = list(dict.fromkeys(targets))
    neighbours = draw(st.one_of(st.sampled_from(["auto", "none", None]),
                                st.lists(st.sampled_from(pool), max_size=2)))
    keep_going = draw(st.booleans())
    return scene, overrides, targets, neighbours, keep_going


@given(many_cases())
@example((_phantomish_scene(
    size=(44, 30, 30),
    objects=[Obj("ellipsoid", np.array([11.0, 15.0, 18.0]), np.array([8.0, 9.0, 11.0]), 1200.0,
                 2.0, np.array([1.0, 0, 0])),
             Obj("ellipsoid", np.array([31.0, 15.0, 18.0]), np.array([8.0, 9.0, 11.0]), 900.0,
                 1.5, np.array([1.0, 0, 0]))], labels=[3, 7]),
    dict(FAST_BASE), [3, 7], "auto", True))
@examples(12)
def test_reconstruct_many_valid_surfaces_or_typed_errors(case):
    scene, overrides, targets, neighbours, keep_going = case
    ct, labels = scene.ct(), scene.label_map()
    params = Parameters(**overrides)
    targets_in = list(targets)
    neighbours_in = list(neighbours) if isinstance(neighbours, list) else neighbours
    describe = {"scene": scene.describe(), "params": {k: repr(v) for k, v in overrides.items()},
                "targets": targets, "neighbours": neighbours, "keep_going": keep_going}
    note(repr(describe))
    run_case("reconstruct_many", describe,
             lambda progress: reconstruct_many(ct, labels, targets, params, progress,
                                               neighbours=neighbours, keep_going=keep_going,
                                               names={t: f"bone {t}" for t in targets}),
             [ct, labels], params, expect=expected_error_many(ct, labels, overrides, targets))
    assert targets == targets_in
    assert neighbours == neighbours_in


# ---------------------------------------------------------------------------- huge grids

@st.composite
def huge_cases(draw):
    size = draw(st.tuples(*[st.integers(40, 96)] * 3))
    ct_spacing = draw(st.tuples(*[st.floats(1.0, 4.0)] * 3))
    spacing = draw(st.floats(0.05, 0.5))
    memory = draw(st.one_of(st.floats(0.25, 8.0), st.just(256.0)))
    return size, ct_spacing, spacing, memory


@given(huge_cases())
@examples(12)
def test_huge_working_grids_are_refused_before_the_work(case):
    """A working grid beyond the memory limit (or the element limit) is refused quickly with
    MemoryLimitError naming a spacing that fits; nothing is allocated first."""
    size, ct_spacing, spacing, memory = case
    arr = np.random.default_rng(0).normal(40.0, 10.0, size[::-1]).astype(np.int16)
    arr[2:-2, 2:-2, 2:-2] += 1200
    ct = sitk.GetImageFromArray(arr)
    ct.SetSpacing(ct_spacing)
    lab = sitk.GetImageFromArray((arr > 500).astype(np.uint8))
    lab.CopyInformation(ct)
    extent = (np.array(size) - 1) * np.array(ct_spacing)
    need = prepare_stage.estimate_memory_bytes(extent, spacing)
    voxels = float(np.prod(np.floor(extent / spacing) + 1))
    limit = getattr(prepare_stage, "MAX_GRID_VOXELS", float("inf"))
    if need <= memory * 1024 ** 3 and voxels <= limit:
        return  # it would be accepted: not this test's subject (it would take minutes)
    params = Parameters(spacing=spacing, max_memory_gb=memory, **FAST_BASE)
    describe = {"size": size, "ct_spacing": ct_spacing, "spacing": spacing, "memory": memory}

    def check(result, outcome):
        assert outcome == "MemoryLimitError", outcome

    run_case("huge", describe, lambda progress: reconstruct(ct, lab, params, progress),
             [ct, lab], params, check)
