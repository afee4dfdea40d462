"""Command line: ``python -m BoneWatertightLib --ct CT --seg SEG --label LABEL --out OUT``.

Exit codes: 0 success; 1 unexpected internal error; 2 bad input or usage (message says what to
change); 3 reconstruction failed (or, in a batch, at least one case failed); 4 a dependency or
optional feature is missing; 130 cancelled (Ctrl-C). Errors are one line ``error: <message>``
on stderr. An output file is either complete or not written at all.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import json
import math
import os
import sys
import time
import typing
from typing import Optional

import numpy as np

from . import io as bwio
from .errors import (BoneWatertightError, CancelledError, DependencyError, InputError)
from .params import PRESETS, Parameters, preset

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_INPUT = 2
EXIT_FAILED = 3
EXIT_DEPENDENCY = 4
EXIT_CANCELLED = 130

PROG = "python -m BoneWatertightLib"


def exit_code_for(exc: BaseException) -> int:
    """The documented exit code of an exception raised while processing a case."""
    if isinstance(exc, (CancelledError, KeyboardInterrupt)):
        return EXIT_CANCELLED
    if isinstance(exc, DependencyError):
        return EXIT_DEPENDENCY
    if isinstance(exc, InputError):
        return EXIT_INPUT
    if isinstance(exc, BoneWatertightError):
        return EXIT_FAILED
    return EXIT_INTERNAL


def one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text


# ----------------------------------------------------------------------------------------
# parameters as options

def _field_docs() -> dict:
    """Parameter name -> its attribute docstring in params.py (used as --help text)."""
    try:
        from . import params as params_module

        tree = ast.parse(inspect.getsource(params_module))
    except (OSError, TypeError, SyntaxError):
        return {}
    docs = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ClassDef) and node.name == "Parameters":
            body = node.body
            for stmt, nxt in zip(body, body[1:] + [None]):
                if (isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name)
                        and isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant)
                        and isinstance(nxt.value.value, str)):
                    docs[stmt.target.id] = " ".join(nxt.value.value.split())
    return docs


def _optional_number(kind):
    def parse(text):
        if str(text).lower() in ("auto", "none"):
            return None
        return kind(text)
    parse.__name__ = f"{kind.__name__} or 'auto'"
    return parse


def add_parameter_options(parser: argparse.ArgumentParser) -> None:
    """One option per field of :class:`Parameters` (``--poisson-depth``, ``--h0``, ...).

    Options left out keep the preset's (or the paper's) value, so their default is SUPPRESS.
    """
    group = parser.add_argument_group(
        "pipeline parameters (defaults: the paper's, or the --preset's)")
    hints = typing.get_type_hints(Parameters)
    docs = _field_docs()
    defaults = Parameters()
    for f in dataclasses.fields(Parameters):
        flag = "--" + f.name.replace("_", "-")
        kind = hints[f.name]
        args = typing.get_args(kind)
        default = getattr(defaults, f.name)
        helptext = docs.get(f.name, "")
        shown = "auto" if default is None else default
        helptext = (helptext + " " if helptext else "") + f"[paper default: {shown}]"
        helptext = helptext.replace("%", "%%")
        dest = "param_" + f.name
        if kind is bool:
            group.add_argument(flag, dest=dest, action=argparse.BooleanOptionalAction,
                               default=argparse.SUPPRESS, help=helptext)
        elif type(None) in args:
            inner = next(a for a in args if a is not type(None))
            group.add_argument(flag, dest=dest, type=_optional_number(inner), metavar="X|auto",
                               default=argparse.SUPPRESS, help=helptext)
        else:
            group.add_argument(flag, dest=dest, type=kind, metavar=kind.__name__.upper(),
                               default=argparse.SUPPRESS, help=helptext)


def parameters_from_args(args: argparse.Namespace) -> Parameters:
    overrides = {k[len("param_"):]: v for k, v in vars(args).items() if k.startswith("param_")}
    if getattr(args, "save_intermediates", None):
        overrides["keep_intermediates"] = True
    if getattr(args, "preset", None):
        params = preset(args.preset, **overrides)
    else:
        params = Parameters().replace(**overrides)
    return params.validate()


# ----------------------------------------------------------------------------------------
# argument parser

class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error as one line and exit code 2."""

    def error(self, message):
        raise InputError(f"{message} (see --help)")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog=PROG,
        description=(
            "Reconstruct a watertight 2-manifold surface of one bone from a CT and a rough\n"
            "segment of that bone, by the method of \"Watertight 2-manifold 3D bone surface\n"
            "model reconstruction from CT images based on visual hyper-spherical mapping\"."),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=_EPILOG,
    )
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
    io_group.add_argument("--picture", metavar="PNG", help="Render a PNG picture of the result.")
    parser.add_argument("--preset", choices=sorted(PRESETS),
                        help="Parameter preset; single options below override it.")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="Print nothing but errors.")
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="Print each stage; tracebacks on internal errors.")
    batch = parser.add_argument_group("batch (many cases)")
    batch.add_argument("--cases", metavar="CSV|DIR",
                       help="Run many cases: a CSV (columns ct,seg,label,out[,preset]) or a "
                            "folder of case folders (see below).")
    batch.add_argument("--workers", type=int, default=1, metavar="N",
                       help="Worker processes for --cases (default 1).")
    batch.add_argument("--summary", metavar="CSV|MD",
                       help="Write the batch summary table (.csv, or .md for markdown).")
    batch.add_argument("--dask", metavar="SCHEDULER",
                       help="Run the batch on a dask.distributed cluster at this scheduler "
                            "address (pip install \"dask[distributed]\").")
    add_parameter_options(parser)
    return parser


_EPILOG = """\
coordinates:
  Surfaces are written in physical LPS coordinates (as ITK, SimpleITK) unless --ras is given.
  The file says which: STL header and PLY/OBJ comment "SPACE=LPS" or "SPACE=RAS", VTP/VTK
  field data "SPACE" (the convention 3D Slicer reads).

batch folder layout (--cases DIR):
  DIR/<case>/ct.nrrd | ct.nii.gz | ct.nii | ct.mha | ct.mhd | ct/ (DICOM folder)
  DIR/<case>/<name>.seg.nrrd      (a 3D Slicer segmentation; preferred when present)
          or seg.* | labels.* | *_labels.* | mask.*   (a label map; labels.csv value,name
                                                      beside it allows segment names)
  Give --label (repeatable) and --out as a template with {case} and {label}, e.g.
  --out results/{case}_{label}.stl. A CSV (--cases cases.csv) instead lists one surface per
  row: ct,seg,label,out[,preset]; relative paths are relative to the CSV's folder.

exit codes:
  0 success, 2 bad input, 3 reconstruction failed (batch: some case failed),
  4 missing dependency or feature, 130 cancelled, 1 internal error.

example:
  python -m BoneWatertightLib --ct ct.nrrd --seg bones.seg.nrrd --label femur_left \\
      --preset femur --out femur_left.stl --report femur_left.json
"""


# ----------------------------------------------------------------------------------------
# progress

class ProgressBar:
    """A one-line progress bar on a terminal (\\r updates on stderr); silent otherwise."""

    def __init__(self, stream=None, enabled: Optional[bool] = None, prefix: str = "",
                 verbose: bool = False):
        self.stream = stream or sys.stderr
        self.enabled = (self.stream.isatty() if enabled is None else enabled)
        self.verbose = verbose
        self.prefix = prefix
        self._last = -1.0
        self._last_message = None
        self._shown = False

    def __call__(self, fraction: float, message: str = "") -> None:
        if self.verbose and message and message != self._last_message:
            if self._shown:
                self._clear()
            self.stream.write(f"[{100 * fraction:5.1f}%] {self.prefix}{message}\n")
            self.stream.flush()
        self._last_message = message
        if not self.enabled:
            return
        now = time.monotonic()
        if fraction < 1.0 and now - self._last < 0.1:
            return
        self._last = now
        width = 30
        filled = int(round(width * min(max(fraction, 0.0), 1.0)))
        bar = "#" * filled + "." * (width - filled)
        text = f"\r{self.prefix}[{bar}] {100 * fraction:3.0f}% {message}"
        self.stream.write(text[:120].ljust(120))
        self.stream.flush()
        self._shown = True

    def _clear(self):
        self.stream.write("\r" + " " * 120 + "\r")
        self.stream.flush()
        self._shown = False

    def close(self):
        if self._shown:
            self._clear()


# ----------------------------------------------------------------------------------------
# one surface

def render_function():
    """The picture renderer (BoneWatertightLib.render.render_surface), or raise DependencyError."""
    try:
        from . import render
    except ImportError as exc:
        raise DependencyError(
            f"--picture is not available: BoneWatertightLib.render cannot be imported ({exc})."
        ) from None
    func = getattr(render, "render_surface", None)
    if func is None:
        raise DependencyError("--picture is not available: BoneWatertightLib.render has no "
                              "render_surface(surface, path, ...) function.")
    return func


def load_reconstruct():
    try:
        from .pipeline import reconstruct
    except ImportError as exc:
        if isinstance(exc, DependencyError):
            raise
        raise DependencyError(f"The reconstruction pipeline cannot be imported: {exc}") from exc
    return reconstruct


def distance_summary(distances) -> dict:
    d = np.asarray(distances if distances is not None else [], dtype=np.float64).ravel()
    d = d[np.isfinite(d)]
    if d.size == 0:
        return {"n": 0}
    return {"n": int(d.size), "mean": float(d.mean()), "median": float(np.median(d)),
            "rms": float(np.sqrt(np.mean(d * d))), "p95": float(np.percentile(d, 95)),
            "max": float(d.max())}


def _checks_of(result) -> dict:
    checks = result.report.get("checks") if isinstance(result.report, dict) else None
    if isinstance(checks, dict) and "ok" in checks:
        return checks
    if isinstance(checks, dict) and isinstance(checks.get("final"), dict):
        return checks["final"]
    from .checks import check_surface

    return check_surface(result.surface.vertices, result.surface.faces).to_dict()


def _stage_times(report: dict):
    for key in ("timings", "times", "stage_times", "seconds"):
        if isinstance(report.get(key), dict):
            return report[key]
    return None


def _safe_name(text: str) -> str:
    keep = "".join(c if (c.isalnum() or c in "-_.") else "_" for c in str(text))
    return keep.strip("._") or "segment"


def fill_template(template: str, label: str, case: Optional[str] = None) -> str:
    out = template.replace("{label}", _safe_name(label))
    if case is not None:
        out = out.replace("{case}", _safe_name(case))
    return out


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if dataclasses.is_dataclass(value):
        return dataclasses.asdict(value)
    if hasattr(value, "to_dict"):
        return value.to_dict()
    return str(value)


def _finite(obj):
    """JSON has no NaN/inf: replace them by None so every JSON reader accepts the report."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def to_json(obj) -> str:
    plain = json.loads(json.dumps(obj, default=_json_default, allow_nan=True))
    return json.dumps(_finite(plain), indent=2, allow_nan=False) + "\n"


def reconstruct_and_write(ct, mask, segment_name: str, out: str, params: Parameters, *,
                          coordinate_system: str = "LPS", intermediates_dir: Optional[str] = None,
                          picture: Optional[str] = None, progress=None,
                          inputs: Optional[dict] = None, reconstruct=None) -> dict:
    """Run the pipeline on one segment and write its outputs. Returns the report dict.

    Outputs are written only after the reconstruction succeeded, each one atomically; the
    picture is rendered before the surface file so a rendering failure writes nothing.
    """
    reconstruct = reconstruct or load_reconstruct()
    t0 = time.perf_counter()
    result = reconstruct(ct, mask, params, progress)
    t_reconstruct = time.perf_counter() - t0
    surface = result.surface
    checks = _checks_of(result)

    t1 = time.perf_counter()
    for path in (out, picture):
        if path:
            os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    if picture:
        render = render_function()
        with bwio.atomic_path(picture) as tmp:
            render(surface, tmp, ct=ct, title=segment_name)
    written_intermediates = []
    if intermediates_dir and result.intermediates:
        written_intermediates = write_intermediates(result.intermediates, intermediates_dir,
                                                    segment_name, coordinate_system)
    bwio.write_surface(surface, out, coordinate_system)
    t_write = time.perf_counter() - t1

    report = {
        "tool": "BoneWatertight",
        "inputs": dict(inputs or {}, segment_name=segment_name),
        "output": {"path": os.path.abspath(out), "format": os.path.splitext(out)[1].lower(),
                   "coordinate_system": coordinate_system,
                   "n_vertices": int(surface.n_vertices), "n_faces": int(surface.n_faces),
                   "picture": os.path.abspath(picture) if picture else None,
                   "intermediates": written_intermediates},
        "coordinate_system": coordinate_system,
        "checks": checks,
        "distance_to_constraints_mm": distance_summary(result.distance_to_constraints),
        "parameters": params.to_dict(),
        "timings_s": {"reconstruct": t_reconstruct, "write": t_write,
                      "stages": _stage_times(result.report) if isinstance(result.report, dict)
                      else None},
        "pipeline": result.report,
    }
    return report


def write_intermediates(intermediates: dict, folder: str, segment_name: str,
                        coordinate_system: str) -> list:
    """Points as .ply, surfaces as .vtp, images as .nrrd; returns the files written."""
    import SimpleITK as sitk

    from .mesh import Surface

    os.makedirs(folder, exist_ok=True)
    written = []
    prefix = _safe_name(segment_name)
    for name, value in intermediates.items():
        base = os.path.join(folder, f"{prefix}_{_safe_name(name)}")
        if isinstance(value, Surface):
            path = base + ".vtp"
            bwio.write_surface(value, path, coordinate_system)
        elif isinstance(value, np.ndarray) and value.ndim == 2 and value.shape[1] == 3:
            path = base + ".ply"
            bwio.write_points(value, path, coordinate_system)
        elif isinstance(value, sitk.Image):
            path = base + ".nrrd"
            with bwio.atomic_path(path) as tmp:
                sitk.WriteImage(value, tmp, True)
        else:
            continue
        written.append(os.path.abspath(path))
    return written


def summary_line(report: dict, seconds: float) -> str:
    out = report["output"]
    checks = report.get("checks") or {}
    if checks.get("ok"):
        genus = checks.get("genus")
        state = ("checks passed (closed, manifold, "
                 f"{checks.get('n_components', 1)} component"
                 + ("" if genus is None else f", genus {genus}") + ")")
    else:
        state = "CHECKS FAILED: " + "; ".join(map(str, checks.get("problems", [])))
    dist = report.get("distance_to_constraints_mm", {})
    dist_text = f", distance to constraints mean {dist['mean']:.2f} mm" if dist.get("n") else ""
    return (f"{report['inputs'].get('segment_name')}: {out['n_vertices']} vertices, "
            f"{out['n_faces']} faces, {state}{dist_text}, {seconds:.1f} s -> {out['path']} "
            f"({out['coordinate_system']})")


# ----------------------------------------------------------------------------------------
# main

def main(argv=None) -> int:
    parser = build_parser()
    args = None
    try:
        args = parser.parse_args(argv)
        if args.quiet and args.verbose:
            parser.error("--quiet and --verbose exclude each other")
        if args.cases:
            from . import batch

            return batch.run_from_args(args, parser)
        return _run_single(args, parser)
    except SystemExit as exc:  # --help
        return exc.code if isinstance(exc.code, int) else EXIT_OK
    except KeyboardInterrupt:
        sys.stderr.write("\nerror: cancelled by the user; no output file was written.\n")
        return EXIT_CANCELLED
    except Exception as exc:  # one line for the user; the traceback only on request
        code = exit_code_for(exc)
        if code == EXIT_INTERNAL and args is not None and args.verbose:
            import traceback

            traceback.print_exc()
        internal = code == EXIT_INTERNAL and not isinstance(exc, OSError)
        prefix = "internal error: " if internal else ""
        sys.stderr.write(f"error: {prefix}{one_line(exc)}\n")
        return code


def check_single_args(args, parser) -> None:
    missing = [flag for flag, value in (("--ct", args.ct), ("--seg", args.seg),
                                        ("--label", args.label), ("--out", args.out)) if not value]
    if missing:
        parser.error("missing " + ", ".join(missing))
    if len(args.label) > 1 and "{label}" not in args.out:
        parser.error(f"{len(args.label)} labels given but --out has no {{label}} placeholder; "
                     "use e.g. --out bone_{label}.stl")
    if len(set(args.label)) != len(args.label):
        parser.error("the same --label is given twice")
    for path in [args.out] + ([args.report] if args.report else []):
        if "{case}" in path:
            parser.error("{case} is only available with --cases")
    ext = bwio._extension(args.out)
    if ext not in bwio.SURFACE_EXTENSIONS:
        parser.error(f"--out must end in one of {', '.join(bwio.SURFACE_EXTENSIONS)}, "
                     f"not '{ext or args.out}'")
    if args.report and not args.report.lower().endswith(".json"):
        parser.error("--report must be a .json file")
    if args.picture and not args.picture.lower().endswith(".png"):
        parser.error("--picture must be a .png file")


def _run_single(args, parser) -> int:
    check_single_args(args, parser)
    params = parameters_from_args(args)
    if args.picture:
        render_function()  # fail before the long run, not after it
    reconstruct = load_reconstruct()
    system = "RAS" if args.ras else "LPS"

    t0 = time.perf_counter()
    ct = bwio.read_ct(args.ct, args.ct_series)
    segments = [bwio.read_segment(args.seg, label) for label in args.label]
    t_read = time.perf_counter() - t0

    outputs = [fill_template(args.out, name) for _, name in segments]
    if len(set(outputs)) != len(outputs):
        raise InputError("Two labels give the same output file name; use distinct labels.")

    reports, codes = [], []
    for (mask, name), label, out in zip(segments, args.label, outputs):
        bar = ProgressBar(enabled=None if not args.quiet else False,
                          prefix=f"{name}: " if len(segments) > 1 else "",
                          verbose=args.verbose)
        t_case = time.perf_counter()
        inputs = {"ct": os.path.abspath(args.ct), "seg": os.path.abspath(args.seg),
                  "label": label, "ct_size": list(ct.GetSize()),
                  "ct_spacing": list(ct.GetSpacing()), "preset": args.preset,
                  "read_seconds": t_read}
        picture = fill_template(args.picture, name) if args.picture else None
        if picture and len(segments) > 1 and "{label}" not in args.picture:
            picture = os.path.splitext(picture)[0] + f"_{_safe_name(name)}.png"
        try:
            report = reconstruct_and_write(
                ct, mask, name, out, params, coordinate_system=system,
                intermediates_dir=args.save_intermediates, picture=picture, progress=bar,
                inputs=inputs, reconstruct=reconstruct)
        except (CancelledError, KeyboardInterrupt):
            bar.close()
            raise KeyboardInterrupt from None
        except Exception as exc:
            bar.close()
            code = exit_code_for(exc)
            if code == EXIT_INTERNAL:
                raise
            sys.stderr.write(f"error: {name}: {one_line(exc)}\n")
            codes.append(code)
            continue
        bar.close()
        seconds = time.perf_counter() - t_case
        report["timings_s"]["total"] = seconds
        reports.append(report)
        codes.append(EXIT_OK)
        if not args.quiet:
            print(summary_line(report, seconds), flush=True)

    if args.report and reports:
        _write_reports(args.report, reports)
    return max(codes, key=lambda c: (c != 0, c == EXIT_INPUT, c)) if codes else EXIT_OK


def _write_reports(template: str, reports: list) -> None:
    if "{label}" in template:
        for report in reports:
            bwio.write_text(to_json(report),
                            _ensure_folder(fill_template(template,
                                                         report["inputs"]["segment_name"])))
    elif len(reports) == 1:
        bwio.write_text(to_json(reports[0]), _ensure_folder(template))
    else:
        bwio.write_text(to_json({"tool": "BoneWatertight", "surfaces": reports}),
                        _ensure_folder(template))


def _ensure_folder(path: str) -> str:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    return path
