"""The Slicer batch script (Resources/Scripts/bonewatertight_batch.py) on slicer-core.

Its main() runs here as it runs in Slicer (--no-main-window --python-script) and in
PythonSlicer: files in, STL / VTP out in LPS and RAS, read back with 3D Slicer's own model
reader (vtkMRMLModelStorageNode) and checked to lie on the phantom's surface in RAS; the
documented exit codes; the --self-test on MRML nodes, and its skip without open3d; the
installed layout (CMake puts the script at <qt-scripted-modules>/Resources/Scripts/).
Issue 13, defect 1 (and the batch self-test's install-or-skip).
"""

from __future__ import annotations

import builtins
import importlib.util
import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

slicer = pytest.importorskip("slicer")
vtk = pytest.importorskip("vtk")
from vtk.util import numpy_support as ns  # noqa: E402

from BoneWatertightLib import errors, mrml  # noqa: E402
from BoneWatertightLib.app import slicer_support  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
BATCH_SCRIPT = ROOT / "Resources" / "Scripts" / "bonewatertight_batch.py"
MODULE_CMAKE = ROOT / "BoneWatertight" / "CMakeLists.txt"
TEST_CMAKE = ROOT / "BoneWatertight" / "Testing" / "Python" / "CMakeLists.txt"
FAST = ["--spacing", "1.0", "--iterations", "3", "--poisson-depth", "6", "--views", "6", "-q"]
RADIUS = 9.0


def _batch():
    spec = importlib.util.spec_from_file_location("bonewatertight_batch", BATCH_SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # runs nothing: __name__ is not "__main__"
    return module


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """An oblique CT (LPS, rotated direction, non-zero origin) with a blurred 1000 HU ball and
    a rough label map of it; returns (folder, ball centre in RAS)."""
    folder = tmp_path_factory.mktemp("batch_case")
    n = 36
    a = np.radians(25.0)
    direction = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    origin = np.array([-20.0, 30.0, 100.0])
    centre_index = np.array([17.5, 18.0, 17.0])
    z, y, x = np.mgrid[:n, :n, :n]
    r = np.sqrt((x - centre_index[0]) ** 2 + (y - centre_index[1]) ** 2 + (z - centre_index[2]) ** 2)
    edge = 0.5 * (1.0 - np.tanh((r - RADIUS) / 0.5))
    noise = np.random.default_rng(0).normal(0.0, 10.0, r.shape)
    ct = sitk.GetImageFromArray(np.round(40.0 + 960.0 * edge + noise).astype(np.int16))
    ct.SetOrigin(origin.tolist())
    ct.SetDirection(direction.ravel().tolist())
    mask = sitk.GetImageFromArray((r < RADIUS - 1.5).astype(np.uint8))
    mask.CopyInformation(ct)
    sitk.WriteImage(ct, str(folder / "ct.nrrd"))
    sitk.WriteImage(mask, str(folder / "mask.nrrd"))
    centre_lps = np.array(ct.TransformContinuousIndexToPhysicalPoint(centre_index.tolist()))
    return folder, centre_lps * [-1.0, -1.0, 1.0]


def _raw_points(path):
    """The coordinates as stored in the file (no SPACE handling)."""
    reader = vtk.vtkSTLReader() if str(path).endswith(".stl") else vtk.vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    return ns.vtk_to_numpy(reader.GetOutput().GetPoints().GetData())


@pytest.mark.parametrize("ext", [".stl", ".vtp"])
def test_batch_writes_stl_and_vtp_in_lps_and_ras_that_slicer_places_right(case, tmp_path, ext, capsys):
    folder, centre_ras = case
    batch = _batch()
    outputs = {}
    for system in ("LPS", "RAS"):
        out = tmp_path / f"bone_{system}{ext}"
        argv = ["--ct", str(folder / "ct.nrrd"), "--seg", str(folder / "mask.nrrd"), "--label", "1",
                "--out", str(out), "--report", str(tmp_path / f"report_{system}.json")] + FAST
        if system == "RAS":
            argv.append("--ras")
        assert batch.main(argv) == errors.EXIT_OK, capsys.readouterr().err
        assert out.is_file()
        outputs[system] = out
    text = capsys.readouterr().out
    assert text.count("RESULT ") == 2
    for system, out in outputs.items():
        # where 3D Slicer puts it (its reader honours the SPACE tag): on the ball, in RAS
        model = mrml.read_model_file(out)
        ras = ns.vtk_to_numpy(model.GetPolyData().GetPoints().GetData())
        radial = np.linalg.norm(ras - centre_ras, axis=1) - RADIUS
        print(f"{out.name}: {len(ras)} points, |r - R| max {np.abs(radial).max():.2f} mm")
        assert np.abs(radial).max() < 1.0 and abs(np.mean(radial)) < 0.3
        # and the file holds the coordinates of the system it names
        raw = _raw_points(out)
        expect = raw if system == "RAS" else raw * [-1.0, -1.0, 1.0]
        assert np.abs(np.linalg.norm(expect - centre_ras, axis=1) - RADIUS).max() < 1.0
        assert _space_tag(out) == system
    # one surface, two coordinate systems: identical once Slicer has read them
    a = ns.vtk_to_numpy(mrml.read_model_file(outputs["LPS"]).GetPolyData().GetPoints().GetData())
    b = ns.vtk_to_numpy(mrml.read_model_file(outputs["RAS"]).GetPolyData().GetPoints().GetData())
    assert a.shape == b.shape and np.allclose(np.sort(a, axis=0), np.sort(b, axis=0), atol=1e-3)


def test_batch_reconstructs_several_labels_together_as_the_command_does(tmp_path, capsys):
    """--all-labels / several --label: one joint run (run service), every other label a
    neighbour by default, a RESULT line per bone and a PAIR line per pair; the surfaces, read
    back as Slicer reads them, do not enter each other."""
    n, r = (48, 28, 28), 7.0
    z, y, x = np.mgrid[:n[2], :n[1], :n[0]].astype(float)
    centres = [np.array([15.75, 13.5, 13.5]), np.array([31.25, 13.5, 13.5])]  # 1.5 mm apart
    dist = [np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) for c in centres]
    edge = sum(0.5 * (1.0 - np.tanh((d - r) / 0.5)) for d in dist)
    noise = np.random.default_rng(1).normal(0.0, 8.0, edge.shape)
    ct = sitk.GetImageFromArray(np.round(40.0 + 960.0 * np.clip(edge, 0, 1) + noise).astype(np.int16))
    ct.SetOrigin([5.0, -7.0, 20.0])
    labels = np.zeros(edge.shape, np.uint8)
    labels[dist[0] < r - 1.5] = 1
    labels[dist[1] < r - 1.5] = 2
    seg = sitk.GetImageFromArray(labels)
    seg.CopyInformation(ct)
    sitk.WriteImage(ct, str(tmp_path / "ct.nrrd"))
    sitk.WriteImage(seg, str(tmp_path / "labels.nrrd"))
    out = tmp_path / "bone_{label}.vtp"
    argv = ["--ct", str(tmp_path / "ct.nrrd"), "--seg", str(tmp_path / "labels.nrrd"), "--all-labels",
            "--out", str(out), "--report", str(tmp_path / "report.json")] + FAST
    assert _batch().main(argv) == errors.EXIT_OK, capsys.readouterr().err
    text = capsys.readouterr().out
    assert text.count("RESULT ") == 2 and text.count("PAIR ") == 1
    files = sorted(tmp_path.glob("bone_*.vtp"))
    assert [f.name for f in files] == ["bone_1.vtp", "bone_2.vtp"]
    centres_ras = [np.array(ct.TransformContinuousIndexToPhysicalPoint(c.tolist())) * [-1, -1, 1]
                   for c in centres]
    for f, centre, other in zip(files, centres_ras, centres_ras[::-1]):
        pts = ns.vtk_to_numpy(mrml.read_model_file(f).GetPolyData().GetPoints().GetData())
        assert np.abs(np.linalg.norm(pts - centre, axis=1) - r).max() < 1.0
        assert not (np.linalg.norm(pts - other, axis=1) < r).any()  # not inside the other ball
    # the command's own argument checks: several labels need {label} in --out
    assert _batch().main(argv[:4] + ["--all-labels", "--out", str(tmp_path / "one.stl")] + FAST) \
        == errors.EXIT_INPUT
    assert "{label}" in capsys.readouterr().err


def _space_tag(path):
    """The coordinate system the file states: STL header, VTP field data (as Slicer writes them)."""
    if str(path).endswith(".stl"):
        reader = vtk.vtkSTLReader()
        reader.SetFileName(str(path))
        reader.Update()
        found = re.search(r"SPACE=(LPS|RAS)", reader.GetHeader() or "")
        return found.group(1) if found else None
    reader = vtk.vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    space = reader.GetOutput().GetFieldData().GetAbstractArray("SPACE")
    return space.GetValue(0) if space is not None else None


def test_batch_self_test_runs_on_mrml_nodes(tmp_path, capsys):
    out = tmp_path / "sphere.vtp"
    assert _batch().main(["--self-test", "-q", "--out", str(out)]) == errors.EXIT_OK
    text = capsys.readouterr().out
    error = float(re.search(r"SELFTEST max radial error ([0-9.]+) mm", text).group(1))
    assert error <= 1.0 and out.is_file()


def test_batch_self_test_without_open3d_skips_with_the_dependency_code(monkeypatch, capsys):
    real_import = builtins.__import__

    def no_open3d(name, *args, **kwargs):
        if name == "open3d" or name.startswith("open3d."):
            raise ImportError("No module named 'open3d' (test)")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_open3d)
    monkeypatch.setenv(slicer_support.TEST_INSTALL_VARIABLE, "0")
    assert _batch().main(["--self-test"]) == errors.EXIT_DEPENDENCY
    assert "SKIPPED: open3d is not available" in capsys.readouterr().out
    # ctest reports that exit code as "skipped", not as a failure
    text = TEST_CMAKE.read_text(encoding="utf-8")
    assert re.search(rf"set_tests_properties\(py_nomainwindow_bonewatertight_batch\s+PROPERTIES\s+"
                     rf"SKIP_RETURN_CODE\s+{errors.EXIT_DEPENDENCY}\)", text)


def test_batch_exit_codes_are_the_documented_ones(case, tmp_path, capsys):
    folder, _ = case
    batch = _batch()
    # the docstring's table is the library's
    doc = dict((int(c), t.strip()) for c, t in re.findall(r"^\s+(\d+)\s+(.+)$", batch.__doc__, re.M))
    assert set(doc) == set(errors.EXIT_CODES)
    base = ["--ct", str(folder / "ct.nrrd"), "--seg", str(folder / "mask.nrrd")] + FAST
    assert batch.main([]) == errors.EXIT_INPUT  # nothing to do
    assert "error: missing --ct" in capsys.readouterr().err
    assert batch.main(base + ["--label", "7", "--out", str(tmp_path / "x.stl")]) == errors.EXIT_INPUT
    assert batch.main(base + ["--label", "1", "--out", str(tmp_path / "x.txt")]) == errors.EXIT_INPUT
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    assert batch.main(base + ["--label", "1", "--out", str(blocker / "x.stl")]) == errors.EXIT_OUTPUT
    # the outputs of a run are committed together (the run service's transaction, as in the
    # bonewatertight command): a report that cannot be written leaves no surface behind
    assert batch.main(base + ["--label", "1", "--out", str(tmp_path / "y.stl"),
                              "--report", str(blocker / "report.json")]) == errors.EXIT_OUTPUT
    assert not (tmp_path / "y.stl").exists()
    capsys.readouterr()
    assert batch.main(["--help"]) == errors.EXIT_OK
    assert not list(tmp_path.glob("*.stl"))


def test_cmake_installs_the_batch_script_where_it_finds_the_library(tmp_path):
    """The module CMakeLists installs the script at <qt-scripted-modules>/Resources/Scripts/
    beside the installed BoneWatertightLib; from there (and with no other copy of the library
    importable) the script imports that library and runs."""
    text = MODULE_CMAKE.read_text(encoding="utf-8")
    assert "set(_batch_script Resources/Scripts/bonewatertight_batch.py)" in text
    install = re.search(r"install\(PROGRAMS \$\{CMAKE_CURRENT_SOURCE_DIR\}/\.\./\$\{_batch_script\}\s+"
                        r"DESTINATION \$\{Slicer_INSTALL_QTSCRIPTEDMODULES_LIB_DIR\}/(\S+)\s+", text)
    assert install, "no install rule for the batch script"
    assert re.search(r"configure_file\(\s+\$\{CMAKE_CURRENT_SOURCE_DIR\}/\.\./\$\{_batch_script\}\s+"
                     r"\$\{CMAKE_BINARY_DIR\}/\$\{Slicer_QTSCRIPTEDMODULES_LIB_DIR\}/\$\{_batch_script\}", text)
    lib_dir = tmp_path / "lib" / "Slicer-5.10" / "qt-scripted-modules"  # as the extension installs
    script = lib_dir / install.group(1) / BATCH_SCRIPT.name
    script.parent.mkdir(parents=True)
    shutil.copy(BATCH_SCRIPT, script)
    shutil.copytree(ROOT / "BoneWatertightLib", lib_dir / "BoneWatertightLib",
                    ignore=shutil.ignore_patterns("__pycache__"))
    probe = tmp_path / "probe.py"
    probe.write_text(textwrap.dedent(f"""
        import runpy, sys
        checkout = {str(ROOT)!r}
        # hide the checkout (and its editable install) so only the installed copy can be found
        sys.path[:] = [p for p in sys.path if p and p.rstrip("/") not in (checkout, checkout + "/Testing")]
        sys.meta_path[:] = [f for f in sys.meta_path if "editable" not in repr(f).lower()]
        sys.path_hooks[:] = [h for h in sys.path_hooks if "editable" not in repr(h).lower()]
        sys.path_importer_cache.clear()
        try:
            import BoneWatertightLib
            raise SystemExit("the checkout's library is still importable: " + BoneWatertightLib.__file__)
        except ImportError:
            pass
        sys.argv = [{str(script)!r}, "--help"]
        try:
            runpy.run_path({str(script)!r}, run_name="__main__")
        except SystemExit as exc:
            code = exc.code
        import BoneWatertightLib
        print("LIBRARY", BoneWatertightLib.__file__)
        print("EXIT", code)
    """), encoding="utf-8")
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    proc = subprocess.run([sys.executable, str(probe)], capture_output=True, text=True, env=env,
                          cwd=str(tmp_path), timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "--self-test" in proc.stdout and "EXIT 0" in proc.stdout
    library = re.search(r"LIBRARY (\S+)", proc.stdout).group(1)
    assert Path(library).resolve().is_relative_to(lib_dir.resolve())
