"""One parameter schema (BoneWatertightLib.params.SCHEMA); every surface derived from it agrees.

Surfaces checked against the schema, ranges and defaults included:
- the library's Parameters (defaults) and validate() (type and inclusive range of every
  parameter, NaN/inf, wrong types, the HT < H0 < theta_max cross-check);
- the command line (flags, help text with range/unit/default, value parsing, out-of-range
  refused with exit code 2 and no file);
- the Slicer parameter node (annotations with WithinRange and defaults, built by
  BoneWatertight.py's withLibraryParameters; executed from the module's own source);
- the panel's .ui (one widget per parameter, right class, right section, and no copy of a
  bound, default or tooltip: those come from the schema in setup());
- the Slicer batch script's options;
- no presets anywhere (they were removed: each equalled the defaults).
"""

from __future__ import annotations

import ast
import dataclasses
import importlib.util
import math
import os
import typing
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from BoneWatertightLib.app import cli, options
from BoneWatertightLib.errors import InputError
from BoneWatertightLib.params import PRESETS_REMOVED, SCHEMA, Parameters

ROOT = Path(__file__).resolve().parents[1]
MODULE_PY = ROOT / "BoneWatertight" / "BoneWatertight.py"
UI_FILE = ROOT / "BoneWatertight" / "Resources" / "UI" / "BoneWatertight.ui"
BATCH_SCRIPT = ROOT / "Resources" / "Scripts" / "bonewatertight_batch.py"
PANEL = [s for s in SCHEMA.values() if s.panel is not None]
NUMERIC = [s for s in SCHEMA.values() if s.numeric]
WIDGET_CLASS = {float: "ctkSliderWidget", int: "QSpinBox", bool: "QCheckBox", str: "QComboBox"}
# Properties that the schema sets in setup(); the .ui must not repeat them.
SCHEMA_OWNED = {"minimum", "maximum", "value", "toolTip", "singleStep", "decimals", "suffix",
                "specialValueText", "checked", "text"}


def _ids(specs):
    return [s.name for s in specs]


# ---------------------------------------------------------------------------------- library

def test_schema_is_complete_and_matches_the_dataclass():
    fields = {f.name: f for f in dataclasses.fields(Parameters)}
    assert list(fields) == list(SCHEMA)
    defaults = Parameters()
    hints = typing.get_type_hints(Parameters)
    for name, spec in SCHEMA.items():
        assert getattr(defaults, name) == spec.default
        assert spec.help and spec.label, name
        if spec.numeric:
            assert spec.minimum is not None and spec.maximum is not None, name
            assert spec.minimum < spec.maximum
        allows_none = type(None) in typing.get_args(hints[name])
        assert allows_none == spec.allows_auto, f"{name}: Optional iff it has an auto meaning"
    assert SCHEMA["edge_level"].default is None  # auto: the blurred-slab model
    assert (SCHEMA["edge_level"].minimum, SCHEMA["edge_level"].maximum) == (0.3, 0.9)
    assert "damping" in SCHEMA["beta"].help and "constraint term" not in SCHEMA["beta"].help


def test_stage_defaults_agree_with_the_schema():
    """Stage functions' own keyword defaults are those of the schema (no second default)."""
    import inspect

    from BoneWatertightLib.stages import deform, filtering, prepare, refine, threshold, visible

    checked = 0
    for func in (prepare.prepare_labels, filtering.hybrid_filter,
                 threshold.bone_masks, threshold.erosions_to_separate,
                 visible.visible_points, deform.Deformer.__init__, refine.refine_to_edges,
                 refine.refine_pass):
        for name, p in inspect.signature(func).parameters.items():
            if name in SCHEMA and p.default is not inspect.Parameter.empty:
                assert p.default == SCHEMA[name].default, f"{func.__qualname__}({name}=...)"
                checked += 1
    assert checked >= 15


@pytest.mark.parametrize("spec", NUMERIC, ids=_ids(NUMERIC))
def test_validate_range_of_every_number(spec):
    base = Parameters(h0=300.0, ht=150.0, theta_max=2500.0)

    def with_value(value):
        changes = {spec.name: value}
        # keep HT < H0 < theta_max satisfiable at the range ends of the thresholds
        if spec.name == "ht" and isinstance(value, float) and value >= 300:
            changes.update(h0=4000.0, theta_max=4000.0)
        return base.replace(**changes)

    for ok in (spec.minimum, spec.maximum, spec.default):
        if ok is None:
            continue
        try:
            with_value(ok).validate()
        except InputError as exc:
            assert "Thresholds out of order" in str(exc), exc
    step = 1 if spec.kind is int else 1e-6 * max(1.0, abs(spec.maximum))
    bad_values = [spec.minimum - step, spec.maximum + step, "3", True]
    if spec.kind is float:
        bad_values += [math.nan, math.inf, -math.inf]
    else:
        bad_values += [float(spec.default or 1) + 0.5]
    if not spec.allows_auto:
        bad_values.append(None)
    for bad in bad_values:
        with pytest.raises(InputError) as err:
            with_value(bad).validate()
        text = str(err.value)
        assert text.startswith(spec.name + " "), text
        if bad is not None and not isinstance(bad, (str, bool)):
            assert f"{spec.minimum:g} and {spec.maximum:g}" in text, text
    if spec.allows_auto:
        with_value(None).validate()


def test_validate_bools_and_thresholds():
    for spec in SCHEMA.values():
        if spec.kind is bool:
            for bad in (1, "yes", None):
                with pytest.raises(InputError, match=spec.name):
                    Parameters().replace(**{spec.name: bad}).validate()
    with pytest.raises(InputError, match="HT < H0 < theta_max"):
        Parameters(h0=200.0, ht=250.0).validate()
    with pytest.raises(InputError, match="Unknown parameter"):
        Parameters().replace(no_such=1)


def test_choice_parameter_is_one_declaration():
    """A str from a fixed set needs only its declaration: schema, validation, CLI option."""
    from BoneWatertightLib import params as P

    @dataclasses.dataclass
    class Extended(P.Parameters):
        on_implausible: str = P.param("fail", "output", None, label="On implausible",
                                      choices=("fail", "warn"), help="What an implausible "
                                      "surface does")

    schema = P._build_schema(Extended)
    spec = schema["on_implausible"]
    assert spec.kind is str and spec.choices == ("fail", "warn")
    spec.check("warn")
    with pytest.raises(InputError, match="on_implausible must be one of fail, warn"):
        spec.check("ignore")
    assert "One of: fail, warn" in spec.describe()


# ---------------------------------------------------------------------------------- CLI

def _actions(parser):
    return {a.dest[len(options.PARAM_DEST_PREFIX):]: a for a in parser._actions
            if a.dest.startswith(options.PARAM_DEST_PREFIX)}


def _normal(text):
    return " ".join(text.split())


def test_cli_options_match_the_schema():
    parser = cli.build_parser()
    actions = _actions(parser)
    assert list(actions) == list(SCHEMA)
    helptext = _normal(parser.format_help())
    for name, spec in SCHEMA.items():
        action = actions[name]
        flag = "--" + name.replace("_", "-")
        assert flag in action.option_strings
        shown = action.help.replace("%%", "%")
        assert _normal(shown) == _normal(spec.describe())
        if spec.numeric:
            assert f"Range: {spec.range_text()}." in shown
            assert f"Default: {spec.default_text()}" in shown
            if spec.unit:
                assert spec.unit in shown
            assert action.type("auto" if spec.allows_auto else str(spec.default)) == spec.default
        if spec.kind is bool:
            assert "--no-" + name.replace("_", "-") in action.option_strings
        # every option's help (with its range) is in --help, whatever argparse's line breaks
        assert _normal(spec.describe()).split(" Default:")[0][:60] in helptext
    assert cli.parameters_from_args(parser.parse_args([])) == Parameters()


@pytest.mark.parametrize("spec", NUMERIC, ids=_ids(NUMERIC))
def test_cli_refuses_out_of_range_values(spec, capsys, tmp_path):
    beyond = spec.maximum + (1 if spec.kind is int else 0.5 * (spec.maximum - spec.minimum))
    code = cli.main(["--ct", str(tmp_path / "ct.nrrd"), "--seg", str(tmp_path / "s.nrrd"),
                     "--label", "1", "--out", str(tmp_path / "b.stl"),
                     "--" + spec.name.replace("_", "-"), f"{beyond:g}"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"error: {spec.name} must be between {spec.minimum:g} and {spec.maximum:g}" in err
    assert os.listdir(tmp_path) == []


# ---------------------------------------------------------------------------------- Slicer node

class _Recorded:
    """Stand-in for Slicer's validator classes (not in any installed package): records args."""

    def __init__(self, *args):
        self.args = args


def _parameter_node_class():
    """Execute BoneWatertight.py's parameter-node class definition and the helpers that build
    it from the schema, as the module does, minus @parameterNodeWrapper (Slicer only)."""
    import slicer

    tree = ast.parse(MODULE_PY.read_text(encoding="utf-8"))
    wanted = {"libraryParameterAnnotation", "withLibraryParameters"}
    body, classdef = [], None
    for node in tree.body:
        if isinstance(node, ast.FunctionDef) and node.name in wanted:
            body.append(node)
        elif isinstance(node, ast.ClassDef) and node.name == "BoneWatertightParameterNode":
            classdef = node
    assert classdef is not None and len(body) == 2
    decorators = [d.id for d in classdef.decorator_list if isinstance(d, ast.Name)]
    # the schema fields must be added before parameterNodeWrapper reads the class
    assert decorators == ["parameterNodeWrapper", "withLibraryParameters"], decorators
    classdef.decorator_list = classdef.decorator_list[1:]
    body.append(classdef)
    namespace = {"Annotated": typing.Annotated, "Optional": typing.Optional, "SCHEMA": SCHEMA,
                 "WithinRange": _Recorded, "Choice": _Recorded,
                 "vtkMRMLScalarVolumeNode": slicer.vtkMRMLScalarVolumeNode,
                 "vtkMRMLSegmentationNode": slicer.vtkMRMLSegmentationNode,
                 "vtkMRMLModelNode": slicer.vtkMRMLModelNode}
    exec(compile(ast.Module(body=body, type_ignores=[]), str(MODULE_PY), "exec", dont_inherit=True),
         namespace)
    return namespace["BoneWatertightParameterNode"], namespace


def test_parameter_node_fields_match_the_schema():
    cls, namespace = _parameter_node_class()
    hints = typing.get_type_hints(cls, include_extras=True)  # what parameterNodeWrapper reads
    for spec in SCHEMA.values():
        if spec.panel is None:
            assert spec.name not in hints
            continue
        hint = hints[spec.name]
        assert getattr(cls, spec.name) == spec.to_panel(spec.default), spec.name
        if spec.kind is bool:
            assert hint is bool
            continue
        assert typing.get_origin(hint) is typing.Annotated
        base, *extras = typing.get_args(hint)
        assert base is spec.kind, spec.name
        ranges = [e.args for e in extras if isinstance(e, _Recorded)]
        if spec.choices:
            assert ranges == [(list(spec.choices),)]
        else:
            low = min(spec.sentinel, spec.minimum) if spec.allows_auto else spec.minimum
            assert ranges == [(low, spec.maximum)], spec.name
    # the module's conversion back to library values comes from the schema as well
    assert "spec.from_panel(" in MODULE_PY.read_text(encoding="utf-8")
    for name in ("inputVolume", "inputSegmentation", "segmentIds", "segmentId", "neighbours",
                 "outputModel", "addAsSegment", "showIntermediates", "colorByDistance"):
        assert name in hints
    assert "preset" not in hints


def test_module_has_no_literal_range_or_default_of_a_schema_parameter():
    """No WithinRange(...) with literal bounds and no schema parameter assigned a literal in
    the module: a second declaration would drift."""
    tree = ast.parse(MODULE_PY.read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "WithinRange":
            assert not any(isinstance(a, ast.Constant) for a in node.args), ast.unparse(node)
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            assert node.target.id not in SCHEMA, f"{node.target.id} declared again in the module"


# ---------------------------------------------------------------------------------- .ui

def _ui():
    tree = ET.parse(UI_FILE)
    parents = {c: p for p in tree.iter() for c in p}
    return tree, parents


def _section_of(elem, parents):
    while elem in parents:
        elem = parents[elem]
        if elem.tag == "widget" and elem.get("class") == "ctkCollapsibleButton":
            return next(p.findtext("string") for p in elem.findall("property")
                        if p.get("name") == "text")
    return None


def test_ui_has_one_bare_widget_per_panel_parameter():
    tree, parents = _ui()
    bound = {}
    for w in tree.iter("widget"):
        for prop in w.findall("property"):
            if prop.get("name") == "SlicerParameterName":
                bound.setdefault(prop.findtext("string"), []).append(w)
    by_name = {w.get("name"): w for w in tree.iter("widget")}
    for spec in PANEL:
        assert len(bound.get(spec.name, [])) == 1, f"{spec.name}: one widget expected"
        w = bound[spec.name][0]
        assert w.get("class") == WIDGET_CLASS[spec.kind], spec.name
        assert _section_of(w, parents) == spec.panel, spec.name
        owned = {p.get("name") for p in w.findall("property")} & SCHEMA_OWNED
        assert not owned, f"{w.get('name')} repeats {sorted(owned)} of the schema"
        if spec.kind is not bool:
            label = by_name.get("label_" + w.get("name"))
            assert label is not None and label.get("class") == "QLabel", spec.name
            assert not [p for p in label.findall("property") if p.get("name") == "text"]
    non_panel = [s.name for s in SCHEMA.values() if s.panel is None]
    assert not set(non_panel) & set(bound)


def test_module_applies_the_schema_to_the_widgets():
    """setup() sets bounds, steps, units, labels and tooltips from the schema."""
    source = MODULE_PY.read_text(encoding="utf-8")
    tree = ast.parse(source)
    method = next(n for n in ast.walk(tree)
                  if isinstance(n, ast.FunctionDef) and n.name == "applySchemaToWidgets")
    text = ast.unparse(method)
    for piece in ("SCHEMA.get", "spec.describe()", "spec.panel_range()", "widget.minimum",
                  "widget.maximum", "setRange", "widget.toolTip", "widget.suffix",
                  "specialValueText", "label.text = spec.label"):
        assert piece in text, piece
    setup = next(n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and n.name == "setup")
    assert "self.applySchemaToWidgets(uiWidget)" in ast.unparse(setup)


# ---------------------------------------------------------------------------------- batch script

def test_slicer_batch_script_options_match_the_schema():
    spec_ = importlib.util.spec_from_file_location("bonewatertight_batch", BATCH_SCRIPT)
    module = importlib.util.module_from_spec(spec_)
    spec_.loader.exec_module(module)  # imports slicer (slicer-core) but runs nothing
    parser = module.build_parser()
    theirs, ours = _actions(parser), _actions(cli.build_parser())
    assert list(theirs) == list(SCHEMA)
    for name in SCHEMA:
        a, b = theirs[name], ours[name]
        assert (a.option_strings, a.help, a.choices, a.default) == \
            (b.option_strings, b.help, b.choices, b.default), name
    flags = {s for a in parser._actions for s in a.option_strings}
    for flag in ("--ct", "--seg", "--label", "--out", "--ras", "--report",
                 "--picture", "--self-test"):
        assert flag in flags
    with pytest.raises(InputError, match="edge_level must be between 0.3 and 0.9"):
        options.parameters_from_args(parser.parse_args(["--edge-level", "5"]))


# ---------------------------------------------------------------------------------- presets

def test_presets_are_refused_with_the_reason_everywhere():
    """The presets were removed (each equalled the defaults): the command line and the Slicer
    batch script refuse --preset saying why, the logic refuses preset=, the panel has no
    preset selector."""
    spec_ = importlib.util.spec_from_file_location("bonewatertight_batch", BATCH_SCRIPT)
    module = importlib.util.module_from_spec(spec_)
    spec_.loader.exec_module(module)
    for parser in (cli.build_parser(), module.build_parser()):
        with pytest.raises(InputError, match="presets were removed") as err:
            parser.parse_args(["--preset", "femur"])
        assert PRESETS_REMOVED in str(err.value)
        assert "--preset" not in parser.format_help()
    source = MODULE_PY.read_text(encoding="utf-8")
    assert "PRESETS_REMOVED" in source and "presetComboBox" not in source
    assert "presetComboBox" not in UI_FILE.read_text(encoding="utf-8")
    import BoneWatertightLib
    from BoneWatertightLib import params

    assert not hasattr(BoneWatertightLib, "preset") and not hasattr(params, "PRESETS")
