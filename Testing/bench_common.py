"""Shared pieces of the benchmark (Testing/benchmark.py, Testing/bench_real.py): surface
evaluation against a truth or a reference, pair measures, figures and Markdown tables.

Everything here runs in the benchmark's parent process on surfaces returned by the child
processes (Testing/bench_worker.py); nothing here is timed.
"""

from __future__ import annotations

import math
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
for _p in (ROOT, HERE):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from BoneWatertightLib.mesh import Surface  # noqa: E402
from BoneWatertightLib.mesh.surface import enclosed_volume, surface_area  # noqa: E402

# Self-intersections are checked up to this many faces (the check costs ~1 s per 200k faces).
CHECK_SI_MAX_FACES = 1_500_000


# ---------------------------------------------------------------------------- evaluation

def surface_of(bone: dict) -> Surface:
    return Surface(bone["vertices"], bone["faces"])


def check(v, f) -> dict:
    """SPEC §4 checks of a surface (checks.check_surface), as a small dict."""
    from BoneWatertightLib.mesh.checks import check_surface

    if not len(f):
        return {"ok": False, "problems": ["empty surface"], "genus": None, "n_components": 0,
                "si_checked": False}
    si = len(f) <= CHECK_SI_MAX_FACES
    rep = check_surface(v, f, check_self_intersections=si)
    return {"ok": bool(rep.ok), "problems": [str(p) for p in rep.problems], "genus": rep.genus,
            "n_components": int(rep.n_components), "n_self_intersections": int(rep.n_self_intersections),
            "closed": bool(rep.closed), "si_checked": si}


_LOCATORS: dict = {}


def locator(surface: Surface):
    """metrics.TriangleLocator of a surface, cached (the truths are measured many times)."""
    from metrics import TriangleLocator

    key = id(surface)
    hit = _LOCATORS.get(key)
    if hit is None or hit[0] is not surface:
        if len(_LOCATORS) > 16:
            _LOCATORS.clear()
        hit = (surface, TriangleLocator(surface))
        _LOCATORS[key] = hit
    return hit[1]


def _stats(d):
    return dict(mean=float(d.mean()), median=float(np.median(d)), p95=float(np.percentile(d, 95)),
                p99=float(np.percentile(d, 99)), max=float(d.max()),
                frac_under_0_5=float((d < 0.5).mean()), frac_under_1=float((d < 1.0).mean()),
                rms=float(np.sqrt((d * d).mean())))


def distances(s: Surface, other: Surface, n_samples: int, seed: int = 0):
    """As metrics.surface_distance (uniform area samples on each surface, exact distance to the
    other's triangles, both directions pooled), with cached locators; and the raw samples."""
    from metrics import sample_surface

    pa = sample_surface(s, n_samples, seed)
    pb = sample_surface(other, n_samples, seed + 1)
    d_ab = locator(other).query(pa)[0]
    d_ba = locator(s).query(pb)[0]
    out = _stats(np.concatenate([d_ab, d_ba]))
    out["a_to_b"] = _stats(d_ab)
    out["b_to_a"] = _stats(d_ba)
    out["n_samples"] = int(n_samples)
    return out, {"to_truth": d_ab, "from_truth": d_ba}


def truth_metrics(v, f, truth: Surface, n_samples: int, neighbour: Surface | None = None,
                  seed: int = 0, keep_samples: bool = False) -> dict:
    """Distances of the surface (v, f) to an analytic truth, both directions (area samples,
    exact point-to-triangle), the bias (mean signed distance of the surface's vertices to the
    truth, + outside), the volume ratio, and with ``neighbour`` the fraction of the surface's
    area closer to the neighbour's truth than to its own (a bridge to the neighbour)."""
    from metrics import sample_surface

    s = Surface(v, f)
    d, samples = distances(s, truth, n_samples, seed)
    out = {"distance": d}
    sd = locator(truth).signed(v)
    out["bias_mm"] = float(sd.mean())
    out["vertex_abs_mean_mm"] = float(np.abs(sd).mean())
    vt = enclosed_volume(truth.vertices, truth.faces)
    out["volume_ratio"] = float(enclosed_volume(v, f) / vt) if vt else None
    if neighbour is not None:
        p = sample_surface(s, min(n_samples, 50_000), seed=seed + 7)
        dn = locator(neighbour).query(p)[0]
        do = locator(truth).query(p)[0]
        out["frac_on_neighbour"] = float((dn < do).mean())
    if keep_samples:
        out["_samples"] = samples
    return out


def reference_metrics(v, f, reference: Surface, n_samples: int, reference_ml: float,
                      cap=None) -> dict:
    """Distances of a surface to a reference surface (both directions), signed vertex
    distances (bias), and the volume ratio to ``reference_ml``; with ``cap`` (1 on cap faces)
    also the distances of the surface's non-cap part."""
    s = Surface(v, f)
    d, _ = distances(s, reference, n_samples)
    out = {"distance": d}
    sd = locator(reference).signed(v)
    out["bias_mm"] = float(sd.mean())
    out["_vertex_distance"] = np.abs(sd)
    out["volume_ml"] = float(enclosed_volume(v, f) / 1000.0)
    out["volume_ratio"] = float(out["volume_ml"] / reference_ml) if reference_ml else None
    if cap is not None and np.any(cap):
        keep = np.asarray(cap) == 0
        out["cap_faces"] = int((~keep).sum())
        out["cap_area_mm2"] = float(surface_area(v, f[~keep]))
    return out


def inside_of(points, surface: Surface) -> dict:
    """How many points lie inside a closed surface, and the smallest signed distance (mm,
    negative = inside), measured independently of the library (metrics.TriangleLocator)."""
    sd = locator(surface).signed(points)
    return {"inside": int((sd < 0).sum()), "min_signed_mm": float(sd.min())}


def pair_measures(a: Surface, b: Surface) -> dict:
    """Two surfaces against each other: crossing face pairs, vertices of each inside the
    other and the smallest gap (BoneWatertightLib.stages.contacts.pair_report, exact)."""
    from BoneWatertightLib.stages.contacts import pair_report

    return pair_report(a.vertices, a.faces, b.vertices, b.faces)


def status_mb(key: str) -> float:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


# ---------------------------------------------------------------------------- figures

def plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as _plt
    return _plt


def fig_cdf(title, samples_by_method, path, xmax=3.0, highlight=("full",)):
    p = plt()
    fig, ax = p.subplots(figsize=(6.5, 4.5))
    for name, s in samples_by_method.items():
        d = np.sort(np.concatenate([s["to_truth"], s["from_truth"]]))
        ax.plot(d, np.arange(1, len(d) + 1) / len(d), label=name,
                lw=2.4 if name in highlight else 1.2)
    ax.set_xlim(0, xmax)
    ax.set_ylim(0, 1.0)
    for x in (0.25, 0.5, 1.0):
        ax.axvline(x, color="0.75", lw=0.8, ls="--")
    ax.set_xlabel("distance to the true surface (mm, both directions)")
    ax.set_ylabel("fraction of surface area")
    ax.set_title(title)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    p.close(fig)


def plane_segments(idx_vertices, faces, axis, level):
    """Segments where a mesh (vertices in continuous index coordinates i, j, k) crosses the
    plane idx[axis] == level: (m, 2, 3) index coordinates."""
    s = idx_vertices[:, axis] - level
    sf = s[faces]
    cross = (sf.min(axis=1) < 0) & (sf.max(axis=1) > 0)
    fc = faces[cross]
    sf = sf[cross]
    if not len(fc):
        return np.zeros((0, 2, 3))
    pts, hits = [], []
    for (i, j) in ((0, 1), (1, 2), (2, 0)):
        si, sj = sf[:, i], sf[:, j]
        hit = (si < 0) != (sj < 0)
        t = np.where(hit, si / np.where(hit, si - sj, 1.0), 0.0)
        p = idx_vertices[fc[:, i]] + t[:, None] * (idx_vertices[fc[:, j]] - idx_vertices[fc[:, i]])
        pts.append(p)
        hits.append(hit)
    hits = np.stack(hits, 1)
    pts = np.stack(pts, 1)
    two = hits.sum(1) == 2
    order = np.argsort(~hits[two], axis=1, kind="stable")[:, :2]
    sel = pts[two][np.arange(two.sum())[:, None], order]
    return sel


def to_index(ct, points):
    origin = np.array(ct.GetOrigin())
    D = np.array(ct.GetDirection()).reshape(3, 3)
    sp = np.array(ct.GetSpacing())
    return ((np.asarray(points, float) - origin) @ D) / sp


def fig_sections(title, ct, entries, path, centre_phys, half_width_mm=None, axes=(2, 1, 0),
                 window=(-350, 1250)):
    """CT index planes through ``centre_phys`` with the cross-sections of several surfaces.

    entries: list of (label, Surface or None, colour, line width, line style). Displayed in
    millimetres along the CT's index axes; ``half_width_mm`` zooms to a square around the
    centre (None: the whole slice)."""
    import SimpleITK as sitk
    from matplotlib.collections import LineCollection
    p = plt()
    arr = sitk.GetArrayViewFromImage(ct)
    sp = np.array(ct.GetSpacing())
    size = np.array(ct.GetSize())
    c = to_index(ct, np.asarray(centre_phys, float)[None])[0]
    fig, axs = p.subplots(1, len(axes), figsize=(5.2 * len(axes), 5.4))
    axs = np.atleast_1d(axs)
    for ax, axis in zip(axs, axes):
        level = int(np.clip(round(c[axis]), 0, size[axis] - 1))
        others = [a for a in range(3) if a != axis]  # (horizontal, vertical) index axes
        img = np.take(arr, level, axis=2 - axis)  # array axes (z, y, x) = index (k, j, i)
        # img rows = the higher remaining array axis... arrange as (vertical, horizontal).
        # remaining array axes in order: for axis 2 (k): (j, i); axis 1 (j): (k, i); axis 0: (k, j)
        h, v = others[0], others[1]
        ext = [-0.5 * sp[h], (size[h] - 0.5) * sp[h], -0.5 * sp[v], (size[v] - 0.5) * sp[v]]
        ax.imshow(img, cmap="gray", vmin=window[0], vmax=window[1], origin="lower", extent=ext,
                  interpolation="nearest")
        for label, s, col, lw, ls in entries:
            if s is None or not len(s.faces):
                continue
            seg = plane_segments(to_index(ct, s.vertices), s.faces, axis, float(level))
            if not len(seg):
                ax.plot([], [], color=col, lw=lw, ls=ls, label=label)
                continue
            xy = np.stack([seg[..., h] * sp[h], seg[..., v] * sp[v]], -1)
            ax.add_collection(LineCollection(xy, colors=[col], linewidths=lw, linestyles=ls,
                                             label=label))
        if half_width_mm:
            cx, cy = c[h] * sp[h], c[v] * sp[v]
            ax.set_xlim(cx - half_width_mm, cx + half_width_mm)
            ax.set_ylim(cy - half_width_mm, cy + half_width_mm)
        ax.set_xlabel(f"{'ijk'[h]} (mm)")
        ax.set_ylabel(f"{'ijk'[v]} (mm)")
        ax.set_title(f"{'ijk'[axis]} = {level}")
    handles, labels = axs[0].get_legend_handles_labels()
    ncol = min(4, max(1, len(labels)))
    rows = int(math.ceil(len(labels) / ncol))
    fig.legend(handles, labels, loc="lower center", ncol=ncol, fontsize=8, frameon=False)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.035 * rows + 0.02, 1, 1))
    fig.savefig(path, dpi=100)
    p.close(fig)


def render_distance(surface: Surface, path, ct, title, values, label, vrange):
    """VTK picture (BoneWatertightLib.app.render): views coloured by ``values`` + CT sections.
    Returns the path, or None with the reason when offscreen rendering is unavailable."""
    try:
        from BoneWatertightLib.app.render import render_surface
        render_surface(surface, path, ct=ct, title=title, scalars=np.asarray(values, float),
                       scalar_label=label, scalar_range=vrange)
        return path, None
    except Exception as exc:  # noqa: BLE001 - no picture is not a benchmark failure
        return None, f"{type(exc).__name__}: {exc}"


def render_sections(ct, surfaces: dict, path, center, title, margin_mm=12.0):
    try:
        from BoneWatertightLib.app.render import render_cross_sections
        render_cross_sections(ct, surfaces, path, center=center, title=title, margin_mm=margin_mm)
        return path, None
    except Exception as exc:  # noqa: BLE001
        return None, f"{type(exc).__name__}: {exc}"


# ---------------------------------------------------------------------------- Markdown

def fmt(x, nd=3):
    if x is None:
        return "-"
    if isinstance(x, bool):
        return "yes" if x else "NO"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if isinstance(x, (float, np.floating)):
        if not math.isfinite(float(x)):
            return "-"
        return f"{x:.{nd}f}"
    return str(x)


def md_table(head, rows):
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [str(c).replace("|", "/").replace("\n", " ") for c in r]
        cells += [""] * (len(head) - len(cells))
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def short(text, n=140):
    text = str(text or "").replace("\n", " ")
    return text if len(text) <= n else text[:n - 1] + "…"


def verdict(ok):
    if ok is None:
        return "n/a"
    return "**met**" if ok else "**NOT met**"


def jsonable(o):
    if isinstance(o, dict):
        return {str(k): jsonable(v) for k, v in o.items() if not str(k).startswith("_")}
    if isinstance(o, (list, tuple)):
        return [jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o


def gate_text(pipe):
    """The default (on_implausible = fail) outcome: fails on plausibility problems; warnings
    (pairs split by labels alone, a surface far outside its segment) do not fail a run."""
    problems = ((pipe or {}).get("plausibility") or {}).get("problems") or []
    if problems:
        return "**default FAILS**: " + short("; ".join(problems), 160)
    w = (pipe or {}).get("warnings") or []
    if not pipe:
        return ""
    return "pass" + (f" (warning: {short('; '.join(w), 120)})" if w else "")


def write_phantom(cdir, ph, seconds, **extra):
    """A built phantom's files in ``cdir``: ct.nrrd, labels.nrrd, the truth meshes
    (truths.npz: v<label>, f<label>) and info.json (its info without the private keys, the
    names, the build time and ``extra``)."""
    import json

    import SimpleITK as sitk

    sitk.WriteImage(ph.ct, os.path.join(cdir, "ct.nrrd"), True)
    sitk.WriteImage(ph.labels, os.path.join(cdir, "labels.nrrd"), True)
    arrays = {}
    for label, s in ph.truths.items():
        arrays[f"v{label}"] = s.vertices
        arrays[f"f{label}"] = s.faces
    np.savez(os.path.join(cdir, "truths.npz"), **arrays)
    info = {k: v for k, v in ph.info.items() if not k.startswith("_")}
    info["names"] = {str(k): v for k, v in ph.names.items()}
    info["build_seconds"] = seconds
    info.update(extra)
    with open(os.path.join(cdir, "info.json"), "w") as fh:
        json.dump(jsonable(info), fh, indent=1, default=str)
