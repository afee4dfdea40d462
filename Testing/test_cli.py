"""The plain-Python CLI and the batch runner, end to end on a small synthetic CT.

The end-to-end tests run the real pipeline (BoneWatertightLib.pipeline.reconstruct); they
fail, not skip, when it cannot be imported.
"""

import csv
import io as stringio
import os
import subprocess
import sys

import numpy as np
import pytest
import SimpleITK as sitk

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from BoneWatertightLib.app import cli  # noqa: E402
from BoneWatertightLib import io as bwio  # noqa: E402
from BoneWatertightLib.io import meshes  # noqa: E402
from BoneWatertightLib.params import Parameters  # noqa: E402
from test_io import write_dicom_series  # noqa: E402

# Small, fast settings: the point here is the plumbing, not accuracy.
FAST = ["--spacing", "1.0", "--iterations", "3", "--poisson-depth", "6", "--views", "6", "-q"]
CENTRE_INDEX = np.array([17.5, 18.0, 17.0])
RADIUS = 9.0


def sphere_ct(direction=None):
    """A 1000 HU ball of radius 9 mm in 40 HU tissue, 1 mm voxels, and a rough mask of it."""
    n = 36
    z, y, x = np.mgrid[:n, :n, :n]
    r = np.sqrt((x - CENTRE_INDEX[0]) ** 2 + (y - CENTRE_INDEX[1]) ** 2
                + (z - CENTRE_INDEX[2]) ** 2)
    noise = np.random.default_rng(0).normal(0.0, 10.0, r.shape)
    ct = sitk.GetImageFromArray((np.where(r < RADIUS, 1000.0, 40.0) + noise).astype(np.int16))
    ct.SetOrigin((-20.0, 30.0, 100.0))
    if direction is not None:
        ct.SetDirection(direction)
    mask = sitk.GetImageFromArray((r < RADIUS - 1.5).astype(np.uint8))
    mask.CopyInformation(ct)
    return ct, mask


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    folder = tmp_path_factory.mktemp("case")
    ct, mask = sphere_ct()
    sitk.WriteImage(ct, str(folder / "ct.nrrd"))
    sitk.WriteImage(mask, str(folder / "mask.nrrd"))
    centre = np.array(ct.TransformContinuousIndexToPhysicalPoint(CENTRE_INDEX.tolist()))
    return folder, centre


@pytest.fixture(scope="module")
def lps_run(case, tmp_path_factory):
    folder, _ = case
    out = tmp_path_factory.mktemp("out")
    argv = ["--ct", str(folder / "ct.nrrd"), "--seg", str(folder / "mask.nrrd"), "--label", "1",
            "--out", str(out / "bone.ply"), "--report", str(out / "report.json")] + FAST
    return cli.main(argv), out


def run(argv, capsys):
    code = cli.main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def assert_no_files(folder):
    leftovers = [f for f in os.listdir(folder) if not f.endswith((".nrrd", ".csv"))]
    assert leftovers == [], leftovers


# ---------------------------------------------------------------------------- end to end

def test_cli_writes_surface_and_report(case, lps_run):
    import json

    _, centre = case
    code, out = lps_run
    assert code == 0
    surface = bwio.read_surface(str(out / "bone.ply"))
    radii = np.linalg.norm(surface.vertices - centre, axis=1)
    assert abs(np.median(radii) - RADIUS) < 1.0
    report = json.loads((out / "report.json").read_text())
    assert report["checks"]["ok"] is True
    assert report["coordinate_system"] == "LPS"
    assert report["output"]["n_faces"] == surface.n_faces
    assert report["inputs"]["ct"].endswith("ct.nrrd")
    assert report["distance_to_constraints_mm"]["n"] == surface.n_vertices
    assert report["timings_s"]["reconstruct"] > 0
    assert report["parameters"]["spacing"] == 1.0
    # per-stage timings come from the typed pipeline report, field by field (never null)
    import dataclasses

    from BoneWatertightLib.report import StageTimes

    stages = report["timings_s"]["stages"]
    assert set(stages) == {f.name for f in dataclasses.fields(StageTimes)}
    assert all(isinstance(v, float) and v >= 0 for v in stages.values()), stages
    assert stages["total"] > 0 and stages["poisson"] > 0
    assert report["pipeline"]["timings"] == stages
    assert report["pipeline"]["constants"]["deform"]["STATIONARY_MOVE"] == 0.02


def test_cli_ras_is_lps_with_x_y_negated(case, lps_run, tmp_path):
    folder, _ = case
    _, out = lps_run
    code = cli.main(["--ct", str(folder / "ct.nrrd"), "--seg", str(folder / "mask.nrrd"),
                     "--label", "1", "--out", str(tmp_path / "bone.ply"), "--ras"] + FAST)
    assert code == 0
    lps = bwio.read_surface(str(out / "bone.ply"))
    ras_raw = bwio.read_surface(str(tmp_path / "bone.ply"), "RAS")
    assert ras_raw.n_vertices == lps.n_vertices
    np.testing.assert_allclose(ras_raw.vertices[:, :2], -lps.vertices[:, :2], atol=1e-4)
    np.testing.assert_allclose(ras_raw.vertices[:, 2], lps.vertices[:, 2], atol=1e-4)
    with open(tmp_path / "bone.ply", "rb") as f:
        assert b"comment SPACE=RAS" in f.read(400)


def test_cli_dicom_folder_gives_same_surface(case, lps_run, tmp_path):
    folder, _ = case
    _, out = lps_run
    write_dicom_series(sitk.ReadImage(str(folder / "ct.nrrd")), str(tmp_path / "dicom"))
    code = cli.main(["--ct", str(tmp_path / "dicom"), "--seg", str(folder / "mask.nrrd"),
                     "--label", "1", "--out", str(tmp_path / "bone.ply")] + FAST)
    assert code == 0
    a = bwio.read_surface(str(out / "bone.ply"))
    b = bwio.read_surface(str(tmp_path / "bone.ply"))
    assert a.n_vertices == b.n_vertices and a.n_faces == b.n_faces
    np.testing.assert_allclose(b.vertices, a.vertices, atol=1e-3)


def test_cli_runs_as_module(tmp_path):
    """The real entry point in a fresh interpreter: exit code and the one-line error."""
    proc = subprocess.run(
        [sys.executable, "-m", "BoneWatertightLib", "--ct", str(tmp_path / "missing.nrrd"),
         "--seg", str(tmp_path / "m.nrrd"), "--label", "1", "--out", str(tmp_path / "b.stl")],
        cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [f"error: CT not found: {tmp_path / 'missing.nrrd'}"]
    assert os.listdir(tmp_path) == []


# ---------------------------------------------------------------------------- bad input

@pytest.fixture()
def bad_case(case, tmp_path):
    folder, _ = case
    return str(folder / "ct.nrrd"), str(folder / "mask.nrrd"), tmp_path


@pytest.mark.parametrize("extra, message", [
    (["--label", "7"], "Label 7 is not in the label map"),
    (["--label", "femur"], "'femur' is not a label value"),
    (["--label", "1", "--ht", "400", "--h0", "300"], "Thresholds out of order"),
    (["--label", "1", "--label", "2"], "no {label} placeholder"),
    (["--label", "1", "--preset", "femur"], "--preset: Parameter presets were removed"),
    (["--label", "1", "--poisson-depth", "12"], "poisson_depth must be between 4 and 10"),
    (["--label", "1", "--views", "many"], "invalid int value: 'many'"),
])
def test_bad_input_exit_2_one_line_no_output(bad_case, capsys, extra, message):
    ct, mask, out = bad_case
    code, stdout, stderr = run(["--ct", ct, "--seg", mask, "--out", str(out / "b.stl")]
                               + extra, capsys)
    assert code == 2
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], stderr
    assert os.listdir(out) == []


def test_bad_output_extension(bad_case, capsys):
    ct, mask, out = bad_case
    code, _, stderr = run(["--ct", ct, "--seg", mask, "--label", "1",
                           "--out", str(out / "b.xyz")], capsys)
    assert code == 2 and "--out must end in one of .stl" in stderr
    assert os.listdir(out) == []


def test_empty_segment_and_no_overlap(case, tmp_path, capsys):
    folder, _ = case
    ct = sitk.ReadImage(str(folder / "ct.nrrd"))
    empty = sitk.Image(ct.GetSize(), sitk.sitkUInt8)
    empty.CopyInformation(ct)
    sitk.WriteImage(empty, str(tmp_path / "empty.nrrd"))
    code, _, stderr = run(["--ct", str(folder / "ct.nrrd"), "--seg", str(tmp_path / "empty.nrrd"),
                           "--label", "1", "--out", str(tmp_path / "b.stl")], capsys)
    assert code == 2 and "empty" in stderr and stderr.count("\n") == 1

    _, mask = sphere_ct()
    mask.SetOrigin((500.0, 500.0, 500.0))  # far from the CT
    sitk.WriteImage(mask, str(tmp_path / "far.nrrd"))
    code, _, stderr = run(["--ct", str(folder / "ct.nrrd"), "--seg", str(tmp_path / "far.nrrd"),
                           "--label", "1", "--out", str(tmp_path / "b.stl")], capsys)
    assert code == 2 and stderr.startswith("error: ") and stderr.count("\n") == 1, stderr
    assert "overlap" in stderr.lower()
    assert_no_files(tmp_path)


def test_label_map_given_as_ct(case, tmp_path, capsys):
    folder, _ = case
    code, _, stderr = run(["--ct", str(folder / "mask.nrrd"), "--seg", str(folder / "mask.nrrd"),
                           "--label", "1", "--out", str(tmp_path / "b.stl")], capsys)
    assert code == 2 and "looks like a label map" in stderr
    assert os.listdir(tmp_path) == []


def test_cancel_exit_130_no_output(bad_case, capsys, monkeypatch):
    ct, mask, out = bad_case
    calls = []

    def cancel(self, fraction, message=""):
        calls.append(fraction)
        return False if len(calls) > 2 else None

    monkeypatch.setattr(cli.ProgressBar, "__call__", cancel)
    code, _, stderr = run(["--ct", ct, "--seg", mask, "--label", "1",
                           "--out", str(out / "b.stl"), "--report", str(out / "r.json")]
                          + FAST, capsys)
    assert code == 130 and "cancelled" in stderr
    assert os.listdir(out) == []


def test_failed_write_leaves_no_output(bad_case, capsys, monkeypatch):
    """Reconstruction succeeds but the disk write fails: no half file, no report."""
    ct, mask, out = bad_case

    def broken(poly, tmp, system):
        with open(tmp, "wb") as f:
            f.write(b"half")
        raise OSError("No space left on device")

    monkeypatch.setitem(meshes._WRITERS, ".stl", broken)
    code, _, stderr = run(["--ct", ct, "--seg", mask, "--label", "1",
                           "--out", str(out / "b.stl"), "--report", str(out / "r.json")]
                          + FAST, capsys)
    assert code == 5 and "No space left on device" in stderr
    assert os.listdir(out) == []


# ---------------------------------------------------------------------------- options

def test_the_command_line_turns_numpys_huge_page_advice_off(capsys):
    # measured: with the advice on, the kernel spends 9-12 s of a 25 s femur run finding and
    # zeroing huge pages for the pipeline's temporary volumes
    from numpy._core import multiarray

    previous = multiarray._set_madvise_hugepage(True)
    try:
        assert cli.main(["--help"]) == 0
        assert multiarray._set_madvise_hugepage(True) is False  # it returns the setting it replaces
    finally:
        multiarray._set_madvise_hugepage(previous)


def test_every_parameter_is_an_option():
    import dataclasses

    helptext = cli.build_parser().format_help()
    for f in dataclasses.fields(Parameters):
        assert "--" + f.name.replace("_", "-") in helptext, f.name
    assert "--no-refine-edges" in helptext


def test_parameters_from_options():
    parser = cli.build_parser()
    args = parser.parse_args(["--h0", "360", "--no-refine-edges", "--max-erosions", "2",
                              "--spacing", "auto", "--edge-length", "0.8",
                              "--save-intermediates", "x"])
    p = cli.parameters_from_args(args)
    # what is not given keeps its default; HT stays automatic (None)
    assert (p.h0, p.ht, p.refine_edges, p.spacing, p.edge_length) == (360.0, None, False,
                                                                       None, 0.8)
    assert p.keep_intermediates is True and p.max_erosions == 2
    assert p.replace(h0=None, refine_edges=True, max_erosions=3, edge_length=None,
                     keep_intermediates=False) == Parameters()
    assert cli.parameters_from_args(parser.parse_args([])) == Parameters()


def test_progress_bar_only_on_a_terminal():
    class Stream(stringio.StringIO):
        def __init__(self, tty):
            super().__init__()
            self.tty = tty

        def isatty(self):
            return self.tty

    quiet = Stream(False)
    bar = cli.ProgressBar(stream=quiet)
    bar(0.5, "threshold")
    bar.close()
    assert quiet.getvalue() == ""
    tty = Stream(True)
    bar = cli.ProgressBar(stream=tty)
    bar(0.5, "threshold")
    bar(1.0, "done")
    bar.close()
    assert "\r[" in tty.getvalue() and "50% threshold" in tty.getvalue()
    assert "100% done" in tty.getvalue()


# ---------------------------------------------------------------------------- batch

def _params_csv(rows, path):
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["ct", "seg", "label", "out", "preset"])
        writer.writerows(rows)


def _read_summary(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_batch_csv_goes_on_past_a_failed_case(case, tmp_path, capsys):
    folder, _ = case
    ct, mask = str(folder / "ct.nrrd"), str(folder / "mask.nrrd")
    _params_csv([[ct, mask, "1", "out/good.stl", ""],
                 [ct, mask, "5", "out/bad.stl", ""],
                 ["missing.nrrd", mask, "1", "out/missing.stl", ""],
                 [ct, mask, "1", "out/preset.stl", "femur"]],
                tmp_path / "cases.csv")
    code, stdout, stderr = run(["--cases", str(tmp_path / "cases.csv"), "--workers", "2",
                                "--summary", str(tmp_path / "summary.csv")] + FAST[:-1], capsys)
    assert code == 3
    rows = _read_summary(tmp_path / "summary.csv")
    assert [r["status"] for r in rows] == ["ok", "bad input", "bad input", "bad input"]
    assert "Label 5 is not in" in rows[1]["message"]
    assert "CT not found" in rows[2]["message"]
    assert "row 4 of" in rows[3]["message"] and "presets were removed" in rows[3]["message"]
    assert rows[0]["checks_ok"] == "True"
    assert sorted(os.listdir(tmp_path / "out")) == ["good.stl"]
    assert "1 of 4 surfaces built" in stdout
    assert bwio.read_surface(str(tmp_path / "out" / "good.stl")).n_faces > 100


def test_batch_folder_layout(case, tmp_path, capsys):
    folder, _ = case
    os.makedirs(tmp_path / "cases" / "a")
    os.makedirs(tmp_path / "cases" / "b")
    sitk.WriteImage(sitk.ReadImage(str(folder / "ct.nrrd")), str(tmp_path / "cases/a/ct.nrrd"))
    sitk.WriteImage(sitk.ReadImage(str(folder / "mask.nrrd")),
                    str(tmp_path / "cases/a/bone_labels.nrrd"))
    sitk.WriteImage(sitk.ReadImage(str(folder / "ct.nrrd")), str(tmp_path / "cases/b/ct.nrrd"))
    code, _, _ = run(["--cases", str(tmp_path / "cases"), "--label", "1",
                      "--out", str(tmp_path / "res/{case}_{label}.vtp"),
                      "--report", str(tmp_path / "res/{case}.json"),
                      "--summary", str(tmp_path / "summary.md")] + FAST, capsys)
    assert code == 3
    table = (tmp_path / "summary.md").read_text()
    assert "| a | 1 | ok |" in table
    assert "| b | 1 | bad input |" in table and "no segmentation" in table
    assert sorted(os.listdir(tmp_path / "res")) == ["a.json", "a_1.vtp"]


def test_batch_folder_needs_case_placeholder(tmp_path, capsys):
    os.makedirs(tmp_path / "a")
    code, _, stderr = run(["--cases", str(tmp_path), "--label", "1",
                           "--out", str(tmp_path / "x.stl")], capsys)
    assert code == 2 and "{case}" in stderr


def _wait_for(predicate, seconds, what):
    import time

    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if predicate():
            return
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture(params=["installed", "shipped"])
def dask_cluster(request, tmp_path_factory):
    """A Dask scheduler and one worker started as processes outside the checkout (cwd in a
    temporary folder, no PYTHONPATH). "installed": the worker's Python has the package (pip
    install -e, done by setup_env.sh). "shipped": the worker's Python has the dependencies but
    not the package (site-packages put on sys.path by hand under -S, so no .pth file and no
    editable install), so the client must ship the code."""
    import json
    import sysconfig

    pytest.importorskip("distributed", reason="dask[distributed] not installed")
    folder = tmp_path_factory.mktemp("dask")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    sched_file = folder / "scheduler.json"
    scheduler = subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_scheduler", "--scheduler-file",
         str(sched_file), "--port", "0", "--no-dashboard"], cwd=folder, env=env,
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    worker = None
    try:
        _wait_for(sched_file.exists, 60, "the scheduler")
        worker_args = ["--scheduler-file", str(sched_file), "--nthreads", "1", "--no-nanny",
                       "--no-dashboard", "--local-directory", str(folder / "work")]
        if request.param == "installed":
            cmd = [sys.executable, "-m", "distributed.cli.dask_worker", *worker_args]
        else:
            boot = ("import sys; sys.path[:0] = [%r, %r]; sys.argv = ['dask-worker'] + %r; "
                    "from distributed.cli.dask_worker import main; main()") % (
                sysconfig.get_path("purelib"), sysconfig.get_path("platlib"), worker_args)
            cmd = [sys.executable, "-S", "-c", boot]
        worker = subprocess.Popen(cmd, cwd=folder, env=env, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)
        address = json.loads(sched_file.read_text())["address"]
        from distributed import Client

        with Client(address, timeout=60) as client:
            client.wait_for_workers(1, timeout=60)
            from BoneWatertightLib.app.batch import _IMPORT_PROBE

            importable = all(client.run(eval, _IMPORT_PROBE).values())
        assert importable == (request.param == "installed")
        yield request.param, address
    finally:
        for proc in (worker, scheduler):
            if proc is not None:
                proc.terminate()
                try:
                    proc.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    proc.kill()


def test_batch_on_dask_workers_outside_the_checkout(case, tmp_path, capsys, dask_cluster):
    kind, address = dask_cluster
    folder, _ = case
    ct, mask = str(folder / "ct.nrrd"), str(folder / "mask.nrrd")
    _params_csv([[ct, mask, "1", "good.ply", ""], [ct, mask, "9", "bad.ply", ""]],
                tmp_path / "cases.csv")
    code, _, _ = run(["--cases", str(tmp_path / "cases.csv"), "--dask", address,
                      "--summary", str(tmp_path / "summary.csv")] + FAST, capsys)
    assert code == 3
    rows = _read_summary(tmp_path / "summary.csv")
    assert [r["status"] for r in rows] == ["ok", "bad input"]
    assert os.path.exists(tmp_path / "good.ply") and not os.path.exists(tmp_path / "bad.ply")
    from distributed import Client

    with Client(address, timeout=60) as client:
        where = list(client.run(eval, "__import__('BoneWatertightLib').__file__").values())
    if kind == "installed":
        assert ".zip" not in where[0]
    else:
        assert "BoneWatertightLib.zip" in where[0], where


def test_dask_missing_gives_install_hint(tmp_path, capsys, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_dask(name, *args, **kwargs):
        if name.startswith("dask") or name.startswith("distributed"):
            raise ImportError("No module named 'dask'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_dask)
    (tmp_path / "cases.csv").write_text("ct,seg,label,out\na,b,1,c.stl\n")
    code, _, stderr = run(["--cases", str(tmp_path / "cases.csv"), "--dask", "tcp://x:1"],
                          capsys)
    assert code == 4 and 'pip install "dask[distributed]"' in stderr
