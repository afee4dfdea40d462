"""Issue 21 measured: every bone of a synthetic labelled chest CT (Testing/chest_phantom.py) in one
run of the command line at its defaults, against the phantom's exact truth.

    python Testing/bench_chest.py --seed 0                                   # 512 x 512 x 300, 0.7 x 0.7 x 1 mm
    python Testing/bench_chest.py --seed 0 --shape 512,512,120 --spacing 0.7,0.7,2.5 --tag 2p5mm

1. The phantom is built in its own process (``--build``; time and peak memory of that process)
   into ``<work>/<tag>_s<seed>/``: ct.nrrd, labels.nrrd + labels.csv (value,name, so the surfaces
   are named), truths.npz, info.json; kept while the generator's source and the arguments are
   unchanged.
2. ``bonewatertight --ct ct.nrrd --seg labels.nrrd --all-labels --out 'out/{label}.stl'
   --report report.json`` in a child process under ``/usr/bin/time -v`` (wall time, peak RSS of
   the child), cwd the case folder: the defaults, as a user would type it.
3. Per bone: written or refused (the report's reason), volume ratio to the truth, distances to
   the truth (area samples on both surfaces, exact point-to-triangle, both directions pooled:
   mean / p95 / max), genus, the report's warnings. Per pair of written bones whose boxes come
   within 3 mm: crossing faces and the smallest gap (BoneWatertightLib.stages.contacts.pair_report)
   and, independently, vertices of one inside the other (Testing/metrics.TriangleLocator).
4. ``<doc>/chest_<tag>_s<seed>.json`` (the numbers) and ``<doc>/CHEST.md`` (every json there as
   tables), ``<doc>/chest_<tag>_s<seed>_axial.png`` (CT slices with the written surfaces' and
   the truths' cross-sections) and ``_zoom.png`` (joints up close).

Nothing here judges the library beyond the issue's stated targets (<= 10 min, <= 4 GB, every bone
written or refused with a reason, no interpenetration).
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

from bench_common import (check, fmt, jsonable, md_table, short, truth_metrics,  # noqa: E402
                          write_phantom)

CLI = os.path.join(ROOT, ".venv", "bin", "bonewatertight")
DOC = os.path.join(ROOT, "Resources", "Benchmark", "chest")
TARGET_S, TARGET_GB = 600.0, 4.0


def log(msg):
    print(time.strftime("%H:%M:%S"), msg, flush=True)


def _ints(s):
    return tuple(int(v) for v in s.split(","))


def _floats(s):
    return tuple(float(v) for v in s.split(","))


def _time_v(path):
    """Wall seconds, peak RSS (MB) and exit status from a /usr/bin/time -v output file."""
    out = {}
    if not os.path.exists(path):
        return out
    for line in open(path):
        line = line.strip()
        if line.startswith("Elapsed (wall clock) time"):
            t = line.split("):", 1)[1].strip() if "):" in line else line.rsplit(" ", 1)[-1]
            parts = [float(p) for p in t.split(":")]
            sec = 0.0
            for p in parts:
                sec = sec * 60.0 + p
            out["wall_s"] = sec
        elif line.startswith("Maximum resident set size"):
            out["peak_rss_mb"] = float(line.rsplit(":", 1)[1]) / 1024.0
        elif line.startswith("Exit status"):
            out["exit_status"] = int(line.rsplit(":", 1)[1])
        elif line.startswith("User time"):
            out["user_s"] = float(line.rsplit(":", 1)[1])
        elif line.startswith("System time"):
            out["system_s"] = float(line.rsplit(":", 1)[1])
    return out


# ---------------------------------------------------------------------------- build

def _build_here(cdir, seed, shape, spacing):
    import SimpleITK as sitk

    import chest_phantom

    t0 = time.perf_counter()
    ph = chest_phantom.make_chest(seed, shape=shape, spacing=spacing)
    seconds = time.perf_counter() - t0
    with open(os.path.join(cdir, "labels.csv"), "w") as fh:
        fh.write("value,name\n")
        for k in sorted(ph.names):
            fh.write(f"{k},{ph.names[k]}\n")
    lab = sitk.GetArrayViewFromImage(ph.labels)
    write_phantom(cdir, ph, seconds, label_voxels={
        str(k): int(v) for k, v in zip(*np.unique(lab, return_counts=True)) if k})


def build(cdir, seed, shape, spacing, timeout=3600):
    os.makedirs(cdir, exist_ok=True)
    src = open(os.path.join(HERE, "chest_phantom.py"), "rb").read()
    key = hashlib.sha1(src + repr((seed, shape, spacing)).encode()).hexdigest()[:16]
    kpath = os.path.join(cdir, ".key")
    files = [os.path.join(cdir, f) for f in ("ct.nrrd", "labels.nrrd", "labels.csv", "truths.npz", "info.json")]
    if os.path.exists(kpath) and open(kpath).read() == key and all(map(os.path.exists, files)):
        rec = json.load(open(os.path.join(cdir, "build.json")))
        rec["cached"] = True
        return rec
    tpath = os.path.join(cdir, "build_time.txt")
    cmd = ["/usr/bin/time", "-v", "-o", tpath, sys.executable, os.path.abspath(__file__), "--build", cdir,
           "--seed", str(seed), "--shape", ",".join(map(str, shape)), "--spacing", ",".join(map(str, spacing))]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    rec = _time_v(tpath)
    rec["exit_code"] = proc.returncode
    if proc.returncode != 0:
        raise RuntimeError("phantom build failed: " + (proc.stderr or proc.stdout)[-2000:])
    with open(kpath, "w") as fh:
        fh.write(key)
    with open(os.path.join(cdir, "build.json"), "w") as fh:
        json.dump(rec, fh)
    rec["cached"] = False
    return rec


# ---------------------------------------------------------------------------- CLI

def run_cli(cdir, timeout):
    import shutil

    out_dir = os.path.join(cdir, "out")
    if os.path.isdir(out_dir):
        shutil.rmtree(out_dir)
    rep = os.path.join(cdir, "report.json")
    if os.path.exists(rep):
        os.unlink(rep)
    argv = [CLI, "--ct", "ct.nrrd", "--seg", "labels.nrrd", "--all-labels", "--out", "out/{label}.stl",
            "--report", "report.json"]
    tpath = os.path.join(cdir, "cli_time.txt")
    t0 = time.perf_counter()
    with open(os.path.join(cdir, "cli.log"), "w") as fh:
        try:
            proc = subprocess.run(["/usr/bin/time", "-v", "-o", tpath] + argv, cwd=cdir, stdout=fh,
                                  stderr=subprocess.STDOUT, timeout=timeout)
            code = proc.returncode
        except subprocess.TimeoutExpired:
            code = None
    rec = _time_v(tpath)
    rec["exit_code"] = code
    rec["measured_wall_s"] = time.perf_counter() - t0
    rec["argv"] = ["bonewatertight"] + argv[1:]
    return rec


def _library_version():
    """The commit of the work tree the CLI ran from, and whether the library had uncommitted
    changes then (another engineer works in the same tree)."""
    def git(*a):
        try:
            return subprocess.run(["git"] + list(a), cwd=ROOT, capture_output=True, text=True, timeout=30).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""
    return {"commit": git("rev-parse", "--short", "HEAD"),
            "library_uncommitted": bool(git("status", "--porcelain", "--", "BoneWatertightLib"))}


# ---------------------------------------------------------------------------- evaluation

def _read_stl(path):
    import vtk

    from BoneWatertightLib.mesh import from_polydata

    r = vtk.vtkSTLReader()
    r.SetFileName(path)
    r.MergingOn()
    r.Update()
    return from_polydata(r.GetOutput())


def _spacing_info(report):
    """What the report says of the working grid and the fallbacks."""
    out = {}
    if not isinstance(report, dict):
        return out
    joint = report.get("joint") or {}
    out["joint_input"] = joint.get("input")
    out["joint_fallbacks"] = joint.get("fallbacks")
    out["joint_thresholds"] = joint.get("thresholds")
    out["joint_timings"] = joint.get("timings")
    surf = report.get("surfaces") or []
    if surf:
        pipe = surf[0].get("pipeline") or {}
        out["first_input"] = pipe.get("input")
    fb = {}
    for s in surf:
        for f in (s.get("pipeline") or {}).get("fallbacks") or []:
            key = f"{f.get('stage')}: {f.get('what')}"
            rec = fb.setdefault(key, {"bones": 0, "count": 0, "unit": f.get("unit")})
            rec["bones"] += 1
            rec["count"] += int(f.get("count") or 0)
    out["bone_fallbacks"] = fb
    return out


def evaluate(cdir, samples):
    from BoneWatertightLib.mesh import Surface
    from bench_common import inside_of, pair_measures

    info = json.load(open(os.path.join(cdir, "info.json")))
    names = {int(k): v for k, v in info["names"].items()}
    z = np.load(os.path.join(cdir, "truths.npz"))
    truths = {int(k[1:]): Surface(z[k], z["f" + k[1:]], "LPS") for k in z.files if k.startswith("v")}
    rep_path = os.path.join(cdir, "report.json")
    report = json.load(open(rep_path)) if os.path.exists(rep_path) else None
    failed, warnings, bone_reports = {}, {}, {}
    if isinstance(report, dict):
        for f in report.get("failed") or []:
            failed[str(f.get("segment"))] = f.get("error")
        for s in report.get("surfaces") or []:
            nm = str((s.get("inputs") or {}).get("segment_name"))
            pipe = s.get("pipeline") or {}
            warnings[nm] = pipe.get("warnings") or []
            bone_reports[nm] = {"cap_area_mm2": (pipe.get("cap") or {}).get("area_mm2"),
                                "checks_ok": (pipe.get("checks") or {}).get("ok"),
                                "volume_ml": (pipe.get("volume_mm3") or 0) / 1000.0}
    log_text = open(os.path.join(cdir, "cli.log")).read() if os.path.exists(os.path.join(cdir, "cli.log")) else ""
    rows, surfaces = [], {}
    for lv in sorted(names):
        name = names[lv]
        row = {"label": lv, "name": name, "truth_ml": info["bones"][name].get("volume_ml"),
               "truth_genus": info["bones"][name].get("genus"),
               "label_ml": info.get("label_voxels", {}).get(str(lv), 0) * float(np.prod(info["spacing"])) / 1000.0}
        path = os.path.join(cdir, "out", f"{name}.stl")
        if os.path.exists(path):
            s = _read_stl(path)
            surfaces[lv] = s
            row["outcome"] = "written"
            row["checks"] = check(s.vertices, s.faces)
            row.update(truth_metrics(s.vertices, s.faces, truths[lv], samples))
            row["warnings"] = warnings.get(name) or []
            row.update(bone_reports.get(name) or {})
        else:
            row["outcome"] = "refused" if name in failed else "missing"
            row["reason"] = failed.get(name) or _log_reason(log_text, name)
        d = row.get("distance") or {}
        log(f"  {name}: " + (f"mean {fmt(d.get('mean'))} p95 {fmt(d.get('p95'))} max {fmt(d.get('max'))} "
                             f"vol {fmt(row.get('volume_ratio'))}" if row["outcome"] == "written"
                             else f"{row['outcome'].upper()}: {short(row.get('reason'), 200)}"))
        rows.append(row)
    # pairs of written bones whose boxes come within 3 mm
    pairs = []
    labs = sorted(surfaces)
    boxes = {lv: (surfaces[lv].vertices.min(0), surfaces[lv].vertices.max(0)) for lv in labs}
    truth_gap = {(j["a"], j["b"]): j.get("min_distance_mm") for j in info.get("joints") or []}
    for i, a in enumerate(labs):
        for b in labs[i + 1:]:
            lo = np.maximum(boxes[a][0], boxes[b][0])
            hi = np.minimum(boxes[a][1], boxes[b][1])
            if np.any(hi < lo - 3.0):
                continue
            pm = pair_measures(surfaces[a], surfaces[b])
            ia = inside_of(surfaces[a].vertices, surfaces[b])
            ib = inside_of(surfaces[b].vertices, surfaces[a])
            tg = truth_gap.get((names[a], names[b]), truth_gap.get((names[b], names[a])))
            pairs.append({"a": names[a], "b": names[b], "min_gap_mm": pm.get("min_gap_mm"),
                          "crossing_face_pairs": pm.get("crossing_face_pairs"),
                          "a_in_b": ia["inside"], "b_in_a": ib["inside"],
                          "deepest_mm": min(ia["min_signed_mm"], ib["min_signed_mm"]),
                          "truth_gap_mm": tg})
    return {"bones": rows, "pairs": pairs, "report_info": _spacing_info(report),
            "report_pairs": [{k: p.get(k) for k in ("a", "b", "min_gap_mm", "crossing_face_pairs",
                                                    "joint_valley_seen_fraction", "warnings")}
                             for p in ((report or {}).get("pairs") or []) if p.get("min_gap_mm") is not None]
            if isinstance(report, dict) else None,
            "log_tail": log_text[-3000:]}, surfaces, truths, names


def _log_reason(text, name):
    lines = [ln.strip() for ln in (text or "").splitlines() if name in ln and re.search(r"error|fail|refus", ln, re.I)]
    return lines[0] if lines else "no surface and no reason in the report"


EDGE_VARIANTS = (("default (auto edge level)", []), ("--edge-level 0.5", ["--edge-level", "0.5"]),
                 ("--edge-level 0.9", ["--edge-level", "0.9"]), ("--no-refine-edges", ["--no-refine-edges"]))
EDGE_BONES = ("rib_left_6", "vertebrae_T6", "sternum", "humerus_left")


def edge_variants(cdir, samples):
    """Where the edge refinement puts thin- and thick-cortex bones: the CLI on a few bones
    together, at its defaults and with the edge level fixed or the refinement off; bias, volume
    ratio and p95 distance to the truth."""
    from BoneWatertightLib.mesh import Surface

    info = json.load(open(os.path.join(cdir, "info.json")))
    lab = {v: int(k) for k, v in info["names"].items()}
    z = np.load(os.path.join(cdir, "truths.npz"))
    out = []
    for tag, extra in EDGE_VARIANTS:
        odir = os.path.join(cdir, "edge_" + re.sub(r"[^a-z0-9.]+", "_", tag.lower()).strip("_"))
        argv = [CLI, "--ct", "ct.nrrd", "--seg", "labels.nrrd"] + sum([["--label", n] for n in EDGE_BONES], []) \
            + ["--out", os.path.join(odir, "{label}.stl"), "-q"] + extra
        t0 = time.perf_counter()
        proc = subprocess.run(argv, cwd=cdir, capture_output=True, text=True)
        rec = {"variant": tag, "argv": ["bonewatertight"] + argv[1:], "exit_code": proc.returncode,
               "seconds": time.perf_counter() - t0, "bones": {}}
        for n in EDGE_BONES:
            p = os.path.join(odir, f"{n}.stl")
            if os.path.exists(p):
                s = _read_stl(p)
                k = lab[n]
                m = truth_metrics(s.vertices, s.faces, Surface(z[f"v{k}"], z[f"f{k}"]), samples)
                rec["bones"][n] = {"bias_mm": m["bias_mm"], "volume_ratio": m["volume_ratio"],
                                   "p95": m["distance"]["p95"], "mean": m["distance"]["mean"]}
        log(f"  edge variant {tag}: exit {proc.returncode}, " + "; ".join(
            f"{n} bias {fmt(b['bias_mm'], 2)} vol {fmt(b['volume_ratio'], 3)}" for n, b in rec["bones"].items()))
        out.append(rec)
    return out


# ---------------------------------------------------------------------------- pictures

def _save_png(fig, path, colors=96):
    """Save a matplotlib figure as a palette PNG (small)."""
    import io

    from PIL import Image

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=fig.dpi)
    buf.seek(0)
    im = Image.open(buf).convert("RGB").quantize(colors=colors, method=Image.Quantize.MEDIANCUT)
    im.save(path, optimize=True)


def pictures(cdir, prefix, surfaces, truths, names, info):
    import SimpleITK as sitk
    from matplotlib.collections import LineCollection

    from bench_common import plane_segments, plt, to_index

    p = plt()
    ct = sitk.ReadImage(os.path.join(cdir, "ct.nrrd"))
    arr = sitk.GetArrayViewFromImage(ct)
    sp = np.array(ct.GetSpacing())
    size = np.array(ct.GetSize())
    origin = np.array(ct.GetOrigin())
    # a-frame heights of interest -> physical z (identity direction: z index = (z_phys - o) / sp)
    # the vertebrae's heights (anatomy frame) in physical z (= a + P_ANAT; the CT's direction is
    # the identity here, so an axial slice is a plane of constant z)
    import chest_phantom
    zphys = {v["k"]: v["zc"] + chest_phantom.P_ANAT[2] for v in info["vertebrae"]}
    hum = [lv for lv, n in names.items() if n == "humerus_left"][0]
    z_gh = float(truths[hum].vertices[:, 2].max()) - 22.0
    levels = [("clavicles, acromion", z_gh + 34.0), ("glenohumeral, T3/T4", z_gh), ("T7", zphys[7]),
              ("T10 (+4 mm)", zphys[10] + 4.0)]
    idx = {k: to_index(ct, s.vertices) for k, s in surfaces.items()}
    tidx = {k: to_index(ct, s.vertices + 1e-3) for k, s in truths.items()}
    fig, axs = p.subplots(2, 2, figsize=(13, 11.5), dpi=80)
    for ax, (title, zp) in zip(axs.ravel(), levels):
        k = int(np.clip(round((zp - origin[2]) / sp[2]), 0, size[2] - 1))
        ext = [-0.5 * sp[0], (size[0] - 0.5) * sp[0], -0.5 * sp[1], (size[1] - 0.5) * sp[1]]
        ax.imshow(arr[k], cmap="gray", vmin=-500, vmax=1300, origin="lower", extent=ext, interpolation="nearest")
        for col, lw, src in (("lime", 1.2, tidx), ("red", 0.7, idx)):
            for lv, iv in src.items():
                seg = plane_segments(iv, (truths if src is tidx else surfaces)[lv].faces, 2, float(k))
                if len(seg):
                    xy = np.stack([seg[..., 0] * sp[0], seg[..., 1] * sp[1]], -1)
                    ax.add_collection(LineCollection(xy, colors=[col], linewidths=lw))
        ax.set_title(f"axial k={k} ({title})", fontsize=10)
        ax.set_xlabel("i (mm), patient's right on the left")
        ax.set_ylabel("j (mm), posterior up")
    fig.suptitle(f"{prefix}: CT (W 1800 / L 400), truth (green), written surfaces (red)", fontsize=11)
    fig.tight_layout()
    out1 = os.path.join(DOC, f"{prefix}_axial.png")
    _save_png(fig, out1)
    p.close(fig)
    # zooms: costovertebral joint (T6 left), glenohumeral joint, scapular blade, sternoclavicular
    by_name = {n: lv for lv, n in names.items()}

    def centre_of(name, frac=None):
        v = truths[by_name[name]].vertices
        return v.mean(0) if frac is None else v[np.argsort(v[:, 2])[int(frac * (len(v) - 1))]]

    zooms = []
    t6 = truths[by_name["vertebrae_T6"]].vertices
    zooms.append(("T6 / rib 6 left (costovertebral, costotransverse)", np.array([t6[:, 0].max() - 12.0, t6[:, 1].mean(), t6[:, 2].mean() + 3.0]), 40.0))
    zooms.append(("glenohumeral left", np.array([truths[hum].vertices[:, 0].min() + 10.0, truths[hum].vertices[:, 1].mean(), z_gh]), 40.0))
    sc = truths[by_name["scapula_left"]].vertices
    zooms.append(("scapular blade left (infraspinous fossa)", np.array([np.median(sc[:, 0]), np.median(sc[:, 1]), np.percentile(sc[:, 2], 30)]), 45.0))
    cl = truths[by_name["clavicula_left"]].vertices
    zooms.append(("sternoclavicular left", cl[np.argmin(cl[:, 0])] + np.array([-2.0, 0, 0]), 30.0))
    fig, axs = p.subplots(1, 4, figsize=(18, 5.2), dpi=80)
    for ax, (title, c, hw) in zip(axs, zooms):
        ci = to_index(ct, c[None])[0]
        k = int(np.clip(round(ci[2]), 0, size[2] - 1))
        ext = [-0.5 * sp[0], (size[0] - 0.5) * sp[0], -0.5 * sp[1], (size[1] - 0.5) * sp[1]]
        ax.imshow(arr[k], cmap="gray", vmin=-500, vmax=1300, origin="lower", extent=ext, interpolation="nearest")
        for col, lw, src in (("lime", 1.4, tidx), ("red", 1.0, idx)):
            for lv, iv in src.items():
                seg = plane_segments(iv, (truths if src is tidx else surfaces)[lv].faces, 2, float(k))
                if len(seg):
                    xy = np.stack([seg[..., 0] * sp[0], seg[..., 1] * sp[1]], -1)
                    ax.add_collection(LineCollection(xy, colors=[col], linewidths=lw))
        ax.set_xlim(ci[0] * sp[0] - hw, ci[0] * sp[0] + hw)
        ax.set_ylim(ci[1] * sp[1] - hw, ci[1] * sp[1] + hw)
        ax.set_title(f"{title}\naxial k={k}", fontsize=9)
    fig.suptitle(f"{prefix}: joints and thin bone up close (truth green, written red)", fontsize=11)
    fig.tight_layout()
    out2 = os.path.join(DOC, f"{prefix}_zoom.png")
    _save_png(fig, out2)
    p.close(fig)
    return [os.path.basename(out1), os.path.basename(out2)]


# ---------------------------------------------------------------------------- markdown

def _g(genus):
    """The genus of _genus's (genus, components)."""
    return genus[0] if isinstance(genus, (list, tuple)) else genus


def _bone_rows(res):
    rows = []
    for b in res["bones"]:
        if b["outcome"] == "written":
            d = b["distance"]
            ch = b.get("checks") or {}
            rows.append([b["name"], "written", fmt(b.get("volume_ratio"), 3), fmt(b.get("bias_mm"), 2),
                         fmt(d["mean"], 2), fmt(d["p95"], 2),
                         fmt(d["max"], 2), f"{ch.get('genus')} / {_g(b.get('truth_genus'))}",
                         "yes" if ch.get("ok") else "NO: " + short("; ".join(ch.get("problems") or []), 80),
                         short("; ".join(b.get("warnings") or []), 160) or "-"])
        else:
            rows.append([b["name"], f"**{b['outcome']}**", "-", "-", "-", "-", "-", f"- / {_g(b.get('truth_genus'))}", "-",
                         short(b.get("reason"), 220)])
    return rows


def section(res):
    L = []
    ph, cli, build = res["phantom"], res["cli"], res["build"]
    bones = res["bones"]
    written = [b for b in bones if b["outcome"] == "written"]
    refused = [b for b in bones if b["outcome"] == "refused"]
    missing = [b for b in bones if b["outcome"] == "missing"]
    crossing = [p for p in res["pairs"] if (p.get("crossing_face_pairs") or 0) > 0 or p["a_in_b"] or p["b_in_a"]]
    gaps = sorted((p for p in res["pairs"] if p.get("min_gap_mm") is not None), key=lambda p: p["min_gap_mm"])
    L.append(f"## {res['tag']}, seed {res['seed']}: {ph['shape'][0]} x {ph['shape'][1]} x {ph['shape'][2]} voxels, "
             f"{ph['spacing'][0]} x {ph['spacing'][1]} x {ph['spacing'][2]} mm")
    L.append("")
    L.append(f"Phantom build (own process): {fmt(build.get('wall_s'), 0)} s, peak RSS {fmt(build.get('peak_rss_mb'), 0)} MiB"
             f"{' (cached)' if build.get('cached') else ''}; generator timings (s): "
             + ", ".join(f"{k} {fmt(v, 1)}" for k, v in (ph.get('timing') or {}).items()) + ".")
    L.append("")
    lib = cli.get("library") or {}
    if lib:
        L.append(f"Library: work tree at commit {lib.get('commit')}"
                 + (" with uncommitted library changes" if lib.get("library_uncommitted") else "") + ".")
        L.append("")
    L.append("Command (cwd = the case folder): `" + " ".join(
        a if "{" not in a else f"'{a}'" for a in cli["argv"]) + "`")
    L.append("")
    L.append(f"Exit code **{cli.get('exit_code')}**, wall **{fmt(cli.get('wall_s'), 1)} s**, peak RSS **"
             f"{fmt((cli.get('peak_rss_mb') or float('nan')) / 1024.0, 2)} GiB** (user {fmt(cli.get('user_s'), 0)} s, "
             f"system {fmt(cli.get('system_s'), 0)} s; 2 cores shared with other work).")
    L.append("")
    ri = res.get("report_info") or {}
    ji = ri.get("joint_input") or ri.get("first_input") or {}
    if ji:
        keep = {k: v for k, v in ji.items() if any(t in k for t in ("spacing", "grid", "memory", "crop", "shape", "extent", "rule"))
                and k not in ("labels_in_crop",)}
        L.append("Working grid (report `joint.input`): `" + short(json.dumps(jsonable(keep), default=str), 600) + "`")
        L.append("")
    if ri.get("joint_thresholds"):
        L.append("Thresholds (report `joint.thresholds`): `" + json.dumps(jsonable(ri["joint_thresholds"])) + "`; "
                 "stage seconds (`joint.timings`): " + ", ".join(f"{k} {fmt(v, 1)}" for k, v in
                                                                 (ri.get("joint_timings") or {}).items() if v))
        L.append("")
    fbs = (ri.get("joint_fallbacks") or [])
    if fbs or ri.get("bone_fallbacks"):
        L.append("Fallbacks (the run's shared stages): " + (short("; ".join(
            f"{f.get('stage')}: {f.get('what')} ({f.get('count')} {f.get('unit')})" for f in fbs), 600) or "none")
                 + ". Per bone (the report's `pipeline.fallbacks`, bones affected, total count): "
                 + "; ".join(f"{k} ({v['bones']} bones, {v['count']} {v['unit']})"
                             for k, v in (ri.get("bone_fallbacks") or {}).items()) + ".")
        L.append("")
    ok_time = cli.get("wall_s") is not None and cli["wall_s"] <= TARGET_S
    ok_mem = cli.get("peak_rss_mb") is not None and cli["peak_rss_mb"] <= TARGET_GB * 1024
    ok_all = not missing and cli.get("exit_code") in (0, 6)
    ok_pen = not crossing
    L.append("| issue-21 target | measured | held |")
    L.append("|---|---|---|")
    L.append(f"| completes, <= 10 min | exit {cli.get('exit_code')}, {fmt(cli.get('wall_s'), 1)} s | {'yes' if ok_time and cli.get('exit_code') is not None else '**NO**'} |")
    L.append(f"| peak <= 4 GB | {fmt((cli.get('peak_rss_mb') or float('nan')) / 1024, 2)} GiB | {'yes' if ok_mem else '**NO**'} |")
    L.append(f"| every bone written or refused with a reason | {len(written)} written, {len(refused)} refused, "
             f"{len(missing)} neither | {'yes' if ok_all else '**NO**'} |")
    L.append(f"| no interpenetration in what is written | {len(crossing)} pair(s) crossing / inside of {len(res['pairs'])} "
             f"checked | {'yes' if ok_pen else '**NO**'} |")
    L.append("")
    if written:
        p95 = np.array([b["distance"]["p95"] for b in written])
        mx = np.array([b["distance"]["max"] for b in written])
        vr = np.array([b["volume_ratio"] for b in written])
        bias = np.array([b["bias_mm"] for b in written])
        L.append(f"Bias (mean signed distance of the surface's vertices to the truth, + outside): median "
                 f"{fmt(np.median(bias), 2)} mm, range {fmt(bias.min(), 2)} to {fmt(bias.max(), 2)}.")
        L.append(f"Written bones: p95 distance to the truth median {fmt(np.median(p95), 2)} mm (range {fmt(p95.min(), 2)}"
                 f"-{fmt(p95.max(), 2)}), max median {fmt(np.median(mx), 2)} (up to {fmt(mx.max(), 2)}) mm, volume "
                 f"ratio {fmt(vr.min(), 3)}-{fmt(vr.max(), 3)}.")
        L.append("")
    L.append(md_table(["bone", "outcome", "volume / truth", "bias mm", "mean mm", "p95 mm", "max mm",
                       "genus (surface / truth)",
                       "checks", "warnings / reason"], _bone_rows(res)))
    L.append("")
    L.append(f"Pairs of written bones within 3 mm of each other's box: {len(res['pairs'])}; smallest gaps "
             "(exact, BoneWatertightLib.stages.contacts.pair_report; inside counts by Testing/metrics):")
    L.append("")
    L.append(md_table(["pair", "smallest gap mm", "truth gap mm", "crossing faces", "vertices inside the other"],
                      [[f"{p['a']} / {p['b']}", fmt(p['min_gap_mm'], 2), fmt(p.get('truth_gap_mm'), 2),
                        p.get('crossing_face_pairs'), f"{p['a_in_b']} / {p['b_in_a']}"]
                       for p in (crossing + [g for g in gaps if g not in crossing])[:15]]))
    L.append("")
    if res.get("edge_variants"):
        L.append("Edge refinement on thin and thick cortex (`--label " + " --label ".join(EDGE_BONES)
                 + "` in one run, otherwise the defaults; ribs 0.6, vertebrae 0.7, sternum 0.5 mm of cortex, the "
                 "humerus 0.8 (head) to 2.5 mm (shaft)): bias (mean signed distance of the vertices to the truth, "
                 "+ outside) / volume ratio / p95 distance (mm):")
        L.append("")
        L.append(md_table(["variant"] + list(EDGE_BONES),
                          [[v["variant"] + ("" if v["exit_code"] == 0 else f" (exit {v['exit_code']})")]
                           + [(f"{b['bias_mm']:+.2f} / {b['volume_ratio']:.3f} / {b['p95']:.2f}"
                               if (b := v["bones"].get(n)) else "-") for n in EDGE_BONES]
                           for v in res["edge_variants"]]))
        L.append("")
    for f in res.get("figures") or []:
        L.append(f"![{f}]({f})")
        L.append("")
    return "\n".join(L)


HEADER = """# Issue 21: all bones of a chest CT in one run, measured on a synthetic labelled chest

Made by `Testing/bench_chest.py` (phantom: `Testing/chest_phantom.py`; its docstring has the
geometry and HU model). 43 bones with known truth: T1-T12 (body, pedicle/lamina ring around an
open canal, transverse and spinous processes; discs 4.6-5.4 mm), ribs 1-12 left and right (swept
tubes, elliptical section 13 x 6.4 mm, rib 1 7 x 14 mm, ending 3-6 cm short of the sternum; costal
cartilage 110 HU continues), sternum, clavicles, scapulae (blade 1.0 mm thick in the infraspinous
fossa to ~3 mm at the borders), proximal humeri (head in the glenoid). Joint spaces carved: 1.5 mm
costovertebral / costotransverse, 2.0 mm between vertebrae outside the discs, 2.5 mm
glenohumeral, sternoclavicular and acromioclavicular, >= 3 mm between any other bones. HU: cortex
1000-1400 (0.4-2.5 mm thick: ribs 0.6, sternum 0.5, vertebrae 0.7, scapula 0.9, clavicle 1.4,
humerus 0.8 head to 2.5 shaft), trabecular 150-300, soft tissue 40, fat -100, lungs -850, air
-1000; in-plane PSF sigma 0.5 mm with the pixel box, along z a Gaussian of FWHM = slice thickness,
noise 20 HU. Labels: majority vote of the truth on a 1.5 mm grid, nearest neighbour onto the CT.
Distances: area samples on both surfaces, exact point-to-triangle, both directions pooled.
"""


def write_doc():
    parts = [HEADER]
    for fn in sorted(os.listdir(DOC)):
        if fn.startswith("chest_") and fn.endswith(".json"):
            parts.append(section(json.load(open(os.path.join(DOC, fn)))))
    with open(os.path.join(DOC, "CHEST.md"), "w") as fh:
        fh.write("\n\n".join(parts).rstrip() + "\n")


# ---------------------------------------------------------------------------- main

def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--shape", type=_ints, default=(512, 512, 300))
    ap.add_argument("--spacing", type=_floats, default=(0.7, 0.7, 1.0))
    ap.add_argument("--tag", default=None, help="name of the run (default from the spacing)")
    ap.add_argument("--work", default="/tmp/bench_chest")
    ap.add_argument("--timeout", type=float, default=3600.0)
    ap.add_argument("--samples", type=int, default=40000)
    ap.add_argument("--edge-variants", action="store_true",
                    help="also run a few bones with the edge level fixed / the refinement off (see EDGE_VARIANTS)")
    ap.add_argument("--build", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--doc-only", action="store_true", help="only rewrite CHEST.md from the json files")
    ap.add_argument("--reuse-phantom", action="store_true",
                    help="use the phantom already built in the case folder even if the generator's source changed")
    ap.add_argument("--reuse-cli", action="store_true",
                    help="evaluate the outputs of the last CLI run in the case folder again (no new run)")
    args = ap.parse_args(argv)
    if args.build:
        _build_here(args.build, args.seed, args.shape, args.spacing)
        return 0
    if args.doc_only:
        write_doc()
        return 0
    tag = args.tag or "x".join(f"{v:g}".replace(".", "p") for v in args.spacing) + "mm"
    cdir = os.path.join(args.work, f"{tag}_s{args.seed}")
    log(f"building the phantom into {cdir} ...")
    if (args.reuse_cli or args.reuse_phantom) and os.path.exists(os.path.join(cdir, "build.json")):
        brec = dict(json.load(open(os.path.join(cdir, "build.json"))), cached=True)
    else:
        brec = build(cdir, args.seed, args.shape, args.spacing)
    log(f"built: {fmt(brec.get('wall_s'), 1)} s, peak {fmt(brec.get('peak_rss_mb'), 0)} MB"
        f"{' (cached)' if brec.get('cached') else ''}; running the CLI ...")
    if args.reuse_cli and os.path.exists(os.path.join(cdir, "cli_time.txt")):
        old = json.load(open(os.path.join(DOC, f"chest_{tag}_s{args.seed}.json"))).get("cli", {})
        cli = dict(old, **_time_v(os.path.join(cdir, "cli_time.txt")))
        cli["exit_code"] = cli.get("exit_status", cli.get("exit_code"))
    else:
        cli = run_cli(cdir, args.timeout)
        cli["library"] = _library_version()
    log(f"CLI exit {cli.get('exit_code')} in {fmt(cli.get('wall_s'), 1)} s, peak {fmt(cli.get('peak_rss_mb'), 0)} MB")
    res, surfaces, truths, names = evaluate(cdir, args.samples)
    info = json.load(open(os.path.join(cdir, "info.json")))
    if args.edge_variants:
        res["edge_variants"] = edge_variants(cdir, min(args.samples, 20000))
    res.update(tag=tag, seed=args.seed, build=brec, cli=cli,
               phantom={k: info.get(k) for k in ("shape", "spacing", "slice_thickness", "h", "timing", "peak_rss_mb",
                                                  "joints", "bones", "origin", "direction")})
    os.makedirs(DOC, exist_ok=True)
    prefix = f"chest_{tag}_s{args.seed}"
    try:
        res["figures"] = pictures(cdir, prefix, surfaces, truths, names, info)
    except Exception as exc:  # noqa: BLE001 - no picture is not a benchmark failure
        res["figures"] = []
        res["figure_error"] = f"{type(exc).__name__}: {exc}"
        log(f"pictures failed: {res['figure_error']}")
    with open(os.path.join(DOC, prefix + ".json"), "w") as fh:
        json.dump(jsonable(res), fh, indent=1, default=str)
    write_doc()
    log(f"wrote {os.path.join(DOC, 'CHEST.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
