"""Every ``slicer.*`` / ``vtk.*`` name the module, the MRML adapter and the Slicer batch script
use exists in the real classes (slicer-core's wheel, VTK); names only the running 3D Slicer
application has (slicer.app, slicer.modules, qt, ctk, ...) are listed here explicitly.

An AST scan: each attribute chain rooted at an imported ``slicer``/``vtk``/``qt``/``ctk`` name
(import aliases followed, e.g. ``ns`` = vtk.util.numpy_support) is resolved attribute by
attribute on the real objects. ``slicer.mrmlScene`` resolves on vtkMRMLScene and
``slicer.modules.segmentations.logic()`` on vtkSlicerSegmentationsModuleLogic, the classes
of the objects Slicer puts there. Issue 13, defect 1: the batch script called
``slicer.vtkMRMLStorageNode.GetCoordinateSystemFromString``, which does not exist.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

slicer = pytest.importorskip("slicer")

ROOT = Path(__file__).resolve().parents[1]
FILES = {
    "module": ROOT / "BoneWatertight" / "BoneWatertight.py",
    "adapter": ROOT / "BoneWatertightLib" / "mrml.py",
    "batch": ROOT / "Resources" / "Scripts" / "bonewatertight_batch.py",
}
ROOTS = ("slicer", "vtk", "qt", "ctk")

# Only in the running application (not in slicer-core): what each is, and which files may use it.
SLICER_ONLY = {
    "slicer.app": "qSlicerApplication, the running application",
    "slicer.modules": "the application's loaded modules",
    "slicer.i18n": "Slicer's translation helpers (Base/Python/slicer/i18n.py)",
    "slicer.ScriptedLoadableModule": "scripted-module base classes (Base/Python/slicer)",
    "slicer.parameterNodeWrapper": "parameter node wrapper (Base/Python/slicer)",
    "slicer.packaging": "pip helpers, Slicer >= 5.12 (Base/Python/slicer/packaging.py)",
}
# Objects the application creates, resolved on their classes.
INSTANCES = {
    ("slicer", "mrmlScene"): "vtkMRMLScene",
    ("slicer", "modules", "segmentations", "logic"): "vtkSlicerSegmentationsModuleLogic",
}
# Every qt / ctk name the files use (PythonQt, application only). Checked by reading the
# sources: CTK @868d56c, Qt 5/6 documentation. A new name must be added here on purpose.
QT_CTK_NAMES = {
    "qt.QApplication.restoreOverrideCursor",
    "qt.QApplication.setOverrideCursor",
    "qt.QDoubleSpinBox",       # the spin box inside ctkSliderWidget's ctkDoubleSpinBox
    "qt.QLabel",
    "qt.QTimer",
    "qt.QWidget",
    "qt.Qt.BusyCursor",
}


def scan(source: str):
    """(dotted chain, line) of every maximal attribute chain and every ``from X import Y``
    rooted at slicer/vtk/qt/ctk."""
    tree = ast.parse(source)
    aliases = {}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] in ROOTS:
                    aliases[a.asname or a.name.split(".")[0]] = a.name if a.asname else a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module \
                and node.module.split(".")[0] in ROOTS:
            for a in node.names:
                aliases[a.asname or a.name] = f"{node.module}.{a.name}"
                found.append((f"{node.module}.{a.name}", node.lineno))
    parents = {child: parent for parent in ast.walk(tree) for child in ast.iter_child_nodes(parent)}
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute) or isinstance(parents.get(node), ast.Attribute):
            continue
        parts, n = [], node
        while isinstance(n, ast.Attribute):
            parts.append(n.attr)
            n = n.value
        if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute):
            # slicer.modules.segmentations.logic().X: the chain continues on the call's result
            head = []
            f = n.func
            while isinstance(f, ast.Attribute):
                head.append(f.attr)
                f = f.value
            if isinstance(f, ast.Name) and f.id in aliases:
                chain = aliases[f.id].split(".") + head[::-1]
                if tuple(chain) in INSTANCES:
                    found.append((".".join(chain + parts[::-1]), node.lineno))
            continue
        if isinstance(n, ast.Name) and n.id in aliases:
            found.append((".".join(aliases[n.id].split(".") + parts[::-1]), node.lineno))
    return found


def resolve(dotted: str) -> str:
    """'ok', 'slicer-only:<prefix>', 'qt/ctk' or 'missing:<name>'."""
    parts = dotted.split(".")
    if parts[0] in ("qt", "ctk"):
        return "qt/ctk"
    for prefix in sorted(SLICER_ONLY, key=len, reverse=True):
        if dotted == prefix or dotted.startswith(prefix + "."):
            if not any(tuple(parts[:len(k)]) == k for k in INSTANCES):
                return f"slicer-only:{prefix}"
    obj, rest, done = None, parts, []
    for key, cls in sorted(INSTANCES.items(), key=lambda kv: -len(kv[0])):
        if tuple(parts[:len(key)]) == key:
            obj, rest, done = getattr(slicer, cls), parts[len(key):], list(key)
            break
    if obj is None:
        obj, rest, done = importlib.import_module(parts[0]), parts[1:], [parts[0]]
    for name in rest:
        done.append(name)
        try:
            obj = getattr(obj, name)
        except AttributeError:
            try:
                obj = importlib.import_module(".".join(done))
            except ImportError:
                return f"missing:{'.'.join(done)}"
    return "ok"


def _results(path):
    return [(dotted, line, resolve(dotted)) for dotted, line in scan(path.read_text(encoding="utf-8"))]


@pytest.mark.parametrize("name", sorted(FILES))
def test_every_slicer_and_vtk_name_exists(name):
    results = _results(FILES[name])
    assert results, f"{name}: nothing scanned?"
    missing = [f"{FILES[name].name}:{line}: {dotted} ({status})" for dotted, line, status in results
               if status.startswith("missing")]
    assert not missing, "names that do not exist in slicer-core / VTK:\n" + "\n".join(missing)
    print(f"{name}: {len(results)} names, "
          f"{sum(s == 'ok' for _, _, s in results)} resolved on slicer-core/VTK")


def test_slicer_only_names_are_the_listed_ones():
    used = {}
    for name, path in FILES.items():
        for dotted, line, status in _results(path):
            if status.startswith("slicer-only:"):
                used.setdefault(status.split(":", 1)[1], set()).add(name)
            elif status == "qt/ctk":
                used.setdefault(dotted, set()).add(name)
    slicer_only = {k for k in used if k.startswith("slicer.")}
    assert slicer_only <= set(SLICER_ONLY)
    qt_ctk = {k for k in used if not k.startswith("slicer.")}
    assert qt_ctk == QT_CTK_NAMES, "qt/ctk names changed: check them against Qt/CTK, then update the list"
    # the adapter runs on slicer-core: no application-only name at all
    assert not [k for k, files in used.items() if "adapter" in files]
    # the batch script must run headless: only the application's exit/pip helpers, which it
    # guards (slicer.util.exit only when slicer.app exists)
    assert not [k for k, files in used.items() if "batch" in files]


def test_the_scan_catches_the_batch_scripts_old_storage_call():
    """The check would have caught defect 1 (and finds the right name)."""
    old = ("import slicer\n"
           "storage.SetCoordinateSystem(slicer.vtkMRMLStorageNode.GetCoordinateSystemFromString('RAS'))\n")
    [(dotted, _line)] = scan(old)
    assert resolve(dotted) == "missing:slicer.vtkMRMLStorageNode.GetCoordinateSystemFromString"
    assert resolve("slicer.vtkMRMLStorageNode.GetCoordinateSystemTypeFromString") == "ok"
    assert resolve("slicer.mrmlScene.StartCloseEvent") == "ok"
    assert resolve("slicer.mrmlScene.NoSuchEvent") == "missing:slicer.mrmlScene.NoSuchEvent"
    assert resolve("slicer.modules.segmentations.logic.ImportLabelmapToSegmentationNode") == "ok"
    assert resolve("slicer.app.processEvents") == "slicer-only:slicer.app"
