"""The Slicer module's .ui and Python file agree; the .ui renders with a real Qt loader.

The module file imports qt/ctk (Slicer's application only), so it is checked by parsing
(ast) and compiling, not by importing.
"""

from __future__ import annotations

import ast
import dataclasses
import os
import py_compile
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MODULE_PY = ROOT / "BoneWatertight" / "BoneWatertight.py"
UI_FILE = ROOT / "BoneWatertight" / "Resources" / "UI" / "BoneWatertight.ui"
# bound by hand (the parameter-node wrapper has no connector for qMRMLSegmentSelectorWidget)
MANUAL_FIELDS = {"inputSegmentation": "segmentSelector", "segmentId": "segmentSelector",
                 "segmentIds": "segmentSelector"}


def _ui_widgets():
    tree = ET.parse(UI_FILE)
    widgets = {}
    for w in tree.iter("widget"):
        params = [p.findtext("string") for p in w.findall("property") if p.get("name") == "SlicerParameterName"]
        tips = [p.findtext("string") for p in w.findall("property") if p.get("name") == "toolTip"]
        widgets[w.get("name")] = dict(cls=w.get("class"), param=params[0] if params else None,
                                      tip=tips[0] if tips else None, elem=w)
    return tree, widgets


def _module_ast():
    return ast.parse(MODULE_PY.read_text(encoding="utf-8"))


def _parameter_node_fields():
    """Fields declared in the class body plus those withLibraryParameters adds from the
    library's schema (every parameter with a panel section; see test_schema.py)."""
    from BoneWatertightLib.params import SCHEMA

    for node in ast.walk(_module_ast()):
        if isinstance(node, ast.ClassDef) and any(
                (isinstance(d, ast.Name) and d.id == "parameterNodeWrapper") for d in node.decorator_list):
            assert any(isinstance(d, ast.Name) and d.id == "withLibraryParameters" for d in node.decorator_list)
            own = [s.target.id for s in node.body if isinstance(s, ast.AnnAssign)]
            return own + [name for name, spec in SCHEMA.items() if spec.panel is not None]
    raise AssertionError("no @parameterNodeWrapper class in BoneWatertight.py")


def test_module_compiles():
    py_compile.compile(str(MODULE_PY), doraise=True)


def test_ui_is_valid_qt_designer_xml():
    tree, widgets = _ui_widgets()
    root = tree.getroot()
    assert root.tag == "ui" and root.findtext("class") == "BoneWatertight"
    top = root.find("widget")
    assert top.get("class") == "qMRMLWidget"
    names = [w.get("name") for w in root.iter("widget")]
    assert len(names) == len(set(names)), "duplicate widget names"
    customs = {c.findtext("class") for c in root.iter("customwidget")}
    used = {w["cls"] for w in widgets.values()}
    assert {c for c in used if c.startswith(("ctk", "qMRML"))} <= customs
    sections = {w["elem"].findtext("property/string"): w for w in widgets.values()
                if w["cls"] == "ctkCollapsibleButton"}
    assert {"Inputs", "Thresholds", "Resampling", "Advanced", "Output", "Log"} <= set(sections)
    adv = sections["Advanced"]["elem"]
    collapsed = [p.findtext("bool") for p in adv.findall("property") if p.get("name") == "collapsed"]
    assert collapsed == ["true"]
    for receiver in ("inputVolumeSelector", "segmentSelector", "outputModelSelector"):
        assert any(c.findtext("receiver") == receiver and c.findtext("slot") == "setMRMLScene(vtkMRMLScene*)"
                   for c in root.iter("connection"))


def test_every_ui_name_used_by_the_module_exists():
    _, widgets = _ui_widgets()
    used = set(re.findall(r"self\.ui\.(\w+)", MODULE_PY.read_text(encoding="utf-8")))
    assert used, "the module uses no ui widgets?"
    missing = sorted(used - set(widgets))
    assert not missing, f"BoneWatertight.py uses widgets missing from the .ui: {missing}"


def test_every_parameter_field_has_a_widget():
    _, widgets = _ui_widgets()
    bound = {w["param"]: name for name, w in widgets.items() if w["param"]}
    fields = _parameter_node_fields()
    for f in fields:
        if f in MANUAL_FIELDS:
            assert MANUAL_FIELDS[f] in widgets
            assert f in MODULE_PY.read_text(encoding="utf-8")
            continue
        assert f in bound, f"parameter '{f}' has no widget with SlicerParameterName"
    # and no widget binds to a parameter that does not exist
    assert set(bound) <= set(fields)
    # every bound widget has a tooltip: in the .ui, or from the schema in setup()
    from BoneWatertightLib.params import SCHEMA

    for param, name in bound.items():
        assert widgets[name]["tip"] or param in SCHEMA, f"widget {name} ({param}) has no tooltip"


def test_parameter_node_covers_every_library_parameter():
    from BoneWatertightLib.params import Parameters

    fields = set(_parameter_node_fields())
    lib = {f.name for f in dataclasses.fields(Parameters)} - {"keep_intermediates"}  # = showIntermediates
    assert lib <= fields, f"missing in the parameter node: {sorted(lib - fields)}"
    assert "showIntermediates" in fields


def test_panel_chooses_several_bones_and_their_neighbours():
    """Issue 10 item 3: the segment selector is a multi-select (one bone = one checked
    segment), "Other segments are neighbours" is on by default and bound to the parameter
    node, the one output model is for one bone (a note says what several bones get)."""
    _, widgets = _ui_widgets()

    def prop(name, key):
        return [p for p in widgets[name]["elem"].findall("property") if p.get("name") == key]

    selector = widgets["segmentSelector"]
    assert selector["cls"] == "qMRMLSegmentSelectorWidget"
    assert [p.findtext("bool") for p in prop("segmentSelector", "multiSelection")] == ["true"]
    box = widgets["neighboursCheckBox"]
    assert box["cls"] == "QCheckBox" and box["param"] == "neighbours" and box["tip"]
    assert [p.findtext("bool") for p in prop("neighboursCheckBox", "checked")] == ["true"]
    assert prop("neighboursCheckBox", "text")[0].findtext("string") == "Other segments are neighbours"
    note = widgets["outputNoteLabel"]
    assert note["cls"] == "QLabel" and [p.findtext("bool") for p in prop("outputNoteLabel", "visible")] == ["false"]
    # the parameter node: the chosen segments as a list, the neighbours switch on by default
    tree = _module_ast()
    cls = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == "BoneWatertightParameterNode")
    fields = {s.target.id: s for s in cls.body if isinstance(s, ast.AnnAssign)}
    assert ast.unparse(fields["segmentIds"].annotation) == "list[str]"
    assert ast.unparse(fields["neighbours"].annotation) == "bool" and fields["neighbours"].value.value is True
    # each .ui row of a form layout is used once per column
    for layout in ET.parse(UI_FILE).iter("layout"):
        if layout.get("class") != "QFormLayout":
            continue
        cells = [(i.get("row"), i.get("column")) for i in layout.findall("item")]
        assert len(cells) == len(set(cells)), layout.get("name")


def _placeholder_ui(tmp_path):
    """Copy of the .ui with ctk/qMRML classes replaced by plain Qt ones (for the picture only)."""
    text = UI_FILE.read_text(encoding="utf-8")
    tree = ET.ElementTree(ET.fromstring(text))
    root = tree.getroot()
    repl = {"qMRMLWidget": "QWidget", "ctkCollapsibleButton": "QGroupBox", "ctkSliderWidget": "QDoubleSpinBox",
            "qMRMLNodeComboBox": "QComboBox", "qMRMLSegmentSelectorWidget": "QComboBox"}
    for w in root.iter("widget"):
        cls = w.get("class")
        if cls in repl:
            w.set("class", repl[cls])
            for p in list(w.findall("property")):
                n = p.get("name")
                if cls == "ctkCollapsibleButton" and n == "text":
                    p.set("name", "title")
                elif n in ("collapsed", "nodeTypes", "showChildNodeTypes", "addEnabled", "removeEnabled",
                           "noneEnabled", "renameEnabled", "baseName", "editEnabled", "specialValueText",
                           "multiSelection"):
                    w.remove(p)
    cw = root.find("customwidgets")
    if cw is not None:
        root.remove(cw)
    out = tmp_path / "placeholder.ui"
    tree.write(out, encoding="utf-8", xml_declaration=True)
    return out


def test_render_ui_offscreen(tmp_path):
    pytest.importorskip("PySide6")
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from PySide6.QtCore import QFile
    from PySide6.QtUiTools import QUiLoader
    from PySide6.QtWidgets import QApplication

    app = QApplication.instance() or QApplication([])
    path = _placeholder_ui(tmp_path)
    f = QFile(str(path))
    assert f.open(QFile.ReadOnly)
    widget = QUiLoader().load(f)
    f.close()
    assert widget is not None
    widget.findChild(type(widget), "BoneWatertight")
    widget.resize(440, 1250)
    widget.show()
    app.processEvents()
    picture = widget.grab()
    out = Path(os.environ.get("BW_UI_PNG", "/tmp/BoneWatertight_ui.png"))
    assert picture.save(str(out))
    assert picture.width() > 100 and picture.height() > 100
    widget.close()
