"""Benchmark part: the product on the anatomical phantoms (Testing/anatomical.py), against
their exact truths, beside the plain baselines on the same input.

    python Testing/bench_anatomical.py --out bench_anat [--cases pelvis_3mm,...] [--seed 0]
    python Testing/benchmark.py --cases none --anatomical      # the same, as a benchmark part

Per case (hip bone + sacrum + femur, L3-L5, scapula + humerus, each as a 0.7 x 0.7 x 2.5 mm and
a 3 mm CT):

1. The phantom is built in its own process (``--build``) and written to disk: ``ct.nrrd``,
   ``labels.nrrd`` (AI-style, on the CT grid), ``truths.npz`` and ``info.json``; kept while
   the generator's source, the case and the seed are unchanged (``.key``).
2. The product's command line at its defaults, every bone of the case in one run as a user
   would (``bonewatertight --ct CT --seg LABELS --label L1 --label L2 ... --out '{label}.vtp'
   --report report.json``), in a fresh process (Testing/bench_worker.py, kind ``cli``): exit
   code, the error lines of a refusal, time, peak memory.
3. Per bone: distances to the truth (area samples on both surfaces, exact point-to-triangle,
   both directions pooled: mean / p95 / max; Testing/bench_common.truth_metrics), bias, volume
   ratio, genus against the truth's, the surface checks, the share of the surface closer to a
   neighbour's truth than to its own; the pipeline's warnings.
4. Baselines on the same CT and label, each in a fresh process: threshold + marching cubes +
   Slicer's smoothing on the working grid (baselines.threshold_marching_cubes, HT 150 HU) and
   the label's own closed surface through Slicer's conversion (baselines.segment_closed_surface).

Output: ``<out>/ANATOMICAL.md`` (markdown tables) and ``<out>/anatomical.json``, with a
cross-section figure per case. Nothing here judges pass or fail: the tables report.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
for _p in (ROOT, HERE):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from bench_common import (check, fig_sections, fmt, jsonable, md_table, short,  # noqa: E402
                          truth_metrics, write_phantom)
from bench_worker import run_isolated  # noqa: E402

CASES = ["pelvis_3mm", "pelvis_0p7x2p5", "lumbar_3mm", "lumbar_0p7x2p5", "scapula_3mm", "scapula_0p7x2p5"]
QUICK_CASES = ["sample_L3L4"]
BASELINES = {"threshold_mc": "threshold + MC + smoothing (HT 150)",
             "segment": "label's closed surface (Slicer)"}


def log(msg):
    print(time.strftime("%H:%M:%S"), msg, flush=True)


# ---------------------------------------------------------------------------- building

def _key(case, seed):
    src = open(os.path.join(HERE, "anatomical.py"), "rb").read()
    return hashlib.sha1(src + repr((case, seed)).encode()).hexdigest()[:16]


def _build_here(case, seed, cdir):
    """In the build process: make the phantom and write it to cdir."""
    import anatomical

    os.makedirs(cdir, exist_ok=True)  # before the work: an unwritable place fails at once
    t0 = time.perf_counter()
    ph = anatomical.make_anatomical(case, seed=seed)
    seconds = time.perf_counter() - t0
    write_phantom(cdir, ph, seconds)


def build_case(case, seed, cdir, timeout=900.0):
    """The phantom's files in cdir (built in a fresh process unless cached). Returns
    (info dict, build record: seconds, peak MB, cached, error)."""
    os.makedirs(cdir, exist_ok=True)
    key = _key(case, seed)
    kpath = os.path.join(cdir, ".key")
    files = [os.path.join(cdir, f) for f in ("ct.nrrd", "labels.nrrd", "truths.npz", "info.json")]
    rec = {"cached": False, "error": None}
    if not (os.path.exists(kpath) and open(kpath).read() == key and all(map(os.path.exists, files))):
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, os.path.abspath(__file__), "--build", case, str(seed), cdir],
                              cwd=ROOT, capture_output=True, text=True, timeout=timeout)
        rec["process_seconds"] = time.perf_counter() - t0
        if proc.returncode != 0:
            rec["error"] = short((proc.stderr or proc.stdout).strip().splitlines()[-1] if (proc.stderr or proc.stdout) else
                                 f"exit {proc.returncode}", 300)
            return None, rec
        with open(kpath, "w") as fh:
            fh.write(key)
    else:
        rec["cached"] = True
    with open(files[3]) as fh:
        info = json.load(fh)
    rec["seconds"] = info.get("build_seconds")
    rec["peak_rss_mb"] = info.get("peak_rss_mb")
    return info, rec


def load_truths(cdir):
    from BoneWatertightLib.mesh import Surface

    z = np.load(os.path.join(cdir, "truths.npz"))
    return {int(k[1:]): Surface(z[k], z["f" + k[1:]], "LPS") for k in z.files if k.startswith("v")}


def _read_vtp(path):
    import vtk

    from BoneWatertightLib.mesh import from_polydata

    r = vtk.vtkXMLPolyDataReader()
    r.SetFileName(path)
    r.Update()
    return from_polydata(r.GetOutput())


# ---------------------------------------------------------------------------- one case

def _error_lines(text):
    """The lines of a CLI log that say why something failed."""
    keep = [ln.strip() for ln in (text or "").splitlines()
            if re.match(r"^\s*(error|ERROR)\b", ln) or "FAILED" in ln or "failed" in ln.lower()[:40]]
    return keep[:6]


def _nearest_neighbour(label, joints, names):
    """The label of the bone this one shares its closest joint with (or None)."""
    by_name = {v: int(k) for k, v in names.items()}
    best = None
    for j in joints:
        if j.get("carved") and names.get(str(label)) in (j["a"], j["b"]):
            other = j["b"] if j["a"] == names.get(str(label)) else j["a"]
            if best is None or j["min_distance_mm"] < best[0]:
                best = (j["min_distance_mm"], by_name[other])
    return None if best is None else best[1]


def run_case(case, args):
    import SimpleITK as sitk

    cdir = os.path.join(args.out_dir, "anatomical", f"{case}_s{args.seed}")
    log(f"[{case}] building the phantom ...")
    info, build = build_case(case, args.seed, cdir)
    res = {"case": case, "seed": args.seed, "build": build, "bones": [], "figures": {}}
    if info is None:
        log(f"[{case}] build FAILED: {build['error']}")
        return res
    res["info"] = {k: info.get(k) for k in ("pixel", "slice_spacing", "slice_thickness", "psf_sigma", "noise",
                                            "label_grid", "model_grid", "direction_angles_deg", "ct_size",
                                            "joints", "plates", "ct_figures", "bones_info", "timing",
                                            "peak_rss_mb", "bones")}
    names = info["names"]
    labels = sorted(int(k) for k in names)
    truths = load_truths(cdir)
    ct_path, lab_path = os.path.join(cdir, "ct.nrrd"), os.path.join(cdir, "labels.nrrd")
    log(f"[{case}] built in {fmt(build.get('seconds'), 1)} s ({fmt(build.get('peak_rss_mb'), 0)} MB"
        f"{', cached' if build['cached'] else ''}); product CLI on labels {labels} ...")
    out_t = os.path.join(cdir, "out_{label}.vtp")
    rep_path = os.path.join(cdir, "report.json")
    for lv in labels:
        for p in (out_t.replace("{label}", str(lv)),):
            if os.path.exists(p):
                os.unlink(p)
    if os.path.exists(rep_path):
        os.unlink(rep_path)
    argv = ["--ct", ct_path, "--seg", lab_path]
    for lv in labels:
        argv += ["--label", str(lv)]
    argv += ["--out", out_t, "--report", rep_path]
    cli = run_isolated({"kind": "cli", "argv": argv, "log": os.path.join(cdir, "cli.log")}, args.timeout,
                       os.path.join(args.out_dir, "_work"))
    log_text = open(os.path.join(cdir, "cli.log")).read() if os.path.exists(os.path.join(cdir, "cli.log")) else ""
    report = None
    if os.path.exists(rep_path):
        with open(rep_path) as fh:
            report = json.load(fh)
    res["cli"] = {"argv": ["bonewatertight"] + [os.path.basename(a) if os.path.isabs(a) else a for a in argv],
                  "exit_code": cli.get("exit_code"), "ok": bool(cli.get("ok")), "error": cli.get("error"),
                  "seconds": cli.get("seconds"), "peak_rss_mb": cli.get("peak_rss_mb"),
                  "error_lines": _error_lines(log_text), "log_tail": log_text[-1500:],
                  "pairs": (report or {}).get("pairs") if isinstance(report, dict) else None}
    log(f"[{case}] CLI exit {cli.get('exit_code')} in {fmt(cli.get('seconds'), 1)} s, "
        f"{fmt(cli.get('peak_rss_mb'), 0)} MB" + ("" if not res["cli"]["error_lines"] else
                                                  ": " + short(" | ".join(res["cli"]["error_lines"]), 300)))
    failed = {}
    warnings = {}
    if isinstance(report, dict):
        for f in report.get("failed") or []:
            failed[str(f.get("segment"))] = f.get("error")
        for s in report.get("surfaces") or []:
            pipe = s.get("pipeline") or {}
            warnings[str((s.get("inputs") or {}).get("label"))] = pipe.get("warnings") or []
    surfaces = {}
    for lv in labels:
        name = names[str(lv)]
        truth = truths[lv]
        nb = _nearest_neighbour(lv, info.get("joints") or [], names)
        row = {"label": lv, "name": name, "truth_genus": (info["bones_info"][name] or {}).get("genus"),
               "truth_ml": (info["bones_info"][name] or {}).get("volume_ml"), "baselines": {}}
        path = out_t.replace("{label}", str(lv))
        if os.path.exists(path):
            s = _read_vtp(path)
            ev = {"checks": check(s.vertices, s.faces), "n_faces": int(len(s.faces))}
            ev.update(truth_metrics(s.vertices, s.faces, truth, args.samples, truths.get(nb) if nb else None))
            row.update(ev)
            row["ok"] = True
            row["warnings"] = warnings.get(str(lv)) or []
            surfaces[lv] = s
        else:
            row["ok"] = False
            row["refusal"] = failed.get(str(lv)) or failed.get(name) or "; ".join(res["cli"]["error_lines"]) or \
                cli.get("error") or f"no surface (exit {cli.get('exit_code')})"
        # baselines
        mask_path = os.path.join(cdir, f"mask_{lv}.nrrd")
        lab_img = sitk.ReadImage(lab_path)
        sitk.WriteImage(sitk.Cast(sitk.Equal(lab_img, lv), sitk.sitkUInt8), mask_path, True)
        for key in BASELINES:
            if key == "segment":
                task = {"kind": "segment_surface", "labels": lab_path, "value": lv}
            else:
                task = {"kind": "baseline", "method": key, "ct": ct_path, "mask": mask_path, "params": {}}
            r = run_isolated(task, args.timeout, os.path.join(args.out_dir, "_work"))
            br = {"ok": bool(r.get("ok")), "error": r.get("error"), "seconds": r.get("seconds"),
                  "peak_rss_mb": r.get("peak_rss_mb")}
            if r.get("ok") and len(r["bones"][0]["faces"]):
                bv, bf = r["bones"][0]["vertices"], r["bones"][0]["faces"]
                br["checks"] = check(bv, bf)
                br.update(truth_metrics(bv, bf, truth, args.samples))
                from BoneWatertightLib.mesh import Surface
                surfaces[(key, lv)] = Surface(bv, bf)
            elif r.get("ok"):
                br["ok"] = False
                br["error"] = "empty surface"
            row["baselines"][key] = br
        d = row.get("distance") or {}
        log(f"[{case}] {name}: " + (f"mean {fmt(d.get('mean'))} p95 {fmt(d.get('p95'))} max {fmt(d.get('max'))} "
                                    f"vol {fmt(row.get('volume_ratio'))} genus {row['checks'].get('genus')} "
                                    f"(truth {row['truth_genus']})" if row["ok"] else
                                    "REFUSED: " + short(row["refusal"], 200))
            + " | " + "; ".join(f"{k}: " + (f"p95 {fmt((b.get('distance') or {}).get('p95'))} vol {fmt(b.get('volume_ratio'))}"
                                          if b.get("ok") else "failed") for k, b in row["baselines"].items()))
        res["bones"].append(row)
    # a picture: CT planes through the first bone's thinnest region with every surface
    try:
        ct = sitk.ReadImage(ct_path)
        first = labels[0] if case.startswith(("pelvis", "scapula")) else labels[len(labels) // 2]
        first = 78 if 78 in labels else (72 if 72 in labels else first)
        centre = truths[first].vertices.mean(axis=0)
        entries = []
        # The truths' vertices lie on the model grid's planes, which contain the CT's voxel
        # planes: shifted by 1 um off them, so that the section finds the faces.
        from BoneWatertightLib.mesh import Surface
        shift = 1e-3 * np.array(ct.GetDirection()).reshape(3, 3) @ np.ones(3)
        for lv, col in zip(labels, ("lime", "yellow", "cyan")):
            entries.append((f"truth {names[str(lv)]}", Surface(truths[lv].vertices + shift, truths[lv].faces),
                            col, 1.8, "-"))
        for lv in labels:
            if lv in surfaces:
                entries.append((f"product {names[str(lv)]}", surfaces[lv], "red", 1.0, "-"))
            if ("threshold_mc", lv) in surfaces:
                entries.append((f"threshold_mc {names[str(lv)]}", surfaces[("threshold_mc", lv)], "orange", 0.7, "--"))
        fig = os.path.join(cdir, "sections.png")
        fig_sections(f"{case} seed {args.seed}: truth (green/yellow/cyan), product (red), threshold+MC (orange)",
                     ct, entries, fig, centre)
        res["figures"]["sections"] = os.path.relpath(fig, args.out_dir)
    except Exception as exc:  # noqa: BLE001 - no picture is not a benchmark failure
        res["figures"]["error"] = f"{type(exc).__name__}: {exc}"
    return res


# ---------------------------------------------------------------------------- report

def report_lines(anat: dict) -> list:
    L = ["## Anatomical phantoms (issue 18)", "",
         "Real bone shapes (TotalSegmentator labels of the 3 mm pelvis CT; a synthetic scapula) made "
         "smooth, with thin plates, joint spaces, a cortex of varying thickness, CT formed at the stated "
         "resolution, AI-style labels (Testing/anatomical.py). The product's command line at its "
         "defaults, every bone of the case in one run; distances to the exact truth (mean / p95 / max, "
         "both directions), volume ratio, genus (surface / truth), refusals with their message; the "
         "baselines on the same CT and label.", ""]
    if anat.get("_skipped"):
        return L + [anat["_skipped"], ""]
    for case, r in anat.items():
        if case.startswith("_"):
            continue
        b = r.get("build") or {}
        if r.get("info") is None:
            L += [f"### `{case}`: build FAILED: {b.get('error')}", ""]
            continue
        info = r["info"]
        cli = r.get("cli") or {}
        thick = info.get("slice_thickness") or info.get("slice_spacing")
        gaps = "; ".join(f"{j['a']}/{j['b']} {j['gap_mm']:g} mm (truths {fmt(j.get('min_distance_mm'), 2)} mm apart)"
                         for j in info.get("joints") or [] if j.get("carved"))
        L += [f"### `{case}` (seed {r['seed']}): CT {info['pixel']} x {info['pixel']} x {info['slice_spacing']} mm "
              f"(slice {thick} mm, PSF {info['psf_sigma']} mm, noise {info['noise']} HU), labels "
              f"{info['label_grid']} mm", "",
              f"Joints: {gaps or 'none'}. Built in {fmt(b.get('seconds'), 1)} s, peak {fmt(b.get('peak_rss_mb'), 0)} MB. "
              f"Product run: exit **{cli.get('exit_code')}**, {fmt(cli.get('seconds'), 1)} s, "
              f"{fmt(cli.get('peak_rss_mb'), 0)} MB"
              + (f"; error lines: `{short(' | '.join(cli.get('error_lines') or []), 400)}`" if cli.get("error_lines") else "")
              + ".", ""]
        rows = []
        for bone in r["bones"]:
            pl = (info.get("plates") or {}).get(bone["name"]) or {}
            thin = (f"{100 * pl.get('whole_bone_area_frac_thinner_than_1mm', 0):.1f} / "
                    f"{100 * pl.get('whole_bone_area_frac_thinner_than_2mm', 0):.1f}")
            if bone.get("ok"):
                d = bone["distance"]
                rows.append([bone["name"], thin, fmt(bone.get("truth_ml"), 1), "product",
                             f"{d['mean']:.2f} / {d['p95']:.2f} / {d['max']:.2f}", f"{bone['bias_mm']:+.2f}",
                             fmt(bone.get("volume_ratio"), 3),
                             f"{bone['checks'].get('genus')} / {bone['truth_genus']}",
                             "pass" if bone["checks"]["ok"] else "**fail**: " + short("; ".join(bone["checks"]["problems"]), 80),
                             fmt(bone.get("frac_on_neighbour"), 3),
                             short("; ".join(bone.get("warnings") or []), 160) or "-"])
            else:
                rows.append([bone["name"], thin, fmt(bone.get("truth_ml"), 1), "product",
                             "**REFUSED**", "", "", f"- / {bone['truth_genus']}", "", "", short(bone.get("refusal"), 220)])
            for key, br in (bone.get("baselines") or {}).items():
                if br.get("ok"):
                    d = br["distance"]
                    rows.append(["", "", "", BASELINES[key], f"{d['mean']:.2f} / {d['p95']:.2f} / {d['max']:.2f}",
                                 f"{br['bias_mm']:+.2f}", fmt(br.get("volume_ratio"), 3),
                                 f"{br['checks'].get('genus')} / {bone['truth_genus']}",
                                 "pass" if br["checks"]["ok"] else "fail", "", ""])
                else:
                    rows.append(["", "", "", BASELINES[key], "FAILED: " + short(br.get("error"), 100), "", "", "", "", "", ""])
        L += [md_table(["bone", "truth area < 1 / < 2 mm thick (%)", "truth ml", "method", "mean / p95 / max mm",
                        "bias mm", "vol ratio", "genus (surface / truth)", "checks", "on neighbour", "warnings / refusal"],
                       rows), ""]
        cf = info.get("ct_figures") or {}
        figs = []
        for name, c in cf.items():
            p1 = c.get("plate_0-1mm_mid_HU_p10_p50_p90")
            p2 = c.get("plate_1-2mm_mid_HU_p10_p50_p90")
            tc = c.get("thick_cortex_peak_HU_p10_p50_p90")
            figs.append(f"{name}: plates < 1 mm {fmt(p1[1], 0) if p1 else '-'} HU (median at the plate's middle), "
                        f"1-2 mm {fmt(p2[1], 0) if p2 else '-'} HU, thick cortex peak {fmt(tc[1], 0) if tc else '-'} HU")
        if figs:
            L += ["What the CT shows: " + "; ".join(figs) + ".", ""]
        if (r.get("figures") or {}).get("sections"):
            L += [f"![{case}]({r['figures']['sections']})", ""]
    return L


def run_anatomical(results, args, save, log_fn=log):
    """Benchmark part (Testing/benchmark.py --anatomical): every case of ``args.anatomical_cases``
    into results["anatomical"], saved after each case."""
    import anatomical

    anat = results.setdefault("anatomical", {})
    cases = args.anatomical_cases
    missing = [c for c in cases if anatomical.CASES[c].get("source", "pelvis") == "pelvis"
               and not anatomical.data_available("pelvis")]
    if missing:
        anat["_skipped_cases"] = f"no real CT data ({anatomical.data_dir()} absent): {', '.join(missing)} skipped"
        log_fn(f"[anatomical] {anat['_skipped_cases']}")
    for case in cases:
        if case in missing:
            continue
        if getattr(args, "resume", False) and case in anat:
            log_fn(f"[{case}] kept from the previous run")
            continue
        t0 = time.perf_counter()
        anat[case] = run_case(case, args)
        anat[case]["seconds"] = time.perf_counter() - t0
        save(results, args)
    return anat


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="bench_anatomical")
    ap.add_argument("--cases", default=None, help=f"comma-separated (default: {','.join(CASES)})")
    ap.add_argument("--quick", action="store_true", help="the bundled sample only, 20k samples")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--samples", type=int, default=None, help="area samples per surface and direction")
    ap.add_argument("--timeout", type=float, default=3600.0)
    ap.add_argument("--build", nargs=3, metavar=("CASE", "SEED", "DIR"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.build:
        _build_here(args.build[0], int(args.build[1]), args.build[2])
        return 0
    args.out_dir = os.path.abspath(args.out)
    os.makedirs(args.out_dir, exist_ok=True)
    args.anatomical_cases = ([c.strip() for c in args.cases.split(",") if c.strip()] if args.cases else
                             (QUICK_CASES if args.quick else CASES))
    args.samples = args.samples or (20_000 if args.quick else 100_000)
    results = {"meta": {"started": time.strftime("%Y-%m-%d %H:%M:%S"), "seed": args.seed,
                        "samples": args.samples, "load_start": _load()}}

    def save(res, a):
        res["meta"]["load_now"] = _load()
        with open(os.path.join(a.out_dir, "anatomical.json.tmp"), "w") as fh:
            json.dump(jsonable(res), fh, indent=1, default=str)
        os.replace(os.path.join(a.out_dir, "anatomical.json.tmp"), os.path.join(a.out_dir, "anatomical.json"))
        with open(os.path.join(a.out_dir, "ANATOMICAL.md"), "w") as fh:
            fh.write("\n".join(report_lines(res.get("anatomical") or {})) + "\n")

    run_anatomical(results, args, save)
    results["meta"]["finished"] = time.strftime("%Y-%m-%d %H:%M:%S")
    save(results, args)
    log(f"wrote {os.path.join(args.out_dir, 'ANATOMICAL.md')}")
    return 0


def _load():
    try:
        return " ".join(open("/proc/loadavg").read().split()[:3])
    except OSError:
        return "?"


if __name__ == "__main__":
    sys.exit(main())
