"""Part 3 of the benchmark: real CT (/work/shared/data), used by Testing/benchmark.py --real.

Every bone above 20 ml with a reference label, in the runs a user would make (several bones of
one segmentation in one run, every other label a neighbour), at the pipeline's defaults with
``on_implausible="warn"`` (a surface the default would refuse is kept and marked), plus the
20-slice case's T11 / T12 / humeri (cut by the slab: capped). The reference of a bone is the
flying-edges surface of its label at 0.5 on the label's own grid (padded by one voxel, so a
bone cut by the image closes exactly at the image boundary, as the pipeline's cap does), in
physical LPS; its volume is the label's voxel count x voxel volume. The references are
TotalSegmentator predictions (see each folder's PROVENANCE.md), a loose check, not ground truth.

Baselines per bone, each in its own process: threshold + MC + smoothing, direct Poisson and
closing wrap on the bone's label (they refuse a segment touching the CT border, so for a cut
bone the CT is padded with 2 voxels of air and the mask with zeros: the threshold surface then
closes at the image boundary, like a padded segment in 3D Slicer), and the label's own closed
surface (Slicer's conversion). Also the refusal test of issue 9: ``--h0 900 --ht 700`` on L4.
"""

from __future__ import annotations

import csv
import os

import numpy as np

from bench_common import (check, fmt, md_table, reference_metrics, render_distance, render_sections,
                          short, verdict)
from bench_worker import run_isolated

DATA = "/work/shared/data"
PELVIS = "ts_example_ct_abdomen_pelvis_3mm"
AORTA = "ts_aorta_report_ct_cropped_1p5mm"
SLAB = "ts_example_ct_dicom_20slices"
MIN_ML = 20.0

# (run name, folder, label map, targets, what it shows)
RUNS = [
    ("pelvis_L1-L5", PELVIS, "bones_labels.nrrd", [31, 30, 29, 28, 27], "lumbar chain in one run"),
    ("pelvis_right", PELVIS, "bones_labels.nrrd", [76, 78, 25], "femur + hip + sacrum (right) in one run"),
    ("pelvis_left_metal", PELVIS, "bones_labels.nrrd", [75, 77], "femur (metal implant) + hip (left)"),
    ("pelvis_T12", PELVIS, "bones_labels.nrrd", [32], "T12 (the other bones above 20 ml)"),
    ("pelvis_S1", PELVIS, "bones_labels.nrrd", [26], "S1"),
    ("aorta1p5_T12", AORTA, "vertebra_T12_labels.nrrd", [32], "1.5 mm contrast CTA, T12 (only label)"),
    ("slab_T11-T12", SLAB, "bones_labels.nrrd", [33, 32], "20-slice slab: T11 + T12 (capped)"),
    ("slab_humerus_left", SLAB, "bones_labels.nrrd", [69], "20-slice slab: left humerus shaft (capped)"),
    ("slab_humerus_right", SLAB, "bones_labels.nrrd", [70], "20-slice slab: right humerus shaft (capped)"),
]
QUICK_RUNS = ["pelvis_T12"]
BASELINES = ["threshold_mc", "direct_poisson", "closing_wrap", "segment"]
BASE_LABELS = {"threshold_mc": "threshold + MC + smoothing", "direct_poisson": "direct Poisson",
               "closing_wrap": "closing wrap (2 mm)", "segment": "label's closed surface (Slicer)"}


def _names(folder):
    out = {}
    try:
        with open(os.path.join(DATA, folder, "labels.csv")) as fh:
            for row in csv.DictReader(fh):
                out[int(row["value"])] = row["name"]
    except OSError:
        pass
    return out


def label_reference(lab_img, value):
    """Flying edges of (label == value) at 0.5 on the label's grid (padded), physical LPS;
    and the label's volume (ml)."""
    import SimpleITK as sitk
    import vtk
    from vtk.util import numpy_support as ns

    from BoneWatertightLib.mesh import Surface, from_polydata
    from BoneWatertightLib.mesh.surface import enclosed_volume

    arr = sitk.GetArrayViewFromImage(lab_img) == value
    nz = np.argwhere(arr)
    lo, hi = nz.min(0), nz.max(0) + 1  # (k, j, i)
    crop = np.pad(arr[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].astype(np.float32), 1)
    img = vtk.vtkImageData()
    img.SetDimensions(*[int(v) for v in crop.shape[::-1]])
    img.GetPointData().SetScalars(ns.numpy_to_vtk(crop.ravel(), deep=True))
    fe = vtk.vtkFlyingEdges3D()
    fe.SetInputData(img)
    fe.SetValue(0, 0.5)
    fe.ComputeNormalsOff()
    fe.Update()
    s = from_polydata(fe.GetOutput())
    ijk = s.vertices + (lo[::-1] - 1)
    D = np.array(lab_img.GetDirection(), float).reshape(3, 3)
    v = np.array(lab_img.GetOrigin()) + (ijk * np.array(lab_img.GetSpacing())) @ D.T
    f = s.faces
    if enclosed_volume(v, f) < 0:
        f = f[:, ::-1].copy()
    ml = float(arr.sum() * np.prod(lab_img.GetSpacing()) / 1000.0)
    touches = bool(lo.min() == 0 or np.any(hi == np.array(arr.shape)))
    return Surface(v, f), ml, touches


def run_real(results, args, save, log):
    import SimpleITK as sitk

    from BoneWatertightLib.mesh import Surface

    global DATA
    data = args.data or DATA
    DATA = data
    real = results.setdefault("real", {})
    if not os.path.isdir(data):
        real["_skipped"] = f"no real CT: {data} is absent"
        log(f"[real] skipped: {data} is absent")
        save(results, args)
        return
    wanted = [r.strip() for r in args.real_runs.split(",")] if args.real_runs else (
        QUICK_RUNS if args.quick else [r[0] for r in RUNS])
    from benchmark import _workdir, params_dict, pipeline_summary, run_row, _cli_run
    for name, folder, labfile, targets, what in RUNS:
        if name not in wanted:
            continue
        if args.resume and name in real:
            log(f"[real {name}] kept from the previous run")
            continue
        ct_path = os.path.join(data, folder, "ct.nrrd")
        lab_path = os.path.join(data, folder, labfile)
        if not (os.path.exists(ct_path) and os.path.exists(lab_path)):
            real[name] = {"skipped": f"{folder} incomplete"}
            continue
        rdir = os.path.join(args.out_dir, "real", name)
        os.makedirs(rdir, exist_ok=True)
        ct = sitk.ReadImage(ct_path)
        lab = sitk.ReadImage(lab_path)
        names = _names(folder)
        log(f"[real {name}] pipeline, targets {[names.get(t, t) for t in targets]} ...")
        res = run_isolated({"kind": "many", "ct": ct_path, "labels": lab_path, "targets": targets,
                            "neighbours": "auto", "names": names, "params": params_dict(args)},
                           args.timeout, _workdir(args))
        run = {"name": name, "folder": folder, "what": what, "targets": targets,
               "ct_spacing": list(ct.GetSpacing()), "ct_size": list(ct.GetSize()),
               **run_row("pipeline", res), "bones": [], "pairs": res.get("pairs") or [],
               "joint_timings": (res.get("joint") or {}).get("timings"),
               "thresholds": (res.get("joint") or {}).get("thresholds"),
               "neighbours": (res.get("joint") or {}).get("neighbours"), "figures": {}}
        log(f"[real {name}] pipeline: {fmt(res.get('seconds'), 1)} s, {fmt(res.get('peak_rss_mb'), 0)} MB"
            + ("" if res.get("ok") else " FAILED " + short(res.get("error"), 200)))
        ours_by = {b.get("label"): b for b in res.get("bones", [])}
        run_surfaces = {}
        for value in targets:
            bname = names.get(value, str(value))
            ref, ml, touches = label_reference(lab, value)
            row = {"label": value, "name": bname, "reference_ml": ml, "cut_by_image": touches,
                   "baselines": {}}
            b = ours_by.get(value)
            if b is None or not b.get("ok"):
                row["ok"] = False
                row["error"] = (b or {}).get("error") or res.get("error")
            else:
                row["ok"] = True
                v, f = b["vertices"], b["faces"]
                row["checks"] = check(v, f)
                m = reference_metrics(v, f, ref, args.samples, ml, b.get("cap"))
                vd = m.pop("_vertex_distance")
                row.update(m)
                row["n_faces"] = int(len(f))
                row["pipeline"] = pipeline_summary(b.get("report"))
                s = Surface(v, f)
                run_surfaces[bname] = s
                pic = os.path.join(rdir, f"{bname}.png")
                p, why = render_distance(s, pic, ct, f"{name}: {bname}, distance to the reference label "
                                         "surface", vd, "distance to reference", (0.0, 3.0))
                if p:
                    row["figure"] = f"real/{name}/{bname}.png"
                else:
                    row["figure_error"] = why
            # baselines
            mask_path = os.path.join(rdir, f"mask_{bname}.nrrd")
            sitk.WriteImage(sitk.Cast(sitk.Equal(lab, value), sitk.sitkUInt8), mask_path, False)
            base_surf = {}
            for bl in BASELINES:
                if args.methods and bl not in args.methods and not (bl == "segment" and "label" in args.methods):
                    continue
                if bl == "segment":
                    task = {"kind": "segment_surface", "labels": lab_path, "value": value}
                else:
                    task = {"kind": "baseline", "method": bl, "ct": ct_path, "mask": mask_path,
                            "params": params_dict(args), "pad_air": 2 if touches else 0}
                r = run_isolated(task, args.timeout, _workdir(args))
                br = run_row(bl, r)
                br["padded"] = bool(touches and bl != "segment")
                if r.get("ok") and len(r["bones"][0]["faces"]):
                    bv, bf = r["bones"][0]["vertices"], r["bones"][0]["faces"]
                    br["checks"] = check(bv, bf)
                    mm = reference_metrics(bv, bf, ref, args.samples, ml)
                    mm.pop("_vertex_distance")
                    br.update(mm)
                    br["n_faces"] = int(len(bf))
                    base_surf[bl] = Surface(bv, bf)
                elif r.get("ok"):
                    br["ok"] = False
                    br["error"] = "empty surface"
                row["baselines"][bl] = br
            # cross-sections: ours, the reference, the label's closed surface
            if row.get("ok"):
                ss = {"pipeline": run_surfaces[bname], "reference (label, FE 0.5)": ref}
                if "segment" in base_surf:
                    ss["label closed surface (Slicer)"] = base_surf["segment"]
                if "threshold_mc" in base_surf:
                    ss["threshold + MC"] = base_surf["threshold_mc"]
                p, why = render_sections(ct, ss, os.path.join(rdir, f"{bname}_sections.png"),
                                         run_surfaces[bname].vertices.mean(axis=0),
                                         f"{name}: {bname} over the CT")
                if p:
                    row["sections"] = f"real/{name}/{bname}_sections.png"
            d = row.get("distance") or {}
            log(f"[real {name}] {bname}: " + (f"p95 {fmt(d.get('p95'))} max {fmt(d.get('max'))} vol "
                                              f"{fmt(row.get('volume_ratio'))} checks {row['checks']['ok']} "
                                              f"warnings {len(row['pipeline']['warnings'])}"
                                              if row.get("ok") else "FAILED " + short(row.get("error"), 200)))
            run["bones"].append(row)
        if len(run_surfaces) > 1:
            centre = np.mean([s.vertices.mean(axis=0) for s in run_surfaces.values()], axis=0)
            p, why = render_sections(ct, run_surfaces, os.path.join(rdir, "all_sections.png"), centre,
                                     f"{name}: every bone of the run over the CT")
            if p:
                run["figures"]["all"] = f"real/{name}/all_sections.png"
        real[name] = run
        save(results, args)
    # issue 9: thresholds far too high are refused, no file written
    if "refusal_L4" not in real or not args.resume:
        seg = os.path.join(data, PELVIS, "bones.seg.nrrd")
        if os.path.exists(seg):
            rdir = os.path.join(args.out_dir, "real", "refusal_L4")
            os.makedirs(rdir, exist_ok=True)
            log("[real] refusal test: --h0 900 --ht 700 on vertebrae_L4 ...")
            out = os.path.join(rdir, "L4.vtp")
            cli = _cli_run(os.path.join(data, PELVIS, "ct.nrrd"), seg, "vertebrae_L4", out,
                           os.path.join(rdir, "L4.json"), _AtDefaults(args), extra=["--h0", "900", "--ht", "700"])
            real["refusal_L4"] = {"exit_code": cli.get("exit_code"), "file_written": cli.get("out_exists"),
                                  "message": short(cli.get("log"), 600), "seconds": cli.get("seconds"),
                                  "argv": cli.get("argv")}
            log(f"[real] refusal: exit {cli.get('exit_code')}, file {cli.get('out_exists')}: "
                f"{short(cli.get('log'), 200)}")
            save(results, args)


class _AtDefaults:
    """The benchmark's arguments without --spacing (the refusal test uses the CLI's own
    defaults and only the thresholds it names)."""

    def __init__(self, args):
        self.__dict__.update(vars(args))
        self.spacing = None


# ---------------------------------------------------------------------------- targets / report

def _bone_ok(b, p95, mx, lo, hi):
    if not b.get("ok"):
        return False, f"{b['name']} FAILED"
    d = b["distance"]
    gate = not ((b.get("pipeline") or {}).get("plausibility") or {}).get("problems")
    ok = b["checks"]["ok"] and gate and d["p95"] <= p95 and d["max"] <= mx and lo <= b["volume_ratio"] <= hi
    return ok, (f"{b['name']} {d['p95']:.2f}/{d['max']:.2f}/{b['volume_ratio']:.2f}"
                + ("" if b["checks"]["ok"] else " checks FAIL") + ("" if gate else " gate FAILS"))


def targets(real):
    T = []
    if not real:
        return T
    if real.get("_skipped"):
        return [("9, 10", "real CT targets", real["_skipped"], None)]
    pel = [(n, r) for n, r in real.items() if n.startswith("pelvis_") and isinstance(r, dict) and r.get("bones")]
    bones = [b for _, r in pel for b in r["bones"] if b["reference_ml"] > MIN_ML]
    if bones:
        res = [_bone_ok(b, 3.0, 6.0, 0.85, 1.15) for b in bones]
        T.append(("9", "3 mm pelvis CT, defaults: every labelled bone above 20 ml passes every check (and "
                       "the plausibility gates), p95 ≤ 3 mm, max ≤ 6 mm to the reference, volume 0.85–1.15 "
                       "(figures: p95 / max / volume ratio)",
                  f"{sum(o for o, _ in res)} of {len(res)} bones: " + "; ".join(w for _, w in res),
                  all(o for o, _ in res)))
    for run_name, text in (("pelvis_right", "femur, hip bone and sacrum in one run"),
                           ("pelvis_left_metal", "left femur (metal) + hip bone in one run"),
                           ("pelvis_L1-L5", "L1–L5 in one run (the issue's L3–L5 inside it)")):
        r = real.get(run_name)
        if not r or not r.get("bones"):
            continue
        res = [_bone_ok(b, 3.0, 6.0, 0.85, 1.15) for b in r["bones"]]
        pairs = r.get("pairs") or []
        inter = sum((p.get("crossing_face_pairs") or 0) + (p.get("a_inside_b") or 0) + (p.get("b_inside_a") or 0)
                    for p in pairs)
        ok = all(o for o, _ in res) and inter == 0 and len(pairs) == len(r["bones"]) * (len(r["bones"]) - 1) // 2
        T.append(("10", f"real 3 mm pelvis, {text}: every check, p95 ≤ 3, max ≤ 6 mm, volume 0.85–1.15, "
                        "no interpenetration",
                  "; ".join(w for _, w in res) + f"; {len(pairs)} pairs checked, interpenetration {inter}"
                  + ("" if r.get("ok") else f"; run FAILED: {short(r.get('error'), 100)}"), ok))
    ref = real.get("refusal_L4")
    if ref:
        ok = ref.get("exit_code") == 3 and not ref.get("file_written")
        T.append(("9", "`--h0 900 --ht 700` on L4: refused with a reason, no file",
                  f"exit {ref.get('exit_code')}, file written: {'yes' if ref.get('file_written') else 'no'}; "
                  f"\"{short(ref.get('message'), 220)}\"", ok))
    hi = [b for n, r in real.items() if (n.startswith("slab_") or n.startswith("aorta")) and isinstance(r, dict)
          for b in r.get("bones", [])]
    if hi:
        res = [_bone_ok(b, 2.5, 1e9, 0.8, 1.25) for b in hi]
        T.append(("9", "higher-resolution real CT (held out: 0.7 mm pixels, 2.5 mm slices; proxies here: the "
                       "0.98 × 2 mm slab's T11/T12/humeri, capped, and the 1.5 mm T12): every check, p95 ≤ "
                       "2.5 mm, volume 0.8–1.25",
                  "; ".join(w for _, w in res), all(o for o, _ in res)))
    return T


def report_lines(real):
    L = ["## 3. Real CT", ""]
    if real.get("_skipped"):
        return L + [real["_skipped"], ""]
    L += ["References: TotalSegmentator labels (not expert contours); distances are to the flying-edges "
          "surface of the label at 0.5 on its grid (a 3 mm label is itself stair-stepped by ±1.5 mm), "
          "volume ratio to the label's voxel volume. The pipeline runs at its defaults with "
          "`on_implausible=\"warn\"`; **default FAILS** marks a surface the default would have refused "
          "(the gate's reasons follow). Time = the whole run (all bones of the row's run). Baselines on "
          "bones cut by the image run on the CT padded with air (closed at the image boundary).", ""]
    head = ["bone", "ref ml", "checks", "genus", "mean / p95 / max mm", "bias", "vol ratio", "cap mm²",
            "inside / vol / max exc. / nbr overlap / edge / HT reach", "gate", "run s", "run peak MB"]
    for name, r in real.items():
        if name.startswith("_") or name == "refusal_L4" or not isinstance(r, dict):
            continue
        if r.get("skipped"):
            L += [f"### {name}: skipped ({r['skipped']})", ""]
            continue
        th = r.get("thresholds") or {}
        L += [f"### `{name}`: {r['what']} ({r['folder']}, CT {' × '.join(f'{v:g}' for v in r['ct_spacing'])} mm)", "",
              f"Thresholds (auto): H0 {fmt(th.get('h0'), 0)}, HT {fmt(th.get('ht'), 0)} HU; neighbours: "
              f"{', '.join(map(str, r.get('neighbours') or [])) or 'none'}."
              + ("" if r.get("ok") else f" **Run FAILED**: {short(r.get('error'), 300)}"), ""]
        rows = []
        for b in r["bones"]:
            if not b.get("ok"):
                rows.append([b["name"], fmt(b["reference_ml"], 1), "FAILED: " + short(b.get("error"), 160)])
                continue
            d = b["distance"]
            pl = (b.get("pipeline") or {}).get("plausibility") or {}
            cap = (b.get("pipeline") or {}).get("cap") or {}
            rows.append([b["name"] + ("" if b["reference_ml"] > MIN_ML else " (< 20 ml)") + _moved_text(b),
                         fmt(b["reference_ml"], 1),
                         "pass" if b["checks"]["ok"] else "**fail** " + short("; ".join(b["checks"]["problems"]), 60),
                         fmt(b["checks"].get("genus")), f"{d['mean']:.2f} / {d['p95']:.2f} / {d['max']:.2f}",
                         f"{b['bias_mm']:+.2f}", fmt(b["volume_ratio"], 3), fmt(cap.get("area_mm2"), 0),
                         " / ".join(fmt(pl.get(k), 2) for k in ("segment_inside_fraction", "volume_ratio",
                                                                 "max_excursion_mm", "neighbour_label_overlap",
                                                                 "edge_support", "threshold_reach")),
                         _gate(b), fmt(r.get("seconds"), 1), fmt(r.get("peak_rss_mb"), 0)])
        L += [md_table(head, rows), ""]
        pairs = r.get("pairs") or []
        if pairs:
            L += [md_table(["pair", "crossing face pairs", "a in b", "b in a", "min gap mm", "contact mm²",
                            "joint valley seen"],
                           [[f"{p['a']} / {p['b']}", fmt(p.get("crossing_face_pairs")), fmt(p.get("a_inside_b")),
                             fmt(p.get("b_inside_a")), fmt(p.get("min_gap_mm"), 2), fmt(p.get("contact_area_mm2"), 0),
                             fmt(p.get("joint_valley_seen_fraction"), 2)] for p in pairs]), ""]
        brow = []
        for b in r["bones"]:
            for key, br in b.get("baselines", {}).items():
                if not br.get("ok"):
                    brow.append([b["name"], BASE_LABELS[key], "FAILED: " + short(br.get("error"), 120)])
                    continue
                d = br["distance"]
                brow.append([b["name"], BASE_LABELS[key] + (" (padded)" if br.get("padded") else ""),
                             "pass" if br["checks"]["ok"] else "fail (" + short("; ".join(br["checks"]["problems"]), 70) + ")",
                             f"{d['mean']:.2f} / {d['p95']:.2f} / {d['max']:.2f}", fmt(br["volume_ratio"], 3),
                             fmt(br.get("seconds"), 2)])
        if brow:
            L += ["Baselines:", "", md_table(["bone", "method", "checks", "mean / p95 / max mm", "vol ratio",
                                               "time s"], brow), ""]
        for b in r["bones"]:
            for key in ("figure", "sections"):
                if b.get(key):
                    L.append(f"![{b['name']} {key}]({b[key]})")
        if r.get("figures", {}).get("all"):
            L.append(f"![{name}]({r['figures']['all']})")
        L.append("")
    ref = real.get("refusal_L4")
    if ref:
        L += ["### Thresholds far too high (issue 9)", "",
              f"`bonewatertight {' '.join(ref.get('argv') or [])}` → exit **{ref.get('exit_code')}**, surface "
              f"file written: **{'yes' if ref.get('file_written') else 'no'}**, message:", "", "```",
              (ref.get("message") or "").strip(), "```", ""]
    return L


def _moved_text(b):
    """' (+6.0 ml ...)': what the ownership moved between this bone's label and a neighbour's
    (the reference is the label as it was, so its distances count the moved part)."""
    own = (b.get("pipeline") or {}).get("ownership") or {}
    out = ""
    if own.get("segment_taken_ml"):
        out += (f" (+{own['segment_taken_ml']:.1f} ml of a neighbour's label that lies in this "
                "bone: the reference lacks it)")
    if own.get("segment_given_ml"):
        out += (f" (-{own['segment_given_ml']:.1f} ml of its label, in a neighbour's bone: the "
                "reference holds it)")
    return out


def _gate(b):
    from bench_common import gate_text

    return gate_text(b.get("pipeline"))


def verdicts(real):  # pragma: no cover - convenience for interactive use
    return [(a, b, c, verdict(d)) for a, b, c, d in targets(real)]
