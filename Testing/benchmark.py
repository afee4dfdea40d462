"""Benchmark: the pipeline, its ablations and the plain alternatives on phantoms (and real CT).

    python Testing/benchmark.py [--cases tiny,easy,femur,hard,lesion] [--out bench_out]
                                [--real] [--scaling] [--spacing MM] [--samples N]

Every method runs in its own freshly spawned process, so its wall time and peak memory are
its own: wall time is measured around the call only (imports and file reading excluded);
"peak MB" is the process's peak RSS (VmHWM) and "+MB" the part above the RSS just before
the call (the interpreter with numpy/vtk/open3d loaded and the inputs read).
Each surface is checked (checks.check_surface) and compared with the phantom's analytic truth
(metrics.surface_distance: exact point-to-triangle distances of uniform area samples, both
directions). Writes <out>/REPORT.md, <out>/results.json and PNG figures.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import sys
import time
import traceback
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
import multiprocessing as mp

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
for _p in (ROOT, HERE):
    if _p not in sys.path:
        sys.path.insert(0, _p)

import SimpleITK as sitk  # noqa: E402

from BoneWatertightLib.mesh import Surface  # noqa: E402

DATA = "/work/shared/data"

PIPELINE_VARIANTS = {
    "pipeline": {},
    "pipeline_M0": {"iterations": 0},          # ablation: the Poisson surface M0 only
    "pipeline_alpha0": {"alpha": 0.0},         # ablation: no deformation stiffness
    "pipeline_no_refine": {"refine_edges": False},  # the paper's HT surface (no edge step)
}
BASELINES = ["threshold_mc", "direct_poisson", "closing_wrap"]

REAL_CASES = [
    # (name, folder, label file, label value, preset, trim): trim > 0 removes the segment's
    # voxels within trim voxels of the volume border (the bone is cut by the scan there; the
    # untrimmed femur shows the BorderError every method gives).
    ("pelvis3mm_femur_right", "ts_example_ct_abdomen_pelvis_3mm", "bones_labels.nrrd", 76, "femur", 0),
    ("pelvis3mm_femur_right_trimmed", "ts_example_ct_abdomen_pelvis_3mm", "bones_labels.nrrd", 76, "femur", 3),
    ("pelvis3mm_L3", "ts_example_ct_abdomen_pelvis_3mm", "bones_labels.nrrd", 29, "vertebra", 0),
    ("aorta1p5mm_T12_trimmed", "ts_aorta_report_ct_cropped_1p5mm", "vertebra_T12_labels.nrrd", 32,
     "vertebra", 2),
]


# ---------------------------------------------------------------------------- child process

def _status_mb(key: str) -> float:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def _rss_mb() -> float:
    return _status_mb("VmRSS")


def _peak_mb() -> float:
    """Peak RSS of this process image. VmHWM, not ru_maxrss: on Linux ru_maxrss survives
    exec, so a spawned child would report its (large) parent's RSS."""
    v = _status_mb("VmHWM")
    if math.isnan(v):
        v = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return v


def _run_method(method: str, ct_path: str, mask_path: str, params: dict) -> dict:
    """Runs in a spawned process: one method on one case."""
    for p in (ROOT, HERE):
        if p not in sys.path:
            sys.path.insert(0, p)
    import SimpleITK as sitk  # noqa: F811
    from BoneWatertightLib.params import Parameters

    out = {"method": method, "ok": False}
    try:
        ct = sitk.ReadImage(ct_path)
        mask = sitk.ReadImage(mask_path)
        if method.startswith("pipeline"):
            try:
                from BoneWatertightLib.pipeline import reconstruct
            except Exception as exc:  # the pipeline may not exist yet
                return {"method": method, "ok": False, "not_available": True,
                        "error": f"pipeline not available: {type(exc).__name__}: {exc}"}
            import BoneWatertightLib.stages.deform  # noqa: F401  (imports before the clock starts)
            import open3d  # noqa: F401
            base = _rss_mb()
            prm = Parameters(**params).replace(**PIPELINE_VARIANTS[method])
            t0 = time.perf_counter()
            res = reconstruct(ct, mask, prm)
            out["seconds"] = time.perf_counter() - t0
            surf = res.surface
            rep = res.report
            from BoneWatertightLib.report import to_plain
            out["report"] = {"times_s": to_plain(rep.timings), "counts": to_plain(rep.counts),
                             "refinement": to_plain(rep.refinement), "input": to_plain(rep.input),
                             "distance_to_constraints_mm": to_plain(rep.distance_to_constraints_mm)}
        else:
            import baselines
            import open3d  # noqa: F401
            import vtk  # noqa: F401
            base = _rss_mb()
            prm = Parameters(**params)
            t0 = time.perf_counter()
            surf = baselines.METHODS[method](ct, mask, prm)
            out["seconds"] = time.perf_counter() - t0
        out["base_rss_mb"] = base
        out["peak_rss_mb"] = _peak_mb()
        out["vertices"] = np.asarray(surf.vertices, np.float64)
        out["faces"] = np.asarray(surf.faces, np.int64)
        out["ok"] = True
    except BaseException as exc:  # noqa: BLE001 - a failed method is a result, not a crash
        out["error"] = f"{type(exc).__name__}: {exc}"
        out["traceback"] = traceback.format_exc(limit=6)
        out["peak_rss_mb"] = _peak_mb()
    return out


def run_isolated(method, ct_path, mask_path, params, timeout):
    ctx = mp.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=ctx) as ex:
        fut = ex.submit(_run_method, method, ct_path, mask_path, params)
        try:
            return fut.result(timeout=timeout)
        except FutureTimeout:
            for pid in list(getattr(ex, "_processes", {}) or {}):
                try:
                    os.kill(pid, 9)  # only the worker this executor started
                except OSError:
                    pass
            return {"method": method, "ok": False, "error": f"timeout after {timeout:.0f} s"}
        except Exception as exc:  # worker died (e.g. killed by the OOM killer)
            return {"method": method, "ok": False, "error": f"worker crashed: {type(exc).__name__}: {exc}"}


# ---------------------------------------------------------------------------- evaluation

def evaluate(result, truth, neighbour, n_samples, check_si_max_faces=400_000):
    from BoneWatertightLib.mesh.checks import check_surface
    from metrics import TriangleLocator, sample_surface, surface_distance

    row = {k: v for k, v in result.items() if k not in ("vertices", "faces")}
    if not result.get("ok"):
        return row, None
    v, f = result["vertices"], result["faces"]
    row["n_faces"] = int(len(f))
    if not len(f):
        row["ok"] = False
        row["error"] = "empty surface"
        return row, None
    si = len(f) <= check_si_max_faces
    rep = check_surface(v, f, check_self_intersections=si)
    row["checks"] = rep.to_dict()
    row["watertight"] = bool(rep.ok)
    row["self_intersections_checked"] = si
    surf = Surface(v, f)
    if truth is not None:
        d = surface_distance(surf, truth, n_samples=n_samples, return_samples=True)
        samples = {"method_to_truth": d.pop("d_ab"), "truth_to_method": d.pop("d_ba")}
        row["distance"] = d
        # Bias (positive = outside the truth) and contact with the neighbour bone.
        p = sample_surface(surf, min(n_samples, 50_000), seed=7)
        loc = TriangleLocator(truth)
        sd = loc.signed(p)
        row["bias_mm"] = float(sd.mean())
        if neighbour is not None:
            dn = TriangleLocator(neighbour).query(p)[0]
            row["frac_on_neighbour"] = float((dn < np.abs(sd)).mean())
        return row, samples
    return row, None


# ---------------------------------------------------------------------------- figures

def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def fig_cdf(case, samples_by_method, path):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for name, s in samples_by_method.items():
        d = np.sort(np.concatenate([s["method_to_truth"], s["truth_to_method"]]))
        ax.plot(d, np.arange(1, len(d) + 1) / len(d), label=name,
                lw=2.2 if name == "pipeline" else 1.2)
    ax.set_xlim(0, 3)
    ax.set_ylim(0, 1.0)
    ax.axvline(0.5, color="0.7", lw=0.8, ls="--")
    ax.axvline(1.0, color="0.7", lw=0.8, ls="--")
    ax.set_xlabel("distance to the true surface (mm, both directions)")
    ax.set_ylabel("fraction of surface area")
    ax.set_title(f"Deviation CDF - {case}")
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fig_colored(case, surf, truth, path, vmax=1.0):
    """Pipeline surface coloured by signed distance to the truth: front-facing triangles
    drawn back to front (painter's algorithm), two views along the principal axes."""
    from matplotlib.collections import PolyCollection
    from metrics import vertex_distances
    plt = _plt()
    d = vertex_distances(surf.vertices, truth, signed=True)
    fd = d[surf.faces].mean(axis=1)
    c = surf.vertices - surf.vertices.mean(axis=0)
    tri = c[surf.faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    w, vec = np.linalg.eigh(np.cov(c.T))
    vec = vec[:, ::-1]  # long axis first: drawn vertical
    fig, axes = plt.subplots(1, 2, figsize=(10, 7.5))
    coll = None
    for ax, (view, sgn, title) in zip(axes, ((1, 1, "view along 2nd axis"), (2, -1, "view along 3rd axis"))):
        view_dir = vec[:, view] * sgn  # towards the viewer
        shade = fn @ view_dir
        front = shade > 0
        up = vec[:, 0]
        right = np.cross(up, view_dir)
        depth = (tri[front].mean(axis=1)) @ view_dir
        order = np.argsort(depth)
        t2 = np.stack([tri[front] @ right, tri[front] @ up], axis=-1)[order]
        cmap = plt.get_cmap("coolwarm")
        rgba = cmap(np.clip((fd[front][order] + vmax) / (2 * vmax), 0, 1))
        rgba[:, :3] *= (0.45 + 0.55 * shade[front][order])[:, None]  # simple headlight shading
        coll = PolyCollection(t2, facecolors=rgba, edgecolors="none", antialiased=False)
        ax.add_collection(coll)
        ax.set_xlim(t2[..., 0].min(), t2[..., 0].max())
        ax.set_ylim(t2[..., 1].min(), t2[..., 1].max())
        ax.set_aspect("equal")
        ax.axis("off")
        ax.set_title(title)
    sm = plt.cm.ScalarMappable(cmap="coolwarm", norm=plt.Normalize(-vmax, vmax))
    fig.colorbar(sm, ax=axes, shrink=0.7, label="signed distance to truth (mm, + outside)")
    fig.suptitle(f"Pipeline surface vs truth - {case}: mean |d| at vertices {np.abs(d).mean():.3f} mm")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plane_segments(idx_vertices, faces, axis, level):
    """Segments where the mesh (vertices in continuous index coordinates) crosses the
    plane idx[axis] == level; returned as (m, 2, 2) in the other two index axes."""
    s = idx_vertices[:, axis] - level
    sf = s[faces]
    cross = (sf.min(axis=1) < 0) & (sf.max(axis=1) > 0)
    fc = faces[cross]
    sf = sf[cross]
    others = [a for a in range(3) if a != axis]
    pts = []
    for (i, j) in ((0, 1), (1, 2), (2, 0)):
        si, sj = sf[:, i], sf[:, j]
        hit = (si < 0) != (sj < 0)
        t = np.where(hit, si / np.where(hit, si - sj, 1.0), 0.0)
        p = idx_vertices[fc[:, i]] + t[:, None] * (idx_vertices[fc[:, j]] - idx_vertices[fc[:, i]])
        pts.append((hit, p[:, others]))
    seg = []
    for k in range(len(fc)):
        q = [p[k] for hit, p in pts if hit[k]]
        if len(q) == 2:
            seg.append(q)
    return np.array(seg).reshape(-1, 2, 2)


def fig_sections(case, ct, surfaces, truth, neighbour, path, centre_phys):
    """Contours of each method over an axial and a coronal CT slice (image index space,
    so an oblique grid is handled by the direction matrix)."""
    from matplotlib.collections import LineCollection
    plt = _plt()
    arr = sitk.GetArrayViewFromImage(ct)
    origin = np.array(ct.GetOrigin())
    D = np.array(ct.GetDirection()).reshape(3, 3)
    sp = np.array(ct.GetSpacing())
    to_idx = lambda v: ((v - origin) @ D) / sp  # noqa: E731
    cidx = to_idx(np.asarray(centre_phys, float)[None])[0]
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    fig, axes = plt.subplots(1, 2, figsize=(13, 6.5))
    for ax, axis in zip(axes, (2, 1)):
        level = int(round(cidx[axis]))
        level = int(np.clip(level, 0, arr.shape[2 - axis] - 1))
        img = arr[level] if axis == 2 else arr[:, level, :]
        extent = None
        aspect = sp[2] / sp[0] if axis == 1 else 1.0
        ax.imshow(img, cmap="gray", vmin=-300, vmax=1600, origin="lower", aspect=aspect, extent=extent,
                  interpolation="nearest")
        entries = [("truth", truth, "lime", 3.0)]
        if neighbour is not None:
            entries.append(("neighbour truth", neighbour, "yellow", 1.2))
        # Baselines first, the pipeline last (on top).
        names = sorted(surfaces, key=lambda n: (n.startswith("pipeline"), n == "pipeline"))
        for k, name in enumerate(names):
            entries.append((name, surfaces[name], colors[k % len(colors)],
                            1.6 if name == "pipeline" else 1.0))
        for name, s, col, lw in entries:
            if s is None:
                continue
            seg = _plane_segments(to_idx(s.vertices), s.faces, axis, level)
            if not len(seg):
                continue
            # Plot coordinates: axial -> (i, j) ; coronal -> (i, k).
            ax.add_collection(LineCollection(seg, colors=col, linewidths=lw, label=name,
                                             linestyles="--" if name == "neighbour truth" else "-"))
        ax.set_title(("axial slice k=%d" if axis == 2 else "coronal slice j=%d") % level)
        ax.legend(fontsize=7, loc="upper right")
    fig.suptitle(f"Cross-sections - {case}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------- report

def _fmt(x, nd=3):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    if isinstance(x, bool):
        return "yes" if x else "NO"
    if isinstance(x, float):
        return f"{x:.{nd}f}"
    return str(x)


def table(rows, with_truth=True):
    head = ["method", "watertight", "faces", "time s", "peak MB", "+MB"]
    if with_truth:
        head[2:2] = ["mean", "p95", "max", "<0.5", "<1", "bias", "on nbr"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        if not r.get("ok"):
            msg = "not available" if r.get("not_available") else "FAILED: " + r.get("error", "?")[:160]
            lines.append(f"| {r['method']} | {msg} |" + " |" * (len(head) - 2))
            continue
        cells = [r["method"], _fmt(r.get("watertight"))]
        if with_truth:
            d = r.get("distance", {})
            cells += [_fmt(d.get("mean")), _fmt(d.get("p95")), _fmt(d.get("max")),
                      _fmt(d.get("frac_under_0_5"), 3), _fmt(d.get("frac_under_1"), 3),
                      _fmt(r.get("bias_mm")), _fmt(r.get("frac_on_neighbour"), 3)]
        peak = r.get("peak_rss_mb")
        base = r.get("base_rss_mb")
        cells += [str(r.get("n_faces", "-")), _fmt(r.get("seconds"), 2), _fmt(peak, 0),
                  _fmt(peak - base if peak is not None and base is not None else None, 0)]
        lines.append("| " + " | ".join(cells) + " |")
    probs = [(r["method"], r["checks"]["problems"]) for r in rows
             if r.get("ok") and r.get("checks") and r["checks"].get("problems")]
    if probs:
        lines.append("")
        lines.append("Check problems:")
        for m, p in probs:
            lines.append(f"- {m}: " + "; ".join(str(x) for x in p)[:400])
    return "\n".join(lines)


# ---------------------------------------------------------------------------- drivers

def _params_for(preset_name, spacing):
    from BoneWatertightLib.params import preset
    kw = {} if spacing is None else {"spacing": spacing}
    return preset(preset_name, **kw).to_dict()


def run_phantom_case(case, args, out_dir, log):
    from phantoms import make_phantom
    t0 = time.perf_counter()
    ph = make_phantom(case, seed=args.seed)
    t_make = time.perf_counter() - t0
    case_dir = os.path.join(out_dir, case)
    os.makedirs(case_dir, exist_ok=True)
    ct_path = os.path.join(case_dir, "ct.nrrd")
    mask_path = os.path.join(case_dir, "mask.nrrd")
    sitk.WriteImage(ph.ct, ct_path, True)
    sitk.WriteImage(ph.mask, mask_path, True)
    params = _params_for("femur", args.spacing)
    methods = [m for m in list(PIPELINE_VARIANTS) + BASELINES if m in args.methods]
    rows, samples, surfaces = [], {}, {}
    for m in methods:
        log(f"[{case}] {m} ...")
        res = run_isolated(m, ct_path, mask_path, params, args.timeout)
        if res.get("not_available"):
            log(f"[{case}] {m}: not available ({res.get('error')})")
        row, s = evaluate(res, ph.truth, ph.neighbour_truth, args.samples)
        rows.append(row)
        if s is not None:
            samples[m] = s
            surfaces[m] = Surface(res["vertices"], res["faces"])
        log(f"[{case}] {m}: " + (f"{row.get('seconds', 0):.1f} s, mean {row['distance']['mean']:.3f} mm, "
                                 f"watertight {row.get('watertight')}" if row.get("ok") else row.get("error", "")))
    figs = {}
    if samples:
        figs["cdf"] = f"{case}/cdf.png"
        fig_cdf(case, samples, os.path.join(out_dir, figs["cdf"]))
    if "pipeline" in surfaces:
        figs["colored"] = f"{case}/pipeline_vs_truth.png"
        fig_colored(case, surfaces["pipeline"], ph.truth, os.path.join(out_dir, figs["colored"]))
    model = ph.info["_model"]
    centre = model.to_physical(model.head_c[None])[0]
    figs["sections"] = f"{case}/sections.png"
    fig_sections(case, ph.ct, {k: v for k, v in surfaces.items() if k in ("pipeline", "pipeline_M0", *BASELINES)},
                 ph.truth, ph.neighbour_truth, os.path.join(out_dir, figs["sections"]), centre)
    info = {k: v for k, v in ph.info.items() if not k.startswith("_")}
    return {"case": case, "info": info, "make_seconds": t_make, "rows": rows, "figures": figs}


def _iso_surface_near(ct, mask, level, params):
    """HT isosurface of the CT (on the pipeline's working grid) near the segment."""
    from scipy import ndimage
    from baselines import _dilate_mm, _prepared
    prep = _prepared(ct, mask, params)
    d = prep.grid.spacing
    near = _dilate_mm(prep.segment, (params.segment_dilation + 3.0) / d)
    field = np.where(near, prep.ct, -1000.0).astype(np.float32)
    field = ndimage.gaussian_filter(field, 0.5)
    import vtk
    from vtk.util import numpy_support as ns
    from BoneWatertightLib.mesh import from_polydata
    img = vtk.vtkImageData()
    img.SetDimensions(*[int(v) for v in field.shape[::-1]])
    img.SetSpacing(d, d, d)
    img.GetPointData().SetScalars(ns.numpy_to_vtk(field.ravel(), deep=True))
    fe = vtk.vtkFlyingEdges3D()
    fe.SetInputData(img)
    fe.SetValue(0, float(level))
    fe.Update()
    s = from_polydata(fe.GetOutput())
    return Surface(prep.grid.grid_to_physical(s.vertices), s.faces)


def run_real_case(spec, args, out_dir, log):
    from BoneWatertightLib.params import Parameters
    from metrics import TriangleLocator
    name, folder, labels, value, preset_name, trim = spec
    case_dir = os.path.join(out_dir, "real", name)
    os.makedirs(case_dir, exist_ok=True)
    ct = sitk.ReadImage(os.path.join(DATA, folder, "ct.nrrd"))
    lab = sitk.ReadImage(os.path.join(DATA, folder, labels))
    mask = sitk.Cast(sitk.Equal(lab, int(value)), sitk.sitkUInt8)
    if trim:
        arr = sitk.GetArrayFromImage(mask)
        for ax in range(3):
            sl = [slice(None)] * 3
            sl[ax] = slice(0, trim)
            arr[tuple(sl)] = 0
            sl[ax] = slice(arr.shape[ax] - trim, None)
            arr[tuple(sl)] = 0
        m2 = sitk.GetImageFromArray(arr)
        m2.CopyInformation(mask)
        mask = m2
    ct_path = os.path.join(case_dir, "ct.nrrd")
    mask_path = os.path.join(case_dir, "mask.nrrd")
    sitk.WriteImage(ct, ct_path, True)
    sitk.WriteImage(mask, mask_path, True)
    params = _params_for(preset_name, args.spacing)
    iso = None
    try:
        iso = _iso_surface_near(ct, mask, params["ht"], Parameters(**params))
    except Exception as exc:  # e.g. BorderError: reported by every method anyway
        log(f"[real {name}] no HT isosurface: {exc}")
    rows, surfaces = [], {}
    for m in ["pipeline", "pipeline_M0"] + BASELINES:
        if m not in args.methods:
            continue
        log(f"[real {name}] {m} ...")
        res = run_isolated(m, ct_path, mask_path, params, args.timeout)
        row, _ = evaluate(res, None, None, args.samples)
        if res.get("ok") and iso is not None and iso.n_faces:
            dv = TriangleLocator(iso).query(res["vertices"])[0]
            row["to_ht_iso"] = {"mean": float(dv.mean()), "p95": float(np.percentile(dv, 95)),
                                "max": float(dv.max())}
            surfaces[m] = Surface(res["vertices"], res["faces"])
        rows.append(row)
        log(f"[real {name}] {m}: " + (f"{row.get('seconds', 0):.1f} s, watertight {row.get('watertight')}"
                                      if row.get("ok") else row.get("error", "")))
    figs = {}
    if surfaces:
        arr = sitk.GetArrayViewFromImage(mask)
        idx = np.argwhere(arr > 0).mean(axis=0)[::-1]
        centre = mask.TransformContinuousIndexToPhysicalPoint(idx.tolist())
        figs["sections"] = f"real/{name}/sections.png"
        fig_sections(name, ct, surfaces, None, None, os.path.join(out_dir, figs["sections"]), centre)
    return {"case": name, "folder": folder, "label": value, "preset": preset_name, "trim_slices": trim,
            "rows": rows, "figures": figs}


def run_scaling(args, out_dir, log):
    from phantoms import make_phantom
    ph = make_phantom("femur", seed=args.seed)
    case_dir = os.path.join(out_dir, "scaling")
    os.makedirs(case_dir, exist_ok=True)
    ct_path = os.path.join(case_dir, "ct.nrrd")
    mask_path = os.path.join(case_dir, "mask.nrrd")
    sitk.WriteImage(ph.ct, ct_path, True)
    sitk.WriteImage(ph.mask, mask_path, True)
    rows = []
    for sp in args.scaling_spacings:
        log(f"[scaling] spacing {sp} mm ...")
        res = run_isolated("pipeline", ct_path, mask_path, _params_for("femur", sp), args.timeout)
        row = {"spacing": sp, "ok": res.get("ok"), "error": res.get("error"),
               "seconds": res.get("seconds"), "peak_rss_mb": res.get("peak_rss_mb"),
               "not_available": res.get("not_available", False)}
        if res.get("ok"):
            counts = (res.get("report") or {}).get("counts") or {}
            row["surface_voxels"] = counts.get("p_h0_surface_points")
            row["faces"] = int(len(res["faces"]))
            row["stage_times"] = (res.get("report") or {}).get("times_s")
        rows.append(row)
        log(f"[scaling] {sp} mm: {row.get('seconds')} s, surface voxels {row.get('surface_voxels')}")
    good = [r for r in rows if r.get("ok") and r.get("surface_voxels")]
    fit = None
    if len(good) >= 2:
        x = np.log([r["surface_voxels"] for r in good])
        y = np.log([r["seconds"] for r in good])
        k, c = np.polyfit(x, y, 1)
        fit = {"exponent": float(k), "coefficient": float(math.exp(c))}
        plt = _plt()
        fig, ax = plt.subplots(figsize=(5.5, 4))
        ax.loglog(np.exp(x), np.exp(y), "o-")
        for r in good:
            ax.annotate(f"{r['spacing']} mm", (r["surface_voxels"], r["seconds"]), fontsize=8)
        ax.set_xlabel("surface voxels (P_H0 boundary)")
        ax.set_ylabel("wall time (s)")
        ax.set_title(f"time ~ n^{k:.2f}")
        fig.tight_layout()
        fig.savefig(os.path.join(case_dir, "scaling.png"), dpi=110)
        plt.close(fig)
    return {"rows": rows, "fit": fit}


def write_report(out_dir, results, args):
    L = ["# BoneWatertight benchmark", "",
         f"Generated {time.strftime('%Y-%m-%d %H:%M:%S')} by `Testing/benchmark.py` "
         f"(seed {args.seed}, {args.samples} area samples per surface and direction, "
         f"resample spacing {'auto' if args.spacing is None else args.spacing} mm, "
         f"{os.cpu_count()} CPU cores).", "",
         "Columns: distances in mm between each surface and the phantom's analytic truth, both "
         "directions pooled (mean, 95th percentile, sampled maximum, fraction of area under 0.5 / 1 mm); "
         "bias = mean signed distance of the method's surface to the truth (+ = outside); "
         "on nbr = fraction of the method's area closer to the neighbouring cup than to the bone "
         "(fused with the neighbour); watertight = checks.check_surface ok (closed, 2-manifold, one "
         "component, consistently oriented, no self-intersections; self-intersections are not "
         "checked above 400k faces); time = wall time of the call in a fresh process; peak MB = "
         "peak RSS of that process, +MB = above its RSS before the call.", "",
         "Ablations: pipeline_M0 = `iterations=0` (Poisson M0 only); pipeline_alpha0 = `alpha=0` "
         "for every deformation iteration (Parameters has no last-step-only alpha); "
         "pipeline_no_refine = `refine_edges=False` (the paper's HT surface, no half-maximum edge step).",
         ""]
    for r in results.get("phantoms", []):
        info = r["info"]
        L += [f"## Phantom `{r['case']}`", "",
              f"scale {info['scale']} (bone {info['bone_length_mm']:.0f} mm long), pixel {info['pixel']} mm, "
              f"slices {info['slice_spacing']} mm (thickness {info['slice_thickness']} mm), joint gap "
              f"{info['gap']} mm, noise {info['noise']} HU, lesion {info['lesion']}, CT size "
              f"{info['ct_size']}; truth mesh: {info['truth_note']} ({info['truth_grid_mm']} mm). "
              f"Phantom made in {r['make_seconds']:.1f} s.", "",
              table(r["rows"]), ""]
        for key, title in (("cdf", "Deviation CDF"), ("colored", "Pipeline vs truth"),
                           ("sections", "Cross-sections")):
            if key in r["figures"]:
                L.append(f"![{title}]({r['figures'][key]})")
        L.append("")
    if results.get("real"):
        L += ["## Real CT", "",
              "No ground truth: 'to HT iso' = distance (mm) of the method's vertices to the HT isosurface of "
              "the CT near the segment (a loose check: the HT isosurface itself leaks into neighbours).", ""]
        for r in results["real"]:
            L += [f"### {r['case']} ({r['folder']}, label {r['label']}, preset {r['preset']}"
                  + (f", segment trimmed {r['trim_slices']} voxels from the volume border" if r["trim_slices"] else "")
                  + ")", "", table(r["rows"], with_truth=False), ""]
            iso_rows = [(x["method"], x["to_ht_iso"]) for x in r["rows"] if x.get("to_ht_iso")]
            if iso_rows:
                L += ["| method | to HT iso mean | p95 | max |", "|---|---|---|---|"]
                L += [f"| {m} | {d['mean']:.3f} | {d['p95']:.3f} | {d['max']:.3f} |" for m, d in iso_rows]
                L.append("")
            if "sections" in r["figures"]:
                L += [f"![sections]({r['figures']['sections']})", ""]
    if results.get("scaling"):
        sc = results["scaling"]
        L += ["## Scaling (femur phantom)", "", "| spacing mm | surface voxels | faces | time s | peak MB |",
              "|---|---|---|---|---|"]
        for r in sc["rows"]:
            if r.get("ok"):
                L.append(f"| {r['spacing']} | {r.get('surface_voxels')} | {r.get('faces')} | "
                         f"{_fmt(r.get('seconds'), 1)} | {_fmt(r.get('peak_rss_mb'), 0)} |")
            else:
                why = "not available" if r.get("not_available") else "FAILED: " + str(r.get("error"))[:120]
                L.append(f"| {r['spacing']} | {why} | | | |")
        if sc.get("fit"):
            L += ["", f"Fit: time = {sc['fit']['coefficient']:.3g} * n^{sc['fit']['exponent']:.2f} "
                      "(n = surface voxels).", "", "![scaling](scaling/scaling.png)"]
        L.append("")
    with open(os.path.join(out_dir, "REPORT.md"), "w") as fh:
        fh.write("\n".join(L))


def _jsonable(o):
    if isinstance(o, dict):
        return {k: _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return o


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default="tiny,easy,femur,hard,lesion")
    ap.add_argument("--out", default="bench_out")
    ap.add_argument("--real", action="store_true", help="also run the real CT cases in " + DATA)
    ap.add_argument("--scaling", action="store_true", help="pipeline time vs spacing on the femur phantom")
    ap.add_argument("--scaling-spacings", default="1.0,0.7,0.5,0.35")
    ap.add_argument("--spacing", type=float, default=None, help="resample spacing (mm); default auto")
    ap.add_argument("--samples", type=int, default=200_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout", type=float, default=1800.0, help="per method (s)")
    ap.add_argument("--methods", default=",".join(list(PIPELINE_VARIANTS) + BASELINES))
    args = ap.parse_args(argv)
    args.methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    args.scaling_spacings = [float(x) for x in args.scaling_spacings.split(",")]
    out_dir = os.path.abspath(args.out)
    os.makedirs(out_dir, exist_ok=True)

    def log(msg):
        print(time.strftime("%H:%M:%S"), msg, flush=True)

    results = {"phantoms": [], "real": [], "scaling": None}
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    for case in cases:
        results["phantoms"].append(run_phantom_case(case, args, out_dir, log))
        write_report(out_dir, results, args)
    if args.real:
        for spec in REAL_CASES:
            results["real"].append(run_real_case(spec, args, out_dir, log))
            write_report(out_dir, results, args)
    if args.scaling:
        results["scaling"] = run_scaling(args, out_dir, log)
    write_report(out_dir, results, args)
    with open(os.path.join(out_dir, "results.json"), "w") as fh:
        json.dump(_jsonable(results), fh, indent=1, default=str)
    log(f"wrote {os.path.join(out_dir, 'REPORT.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
