"""Command line: ``bonewatertight`` (or ``python -m BoneWatertightLib``) ``--ct CT --seg SEG
--label LABEL --out OUT``.

This module only parses the arguments and shows progress; the work is done by the run service
(:mod:`.run`) and, for ``--cases``, the batch runner (:mod:`.batch`). Exit codes are those of
:mod:`BoneWatertightLib.errors`: 0 success, 2 bad input or usage (the message says what to
change), 3 reconstruction failed (batch: some case failed), 4 missing dependency, 5 an output
could not be written (or another OS error), 6 partly done (of several bones, those that passed
are written, the others failed), 130 cancelled (Ctrl-C, SIGTERM or SIGHUP), 1
internal error. Errors are one line ``error: <message>`` on stderr. The files of a run (surfaces,
report, picture, intermediates) appear together, complete, or not at all.

For a program that runs the command (3D Slicer's panel through
:class:`BoneWatertightLib.app.child.ChildRun`), ``--progress-lines`` prints machine-readable
lines on stdout, each flushed at once: ``PROGRESS <fraction> <message>`` for every progress
step (fraction 0 to 1, six decimals, non-decreasing; the message on one line) and, for every
error, ``ERROR <json>`` with ``type`` (the exception's class name), ``message`` (its full text),
``segment`` (the bone it concerns, or null) and ``code`` (the exit code), beside the usual
``error:`` line on stderr.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Optional

from ..errors import (EXIT_CANCELLED, EXIT_INTERNAL, EXIT_OK, CancelledBySignal, CancelledError,
                      InputError, exit_code_for, joint_exit_code, one_line)
from ..io import files as bwfiles
from ..io import images, segmentations
from ..report import case_summary_line, pair_summary_line
from . import run
from .options import (Parser, add_io_options, add_parameter_options, add_removed_options,
                      parameters_from_args)

PROG = "bonewatertight"


# ----------------------------------------------------------------------------------------
# argument parser

def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog=PROG,
        description=(
            "Reconstruct a watertight 2-manifold surface of one bone from a CT and a rough\n"
            "segment of that bone, by the method of \"Watertight 2-manifold 3D bone surface\n"
            "model reconstruction from CT images based on visual hyper-spherical mapping\"."),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=_EPILOG,
    )
    add_io_options(parser)
    add_removed_options(parser)
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="Print nothing but errors.")
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="Print each stage; tracebacks on internal errors.")
    parser.add_argument("--progress-lines", action="store_true",
                        help="For a program running this command: print 'PROGRESS <fraction> "
                             "<message>' on stdout at every progress step and 'ERROR <json>' "
                             "(type, message, segment, code) for every error, each line "
                             "flushed at once.")
    batch = parser.add_argument_group("batch (many cases)")
    batch.add_argument("--cases", metavar="CSV|DIR",
                       help="Run many cases: a CSV (columns ct,seg,label,out[,case]) or a "
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
  row: ct,seg,label,out[,case]; relative paths are relative to the CSV's folder.

exit codes:
  0 success, 2 bad input, 3 reconstruction failed (batch: some case failed),
  4 missing dependency, 5 an output could not be written (or another OS error),
  6 partly done (several bones: those that passed are written, the others failed),
  130 cancelled (Ctrl-C, SIGTERM, SIGHUP), 1 internal error.

outputs:
  The files of one run (surfaces, report, picture, intermediates) are written as temporary
  files beside their destinations and renamed together at the end: they appear complete and
  together, or not at all (a failure or cancellation leaves earlier files as they were).
  {label} and {case} become the segment's and case's names, one-to-one: characters other
  than letters, digits, '-', '_' and '.' are written as %XX (e.g. "femur left" ->
  femur%20left, "." -> %2E).

example:
  bonewatertight --ct ct.nrrd --seg bones.seg.nrrd --label femur_left \\
      --out femur_left.stl --report femur_left.json
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


PROGRESS_PREFIX = "PROGRESS "
ERROR_PREFIX = "ERROR "


class ProgressLines:
    """``--progress-lines``: one ``PROGRESS <fraction> <message>`` line per progress callback
    on ``stream`` (stdout), flushed at once, then the wrapped callback (the terminal bar),
    whose answer is returned (False still cancels). Fractions never go back: a smaller one is
    printed as the largest so far."""

    def __init__(self, stream=None, then=None):
        self.stream = stream or sys.stdout
        self.then = then
        self.highest = 0.0

    def __call__(self, fraction: float, message: str = ""):
        self.highest = max(self.highest, min(max(float(fraction), 0.0), 1.0))
        text = " ".join(str(message or "").split())
        self.stream.write(f"{PROGRESS_PREFIX}{self.highest:.6f} {text}\n")
        self.stream.flush()
        if self.then is not None:
            return self.then(fraction, message)
        return None

    def close(self):
        if self.then is not None and hasattr(self.then, "close"):
            self.then.close()


def error_line(exc: BaseException, code: int, segment: Optional[str] = None) -> str:
    """The ``ERROR <json>`` line of ``--progress-lines`` for an exception."""
    name = "CancelledError" if isinstance(exc, KeyboardInterrupt) else type(exc).__name__
    message = str(exc) if not isinstance(exc, KeyboardInterrupt) else (
        f"Cancelled ({exc.name}); nothing was written." if isinstance(exc, CancelledBySignal)
        else "Cancelled by the user; nothing was changed.")
    return ERROR_PREFIX + json.dumps({"type": name, "message": message, "segment": segment,
                                      "code": int(code)}, ensure_ascii=True)


def _print_error_line(args, exc: BaseException, code: int, segment: Optional[str] = None) -> None:
    if args is not None and getattr(args, "progress_lines", False):
        try:
            sys.stdout.write(error_line(exc, code, segment) + "\n")
            sys.stdout.flush()
        except (OSError, ValueError):  # the reader went away: the error line on stderr stays
            pass


# ----------------------------------------------------------------------------------------
# main

def main(argv=None) -> int:
    """Run the command line with ``argv`` (default ``sys.argv[1:]``); return the exit code.

    SIGINT, SIGTERM and SIGHUP cancel the run (exit code 130) with every staged output
    removed.
    """
    run.configure_own_process()
    with run.cancel_on_signals():
        return _main(argv)


def _main(argv=None) -> int:
    parser = build_parser()
    args = None
    try:
        args = parser.parse_args(argv)
        if args.quiet and args.verbose:
            parser.error("--quiet and --verbose exclude each other")
        if args.cases and args.progress_lines:
            parser.error("--progress-lines is for one run (--ct/--seg), not for --cases")
        if args.cases:
            from . import batch

            return batch.run_from_args(args, parser)
        return _run_single(args, parser)
    except SystemExit as exc:  # --help
        return exc.code if isinstance(exc.code, int) else EXIT_OK
    except KeyboardInterrupt as exc:
        how = f" ({exc.name})" if isinstance(exc, CancelledBySignal) else " by the user"
        sys.stderr.write(f"\nerror: cancelled{how}; no output file was written.\n")
        _print_error_line(args, exc, EXIT_CANCELLED)
        return EXIT_CANCELLED
    except Exception as exc:  # one line for the user; the traceback only on request
        code = exit_code_for(exc)
        _print_error_line(args, exc, code)
        if code == EXIT_INTERNAL and args is not None and args.verbose:
            import traceback

            traceback.print_exc()
        internal = code == EXIT_INTERNAL and not isinstance(exc, OSError)
        prefix = "internal error: " if internal else ""
        sys.stderr.write(f"error: {prefix}{one_line(exc)}\n")
        return code


def check_single_args(args, parser) -> None:
    missing = [flag for flag, value in (("--ct", args.ct), ("--seg", args.seg),
                                        ("--out", args.out)) if not value]
    if not args.label and not args.all_labels:
        missing.append("--label (or --all-labels)")
    if missing:
        parser.error("missing " + ", ".join(missing))
    if args.label and args.all_labels:
        parser.error("--label and --all-labels exclude each other")
    if (args.all_labels or len(args.label) > 1) and "{label}" not in args.out:
        parser.error("several labels but --out has no {label} placeholder; "
                     "use e.g. --out bone_{label}.stl")
    if args.label and len(set(args.label)) != len(args.label):
        parser.error("the same --label is given twice")
    for path in [args.out] + ([args.report] if args.report else []):
        if "{case}" in path:
            parser.error("{case} is only available with --cases")
    try:
        run.check_surface_path(args.out)
    except InputError as exc:
        parser.error(str(exc))
    if args.report and not args.report.lower().endswith(".json"):
        parser.error("--report must be a .json file")
    if args.picture and not args.picture.lower().endswith(".png"):
        parser.error("--picture must be a .png file")


def parse_neighbours(text: str, names: dict):
    """'auto', 'none' or a list of label values from a comma-separated list of labels."""
    text = (text or "auto").strip()
    if text.lower() in ("auto", "none"):
        return text.lower()
    return [segmentations.resolve_label(names, part.strip()) for part in text.split(",")
            if part.strip()]


def _run_single(args, parser) -> int:
    check_single_args(args, parser)
    params = parameters_from_args(args)
    system = "RAS" if args.ras else "LPS"
    bar = ProgressBar(enabled=None if not args.quiet else False, verbose=args.verbose)
    progress = ProgressLines(sys.stdout, bar) if args.progress_lines else bar
    if args.progress_lines:
        progress(0.0, "Reading the CT")

    t0 = time.perf_counter()
    ct = images.read_ct(args.ct, args.ct_series)
    if args.progress_lines:
        progress(0.0, "Reading the segments")
    labels, names = segmentations.read_label_image(args.seg)
    if args.all_labels:
        present = getattr(names, "present", None)
        targets = [v for v in sorted(names) if present is None or v in present]
        if not targets:
            raise InputError(f"{args.seg} holds no painted label.")
    else:
        targets = [segmentations.resolve_label(names, label) for label in args.label]
    neighbours = parse_neighbours(args.neighbours, names)
    t_read = time.perf_counter() - t0
    for i, v in enumerate(targets):
        if v in targets[:i]:
            raise InputError(f"--label {args.label[targets.index(v)]} and --label {args.label[i]} "
                             f"are the same segment '{names.get(v, v)}'; give each bone once.")
    label_names = {v: str(names.get(v, v)) for v in targets}
    outputs = {v: run.fill_template(args.out, label_names[v]) for v in targets}
    if len(set(outputs.values())) != len(outputs):
        raise InputError("Two labels give the same output file name; use distinct labels.")
    pictures = None
    if args.picture:
        pictures = {}
        for v in targets:
            pic = run.fill_template(args.picture, label_names[v])
            if len(targets) > 1 and "{label}" not in args.picture:
                pic = os.path.splitext(pic)[0] + f"_{run.safe_name(label_names[v])}.png"
            pictures[v] = pic
    inputs = {"ct": os.path.abspath(args.ct), "seg": os.path.abspath(args.seg),
              "ct_size": list(ct.GetSize()), "ct_spacing": list(ct.GetSpacing())}
    tx = bwfiles.OutputTransaction()
    try:
        with tx:
            joint = run.run_joint(ct, labels, targets, dict(names), outputs, params,
                                  coordinate_system=system, pictures=pictures,
                                  intermediates_dir=args.save_intermediates,
                                  neighbours=neighbours, progress=progress, inputs=inputs,
                                  read_seconds=t_read, report_path=args.report,
                                  transaction=tx)
    except CancelledError:
        bar.close()
        raise KeyboardInterrupt from None
    except KeyboardInterrupt as exc:
        bar.close()
        if tx.state != "committed":
            raise
        # A signal that arrived while the files were being renamed is acted on right after.
        how = f" ({exc.name})" if isinstance(exc, CancelledBySignal) else ""
        sys.stderr.write(f"\nerror: cancelled{how} just after the outputs were written; they "
                         "are complete.\n")
        return EXIT_CANCELLED
    finally:
        bar.close()
    codes = [EXIT_OK] * len(joint.reports)
    for name, exc in joint.failures:
        which = f"{name}: " if len(targets) > 1 else ""
        sys.stderr.write(f"error: {which}{one_line(exc)}\n")
        code = exit_code_for(exc)
        if code == EXIT_INTERNAL:
            raise exc
        _print_error_line(args, exc, code, segment=name)
        codes.append(code)
    if not args.quiet:
        for report in joint.reports:
            print(case_summary_line(report), flush=True)
        for pair in joint.pairs:
            print(pair_summary_line(pair), flush=True)
    return joint_exit_code(codes, len(joint.reports))
