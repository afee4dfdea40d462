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
rotated by D in physical space. Every image of a phantom (CT, rough mask, label maps) has
the direction D and a grid aligned with the local axes; arrays are (z, y, x).

Both bones as label maps (1 = femur, 2 = cup, 0 = background): :func:`labels_rough` (the
rough mask plus a rough cup on the mask's grid) and :func:`labels_ai` (majority vote of the
truth on a coarse 1.5-3 mm grid, optionally wrong at the joint), or :func:`make_labels`.

Random streams: ``seed`` seeds the main stream (HU fields, pores, foramina, CT noise, rough
mask, in this order); options added later draw from streams seeded by (seed, 1) (geometry
variation, cortical holes), (seed, 2) (the rough cup label) and (seed, 3) (the AI grid's
phase), so the old cases are reproduced bit for bit.
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
    # Options added later; their defaults reproduce the old cases bit for bit.
    # True: the two truths are exactly `gap` apart over the whole joint. False (the old
    # cases): the cup's smooth clamp widens most of the joint by 0.075 cup_t (e.g. `hard`:
    # 1.2 mm at the pole, 1.425 mm elsewhere; info["gap_min_mm"] is the smallest distance).
    gap_exact=False,
    vary_geometry=False,  # True: the seed also perturbs part sizes/positions (about +-5 %)
    low_density_end=None,  # None | "proximal" | "distal" | "both": osteoporotic end(s)
    low_trab_hu=160.0,    # trabecular HU there (mean; +- low_trab_var from the same field)
    low_trab_var=40.0,
    low_subcortical_hu=0.0,  # extra HU just under the cortex there (80 elsewhere)
    low_cortex_hu=None,   # cortex HU there (None = the normal 1400 +- 180)
    low_cortex_var=30.0,
    cortex_holes=0,       # number of windows in the cortex (filled with cortex_hole_hu)
    cortex_hole_mm=2.0,   # their radius (mm)
    cortex_hole_hu=220.0,
    # False-positive blobs of the rough segment that touch the bone from the soft tissue (as AI
    # segmentations produce): this many balls of radius false_island_mm whose centres lie
    # false_island_mm outside the true surface (away from the cup); stream (seed, 4).
    false_islands=0,
    false_island_mm=3.0,
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
    # Joint cases (issue 10): femur + cup at `easy` size across slice thickness and joint gap,
    # the gap exact over the whole joint (gap_exact); name = joint_s<slice x10>_g<gap x10>.
    "joint_s10_g10": dict(scale=0.6, pixel=0.8, slice_spacing=1.0, gap=1.0, noise=20.0,
                          gap_exact=True),
    "joint_s15_g20": dict(scale=0.6, pixel=0.8, slice_spacing=1.5, gap=2.0, noise=20.0,
                          gap_exact=True, direction_angles_deg=(12.0, -8.0, 20.0)),
    "joint_s20_g15": dict(scale=0.6, pixel=0.8, slice_spacing=2.0, gap=1.5, noise=22.0,
                          gap_exact=True),
    "joint_s25_g12": dict(scale=0.6, pixel=0.8, slice_spacing=2.5, gap=1.2, noise=25.0,
                          gap_exact=True, direction_angles_deg=(-9.0, 14.0, -25.0)),
    "joint_s30_g30": dict(scale=0.6, pixel=0.8, slice_spacing=3.0, gap=3.0, noise=25.0,
                          gap_exact=True),
    # Cases where the paper's HT step matters (issue 14): bone that W_H0 = [H0, theta_max]
    # misses and W_HT = [HT, theta_max] holds; the truth is the same outer envelope.
    # Osteoporotic proximal end (head, neck, trochanters): trabecular 120-200 HU, the 0.8 mm
    # cortex at 280 +- 15 HU (after the blur 150-290 HU: below H0 = 300, above HT = 150).
    "osteo": dict(scale=0.6, pixel=0.8, slice_spacing=1.0, gap=3.0, noise=20.0,
                  low_density_end="proximal", low_trab_hu=160.0, low_trab_var=40.0,
                  low_subcortical_hu=0.0, low_cortex_hu=280.0, low_cortex_var=15.0),
    # Thin end cortex at both ends (0.4 mm, 700 +- 60 HU, over trabecular bone at 150-210 HU)
    # under a soft kernel (PSF sigma 0.7 mm) and 2 mm thick overlapping slices: its blurred
    # peak lies mostly below H0 (W_H0 patchy at the ends), above HT everywhere.
    "thin_cortex": dict(scale=0.6, pixel=0.8, slice_spacing=1.0, slice_thickness=2.0, gap=3.0,
                        noise=20.0, psf_sigma=0.7, cortex_end=0.4, low_density_end="both",
                        low_trab_hu=180.0, low_trab_var=30.0, low_subcortical_hu=20.0,
                        low_cortex_hu=700.0, low_cortex_var=60.0),
    # Windows in the cortex (W_H0 broken, into the marrow cavity in the shaft) filled with
    # low-density bone at 250 +- 20 HU (inside W_HT).
    "cortex_holes": dict(scale=0.6, pixel=0.8, slice_spacing=1.0, gap=3.0, noise=20.0,
                         cortex_holes=14, cortex_hole_mm=2.0, cortex_hole_hu=250.0),
}


@dataclass
class Phantom:
    """ct: int16 HU, physical LPS geometry (non-zero origin, direction possibly oblique).
    mask: rough uint8 segment of the bone on a coarser grid (holes, islands, a missing slab).
    truth / neighbour_truth: watertight meshes (LPS mm) of the bone's outer envelope and of the
    hip-like cup. info: the case parameters plus derived figures (gap_min_mm: the smallest
    distance between the two truths); info["_model"] is the geometry/HU model object (not
    JSON-serialisable; drop keys starting with "_"). Label maps of both bones:
    :meth:`labels_rough`, :meth:`labels_ai`."""

    ct: sitk.Image
    mask: sitk.Image
    truth: Surface
    neighbour_truth: Surface | None
    info: dict = field(default_factory=dict)

    def bone_sdf(self, physical_points: np.ndarray) -> np.ndarray:
        """Signed distance (mm, negative inside) of the true bone at physical LPS points."""
        return self.info["_model"].bone_sdf(self.info["_model"].to_local(physical_points))

    def cup_sdf(self, physical_points: np.ndarray) -> np.ndarray:
        """Signed distance (mm, negative inside) of the true hip-like cup at physical LPS
        points (n, 3) -> (n,); a 1-Lipschitz bound, exact around the joint."""
        return self.info["_model"].cup_sdf(self.info["_model"].to_local(physical_points))

    def labels_rough(self) -> sitk.Image:
        """Both bones as rough labels on the grid of :attr:`mask` (see :func:`labels_rough`)."""
        return labels_rough(self)

    def labels_ai(self, grid_mm=2.0, steal_mm: float = 0.0, subsamples: int = 3,
                  seed: int | None = None) -> sitk.Image:
        """Both bones as an AI-style coarse segmentation (see :func:`labels_ai`)."""
        return labels_ai(self, grid_mm=grid_mm, steal_mm=steal_mm, subsamples=subsamples, seed=seed)


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

    def __init__(self, cfg, rng, aux=None):
        """cfg: the case parameters; rng: the case's main random stream (fields, pores,
        foramina; then the CT noise and the rough mask draw from it, in this order); aux:
        a second stream for the options added later (geometry variation, cortical holes),
        so that those options never shift the main stream of the old cases."""
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
        if cfg.get("vary_geometry"):
            self._vary_geometry(aux)
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
        self.gap_exact = bool(cfg.get("gap_exact"))
        blob_at = self.cup_r_in + self.cup_t + 3.0 * s
        if self.gap_exact:
            # The blob's smooth union must not reach the cup's inner sphere (it pulled the
            # pole of the cup to the clamp of cup_sdf): its near side stays 1.5 blend radii
            # beyond the inner sphere, still overlapping the shell.
            blob_at = max(blob_at, self.cup_r_in + 9.0 * s + 1.5 * max(2.0 * s, 0.6))
        self.pelvis_blob = (self.head_c + self.cup_axis * blob_at, 9.0 * s)
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
        self.cortex_holes = np.zeros((0, 3))
        # Centres (local mm) of the rough segment's false blobs touching the bone (false_islands).
        self.false_island_centres = np.zeros((0, 3))
        if cfg.get("cortex_holes", 0) > 0:
            self._place_cortex_holes(aux)

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
        if self.gap_exact:
            # A hard maximum: where the head is a sphere both terms are equal (no crease), and
            # the smooth maximum's bump (+0.075 cup_t) would widen the whole joint beyond `gap`.
            return np.maximum(cup, self.gap - self.bone_sdf(p))
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

    def _vary_geometry(self, aux):
        """Perturb the parts a little (seeded by aux): every radius times U(0.95, 1.05),
        every centre moved by up to 5 % of the part's diameter per axis, the shaft's length
        times U(0.95, 1.05) (its axis stays the local z axis)."""
        def size(r):
            return r * aux.uniform(0.95, 1.05, size=np.shape(r))

        def move(c, r):
            return c + aux.uniform(-1.0, 1.0, size=3) * 0.05 * 2.0 * float(np.max(r))

        a, b, r = self.shaft
        self.shaft = (a * aux.uniform(0.95, 1.05), b * aux.uniform(0.95, 1.05), size(r))
        self.head_r = size(self.head_r)
        self.head_c = move(self.head_c, self.head_r)
        self.neck_base = move(self.neck_base, self.shaft[2])
        self.neck = (self.neck_base, self.head_c, size(self.neck[2]))
        r = size(self.troch[1])
        self.troch = (move(self.troch[0], r), r)
        r = size(self.lesser[1])
        self.lesser = (move(self.lesser[0], r), r)
        r = size(self.flare[1])
        self.flare = (move(self.flare[0], r), r)
        self.condyles = [(move(c, rr), rr) for c, rr in ((c, size(r)) for c, r in self.condyles)]

    def _place_cortex_holes(self, aux):
        """cfg["cortex_holes"] centres on the outer surface (|sdf| < 0.3 mm), spread out
        (at least 3 hole radii apart, clear of the foramina), drawn from aux."""
        n, r = int(self.cfg["cortex_holes"]), float(self.cfg["cortex_hole_mm"])
        lo, hi = self.bone_bbox()
        cand = aux.uniform(lo, hi, size=(400000, 3))
        cand = cand[np.abs(self.bone_sdf(cand)) < 0.3]
        for a, b, rf in self.foramina:  # not on a vascular channel
            cand = cand[_capsule(cand, a, b, rf) > r + 1.0]
        chosen = []
        for c in cand:
            if all(np.linalg.norm(c - q) > 3.0 * r for q in chosen):
                chosen.append(c)
                if len(chosen) == n:
                    break
        self.cortex_holes = np.array(chosen).reshape(-1, 3)

    def low_density_weight(self, p):
        """(n,) in [0, 1]: 1 in the low-density end(s) of cfg["low_density_end"], 0 in the
        diaphysis, a smoothstep over dia_ramp between (the cortex thickness' own ramp)."""
        z0, z1 = self.dia_z
        prox = _smoothstep(z1, z1 + self.dia_ramp, p[:, 2])
        dist = 1.0 - _smoothstep(z0 - self.dia_ramp, z0, p[:, 2])
        which = self.cfg["low_density_end"]
        if which == "proximal":
            return prox
        if which == "distal":
            return dist
        if which == "both":
            return np.maximum(prox, dist)
        raise ValueError(f"low_density_end must be None, 'proximal', 'distal' or 'both', not {which!r}")

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
        low = cfg.get("low_density_end") is not None
        if not low:
            hu = 300.0 + 110.0 * self.trab_field(pi)
            # Trabecular bone is denser just under the cortex (as in real epiphyses).
            hu = hu + 80.0 * np.exp(-np.maximum(depth - t, 0.0) / 2.0)
        else:
            # Low-density end(s): trabecular bone (and, if low_cortex_hu, the cortex) blend
            # towards the low values with low_density_weight.
            L = self.low_density_weight(pi)
            f = self.trab_field(pi)
            hu = (1.0 - L) * (300.0 + 110.0 * f) + L * (cfg["low_trab_hu"] + cfg["low_trab_var"] * f)
            sub = (1.0 - L) * 80.0 + L * cfg["low_subcortical_hu"]
            hu = hu + sub * np.exp(-np.maximum(depth - t, 0.0) / 2.0)
        cav = _capsule(pi, *self.cavity) < 0
        hu = np.where(cav, 50.0 + 30.0 * self.marrow_field(pi), hu)
        cort = depth < t
        g = self.cort_field(pi)
        cort_hu = 1400.0 + 180.0 * g
        if low and cfg["low_cortex_hu"] is not None:
            cort_hu = (1.0 - L) * cort_hu + L * (cfg["low_cortex_hu"] + cfg["low_cortex_var"] * g)
        hu = np.where(cort, cort_hu, hu)
        if len(self.cortex_holes):
            # Windows in the cortex filled with low-density bone (in W_HT, not in W_H0).
            from scipy.spatial import cKDTree
            dist, _ = cKDTree(self.cortex_holes).query(pi, distance_upper_bound=cfg["cortex_hole_mm"])
            hole = (dist < cfg["cortex_hole_mm"]) & (depth < t + 0.3)
            hu[hole] = cfg["cortex_hole_hu"] + 20.0 * self.marrow_field(pi[hole])
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
    if cfg["false_islands"]:
        m |= _touching_islands(model, cfg, p, lo_ok, hi_ok)
    if cfg["neighbour"]:
        m &= model.cup_sdf(p) > 0.5 * msp.max()
    arr = m.reshape(Z.shape).astype(np.uint8)
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing([float(v) for v in msp])
    img.SetDirection(model.direction.ravel().tolist())
    img.SetOrigin(model.to_physical(m0[None])[0].tolist())
    return img


def _touching_islands(model, cfg, p, lo_ok, hi_ok):
    """Balls (radius r = false_island_mm) centred r outside the true surface, at points of the
    bone's surface drawn from the stream (seed, 4), at least 3 r + the gap from the cup and
    inside the mask grid's interior: (n,) bool over the points ``p`` (local mm)."""
    r = float(cfg["false_island_mm"])
    rng = np.random.default_rng([int(cfg["_seed"]), 4])
    # Candidate centres: mask-grid points at distance r outside the bone.
    sdf = model.bone_sdf(p)
    ok = (np.abs(sdf - r) < 0.5) & np.all((p >= lo_ok + r) & (p <= hi_ok - r), axis=1)
    if cfg["neighbour"]:
        ok &= model.cup_sdf(p) > 3.0 * r + cfg["gap"]
    cand = np.flatnonzero(ok)
    out = np.zeros(len(p), bool)
    chosen = []
    for i in rng.permutation(cand):
        c = p[i]
        if all(np.linalg.norm(c - q) > 6.0 * r for q in chosen):
            chosen.append(c)
            out |= _sphere(p, c, r) < 0
        if len(chosen) == cfg["false_islands"]:
            break
    model.false_island_centres = np.array(chosen).reshape(-1, 3)
    return out


# ---------------------------------------------------------------------------- label maps of both bones

LABEL_FEMUR = 1
LABEL_CUP = 2


def _grid_image(arr_zyx: np.ndarray, model, start_local, spacing) -> sitk.Image:
    """uint8 image of a (z, y, x) array on a grid aligned with the model's local frame:
    voxel (i, j, k) is at local start_local + spacing * (i, j, k), physically
    origin + D @ (local - local0), as every image of the phantom."""
    img = sitk.GetImageFromArray(np.ascontiguousarray(arr_zyx, dtype=np.uint8))
    img.SetSpacing([float(v) for v in spacing])
    img.SetDirection(model.direction.ravel().tolist())
    img.SetOrigin(model.to_physical(np.asarray(start_local, float)[None])[0].tolist())
    return img


def _grid_start_local(img: sitk.Image, model) -> np.ndarray:
    """Local position of voxel (0, 0, 0) of an image made by this module (checks that its
    direction is the model's, i.e. that its axes are the local axes)."""
    D = np.array(img.GetDirection()).reshape(3, 3)
    if not np.allclose(D, model.direction, atol=1e-9):
        raise ValueError("the image's direction differs from the phantom's")
    return model.to_local(np.array(img.GetOrigin(), float)[None])[0]


def _local_points(start, spacing, i0, i1):
    """Local positions (n, 3), x fastest, of the voxels i0 <= (i, j, k) < i1 of a grid."""
    xs, ys, zs = (start[k] + spacing[k] * np.arange(i0[k], i1[k]) for k in range(3))
    Z, Y, X = np.meshgrid(zs, ys, xs, indexing="ij")
    return np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])


def _cup_rough(model, rng, start, spacing, size) -> np.ndarray:
    """Rough mask (z, y, x) bool of the cup on the grid (start, spacing, size), made like
    the femur's in :func:`_rough_mask` but with scales for a thin shell (see
    :func:`labels_rough`)."""
    out = np.zeros(tuple(int(v) for v in size[::-1]), bool)
    h = float(min(spacing[0], spacing[1]))  # in-plane spacing
    lo, hi = model.cup_bbox()
    size = np.asarray(size, int)
    i0 = np.clip(np.floor((lo - 2 * h - start) / spacing).astype(int), 0, size)
    i1 = np.clip(np.ceil((hi + 2 * h - start) / spacing).astype(int) + 1, 0, size)
    if np.any(i1 <= i0):
        return out
    p = _local_points(start, spacing, i0, i1)
    wob = _PlaneWaves(rng, 10, (8.0, 30.0))
    # k points spread over each voxel's z extent, cup if any is inside: centre sampling alone
    # would cut the shell apart where it lies flat on a grid whose z spacing exceeds it.
    k = max(1, int(math.ceil(spacing[2] / (0.5 * model.cup_t))))
    m = np.zeros(len(p), bool)
    for dz in ((np.arange(k) + 0.5) / k - 0.5) * spacing[2]:
        q = p + np.array([0.0, 0.0, dz])
        m |= model.cup_sdf(q) + 0.2 * h * wob(q) + 0.05 * h < 0
    # Never on the femur (as the femur's mask is kept off the cup).
    m &= model.bone_sdf(p) > 0.5 * h
    inside = np.flatnonzero(m)
    for c in p[rng.choice(inside, size=min(2, len(inside)), replace=False)]:
        m &= _sphere(p, c, 1.0 * h) > 0
    # One island beside the cup, clear of both bones.
    away = np.flatnonzero((model.cup_sdf(p) > 3.0 * h) & (model.bone_sdf(p) > 6.0 * model.s + 3.0 * h))
    for c in p[rng.choice(away, size=min(1, len(away)), replace=False)]:
        m |= _sphere(p, c, 1.0 * h) < 0
    sub = m.reshape(tuple((i1 - i0)[::-1]))
    out[i0[2]:i1[2], i0[1]:i1[1], i0[0]:i1[0]] = sub
    return out


def labels_rough(phantom: Phantom) -> sitk.Image:
    """The femur's rough segment and a rough segment of the cup in one label map.

    Parameters
    ----------
    phantom : Phantom

    Returns
    -------
    sitk.Image
        uint8, on the grid of ``phantom.mask`` (same size, spacing, origin and direction;
        array axes (z, y, x)). 0 = background, 1 = femur: exactly ``phantom.mask`` (wobble,
        shrink, holes, islands, a missing slab, all scaled by the mask spacing's *max*);
        2 = cup: the cup's SDF + 0.2 h * wobble + 0.05 h < 0 with h the mask's *in-plane*
        spacing (the femur's scales, 0.6 / 0.3 * max spacing, would cut the 2-5 mm thin shell
        apart) at any of ceil(z spacing / (cup thickness / 2)) points spread over the voxel's
        z extent (so thick slices do not cut it apart either), voxel centres at least h / 2
        off the femur, two holes and one island of radius h. Label 2 only where label 1 is not, so
        the labels never overlap. Without a neighbour (``neighbour=False``) there is no label 2.
        Deterministic: the cup's random stream is seeded by (seed, 2).
    """
    model = phantom.info["_model"]
    lab = sitk.GetArrayFromImage(phantom.mask).astype(np.uint8)
    lab[lab > 0] = LABEL_FEMUR
    if model.cfg["neighbour"]:
        rng = np.random.default_rng([int(phantom.info["seed"]), 2])
        start = _grid_start_local(phantom.mask, model)
        cup = _cup_rough(model, rng, start, np.array(phantom.mask.GetSpacing()),
                         np.array(phantom.mask.GetSize()))
        lab[cup & (lab == 0)] = LABEL_CUP
    img = _grid_image(lab, model, _grid_start_local(phantom.mask, model), phantom.mask.GetSpacing())
    return img


def labels_ai(phantom: Phantom, grid_mm=2.0, steal_mm: float = 0.0, subsamples: int = 3,
              seed: int | None = None) -> sitk.Image:
    """Both bones as an AI segmentation brings them (TotalSegmentator-like): coarse and
    stair-stepped, on its own grid, optionally wrong at the joint.

    Every voxel of a coarse grid takes the majority of the *truth* over subsamples**3
    points spread evenly in it (1 where the femur's SDF < 0, 2 where the cup's SDF < 0, else
    0; ties go to the lower label). Voxels whose centre lies farther than 1.5 half-diagonals
    + 0.2 mm from both surfaces are decided by their centre alone (the SDFs are 1-Lipschitz),
    so only the boundary band is subsampled. A consumer resamples the image
    nearest-neighbour onto the CT (:func:`resample_nearest`).

    Parameters
    ----------
    phantom : Phantom
    grid_mm : float or (3,) floats
        Spacing (x, y, z) of the coarse grid (mm), 1.5-3 mm for AI masks.
    steal_mm : float
        > 0: femur voxels whose centre lies within steal_mm of the cup (the cup's SDF at the
        centre < steal_mm) become cup voxels, as an AI mask that puts the top of the head into
        the hip bone. The depth taken from the head is about steal_mm - gap (nothing when
        steal_mm <= gap). Background voxels are left as they are.
    subsamples : int
        Points per axis in each voxel (3 -> 27 votes).
    seed : int or None
        Seeds the grid's phase (its first voxel centre lies 0 to half a voxel inside the
        corner of the CT's field of view, at random per axis); None = the phantom's seed.
        Deterministic for a seed.

    Returns
    -------
    sitk.Image
        uint8 (array axes (z, y, x)), 0 = background, 1 = femur, 2 = cup; direction = the
        CT's, spacing = grid_mm, covering the CT's field of view (voxel boundaries included).
    """
    model = phantom.info["_model"]
    grid = np.broadcast_to(np.asarray(grid_mm, float), (3,)).copy()
    if np.any(grid <= 0) or subsamples < 1:
        raise ValueError("grid_mm must be > 0 and subsamples >= 1")
    rng = np.random.default_rng([int(phantom.info["seed"] if seed is None else seed), 3])
    ct = phantom.ct
    ct_sp = np.array(ct.GetSpacing(), float)
    ct_size = np.array(ct.GetSize(), int)
    box_lo = model.local0 - 0.5 * ct_sp
    box_hi = model.local0 + (ct_size - 0.5) * ct_sp
    start = box_lo + (1.0 - rng.uniform(0.0, 1.0, 3)) * 0.5 * grid
    size = np.ceil((box_hi - start) / grid + 0.5).astype(int)
    neighbour = bool(model.cfg["neighbour"])

    p = _local_points(start, grid, np.zeros(3, int), size)
    d_f = model.bone_sdf(p)
    d_c = model.cup_sdf(p) if neighbour else np.full(len(p), np.inf)
    lab = np.where(d_f < 0, LABEL_FEMUR, np.where(d_c < 0, LABEL_CUP, 0)).astype(np.uint8)
    r = 1.5 * 0.5 * float(np.linalg.norm(grid)) + 0.2
    near = np.flatnonzero((np.abs(d_f) < r) | (np.abs(d_c) < r))
    if subsamples > 1 and len(near):
        t = ((np.arange(subsamples) + 0.5) / subsamples - 0.5)
        off = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3) * grid
        n_off = len(off)
        step = max(1, int(2e6 // n_off))
        for a in range(0, len(near), step):
            idx = near[a:a + step]
            q = (p[idx][:, None, :] + off[None]).reshape(-1, 3)
            f = (model.bone_sdf(q) < 0).reshape(-1, n_off)
            c = ((model.cup_sdf(q) < 0).reshape(-1, n_off) & ~f) if neighbour else np.zeros_like(f)
            votes = np.column_stack([n_off - f.sum(1) - c.sum(1), f.sum(1), c.sum(1)])
            lab[idx] = np.argmax(votes, axis=1).astype(np.uint8)
    if steal_mm > 0 and neighbour:
        lab[(lab == LABEL_FEMUR) & (d_c < steal_mm)] = LABEL_CUP
    return _grid_image(lab.reshape(tuple(size[::-1])), model, start, grid)


def make_labels(phantom: Phantom, kind: str = "rough", **kw) -> sitk.Image:
    """Label map of both bones: kind "rough" -> :func:`labels_rough`, "ai" ->
    :func:`labels_ai` (keywords grid_mm, steal_mm, subsamples, seed). uint8, 0 =
    background, 1 = femur, 2 = cup."""
    if kind == "rough":
        if kw:
            raise ValueError(f"labels_rough takes no parameters, got {', '.join(sorted(kw))}")
        return labels_rough(phantom)
    if kind == "ai":
        return labels_ai(phantom, **kw)
    raise ValueError(f"Unknown label kind {kind!r}; choose 'rough' or 'ai'")


def resample_nearest(labels: sitk.Image, reference: sitk.Image) -> sitk.Image:
    """labels resampled nearest-neighbour onto reference's grid (as a consumer puts an AI
    label map onto the CT); outside labels' grid -> 0. Same pixel type as labels."""
    return sitk.Resample(labels, reference, sitk.Transform(), sitk.sitkNearestNeighbor, 0,
                         labels.GetPixelID())


# ---------------------------------------------------------------------------- entry point

def _build(case: str, seed: int, overrides: dict):
    """The case's parameters, main random stream and model with its frame, CT size and
    spacing (the model has drawn its fields and pores from the stream; nothing else has)."""
    if case not in CASES:
        raise ValueError(f"Unknown phantom case {case!r}; choose one of {', '.join(CASES)}")
    cfg = dict(_BASE)
    cfg.update(CASES[case])
    unknown = set(overrides) - set(cfg)
    if unknown:
        raise ValueError(f"Unknown phantom parameter(s): {', '.join(sorted(unknown))}")
    cfg.update(overrides)
    cfg["_seed"] = int(seed)
    rng = np.random.default_rng(seed)
    # A second stream for the later options (vary_geometry, cortex_holes): the old cases'
    # main stream stays as it was.
    aux = np.random.default_rng([int(seed), 1])
    model = _Model(cfg, rng, aux)
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
    return cfg, rng, model, size, spacing


def _truths(model, cfg):
    """(truth, neighbour_truth or None, truth grid step h, smallest gap or None)."""
    h = cfg["truth_grid"] or float(np.clip(0.5 * cfg["scale"], 0.15, 0.5))
    lo_b, hi_b = model.bone_bbox()
    v, f = _sdf_mesh(model.bone_sdf, lo_b, hi_b, h)
    truth = Surface(model.to_physical(v), f, "LPS")
    neighbour = None
    gap_min = None
    if cfg["neighbour"]:
        lo_c, hi_c = model.cup_bbox()
        v, f = _sdf_mesh(model.cup_sdf, lo_c, hi_c, h)
        neighbour = Surface(model.to_physical(v), f, "LPS")
        # bone_sdf is 1-Lipschitz (a lower bound of the distance; exact around the head).
        gap_min = float(model.bone_sdf(v).min())
    return truth, neighbour, h, gap_min


def make_truth(case: str = "easy", seed: int = 0, **overrides):
    """The ground truth of a case without its CT and mask (the same meshes as
    :func:`make_phantom` gives, in a fraction of the time).

    Returns
    -------
    (truth, neighbour_truth, info)
        Surfaces in physical LPS (neighbour_truth None without the cup); info has the case
        parameters, truth_grid_mm, gap_min_mm and ``_model``.
    """
    cfg, _, model, _, _ = _build(case, seed, overrides)
    truth, neighbour, h, gap_min = _truths(model, cfg)
    info = dict(cfg)
    info.update(case=case, seed=seed, truth_grid_mm=h, gap_min_mm=gap_min, _model=model)
    return truth, neighbour, info


def make_phantom(case: str = "easy", seed: int = 0, **overrides) -> Phantom:
    """A synthetic CT, a rough segment and the ground-truth surfaces (see module doc).

    Parameters
    ----------
    case : str
        A key of :data:`CASES`.
    seed : int
        Seeds pores, foramina, HU fields, noise and the rough mask; with
        ``vary_geometry=True`` also the parts' sizes and positions.
    **overrides
        Any key of ``_BASE`` (e.g. ``gap=1.5``, ``slice_spacing=2.0``,
        ``low_density_end="proximal"``); unknown keys raise ValueError.

    Returns
    -------
    Phantom
        ct (int16, array (z, y, x)), mask, truth, neighbour_truth (None without the cup),
        info.
    """
    cfg, rng, model, size, spacing = _build(case, seed, overrides)

    arr = _form_ct(model, cfg, rng, tuple(size), spacing)
    ct = sitk.GetImageFromArray(arr)
    ct.SetSpacing(spacing.tolist())
    ct.SetOrigin(model.origin.tolist())
    ct.SetDirection(model.direction.ravel().tolist())

    mask = _rough_mask(model, cfg, rng, size, spacing)

    truth, neighbour, h, gap_min = _truths(model, cfg)
    lo_b, hi_b = model.bone_bbox()

    hu = dict(cortical="1220-1580", trabecular="190-490 (+80 under the cortex)",
              marrow="20-80", soft_tissue=40, fat=-100, air=-1000,
              cartilage=f"{cfg['cartilage_hu'] - 30:g}-{cfg['cartilage_hu'] + 30:g}")
    if cfg["low_density_end"] is not None:
        lt, lv = cfg["low_trab_hu"], cfg["low_trab_var"]
        hu["low_density_end"] = cfg["low_density_end"]
        hu["low_density_trabecular"] = f"{lt - lv:g}-{lt + lv:g} (+{cfg['low_subcortical_hu']:g} under the cortex)"
        if cfg["low_cortex_hu"] is not None:
            lc, lcv = cfg["low_cortex_hu"], cfg["low_cortex_var"]
            hu["low_density_cortical"] = f"{lc - lcv:g}-{lc + lcv:g}"
    if len(model.cortex_holes):
        hu["cortex_holes"] = f"{cfg['cortex_hole_hu'] - 20:g}-{cfg['cortex_hole_hu'] + 20:g}"
    info = dict(cfg)
    info.update(
        case=case, seed=seed, gap_min_mm=gap_min,
        slice_thickness=cfg["slice_thickness"] or cfg["slice_spacing"],
        bone_length_mm=float(hi_b[2] - lo_b[2]),
        truth_grid_mm=h,
        truth_note="flying edges at truth_grid_mm, vertices Newton-projected onto the SDF zero set",
        truth_excludes="pores, foramina, the lesion, low density and cortical holes "
                       "(truth = outer envelope of the healthy bone)",
        ct_size=[int(x) for x in size], ct_spacing=spacing.tolist(),
        mask_spacing=list(mask.GetSpacing()),
        n_pores=int(len(model.pores)), n_foramina=len(model.foramina),
        n_cortex_holes=int(len(model.cortex_holes)),
        hu=hu,
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
