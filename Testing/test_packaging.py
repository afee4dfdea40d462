"""Packaging: pip install of the checkout gives a working `bonewatertight` command; the Slicer
extension's CMake ships every library file; outputs respect the umask; no import cycle; no
file-scope import of optional packages in the library."""

from __future__ import annotations

import ast
import email.parser
import os
import re
import shutil
import stat
import subprocess
import sys
import sysconfig
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
LIB = ROOT / "BoneWatertightLib"
LIBRARY_FILES = sorted(p.relative_to(ROOT).as_posix() for p in LIB.rglob("*.py")
                       if "__pycache__" not in p.parts)
# What library modules may import at file scope (SPEC 2; Slicer loads them): the standard
# library, these packages and the library itself. open3d, matplotlib and dask are optional or
# heavy and must be imported inside functions.
# vtkmodules is VTK's own package of its modules (BoneWatertightLib/_vtk.py imports from it).
ALLOWED_TOP_LEVEL = {"numpy", "scipy", "SimpleITK", "vtk", "vtkmodules", "slicer"}


def _clean_env():
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    return env


def test_cmake_ships_every_library_file(tmp_path):
    """Evaluate the module CMakeLists' own glob with cmake and compare with the files."""
    cmake = shutil.which("cmake")
    assert cmake, "cmake is needed for this test (Resources/Scripts/setup_env.sh installs it)"
    text = (ROOT / "BoneWatertight" / "CMakeLists.txt").read_text(encoding="utf-8")
    glob = re.search(r"file\(GLOB_RECURSE _lib_scripts .*?\)\n", text, re.S)
    assert glob, "the module CMakeLists must glob the library recursively"
    filt = re.search(r"list\(FILTER _lib_scripts .*?\)\n", text, re.S)
    loop = re.search(r"foreach\(_script \$\{_lib_scripts\}\)(.*?)endforeach\(\)", text, re.S)
    assert loop and "configure_file(" in loop.group(1) and "install(FILES" in loop.group(1)
    script = tmp_path / "glob.cmake"
    script.write_text(f'set(CMAKE_CURRENT_SOURCE_DIR "{(ROOT / "BoneWatertight").as_posix()}")\n'
                      + glob.group(0) + (filt.group(0) if filt else "")
                      + 'foreach(f ${_lib_scripts})\n  message("${f}")\nendforeach()\n')
    proc = subprocess.run([cmake, "-P", str(script)], capture_output=True, text=True, encoding="utf-8", timeout=60)
    assert proc.returncode == 0, proc.stderr
    shipped = sorted(line.strip() for line in proc.stderr.splitlines() if line.strip())
    assert shipped == LIBRARY_FILES
    assert "BoneWatertightLib/stages/deform.py" in shipped and len(shipped) > 25
    assert not (LIB / "baselines.py").exists(), "benchmark code must not ship"


def test_pip_install_gives_the_bonewatertight_command(tmp_path):
    """pip install <checkout> (no network: the dependencies are this environment's), then the
    console command from another folder, with the checkout nowhere on the path."""
    target = tmp_path / "site"
    # The checkout's packaging inputs (what an sdist holds), copied so that setuptools' in-tree
    # build folder never lands in (or is reused from) the working copy.
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, checkout / name)
    shutil.copytree(LIB, checkout / "BoneWatertightLib",
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
         "--target", str(target), str(checkout)], capture_output=True, text=True,
        encoding="utf-8", timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    installed = sorted(p.relative_to(target).as_posix() for p in
                       (target / "BoneWatertightLib").rglob("*.py") if "__pycache__" not in p.parts)
    assert installed == LIBRARY_FILES
    meta = next(target.glob("bonewatertight-*.dist-info"))
    metadata = email.parser.Parser().parsestr((meta / "METADATA").read_text(encoding="utf-8"))
    assert metadata["Name"] == "bonewatertight"
    assert "BoneWatertight developers" in (metadata["Author"] or metadata["Author-email"] or "")
    assert metadata["License-Expression"] == "Apache-2.0"
    assert {"numpy", "scipy", "simpleitk", "vtk", "open3d"} <= {
        re.split(r"[<>=!;\[ ]", r)[0].lower() for r in metadata.get_all("Requires-Dist")}
    assert "bonewatertight = BoneWatertightLib.app.cli:main" in (meta / "entry_points.txt").read_text(encoding="utf-8")

    work = tmp_path / "elsewhere"
    work.mkdir()
    env = _clean_env()
    env["PYTHONPATH"] = str(target)
    command = str(target / "bin" / "bonewatertight")
    help_run = subprocess.run([command, "--help"], cwd=work, env=env, capture_output=True,
                              text=True, encoding="utf-8", timeout=120)
    assert help_run.returncode == 0, help_run.stderr
    assert "usage: bonewatertight" in help_run.stdout and "--edge-level" in help_run.stdout
    where = subprocess.run([sys.executable, "-c", "import BoneWatertightLib; print(BoneWatertightLib.__file__)"],
                           cwd=work, env=env, capture_output=True, text=True, encoding="utf-8", timeout=60)
    assert where.stdout.strip().startswith(str(target)), where.stdout
    bad = subprocess.run([command, "--ct", "ct.nrrd", "--seg", "seg.nrrd", "--label", "1",
                          "--out", "bone.stl", "--edge-level", "5"], cwd=work, env=env,
                         capture_output=True, text=True, encoding="utf-8", timeout=120)
    assert bad.returncode == 2
    assert bad.stderr.strip() == "error: edge_level must be between 0.3 and 0.9, got 5."
    assert os.listdir(work) == []


def test_environment_has_the_console_command(tmp_path):
    """setup_env.sh installs the package (editable) into the environment that runs the tests."""
    command = Path(sysconfig.get_path("scripts")) / "bonewatertight"
    assert command.exists(), "run Resources/Scripts/setup_env.sh (pip install -e .)"
    proc = subprocess.run([str(command), "--help"], cwd=tmp_path, env=_clean_env(),
                          capture_output=True, text=True, encoding="utf-8", timeout=120)
    assert proc.returncode == 0 and "--poisson-depth" in proc.stdout


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_outputs_respect_the_umask(tmp_path, umask, mode):
    from BoneWatertightLib.app import run
    from BoneWatertightLib.io import files, meshes
    from BoneWatertightLib.mesh import Surface

    surface = Surface(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]),
                      np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))
    old = os.umask(umask)
    try:
        written = [meshes.write_surface(surface, tmp_path / f"s{ext}") for ext in meshes.SURFACE_EXTENSIONS]
        written.append(meshes.write_points(surface.vertices, tmp_path / "p.ply"))
        files.write_text("x\n", tmp_path / "t.txt")
        run.write_report({"a": float("nan")}, str(tmp_path / "r.json"))
        written += [tmp_path / "t.txt", tmp_path / "r.json"]
    finally:
        os.umask(old)
    for path in written:
        assert stat.S_IMODE(os.stat(path).st_mode) == mode, (path, oct(os.stat(path).st_mode))
    assert (tmp_path / "r.json").read_text(encoding="utf-8").strip().replace(" ", "").replace("\n", "") == '{"a":null}'
    assert not [p for p in os.listdir(tmp_path) if ".part" in p]


def _imports(path: Path):
    """(module-level imports, all imports) of a library file as absolute module names."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    package = parts[:-1] if parts[-1] != "__init__" else parts[:-1]
    if parts[-1] == "__init__":
        package = parts[:-1]
    top, every = set(), set()

    def resolve(node):
        if isinstance(node, ast.Import):
            return [a.name for a in node.names]
        base = package[:len(package) - node.level + 1] if node.level else []
        mod = ".".join(base + ([node.module] if node.module else []))
        if node.module is None:  # from . import x
            return [f"{mod}.{a.name}" for a in node.names]
        return [mod] + [f"{mod}.{a.name}" for a in node.names]

    for node in tree.body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            top.update(resolve(node))
        elif isinstance(node, ast.Try):
            for sub in node.body:
                if isinstance(sub, (ast.Import, ast.ImportFrom)):
                    top.update(resolve(sub))
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            every.update(resolve(node))
    return top, every


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def test_no_import_cycle_and_front_ends_go_through_the_run_service():
    modules = {_module_name(ROOT / f): ROOT / f for f in LIBRARY_FILES}
    graph = {}
    for name, path in modules.items():
        _, every = _imports(path)
        graph[name] = {m for m in every if m in modules and m != name}
    # cli and batch: batch never imports cli; run imports neither
    assert "BoneWatertightLib.app.cli" not in graph["BoneWatertightLib.app.batch"]
    assert not {"BoneWatertightLib.app.cli", "BoneWatertightLib.app.batch"} & graph["BoneWatertightLib.app.run"]
    # stages never import a later stage (refine/poisson no longer take operators from deform)
    for name in ("refine", "poisson"):
        assert "BoneWatertightLib.stages.deform" not in graph[f"BoneWatertightLib.stages.{name}"]
    # and no cycle at all (parent packages' __init__ excluded: importing a submodule runs them)
    state = {}

    def visit(node, trail):
        state[node] = "open"
        for nxt in graph[node]:
            if node.startswith(nxt + "."):
                continue
            if state.get(nxt) == "open":
                raise AssertionError("import cycle: " + " -> ".join(trail + [nxt]))
            if nxt not in state:
                visit(nxt, trail + [nxt])
        state[node] = "done"

    for node in graph:
        if node not in state:
            visit(node, [node])


def test_library_file_scope_imports_are_core_only():
    stdlib = set(sys.stdlib_module_names)
    for f in LIBRARY_FILES:
        top, _ = _imports(ROOT / f)
        for name in top:
            first = name.split(".")[0]
            assert first in stdlib or first in ALLOWED_TOP_LEVEL or first == "BoneWatertightLib" \
                or first == "__future__", f"{f} imports {name} at file scope"
