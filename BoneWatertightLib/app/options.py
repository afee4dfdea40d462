"""Command-line options shared by every command line, derived from the parameter schema.

``bonewatertight`` (:mod:`.cli`), its ``--cases`` batch and the Slicer batch script
(``Resources/Scripts/bonewatertight_batch.py``) build their parsers from these functions, so
their flag names, help texts, ranges and defaults are the same by construction.
"""

from __future__ import annotations

import argparse

from ..errors import InputError
from ..params import PARAMETER_GROUPS, PRESETS_REMOVED, SCHEMA, ParamSpec, Parameters

PARAM_DEST_PREFIX = "param_"


class Parser(argparse.ArgumentParser):
    """argparse that reports a usage error as InputError (one line, exit code 2)."""

    def error(self, message):
        raise InputError(f"{message} (see --help)")


def flag_of(spec: ParamSpec) -> str:
    """``--poisson-depth`` for poisson_depth."""
    return "--" + spec.name.replace("_", "-")


def help_of(spec: ParamSpec) -> str:
    """The option's help: the schema's text with range, unit, auto meaning and default."""
    return spec.describe().replace("%", "%%")


def _parser_for(spec: ParamSpec):
    def parse(text):
        return spec.parse(text)
    parse.__name__ = spec.kind.__name__  # argparse: "invalid int value: 'many'"
    return parse


def add_parameter_options(parser: argparse.ArgumentParser) -> None:
    """One option per schema parameter (``--h0``, ``--poisson-depth``, ``--no-refine-edges``...),
    grouped by pipeline stage. Options left out keep the default value, so
    their default is SUPPRESS; values are checked by :meth:`Parameters.validate`."""
    groups = {}
    for spec in SCHEMA.values():
        if spec.stage not in groups:
            groups[spec.stage] = parser.add_argument_group(
                f"parameters: {PARAMETER_GROUPS[spec.stage]}")
        group = groups[spec.stage]
        dest = PARAM_DEST_PREFIX + spec.name
        if spec.kind is bool:
            group.add_argument(flag_of(spec), dest=dest, action=argparse.BooleanOptionalAction,
                               default=argparse.SUPPRESS, help=help_of(spec))
        elif spec.choices:
            group.add_argument(flag_of(spec), dest=dest, choices=spec.choices,
                               default=argparse.SUPPRESS, help=help_of(spec))
        else:
            metavar = spec.kind.__name__.upper() + ("|auto" if spec.allows_auto else "")
            group.add_argument(flag_of(spec), dest=dest, type=_parser_for(spec),
                               metavar=metavar, default=argparse.SUPPRESS, help=help_of(spec))


def add_io_options(parser: argparse.ArgumentParser) -> None:
    """Inputs and outputs of one run (``--ct --seg --label --out --ras --report --picture``...)."""
    io_group = parser.add_argument_group("inputs and outputs")
    io_group.add_argument("--ct", metavar="CT",
                          help="CT volume in HU: NRRD, NIfTI, MHA/MHD, ... or a DICOM folder.")
    io_group.add_argument("--ct-series", metavar="UID",
                          help="Series instance UID to read when the DICOM folder holds several.")
    io_group.add_argument("--seg", metavar="SEG",
                          help="Rough segment: a label map (any geometry) or a 3D Slicer "
                               ".seg.nrrd.")
    io_group.add_argument("--label", action="append", metavar="LABEL",
                          help="Label value or segment name/ID. Repeat for several bones: one "
                               "surface each, OUT must then contain {label}.")
    io_group.add_argument("--out", metavar="OUT",
                          help="Output surface: .stl, .ply, .vtp, .vtk or .obj. {label} is "
                               "replaced by the segment name (and {case} in a batch).")
    io_group.add_argument("--ras", action="store_true",
                          help="Write RAS coordinates (as 3D Slicer) instead of LPS (as ITK). "
                               "The file header says which.")
    io_group.add_argument("--report", metavar="JSON",
                          help="Write a JSON report: checks, timings, distances, parameters.")
    io_group.add_argument("--save-intermediates", metavar="DIR",
                          help="Write intermediate results (threshold points as .ply, visible "
                               "points, M0 as .vtp) into DIR.")
    io_group.add_argument("--picture", metavar="PNG",
                          help="Render a PNG picture of the result. With several bones, one "
                               "picture each: PNG's {label} is replaced by the segment name, or "
                               "without {label} _<name> is added before .png.")
    io_group.add_argument("--all-labels", action="store_true",
                          help="Reconstruct every label of --seg (together; OUT needs {label}).")
    io_group.add_argument("--neighbours", default="auto", metavar="auto|none|LABEL,...",
                          help="Which other labels of --seg compete as neighbours at the joints "
                               "(no surface enters a neighbour): every other label (auto, the "
                               "default), none, or a comma-separated list of labels.")


class _Removed(argparse.Action):
    """An option that no longer exists (hidden): using it is a usage error that says why."""

    def __init__(self, option_strings, dest, reason: str, **kwargs):
        super().__init__(option_strings, dest, help=argparse.SUPPRESS, **kwargs)
        self.reason = reason

    def __call__(self, parser, namespace, values, option_string=None):
        parser.error(f"{option_string}: {self.reason}")


def add_removed_options(parser: argparse.ArgumentParser) -> None:
    """``--preset``: refused with the reason rather than as an unknown option."""
    parser.add_argument("--preset", action=_Removed, reason=PRESETS_REMOVED)


def parameter_overrides(args: argparse.Namespace) -> dict:
    """The parameters given on the command line ({name: value})."""
    return {k[len(PARAM_DEST_PREFIX):]: v for k, v in vars(args).items()
            if k.startswith(PARAM_DEST_PREFIX)}


def make_parameters(overrides: dict) -> Parameters:
    """Validated Parameters: the defaults with the overrides."""
    return Parameters().replace(**overrides).validate()


def parameters_from_args(args: argparse.Namespace) -> Parameters:
    """Validated Parameters from parsed arguments (the parameter options and
    ``--save-intermediates``)."""
    overrides = parameter_overrides(args)
    if getattr(args, "save_intermediates", None):
        overrides["keep_intermediates"] = True
    return make_parameters(overrides)
