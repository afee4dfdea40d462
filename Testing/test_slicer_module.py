"""The Slicer module's decisions and wiring, without Qt (issue 13).

``BoneWatertight.py`` imports qt/ctk and runs only in 3D Slicer. What it decides lives in
``BoneWatertightLib.app.slicer_support`` and is tested here as plain Python; how the widget
uses it is checked on the module's source (AST): which signals drive the preview, which
properties are set on which widget class (against the properties CTK and Qt declare), that
Auto goes through the preview's hide rule and the schema's ranges. The in-Slicer self-test's
own code (BoneWatertightTest) runs here on slicer-core's real MRML classes.

Defects: 2 (slider signals), 3 (install guard), 4 ("auto" on the inner spin box), 6 (Auto's
overlay), 7 (Auto on metal CT), 9 (scene close, widget side), self-tests install-or-skip.
"""

from __future__ import annotations

import ast
import logging
import time
import types
import typing
import unittest
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from BoneWatertightLib.app import slicer_support
from BoneWatertightLib.app.slicer_support import (
    ApplyGuard,
    PreviewController,
    clamp_threshold_proposal,
    dependency_test_plan,
)
from BoneWatertightLib.params import SCHEMA, Parameters

ROOT = Path(__file__).resolve().parents[1]
MODULE_PY = ROOT / "BoneWatertight" / "BoneWatertight.py"
UI_FILE = ROOT / "BoneWatertight" / "Resources" / "UI" / "BoneWatertight.ui"


def _module():
    return ast.parse(MODULE_PY.read_text(encoding="utf-8"))


def _method(name, cls="BoneWatertightWidget"):
    for node in ast.walk(_module()):
        if isinstance(node, ast.ClassDef) and node.name == cls:
            for item in node.body:
                if isinstance(item, ast.FunctionDef) and item.name == name:
                    return item
    raise AssertionError(f"{cls}.{name} not found")


def _calls(tree):
    return [ast.unparse(n.func) for n in ast.walk(tree) if isinstance(n, ast.Call)]


# ---------------------------------------------------------------------------------------
# defect 3: Apply during the open3d install
# ---------------------------------------------------------------------------------------

def test_apply_guard_ignores_clicks_while_open3d_installs():
    guard = ApplyGuard()
    assert guard.click() == "start" and guard.button(True).enabled
    with guard.installing():
        state = guard.button(True)
        assert not state.enabled and state.busyCursor and "open3d" in state.text
        # pip pumps events: a click queued before the button went grey arrives now
        assert guard.click() == "ignore" and guard.click() == "ignore"
        assert guard.busy and not guard.cancelRequested
        with pytest.raises(RuntimeError):
            guard.beginRun()  # no run may start from inside the install
    assert guard.state == guard.IDLE and guard.button(True) == guard.button(True)
    assert guard.button(True).text == "Apply" and not guard.button(True).busyCursor


def test_apply_guard_run_cancel_and_back():
    guard = ApplyGuard()
    with guard.running():
        assert guard.button(True).text == "Cancel" and guard.button(True).enabled
        assert not guard.cancelRequested
        assert guard.click() == "cancel" and guard.cancelRequested
        assert not guard.button(True).enabled  # "Cancelling...": no second cancel
        assert guard.click() == "ignore"
    assert guard.state == guard.IDLE and not guard.cancelRequested
    assert guard.click() == "start"
    assert not guard.button(False).enabled  # inputs missing
    with pytest.raises(RuntimeError):
        guard.endRun()
    # the scene closing asks a running run to stop (and only a running one)
    assert not guard.requestCancel()
    with guard.running():
        assert guard.requestCancel() and guard.cancelRequested
    # an exception inside a phase still returns to idle
    with pytest.raises(ValueError):
        with guard.installing():
            raise ValueError("pip failed")
    assert guard.state == guard.IDLE


def test_widget_drives_apply_through_the_guard_with_a_busy_cursor():
    apply = _method("onApplyButton")
    first = apply.body[0]
    assert "self._applyGuard.click()" in ast.unparse(first), "the guard must decide first"
    text = ast.unparse(apply)
    assert "self._applyGuard.running()" in text and "self._running" not in text
    assert "action != 'start'" in text  # ignore = return
    install = ast.unparse(_method("_ensureOpen3d"))
    assert "self._applyGuard.installing()" in install
    assert "qt.QApplication.setOverrideCursor" in install and "qt.QApplication.restoreOverrideCursor" in install
    # the restore is in a finally: a failing pip must not leave the busy cursor
    tree = _method("_ensureOpen3d")
    finals = [ast.unparse(t) for n in ast.walk(tree) if isinstance(n, ast.Try) for t in n.finalbody]
    assert any("restoreOverrideCursor" in f for f in finals)
    assert "prompt_install=False" in install  # asked once, before the busy cursor
    assert "self._checkCanApply()" in install  # the button shows the guard's state
    check = ast.unparse(_method("_checkCanApply"))
    assert "self._applyGuard.button(" in check and "self.ui.applyButton.enabled = state.enabled" in check


# ---------------------------------------------------------------------------------------
# defects 2 + 6: the preview follows the sliders, and every show is followed by a hide
# ---------------------------------------------------------------------------------------

class _Recorder:
    def __init__(self):
        self.events = []

    def __getattr__(self, name):
        return lambda *a: self.events.append(name)


def _controller():
    r = _Recorder()
    return PreviewController(show=r.show, hide=r.hide, armHideTimer=r.arm, disarmHideTimer=r.disarm), r


def test_preview_controller_every_show_arms_the_hide_timer():
    c, r = _controller()
    assert c.thresholdsChanged(enabled=True, running=False)
    assert c.thresholdsChanged(enabled=True, running=False)
    assert r.events == ["show", "arm", "show", "arm"] and c.shown
    c.hideNow()
    assert r.events[-2:] == ["disarm", "hide"] and not c.shown


def test_auto_shows_no_overlay_with_live_preview_off_and_a_timed_one_with_it_on():
    c, r = _controller()
    assert not c.autoApplied(enabled=False, running=False)
    assert r.events == []
    assert not c.autoApplied(enabled=True, running=True)  # no preview during a run
    assert r.events == []
    # values unchanged (no valueChanged signal): Auto still gets its hide timer
    assert c.autoApplied(enabled=True, running=False)
    assert r.events == ["show", "arm"]
    c.previewToggled(False)  # switching live preview off takes it away at once
    assert r.events[-2:] == ["disarm", "hide"]


def test_widget_wires_sliders_auto_and_timer_through_the_controller():
    # ctkSliderWidget tracks by default; valueIsChanging is only emitted with tracking off,
    # so a connection to it never fires: the preview must follow valueChanged
    connects = [ast.unparse(n) for n in ast.walk(_module())
                if isinstance(n, ast.Call) and ast.unparse(n.func).endswith(".connect")]
    assert not [c for c in connects if "valueIsChanging" in c]
    setup = ast.unparse(_method("setup"))
    assert "slider.connect('valueChanged(double)', self.onThresholdChanged)" in setup
    assert "slider.tracking = True" in setup
    assert "self._previewTimer.connect('timeout()', self._previewController.hideNow)" in setup
    assert "self.ui.previewCheckBox.connect('toggled(bool)', self._previewController.previewToggled)" in setup
    auto = _method("onAutoThreshold")
    calls = _calls(auto)
    assert "self.updatePreview" not in calls, "Auto must not show a preview without its hide timer"
    assert "self._previewController.autoApplied" in calls
    assert "clamp_threshold_proposal" in calls
    changed = _calls(_method("onThresholdChanged"))
    assert changed == ["self._previewController.thresholdsChanged"]
    # connectGui writes the sliders when the module is entered or a scene loads: no preview
    assert "if self._connectingGui:" in ast.unparse(_method("onThresholdChanged"))
    assert "self._connectingGui = True" in ast.unparse(_method("setParameterNode"))
    # the per-step work is the cached preview, created once and kept
    update = ast.unparse(_method("updatePreview"))
    assert "preview.ThresholdPreview(slicer.mrmlScene)" in update and "self._preview.update(" in update


def test_widget_cancels_a_running_run_when_the_scene_closes():
    close = _calls(_method("onSceneStartClose"))
    assert "self._applyGuard.requestCancel" in close and "self.removePreview" in close
    assert "self._applyGuard.cancelRequested" in ast.unparse(_method("_progress"))


# ---------------------------------------------------------------------------------------
# issue 10 item 3: several bones from the panel
# ---------------------------------------------------------------------------------------

def test_widget_chooses_several_segments_and_runs_them_together():
    """The selector's multi-selection signal drives the parameter node (segmentIds, and the
    first as segmentId for older versions); Apply runs every chosen segment in one joint run
    with the neighbours switch, one bone with the chosen output model, several with the
    models of their previous run; the result shows a line per bone and pair, warnings in the
    status; preview and Auto use all chosen segments."""
    setup = ast.unparse(_method("setup"))
    assert ("self.ui.segmentSelector.connect('segmentSelectionChanged(QStringList)', "
            "self.onSegmentSelectorChanged)") in setup
    # in multi-selection mode the selector never emits currentSegmentChanged
    assert "currentSegmentChanged" not in MODULE_PY.read_text(encoding="utf-8")
    sync = ast.unparse(_method("_syncSegmentSelectorFromParameterNode"))
    assert "nodes.segment_selection(seg, list(p.segmentIds), p.segmentId" in sync
    assert "self.ui.segmentSelector.setSelectedSegmentIDs(ids)" in sync
    assert "self._updatingSegmentSelector = True" in sync and "finally:" in sync
    store = ast.unparse(_method("_storeSegmentSelection"))
    assert "p.segmentIds = ids" in store and "p.segmentId = first" in store
    changed = ast.unparse(_method("onSegmentSelectorChanged"))
    assert "self.ui.segmentSelector.selectedSegmentIDs()" in changed
    check = ast.unparse(_method("_checkCanApply"))
    assert "ids = self._chosenSegmentIds()" in check and "p.inputSegmentation and ids" in check
    apply = _method("onApplyButton")
    calls = _calls(apply)
    assert "self.logic.processManyWithResult" in calls and "self.logic.processWithResult" not in calls
    text = ast.unparse(apply)
    assert "neighbours='auto' if p.neighbours else 'none'" in text
    assert "nodes.previous_output_models(slicer.mrmlScene, p.inputSegmentation, ids) if several" in text
    assert "else [p.outputModel]" in text and "p.outputModel = out.modelNodes[0]" in text
    assert "lines = out.summaryLines()" in text and "self.ui.resultLabel.text = '\\n'.join(lines)" in text
    assert "if out.warnings:" in text
    for method in ("updatePreview", "onAutoThreshold"):
        assert "self._chosenSegmentIds()" in ast.unparse(_method(method)), method
    logic = ast.unparse(_method("processManyWithResult", "BoneWatertightLogic"))
    assert "nodes.run_many_on_nodes(" in logic
    process = ast.unparse(_method("process", "BoneWatertightLogic"))
    assert "return self.processMany(" in process  # a list of segment IDs


# ---------------------------------------------------------------------------------------
# defect 4: which properties exist on which widget class
# ---------------------------------------------------------------------------------------

# Q_PROPERTY declarations (CTK @868d56c: Libs/Widgets/ctkSliderWidget.h, ctkCollapsibleButton.h;
# ctkDoubleSpinBox.h declares no specialValueText either) and the Qt 5/6 property lists of the
# Qt classes the panel uses (inherited ones included). PythonQt silently stores any other name
# as a Python attribute of the wrapper, so a wrong name has no effect and raises nothing.
_QWIDGET = {"enabled", "visible", "toolTip", "styleSheet", "minimumWidth", "maximumWidth",
            "minimumHeight", "maximumHeight", "sizePolicy", "windowTitle", "focusPolicy", "cursor",
            "font", "whatsThis", "statusTip"}
_QABSTRACTBUTTON = _QWIDGET | {"text", "icon", "iconSize", "checkable", "checked", "autoRepeat",
                               "autoExclusive", "shortcut", "down"}
_QABSTRACTSPINBOX = _QWIDGET | {"readOnly", "buttonSymbols", "specialValueText", "wrapping", "frame",
                                "alignment", "accelerated", "keyboardTracking", "correctionMode",
                                "showGroupSeparator", "text"}
QT_CTK_PROPERTIES = {
    "QWidget": _QWIDGET,
    "QPushButton": _QABSTRACTBUTTON | {"default", "autoDefault", "flat"},
    "QCheckBox": _QABSTRACTBUTTON | {"tristate"},
    "QLabel": _QWIDGET | {"text", "wordWrap", "alignment", "textFormat", "openExternalLinks",
                          "textInteractionFlags", "margin", "indent"},
    "QProgressBar": _QWIDGET | {"value", "minimum", "maximum", "format", "textVisible", "orientation",
                                "alignment", "invertedAppearance"},
    "QPlainTextEdit": _QWIDGET | {"plainText", "readOnly", "placeholderText", "lineWrapMode",
                                  "maximumBlockCount"},
    "QComboBox": _QWIDGET | {"currentIndex", "currentText", "editable", "maxVisibleItems", "maxCount"},
    "QSpinBox": _QABSTRACTSPINBOX | {"minimum", "maximum", "value", "singleStep", "prefix", "suffix",
                                     "displayIntegerBase", "stepType"},
    "QDoubleSpinBox": _QABSTRACTSPINBOX | {"minimum", "maximum", "value", "singleStep", "prefix",
                                           "suffix", "decimals", "stepType"},
    "ctkCollapsibleButton": _QABSTRACTBUTTON | {"collapsed", "collapsedHeight", "flat",
                                                "contentsFrameShape", "contentsFrameShadow",
                                                "contentsLineWidth", "contentsMidLineWidth",
                                                "buttonTextAlignment", "indicatorAlignment"},
    # Slicer @583e9b37: Libs/MRML/Widgets/qMRMLNodeComboBox.h
    "qMRMLNodeComboBox": _QWIDGET | {"currentNodeID", "nodeTypes", "showHidden", "showChildNodeTypes",
                                     "hideChildNodeTypes", "baseName", "noneEnabled", "addEnabled",
                                     "removeEnabled", "editEnabled", "renameEnabled",
                                     "interactionNodeSingletonTag", "selectNodeUponCreation",
                                     "noneDisplay", "sizeAdjustPolicy"},
    "ctkSliderWidget": _QWIDGET | {"decimals", "singleStep", "pageStep", "minimum", "maximum", "value",
                                   "prefix", "suffix", "tickInterval", "tickPosition",
                                   "synchronizeSiblings", "spinBoxAlignment", "tracking",
                                   "spinBoxVisible", "popupSlider", "invertedAppearance",
                                   "invertedControls"},
}


def _ui_classes():
    tree = ET.parse(UI_FILE)
    classes, bound = {}, set()
    for w in tree.iter("widget"):
        classes[w.get("name")] = w.get("class")
        for p in w.findall("property"):
            if p.get("name") == "SlicerParameterName" and p.findtext("string") in SCHEMA:
                bound.add(w.get("class"))
    return classes, bound


def _narrow(test: str, body: bool, current: set) -> set:
    """The widget classes ``widget`` can be inside an if-branch of applySchemaToWidgets."""
    kinds = {"spec.kind is bool": {"QCheckBox"}, "spec.kind is float": {"ctkSliderWidget"},
             "spec.numeric": {"ctkSliderWidget", "QSpinBox"}}
    if test not in kinds:
        return current
    return current & kinds[test] if body else current - kinds[test]


def property_audit(function: ast.FunctionDef, widget_classes: set) -> list:
    """Assignments ``<name>.<prop> = ...`` in applySchemaToWidgets whose target class (from
    the branch it is in) does not declare ``prop``. ``label`` is a QLabel, a loop variable over
    innerSpinBoxes(...) a QDoubleSpinBox."""
    problems = []

    def check(target, scope):
        if not (isinstance(target, ast.Attribute) and isinstance(target.value, ast.Name)):
            return
        for cls in sorted(scope.get(target.value.id, ())):
            if target.attr not in QT_CTK_PROPERTIES[cls]:
                problems.append(f"{target.value.id}.{target.attr} = ... on a {cls}, which has no "
                                f"property '{target.attr}'")

    def visit(stmts, scope):
        for stmt in stmts:
            if isinstance(stmt, ast.If):
                test = ast.unparse(stmt.test)
                visit(stmt.body, dict(scope, widget=_narrow(test, True, scope["widget"])))
                visit(stmt.orelse, dict(scope, widget=_narrow(test, False, scope["widget"])))
            elif isinstance(stmt, ast.For):
                inner = dict(scope)
                if isinstance(stmt.target, ast.Name):
                    it = ast.unparse(stmt.iter)
                    if it.startswith("innerSpinBoxes("):
                        inner[stmt.target.id] = {"QDoubleSpinBox"}
                    elif stmt.target.id not in scope:
                        inner[stmt.target.id] = set()
                visit(stmt.body, inner)
            elif isinstance(stmt, ast.Assign):
                for target in stmt.targets:
                    for t in (target.elts if isinstance(target, ast.Tuple) else [target]):
                        check(t, scope)
            elif hasattr(stmt, "body") and isinstance(stmt.body, list):
                visit(stmt.body, scope)

    visit(function.body, {"widget": set(widget_classes), "label": {"QLabel"}})
    return problems


def test_every_property_the_schema_sets_exists_on_its_widget_class():
    _, bound = _ui_classes()
    assert {"ctkSliderWidget", "QSpinBox", "QCheckBox"} <= bound <= {"ctkSliderWidget", "QSpinBox",
                                                                   "QCheckBox", "QComboBox"}
    method = _method("applySchemaToWidgets")
    assert property_audit(method, bound) == []
    # "auto" is set on the spin box inside the slider widget
    text = ast.unparse(method)
    assert "for spinBox in innerSpinBoxes(widget):" in text and "spinBox.specialValueText" in text
    helper = next(n for n in _module().body if isinstance(n, ast.FunctionDef) and n.name == "innerSpinBoxes")
    assert "findChildren(qt.QDoubleSpinBox)" in ast.unparse(helper)


def test_property_audit_catches_special_value_text_on_the_slider_widget():
    """The audit, fed the code as it was before the fix, reports it."""
    before = ast.parse(
        "def applySchemaToWidgets(self, uiWidget):\n"
        "    for widget in uiWidget.findChildren(qt.QWidget):\n"
        "        if spec.kind is bool:\n"
        "            widget.text = spec.label\n"
        "        elif spec.numeric:\n"
        "            if spec.kind is float:\n"
        "                widget.minimum, widget.maximum = low, high\n"
        "                if spec.allows_auto:\n"
        "                    widget.specialValueText = 'auto'\n").body[0]
    _, bound = _ui_classes()
    problems = property_audit(before, bound)
    assert problems == ["widget.specialValueText = ... on a ctkSliderWidget, which has no property "
                        "'specialValueText'"]


def test_every_ui_property_the_module_sets_exists_on_the_widget_class():
    classes, _ = _ui_classes()
    problems = []
    for node in ast.walk(_module()):
        targets = node.targets if isinstance(node, ast.Assign) else []
        for target in targets:
            t = target
            if isinstance(t, ast.Attribute) and isinstance(t.value, ast.Attribute) and \
                    ast.unparse(t.value.value) == "self.ui":
                cls = classes.get(t.value.attr)
                assert cls is not None, f"self.ui.{t.value.attr} is not in the .ui"
                if t.attr not in QT_CTK_PROPERTIES[cls]:
                    problems.append(f"self.ui.{t.value.attr}.{t.attr} ({cls})")
    assert problems == []
    # the sections and sliders the module addresses by loop variable
    setup = ast.unparse(_method("setup"))
    assert "for slider in (self.ui.thetaMaxSlider, self.ui.h0Slider, self.ui.htSlider):" in setup
    assert {classes[n] for n in ("thetaMaxSlider", "h0Slider", "htSlider")} == {"ctkSliderWidget"}
    assert "tracking" in QT_CTK_PROPERTIES["ctkSliderWidget"]


# ---------------------------------------------------------------------------------------
# defect 7: Auto's proposal inside the schema's ranges
# ---------------------------------------------------------------------------------------

def _panel_ok(values):
    for name, value in values.items():
        low, high = SCHEMA[name].panel_range()
        assert low <= value <= high, (name, value)
    Parameters(**values).validate()


def test_clamp_keeps_an_ordinary_proposal():
    values, notes = clamp_threshold_proposal({"theta_max": 2500, "h0": 300, "ht": 150,
                                              "soft_tissue": 40.0, "cortex": 1400.0})
    assert values == {"theta_max": 2500.0, "h0": 300.0, "ht": 150.0} and notes == []
    _panel_ok(values)


@pytest.mark.parametrize("proposal", [
    {"theta_max": 14001, "h0": 2700, "ht": 1150},   # metal, extended-HU scale
    {"theta_max": 30001, "h0": 5200, "ht": 4100},   # both windows above the field's maximum
    {"theta_max": 4200, "h0": 3990, "ht": 3980},    # order must survive the clamp
])
def test_clamp_brings_metal_proposals_into_range_in_order(proposal):
    values, notes = clamp_threshold_proposal(proposal)
    _panel_ok(values)
    assert values["ht"] < values["h0"] < values["theta_max"] == SCHEMA["theta_max"].maximum
    assert any("Upper limit" in n and "4000" in n for n in notes)


def test_auto_on_metal_ct_gives_values_the_parameter_node_accepts():
    slicer = pytest.importorskip("slicer")
    import SimpleITK as sitk

    from BoneWatertightLib import mrml
    from BoneWatertightLib.app import nodes

    scene = slicer.vtkMRMLScene()
    logic = slicer.vtkSlicerSegmentationsModuleLogic()
    logic.SetMRMLScene(scene)
    rng = np.random.default_rng(0)
    k, j, i = np.mgrid[0:40, 0:40, 0:40]
    r = np.sqrt((i - 20.0) ** 2 + (j - 20.0) ** 2 + (k - 20.0) ** 2)
    hu = 40 + 1360 * (r < 10) + rng.normal(0, 10, r.shape)
    hu[(r < 4)] = 18000  # a metal implant (extended HU)
    ct = sitk.GetImageFromArray(np.round(hu).astype(np.int32))
    volume = mrml.volume_node_from_sitk(scene, ct)
    mask = sitk.GetImageFromArray((r < 11).astype(np.uint8))
    seg, segId = mrml.segmentation_node_from_mask(scene, mask)
    proposal = nodes.propose_thresholds(volume, seg, segId)
    # metal is left out of the estimate: theta_max is kept and H0 stays a bone level
    assert proposal["theta_max"] <= SCHEMA["theta_max"].maximum and proposal["h0"] < 600
    values, notes = clamp_threshold_proposal(dict(proposal, theta_max=20000.0))
    _panel_ok(values)  # and the panel's clamp still guards values from elsewhere
    assert notes


# ---------------------------------------------------------------------------------------
# self-tests: install or skip, clearly
# ---------------------------------------------------------------------------------------

def test_dependency_test_plan():
    assert dependency_test_plan(True, {}) == "run"
    assert dependency_test_plan(True, {slicer_support.TEST_INSTALL_VARIABLE: "0"}) == "run"
    assert dependency_test_plan(False, {}) == "install"
    for off in ("0", "no", "false", "OFF"):
        assert dependency_test_plan(False, {slicer_support.TEST_INSTALL_VARIABLE: off}) == "skip"
    message = slicer_support.dependency_skip_message("no network")
    assert message.startswith("SKIPPED: open3d") and "no network" in message
    assert slicer_support.TEST_INSTALL_VARIABLE in message


class _SlicerModuleTestBase(unittest.TestCase):
    """What ScriptedLoadableModuleTest adds to unittest.TestCase, for running the module's
    own test code outside Slicer (it is not in slicer-core)."""

    def delayDisplay(self, message, msec=None):
        logging.info(message)


class _ScriptedLogicBase:
    def __init__(self):
        pass


def _module_test_class():
    """BoneWatertightTest and BoneWatertightLogic from BoneWatertight.py, compiled against
    slicer-core (the Qt-only base classes replaced by the two minimal ones above)."""
    import slicer

    wanted = {"BoneWatertightLogic", "BoneWatertightTest"}
    body = [n for n in _module().body if isinstance(n, ast.ClassDef) and n.name in wanted]
    assert len(body) == 2
    namespace = {
        "__name__": "BoneWatertight_selftest", "slicer": slicer, "logging": logging, "time": time,
        "Optional": typing.Optional, "Sequence": typing.Sequence, "Union": typing.Union,
        "ScriptedLoadableModuleTest": _SlicerModuleTestBase,
        "ScriptedLoadableModuleLogic": _ScriptedLogicBase,
        "vtkMRMLScalarVolumeNode": slicer.vtkMRMLScalarVolumeNode,
        "vtkMRMLSegmentationNode": slicer.vtkMRMLSegmentationNode,
        "vtkMRMLModelNode": slicer.vtkMRMLModelNode,
        "dependency_test_plan": dependency_test_plan,
        "dependency_skip_message": slicer_support.dependency_skip_message,
        "BoneWatertightParameterNode": None,
    }
    exec(compile(ast.Module(body=body, type_ignores=[]), str(MODULE_PY), "exec"), namespace)
    return namespace["BoneWatertightTest"]


@pytest.fixture()
def slicer_scene(monkeypatch):
    """slicer.mrmlScene / slicer.modules as the running application provides them (only
    attributes slicer-core lacks are added; its classes are the real ones)."""
    slicer = pytest.importorskip("slicer")
    scene = slicer.vtkMRMLScene()
    logic = slicer.vtkSlicerSegmentationsModuleLogic()
    logic.SetMRMLScene(scene)
    monkeypatch.setattr(slicer, "mrmlScene", scene, raising=False)
    monkeypatch.setattr(slicer, "modules", types.SimpleNamespace(
        segmentations=types.SimpleNamespace(logic=lambda: logic)), raising=False)
    return scene


def test_the_in_slicer_self_test_passes_on_real_mrml(slicer_scene):
    """BoneWatertightTest's own methods (capsule accuracy, bad input leaves the scene), run
    by unittest as ctest's slicer.testing.runUnitTest does."""
    cls = _module_test_class()
    suite = unittest.TestLoader().loadTestsFromTestCase(cls)
    names = sorted(t._testMethodName for t in suite)
    assert names == ["test_BoneWatertight_bad_input_leaves_scene", "test_BoneWatertight_capsule",
                     "test_BoneWatertight_two_bones"]
    result = unittest.TestResult()
    suite.run(result)
    assert result.wasSuccessful(), result.errors + result.failures
    assert not result.skipped  # open3d is installed here: the capsule really ran


def test_the_in_slicer_self_test_skips_clearly_without_open3d(slicer_scene, monkeypatch):
    """With open3d unavailable and installing switched off, the capsule test is reported as
    skipped with the reason (ctest: passed, not failed); runTest ("Reload and Test") says so
    instead of raising."""
    import builtins

    real_import = builtins.__import__

    def no_open3d(name, *args, **kwargs):
        if name == "open3d" or name.startswith("open3d."):
            raise ImportError("No module named 'open3d' (test)")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_open3d)
    monkeypatch.setenv(slicer_support.TEST_INSTALL_VARIABLE, "0")
    cls = _module_test_class()
    result = unittest.TestResult()
    unittest.TestLoader().loadTestsFromTestCase(cls).run(result)
    assert result.wasSuccessful(), result.errors + result.failures
    assert [t._testMethodName for t, _ in result.skipped] == ["test_BoneWatertight_capsule",
                                                              "test_BoneWatertight_two_bones"]
    assert all(reason.startswith("SKIPPED: open3d is not available") for _, reason in result.skipped)
    shown = []
    test = cls("runTest")
    test.delayDisplay = shown.append
    test.runTest()  # no exception
    assert sum(m.startswith("SKIPPED: open3d") for m in shown) == 2
