"""Batch runs: many cases from a CSV or a folder layout, on worker processes or a Dask cluster.

Each case runs in isolation; a failed case becomes a row with its error message and the
batch goes on. The summary table (CSV or markdown) lists every case with its status. The files
of each case (surface, report, intermediates) are one output transaction: they appear together
or not at all. SIGINT, SIGTERM and SIGHUP stop the batch (exit code 130): worker processes are
stopped, their staged files removed; the cases finished before stay written.
"""

from __future__ import annotations

import csv
import io as stringio
import multiprocessing
import os
import signal
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Optional

from ..errors import (EXIT_CANCELLED, EXIT_CODES, EXIT_FAILED, EXIT_INTERNAL, EXIT_OK,
                      CancelledBySignal, DependencyError, InputError, exit_code_for, one_line)
from ..io import files as bwfiles
from ..params import PRESETS_REMOVED
from . import run
from .options import make_parameters, parameter_overrides, parameters_from_args

CT_NAMES = ("ct.nrrd", "ct.nhdr", "ct.nii.gz", "ct.nii", "ct.mha", "ct.mhd")
LABEL_MAP_PREFIXES = ("seg.", "labels.", "mask.")
SUMMARY_COLUMNS = ("case", "label", "status", "exit_code", "n_vertices", "n_faces", "checks_ok",
                   "distance_mean_mm", "distance_p95_mm", "seconds", "out", "message")
STATUS = {**EXIT_CODES, EXIT_OK: "ok", EXIT_FAILED: "failed", EXIT_INTERNAL: "error"}
# Seconds a cancelled worker process gets to remove its staged files before it is killed.
WORKER_STOP_SECONDS = 30.0


# ----------------------------------------------------------------------------------------
# case lists

def cases_from_csv(path: str) -> list:
    """Tasks from a CSV with columns ct,seg,label,out[,case]."""
    folder = os.path.dirname(os.path.abspath(path))
    with open(path, newline="", encoding="utf-8-sig") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames is None:
            raise InputError(f"Cases file {path} is empty.")
        columns = {c.strip().lower() for c in reader.fieldnames if c}
        missing = [c for c in ("ct", "seg", "label", "out") if c not in columns]
        if missing:
            raise InputError(f"Cases file {path} lacks column(s) {', '.join(missing)}; "
                             "the header must be ct,seg,label,out[,case].")
        tasks = []
        for number, raw in enumerate(reader, start=1):
            row = {(k or "").strip().lower(): (v or "").strip() for k, v in raw.items()}
            if not any(row.values()):
                continue

            def resolve(p):
                return p if not p or os.path.isabs(p) else os.path.join(folder, p)
            case = row.get("case") or f"row{number}"
            task = {"case": case, "ct": resolve(row["ct"]), "seg": resolve(row["seg"]),
                    "label": row["label"], "out": resolve(row["out"])}
            empty = [c for c in ("ct", "seg", "label", "out") if not row.get(c)]
            if empty:
                task["error"] = f"row {number} of {path} has no {', '.join(empty)}"
            elif row.get("preset"):
                task["error"] = f"row {number} of {path}: {PRESETS_REMOVED}"
            tasks.append(task)
    if not tasks:
        raise InputError(f"Cases file {path} lists no case.")
    return tasks


def find_case_files(case_dir: str):
    """(ct, seg) paths in one case folder of the batch layout; None where not found."""
    names = sorted(os.listdir(case_dir))
    ct = next((os.path.join(case_dir, n) for n in CT_NAMES if n in names), None)
    if ct is None and os.path.isdir(os.path.join(case_dir, "ct")):
        ct = os.path.join(case_dir, "ct")
    segs = [n for n in names if n.lower().endswith(".seg.nrrd")]
    if not segs:
        segs = [n for n in names
                if n.lower().startswith(LABEL_MAP_PREFIXES) and not n.lower().endswith(".csv")]
    if not segs:
        segs = [n for n in names if "_labels." in n.lower() and not n.lower().endswith(".csv")]
    seg = os.path.join(case_dir, segs[0]) if len(segs) == 1 else None
    if len(segs) > 1:
        seg = ("ambiguous", [os.path.join(case_dir, n) for n in segs])
    return ct, seg


def cases_from_folder(folder: str, labels: list, out_template: str) -> list:
    """Tasks from the folder layout DIR/<case>/{ct.*, *.seg.nrrd | label map} (see --help)."""
    if not labels:
        raise InputError("--cases DIR needs --label (repeatable) to say which bone(s) to build.")
    if not out_template or "{case}" not in out_template:
        raise InputError("--cases DIR needs --out with a {case} placeholder, e.g. "
                         "--out results/{case}_{label}.stl")
    if len(labels) > 1 and "{label}" not in out_template:
        raise InputError("Several --label values need {label} in --out.")
    case_dirs = [d for d in sorted(os.listdir(folder))
                 if not d.startswith(".") and os.path.isdir(os.path.join(folder, d))]
    if not case_dirs:
        raise InputError(f"No case folder in {folder}; expected {folder}/<case>/ct.nrrd + a "
                         "segmentation (see --help).")
    tasks = []
    for case in case_dirs:
        ct, seg = find_case_files(os.path.join(folder, case))
        for label in labels:
            task = {"case": case, "ct": ct or "", "seg": seg if isinstance(seg, str) else "",
                    "label": label, "out": out_template.replace("{case}", case)}
            if ct is None:
                task["error"] = (f"no CT in {os.path.join(folder, case)} (expected one of "
                                 f"{', '.join(CT_NAMES)} or a ct/ DICOM folder)")
            elif seg is None:
                task["error"] = (f"no segmentation in {os.path.join(folder, case)} (expected a "
                                 "*.seg.nrrd or a seg.*/labels.*/mask.*/*_labels.* label map)")
            elif isinstance(seg, tuple):
                task["error"] = ("several segmentation files in "
                                 f"{os.path.join(folder, case)}: "
                                 + ", ".join(os.path.basename(p) for p in seg[1]))
            tasks.append(task)
    return tasks


# ----------------------------------------------------------------------------------------
# one case (runs in a worker process or on a Dask worker)

def run_task(task: dict, common: dict) -> dict:
    """Run one case and return its summary row; never raises for a failed case.

    Runs in a worker process or on a Dask worker: everything it needs comes in ``task`` and
    ``common`` (plain, picklable values).
    """
    global _task_running
    t0 = time.perf_counter()
    row = {c: "" for c in SUMMARY_COLUMNS}
    row.update(case=task["case"], label=task["label"], out=task.get("out", ""))
    _task_running = True
    try:
        if task.get("error"):
            raise InputError(task["error"])
        threads = common.get("threads")
        if threads:
            import SimpleITK as sitk

            sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(int(threads))
        params = make_parameters(common.get("overrides", {}))
        intermediates = common.get("intermediates")
        # The report is in the case's transaction: surface and report appear together.
        report = run.run_files(
            task["ct"], task["seg"], task["label"], task["out"], params, case=task["case"],
            coordinate_system=common.get("coordinate_system", "LPS"),
            intermediates_dir=intermediates, report_path=common.get("report"))
        dist = report.distance_to_constraints_mm
        row.update(status="ok", exit_code=EXIT_OK, out=report.output.path,
                   n_vertices=report.output.n_vertices, n_faces=report.output.n_faces,
                   checks_ok=bool(report.checks.ok),
                   distance_mean_mm=_fmt(dist.mean), distance_p95_mm=_fmt(dist.p95))
    except Exception as exc:
        code = exit_code_for(exc)
        row.update(status=STATUS.get(code, "error"), exit_code=code, message=one_line(exc))
    finally:
        _task_running = False
    row["seconds"] = f"{time.perf_counter() - t0:.1f}"
    return row


# True while a worker process runs a task: a signal then cancels the task (its staged files
# are removed); an idle worker just exits.
_task_running = False


def _worker_signal(signum, frame):
    if bwfiles.defer_signal(signum):
        return
    if _task_running:
        raise CancelledBySignal(signum)
    os._exit(EXIT_CANCELLED)


def _init_worker() -> None:
    """Worker processes: SIGINT, SIGTERM and SIGHUP cancel the task under way; the settings of
    a process of our own (:func:`run.configure_own_process`)."""
    run.configure_own_process()
    for signum in run.CANCEL_SIGNALS:
        signal.signal(signum, _worker_signal)


def _stop_workers(processes) -> None:
    """SIGTERM each worker (it removes its staged files and exits), then wait; kill the ones
    still running after WORKER_STOP_SECONDS (their temporary files are removed by a later run,
    see :func:`BoneWatertightLib.io.files.remove_stale`)."""
    for process in processes:
        if process.is_alive():
            process.terminate()
    deadline = time.monotonic() + WORKER_STOP_SECONDS
    for process in processes:
        process.join(max(0.0, deadline - time.monotonic()))
        if process.is_alive():
            process.kill()
            process.join()


def _fmt(value) -> str:
    return "" if value is None else f"{value:.3f}"


# ----------------------------------------------------------------------------------------
# running many

def run_tasks(tasks: list, common: dict, workers: int = 1, dask_address: Optional[str] = None,
              on_row=None) -> list:
    """Run every task; return the rows in task order. ``on_row(row, done, total)`` reports."""
    rows = [None] * len(tasks)
    done = 0

    def finished(index, row):
        nonlocal done
        rows[index] = row
        done += 1
        if on_row:
            on_row(row, done, len(tasks))

    if dask_address:
        client_cls, as_done = _dask()
        with client_cls(dask_address) as client:
            ship_code_to_workers(client)
            futures = {client.submit(run_task, task, common, pure=False): i
                       for i, task in enumerate(tasks)}
            for future in as_done(list(futures)):
                index = futures[future]
                try:
                    row = future.result()
                except Exception as exc:  # a worker that died, not a failed case
                    row = _crashed_row(tasks[index], exc)
                finished(index, row)
        return rows
    if workers <= 1:
        for i, task in enumerate(tasks):
            finished(i, run_task(task, common))
        return rows
    # spawn: fresh interpreters, so vtk/open3d/ITK thread pools are never forked mid-use.
    context = multiprocessing.get_context("spawn")
    before = set(multiprocessing.active_children())
    executor = ProcessPoolExecutor(max_workers=workers, mp_context=context,
                                   initializer=_init_worker)
    try:
        futures = {executor.submit(run_task, task, common): i for i, task in enumerate(tasks)}
        for future in as_completed(futures):
            index = futures[future]
            try:
                row = future.result()
            except Exception as exc:  # e.g. a worker killed by the OS for memory
                row = _crashed_row(tasks[index], exc)
            finished(index, row)
    except BaseException:  # cancelled (a signal) or the loop failed: stop every worker
        executor.shutdown(wait=False, cancel_futures=True)
        _stop_workers(set(multiprocessing.active_children()) - before)
        raise
    executor.shutdown(wait=True)
    return rows


def _crashed_row(task, exc) -> dict:
    row = {c: "" for c in SUMMARY_COLUMNS}
    row.update(case=task["case"], label=task["label"], out=task.get("out", ""), status="error",
               exit_code=EXIT_INTERNAL, message=f"worker crashed: {one_line(exc)}")
    return row


# Probe run on every Dask worker: can it import the library? (eval is a builtin, so the probe
# itself needs nothing from this package on the worker.)
_IMPORT_PROBE = "__import__('importlib.util').util.find_spec('BoneWatertightLib') is not None"


def package_zip(folder: str) -> str:
    """Zip of this package's .py files (BoneWatertightLib/... at the root) in ``folder``."""
    import zipfile

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    path = os.path.join(folder, "BoneWatertightLib.zip")
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for dirpath, dirnames, filenames in os.walk(root):
            dirnames[:] = [d for d in dirnames if d != "__pycache__"]
            for name in sorted(filenames):
                if name.endswith(".py"):
                    full = os.path.join(dirpath, name)
                    zf.write(full, os.path.join("BoneWatertightLib",
                                                os.path.relpath(full, root)))
    return path


def ship_code_to_workers(client) -> bool:
    """Make the library importable on every worker of ``client``.

    Workers that have it installed (``pip install <checkout>`` on the worker machines) need
    nothing. Otherwise the client uploads a zip of its own copy (``client.upload_file``, which
    also reaches workers that join later) and checks again. Returns True when it uploaded.
    """
    found = client.run(eval, _IMPORT_PROBE)
    if found and all(found.values()):
        return False
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        client.upload_file(package_zip(folder))
    found = client.run(eval, _IMPORT_PROBE)
    missing = [w for w, ok in found.items() if not ok]
    if missing:
        raise DependencyError(
            "The Dask workers cannot import BoneWatertightLib even after uploading it "
            f"({', '.join(missing)}); install it on the workers: pip install <checkout>.")
    return True


def _dask():
    try:
        from dask.distributed import Client, as_completed as dask_as_completed
    except ImportError:
        raise DependencyError('--dask needs dask.distributed: pip install "dask[distributed]"'
                              ) from None
    return Client, dask_as_completed


def summary_table(rows: list, markdown: bool = True) -> str:
    if markdown:
        lines = ["| " + " | ".join(SUMMARY_COLUMNS) + " |",
                 "|" + "|".join("---" for _ in SUMMARY_COLUMNS) + "|"]
        for row in rows:
            cells = [str(row.get(c, "")).replace("|", "\\|") for c in SUMMARY_COLUMNS]
            lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines) + "\n"
    buffer = stringio.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=SUMMARY_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({c: row.get(c, "") for c in SUMMARY_COLUMNS})
    return buffer.getvalue()


def run_from_args(args, parser) -> int:
    """The --cases entry point of the command line."""
    if args.ct or args.seg:
        parser.error("--cases replaces --ct/--seg; give the inputs in the cases file or folder")
    if args.picture:
        parser.error("--picture is not available with --cases")
    if args.workers < 1:
        parser.error("--workers must be >= 1")
    if args.summary and os.path.splitext(args.summary)[1].lower() not in (".csv", ".md"):
        parser.error("--summary must be a .csv or .md file")
    if not os.path.exists(args.cases):
        raise InputError(f"Cases file or folder not found: {args.cases}")
    if args.dask:
        _dask()  # a clear error before any work when dask is missing
    parameters_from_args(args)  # validate the shared options before starting workers
    overrides = parameter_overrides(args)
    if args.save_intermediates:
        overrides["keep_intermediates"] = True
    if os.path.isdir(args.cases):
        tasks = cases_from_folder(args.cases, args.label or [], args.out)
    else:
        if args.label or args.out:
            parser.error("with a cases CSV, label and out come from its columns")
        tasks = cases_from_csv(args.cases)
    if args.report and len(tasks) > 1 and "{case}" not in args.report:
        parser.error("with several cases --report needs a {case} placeholder")
    intermediates = None
    if args.save_intermediates:
        intermediates = os.path.join(args.save_intermediates, "{case}")
    cpus = os.cpu_count() or 1
    common = {"overrides": overrides,
              "coordinate_system": "RAS" if args.ras else "LPS", "report": args.report,
              "intermediates": intermediates,
              "threads": max(1, cpus // max(1, args.workers)) if args.workers > 1 else None}

    finished_ok = []

    def on_row(row, done, total):
        if row["status"] == "ok":
            finished_ok.append(row)
        if not args.quiet:
            extra = row["message"] if row["status"] != "ok" else row["out"]
            print(f"[{done}/{total}] {row['case']} {row['label']}: {row['status']} "
                  f"({row['seconds']} s) {extra}", flush=True)

    try:
        rows = run_tasks(tasks, common, workers=args.workers, dask_address=args.dask,
                         on_row=on_row)
    except KeyboardInterrupt as exc:
        how = f" ({exc.name})" if isinstance(exc, CancelledBySignal) else ""
        sys.stderr.write(f"\nerror: cancelled{how}: {len(finished_ok)} of {len(tasks)} cases "
                         "had finished and are written; the others wrote nothing.\n")
        return EXIT_CANCELLED
    if args.summary:
        markdown = args.summary.lower().endswith(".md")
        bwfiles.write_text(summary_table(rows, markdown=markdown),
                           bwfiles.ensure_folder(args.summary))
    n_ok = sum(r["status"] == "ok" for r in rows)
    if not args.quiet:
        print(summary_table(rows, markdown=True), end="")
        print(f"{n_ok} of {len(rows)} surfaces built.", flush=True)
    if n_ok < len(rows):
        sys.stderr.write(f"error: {len(rows) - n_ok} of {len(rows)} cases failed "
                         "(see the summary).\n")
        return EXIT_FAILED
    return EXIT_OK
