"""Property-based tests of the command line (issue 12): ``BoneWatertightLib.app.cli.main`` on
generated CT and label-map files with generated options exits with a documented code (0, 2 or
3 here: 1 is an internal error, a bug), prints each error as one line ``error: ...``, leaves no
temporary or partial file, writes every promised file (each a valid surface) on success and
none at all on bad input, and never changes its input files. See test_properties.py.
"""

import hashlib
import os
import sys
import tempfile

import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import example, given, note
from hypothesis import strategies as st

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from test_properties_strategies import (SCHEMA, _phantomish_scene, cli_text,  # noqa: E402
                                        any_scenes, ct_refused, examples, invalid_value, log,
                                        run_case, valid_value)

from BoneWatertightLib.app import cli  # noqa: E402
from BoneWatertightLib.app.options import flag_of  # noqa: E402
from BoneWatertightLib.errors import EXIT_FAILED, EXIT_INPUT, EXIT_OK, EXIT_PARTIAL  # noqa: E402
from BoneWatertightLib.io import files as bwfiles  # noqa: E402
from BoneWatertightLib.io.meshes import read_surface  # noqa: E402
from BoneWatertightLib.mesh.checks import check_surface  # noqa: E402

CT_FORMATS = [".nrrd", ".nrrd", ".nii.gz", ".mha"]
SEG_FORMATS = [".nrrd", ".nrrd", ".nii.gz", ".mha"]
SURFACES = [".stl", ".ply", ".vtp", ".vtk", ".obj"]
BAD_TEXT = ["nan", "inf", "-inf", "abc", "", "1e400", "-1e9", "1e12", "3.5", "auto", "0x10",
            "1,5", " "]


@pytest.fixture(scope="module", autouse=True)
def _open3d_loaded():
    from BoneWatertightLib.stages.poisson import import_open3d

    import_open3d()


@st.composite
def option_values(draw):
    """Parameter options as command-line text: valid values, and bad text or bad values."""
    argv, bad = [], False
    names = draw(st.lists(st.sampled_from(sorted(SCHEMA)), max_size=4, unique=True))
    for name in names:
        spec = SCHEMA[name]
        if name in ("spacing", "keep_intermediates"):
            continue
        if spec.kind is bool:
            argv.append(flag_of(spec) if draw(st.booleans()) else
                        "--no-" + flag_of(spec)[2:])
            continue
        how = draw(st.sampled_from(["valid"] * 10 + ["invalid", "text"]))
        if how == "valid":
            text = cli_text(draw(valid_value(spec)))
        elif how == "invalid":
            value = draw(invalid_value(spec))
            if not isinstance(value, (int, float, str)) or value is None:
                value = "nan"
            text = cli_text(value)
        else:
            text = draw(st.sampled_from(BAD_TEXT))
        if how != "valid":
            try:  # what the command line must refuse ("auto" or "3.5" may be fine)
                spec.check(spec.parse(text))
            except (ValueError, TypeError):
                bad = True
        argv.append(f"{flag_of(spec)}={text}")
    return argv, bad


@st.composite
def cli_cases(draw):
    spacing = draw(st.one_of(st.none(), st.floats(0.4, 3.0)))
    scene = draw(any_scenes(work_spacing=spacing, max_objects=2))
    present = [v for v in scene.labels if v]
    pool = [str(v) for v in present] or ["1"]
    if draw(st.sampled_from([False] * 5 + [True])):
        pool.append(draw(st.sampled_from(["0", "999", "abc", "-1", "1.5", "70000", ""])))
    if draw(st.sampled_from([False] * 5 + [True])):
        labels = None  # --all-labels
    else:
        labels = draw(st.lists(st.sampled_from(pool), min_size=1, max_size=2,
                               unique=draw(st.sampled_from([True] * 5 + [False]))))
    params, bad = draw(option_values())
    extra = []
    fast = ["--iterations=3", "--poisson-depth=6", "--views=6"]
    if spacing is not None:
        extra.append(f"--spacing={spacing!r}")
    if draw(st.booleans()):
        extra.append("--ras")
    if draw(st.booleans()):
        extra.append("--neighbours=" + draw(st.sampled_from(["auto", "none"] + pool)))
    return dict(scene=scene, labels=labels, params=fast + params, bad=bad, extra=extra,
                ct_format=draw(st.sampled_from(CT_FORMATS)),
                seg_format=draw(st.sampled_from(SEG_FORMATS)),
                surface=draw(st.sampled_from(SURFACES)),
                report=draw(st.sampled_from([None, "r.json", "r_{label}.json"])),
                picture=draw(st.sampled_from([None] * 7 + ["p_{label}.png"])),
                intermediates=draw(st.sampled_from([None] * 4 + ["inter"])))


def _write(image, path):
    try:
        sitk.WriteImage(image, path)
    except RuntimeError:  # e.g. NIfTI cannot hold a sheared direction: use NRRD
        path = os.path.splitext(path.replace(".nii.gz", ".nii"))[0] + ".nrrd"
        sitk.WriteImage(image, path)
    return path


def _digest(path):
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        h.update(fh.read())
    return h.hexdigest()


def _all_files(folder):
    out = []
    for root, dirs, names in os.walk(folder):
        out += [os.path.join(root, n) for n in names]
    return out


def check_cli_case(case, capfd):
    scene = case["scene"]
    ct, labels = scene.ct(), scene.label_map()
    # bad input the command must refuse with exit code 2, whatever else the case holds: an
    # option it cannot take, a CT that is no CT, a label map without a painted voxel
    refuse = (case["bad"] or ct_refused(ct)
              or not np.any(sitk.GetArrayViewFromImage(labels) != 0))
    with tempfile.TemporaryDirectory(prefix="bwprop") as tmp:
        inputs = os.path.join(tmp, "in")
        outdir = os.path.join(tmp, "out")
        os.makedirs(inputs)
        ct_path = _write(ct, os.path.join(inputs, "ct" + case["ct_format"]))
        seg_path = _write(labels, os.path.join(inputs, "seg" + case["seg_format"]))
        digests = {p: _digest(p) for p in (ct_path, seg_path)}
        argv = ["--ct", ct_path, "--seg", seg_path,
                "--out", os.path.join(outdir, "bone_{label}" + case["surface"]), "-q"]
        if case["labels"] is None:
            argv.append("--all-labels")
        else:
            for label in case["labels"]:
                argv.append(f"--label={label}")
        if case["report"]:
            argv += ["--report", os.path.join(outdir, case["report"])]
        if case["picture"]:
            argv += ["--picture", os.path.join(outdir, case["picture"])]
        if case["intermediates"]:
            argv += ["--save-intermediates", os.path.join(outdir, case["intermediates"])]
        argv += case["extra"] + case["params"]
        describe = {"scene": scene.describe(), "argv": argv[4:]}
        note(repr(describe))
        capfd.readouterr()
        files_of = {}

        def check(code, outcome):
            captured = capfd.readouterr()
            err = [line for line in captured.err.splitlines() if line.strip()]
            log({"event": "cli", "code": code, "stderr": err[:3]})
            assert code in (EXIT_OK, EXIT_INPUT, EXIT_FAILED, EXIT_PARTIAL), (code, err)
            for line in err:
                assert line.startswith("error: ") and "internal error" not in line, err
            if code == EXIT_OK:
                assert not err, err
            else:
                assert err, "a failure without a message"
            several = case["labels"] is None or len(case["labels"]) > 1
            if code == EXIT_INPUT:
                # one line; with several labels one line per bone that failed (a run of
                # several bones goes on past one bone's bad input, found by the campaign)
                if several:
                    assert all(line.split(":")[1].strip() for line in err), err
                else:
                    assert len(err) == 1, err
            if refuse:
                assert code == EXIT_INPUT, (code, err)
            if case.get("expect") is not None:
                assert code == case["expect"], (code, err)
            files = _all_files(outdir) if os.path.isdir(outdir) else []
            for path in files:
                assert not bwfiles.is_temporary_name(os.path.basename(path)), path
            if code == EXIT_INPUT and not several:
                assert files == [], files
            surfaces = [p for p in files if p.endswith(case["surface"])
                        and os.path.basename(p).startswith("bone_")]
            if code == EXIT_OK:
                assert surfaces, "success without a surface file"
            if code == EXIT_PARTIAL:
                # partly done: only a run of several bones, some written, the others named
                assert several and surfaces and err, (code, err, files)
            if code == EXIT_FAILED and case["labels"] is not None and len(case["labels"]) == 1:
                assert files == [], files
            for path in surfaces:
                s = read_surface(path)
                rep = check_surface(s.vertices, s.faces,
                                    check_self_intersections=case["surface"] in (".vtp", ".vtk"))
                assert rep.ok, (path, rep.problems)
            for p, digest in digests.items():
                assert _digest(p) == digest, f"input file {p} changed"
            files_of["code"] = code

        run_case("cli", describe, lambda progress: cli.main(argv), [], check=check)
        code = files_of.get("code")
        return code


@given(case=cli_cases())
@example(case=dict(scene=_phantomish_scene(), labels=["1"], params=["--iterations=3",
              "--poisson-depth=6", "--views=6"], bad=False, extra=[], ct_format=".nrrd",
              seg_format=".nrrd", surface=".vtp", report="r.json", picture=None,
              intermediates="inter", expect=EXIT_OK))
@example(case=dict(scene=_phantomish_scene(), labels=["1"], params=["--edge-length=-1"], bad=True,
              extra=[], ct_format=".nrrd", seg_format=".nrrd", surface=".stl", report=None,
              picture=None, intermediates=None))
@examples(8)
def test_cli_documented_exit_code_one_line_no_partial_files(case, capfd):
    """Exit code 2 for every case of bad input (check_cli_case: refuse), 0 for the valid
    hand-made example; else a documented code, one line per error, no partial file."""
    check_cli_case(case, capfd)
