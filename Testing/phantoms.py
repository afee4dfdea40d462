"""Synthetic CT phantoms of a femur-like bone with analytic ground truth.

The bone, the hip-like cup and the body are signed distance functions (SDF, negative
inside, mm) of capsules, spheres and ellipsoids joined by a polynomial smooth union.
The CT is formed by evaluating a HU model on a fine grid (half the pixel spacing
in-plane, a third or less of the slice thickness along z), applying the slice profile (box
of the slice thickness along z), an in-plane Gaussian PSF, sampling at the pixel centres
/ slice positions, adding Gaussian noise and rounding to int16.

The ground truth is the zero level set of the bone's outer-envelope SDF (no pores, no
foramina, no lesion): marching cubes on a fine grid, then every vertex projected onto the
zero set by Newton steps on the analytic SDF. Vertices therefore lie on the true surface
to ~1e-6 mm; the remaining error is the chord error of the triangles, about
edge^2 / (8 * curvature radius) < 0.01 mm at the grid steps used (info["truth_grid_mm"]).

Coordinates: the phantom is built in a "local" frame (mm, z = superior along the shaft)
that is aligned with the image grid. Physical LPS = origin + D @ (local - local0), where
local0 is the local position of voxel (0, 0, 0) and D the image direction matrix. So the
oblique case has the same voxel array as the axis-aligned one, and the same object
rotated by D in physical space.
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from BoneWatertightLib.mesh import Surface  # noqa: E402

# ---------------------------------------------------------------------------- cases

_BASE = dict(
    scale=1.0,            # bone size factor; 1.0 = ~157 mm long, 26 mm shaft diameter
    pixel=0.8,            # in-plane spacing (mm)
    slice_spacing=1.0,    # distance between slices (mm)
    slice_thickness=None,  # None = slice_spacing
    gap=3.0,              # joint gap head <-> cup (mm), filled with cartilage HU
    noise=15.0,           # Gaussian noise sigma (HU)
    psf_sigma=0.4,        # in-plane Gaussian PSF sigma (mm)
    cortex_shaft=3.0,     # cortical thickness in the diaphysis (mm, scaled, >= 1 mm)
    cortex_end=0.8,       # cortical thickness at the ends (mm, not scaled)
    pores=True,
    foramina=True,
    lesion=False,
    neighbour=True,
    direction_angles_deg=(0.0, 0.0, 0.0),  # rotations about x, y, z of the image grid
    origin=(-97.3, 61.9, -412.6),          # physical LPS of voxel (0, 0, 0)
    mask_factor=2.0,      # the rough segment's grid is this many times coarser
    truth_grid=None,      # marching-cubes step (mm) of the truth mesh; None = auto
    cartilage_hu=150.0,
)

CASES: dict[str, dict] = {
    # CI: a ~31 mm bone at 1 mm voxels (made in well under a second).
    "tiny": dict(scale=0.2, pixel=1.0, slice_spacing=1.0, gap=2.0, noise=10.0,
                 cortex_end=0.8, pores=False, foramina=False, truth_grid=0.2),
    "easy": dict(scale=0.6, pixel=0.8, slice_spacing=1.0, gap=3.0, noise=15.0),
    # Femur-sized (157 mm of a femur: head, neck, trochanter, shaft, condyles).
    "femur": dict(scale=1.0, pixel=0.6, slice_spacing=1.0, gap=2.0, noise=20.0),
    "hard": dict(scale=0.6, pixel=0.8, slice_spacing=2.5, gap=1.2, noise=35.0),
    "lesion": dict(scale=0.6, pixel=0.8, slice_spacing=1.0, gap=3.0, noise=20.0, lesion=True),
    "oblique": dict(scale=0.6, pixel=0.8, slice_spacing=1.0, gap=3.0, noise=15.0,
                    direction_angles_deg=(17.0, -11.0, 23.0)),
}


@dataclass
class Phantom:
    """ct: int16 HU, physical LPS geometry (non-zero origin, direction possibly oblique).
    mask: rough uint8 segment of the bone on a coarser grid (holes, islands, a missing slab).
    truth / neighbour_truth: watertight meshes (LPS mm) of the bone's outer envelope and of the
    hip-like cup. info: the case parameters plus derived figures; info["_model"] is the
    geometry/HU model object (not JSON-serialisable; drop keys starting with "_")."""

    ct: sitk.Image
    mask: sitk.Image
    truth: Surface
    neighbour_truth: Surface | None
    info: dict = field(default_factory=dict)

    def bone_sdf(self, physical_points: np.ndarray) -> np.ndarray:
        """Signed distance (mm, negative inside) of the true bone at physical LPS points."""
        return self.info["_model"].bone_sdf(self.info["_model"].to_local(physical_points))


# ---------------------------------------------------------------------------- SDF primitives

def _norm(q):
    return np.sqrt(np.einsum("ij,ij->i", q, q))


def _capsule(p, a, b, r):
    a = np.asarray(a, float)
    ba = np.asarray(b, float) - a
    pa = p - a
    h = np.clip(pa @ ba / (ba @ ba), 0.0, 1.0)
    return _norm(pa - h[:, None] * ba) - r


def _sphere(p, c, r):
    return _norm(p - np.asarray(c, float)) - r


def _ellipsoid(p, c, radii):
    # Inigo Quilez's bound: exact on the surface, a good approximation near it.
    q = (p - np.asarray(c, float))
    radii = np.asarray(radii, float)
    k0 = _norm(q / radii)
    k1 = _norm(q / radii ** 2)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def _smin(a, b, k):
    """Polynomial smooth minimum (blend radius k mm): rounds the joins like real bone."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


class _PlaneWaves:
    """Smooth random field in about [-1, 1]: sum of random cosine plane waves."""

    def __init__(self, rng, n, wavelength_range):
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        lam = rng.uniform(*wavelength_range, size=n)
        self.k = d * (2.0 * np.pi / lam)[:, None]
        self.phase = rng.uniform(0, 2 * np.pi, size=n)
        self.norm = 1.0 / math.sqrt(n / 2.0)

    def __call__(self, p):
        return np.clip(np.cos(p @ self.k.T + self.phase).sum(axis=1) * self.norm, -1.5, 1.5) / 1.5


# ---------------------------------------------------------------------------- the model

class _Model:
    """Geometry and HU model of one phantom (local frame, mm)."""

    def __init__(self, cfg, rng):
        self.cfg = cfg
        s = cfg["scale"]
        self.s = s
        v = lambda *xyz: np.array(xyz, float) * s  # noqa: E731
        # Parts of a left femur (head medial = -x), full size at s = 1.
        self.shaft = (v(0, 0, -48), v(0, 0, 42), 13.0 * s)
        self.neck_base = v(0, 0, 40)
        self.head_c = v(-32, 0, 62)
        self.head_r = 21.0 * s
        self.neck = (self.neck_base, self.head_c, 9.5 * s)
        self.troch = (v(14, -2, 50), v(10, 9, 13))
        self.lesser = (v(-9, 7, 22), 6.0 * s)
        self.flare = (v(0, 2, -50), v(23, 17, 15))
        self.condyles = [(v(13, 4, -62), 12.0 * s), (v(-13, 4, -62), 12.0 * s)]
        self.blend = max(3.0 * s, 0.6)
        # Cortex and marrow cavity.
        self.t_shaft = max(cfg["cortex_shaft"] * s, 1.0)
        self.t_end = min(cfg["cortex_end"], self.t_shaft)
        self.dia_z = (-25.0 * s, 22.0 * s)
        self.dia_ramp = 15.0 * s
        r_cav = self.shaft[2] - self.t_shaft
        self.cavity = (v(0, 0, -28), v(0, 0, 24), r_cav)
        # Hip-like cup around the head, opening towards the neck.
        u = self.head_c - self.neck_base
        self.cup_axis = u / np.linalg.norm(u)
        self.cup_r_in = self.head_r + cfg["gap"]
        self.gap = cfg["gap"]
        self.cup_t = max(5.0 * s, 2.0)
        self.pelvis_blob = (self.head_c + self.cup_axis * (self.cup_r_in + self.cup_t + 3.0 * s),
                            9.0 * s)
        # HU fields.
        self.trab_field = _PlaneWaves(rng, 12, (6.0 * max(s, 0.3), 25.0 * max(s, 0.3)))
        self.cort_field = _PlaneWaves(rng, 8, (20.0, 60.0))
        self.marrow_field = _PlaneWaves(rng, 6, (10.0, 30.0))
        self.tumour_field = _PlaneWaves(rng, 24, (1.5, 5.0))
        # Lesion: a ball on the anterior shaft surface.
        self.lesion = None
        if cfg["lesion"]:
            r_l = max(9.0 * s, 3.0)
            c = np.array([0.0, self.shaft[2] + 0.25 * r_l, 3.0 * s])
            self.lesion = (c, r_l)
        self._place_pores(rng)

    # ---- geometry

    def bone_sdf(self, p):
        d = _capsule(p, *self.shaft)
        d = _smin(d, _capsule(p, *self.neck), self.blend)
        d = _smin(d, _sphere(p, self.head_c, self.head_r), self.blend * 0.5)
        d = _smin(d, _ellipsoid(p, *self.troch), self.blend)
        d = _smin(d, _sphere(p, *self.lesser), self.blend)
        d = _smin(d, _ellipsoid(p, *self.flare), self.blend * 2.0)
        for c, r in self.condyles:
            d = _smin(d, _sphere(p, c, r), self.blend)
        return d

    def cup_sdf(self, p):
        q = p - self.head_c
        rr = _norm(q)
        shell = np.abs(rr - (self.cup_r_in + 0.5 * self.cup_t)) - 0.5 * self.cup_t
        # Keep the part beyond a plane 0.2 R past the centre (the cup's rim).
        half = -(q @ self.cup_axis) - 0.2 * self.cup_r_in
        # Smooth maximum: a rounded rim (a sharp crease would fold the projected truth mesh).
        cup = -_smin(-shell, -half, 0.4 * self.cup_t)
        cup = _smin(cup, _sphere(p, *self.pelvis_blob), max(2.0 * self.s, 0.6))
        # The rounded rim comes closer to the neck than the joint gap: keep the whole cup at
        # least `gap` away from the bone (smooth max >= max, so the bound holds exactly).
        return -_smin(-cup, -(self.gap - self.bone_sdf(p)), 0.3 * self.cup_t)

    def cortex_thickness(self, p):
        z0, z1 = self.dia_z
        w = _smoothstep(z0 - self.dia_ramp, z0, p[:, 2]) * (1.0 - _smoothstep(z1, z1 + self.dia_ramp, p[:, 2]))
        # Only the shaft proper is thick (not the trochanter reaching into the diaphysis range).
        w = w * (1.0 - _smoothstep(0.5 * self.shaft[2], 1.5 * self.shaft[2],
                                   np.hypot(p[:, 0], p[:, 1]) - self.shaft[2] + self.t_shaft))
        return self.t_end + (self.t_shaft - self.t_end) * w

    def _place_pores(self, rng):
        cfg, s = self.cfg, self.s
        self.pores = np.zeros((0, 4))
        self.foramina = []
        if cfg["pores"]:
            lo, hi = self.bone_bbox()
            cand = rng.uniform(lo, hi, size=(int(20000 * s ** 3) + 200, 3))
            r = rng.uniform(0.5, 1.4, size=len(cand)) * max(s, 0.5)
            depth = -self.bone_sdf(cand)
            ok = depth > self.cortex_thickness(cand) + r + 0.3
            ok &= _capsule(cand, *self.cavity) > r + 0.3
            keep = np.flatnonzero(ok)[: int(600 * s ** 3) + 20]
            self.pores = np.column_stack([cand[keep], r[keep]])
        if cfg["foramina"]:
            # Vascular channels from the outer surface through the cortex: real bone has
            # them; the truth is the envelope without them.
            n = max(int(8 * s), 2)
            z = rng.uniform(self.dia_z[0] - 10 * s, self.dia_z[1], size=n)
            ang = rng.uniform(0, 2 * np.pi, size=n)
            radial = np.column_stack([np.cos(ang), np.sin(ang), np.zeros(n)])
            for k in range(n):
                outer = radial[k] * self.shaft[2] + np.array([0, 0, z[k]])
                t = float(self.cortex_thickness(outer[None])[0])
                a = outer + radial[k] * 0.3
                b = outer - radial[k] * (t + 0.8)
                self.foramina.append((a, b, rng.uniform(0.4, 0.7)))

    def bone_bbox(self):
        parts = [(self.shaft[0], self.shaft[2]), (self.shaft[1], self.shaft[2]),
                 (self.head_c, self.head_r), (self.troch[0], self.troch[1].max()),
                 (self.lesser[0], self.lesser[1]), (self.flare[0], self.flare[1].max())]
        parts += self.condyles
        lo = np.min([c - r for c, r in parts], axis=0) - self.blend
        hi = np.max([c + r for c, r in parts], axis=0) + self.blend
        return lo, hi

    def cup_bbox(self):
        r = self.cup_r_in + self.cup_t
        lo = np.minimum(self.head_c - r, self.pelvis_blob[0] - self.pelvis_blob[1])
        hi = np.maximum(self.head_c + r, self.pelvis_blob[0] + self.pelvis_blob[1])
        return lo, hi

    # ---- HU

    def hu(self, p, body_hu):
        """HU at local points p (n, 3); body_hu (n,) is the soft-tissue/fat/air background."""
        cfg = self.cfg
        out = body_hu.astype(np.float64).copy()
        d = self.bone_sdf(p)
        # Cartilage-filled joint gap between head and cup.
        if cfg["neighbour"]:
            q = p - self.head_c
            rr = _norm(q)
            in_gap = (rr < self.cup_r_in + 0.3) & ((q @ self.cup_axis) > -0.2 * self.cup_r_in - 0.5) & (d > 0)
            out[in_gap] = cfg["cartilage_hu"] + 30.0 * self.marrow_field(p[in_gap])
            dc = self.cup_sdf(p)
            inc = dc < 0
            cup_hu = np.where(-dc[inc] < 1.0, 1300.0, 320.0 + 100.0 * self.trab_field(p[inc]))
            out[inc] = cup_hu
        inside = d < 0
        pi = p[inside]
        depth = -d[inside]
        t = self.cortex_thickness(pi)
        hu = 300.0 + 110.0 * self.trab_field(pi)
        # Trabecular bone is denser just under the cortex (as in real epiphyses).
        hu = hu + 80.0 * np.exp(-np.maximum(depth - t, 0.0) / 2.0)
        cav = _capsule(pi, *self.cavity) < 0
        hu = np.where(cav, 50.0 + 30.0 * self.marrow_field(pi), hu)
        cort = depth < t
        hu = np.where(cort, 1400.0 + 180.0 * self.cort_field(pi), hu)
        if len(self.pores):
            from scipy.spatial import cKDTree
            tree = cKDTree(self.pores[:, :3])
            rmax = self.pores[:, 3].max()
            dist, idx = tree.query(pi, distance_upper_bound=rmax)
            hit = np.isfinite(dist)
            hit[hit] = dist[hit] < self.pores[idx[hit], 3]
            hu[hit] = 30.0
        for a, b, r in self.foramina:
            hu[_capsule(pi, a, b, r) < 0] = 40.0
        out[inside] = hu
        if self.lesion is not None:
            c, r_l = self.lesion
            dl = _sphere(p, c, r_l)
            # Tumour replaces bone (cortex broken) and bulges a little into the soft tissue.
            hit = (dl < 0) & ((d < 0) | (dl < -0.5 * r_l))
            out[hit] = 180.0 + 260.0 * self.tumour_field(p[hit])
        return out

    # ---- frame

    def to_local(self, x):
        return (np.asarray(x, float) - self.origin) @ self.direction + self.local0

    def to_physical(self, q):
        return (np.asarray(q, float) - self.local0) @ self.direction.T + self.origin


def _rotation(angles_deg):
    ax, ay, az = np.radians(angles_deg)
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    rz = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


# ---------------------------------------------------------------------------- image formation

def _body_slice(model, xs, ys):
    """Soft tissue / fat / air cross-section (the body is a cylinder along z)."""
    cx, cy, ax, ay = model.body
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    rho = np.sqrt(((X - cx) / ax) ** 2 + ((Y - cy) / ay) ** 2)
    depth = (1.0 - rho) * min(ax, ay)  # approximate depth below the skin (mm)
    hu = np.where(depth < 0, -1000.0, np.where(depth < model.fat_mm, -100.0, 40.0))
    return hu


def _form_ct(model, cfg, rng, shape, spacing):
    """Fine-grid HU -> slice profile + PSF -> sample -> noise. Returns int16 (z, y, x) array."""
    from scipy import ndimage

    nx, ny, nz = shape
    px, sz = spacing[0], spacing[2]
    thick = cfg["slice_thickness"] or sz
    sub = 2
    hx = px / sub
    n_box = max(3, int(math.ceil(thick / 0.35)))
    n_box += (n_box + 1) % 2  # odd: the box is centred on a fine sample
    hz = thick / n_box
    pad_xy = int(math.ceil(3 * cfg["psf_sigma"] / hx)) + 1
    pad_z = n_box // 2 + 3
    q0 = model.local0
    xs = q0[0] + hx * (np.arange(nx * sub - 1 + 2 * pad_xy) - pad_xy)
    ys = q0[1] + hx * (np.arange(ny * sub - 1 + 2 * pad_xy) - pad_xy)
    z_first = q0[2] - pad_z * hz
    nzf = int(math.ceil(((nz - 1) * sz) / hz)) + 2 * pad_z + 1
    zs = z_first + hz * np.arange(nzf)

    body = _body_slice(model, xs, ys).astype(np.float32)
    fine = np.empty((nzf, len(ys), len(xs)), np.float32)  # (z, y, x)
    # Region where the bone/cup/lesion model must be evaluated, per fine slice (coarse
    # 1 mm bound of the SDFs), so the rest is just the 2-D body section.
    lo_b, hi_b = model.bone_bbox()
    lo_c, hi_c = model.cup_bbox() if cfg["neighbour"] else (lo_b, hi_b)
    lo = np.minimum(lo_b, lo_c) - 1.5
    hi = np.maximum(hi_b, hi_c) + 1.5
    if model.lesion is not None:
        lo = np.minimum(lo, model.lesion[0] - model.lesion[1] - 1)
        hi = np.maximum(hi, model.lesion[0] + model.lesion[1] + 1)
    step = 1.0
    cz = np.arange(lo[2], hi[2] + step, step)
    cx = np.arange(lo[0], hi[0] + step, step)
    cy = np.arange(lo[1], hi[1] + step, step)
    G = np.stack(np.meshgrid(cx, cy, cz, indexing="ij"), -1).reshape(-1, 3)
    dmin = model.bone_sdf(G)
    if cfg["neighbour"]:
        dmin = np.minimum(dmin, model.cup_sdf(G))
    if model.lesion is not None:
        dmin = np.minimum(dmin, _sphere(G, *model.lesion))
    near = (dmin < 2.0 + step).reshape(len(cx), len(cy), len(cz))

    chunk = max(1, int(4e6 // (len(xs) * len(ys))))
    for z0 in range(0, nzf, chunk):
        zc = zs[z0:z0 + chunk]
        fine[z0:z0 + len(zc)] = body.T[None]
        kz = np.flatnonzero((cz >= zc[0] - step) & (cz <= zc[-1] + step))
        if not len(kz):
            continue
        sel = near[:, :, kz].any(axis=2)
        if not sel.any():
            continue
        ix = np.flatnonzero(sel.any(axis=1))
        iy = np.flatnonzero(sel.any(axis=0))
        x_lo, x_hi = cx[ix[0]] - step, cx[ix[-1]] + step
        y_lo, y_hi = cy[iy[0]] - step, cy[iy[-1]] + step
        jx = np.flatnonzero((xs >= x_lo) & (xs <= x_hi))
        jy = np.flatnonzero((ys >= y_lo) & (ys <= y_hi))
        if not len(jx) or not len(jy):
            continue
        Z, Y, X = np.meshgrid(zc, ys[jy], xs[jx], indexing="ij")
        pts = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
        bg = fine[z0:z0 + len(zc), jy[0]:jy[-1] + 1, jx[0]:jx[-1] + 1].ravel()
        fine[z0:z0 + len(zc), jy[0]:jy[-1] + 1, jx[0]:jx[-1] + 1] = \
            model.hu(pts, bg).reshape(Z.shape).astype(np.float32)

    # Slice profile (box along z), PSF (Gaussian in-plane).
    fine = ndimage.uniform_filter1d(fine, n_box, axis=0, mode="nearest")
    sig = cfg["psf_sigma"] / hx
    fine = ndimage.gaussian_filter(fine, (0.0, sig, sig), mode="nearest", truncate=3.0)
    fine = fine[:, pad_xy:pad_xy + sub * ny:sub, pad_xy:pad_xy + sub * nx:sub]
    # Linear interpolation along z at the slice centres.
    fz = (q0[2] + sz * np.arange(nz) - z_first) / hz
    k0 = np.clip(np.floor(fz).astype(int), 0, nzf - 2)
    w = (fz - k0)[:, None, None].astype(np.float32)
    img = fine[k0] * (1 - w) + fine[k0 + 1] * w
    del fine
    img += rng.normal(0.0, cfg["noise"], size=img.shape).astype(np.float32)
    return np.clip(np.rint(img), -1024, 3071).astype(np.int16)


# ---------------------------------------------------------------------------- truth meshes

def _sdf_mesh(sdf, lo, hi, h, newton=4):
    """Watertight mesh of sdf's zero set: flying edges on a grid of step h, then Newton
    projection of the vertices onto the zero set."""
    import vtk
    from vtk.util import numpy_support as ns

    # An odd offset keeps grid nodes off the primitives' round-number radii and centres, and
    # node values too close to zero are pushed outward: flying edges would otherwise emit
    # coincident vertices (zero-area triangles) at nodes lying on the surface.
    lo = np.asarray(lo, float) - 2 * h - np.array([0.1234567, 0.2345678, 0.3456789]) * h
    hi = np.asarray(hi, float) + 2 * h
    n = np.ceil((hi - lo) / h).astype(int) + 1
    xs, ys, zs = (lo[k] + h * np.arange(n[k]) for k in range(3))
    vol = np.empty((n[2], n[1], n[0]), np.float32)
    step = max(1, int(2e6 // (n[0] * n[1])))
    for k in range(0, n[2], step):
        Z, Y, X = np.meshgrid(zs[k:k + step], ys, xs, indexing="ij")
        vol[k:k + step] = sdf(np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])).reshape(X.shape)
    tiny = np.float32(1e-3 * h)
    vol[np.abs(vol) < tiny] = tiny
    vol[[0, -1]] = 1.0
    vol[:, [0, -1]] = 1.0
    vol[:, :, [0, -1]] = 1.0
    img = vtk.vtkImageData()
    img.SetDimensions(*[int(v) for v in n])
    img.SetSpacing(h, h, h)
    img.SetOrigin(*lo)
    arr = ns.numpy_to_vtk(vol.ravel(), deep=True)
    img.GetPointData().SetScalars(arr)
    fe = vtk.vtkFlyingEdges3D()
    fe.SetInputData(img)
    fe.SetValue(0, 0.0)
    fe.ComputeNormalsOff()
    fe.ComputeGradientsOff()
    fe.ComputeScalarsOff()
    fe.Update()
    out = fe.GetOutput()
    v = ns.vtk_to_numpy(out.GetPoints().GetData()).astype(np.float64)
    f = ns.vtk_to_numpy(out.GetPolys().GetConnectivityArray()).astype(np.int64).reshape(-1, 3)
    eps = 1e-4 * h
    for _ in range(newton):
        d = sdf(v)
        g = np.column_stack([(sdf(v + e) - sdf(v - e)) / (2 * eps) for e in np.eye(3) * eps])
        gn2 = np.maximum((g * g).sum(axis=1), 1e-12)
        v = v - (d / gn2)[:, None] * g
    # Flying edges orients triangles by the gradient (towards increasing sdf = outward);
    # make sure the faces are CCW seen from outside.
    from BoneWatertightLib.mesh import enclosed_volume
    if enclosed_volume(v, f) < 0:
        f = f[:, ::-1].copy()
    return v, f


# ---------------------------------------------------------------------------- rough segment

def _rough_mask(model, cfg, rng, ct_size, ct_spacing):
    fac = cfg["mask_factor"]
    msp = np.array(ct_spacing, float) * fac
    ext = (np.array(ct_size) - 1) * np.array(ct_spacing)
    msize = np.floor(ext / msp).astype(int) + 1
    # The mask grid starts half a CT voxel off the CT grid, as a different grid would.
    m0 = model.local0 + 0.5 * np.array(ct_spacing)
    xs, ys, zs = (m0[k] + msp[k] * np.arange(msize[k]) for k in range(3))
    Z, Y, X = np.meshgrid(zs, ys, xs, indexing="ij")
    p = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    wob = _PlaneWaves(rng, 10, (8.0, 30.0))
    d = model.bone_sdf(p) + 0.6 * msp.max() * wob(p) + 0.3 * msp.max()
    m = d < 0
    lo, hi = model.bone_bbox()
    length = hi[2] - lo[2]
    # Holes.
    inside = np.flatnonzero(m)
    for c in p[rng.choice(inside, size=min(4, len(inside)), replace=False)]:
        m &= _sphere(p, c, 1.6 * msp.max()) > 0
    # A missing chunk (slab) of the shaft.
    zc = rng.uniform(model.dia_z[0], model.dia_z[1])
    m &= np.abs(p[:, 2] - zc) > 0.04 * length
    # Islands in the soft tissue.
    # Islands stay clear of the volume border (a segment touching it means a cut bone).
    lo_ok = m0 + 4 * msp
    hi_ok = m0 + (msize - 5) * msp
    interior = np.all((p >= lo_ok) & (p <= hi_ok), axis=1)
    away = np.flatnonzero((model.bone_sdf(p) > 6.0 * model.s + 3 * msp.max()) & interior)
    for c in p[rng.choice(away, size=min(3, len(away)), replace=False)]:
        m |= _sphere(p, c, 1.2 * msp.max()) < 0
    if cfg["neighbour"]:
        m &= model.cup_sdf(p) > 0.5 * msp.max()
    arr = m.reshape(Z.shape).astype(np.uint8)
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing([float(v) for v in msp])
    img.SetDirection(model.direction.ravel().tolist())
    img.SetOrigin(model.to_physical(m0[None])[0].tolist())
    return img


# ---------------------------------------------------------------------------- entry point

def make_phantom(case: str = "easy", seed: int = 0, **overrides) -> Phantom:
    """A synthetic CT, a rough segment and the ground-truth surfaces (see module doc)."""
    if case not in CASES:
        raise ValueError(f"Unknown phantom case {case!r}; choose one of {', '.join(CASES)}")
    cfg = dict(_BASE)
    cfg.update(CASES[case])
    unknown = set(overrides) - set(cfg)
    if unknown:
        raise ValueError(f"Unknown phantom parameter(s): {', '.join(sorted(unknown))}")
    cfg.update(overrides)
    rng = np.random.default_rng(seed)
    model = _Model(cfg, rng)
    s = cfg["scale"]

    # Field of view: bone (+ cup) with a margin; the body is an elliptic cylinder around it
    # whose skin the FOV corners cut, so there is air in the image.
    lo, hi = model.bone_bbox()
    if cfg["neighbour"]:
        lo_c, hi_c = model.cup_bbox()
        lo, hi = np.minimum(lo, lo_c), np.maximum(hi, hi_c)
    margin = max(15.0 * s, 5 * cfg["pixel"])
    fov_lo = lo - np.array([margin, margin, max(6.0 * s, 3 * cfg["slice_spacing"])])
    fov_hi = hi + np.array([margin, margin, max(6.0 * s, 3 * cfg["slice_spacing"])])
    centre = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo)
    model.body = (centre[0], centre[1], half[0] + 0.8 * margin, half[1] + 0.8 * margin)
    model.fat_mm = max(6.0 * s, 2.0)
    spacing = np.array([cfg["pixel"], cfg["pixel"], cfg["slice_spacing"]], float)
    size = np.floor((fov_hi - fov_lo) / spacing).astype(int) + 1
    model.local0 = fov_lo
    model.direction = _rotation(cfg["direction_angles_deg"])
    model.origin = np.array(cfg["origin"], float)

    arr = _form_ct(model, cfg, rng, tuple(size), spacing)
    ct = sitk.GetImageFromArray(arr)
    ct.SetSpacing(spacing.tolist())
    ct.SetOrigin(model.origin.tolist())
    ct.SetDirection(model.direction.ravel().tolist())

    mask = _rough_mask(model, cfg, rng, size, spacing)

    h = cfg["truth_grid"] or float(np.clip(0.5 * s, 0.15, 0.5))
    lo_b, hi_b = model.bone_bbox()
    v, f = _sdf_mesh(model.bone_sdf, lo_b, hi_b, h)
    truth = Surface(model.to_physical(v), f, "LPS")
    neighbour = None
    if cfg["neighbour"]:
        lo_c, hi_c = model.cup_bbox()
        v, f = _sdf_mesh(model.cup_sdf, lo_c, hi_c, h)
        neighbour = Surface(model.to_physical(v), f, "LPS")

    info = dict(cfg)
    info.update(
        case=case, seed=seed,
        slice_thickness=cfg["slice_thickness"] or cfg["slice_spacing"],
        bone_length_mm=float(hi_b[2] - lo_b[2]),
        truth_grid_mm=h,
        truth_note="flying edges at truth_grid_mm, vertices Newton-projected onto the SDF zero set",
        truth_excludes="pores, foramina and the lesion (truth = outer envelope of the healthy bone)",
        ct_size=[int(x) for x in size], ct_spacing=spacing.tolist(),
        mask_spacing=list(mask.GetSpacing()),
        n_pores=int(len(model.pores)), n_foramina=len(model.foramina),
        hu=dict(cortical="1220-1580", trabecular="190-490 (+80 under the cortex)",
                marrow="20-80", soft_tissue=40, fat=-100, air=-1000,
                cartilage=f"{cfg['cartilage_hu'] - 30:g}-{cfg['cartilage_hu'] + 30:g}"),
        _model=model,
    )
    return Phantom(ct=ct, mask=mask, truth=truth, neighbour_truth=neighbour, info=info)


if __name__ == "__main__":
    import time
    for name in (sys.argv[1:] or ["tiny"]):
        t = time.time()
        ph = make_phantom(name)
        print(name, f"{time.time() - t:.2f}s", ph.ct.GetSize(), ph.mask.GetSize(),
              ph.truth.n_faces, ph.info["bone_length_mm"])
