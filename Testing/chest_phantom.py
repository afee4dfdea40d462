"""Synthetic labelled chest CT with known truth (issue 21): thoracic spine T1-T12, 24 ribs, the
sternum, both clavicles, scapulae and proximal humeri, a CT formed from them and an AI-style
label map.

    ph = make_chest(seed=0)                                   # 512 x 512 x 300, 0.7 x 0.7 x 1 mm
    ph = make_chest(seed=0, shape=(102, 102, 60), spacing=(3.5, 3.5, 5.0), h=1.2)  # coarse, quick
    ph.ct, ph.labels, ph.names[5], ph.truths[5], ph.sdf(5, points), ph.info["joints"]

Frames
------
Anatomy frame ``a`` (mm): x towards the patient's left, y posterior, z superior (LPS axes), origin
on the axis of the vertebral bodies. Physical LPS = a + ``P_ANAT``. The CT grid: physical
= origin + D (spacing * index), D = R(angles_deg) (identity by default), its field of view
centred on a = ``FOV_CENTRE``; the origin is therefore a non-trivial LPS position. The *grid
frame* u = spacing * index (mm along the CT's axes): every bone's fine fields live on the
global grid u = h * (i, j, k) (step ``h``, 0.5 mm by default) so the CT's blur is separable.

Bones (left side built, the right mirrored with its own seeded jitter)
---------------------------------------------------------------------
Each is a signed distance-like function F0 (mm, negative inside, ~1-Lipschitz) of primitives
(rounded elliptic cylinders, first-order ellipsoids, tapered capsules, tubes swept along a
spline with an elliptical section, thickened triangles, a bent plate over a polygon) joined by
polynomial smooth minima:

* T1-T12: body (rounded elliptic cylinder with a waist: 28x20x12 mm at T1 to 44x32x19 mm at
  T12), pedicle/lamina ring around an open canal (genus 1), transverse processes with a knob at
  the tip, a spinous process sloping down. Bodies 5 mm apart (the disc, 4.6-5.4 seeded).
* ribs 1-12 left / right: a tube swept along a cubic spline through the head (beside the body,
  costovertebral joint 1.5 mm), the tubercle (in front of the transverse process tip,
  costotransverse joint 1.5 mm), the angle and an arc round the chest that descends anteriorly;
  elliptical section 13 x 6.4 mm (rib 1: 7 x 14 mm, flat), round 8-10 mm at head / neck; the
  anterior end 3-6 cm short of the sternum, costal cartilage (soft tissue HU) continuing to it.
* sternum: manubrium + body + xiphoid plate (8-12 mm thick), tilted.
* clavicles: S-shaped swept tube (medial bulb 20 mm, flat 18 x 8 mm laterally); joints with the
  manubrium and the acromion 2.5 mm.
* scapulae: a bent blade over a polygon, 1.0 mm thick in the infraspinous fossa to ~3 mm near
  the borders, thick lateral border, medial / superior borders, spine + acromion (thickened
  triangles), coracoid, glenoid with a concave cup; the blade auto-placed >= 9 mm behind the ribs.
* humeri: head (sphere r 22 mm) in the glenoid (2.5 mm joint space), tubercles, 12 cm of shaft
  ending in a rounded stub inside the field of view.

Joints: besides the designed spaces, every pair of bones closer than their joint gap g is carved
as Testing/anatomical.py does: F_a = smax(F0_a, (F0_a - F0_b) / 2 + 1.1 g / 2) with F0 of both
(1-Lipschitz fields keep the two truths >= g apart). g: 2.0 mm between vertebrae (the posterior
elements; the bodies are a disc apart), 1.5 mm rib-vertebra, 2.5 mm glenohumeral, sternoclavicular
and acromioclavicular, 3 mm any other pair. The measured smallest distance of the two truth
meshes is in ``info["joints"]``.

Truth: F on the fine grid, evaluated block-sparse (blocks of 4^3 nodes: skipped where the field at
the block centre proves the block lies outside / deep inside), its zero set by flying edges
(Testing/anatomical._zero_set_mesh), physical LPS.

CT: the background is analytic on the CT grid (every second pixel in-plane for sub-millimetre
pixels, linearly interpolated): air -1000 outside the body, subcutaneous fat -100 HU 10 mm thick,
soft tissue 40, the heart 45, lungs -850 (8 mm inside the rib cage's ribs, cartilages and sternum,
outside the mediastinum, heart and spine, above a diaphragm dome), discs 85, costal cartilage
110, edges smoothed by the in-plane PSF. Bone on the fine grid: occupancy o = clip(0.5 - F / h),
core o_c = clip(0.5 - (F + t_c) / h), HU = bg + o (cortex - bg) + o_c (trabecular - cortex) with
a kind's cortical thickness t_c (0.4-2.5 mm: ribs 0.6, sternum 0.5, vertebrae 0.7, scapula 0.9,
humerus 0.8 in the head to 2.5 in the shaft, clavicle 1.4; x (1 +- 0.3) seeded field), cortex
1000-1400 HU, trabecular 150-300 HU (seeded smooth fields + texture + 40 HU under the cortex). The
bone image is blurred and sampled by one separable operator (in-plane: pixel box * Gaussian
``psf_sigma``; along z a Gaussian of FWHM = slice thickness); + Gaussian noise, int16.

Cost (h 0.5 mm, 2-core machine shared with other work): 512 x 512 x 300 at 0.7 x 0.7 x 1 mm 297 s,
2.3 GB peak; 512 x 512 x 120 at 2.5 mm slices 156 s, 1.4 GB (Testing/bench_chest.py, own process).

Labels: majority vote of the truths over 27 points in each voxel of a ``label_grid`` mm grid (random
phase), nearest neighbour onto the CT grid (as Testing/anatomical.labels_ai).

Random streams: ``np.random.default_rng([seed, stream])``: anatomy jitter (1), HU fields (3), noise
(4), label phase (5).
"""

from __future__ import annotations

import math
import os
import sys
import time
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk
from scipy import sparse
from scipy.interpolate import make_interp_spline
from scipy.spatial import cKDTree
from scipy.special import erf

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
for _p in (ROOT, HERE):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from BoneWatertightLib.mesh import Surface  # noqa: E402
from BoneWatertightLib.mesh.surface import enclosed_volume  # noqa: E402

from anatomical import _Lattice, _genus, _peak_mb, _rotation, _zero_set_mesh  # noqa: E402
from metrics import closest_point_on_triangles  # noqa: E402

# Physical LPS position of the anatomy frame's origin, and the field of view's centre (a frame).
P_ANAT = np.array([-3.5, 24.0, -1187.0])
FOV_CENTRE = np.array([0.0, -25.0, 0.0])

# HU of the background.
AIR_HU, FAT_HU, SOFT_HU, HEART_HU, LUNG_HU = -1000.0, -100.0, 40.0, 45.0, -850.0
DISC_HU, CARTILAGE_HU = 85.0, 110.0

# Bone kinds: mean cortical thickness (mm), cortex HU, trabecular HU.
KINDS = {
    "vertebra": dict(cortex=0.7, cortex_hu=1150.0, trab_hu=200.0),
    "rib": dict(cortex=0.6, cortex_hu=1100.0, trab_hu=180.0),
    "sternum": dict(cortex=0.5, cortex_hu=1050.0, trab_hu=160.0),
    "clavicle": dict(cortex=1.4, cortex_hu=1300.0, trab_hu=220.0),
    "scapula": dict(cortex=0.9, cortex_hu=1250.0, trab_hu=230.0),
    "humerus": dict(cortex=0.8, cortex_hu=1400.0, trab_hu=230.0),
}

# Joint gaps (mm) by pair of kinds; any other pair DEFAULT_GAP.
GAPS = {("vertebra", "vertebra"): 2.0, ("rib", "vertebra"): 1.5, ("humerus", "scapula"): 2.5,
        ("clavicle", "sternum"): 2.5, ("clavicle", "scapula"): 2.5}
DEFAULT_GAP = 3.0
DISC_MM = 5.0          # nominal intervertebral disc (between the bodies)
CARVE_FACTOR = 1.1     # the carve uses 1.1 g (room for the fields' Lipschitz excess)
BLOCK = 4              # fine nodes per block edge
BIG = 6.0              # |F| given to skipped blocks


def pair_gap(kind_a, kind_b):
    return GAPS.get(tuple(sorted((kind_a, kind_b))), DEFAULT_GAP)


# ---------------------------------------------------------------------------- primitives

def _smin(a, b, k):
    hh = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * hh - k * hh * (1.0 - hh)


def _smax(a, b, k):
    hh = np.clip(0.5 - 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * hh + k * hh * (1.0 - hh)


def _smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _ellipsoid(p, c, r):
    """First-order distance to an axis-aligned ellipsoid (exact on its axes)."""
    q = (p - np.asarray(c, float)) / np.asarray(r, float)
    k0 = np.linalg.norm(q, axis=1)
    k1 = np.linalg.norm(q / np.asarray(r, float), axis=1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-9)


def _ellipse2(u, v, a, b):
    k0 = np.sqrt((u / a) ** 2 + (v / b) ** 2)
    k1 = np.sqrt((u / a ** 2) ** 2 + (v / b ** 2) ** 2)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-9)


def _rounded(d2, dz, rr):
    """Intersection of a 2D field d2 and a slab field dz with edges rounded by rr."""
    a, b = d2 + rr, dz + rr
    return np.minimum(np.maximum(a, b), 0.0) + np.hypot(np.maximum(a, 0.0), np.maximum(b, 0.0)) - rr


def _capsule(p, a, b, ra, rb=None):
    """Tapered capsule: distance to segment ab minus a radius linear from ra to rb."""
    a = np.asarray(a, float)
    ba = np.asarray(b, float) - a
    t = np.clip((p - a) @ ba / (ba @ ba), 0.0, 1.0)
    r = ra if rb is None else ra + (rb - ra) * t
    return np.linalg.norm(p - a - t[:, None] * ba, axis=1) - r


def _thick_tris(p, tris, r):
    """min over triangles of (distance to the triangle) - r (only points near each triangle)."""
    out = np.full(len(p), 1e3)
    for t in tris:
        t = np.asarray(t, float)
        near = np.flatnonzero(np.all((p > t.min(0) - r - 8.0) & (p < t.max(0) + r + 8.0), axis=1))
        if not len(near):
            continue
        q = p[near]
        a, b, c = (np.broadcast_to(v, q.shape) for v in t)
        cp, _ = closest_point_on_triangles(q, a, b, c)
        out[near] = np.minimum(out[near], np.linalg.norm(cp - q, axis=1) - r)
    return out


def _polygon2(pts, poly):
    """Signed distance of 2D points (n, 2) to a simple polygon (m, 2), negative inside."""
    poly = np.asarray(poly, float)
    d = np.sum((pts - poly[0]) ** 2, axis=1)
    s = np.ones(len(pts))
    m = len(poly)
    for i in range(m):
        vi, vj = poly[i], poly[i - 1]
        e = vj - vi
        w = pts - vi
        b = w - e * np.clip(w @ e / (e @ e), 0.0, 1.0)[:, None]
        d = np.minimum(d, np.sum(b * b, axis=1))
        c1 = pts[:, 1] >= vi[1]
        c2 = pts[:, 1] < vj[1]
        c3 = e[0] * w[:, 1] > e[1] * w[:, 0]
        flip = (c1 & c2 & c3) | (~c1 & ~c2 & ~c3)
        s[flip] *= -1.0
    return s * np.sqrt(d)


class _Tube:
    """A tube swept along a cubic spline through control points, elliptical section of semi-axes
    a(s) (along the frame's 'up' vector N2, parallel-transported from the z axis) and b(s) (along
    N1 = N2 x T), s the arc length fraction; ellipsoidal end caps of lengths cap0 / cap1."""

    def __init__(self, points, a_of_s, b_of_s, cap0, cap1, step=0.25):
        pts = np.asarray(points, float)
        chord = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))]
        spl = make_interp_spline(chord, pts, k=3 if len(pts) > 3 else len(pts) - 1)
        fine = np.linspace(0, chord[-1], int(chord[-1] / 0.05) + 2)
        c = spl(fine)
        seg = np.linalg.norm(np.diff(c, axis=0), axis=1)
        arc = np.r_[0.0, np.cumsum(seg)]
        self.length = float(arc[-1])
        n = int(self.length / step) + 2
        s_arc = np.linspace(0, self.length, n)
        t_par = np.interp(s_arc, arc, fine)
        self.C = spl(t_par)
        T = spl.derivative()(t_par)
        T /= np.linalg.norm(T, axis=1, keepdims=True)
        N2 = np.zeros_like(T)
        up = np.array([0.0, 0.0, 1.0]) - T[0, 2] * T[0]
        N2[0] = up / np.linalg.norm(up)
        for i in range(1, n):  # parallel transport
            v = N2[i - 1] - (N2[i - 1] @ T[i]) * T[i]
            N2[i] = v / np.linalg.norm(v)
        self.T, self.N2 = T, N2
        self.N1 = np.cross(N2, T)
        s = s_arc / self.length
        self.a = np.asarray(a_of_s(s), float) * np.ones(n)
        self.b = np.asarray(b_of_s(s), float) * np.ones(n)
        self.cap0, self.cap1 = float(cap0), float(cap1)
        self.rmax = float(max(self.a.max(), self.b.max(), self.cap0, self.cap1))
        self.tree = cKDTree(self.C)

    def bounds(self):
        return self.C.min(0) - self.rmax, self.C.max(0) + self.rmax

    def __call__(self, p):
        bound = self.rmax + 12.0
        d, i = self.tree.query(p, distance_upper_bound=bound, workers=2 if len(p) > 300_000 else 1)
        out = np.asarray(d, float) - self.rmax
        far = ~np.isfinite(d)
        out[far] = bound - self.rmax
        ok = np.flatnonzero(~far)
        if len(ok):
            ii = i[ok]
            loc = p[ok] - self.C[ii]
            w = np.einsum("ij,ij->i", loc, self.T[ii])
            u1 = np.einsum("ij,ij->i", loc, self.N1[ii])
            u2 = np.einsum("ij,ij->i", loc, self.N2[ii])
            a, b = self.a[ii], self.b[ii]
            c = np.full(len(ok), 1e9)
            first, last = ii == 0, ii == len(self.C) - 1
            c[first & (w < 0)] = self.cap0
            c[last & (w > 0)] = self.cap1
            w = np.where(c < 1e8, w, 0.0)
            k0 = np.sqrt((u1 / b) ** 2 + (u2 / a) ** 2 + (w / c) ** 2)
            k1 = np.sqrt((u1 / b ** 2) ** 2 + (u2 / a ** 2) ** 2 + (w / c ** 2) ** 2)
            out[ok] = k0 * (k0 - 1.0) / np.maximum(k1, 1e-9)
        return out


# ---------------------------------------------------------------------------- anatomy

@dataclass
class _BoneDef:
    name: str
    label: int
    kind: str
    f0: object            # callable: (n, 3) a-frame points -> (n,) F0
    lo: np.ndarray        # a-frame box (mm)
    hi: np.ndarray
    extra: dict = field(default_factory=dict)


def _mirror(fn):
    """The field of the mirror image (x -> -x) of a left-side field."""
    def g(p):
        q = np.array(p, float, copy=True)
        q[:, 0] *= -1.0
        return fn(q)
    return g


def _vertebrae(rng):
    """T1-T12 parameters (a frame) and their fields."""
    out = []
    z_top = 125.0 + rng.normal(0, 1.0)
    z = z_top
    for k in range(1, 13):
        t = (k - 1) / 11.0
        j = lambda s=0.03: 1.0 + rng.normal(0, s)  # noqa: E731
        rx, ry, hh = (14.0 + 8.0 * t) * j(), (10.0 + 6.0 * t) * j(), (6.0 + 3.5 * t) * j(0.02)
        zc = z - hh
        rc = (7.6 - 0.6 * t) * j(0.02)
        yc = ry + rc + 0.4
        ta = 4.2 + 0.8 * t
        z_arch = zc + 1.0
        ha = 5.5 + 1.0 * t
        tx = (37.0 - 7.0 * t) * j()
        tip = np.array([tx, yc + 9.0 + 2.0 * t, z_arch + 3.0])
        sp_drop = 8.0 + 17.0 * math.sin(math.pi * min(1.0, t * 1.25)) if k < 12 else 6.0
        sp_tip = np.array([0.0, yc + rc + ta + 28.0 + 4.0 * t, zc - sp_drop])
        par = dict(k=k, rx=rx, ry=ry, hh=hh, zc=zc, rc=rc, yc=yc, ta=ta, z_arch=z_arch, ha=ha,
                   tip=tip, sp_tip=sp_tip)
        out.append(par)
        z = zc - hh - DISC_MM * (1.0 + rng.normal(0, 0.03))
    return out


def _vertebra_field(v):
    rx, ry, hh, zc, rc, yc, ta = v["rx"], v["ry"], v["hh"], v["zc"], v["rc"], v["yc"], v["ta"]
    tip, sp_tip = v["tip"], v["sp_tip"]
    tip_r = np.array([-tip[0], tip[1], tip[2]])

    def f(p):
        x, y, zz = p[:, 0], p[:, 1], p[:, 2] - zc
        waist = 1.0 - 0.07 * (1.0 - np.clip((zz / hh) ** 2, 0.0, 1.0))
        body = _rounded(_ellipse2(x, y, rx * waist, ry * waist), np.abs(zz) - hh, 1.6)
        rho = np.hypot(x, y - yc)
        ring = _rounded(np.abs(rho - (rc + 0.5 * ta)) - 0.5 * ta, np.abs(p[:, 2] - v["z_arch"]) - v["ha"], 1.2)
        # ring only behind the body's mid-plane (pedicles + laminae)
        ring = np.maximum(ring, (ry * 0.4) - y)
        F = _smin(body, ring, 2.0)
        root_l = np.array([rc + 0.6 * ta, yc + 2.0, v["z_arch"] + 1.0])
        root_r = root_l * np.array([-1, 1, 1])
        tp = np.minimum(_capsule(p, root_l, tip, 4.6, 3.8), _capsule(p, root_r, tip_r, 4.6, 3.8))
        knob = np.minimum(_ellipsoid(p, tip, (5.0, 5.5, 5.5)), _ellipsoid(p, tip_r, (5.0, 5.5, 5.5)))
        F = _smin(F, _smin(tp, knob, 1.5), 2.0)
        # spinous process: laterally thin (scaled capsule)
        root = np.array([0.0, yc + rc + ta - 1.5, v["z_arch"]])
        ps = p * np.array([1.6, 1.0, 1.0])
        sp = _capsule(ps, root * np.array([1.6, 1, 1]), sp_tip * np.array([1.6, 1, 1]), 5.5, 4.5) / 1.6
        sp_knob = _ellipsoid(p, sp_tip, (4.0, 5.0, 6.0))
        F = _smin(F, _smin(sp, sp_knob, 1.5), 2.5)
        canal = rho - rc
        return np.maximum(F, -canal)

    lo = np.array([-tip[0] - 7, -ry - 2, min(zc - hh, sp_tip[2] - 7) - 2])
    hi = np.array([tip[0] + 7, sp_tip[1] + 7, max(zc + hh, v["z_arch"] + v["ha"], tip[2] + 6) + 2])
    return f, lo, hi


# Rib table: chest half-width W at the arc's lateral point, arc centre yc, posterior / anterior
# half-depths, last arc angle (deg), descent (mm) per 100 degrees of arc (close for neighbours,
# so the intercostal spaces stay open).
RIBS = {
    1: (62, -28, 46, 48, 150, 30), 2: (88, -32, 62, 62, 150, 40), 3: (104, -35, 70, 72, 148, 44),
    4: (115, -36, 74, 76, 146, 47), 5: (122, -37, 76, 78, 143, 49), 6: (126, -38, 77, 80, 139, 51),
    7: (128, -38, 77, 80, 134, 53), 8: (128, -38, 76, 78, 127, 55), 9: (126, -38, 75, 76, 119, 57),
    10: (122, -37, 73, 72, 111, 58), 11: (114, -34, 70, 66, 100, 59), 12: (98, -30, 66, 60, 82, 60),
}


def _rib_tube(v, k, rng):
    """Left rib k of vertebra parameters v: (tube, anterior end point, lateral point)."""
    W, yc, bp, ba, phi_end, drop = RIBS[k]
    j = lambda s=0.025: 1.0 + rng.normal(0, s)  # noqa: E731
    W, bp, ba, drop = W * j(), bp * j(), ba * j(), drop * j(0.02)
    phi_end = math.radians(phi_end + rng.normal(0, 2.0))
    r_head = 5.0
    th = math.radians(38.0)
    e = np.array([v["rx"] * math.cos(th), v["ry"] * math.sin(th)])
    n = np.array([math.cos(th) / v["rx"], math.sin(th) / v["ry"]])
    n /= np.linalg.norm(n)
    hxy = e + n * (r_head + 1.9)
    z_h = v["zc"] + 0.45 * v["hh"]
    H = np.array([hxy[0], hxy[1], z_h])
    tip = v["tip"]
    Q = np.array([tip[0] + 1.0, tip[1] - (5.5 + 1.9 + 4.8), tip[2] - 1.5])
    N = 0.5 * (H + Q) + np.array([0.0, -1.0, 0.0])
    x0 = min(Q[0] + 16.0, 0.9 * W)
    phi0 = math.asin(x0 / W)
    phis = np.linspace(phi0, phi_end, 9)

    def arc(phi):
        b = bp if phi <= math.pi / 2 else ba
        frac = (phi - phi0) / math.radians(100.0)
        return np.array([W * math.sin(phi), yc + b * math.cos(phi), z_h + 1.5 - drop * frac ** 1.3])

    pts = [H, N, Q] + [arc(ph) for ph in phis]
    if k == 1:
        a_fn = lambda s: np.interp(s, [0, 0.08, 0.2, 0.3, 1.0], [5.0, 4.0, 4.5, 3.6, 3.6])  # noqa: E731
        b_fn = lambda s: np.interp(s, [0, 0.08, 0.2, 0.3, 1.0], [5.0, 4.0, 4.8, 7.0, 7.0])  # noqa: E731
    else:
        a_max = 6.6 * j(0.04) if k < 11 else 5.2
        b_max = 3.2 * j(0.04) if k < 11 else 3.0
        a_fn = lambda s: np.interp(s, [0, 0.05, 0.1, 0.16, 0.3, 1.0], [5.0, 3.9, 4.6, 5.0, a_max, a_max])  # noqa: E731
        b_fn = lambda s: np.interp(s, [0, 0.05, 0.1, 0.16, 0.3, 1.0], [5.0, 3.9, 4.8, 4.0, b_max, b_max + 0.3])  # noqa: E731
    tube = _Tube(pts, a_fn, b_fn, cap0=r_head, cap1=2.5)
    return tube, pts[-1], arc(math.pi / 2 if phi_end > math.pi / 2 else phi_end)


def _sternum(rng):
    top = np.array([0.0, -97.0 + rng.normal(0, 1.5), 88.0 + rng.normal(0, 1.5)])
    bot = np.array([0.0, -126.0 + rng.normal(0, 1.5), -70.0 + rng.normal(0, 1.5)])
    ax = (top - bot) / np.linalg.norm(top - bot)          # superior
    ey = np.array([0.0, 1.0, 0.0]) - ax[1] * ax
    ey /= np.linalg.norm(ey)                              # posterior
    L = float(np.linalg.norm(top - bot))
    mlen = 46.0

    def f(p):
        d = p - top
        s = -(d @ ax)                                     # 0 at the top, L at the bottom
        y = d @ ey
        x = d[:, 0]
        # manubrium: trapezoid 52 -> 32 mm wide, 12 mm thick
        hw = 26.0 - 10.0 * np.clip(s / mlen, 0, 1)
        man = _rounded(np.abs(x) - hw, np.maximum(np.abs(s - mlen / 2) - mlen / 2, np.abs(y) - 6.0), 2.0)
        man = np.maximum(man, _rounded(np.abs(x) - hw, np.abs(y) - 6.0, 2.0))
        # the jugular notch
        man = np.maximum(man, -(np.hypot(x, s + 4.0) - 9.0))
        body_hw = 14.0 + 3.0 * np.sin(np.pi * np.clip((s - mlen) / (L - mlen - 12.0), 0, 1))
        b0 = mlen - 5.0  # the body starts inside the manubrium's lower end: one bone
        body = _rounded(np.abs(x) - body_hw, np.maximum(np.abs(s - (b0 + (L - b0 - 14.0) / 2))
                                                        - (L - b0 - 14.0) / 2, np.abs(y) - 4.8), 1.8)
        xi = _capsule(p, top - ax * (L - 14.0), bot, 6.0, 3.0)
        return _smin(_smin(man, body, 2.5), xi, 2.5)

    lo = np.minimum(top, bot) - np.array([30.0, 12.0, 8.0])
    hi = np.maximum(top, bot) + np.array([30.0, 12.0, 8.0])
    return f, lo, hi, top, bot, ax


@dataclass
class _Shoulder:
    scap: object
    hum: object
    clav: object
    scap_box: tuple
    hum_box: tuple
    clav_box: tuple
    Hc: np.ndarray
    r_head: float
    shaft: tuple


def _shoulder_left(rng, rib_fields, sternum_top, sternum_ax):
    """Left scapula, humerus and clavicle (a frame)."""
    j = lambda s=0.03: 1.0 + rng.normal(0, s)  # noqa: E731
    psi = math.radians(33.0 + rng.normal(0, 1.5))
    eu = np.array([math.cos(psi), -math.sin(psi), 0.0])
    ew = np.array([0.0, 0.0, 1.0])
    ev = np.array([math.sin(psi), math.cos(psi), 0.0])
    sc = j()

    def bend(u, w):
        return -0.0045 * (u - 38.0) ** 2 - 0.0004 * (w + 40.0) ** 2

    poly = np.array([(4, 34), (58, 22), (82, -4), (22, -118), (2, -70), (-3, -10)], float) * sc
    O = np.array([60.0 + rng.normal(0, 1.5), 0.0, 68.0 + rng.normal(0, 1.5)])

    def frame_pt(u, w, dv=0.0, O=None):
        return O + u * eu + (bend(u, w) + dv) * ev + w * ew

    # Place the blade 9 mm behind the ribs (plus its half-thickness): sample the outline's
    # interior and push O along ev.
    uu, ww = np.meshgrid(np.linspace(-5, 85 * sc, 40), np.linspace(-120 * sc, 36 * sc, 60))
    uw = np.column_stack([uu.ravel(), ww.ravel()])
    uw = uw[_polygon2(uw, poly) < 6.0]
    O[1] = 20.0
    for _ in range(30):
        pts = O + uw[:, :1] * eu + (bend(uw[:, 0], uw[:, 1])[:, None]) * ev + uw[:, 1:] * ew
        d = min(float(f(pts).min()) for f in rib_fields)
        if d >= 10.5:
            break
        O = O + np.array([0.0, 1.0, 0.0]) * (10.5 - d + 0.2)

    def to_local(p):
        d = p - O
        return d @ eu, d @ ev, d @ ew

    # glenoid, head
    n_g = math.cos(math.radians(10)) * eu - math.sin(math.radians(10)) * ev
    n_g = n_g + np.array([0.0, 0.0, 0.08])
    n_g /= np.linalg.norm(n_g)
    Gc = frame_pt(86.0 * sc, -6.0 * sc, -2.0, O)
    r_head = 22.0 * j(0.03)
    gap = pair_gap("humerus", "scapula")
    Hc = Gc + n_g * (8.0 - 1.5 + gap + r_head)
    # spine crest end and acromion (a frame, relative to the head)
    C1 = Hc + np.array([-14.0, 30.0, 26.0])
    P2 = Hc + np.array([12.0, 20.0, 33.0])
    P3 = Hc + np.array([15.0, -8.0, 35.0])
    P4 = Hc + np.array([-7.0, -14.0, 34.0])
    B0 = frame_pt(0.0, -8.0 * sc, 0.0, O)
    B1 = frame_pt(70.0 * sc, 6.0 * sc, 0.0, O)
    C0 = frame_pt(1.0, -8.0 * sc, 6.0, O)
    # the coracoid rises from the glenoid neck's top and hooks forwards, clear of the spine
    C_sup = frame_pt(74.0 * sc, 6.0 * sc, -2.0, O)
    Cc1 = C_sup + np.array([4.0, -16.0, 10.0])
    Cc2 = Cc1 + np.array([2.0, -14.0, -2.0])
    GI = frame_pt(poly[2, 0], poly[2, 1], 0.0, O)
    II = frame_pt(poly[3, 0], poly[3, 1], 0.0, O)
    medial = [frame_pt(*poly[i], 0.0, O) for i in (0, 5, 4, 3)]
    SS, CC = frame_pt(*poly[0], 0.0, O), frame_pt(*poly[1], 0.0, O)

    def on_blade(p0, p1, n, dv0=0.0, dv1=0.0):
        """Points along the bent blade from (u, w) p0 to p1 (dv: height above the blade)."""
        t = np.linspace(0.0, 1.0, n + 1)
        return [frame_pt(p0[0] + (p1[0] - p0[0]) * s, p0[1] + (p1[1] - p0[1]) * s,
                         dv0 + (dv1 - dv0) * s, O) for s in t]

    lat = on_blade(poly[3], poly[2], 4)
    sup = on_blade(poly[0], poly[1], 3)
    # the spine: a strip from its base on the blade to its crest, which rises to the acromion
    d1 = C1 - O
    u1, w1 = d1 @ eu, d1 @ ew
    v1 = d1 @ ev - bend(u1, w1)
    base = on_blade((0.0, -8.0 * sc), (70.0 * sc, 6.0 * sc), 4)
    crest = on_blade((1.0, -8.0 * sc), (u1, w1), 4, 6.0, v1)
    spine_tris = []
    for i in range(4):
        spine_tris += [(base[i], base[i + 1], crest[i + 1]), (base[i], crest[i + 1], crest[i])]
    fossa = np.array([38.0 * sc, -52.0 * sc])

    def scap(p):
        u, v, w = to_local(p)
        b = bend(u, w)
        slope = np.sqrt(1.0 + (0.009 * (u - 38.0)) ** 2 + (0.0008 * (w + 40.0)) ** 2)
        r = 1.45 - 0.95 * np.exp(-(((u - fossa[0]) / 22.0) ** 2 + ((w - fossa[1]) / 34.0) ** 2))
        plate = np.maximum(np.abs(v - b) / slope - r, _polygon2(np.column_stack([u, w]), poly))
        borders = np.minimum.reduce(
            [_capsule(p, lat[i], lat[i + 1], 3.2 + 0.45 * i, 3.65 + 0.45 * i) for i in range(len(lat) - 1)]
            + [_capsule(p, medial[0], medial[1], 2.0), _capsule(p, medial[1], medial[2], 2.2),
               _capsule(p, medial[2], medial[3], 2.4)]
            + [_capsule(p, sup[i], sup[i + 1], 1.8) for i in range(len(sup) - 1)])
        F = _smin(plate, borders, 2.0)
        spine = _thick_tris(p, spine_tris, 2.3)
        spine = _smin(spine, np.minimum.reduce([_capsule(p, crest[i], crest[i + 1], 3.2 + 0.2 * i, 3.4 + 0.2 * i)
                                                for i in range(len(crest) - 1)]), 2.0)
        acro = _thick_tris(p, [(C1, P2, P3), (C1, P3, P4)], 3.2)
        F = _smin(F, _smin(spine, acro, 3.0), 2.5)
        cor = np.minimum(_capsule(p, C_sup, Cc1, 5.0, 4.6), _capsule(p, Cc1, Cc2, 4.6, 4.2))
        F = _smin(F, cor, 2.5)
        gl = _ellipsoid_oriented(p, Gc, n_g, (8.0, 13.0, 18.0))
        neck = _capsule(p, frame_pt(74.0 * sc, -6.0 * sc, 0.0, O), Gc, 8.0)
        F = _smin(F, _smin(gl, neck, 3.0), 3.0)
        # the cup: nothing of the scapula within r_head + gap of the head's centre
        return np.maximum(F, -(np.linalg.norm(p - Hc, axis=1) - (r_head + gap)))

    pts = np.array([SS, CC, GI, II, C1, P2, P3, P4, Cc2, Gc] + medial)
    scap_box = (pts.min(0) - 22.0, pts.max(0) + 22.0)

    # humerus
    S0 = Hc + np.array([6.0, 4.0, -24.0])
    S1 = S0 + np.array([9.0, 4.0, -118.0]) * j(0.03)
    GT = Hc + np.array([15.0, -3.0, 6.0])
    LT = Hc + np.array([3.0, -19.0, -4.0])

    def hum(p):
        head = np.linalg.norm(p - Hc, axis=1) - r_head
        F = _smin(head, _capsule(p, Hc + np.array([4.0, 2.0, -8.0]), S0, 15.5, 12.0), 5.0)
        F = _smin(F, _ellipsoid(p, GT, (8.0, 12.0, 12.0)), 4.0)
        F = _smin(F, np.linalg.norm(p - LT, axis=1) - 6.5, 3.0)
        return _smin(F, _capsule(p, S0, S1, 12.0, 10.5), 4.0)

    hum_box = (np.minimum(Hc, S1) - 30.0, np.maximum(Hc, S1) + 30.0)

    # clavicle: medial end at the manubrium's clavicular notch, lateral end at the acromion
    M0 = sternum_top + np.array([32.0, -4.0, -3.0]) - 4.0 * sternum_ax
    M1 = M0 + np.array([26.0, -5.0, 6.0])
    L = P4 + np.array([-6.0, -3.0, 1.0])
    M2 = M0 + 0.55 * (L - M0) + np.array([2.0, -12.0, 0.0])
    M3 = M0 + 0.82 * (L - M0) + np.array([-2.0, -2.0, 0.0])
    clav_tube = _Tube([M0, M1, M2, M3, L], lambda s: np.interp(s, [0, 0.12, 0.5, 0.8, 1], [10.0, 7.5, 6.0, 4.6, 4.2]),
                      lambda s: np.interp(s, [0, 0.12, 0.5, 0.8, 1], [10.0, 7.0, 6.0, 8.0, 9.0]), 8.0, 3.0)
    clav_box = clav_tube.bounds()
    return _Shoulder(scap, hum, clav_tube, scap_box, hum_box, clav_box, Hc, r_head, (S0, S1))


def _ellipsoid_oriented(p, c, n, r):
    """Ellipsoid with its first axis along n (radii r: along n, horizontal, vertical-ish)."""
    n = np.asarray(n, float) / np.linalg.norm(n)
    e2 = np.cross(np.array([0.0, 0.0, 1.0]), n)
    e2 /= np.linalg.norm(e2)
    e3 = np.cross(n, e2)
    d = p - np.asarray(c, float)
    q = np.column_stack([d @ n, d @ e2, d @ e3])
    return _ellipsoid(q, np.zeros(3), r)


@dataclass
class _Anatomy:
    bones: list
    vertebrae: list
    rib_lateral: list        # (k, z, W) of the left ribs' lateral points
    rib_ends: dict           # (side, k) -> anterior end point
    sternum: tuple           # top, bottom, axis
    humeri: dict             # side -> (Hc, r_head, S0, S1)
    rib_lines: list = field(default_factory=list)   # centreline samples of every rib (a frame)
    cage: object = None


def _build_anatomy(seed):
    rng = np.random.default_rng([int(seed), 1])
    verts = _vertebrae(rng)
    bones = []
    label = 1
    for v in verts:
        f, lo, hi = _vertebra_field(v)
        bones.append(_BoneDef(f"vertebrae_T{v['k']}", label, "vertebra", f, lo, hi))
        label += 1
    st_f, st_lo, st_hi, st_top, st_bot, st_ax = _sternum(rng)
    rib_ends, rib_lateral, rib_lines = {}, [], []
    ribs = {"left": [], "right": []}
    for side in ("left", "right"):
        for k in range(1, 13):
            tube, end, lat = _rib_tube(verts[k - 1], k, rng)
            lo, hi = tube.bounds()
            if side == "right":
                f = _mirror(tube)
                lo, hi = np.array([-hi[0], lo[1], lo[2]]), np.array([-lo[0], hi[1], hi[2]])
                end = end * np.array([-1, 1, 1])
            else:
                f = tube
                rib_lateral.append((k, float(lat[2]), float(lat[0])))
            rib_ends[(side, k)] = end
            rib_lines.append(tube.C * (np.array([-1.0, 1, 1]) if side == "right" else 1.0))
            bones.append(_BoneDef(f"rib_{side}_{k}", label, "rib", f, lo, hi))
            ribs[side].append(f)
            label += 1
    bones.append(_BoneDef("sternum", label, "sternum", st_f, st_lo, st_hi))
    label += 1
    humeri = {}
    shoulders = {}
    for side in ("left", "right"):
        rib_fields = ribs["left"][:9]
        if side == "left":
            sh = _shoulder_left(rng, rib_fields, st_top, st_ax)
        else:
            sh = _shoulder_left(rng, rib_fields, st_top * np.array([-1, 1, 1]), st_ax * np.array([-1, 1, 1]))
        shoulders[side] = sh
    for kind_name, attr, boxattr in (("clavicula", "clav", "clav_box"), ("scapula", "scap", "scap_box"),
                                     ("humerus", "hum", "hum_box")):
        for side in ("left", "right"):
            sh = shoulders[side]
            f = getattr(sh, attr)
            lo, hi = (np.asarray(b, float) for b in getattr(sh, boxattr))
            if side == "right":
                f = _mirror(f)
                lo, hi = np.array([-hi[0], lo[1], lo[2]]), np.array([-lo[0], hi[1], hi[2]])
            kind = {"clavicula": "clavicle", "scapula": "scapula", "humerus": "humerus"}[kind_name]
            bones.append(_BoneDef(f"{kind_name}_{side}", label, kind, f, lo, hi))
            label += 1
    for side in ("left", "right"):
        sh = shoulders[side]
        m = np.array([1.0, 1, 1]) if side == "left" else np.array([-1.0, 1, 1])
        humeri[side] = (sh.Hc * m, sh.r_head, sh.shaft[0] * m, sh.shaft[1] * m)
    anat = _Anatomy(bones, verts, rib_lateral, rib_ends, (st_top, st_bot, st_ax), humeri, rib_lines)
    anat.cage = _Cage(anat)
    return anat


# ---------------------------------------------------------------------------- background

CAGE_CENTRE = np.array([0.0, -38.0])


def _cartilage_lines(anat):
    """(side, k, end, mid, target) of the costal cartilages of ribs 1-10."""
    top, bot, ax = anat.sternum
    out = []
    for (side, k), end in anat.rib_ends.items():
        if k > 10:
            continue
        s = 1.0 if side == "left" else -1.0
        if k <= 7:
            frac = (k - 0.7) / 7.3
            target = top + (bot - top) * (0.08 + 0.8 * frac) + np.array([s * (17.0 if k > 1 else 22.0), 0.0, 0.0])
        else:
            target = top + (bot - top) * 0.93 + np.array([s * 22.0, -4.0, 6.0 * (k - 8)])
        mid = 0.5 * (end + target) + np.array([0.0, -6.0, 0.0])
        out.append((side, k, end, mid, target))
    return out


class _Cage:
    """Inner radius of the rib cage around CAGE_CENTRE as a table over (z, angle): the smallest
    radius of the ribs' centrelines, the costal cartilages and the sternum within +-7 mm of z, per
    5 degree sector (angle 0 = posterior, increasing towards the left), gaps filled by
    interpolation; the lungs end 8 mm inside it."""

    def __init__(self, anat, dz=2.0, dth=5.0):
        pts = [np.vstack(anat.rib_lines)]
        for side, k, end, mid, target in _cartilage_lines(anat):
            t = np.linspace(0, 1, 40)[:, None]
            pts.append(np.vstack([end + t * (mid - end), mid + t * (target - mid)]))
        top, bot, _ = anat.sternum
        t = np.linspace(0, 1, 200)[:, None]
        st = top + t * (bot - top)
        pts += [st + np.array([dx, 0.0, 0.0]) for dx in (-15.0, 0.0, 15.0)]
        p = np.vstack(pts)
        rel = p[:, :2] - CAGE_CENTRE
        r = np.hypot(rel[:, 0], rel[:, 1])
        th = np.degrees(np.arctan2(rel[:, 0], rel[:, 1])) % 360.0
        self.z0, self.dz, self.dth = -200.0, dz, dth
        nz, nt = int(400 / dz) + 1, int(360 / dth)
        zi = np.round((p[:, 2] - self.z0) / dz).astype(int)
        ti = np.round(th / dth).astype(int) % nt
        win = int(round(7.0 / dz))
        tab2 = np.full((nz, nt), np.inf)
        for dzi in range(-win, win + 1):
            zz = np.clip(zi + dzi, 0, nz - 1)
            for dti in (-1, 0, 1):
                np.minimum.at(tab2, (zz, (ti + dti) % nt), r)
        tab = np.where(np.isfinite(tab2), tab2, np.nan)
        # fill the sectors without ribs (along the angle, periodic), then the rows without any
        for i in range(nz):
            row = tab[i]
            ok = np.isfinite(row)
            if ok.sum() >= 2:
                idx = np.flatnonzero(ok)
                tab[i] = np.interp(np.arange(nt), idx, row[idx], period=nt)
        rows = np.flatnonzero(np.isfinite(tab).all(axis=1))
        self.z_lo, self.z_hi = self.z0 + dz * rows[0], self.z0 + dz * rows[-1]
        for i in range(nz):
            if not np.isfinite(tab[i]).all():
                j = rows[np.argmin(np.abs(rows - i))]
                tab[i] = tab[j]
        self.tab = tab

    def radius(self, z, th_deg):
        fz = np.clip((z - self.z0) / self.dz, 0, self.tab.shape[0] - 1.001)
        ft = (th_deg % 360.0) / self.dth
        i0 = np.floor(fz).astype(int)
        j0 = np.floor(ft).astype(int) % self.tab.shape[1]
        j1 = (j0 + 1) % self.tab.shape[1]
        wz, wt = fz - i0, ft - np.floor(ft)
        r0 = self.tab[i0, j0] * (1 - wt) + self.tab[i0, j1] * wt
        r1 = self.tab[i0 + 1, j0] * (1 - wt) + self.tab[i0 + 1, j1] * wt
        return r0 * (1 - wz) + r1 * wz


def _background(anat, a, sigma):
    """HU of the background at points a (n, 3) (a frame), edges smoothed by sigma (mm)."""
    x, y, z = a[:, 0], a[:, 1], a[:, 2]
    ax_ = np.abs(x)
    cage = anat.cage

    def inside(sdf):
        return 0.5 * (1.0 - erf(sdf / (math.sqrt(2.0) * sigma)))

    rel_x, rel_y = x - CAGE_CENTRE[0], y - CAGE_CENTRE[1]
    rr = np.hypot(rel_x, rel_y)
    th = np.degrees(np.arctan2(rel_x, rel_y))
    r_cage = cage.radius(np.clip(z, cage.z_lo, cage.z_hi), th)
    r_lat = cage.radius(np.clip(z, cage.z_lo, cage.z_hi), np.where(x >= 0, 90.0, 270.0))
    # body: superellipse torso (the cage + 30 mm), shoulders, neck; arms around the humeri
    zs = np.clip((z - 40.0) / 50.0, 0.0, 1.0)
    X = (np.maximum(r_lat, 100.0) + 30.0) * (1 - zs) + 172.0 * zs
    X = np.where(z > 105.0, 172.0 - (z - 105.0) * 2.2, X)
    X = np.maximum(X, 70.0)
    yc, Yb, Yf = -25.0, 118.0, 114.0
    Y = np.where(y > yc, Yb, Yf)
    n = 2.6
    r = (np.abs(x / X) ** n + np.abs((y - yc) / Y) ** n) ** (1.0 / n)
    body = (r - 1.0) * np.minimum(X, Y) * 0.9
    for side in ("left", "right"):
        Hc, rh, S0, S1 = anat.humeri[side]
        top = Hc + np.array([0.0, 0.0, 10.0])
        bot = S1 + (S1 - S0) / np.linalg.norm(S1 - S0) * 200.0
        body = _smin(body, _capsule(a, top, bot, 48.0), 20.0)
    hu = AIR_HU + inside(body) * (FAT_HU - AIR_HU) + inside(body + 10.0) * (SOFT_HU - FAT_HU)
    # lungs: inside the cage, outside the mediastinum, the heart and the spine, above the
    # diaphragm, below the apex
    lung = rr - (r_cage - 8.0)
    med = _ellipse2(x, y + 45.0, 30.0 + 8.0 * np.clip((60.0 - z) / 120.0, 0, 1), 75.0)
    lung = _smax(lung, -med, 6.0)
    v0 = anat.vertebrae[6]
    lung = _smax(lung, -(np.hypot(x, y) - (v0["rx"] + 12.0)), 6.0)
    heart = _ellipsoid(a, (20.0, -60.0, -28.0), (60.0, 44.0, 50.0))
    lung = _smax(lung, -heart, 4.0)
    v10 = anat.vertebrae[9]
    z_dia = v10["zc"] + 30.0 - 0.003 * x ** 2 - 0.25 * np.clip(y + 10.0, 0, None) + np.where(x < 0, 8.0, 0.0)
    lung = np.maximum(lung, z_dia - z)
    z_apex = cage.z_hi + 6.0 - 0.006 * (ax_ - 40.0) ** 2
    lung = np.maximum(lung, z - z_apex)
    w_lung = inside(lung)
    hu = hu + w_lung * (LUNG_HU - hu)
    hu = hu + inside(heart) * (1.0 - w_lung) * (HEART_HU - hu)
    # discs (between consecutive bodies) and costal cartilage
    for va, vb in zip(anat.vertebrae[:-1], anat.vertebrae[1:]):
        zt, zb = va["zc"] - va["hh"], vb["zc"] + vb["hh"]
        sel = np.flatnonzero((z > zb - 4) & (z < zt + 4) & (ax_ < va["rx"] + 5) & (np.abs(y) < va["ry"] + 5))
        if len(sel):
            rx, ry = 0.5 * (va["rx"] + vb["rx"]), 0.5 * (va["ry"] + vb["ry"])
            d = _rounded(_ellipse2(x[sel], y[sel], rx, ry), np.abs(z[sel] - 0.5 * (zt + zb)) - 0.5 * (zt - zb) - 0.6, 1.0)
            hu[sel] += inside(d) * (DISC_HU - hu[sel])
    for side, k, end, mid, target in _cartilage_lines(anat):
        lo = np.minimum.reduce([end, mid, target]) - 8.0
        hi = np.maximum.reduce([end, mid, target]) + 8.0
        sel = np.flatnonzero(np.all((a > lo) & (a < hi), axis=1))
        if len(sel):
            d = np.minimum(_capsule(a[sel], end, mid, 4.5), _capsule(a[sel], mid, target, 4.5))
            hu[sel] += inside(d) * (CARTILAGE_HU - hu[sel])
    return hu


# ---------------------------------------------------------------------------- fine fields

class _Field:
    """A bone's F on the global fine grid u = h * idx, block-sparse: blocks of BLOCK^3 nodes over
    the box [lo, lo + BLOCK * nb) (node indices x-y-z); bmap (z, y, x) of blocks: -1 outside
    (F = +BIG), -2 deep inside (F = -BIG), >= 0 the slot of data (slots, B, B, B) (z, y, x)."""

    def __init__(self, lo, nb, h):
        self.lo = np.asarray(lo, int)
        self.nb = np.asarray(nb, int)
        self.h = float(h)
        self.bmap = np.full(tuple(self.nb[::-1]), -1, np.int32)
        self.data = np.zeros((0, BLOCK, BLOCK, BLOCK), np.float32)

    @property
    def shape_nodes(self):
        return tuple((self.nb * BLOCK)[::-1])

    def node_values(self, idx):
        """F at global node indices idx (n, 3) x-y-z."""
        rel = np.asarray(idx) - self.lo
        b = rel // BLOCK
        inb = np.all((b >= 0) & (b < self.nb), axis=1)
        out = np.full(len(rel), BIG, np.float32)
        if not inb.any():
            return out
        b, r = b[inb], rel[inb] % BLOCK
        m = self.bmap[b[:, 2], b[:, 1], b[:, 0]]
        val = np.where(m == -2, -BIG, BIG).astype(np.float32)
        s = m >= 0
        val[s] = self.data[m[s], r[s, 2], r[s, 1], r[s, 0]]
        out[inb] = val
        return out

    def sample(self, u):
        """Trilinear F at grid-frame points u (n, 3) mm."""
        t = np.asarray(u, float) / self.h
        i0 = np.floor(t).astype(np.int64)
        f = t - i0
        out = np.zeros(len(t))
        for dx in (0, 1):
            wx = f[:, 0] if dx else 1.0 - f[:, 0]
            for dy in (0, 1):
                wy = f[:, 1] if dy else 1.0 - f[:, 1]
                for dz in (0, 1):
                    wz = f[:, 2] if dz else 1.0 - f[:, 2]
                    out += wx * wy * wz * self.node_values(i0 + np.array([dx, dy, dz]))
        return out

    def dense(self, z0=0, z1=None):
        """F on the box's nodes with local z index in [z0, z1) (multiples of BLOCK, or the end)
        (z, y, x) float32."""
        B = BLOCK
        nz = self.nb[2] * B
        z1 = nz if z1 is None else z1
        b0, b1 = z0 // B, -(-z1 // B)
        bm = self.bmap[b0:b1]
        out = np.empty(((b1 - b0) * B, self.nb[1] * B, self.nb[0] * B), np.float32)
        view = out.reshape(b1 - b0, B, self.nb[1], B, self.nb[0], B).transpose(0, 2, 4, 1, 3, 5)
        view[bm == -1] = BIG
        view[bm == -2] = -BIG
        s = bm >= 0
        view[s] = self.data[bm[s]]
        return out[z0 - b0 * B:z1 - b0 * B]


class _Frame:
    """CT grid and frames."""

    def __init__(self, shape, spacing, angles_deg):
        self.size = np.asarray(shape, int)
        self.spacing = np.asarray(spacing, float)
        self.D = _rotation(angles_deg)
        centre_u = self.spacing * (self.size - 1) / 2.0
        self.origin = P_ANAT + FOV_CENTRE - self.D @ centre_u
        self.a0 = self.origin - P_ANAT  # a = a0 + D u

    def u_to_a(self, u):
        return self.a0 + np.asarray(u, float) @ self.D.T

    def a_to_u(self, a):
        return (np.asarray(a, float) - self.a0) @ self.D

    def u_to_phys(self, u):
        return self.origin + np.asarray(u, float) @ self.D.T

    def phys_to_u(self, x):
        return (np.asarray(x, float) - self.origin) @ self.D


def _box_u(frame, lo_a, hi_a):
    """Grid-frame box of an a-frame box (its 8 corners)."""
    c = np.array([[lo_a[0] if i & 1 else hi_a[0], lo_a[1] if i & 2 else hi_a[1],
                   lo_a[2] if i & 4 else hi_a[2]] for i in range(8)])
    u = frame.a_to_u(c)
    return u.min(0), u.max(0)


def _coarse_fields(frame, bones, step=3.0):
    """Each bone's F0 on a global coarse grid (step mm, grid frame) over its box: dict name ->
    (index lo (x-y-z), array (z, y, x))."""
    out = {}
    for b in bones:
        lo_u, hi_u = _box_u(frame, b.lo, b.hi)
        i0 = np.floor(lo_u / step).astype(int) - 1
        i1 = np.ceil(hi_u / step).astype(int) + 2
        axes = [step * np.arange(i0[a], i1[a]) for a in range(3)]
        Z, Y, X = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
        u = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
        f = b.f0(frame.u_to_a(u)).astype(np.float32).reshape(X.shape)
        border = min(float(f[[0, -1]].min()), float(f[:, [0, -1]].min()), float(f[:, :, [0, -1]].min()))
        if border < 2.0:
            raise RuntimeError(f"{b.name}: its box cuts the bone (field {border:.2f} mm at the box border)")
        out[b.name] = (i0, f)
    return out


def _neighbours(bones, coarse, step=3.0):
    """Pairs (i, j, gap) of bones that come closer than their gap + the coarse grid's reach."""
    pairs = []
    for i in range(len(bones)):
        for j in range(i + 1, len(bones)):
            a, b = bones[i], bones[j]
            g = pair_gap(a.kind, b.kind)
            ia, fa = coarse[a.name]
            ib, fb = coarse[b.name]
            lo = np.maximum(ia, ib)
            hi = np.minimum(ia + np.array(fa.shape[::-1]), ib + np.array(fb.shape[::-1]))
            if np.any(hi <= lo):
                continue
            sa = fa[lo[2] - ia[2]:hi[2] - ia[2], lo[1] - ia[1]:hi[1] - ia[1], lo[0] - ia[0]:hi[0] - ia[0]]
            sb = fb[lo[2] - ib[2]:hi[2] - ib[2], lo[1] - ib[1]:hi[1] - ib[1], lo[0] - ib[0]:hi[0] - ib[0]]
            # both fields small at one node (their midpoint): the bones come close there
            m = float(np.maximum(sa, sb).min())
            if m < 0.5 * CARVE_FACTOR * g + 0.5 * step * math.sqrt(3.0) + 1.5:
                pairs.append((i, j, g, m))
    return pairs


def _make_field(frame, b, h, nbrs, coarse, step=3.0):
    """Block-sparse fine field of bone b carved against its neighbours [(bone, gap)]."""
    i0, fc = coarse[b.name]
    inside = np.argwhere(fc < 2.0 + step)  # (z, y, x) coarse nodes near / in the bone
    if not len(inside):
        raise RuntimeError(f"{b.name}: empty")
    lo_u = (i0 + inside.min(0)[::-1]) * step - step
    hi_u = (i0 + inside.max(0)[::-1]) * step + step
    lo = (np.floor(lo_u / h / BLOCK).astype(int)) * BLOCK
    nb = np.ceil((hi_u / h - lo) / BLOCK).astype(int) + 1
    fld = _Field(lo, nb, h)
    B = BLOCK
    R = math.sqrt(3.0) * (B / 2.0 + 0.5) * h
    thr = R + max(1.5, math.sqrt(3.0) * h + 0.2)  # the corners of every cell near the surface are evaluated
    bz, by, bx = np.meshgrid(*[np.arange(n) for n in nb[::-1]], indexing="ij")
    bidx = np.column_stack([bx.ravel(), by.ravel(), bz.ravel()])
    cen_u = (lo + bidx * B + (B - 1) / 2.0) * h
    cen_a = frame.u_to_a(cen_u)
    f0c = b.f0(cen_a)
    Fc = f0c.copy()
    active = []
    cand = np.flatnonzero(f0c <= thr)  # the carve only raises F: the others stay outside
    for nb_bone, g in nbrs:
        fb = np.full(len(f0c), BIG * 10)
        fb[cand] = nb_bone.f0(cen_a[cand])
        gc = CARVE_FACTOR * g
        Fc = np.maximum(Fc, 0.5 * (f0c - fb) + 0.5 * gc)
        active.append((fb - R < gc + 0.5) & (f0c - R < gc + 0.5))
    cls = np.where(Fc > thr, -1, np.where(Fc < -thr, -2, 0))
    band = np.flatnonzero(cls == 0)
    flat = fld.bmap.reshape(-1)
    flat[cls == -2] = -2
    flat[band] = np.arange(len(band))
    fld.data = np.zeros((len(band), B, B, B), np.float32)
    oz, oy, ox = np.meshgrid(np.arange(B), np.arange(B), np.arange(B), indexing="ij")
    off = np.column_stack([ox.ravel(), oy.ravel(), oz.ravel()])  # (B^3, 3) in (z, y, x) order
    chunk = max(1, 200_000 // B ** 3)
    for c0 in range(0, len(band), chunk):
        sel = band[c0:c0 + chunk]
        u = ((lo + bidx[sel] * B)[:, None, :] + off[None]).reshape(-1, 3) * h
        a = frame.u_to_a(u)
        f0 = b.f0(a)
        F = f0.copy()
        for (nb_bone, g), act in zip(nbrs, active):
            am = act[sel]
            if not am.any():
                continue
            rows = (np.flatnonzero(am)[:, None] * B ** 3 + np.arange(B ** 3)[None]).ravel()
            fb = nb_bone.f0(a[rows])
            F[rows] = _smax(F[rows], 0.5 * (f0[rows] - fb) + 0.5 * CARVE_FACTOR * g, 0.6)
        fld.data[c0:c0 + len(sel)] = F.reshape(len(sel), B, B, B).astype(np.float32)
    return fld


def _truth_mesh(frame, fld):
    F = fld.dense()
    v, f = _zero_set_mesh(F, fld.h, fld.lo * fld.h)
    del F
    return Surface(frame.u_to_phys(v), f, "LPS")


# ---------------------------------------------------------------------------- CT

def _kernel(ct_axis, fine_axis, width, sigma):
    """Sparse (len(ct_axis), len(fine_axis)) weights: a box of width convolved with a Gaussian
    of sigma (width 0: the Gaussian alone), rows normalised."""
    h = fine_axis[1] - fine_axis[0]
    reach = 0.5 * width + 4.0 * sigma + h
    rows, cols, vals = [], [], []
    s = max(sigma, 1e-6) * math.sqrt(2.0)
    for i, c in enumerate(ct_axis):
        j0 = max(0, int(np.floor((c - reach - fine_axis[0]) / h)))
        j1 = min(len(fine_axis), int(np.ceil((c + reach - fine_axis[0]) / h)) + 1)
        d = c - fine_axis[j0:j1]
        if width > 0:
            w = 0.5 * (erf((d + 0.5 * width) / s) - erf((d - 0.5 * width) / s))
        else:
            w = np.exp(-0.5 * (d / sigma) ** 2)
        if w.sum() <= 0:
            continue
        w /= w.sum()
        rows += [i] * len(w)
        cols += list(range(j0, j1))
        vals += list(w)
    return sparse.csr_matrix((np.asarray(vals, np.float32), (rows, cols)), shape=(len(ct_axis), len(fine_axis)))


def _bone_fields_hu(rng, lo_u, hi_u):
    """Seeded smooth fields of a bone (cortex thickness, cortex HU, trabecular HU)."""
    return {"tc": _Lattice(rng, lo_u, hi_u, 20.0), "chu": _Lattice(rng, lo_u, hi_u, 25.0),
            "thu": _Lattice(rng, lo_u, hi_u, 18.0)}


def _form_ct(frame, anat, bones, fields, h, psf, thick, noise, seed):
    t0 = time.perf_counter()
    nx, ny, nz = frame.size
    sp = frame.spacing
    sig_bg = math.sqrt(psf ** 2 + sp[0] ** 2 / 12.0)
    bg = np.empty((nz, ny, nx), np.float32)
    # sub-millimetre pixels: the (smooth) background on every second pixel, linearly interpolated
    stride = 2 if max(sp[0], sp[1]) < 1.0 else 1
    ci, cj = np.arange(0, nx + stride - 1, stride), np.arange(0, ny + stride - 1, stride)
    ii, jj = np.meshgrid(ci, cj, indexing="xy")
    plane = np.column_stack([ii.ravel() * sp[0], jj.ravel() * sp[1]])
    if stride > 1:
        from scipy.ndimage import map_coordinates
        J, I = np.meshgrid(np.arange(ny) / stride, np.arange(nx) / stride, indexing="ij")
        up = np.stack([J.ravel(), I.ravel()])
    for k in range(nz):
        u = np.column_stack([plane, np.full(len(plane), k * sp[2])])
        v = _background(anat, frame.u_to_a(u), sig_bg).reshape(len(cj), len(ci)).astype(np.float32)
        bg[k] = v if stride == 1 else map_coordinates(v, up, order=1, mode="nearest").reshape(ny, nx)
    t_bg = time.perf_counter() - t0
    ct = bg.copy()
    sz = thick / 2.3548
    # global fine axes covering the CT (+ the kernels' reach)
    reach = np.array([0.5 * sp[0] + 4 * psf, 0.5 * sp[1] + 4 * psf, 4 * sz]) + 2 * h
    f_lo = np.floor(-reach / h).astype(int)
    f_hi = np.ceil(((frame.size - 1) * sp + reach) / h).astype(int) + 1
    for b in bones:  # the fine axes also cover every bone's box (the kernels weigh what they reach)
        fld = fields[b.name]
        f_lo = np.minimum(f_lo, fld.lo)
        f_hi = np.maximum(f_hi, fld.lo + fld.nb * BLOCK)
    faxes = [h * np.arange(f_lo[a], f_hi[a]) for a in range(3)]
    ct_axes = [sp[a] * np.arange(frame.size[a]) for a in range(3)]
    K = [_kernel(ct_axes[0], faxes[0], sp[0], psf), _kernel(ct_axes[1], faxes[1], sp[1], psf),
         _kernel(ct_axes[2], faxes[2], 0.0, sz)]
    rng_tex = np.random.default_rng([int(seed), 3, 999])
    from scipy.ndimage import gaussian_filter
    tex = gaussian_filter(rng_tex.normal(size=(64, 64, 64)).astype(np.float32), 0.8 / h, mode="wrap")
    tex /= tex.std()
    nt = 64
    for index, b in enumerate(bones):
        fld = fields[b.name]
        kind = KINDS[b.kind]
        n_nodes = np.array(fld.shape_nodes[::-1])
        # the box within the global fine axes
        g0 = fld.lo - f_lo
        g1 = g0 + n_nodes
        Ks = [K[a][:, g0[a]:g1[a]] for a in range(3)]
        rows = [np.flatnonzero(np.asarray(Ks[a].sum(axis=1)).ravel() > 0) for a in range(3)]
        Ks = [Ks[a][rows[a]] for a in range(3)]
        KxT = Ks[0].T.tocsr()
        acc = np.zeros((n_nodes[2], len(rows[1]), len(rows[0])), np.float32)
        u_lo, u_hi = fld.lo * h, (fld.lo + n_nodes - 1) * h
        rng = np.random.default_rng([int(seed), 3, index])
        flds = _bone_fields_hu(rng, u_lo, u_hi)
        xs = h * (fld.lo[0] + np.arange(n_nodes[0]))
        ys = h * (fld.lo[1] + np.arange(n_nodes[1]))
        slab = max(BLOCK, (int(4e6 // (n_nodes[0] * n_nodes[1])) // BLOCK) * BLOCK)
        for z0 in range(0, n_nodes[2], slab):
            z1 = min(n_nodes[2], z0 + slab)
            if np.all(fld.bmap[z0 // BLOCK:(z1 - 1) // BLOCK + 1] == -1):
                continue
            F = fld.dense(z0, z1)
            occ = np.clip(0.5 - F / h, 0.0, 1.0)
            nzr = np.flatnonzero(occ.any(axis=(1, 2)))
            if not len(nzr):
                continue
            zs = h * (fld.lo[2] + np.arange(z0, z1))
            tc = kind["cortex"] * (1.0 + 0.3 * np.clip(flds["tc"].grid(xs, ys, zs), -1.5, 1.5))
            if b.kind == "humerus":
                tc = tc * _humerus_cortex(frame, anat, b.name, xs, ys, zs)
            tc = np.clip(tc, 0.4, 2.5)
            chu = np.clip(kind["cortex_hu"] + 120.0 * flds["chu"].grid(xs, ys, zs), 1000.0, 1400.0)
            thu = kind["trab_hu"] + 35.0 * np.clip(flds["thu"].grid(xs, ys, zs), -1.5, 1.5)
            zi = (fld.lo[2] + np.arange(z0, z1)) % nt
            yi = (fld.lo[1] + np.arange(n_nodes[1])) % nt
            xi = (fld.lo[0] + np.arange(n_nodes[0])) % nt
            thu = thu + 25.0 * tex[np.ix_(zi, yi, xi)]
            thu = np.clip(thu + 40.0 * np.exp(-np.maximum(-F - tc, 0.0) / 1.5), 150.0, 300.0)
            occ_c = np.clip(0.5 - (F + tc) / h, 0.0, 1.0)
            # background under the bone: the CT grid's background, nearest voxel
            m = occ > 0
            idx = np.argwhere(m)
            u = np.column_stack([xs[idx[:, 2]], ys[idx[:, 1]], zs[idx[:, 0]]])
            vox = np.rint(u / sp).astype(int)
            vox = np.clip(vox, 0, frame.size - 1)
            bgv = bg[vox[:, 2], vox[:, 1], vox[:, 0]]
            delta = np.zeros_like(F)
            delta[m] = occ[m] * (chu[m] - bgv) + occ_c[m] * (thu[m] - chu[m])
            del F, occ, occ_c, tc, chu, thu
            t = (KxT.T @ delta.reshape(-1, n_nodes[0]).T).T  # (z*y, ncx)
            t = t.reshape(z1 - z0, n_nodes[1], -1)
            t = np.einsum("zyx->yzx", t).reshape(n_nodes[1], -1)
            t = (Ks[1] @ t).reshape(len(rows[1]), z1 - z0, -1)
            acc[z0:z1] = np.einsum("yzx->zyx", t)
        out = (Ks[2] @ acc.reshape(n_nodes[2], -1)).reshape(len(rows[2]), len(rows[1]), len(rows[0]))
        ct[np.ix_(rows[2], rows[1], rows[0])] += out
        del acc, out
    t_form = time.perf_counter() - t0
    ct += np.random.default_rng([int(seed), 4]).normal(0.0, noise, size=ct.shape).astype(np.float32)
    arr = np.clip(np.rint(ct), -1024, 3071).astype(np.int16)
    del ct
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing([float(v) for v in sp])
    img.SetOrigin([float(v) for v in frame.origin])
    img.SetDirection([float(v) for v in frame.D.ravel()])
    return img, bg, {"seconds": t_form, "background_seconds": t_bg}


def _humerus_cortex(frame, anat, name, xs, ys, zs):
    """Multiplier of the humerus's cortical thickness: 1 in the head, 3 in the shaft."""
    side = name.split("_")[1]
    Hc, rh, S0, S1 = anat.humeri[side]
    zc = frame.u_to_a(np.column_stack([np.full(len(zs), xs.mean()), np.full(len(zs), ys.mean()), zs]))[:, 2]
    t = np.clip((Hc[2] - 20.0 - zc) / 40.0, 0.0, 1.0)
    return (1.0 + 2.1 * t)[:, None, None]


# ---------------------------------------------------------------------------- labels

def _labels_ai(frame, bones, fields, grid_mm, seed, ct):
    grid = np.broadcast_to(np.asarray(grid_mm, float), (3,)).copy()
    rng = np.random.default_rng([int(seed), 5])
    box_lo = -0.5 * frame.spacing
    box_hi = (frame.size - 0.5) * frame.spacing
    start = box_lo + (1.0 - rng.uniform(0.0, 1.0, 3)) * 0.5 * grid
    size = np.ceil((box_hi - start) / grid + 0.5).astype(int)
    best = np.zeros(tuple(size[::-1]), np.uint8)
    best_n = np.zeros(tuple(size[::-1]), np.int8)
    total = np.zeros(tuple(size[::-1]), np.int8)
    t = (np.arange(3) + 0.5) / 3 - 0.5
    off = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3) * grid
    r = 0.6 * float(np.linalg.norm(grid)) + 0.2  # beyond the half-diagonal: one side only
    from scipy.ndimage import map_coordinates
    for b in bones:
        fld = fields[b.name]
        lo_u = fld.lo * fld.h
        hi_u = (fld.lo + fld.nb * BLOCK) * fld.h
        i0 = np.clip(np.floor((lo_u - start) / grid).astype(int), 0, size)
        i1 = np.clip(np.ceil((hi_u - start) / grid).astype(int) + 1, 0, size)
        axes = [start[a] + grid[a] * np.arange(i0[a], i1[a]) for a in range(3)]
        Z, Y, X = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
        u = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
        Fd = fld.dense()

        def samp(q):
            c = (q / fld.h - fld.lo)[:, ::-1].T
            return map_coordinates(Fd, c, order=1, mode="constant", cval=BIG)

        f = samp(u)
        cnt = np.where(f < 0, 27, 0).astype(np.int8)
        near = np.flatnonzero(np.abs(f) < r)
        if len(near):
            q = (u[near][:, None, :] + off[None]).reshape(-1, 3)
            cnt[near] = (samp(q) < 0).reshape(-1, 27).sum(axis=1)
        del Fd
        cnt = cnt.reshape(X.shape)
        sl = (slice(i0[2], i1[2]), slice(i0[1], i1[1]), slice(i0[0], i1[0]))
        bb, bn, tt = best[sl], best_n[sl], total[sl]
        better = cnt > bn
        bb[better] = b.label
        bn[better] = cnt[better]
        tt += cnt
    bg_votes = 27 - total
    arr = np.where(best_n > bg_votes, best, 0).astype(np.uint8)
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing([float(v) for v in grid])
    img.SetDirection([float(v) for v in frame.D.ravel()])
    img.SetOrigin([float(v) for v in frame.u_to_phys(start[None])[0]])
    return sitk.Resample(img, ct, sitk.Transform(), sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8)


# ---------------------------------------------------------------------------- measurements

def _mesh_gap(frame, sa: Surface, sb: Surface, fa, fb, reach=6.0):
    """Smallest distance (mm) of a vertex of one surface to the other surface (both ways; only
    the vertices where the other's field is below ``reach`` are measured; inf if none)."""
    best = float("inf")
    lo = np.maximum(sa.vertices.min(0), sb.vertices.min(0)) - reach
    hi = np.minimum(sa.vertices.max(0), sb.vertices.max(0)) + reach
    for s, o, fo in ((sa, sb, fb), (sb, sa, fa)):
        v = s.vertices[np.all((s.vertices > lo) & (s.vertices < hi), axis=1)]
        v = v[fo.sample(frame.phys_to_u(v)) < reach]
        if len(v):
            best = min(best, float(_locator(o).query(v)[0].min()))
    return best


_LOC = {}


def _locator(s: Surface):
    from metrics import TriangleLocator

    hit = _LOC.get(id(s))
    if hit is None or hit[0] is not s:
        if len(_LOC) > 64:
            _LOC.clear()
        hit = _LOC[id(s)] = (s, TriangleLocator(s))
    return hit[1]


def _components(s: Surface):
    from scipy.sparse.csgraph import connected_components

    f = s.faces
    n = len(s.vertices)
    e = np.vstack([f[:, [0, 1]], f[:, [1, 2]]])
    g = sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return int(connected_components(g, directed=False)[0])


# ---------------------------------------------------------------------------- entry point

@dataclass
class ChestPhantom:
    ct: sitk.Image
    labels: sitk.Image
    names: dict                 # label value -> name
    truths: dict                # label value -> Surface (physical LPS)
    info: dict
    _fields: dict = field(default_factory=dict, repr=False)
    _frame: object = None

    def sdf(self, label: int, physical_points) -> np.ndarray:
        """The truth's field (mm, negative inside; ~ signed distance near the surface) at
        physical LPS points, trilinear on the fine grid (+-6 far from the surface)."""
        u = self._frame.phys_to_u(np.asarray(physical_points, float).reshape(-1, 3))
        return self._fields[self.names[label]].sample(u)


def make_chest(seed: int = 0, shape=(512, 512, 300), spacing=(0.7, 0.7, 1.0), h: float = 0.5,
               angles_deg=(0.0, 0.0, 0.0), noise: float = 20.0, label_grid=1.5,
               psf_sigma: float = 0.5, slice_thickness: float | None = None,
               meshes: bool = True, measure_joints: bool = True) -> ChestPhantom:
    """A synthetic chest CT (int16 HU, LPS) with its AI-style label map (uint8, the CT's grid),
    names {label: name}, truth meshes {label: Surface} and ``info`` (bones, joints with their
    measured gaps, timings, peak memory). ``shape`` x ``spacing`` must cover about 358 x 358 x
    300 mm (the default field of view); ``h`` is the fine model step (0.5 mm; 0.8 for a quick
    coarse phantom); ``slice_thickness`` defaults to the slice spacing. ``meshes=False`` skips the
    truth meshes, ``measure_joints=False`` the exact gaps of the truth meshes."""
    t_all = time.perf_counter()
    timing = {}
    frame = _Frame(shape, spacing, angles_deg)
    t0 = time.perf_counter()
    anat = _build_anatomy(seed)
    bones = anat.bones
    step = max(3.0, 2.0 * h)
    coarse = _coarse_fields(frame, bones, step)
    pairs = _neighbours(bones, coarse, step)
    timing["anatomy_s"] = time.perf_counter() - t0
    nbrs = {b.name: [] for b in bones}
    for i, j, g, _ in pairs:
        nbrs[bones[i].name].append((bones[j], g))
        nbrs[bones[j].name].append((bones[i], g))
    t0 = time.perf_counter()
    fields = {b.name: _make_field(frame, b, h, nbrs[b.name], coarse, step) for b in bones}
    del coarse
    timing["fields_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    truths, binfo = {}, {}
    for b in bones:
        fld = fields[b.name]
        ev = int((fld.bmap >= 0).sum())
        binfo[b.name] = {"label": b.label, "kind": b.kind, "blocks_evaluated": ev}
        if meshes:
            s = _truth_mesh(frame, fld)
            truths[b.label] = s
            binfo[b.name].update(volume_ml=float(enclosed_volume(s.vertices, s.faces) / 1000.0),
                                 n_faces=int(len(s.faces)), components=_components(s),
                                 genus=_genus(s.vertices, s.faces) if len(s.faces) else None,
                                 extent_mm=[float(v) for v in (s.vertices.max(0) - s.vertices.min(0))])
    timing["meshes_s"] = time.perf_counter() - t0
    thick = float(slice_thickness or spacing[2])
    ct, bg, ct_info = _form_ct(frame, anat, bones, fields, h, psf_sigma, thick, noise, seed)
    del bg
    timing["ct_s"] = ct_info["seconds"]
    timing["ct_background_s"] = ct_info["background_seconds"]
    t0 = time.perf_counter()
    labels = _labels_ai(frame, bones, fields, label_grid, seed, ct)
    timing["labels_s"] = time.perf_counter() - t0
    joints = []
    t0 = time.perf_counter()
    for i, j, g, coarse_min in pairs:
        a, b = bones[i], bones[j]
        rec = {"a": a.name, "b": b.name, "gap_mm": g}
        if meshes and measure_joints:
            rec["min_distance_mm"] = _mesh_gap(frame, truths[a.label], truths[b.label],
                                               fields[a.name], fields[b.name])
        joints.append(rec)
    timing["joints_s"] = time.perf_counter() - t0
    timing["total_s"] = time.perf_counter() - t_all
    names = {b.label: b.name for b in bones}
    info = {"seed": int(seed), "shape": [int(v) for v in shape], "spacing": [float(v) for v in spacing],
            "slice_thickness": thick, "h": float(h), "psf_sigma": float(psf_sigma), "noise": float(noise),
            "label_grid": label_grid, "angles_deg": [float(v) for v in angles_deg],
            "origin": [float(v) for v in frame.origin], "direction": [float(v) for v in frame.D.ravel()],
            "bones": binfo, "joints": joints, "timing": timing, "peak_rss_mb": _peak_mb(),
            "vertebrae": [{k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in vp.items()}
                          for vp in anat.vertebrae]}
    ph = ChestPhantom(ct, labels, names, truths, info, {b.name: fields[b.name] for b in bones}, frame)
    ph.info["_anatomy"] = anat
    return ph


if __name__ == "__main__":
    import argparse
    import json

    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--small", action="store_true")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    kw = dict(shape=(160, 160, 100), spacing=(2.24, 2.24, 3.0), h=0.8) if args.small else {}
    t = time.perf_counter()
    ph = make_chest(args.seed, **kw)
    print(f"{time.perf_counter() - t:.1f} s, peak {_peak_mb():.0f} MB")
    print(json.dumps(ph.info["timing"], indent=1))
    for n, bi in ph.info["bones"].items():
        print(n, bi)
    for j in ph.info["joints"]:
        print(j)
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        sitk.WriteImage(ph.ct, os.path.join(args.out, "ct.nrrd"), True)
        sitk.WriteImage(ph.labels, os.path.join(args.out, "labels.nrrd"), True)
