"""Every bad value of issue 12, through the command line, its batch and the Python API.

The command line and the batch exit with code 2 and one line ``error: ...`` that names the
parameter (and its value), before any work and without leaving a file. The Python API raises
InputError from :meth:`Parameters.validate` naming the parameter.
"""

import csv
import math
import os
import sys

import numpy as np
import pytest
import SimpleITK as sitk

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from BoneWatertightLib.app import cli  # noqa: E402
from BoneWatertightLib.errors import InputError  # noqa: E402
from BoneWatertightLib.params import Parameters  # noqa: E402
from test_cli import sphere_ct  # noqa: E402

BAD_OPTIONS = [
    (["--alpha", "0", "--beta", "0"], "alpha and beta cannot both be 0"),
    (["--edge-length", "-1"], "edge_length must be between 0.1 and 5 mm, got -1."),
    (["--edge-length", "nan"], "edge_length must be between 0.1 and 5 mm, got nan."),
    (["--edge-length", "0"], "edge_length must be between 0.1 and 5 mm, got 0."),
    (["--rho", "-1"], "rho must be between 50 and 100 %, got -1."),
    (["--rho", "nan"], "rho must be between 50 and 100 %, got nan."),
    (["--view-distance", "inf"], "view_distance must be between 1 and 50 x radius, got inf."),
    (["--margin", "nan"], "margin must be between 0 and 30 mm, got nan."),
    (["--margin", "inf"], "margin must be between 0 and 30 mm, got inf."),
    (["--margin=-inf"], "margin must be between 0 and 30 mm, got -inf."),
    (["--max-memory-gb", "0"], "max_memory_gb must be between 0.25 and 256 GB, got 0."),
    (["--max-memory-gb", "-2"], "max_memory_gb must be between 0.25 and 256 GB, got -2."),
    (["--segment-dilation", "nan"], "segment_dilation must be between 0 and 20 mm, got nan."),
    (["--spacing", "inf"], "spacing must be between 0.05 and 5 mm, got inf."),
    (["--spacing", "-0.5"], "spacing must be between 0.05 and 5 mm, got -0.5."),
    (["--h0", "nan"], "h0 must be between -500 and 4000 HU, got nan."),
    (["--edge-level", "5"], "edge_level must be between 0.3 and 0.9, got 5."),
    (["--views", "3.5"], "argument --views: invalid int value: '3.5'"),
    (["--poisson-depth", "7.0"], "argument --poisson-depth: invalid int value: '7.0'"),
    (["--iterations", "1e3"], "argument --iterations: invalid int value: '1e3'"),
    (["--max-erosions", "nan"], "argument --max-erosions: invalid int value: 'nan'"),
    (["--h0", "abc"], "argument --h0: invalid float value: 'abc'"),
    (["--ht", "400", "--h0", "300"], "Thresholds out of order"),
]


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("inputs")
    ct, mask = sphere_ct()
    sitk.WriteImage(ct, str(folder / "ct.nrrd"))
    sitk.WriteImage(mask, str(folder / "mask.nrrd"))
    return str(folder / "ct.nrrd"), str(folder / "mask.nrrd")


def one_line(err):
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


@pytest.mark.parametrize("extra, message", BAD_OPTIONS)
def test_cli_bad_value_exit_2_one_line_no_file(inputs, tmp_path, capfd, extra, message):
    ct, mask = inputs
    out = tmp_path / "out"
    code = cli.main(["--ct", ct, "--seg", mask, "--label", "1", "--out", str(out / "b.stl"),
                     "--report", str(out / "r.json"), "--picture", str(out / "b.png"),
                     "--save-intermediates", str(out / "inter"), "-q"] + extra)
    line = one_line(capfd.readouterr().err)
    assert code == 2 and message in line, line
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("extra, message", BAD_OPTIONS[:6] + BAD_OPTIONS[-6:])
def test_batch_bad_value_exit_2_no_file(inputs, tmp_path, capfd, extra, message):
    ct, mask = inputs
    with open(tmp_path / "cases.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["ct", "seg", "label", "out"])
        writer.writerow([ct, mask, "1", str(tmp_path / "out" / "b.stl")])
    code = cli.main(["--cases", str(tmp_path / "cases.csv"), "--workers", "2",
                     "--summary", str(tmp_path / "out" / "summary.csv"),
                     "--report", str(tmp_path / "out" / "{case}.json"), "-q"] + extra)
    line = one_line(capfd.readouterr().err)
    assert code == 2 and message in line, line
    assert os.listdir(tmp_path) == ["cases.csv"]


@pytest.mark.parametrize("label, message", [
    ("257", r"Label 257 cannot be in the label map .*: its voxels are uint8 \(0 to 255\). "
            "Labels present: 1."),
    ("256", "Label 256 cannot be in the label map"),
    ("0", "Label 0 is the background"),
    ("2", "Label 2 is not in the label map"),
])
def test_cli_label_value_not_there_exit_2_no_file(inputs, tmp_path, capfd, label, message):
    """Before: --label 257 on a uint8 map built label 1 (exit 0); 256 the background."""
    import re

    ct, mask = inputs
    code = cli.main(["--ct", ct, "--seg", mask, "--label", label,
                     "--out", str(tmp_path / "b.stl"), "-q"])
    line = one_line(capfd.readouterr().err)
    assert code == 2 and re.search(message, line), line
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("values, name", [
    (dict(alpha=0.0, beta=0.0), "alpha and beta"),
    (dict(alpha=0, beta=0), "alpha and beta"),
    (dict(edge_length=-1.0), "edge_length"),
    (dict(edge_length=float("nan")), "edge_length"),
    (dict(rho=-5.0), "rho"),
    (dict(rho=math.nan), "rho"),
    (dict(view_distance=math.inf), "view_distance"),
    (dict(margin=math.nan), "margin"),
    (dict(margin=math.inf), "margin"),
    (dict(max_memory_gb=0.0), "max_memory_gb"),
    (dict(max_memory_gb=-1.0), "max_memory_gb"),
    (dict(segment_dilation=math.nan), "segment_dilation"),
    (dict(views=3.0), "views"),
    (dict(views=np.float64(3.0)), "views"),
    (dict(poisson_depth=7.5), "poisson_depth"),
    (dict(max_erosions=True), "max_erosions"),
    (dict(h0="abc"), "h0"),
    (dict(h0="300"), "h0"),
    (dict(views="6"), "views"),
    (dict(spacing=np.float64("nan")), "spacing"),
    (dict(spacing="auto"), "spacing"),
    (dict(refine_edges="yes"), "refine_edges"),
    (dict(refine_edges=1), "refine_edges"),
    (dict(sigma=complex(1, 1)), "sigma"),
])
def test_python_api_refuses_with_the_parameter_named(values, name):
    with pytest.raises(InputError) as info:
        Parameters(**values).validate()
    assert str(info.value).startswith(name), str(info.value)
    assert ValueError in type(info.value).__mro__  # a ValueError for plain-Python callers


@pytest.mark.parametrize("values", [
    dict(alpha=0.0),                        # beta alone damps the step
    dict(beta=0.0),                         # alpha alone regularises it
    dict(alpha=0.0, beta=0.0, iterations=0),  # no deformation: the weights are unused
    dict(views=np.int64(6), h0=np.float32(320.0)),
    dict(spacing=None, sigma=None, edge_length=None),
])
def test_python_api_accepts_meaningful_edge_values(values):
    Parameters(**values).validate()


def test_cli_the_same_bone_twice_exit_2_no_file(inputs, tmp_path, capfd):
    """Two --label values that name one segment (a value and its name) are refused."""
    _, mask = inputs
    folder = tmp_path / "in"
    folder.mkdir()
    sitk.WriteImage(sitk.ReadImage(mask), str(folder / "mask.nrrd"))
    (folder / "labels.csv").write_text("value,name\n1,ball\n")
    code = cli.main(["--ct", inputs[0], "--seg", str(folder / "mask.nrrd"), "--label", "1",
                     "--label", "ball", "--out", str(tmp_path / "out" / "b_{label}.stl"), "-q"])
    line = one_line(capfd.readouterr().err)
    assert code == 2 and "--label 1 and --label ball are the same segment 'ball'" in line, line
    assert sorted(os.listdir(tmp_path)) == ["in"]
