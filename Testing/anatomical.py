"""Anatomical CT phantoms: real bone shapes (TotalSegmentator labels of a real CT), made
smooth, with thin plates, joint spaces, a cortex of varying thickness and a CT formed from
them, with the exact truth (issue 18).

    ph = make_anatomical("pelvis_3mm", seed=0)
    ph.ct, ph.labels, ph.truths[78], ph.names[78], ph.info["plates"]["hip_right"]

Why: the geometric femur phantoms (Testing/phantoms.py) have thick, convex parts. The product
fails where the CT barely resolves the bone: thin cortical plates, thinner than the voxel,
blurred to a few hundred HU (iliac wing, sacral ala, transverse processes, scapular blade).
These phantoms reproduce that physical effect on real shapes, with a known truth.

Frames and arrays
-----------------
Everything is built in the **local frame** q (mm): the source label map's index frame times
its spacing, q = spacing * (i, j, k) (x-y-z). The source's physical LPS position of q is
``origin_src + D_src @ q``. The **model grid** is an isotropic grid of step ``h``
(``model_grid`` mm, 0.4-0.5) aligned with q; every bone's fields live on a sub-box (crop) of it.
The CT grid is aligned with q too; physical LPS = ``x0 + D @ (q - q_ct0)`` with ``D = D_src @
R(direction_angles_deg)`` and x0 the source's physical position of the first CT voxel: at zero
angles the phantom lies exactly where the real CT's bones are; with angles the voxel arrays are
the same and the object is rotated in physical space (as Testing/phantoms.py does). Arrays are
(z, y, x); point arrays (n, 3) x-y-z in mm.

How a bone is made (:func:`_make_bone`, :func:`_carve_joints`)
---------------------------------------------------------------
The smooth fields are computed on a geometry grid of step hg = 2 h (nothing in a 3 mm label is
finer) and brought to the model grid by separable cubic convolution (Keys; exact for
quadratics); F is composed from them node by node on the model grid.

1. **Label -> smooth shape.** The bone's voxels of the source label (several label values may
   form one bone: sacrum = sacrum + S1) as a 0/1 box function, blurred analytically by a
   Gaussian of ``label_sigma`` mm (the exact blur of the voxel boxes: a tensor product of
   erf-differences, no resampling). Where the source volume cuts a bone at its lowest slice
   (the femur below the lesser trochanter, the ischium), that slice is first repeated for the
   bone's ``extend_mm`` (femur 24 mm, hip 6 mm), so the bone ends in a rounded stub inside the
   phantom's field of view.
2. **SDF.** Nodes where the blur exceeds 0.5 are inside; their signed Euclidean distance (the
   ``edt`` package, node centres moved to the voxel faces by h/2), smoothed by a Gaussian of
   one geometry node, is sdf0 (mm, negative inside, 1-Lipschitz), free of the label's stair steps.
3. **Seeded perturbation:** sdf0 += ``perturb_mm`` x f, f a smooth random field of unit std
   (cubic B-spline lattice, 40 mm): a low-frequency shape change per seed.
4. **Thin plates** (kinds with ``plate`` = (t_min, t_max) mm; the 3 mm labels are 6-12 mm
   thick where the real bone is a 1-3 mm plate):

   * local half-thickness R = the largest depth (-sdf0) within a cube of half-width r_b + 1 mm
     (an upper bound of the inscribed-ball radius, exact up to that width); plate weight
     w = 1 - smoothstep(r_a, r_b, R) (kind's r_a, r_b);
   * D_s = G(``medial_sigma``) * sdf0 and its gradient; the plate's normal n = principal
     eigenvector of the structure tensor G(2 mm) * (grad D_s grad D_s^T) (gradients are +-n on
     a plate's two faces); sheetness 1 - m2/m1 of its two largest eigenvalues (~1 on a plate,
     ~0 on a rod: the pubic rami or a process are not turned into wires); w *= smoothstep(0.35,
     0.65, sheetness);
   * distance to the medial surface d_m = s sqrt(2) erfinv(|grad D_s . n|) with
     s = sqrt(medial_sigma^2 + hg^2): exact for a flat plate, whose SDF |u| - r smoothed by a
     Gaussian of s has |dD/du| = erf(|u| / (s sqrt 2)) for any r; only the component along n
     counts, so a wedge (a plate thickening) is not pierced; |grad D_s . n|^2 (smooth through
     the medial surface) is what is interpolated to the model grid;
   * target half-thickness rho = t / 2, t = t_min + (t_max - t_min) s', s' = clip(0.35 + 0.3 f2
     + 0.25 (R - r_a) / (r_b - r_a)), f2 a seeded 25 mm field: thinner where the label is thinner;
   * **F = max(sdf0, (1 - w) sdf0 + w (d_m - rho))**: F >= sdf0, so the plate stays inside the
     label's shape; on the medial surface d_m = 0, so it stays inside the bone; the plate is 2 rho
     thick where w = 1 and thickens smoothly into the bodies;
   * protection (:func:`_protect_medial`): where plates meet (T-junctions) d_m is unreliable;
     medial nodes (depth maximal along n) that the thinning would remove get w = 0 around them,
     so no hole opens. The truth's genus is checked against the genus of sdf0's zero set
     (``info["bones_info"][name]["genus_smoothed_label"]``).
5. **Joints.** For every pair of bones whose sdf0 sum drops below 1.1 g + 2 k:
   psi = (sdf0_a - sdf0_b) / 2 (1-Lipschitz, zero on their bisector) carves both:
   F_a = smax(F_a, psi + 0.55 g), F_b = smax(F_b, -psi + 0.55 g) (polynomial smooth max,
   k = ``joint_margin_mm``: rounded joint margins), g = ``joint_gaps[(a, b)]`` or
   ``joint_gap_mm``: a and b end at least g apart (1.1 g leaves room for the perturbation's
   Lipschitz excess), with parallel articular surfaces. The smallest distance of the two truth
   meshes is measured exactly and stored (``info["joints"]``).
6. Only the largest component of {F < 0} is kept; enclosed cavities are filled.

**Truth** = the zero set of F: flying edges of F's samples on the model grid (inside negative,
which keeps plates >= h connected; vertices exactly on the zero set of F's trilinear
interpolant, the triangle interiors within ~h^2 / (8 R_curv)), faces outward, physical LPS.
``info["plates"]`` gives the truth's wall thickness by ray casting (:func:`thickness_samples`):
per bone the area fractions thinner than 1 / 2 / 3 mm, the plate zone's thickness percentiles
and the agreement with 2 rho where w >= 0.95.

HU model and CT formation (:func:`_form_ct`)
--------------------------------------------
On a fine grid (the model grid, or every second node of it when pixel and slice thickness are
>= 3 h): the background is the source's real CT (its bones and everything above 120 HU set
to 45 HU, clipped to [-1000, 100], smoothed by one source voxel): the real body outline with
air outside, subcutaneous and intermuscular fat, muscle and organs, bowel gas (the synthetic
shoulder: muscle, fat and air behind the back, lung in front). Bone: occupancy
o = clip(0.5 - F / w_f, 0, 1) (w_f the fine step: a box anti-aliasing that keeps a sub-voxel
plate's HU x thickness exact), core o_c = clip(0.5 - (F + t_c) / w_f, 0, 1);
HU = bg + o (cortex - bg) + o_c (trabecular - cortex). Cortex thickness t_c = kind's ``cortex``
x (1 + 0.35 f), clipped to [0.3, 3] mm (a plate thinner than 2 t_c is all cortex); cortex HU =
kind's ``cortex_hu`` + 220 f - 350 w, clipped to [1000, 1800] (thin plates are the less dense);
trabecular HU = kind's ``trab_hu`` + 50 f + 35 texture + 60 exp(-(depth - t_c) / 1.5 mm)
(denser under the cortex); f seeded smooth fields (18-25 mm), texture a periodic field of
0.8 mm correlation. The kinds' HU and thicknesses are calibrated against the real 3 mm CT the
shapes come from (its thin iliac plates peak at ~300 HU, its trabecular bone is 100-200 HU).
Between two bones where F_a + F_b < L (L = g + 1 mm; between vertebrae the disc, L =
``disc_mm``) the space is cartilage (``cartilage_hu`` +- 18) or disc (``disc_hu`` +- 12). The
fine image is blurred and sampled in one separable linear operator: in-plane the pixel aperture
(a box of the pixel size) convolved with a Gaussian PSF (``psf_sigma``), along z the slice
profile (a box of ``slice_thickness`` convolved with a Gaussian of 0.15 x thickness); then
Gaussian noise (``noise`` HU), rounded, int16.

**Labels** (AI-style, :func:`labels_ai`): majority vote of the truths (F < 0) over 3 x 3 x 3
points in every voxel of a coarse grid (``label_grid`` mm, random phase), nearest-neighbour onto
the CT grid; optionally ``steal_mm``: voxels of one bone within that distance of another given
to the other.

Random streams: seeded by ``[seed, stream, bone index]``: geometry perturbation (1), plate
thickness field (2), HU fields (3), CT noise (4), label grid phase (5). Held-out seeds change
every one of them.

The source data is ``../shared/data`` (beside the repository; ``BONEWATERTIGHT_DATA``
overrides). Without it :class:`DataMissing` is raised (tests skip); the ``sample_*`` cases use
the bundled ``Resources/SampleData/lumbar_spine_3mm`` (L3, L4) and always work.
"""

from __future__ import annotations

import math
import os
import sys
import time
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
for _p in (ROOT, HERE):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from BoneWatertightLib.mesh import Surface  # noqa: E402

# ---------------------------------------------------------------------------- data

SAMPLE_DIR = os.path.join(ROOT, "Resources", "SampleData", "lumbar_spine_3mm")


def data_dir() -> str:
    """Folder of the real CT data: $BONEWATERTIGHT_DATA, else ../shared/data beside the
    repository (a worktree or the main checkout), else /work/shared/data."""
    env = os.environ.get("BONEWATERTIGHT_DATA")
    if env:
        return env
    for cand in (os.path.join(ROOT, "..", "shared", "data"), "/work/shared/data"):
        if os.path.isdir(cand):
            return os.path.abspath(cand)
    return os.path.abspath(os.path.join(ROOT, "..", "shared", "data"))


class DataMissing(FileNotFoundError):
    """The real CT / reference labels a case is made from are not on this machine."""


# Source volumes: (folder or None for the bundled sample, CT file, label file).
SOURCES = {
    "pelvis": ("ts_example_ct_abdomen_pelvis_3mm", "ct.nrrd", "bones_labels.nrrd"),
    "sample": (None, "ct.nrrd", "labels.nrrd"),
    # No scapula label exists in the shared data (the CT that shows scapulae has no reference):
    # a synthetic right scapula + proximal humerus label on a 1.5 mm grid, see _synthetic_shoulder.
    "shoulder": ("synthetic", None, None),
}


def _source_paths(source: str):
    folder, ct, lab = SOURCES[source]
    if folder == "synthetic":
        return None, None
    base = SAMPLE_DIR if folder is None else os.path.join(data_dir(), folder)
    paths = os.path.join(base, ct), os.path.join(base, lab)
    missing = [p for p in paths if not os.path.exists(p)]
    if missing:
        raise DataMissing(
            f"anatomical phantoms need the real CT data: {', '.join(missing)} not found. "
            f"Put the shared data folder at {data_dir()} (or set BONEWATERTIGHT_DATA); the "
            f"'sample_*' cases use the bundled Resources/SampleData instead.")
    return paths


def data_available(source: str = "pelvis") -> bool:
    try:
        _source_paths(source)
        return True
    except DataMissing:
        return False


# ---------------------------------------------------------------------------- bones and cases

# Bone kinds. plate: (t_min, t_max) mm of the thinned plates, or None (no thinning); r_a / r_b:
# local half-thickness (mm) of the smoothed label below which the bone is a plate (w = 1) /
# above which it is left as it is (w = 0); cortex: mean cortical thickness (mm) outside the
# plates; cortex_hu / trab_hu: mean HU.
KINDS = {
    "hip": dict(plate=(0.6, 1.7), r_a=4.5, r_b=6.5, cortex=1.2, cortex_hu=1350.0, trab_hu=150.0),
    "sacrum": dict(plate=(0.7, 2.4), r_a=2.8, r_b=4.2, cortex=0.6, cortex_hu=1200.0, trab_hu=95.0),
    "femur": dict(plate=None, r_a=0.0, r_b=0.0, cortex=1.0, cortex_hu=1300.0, trab_hu=170.0),
    "vertebra": dict(plate=(1.2, 3.0), r_a=3.0, r_b=4.6, cortex=0.7, cortex_hu=1250.0, trab_hu=170.0),
    "scapula": dict(plate=(0.6, 2.2), r_a=2.6, r_b=4.2, cortex=0.9, cortex_hu=1350.0, trab_hu=200.0),
    "humerus": dict(plate=None, r_a=0.0, r_b=0.0, cortex=1.6, cortex_hu=1400.0, trab_hu=220.0),
}

# Bones of the sources: label values forming the bone (the first is the phantom's label value,
# the TotalSegmentator id), kind, and how far (mm) to extend a bone the source volume cuts.
BONES = {
    "hip_right": dict(values=(78,), kind="hip", extend_mm=6.0),
    "hip_left": dict(values=(77,), kind="hip", extend_mm=6.0),
    "sacrum": dict(values=(25, 26), kind="sacrum", extend_mm=0.0),
    "femur_right": dict(values=(76,), kind="femur", extend_mm=24.0),
    "femur_left": dict(values=(75,), kind="femur", extend_mm=24.0),
    "L3": dict(values=(29,), kind="vertebra", extend_mm=0.0),
    "L4": dict(values=(28,), kind="vertebra", extend_mm=0.0),
    "L5": dict(values=(27,), kind="vertebra", extend_mm=0.0),
    "scapula_right": dict(values=(72,), kind="scapula", extend_mm=0.0),
    "humerus_right": dict(values=(70,), kind="humerus", extend_mm=0.0),
}

_BASE = dict(
    source="pelvis",
    bones=("hip_right", "sacrum", "femur_right"),
    model_grid=0.5,         # h: step (mm) of the model grid (SDFs, truth, fine CT grid)
    label_sigma=1.5,        # Gaussian (mm) smoothing the 3 mm label's voxel boxes
    medial_sigma=1.2,       # Gaussian (mm) of D_s whose gradient gives the medial distance
    perturb_mm=0.3,         # seeded low-frequency shape change (std, mm)
    plates=True,            # thin the plates (False: the smoothed label as it is)
    plate_scale=1.0,        # multiplies every kind's plate thicknesses (t_min, t_max)
    joint_gap_mm=1.5,       # default joint space between two bones that touch (mm)
    joint_gaps=None,        # {(bone a, bone b): gap mm} overrides
    joint_margin_mm=1.0,    # smooth-max radius rounding the joint margins
    disc_mm=10.0,           # sum of distances below which the space between vertebrae is disc
    margin_mm=12.0,         # CT field of view: the bones' box plus this
    pixel=0.7,              # in-plane spacing (mm)
    slice_spacing=2.5,      # distance between slices (mm)
    slice_thickness=None,   # None = slice_spacing
    psf_sigma=0.5,          # in-plane Gaussian PSF (mm), convolved with the pixel aperture
    noise=25.0,             # Gaussian noise (HU)
    direction_angles_deg=(0.0, 0.0, 0.0),  # rotations about x, y, z of the image grid
    label_grid=1.5,         # AI label grid (mm), scalar or (x, y, z)
    steal_mm=None,          # None or (bone from, bone to, mm): AI label error at a joint
    cartilage_hu=120.0,
    disc_hu=85.0,
)

CASES: dict[str, dict] = {
    # (a) hip bone + sacrum + proximal femur of the 3 mm pelvis CT, as a fine clinical CT and as
    # the 3 mm CT itself.
    "pelvis_0p7x2p5": dict(bones=("hip_right", "sacrum", "femur_right"), pixel=0.7,
                           slice_spacing=2.5, psf_sigma=0.5, noise=25.0, label_grid=1.5,
                           joint_gaps={("hip_right", "femur_right"): 2.5,
                                       ("hip_right", "sacrum"): 1.5}),
    "pelvis_3mm": dict(bones=("hip_right", "sacrum", "femur_right"), pixel=3.0,
                       slice_spacing=3.0, psf_sigma=0.6, noise=20.0, label_grid=3.0,
                       joint_gaps={("hip_right", "femur_right"): 2.5,
                                   ("hip_right", "sacrum"): 1.5}),
    # (b) lumbar L3-L5 (discs, facet joints, transverse processes).
    "lumbar_3mm": dict(bones=("L3", "L4", "L5"), pixel=3.0, slice_spacing=3.0, psf_sigma=0.6,
                       noise=20.0, label_grid=3.0, model_grid=0.4, joint_gap_mm=1.5),
    "lumbar_0p7x2p5": dict(bones=("L3", "L4", "L5"), pixel=0.7, slice_spacing=2.5,
                           psf_sigma=0.5, noise=25.0, label_grid=1.5, model_grid=0.4,
                           joint_gap_mm=1.5, direction_angles_deg=(6.0, -4.0, 9.0)),
    # (c) scapula-like: a synthetic right scapula + humerus (no scapula label exists in the
    # data), the blade thinned like the iliac wing; the glenohumeral joint 2.5 mm.
    "scapula_3mm": dict(source="shoulder", bones=("scapula_right", "humerus_right"), pixel=3.0,
                        slice_spacing=3.0, psf_sigma=0.6, noise=20.0, label_grid=3.0,
                        label_sigma=1.0, joint_gap_mm=2.5),
    "scapula_0p7x2p5": dict(source="shoulder", bones=("scapula_right", "humerus_right"), pixel=0.7,
                            slice_spacing=2.5, psf_sigma=0.5, noise=25.0, label_grid=1.5,
                            label_sigma=1.0, joint_gap_mm=2.5, direction_angles_deg=(0.0, 8.0, -12.0)),
    # CI: L3 + L4 of the bundled sample (always available), coarse and quick.
    "sample_L3L4": dict(source="sample", bones=("L3", "L4"), pixel=1.5, slice_spacing=3.0,
                        psf_sigma=0.6, noise=15.0, label_grid=3.0, model_grid=0.5,
                        joint_gap_mm=1.5, margin_mm=8.0),
}


# ---------------------------------------------------------------------------- numerical helpers

def _smoothstep(e0, e1, x):
    t = np.clip((x - e0) / max(e1 - e0, 1e-9), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _smax(a, b, k):
    """Polynomial smooth maximum of radius k (>= max(a, b); equal to it where |a - b| > k)."""
    hh = np.clip(0.5 - 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * hh + k * hh * (1.0 - hh)


def _tensor(arr, mz, my, mx):
    """Apply one matrix per axis to a (z, y, x) array: out[Z, Y, X] = sum mz[Z, z] my[Y, y]
    mx[X, x] arr[z, y, x] (float32). Used for every separable operation: the analytic blur of
    label voxels, linear / B-spline interpolation, the CT's PSF and slice profile."""
    arr = np.asarray(arr, np.float32)
    t = arr @ np.asarray(mx, np.float32).T                       # (z, y, X)
    t = np.asarray(my, np.float32)[None] @ t                    # (z, Y, X)
    nz, ny, nx = t.shape
    t = (np.asarray(mz, np.float32) @ t.reshape(nz, ny * nx)).reshape(-1, ny, nx)
    return t


def _box_gauss_matrix(x_out, centres, width, sigma, step=None):
    """(len(x_out), len(centres)): a box of ``width`` at each centre convolved with a Gaussian
    of ``sigma`` (mm), evaluated at x_out: 0.5 [erf((d + w/2)/(s sqrt 2)) - erf((d - w/2)/(s sqrt 2))].
    With ``step`` the rows are the weights of a sampled convolution (normalised to sum 1)."""
    from scipy.special import erf

    d = np.asarray(x_out, float)[:, None] - np.asarray(centres, float)[None, :]
    s = max(float(sigma), 1e-6) * math.sqrt(2.0)
    m = 0.5 * (erf((d + 0.5 * width) / s) - erf((d - 0.5 * width) / s))
    if step is not None:
        m /= np.maximum(m.sum(axis=1, keepdims=True), 1e-12)
    return m.astype(np.float32)


def _linear_matrix(x_out, x0, step, n):
    """(len(x_out), n): linear interpolation of samples at x0 + step * i, clamped at the ends."""
    t = np.clip((np.asarray(x_out, float) - x0) / step, 0.0, n - 1.0)
    i0 = np.minimum(np.floor(t).astype(int), n - 2) if n > 1 else np.zeros(len(t), int)
    w = t - i0
    m = np.zeros((len(t), n), np.float32)
    r = np.arange(len(t))
    m[r, i0] += (1.0 - w)
    if n > 1:
        m[r, i0 + 1] += w
    return m


def _bspline3(t):
    t = np.abs(t)
    return np.where(t < 1.0, 2.0 / 3.0 - t * t + 0.5 * t ** 3,
                    np.where(t < 2.0, (2.0 - t) ** 3 / 6.0, 0.0))


class _Lattice:
    """Smooth random field of about unit standard deviation over a box: cubic B-spline with
    N(0, 1) coefficients on a lattice of ``spacing`` mm (correlation length ~ spacing).
    Evaluated on grids (:meth:`grid`, separable) or at points (:meth:`points`)."""

    # Variance of a cubic B-spline sum of unit-variance coefficients, per axis (mean over phase).
    _AXIS_VAR = 0.4794

    def __init__(self, rng, lo, hi, spacing):
        self.s = float(spacing)
        self.c0 = np.asarray(lo, float) - 1.5 * self.s
        self.n = np.ceil((np.asarray(hi, float) - self.c0) / self.s).astype(int) + 3
        self.coef = rng.normal(size=tuple(self.n[::-1])).astype(np.float32)
        self.norm = float(1.0 / math.sqrt(self._AXIS_VAR ** 3))

    def _matrix(self, axis, x):
        c = self.c0[axis] + self.s * np.arange(self.n[axis])
        return _bspline3((np.asarray(x, float)[:, None] - c[None, :]) / self.s).astype(np.float32)

    def grid(self, xs, ys, zs):
        """Field on the grid xs x ys x zs (q mm) -> (len(zs), len(ys), len(xs)) float32."""
        return self.norm * _tensor(self.coef, self._matrix(2, zs), self._matrix(1, ys),
                                   self._matrix(0, xs))

    def points(self, p):
        """Field at points p (n, 3) q mm -> (n,)."""
        p = np.asarray(p, float)
        t = (p - self.c0) / self.s
        i0 = np.floor(t).astype(int) - 1
        out = np.zeros(len(p))
        for a in range(4):
            wa = _bspline3(t[:, 2] - (i0[:, 2] + a))
            ia = np.clip(i0[:, 2] + a, 0, self.n[2] - 1)
            for b in range(4):
                wb = wa * _bspline3(t[:, 1] - (i0[:, 1] + b))
                ib = np.clip(i0[:, 1] + b, 0, self.n[1] - 1)
                for c in range(4):
                    w = wb * _bspline3(t[:, 0] - (i0[:, 0] + c))
                    ic = np.clip(i0[:, 0] + c, 0, self.n[0] - 1)
                    out += w * self.coef[ia, ib, ic]
        return self.norm * out


def _rotation(angles_deg):
    ax, ay, az = np.radians(angles_deg)
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    rz = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def _peak_mb() -> float:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


# ---------------------------------------------------------------------------- synthetic shoulder

def _thick_triangles(p, tris, r):
    """min over triangles (k, 3, 3) of (distance of p (n, 3) to the triangle) - r."""
    from metrics import closest_point_on_triangles

    out = np.full(len(p), 1e3)
    for t in tris:
        t = np.asarray(t, float)
        # only the points near the triangle (its box + r + 6 mm); the rest stay far away
        near = np.flatnonzero(np.all((p > t.min(0) - r - 6.0) & (p < t.max(0) + r + 6.0), axis=1))
        q = p[near]
        a, b, c = (np.broadcast_to(v, q.shape) for v in t)
        cp, _ = closest_point_on_triangles(q, a, b, c)
        out[near] = np.minimum(out[near], np.linalg.norm(cp - q, axis=1) - r)
    return out


def _capsule(p, a, b, r):
    a = np.asarray(a, float)
    ba = np.asarray(b, float) - a
    t = np.clip((p - a) @ ba / (ba @ ba), 0.0, 1.0)
    return np.linalg.norm(p - a - t[:, None] * ba, axis=1) - r


def _smin(a, b, k):
    hh = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * hh - k * hh * (1.0 - hh)


_SHOULDER = {}


def _synthetic_shoulder():
    """A right scapula and proximal humerus as a coarse label map (1.5 mm, like an AI label of
    a 1.5 mm CT) and a soft-tissue background, in place of real data (none has a scapula
    label). Local frame (u lateral, v posterior, w superior, mm); LPS x = -u (the patient's
    right), y = v, z = w, identity direction.

    Scapula: the blade, a bent quadrilateral plate 4.5 mm thick in the label (superior angle,
    coracoid base, glenoid neck, inferior angle), a 10 mm lateral border, 5 / 4 mm medial and
    superior borders, the spine (a 7 mm plate rising 6-26 mm posteriorly), the acromion (8 mm
    plate over the joint), the coracoid (10 mm rod) and the glenoid (an ellipsoid lump facing
    laterally); humerus: head (sphere r 24 mm) touching the glenoid as a label would, neck,
    greater tubercle and 85 mm of shaft. Background: muscle 45 HU, subcutaneous fat
    (-100 HU) and air behind the back, the lung (-850 HU) in front of the chest wall (no ribs:
    the case has no other bone)."""
    if "images" in _SHOULDER:
        return _SHOULDER["images"]
    sp = 1.5
    lo = np.array([-20.0, -60.0, -160.0])  # u, v, w
    hi = np.array([185.0, 70.0, 25.0])
    n = np.floor((hi - lo) / sp).astype(int) + 1
    us, vs, ws = (lo[a] + sp * np.arange(n[a]) for a in range(3))
    W, V, U = np.meshgrid(ws, vs, us, indexing="ij")
    p = np.column_stack([U.ravel(), V.ravel(), W.ravel()])

    def bend(u, w):  # the blade follows the rib cage (concave anteriorly)
        return 0.0045 * (u - 55.0) ** 2 - 8.0 + 0.0008 * (w + 60.0) ** 2

    def pt(u, w, dv=0.0):
        return (u, bend(u, w) + dv, w)

    S, C, G, I, M = (5, 0), (65, -8), (88, -32), (25, -125), (48, -55)
    blade = _thick_triangles(p, [(pt(*M), pt(*a), pt(*b)) for a, b in ((S, C), (C, G), (G, I), (I, S))], 2.25)
    borders = np.minimum.reduce([_capsule(p, pt(*I), pt(*G), 5.0), _capsule(p, pt(*S), pt(*I), 2.5),
                                 _capsule(p, pt(*S), pt(*C), 2.0)])
    A0, B0 = pt(5, -30), pt(84, -10)
    spine = _thick_triangles(p, [(A0, B0, pt(84, -10, 26.0)), (A0, pt(84, -10, 26.0), pt(5, -30, 6.0))], 3.5)
    acromion = _thick_triangles(p, [(pt(84, -10, 24.0), (126, 18, 10), (133, 6, 2)),
                                    (pt(84, -10, 24.0), (133, 6, 2), (104, 12, -2))], 4.0)
    coracoid = np.minimum(_capsule(p, pt(66, -8), (80, -32, -14), 5.0), _capsule(p, (80, -32, -14), (95, -36, -26), 4.5))
    q = (p - np.array([97.0, 0.5, -36.0])) / np.array([11.0, 14.0, 20.0])
    glenoid = (np.linalg.norm(q, axis=1) - 1.0) * 11.0
    scap = _smin(_smin(_smin(blade, borders, 2.5), _smin(spine, acromion, 3.0), 3.0),
                 _smin(coracoid, glenoid, 3.0), 3.0)
    scap = _smin(scap, _capsule(p, pt(*G), (97.0, 0.5, -36.0), 7.0), 3.0)
    head_c = np.array([131.0, 0.5, -36.0])
    hum = np.linalg.norm(p - head_c, axis=1) - 24.0
    hum = _smin(hum, _capsule(p, head_c, (140.0, 3.0, -62.0), 15.0), 4.0)
    hum = _smin(hum, np.linalg.norm(p - np.array([150.0, -4.0, -30.0]), axis=1) - 10.0, 4.0)
    hum = _smin(hum, _capsule(p, (140.0, 3.0, -62.0), (142.0, 3.0, -148.0), 11.0), 5.0)
    lab = np.zeros(len(p), np.uint8)
    lab[scap < 0] = BONES["scapula_right"]["values"][0]
    lab[(hum < 0) & (scap >= 0)] = BONES["humerus_right"]["values"][0]
    # background: skin behind the back at v = 58, fat 10 mm under it, lung in front of v = -30,
    # the arm's skin lateral to u = 175
    ct = np.full(len(p), SOFT_TISSUE_HU, np.float32)
    ct[(p[:, 1] > 48.0) | (p[:, 0] > 165.0)] = -100.0
    ct[(p[:, 1] > 58.0) | (p[:, 0] > 175.0)] = -1000.0
    ct[(p[:, 1] < -30.0 - 0.002 * (p[:, 0] - 40.0) ** 2) & (p[:, 0] < 120.0)] = -850.0
    shape = tuple(n[::-1])
    images = []
    for arr in (ct.reshape(shape), lab.reshape(shape)):
        img = sitk.GetImageFromArray(arr)
        img.SetSpacing([sp] * 3)
        # LPS x = -u: the index axis i runs towards -x (direction diag(-1, 1, 1))
        img.SetDirection([-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])
        img.SetOrigin([-lo[0] - 60.0, lo[1] - 150.0, lo[2] + 1200.0])
        images.append(img)
    _SHOULDER["images"] = tuple(images)
    return _SHOULDER["images"]


# ---------------------------------------------------------------------------- the model

@dataclass
class _Bone:
    """One bone on the model grid: F (z, y, x) float32 on the nodes start + (i, j, k)
    (x-y-z order of ``start``, model-grid indices), w the plate weight, rho the target
    half-thickness (mm) of the plates (float16, both on the same nodes)."""

    name: str
    label: int
    kind: str
    start: np.ndarray
    F: np.ndarray
    sdf0: np.ndarray | None = None
    w: np.ndarray | None = None
    rho: np.ndarray | None = None
    stats: dict = field(default_factory=dict)

    @property
    def stop(self):
        return self.start + np.array(self.F.shape[::-1])


class _Model:
    """Geometry of a case: the source, the model grid, the bones and the frame."""

    def __init__(self, cfg, seed):
        self.cfg = cfg
        self.seed = int(seed)
        self.h = float(cfg["model_grid"])
        ct_path, lab_path = _source_paths(cfg["source"])
        if ct_path is None:
            self.src_ct, self.src_lab = _synthetic_shoulder()
        else:
            self.src_ct = sitk.ReadImage(ct_path)
            self.src_lab = sitk.ReadImage(lab_path)
        self.src_spacing = np.array(self.src_lab.GetSpacing(), float)
        self.src_origin = np.array(self.src_lab.GetOrigin(), float)
        self.src_dir = np.array(self.src_lab.GetDirection(), float).reshape(3, 3)
        self.lab = sitk.GetArrayFromImage(self.src_lab)
        for name in cfg["bones"]:
            if name not in BONES:
                raise ValueError(f"unknown bone {name!r}; choose from {', '.join(BONES)}")
            if not np.isin(self.lab, BONES[name]["values"]).any():
                raise ValueError(f"bone {name!r} (labels {BONES[name]['values']}) is not in the "
                                 f"{cfg['source']} label map")
        self.bones: list[_Bone] = []

    def rng(self, stream, index=0):
        return np.random.default_rng([self.seed, int(stream), int(index)])

    # frame
    def node_q(self, idx):
        """q (mm) of model-grid node indices (n, 3) x-y-z (or per-axis arrays)."""
        return self.g0 + self.h * np.asarray(idx, float)

    def to_physical(self, q):
        return (np.asarray(q, float) - self.q_ct0) @ self.direction.T + self.x0

    def to_local(self, x):
        return (np.asarray(x, float) - self.x0) @ self.direction + self.q_ct0

    def bone(self, name):
        for b in self.bones:
            if b.name == name:
                return b
        raise KeyError(name)

    def sample_F(self, b: _Bone, q, outside=1e3):
        """F of bone b at points q (n, 3) by trilinear interpolation of its node values (the
        function whose zero set the truth is); ``outside`` beyond its crop."""
        from scipy import ndimage

        t = (np.asarray(q, float) - self.g0) / self.h - b.start  # x-y-z node coordinates
        return ndimage.map_coordinates(b.F, t[:, ::-1].T, order=1, mode="constant", cval=outside)


# ---------------------------------------------------------------------------- bones

def _source_mask(model, name):
    """The bone's source voxels (z, y, x) bool with the volume-cut sides extended (see module
    doc, step 1), and the source index (i, j, k) of the extended array's voxel (0, 0, 0)."""
    spec = BONES[name]
    m = np.isin(model.lab, spec["values"])
    idx0 = np.zeros(3, int)
    n_ext = int(round(spec["extend_mm"] / float(model.src_spacing[2])))
    if n_ext > 0:
        # The source scans cut the bones only at the bottom (k = 0); repeat the first slice.
        if m[0].any():
            m = np.concatenate([np.repeat(m[:1], n_ext, axis=0), m], axis=0)
            idx0[2] -= n_ext
    return m, idx0


def _crop_pad_mm(cfg):
    """Crop margin (mm) of a bone's fields beyond its label box: room for the blur, the joint
    carving (psi needs the neighbour's sdf0 up to g + 2 k) and the disc filler (F_a + F_b < L)."""
    gaps = [cfg["joint_gap_mm"]] + list((cfg.get("joint_gaps") or {}).values())
    return float(max(8.0, 3.0 * cfg["label_sigma"] + 2.0, max(gaps) * 1.1 + 2 * cfg["joint_margin_mm"] + 3.0,
                     cfg["disc_mm"] + 2.0 if any(BONES[b]["kind"] == "vertebra" for b in cfg["bones"]) else 0.0))


def _edt_sdf(inside, h):
    """Signed distance (mm, negative inside) of a boolean (z, y, x) mask on a grid of step h,
    node centres shifted to the voxel faces (+-h/2), float32."""
    import edt

    d_in = edt.edt(np.ascontiguousarray(inside), anisotropy=(h, h, h), black_border=False, parallel=2)
    d_out = edt.edt(np.ascontiguousarray(~inside), anisotropy=(h, h, h), black_border=False, parallel=2)
    out = np.where(inside, -(d_in - 0.5 * h), d_out - 0.5 * h).astype(np.float32)
    return out


def _grad_norm(a, h, chunk=48):
    """|grad a| (central differences, one-sided at the ends) of a (z, y, x) float32 array, in
    z-chunks (bounded memory)."""
    out = np.empty_like(a)
    nz = a.shape[0]
    for z0 in range(0, nz, chunk):
        z1 = min(nz, z0 + chunk)
        lo, hi = max(0, z0 - 1), min(nz, z1 + 1)
        gz, gy, gx = np.gradient(a[lo:hi], h)
        s = slice(z0 - lo, z0 - lo + (z1 - z0))
        out[z0:z1] = np.sqrt(gz[s] ** 2 + gy[s] ** 2 + gx[s] ** 2)
    return out


def _up2(c, axis, n_fine):
    """Cubic-convolution (Keys) upsampling by 2 along ``axis``: fine node j lies at coarse
    index 1 + j / 2 (even j: a coarse node, copied; odd j: a midpoint, weights
    (-1, 9, 9, -1) / 16). Indices past the end are clamped (edge replication)."""
    c = np.moveaxis(np.asarray(c, np.float32), axis, 0)
    n_even, n_odd = (n_fine + 1) // 2, n_fine // 2
    need = max(1 + n_even, n_odd + 3)
    if len(c) < need:
        c = np.concatenate([c, np.repeat(c[-1:], need - len(c), axis=0)], axis=0)
    out = np.empty((n_fine,) + c.shape[1:], np.float32)
    out[0::2] = c[1:1 + n_even]
    out[1::2] = (9.0 * (c[1:n_odd + 1] + c[2:n_odd + 2]) - c[0:n_odd] - c[3:n_odd + 3]) / 16.0
    return np.moveaxis(out, 0, axis)


class _Upsampler:
    """Fields on the geometry grid (step hg = 2 h, node k at fine node 2 (k - 1)) -> the crop's
    model-grid nodes, by separable cubic convolution; x and y once per field, z per chunk."""

    def __init__(self, fine_shape):
        self.shape = fine_shape
        self.xy = {}

    def add(self, key, arr):
        nz, ny, nx = self.shape
        self.xy[key] = _up2(_up2(arr, 2, nx), 1, ny)  # (coarse z, fine y, fine x)

    def rows(self, key, z0, z1):
        # fine rows z0..z1-1 need coarse rows floor(z0 / 2) .. floor((z1 - 1) / 2) + 3
        c0 = z0 // 2
        sub = self.xy[key][c0:c0 + (z1 - z0) // 2 + 6]
        full = _up2(sub, 0, z1 - z0 + (z0 % 2))
        return full[z0 % 2:]


def _protect_medial(sdf, w, g2, rho, n, idx, hg, sigma_eff, rounds=3):
    """Keep the label's medial surface inside the thinned bone (no hole may open).

    Thinning keeps a node where (1 - w) sdf + w (d_m - rho) < 0. On a clean plate the medial
    surface has d_m = 0 and stays inside; where plates meet (a T-junction, the spine on the
    scapular blade) the medial distance from the structure tensor's normal is unreliable and a
    medial node may be removed, which opens a hole. Medial nodes = nodes at least one geometry
    node deep whose depth (-sdf) is not exceeded one node away along +-n (the plate's normal);
    where thinning (evaluated on the geometry grid) removes one, w is set to 0 in a 2-node
    neighbourhood (smoothly), ``rounds`` times. Returns (w, number of nodes protected)."""
    from scipy import ndimage
    from scipy.special import erfinv

    depth = -sdf
    pts = np.column_stack(idx).astype(np.float32)  # (z, y, x) node coordinates
    step = n[:, ::-1]  # n is x-y-z; node coordinates are z-y-x (isotropic grid: one node = hg)
    dp = ndimage.map_coordinates(depth, (pts + step).T, order=1, mode="nearest")
    dm = ndimage.map_coordinates(depth, (pts - step).T, order=1, mode="nearest")
    d0 = depth[idx]
    medial = (d0 >= dp) & (d0 >= dm) & (d0 > hg)
    # The medial surface passes up to half a node from a medial node: evaluate the thinning at
    # the depth maximum along n (parabola through the three depths), not at the node.
    curv = dp + dm - 2.0 * d0
    delta = np.where(curv < -1e-6, 0.5 * (dm - dp) / np.where(curv < -1e-6, curv, -1.0), 0.0)
    delta = np.clip(delta, -0.5, 0.5)[medial]
    at = (pts[medial] + delta[:, None] * step[medial]).T
    sub = tuple(a[medial] for a in idx)
    sdf_m = ndimage.map_coordinates(sdf, at, order=1, mode="nearest")
    g2_m = ndimage.map_coordinates(g2, at, order=1, mode="nearest")
    rho_m = ndimage.map_coordinates(rho, at, order=1, mode="nearest")
    dmed = sigma_eff * math.sqrt(2.0) * erfinv(np.sqrt(np.clip(g2_m, 0.0, 0.999)))
    total = 0
    for _ in range(rounds):
        wi = ndimage.map_coordinates(w, at, order=1, mode="nearest")
        thin = (1.0 - wi) * sdf_m + wi * (dmed - rho_m)
        bad = (thin >= 0.0) & (wi > 0)
        if not bad.any():
            break
        total += int(bad.sum())
        mask = np.zeros(sdf.shape, np.float32)
        mask[tuple(a[bad] for a in sub)] = 1.0
        # w -> 0 within one node of a removed medial node, back to its value over ~2 more
        mask = np.clip(2.0 * ndimage.gaussian_filter(ndimage.maximum_filter(mask, size=3), 1.0), 0.0, 1.0)
        w = (w * (1.0 - mask)).astype(np.float32)
    return w, total


def _make_bone(model, index, name, src_mask, idx0, start, shape):
    """Steps 1-4 of the module doc for one bone on the crop (start, shape) of the model grid.

    The smooth fields (sdf0, the plate weight w, |grad D_s|^2, rho) are computed on a geometry
    grid of step hg = 2 h (the label is 3 mm: nothing finer exists in it) and brought to the
    model grid by cubic convolution; F is composed from them node by node. |grad D_s|^2 rather
    than d_m is interpolated because it is smooth through the medial surface (d_m has a kink
    there that interpolation would fill in, closing thin plates' holes or opening new ones).
    """
    from scipy import ndimage
    from scipy.special import erfinv

    cfg, h = model.cfg, model.h
    hg = 2.0 * h
    spec = BONES[name]
    kind = KINDS[spec["kind"]]
    t0 = time.perf_counter()
    fine = [model.g0[a] + h * (start[a] + np.arange(shape[2 - a])) for a in range(3)]  # x, y, z
    # geometry grid: covers the crop, one node beyond each end for the interpolation
    coarse = [np.arange(fine[a][0] - hg, fine[a][-1] + 2 * hg, hg) for a in range(3)]
    # 1. analytic Gaussian blur of the label's voxel boxes, on the geometry grid
    sp = model.src_spacing
    ks, lo_i, hi_i = [], [], []
    for a in range(3):
        c_q = sp[a] * (idx0[a] + np.arange(src_mask.shape[2 - a]))
        reach = 4.0 * cfg["label_sigma"] + sp[a]
        ii = np.flatnonzero((c_q > coarse[a][0] - reach) & (c_q < coarse[a][-1] + reach))
        lo_i.append(ii[0])
        hi_i.append(ii[-1] + 1)
        ks.append(_box_gauss_matrix(coarse[a], c_q[ii], sp[a], cfg["label_sigma"]))
    sub = src_mask[lo_i[2]:hi_i[2], lo_i[1]:hi_i[1], lo_i[0]:hi_i[0]].astype(np.float32)
    inside = _tensor(sub, ks[2], ks[1], ks[0]) > 0.5
    # 2. SDF, smoothed by one geometry node (removes its +-hg/2 steps)
    sdf = ndimage.gaussian_filter(_edt_sdf(inside, hg), 1.0, mode="nearest", truncate=3.0)
    del inside
    # 3. seeded low-frequency shape change
    lo_q = np.array([c[0] for c in coarse])
    hi_q = np.array([c[-1] for c in coarse])
    if cfg["perturb_mm"]:
        sdf += np.float32(cfg["perturb_mm"]) * _Lattice(model.rng(1, index), lo_q, hi_q, 40.0).grid(*coarse)
    up = _Upsampler(shape)
    up.add("sdf0", sdf)
    stats = {"seconds_shape": time.perf_counter() - t0}
    plates = bool(cfg["plates"] and kind["plate"] is not None)
    if plates:
        t1 = time.perf_counter()
        r_a, r_b = kind["r_a"], kind["r_b"]
        size = 2 * int(math.ceil((r_b + 1.0) / hg)) + 1
        R = ndimage.maximum_filter(np.maximum(-sdf, 0.0), size=size, mode="constant", cval=0.0)
        w = (1.0 - _smoothstep(r_a, r_b, R)).astype(np.float32)
        w[sdf > hg] = 0.0  # outside the bone w plays no role
        plates = bool((w > 0).any())
    if plates:
        sm = float(cfg["medial_sigma"]) / hg
        grad = []
        for axis in range(3):  # x, y, z components of grad D_s (array axes reversed)
            order = [0, 0, 0]
            order[2 - axis] = 1
            grad.append(ndimage.gaussian_filter(sdf, sm, order=order, mode="nearest", truncate=4.0) / hg)
        # The plate's normal n: principal direction of the structure tensor of grad D_s
        # (smoothed over ``2 r_b``-ish, both faces of a plate): gradients there are +-n on a
        # flat plate and the two face normals on a wedge. Only the component of grad D_s
        # along n measures the distance to the medial surface: on a wedge grad D_s also slopes
        # along the medial surface (by sin(half angle)), which would pierce thin wedges.
        # Sheetness 1 - m2 / m1 (m1 >= m2 its two largest eigenvalues) is ~1 on plates, ~0 on
        # rods (gradients all around the axis): rods (pubic rami, processes seen end-on) are
        # not thinned, they would become wires.
        zone = ndimage.binary_dilation(w > 0, iterations=2) & (sdf < hg)
        idx = np.nonzero(zone)
        st = float(kind.get("structure_mm", 2.0)) / hg
        T = np.empty((len(idx[0]), 3, 3), np.float32)
        for i in range(3):
            for j in range(i, 3):
                T[:, i, j] = T[:, j, i] = ndimage.gaussian_filter(grad[i] * grad[j], st, mode="nearest",
                                                                  truncate=3.0)[idx]
        mu, vec = np.linalg.eigh(T)  # ascending
        del T
        n = vec[:, :, 2]
        gn = sum(grad[a][idx] * n[:, a] for a in range(3))
        g2 = sum(grad[a] ** 2 for a in range(3))  # off the zone w = 0: any value will do
        g2[idx] = gn * gn
        sheet = np.zeros_like(sdf)
        sheet[idx] = np.clip(1.0 - mu[:, 1] / np.maximum(mu[:, 2], 1e-6), 0.0, 1.0)
        n_w0 = int((w > 0.5).sum())
        w *= _smoothstep(0.35, 0.65, sheet).astype(np.float32)
        stats["plate_nodes_by_thickness_sheet"] = [n_w0, int((w > 0.5).sum())]
        del grad, mu, gn, sheet
        t_min, t_max = (cfg["plate_scale"] * v for v in kind["plate"])
        s = np.clip(0.35 + 0.3 * _Lattice(model.rng(2, index), lo_q, hi_q, 25.0).grid(*coarse)
                    + 0.25 * (R - r_a) / (r_b - r_a), 0.0, 1.0)
        rho = (0.5 * (t_min + (t_max - t_min) * s)).astype(np.float32)
        w, n_prot = _protect_medial(sdf, w, g2, rho, n, idx, hg, math.hypot(float(cfg["medial_sigma"]), hg))
        stats["protected_medial_nodes"] = n_prot
        stats["plate_nodes_by_thickness_sheet"].append(int((w > 0.5).sum()))
        del n, vec, zone, idx
        stats["label_half_thickness_in_plates_mm"] = (
            [float(v) for v in np.percentile(R[w > 0.5], [5, 50, 95])] if (w > 0.5).any() else None)
        up.add("w", w)
        up.add("g2", g2)
        up.add("rho", rho)
        del R, s, g2, rho
        stats["seconds_plates"] = time.perf_counter() - t1
    del sdf
    # compose F on the model grid
    t1 = time.perf_counter()
    nz = shape[0]
    F = np.empty(shape, np.float32)
    sdf0 = np.empty(shape, np.float32)
    w16 = np.zeros(shape, np.float16) if plates else None
    rho16 = np.zeros(shape, np.float16) if plates else None
    # sdf was already smoothed by one geometry node (hg) before D_s = G_sm * sdf: the plate's
    # profile is blurred by sqrt(sm^2 + hg^2) in all, which the inversion must use.
    sq2 = np.float32(math.hypot(float(cfg["medial_sigma"]), hg) * math.sqrt(2.0))
    for z0 in range(0, nz, 32):
        z1 = min(nz, z0 + 32)
        s0 = up.rows("sdf0", z0, z1)
        sdf0[z0:z1] = s0
        if plates:
            w = np.clip(up.rows("w", z0, z1), 0.0, 1.0)
            g = np.sqrt(np.clip(up.rows("g2", z0, z1), 0.0, 0.999))
            rho = up.rows("rho", z0, z1)
            d_m = sq2 * erfinv(g).astype(np.float32)
            F[z0:z1] = np.maximum(s0, (1.0 - w) * s0 + w * (d_m - rho))
            w16[z0:z1] = w
            rho16[z0:z1] = rho
        else:
            F[z0:z1] = s0
    stats["seconds_compose"] = time.perf_counter() - t1
    return _Bone(name=name, label=int(spec["values"][0]), kind=spec["kind"], start=np.array(start, int),
                 F=F, sdf0=sdf0, w=w16, rho=rho16, stats=stats)


def _pair_gap(cfg, a, b):
    gaps = cfg.get("joint_gaps") or {}
    for key in ((a, b), (b, a)):
        if key in gaps:
            return float(gaps[key])
    return float(cfg["joint_gap_mm"])


def _overlap(a: _Bone, b: _Bone):
    lo = np.maximum(a.start, b.start)
    hi = np.minimum(a.stop, b.stop)
    if np.any(hi <= lo):
        return None
    sa = tuple(slice(lo[k] - a.start[k], hi[k] - a.start[k]) for k in (2, 1, 0))
    sb = tuple(slice(lo[k] - b.start[k], hi[k] - b.start[k]) for k in (2, 1, 0))
    return sa, sb


def _carve_joints(model):
    """Step 5: a joint space of at least g between every pair of bones that come closer."""
    cfg = model.cfg
    k = float(cfg["joint_margin_mm"])
    out = []
    bones = model.bones
    for i in range(len(bones)):
        for j in range(i + 1, len(bones)):
            a, b = bones[i], bones[j]
            ov = _overlap(a, b)
            if ov is None:
                continue
            sa, sb = ov
            g = _pair_gap(cfg, a.name, b.name)
            sda, sdb = a.sdf0[sa], b.sdf0[sb]
            near = float(np.min(sda + sdb)) if sda.size else np.inf
            # Sum of the two distances < g + 2 k somewhere: the bones come within reach.
            if not near < 1.1 * g + 2.0 * k:
                out.append({"a": a.name, "b": b.name, "gap_mm": g, "carved": False,
                            "label_min_sum_mm": near})
                continue
            psi = 0.5 * (sda - sdb)
            half = np.float32(0.55 * g)  # g' / 2 with g' = 1.1 g
            fa = _smax(a.F[sa], psi + half, k).astype(np.float32)
            fb = _smax(b.F[sb], -psi + half, k).astype(np.float32)
            n_a = int(((a.F[sa] < 0) & (fa >= 0)).sum())
            n_b = int(((b.F[sb] < 0) & (fb >= 0)).sum())
            a.F[sa] = fa
            b.F[sb] = fb
            out.append({"a": a.name, "b": b.name, "gap_mm": g, "carved": True,
                        "label_min_sum_mm": near,
                        "carved_ml": [n_a * model.h ** 3 / 1000.0, n_b * model.h ** 3 / 1000.0]})
    return out


def _cleanup(b: _Bone, h):
    """Step 6: keep the largest component of {F < 0}, fill enclosed cavities."""
    from scipy import ndimage

    inside = b.F < 0
    lab, n = ndimage.label(inside)
    removed = 0
    if n > 1:
        sizes = np.bincount(lab.ravel())[1:]
        keep = int(np.argmax(sizes)) + 1
        drop = inside & (lab != keep)
        removed = int(drop.sum())
        b.F[drop] = np.float32(0.5 * h)
        inside &= ~drop
    del lab
    out_lab, n_out = ndimage.label(~inside)
    filled = 0
    if n_out > 1:
        border = np.unique(np.concatenate([out_lab[[0, -1]].ravel(), out_lab[:, [0, -1]].ravel(),
                                           out_lab[:, :, [0, -1]].ravel()]))
        cav = (out_lab > 0) & ~np.isin(out_lab, border)
        filled = int(cav.sum())
        b.F[cav] = np.float32(-0.5 * h)
    b.stats.update(removed_voxels=removed, filled_voxels=filled)


def _zero_set_mesh(F, h, origin_q):
    """Flying edges of F's node values (inside negative, the nodes at the crop border forced
    outside) -> vertices (n, 3) q mm, faces (m, 3) outward."""
    import vtk
    from vtk.util import numpy_support as ns

    from BoneWatertightLib.mesh import enclosed_volume

    vol = np.array(F, np.float32, copy=True)
    # Nodes exactly on the zero set would give coincident vertices (zero-area triangles).
    tiny = np.float32(1e-4 * h)
    vol[np.abs(vol) < tiny] = tiny
    vol[[0, -1]] = h
    vol[:, [0, -1]] = h
    vol[:, :, [0, -1]] = h
    img = vtk.vtkImageData()
    img.SetDimensions(*[int(v) for v in vol.shape[::-1]])
    img.SetSpacing(h, h, h)
    img.SetOrigin(*[float(v) for v in origin_q])
    img.GetPointData().SetScalars(ns.numpy_to_vtk(vol.ravel(), deep=True))
    fe = vtk.vtkFlyingEdges3D()
    fe.SetInputData(img)
    fe.SetValue(0, 0.0)
    fe.ComputeNormalsOff()
    fe.ComputeGradientsOff()
    fe.ComputeScalarsOff()
    fe.Update()
    out = fe.GetOutput()
    if not out.GetNumberOfPolys():
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    v = ns.vtk_to_numpy(out.GetPoints().GetData()).astype(np.float64)
    f = ns.vtk_to_numpy(out.GetPolys().GetConnectivityArray()).astype(np.int64).reshape(-1, 3)
    if enclosed_volume(v, f) < 0:
        f = f[:, ::-1].copy()
    return v, f


def _genus(v, f):
    from BoneWatertightLib.mesh.checks import check_surface

    if not len(f):
        return None, 0
    rep = check_surface(v, f, check_self_intersections=False, expect_components=None)
    return rep.genus, int(rep.n_components)


# ---------------------------------------------------------------------------- building a case

def _config(case, overrides):
    if case not in CASES:
        raise ValueError(f"Unknown anatomical case {case!r}; choose one of {', '.join(CASES)}")
    cfg = dict(_BASE)
    cfg.update(CASES[case])
    unknown = set(overrides) - set(cfg) - {"_keep_sdf0"}
    if unknown:
        raise ValueError(f"Unknown anatomical phantom parameter(s): {', '.join(sorted(unknown))}")
    cfg.update(overrides)
    cfg["bones"] = tuple(cfg["bones"])
    h = float(cfg["model_grid"])
    if not 0.2 <= h <= 0.6:
        raise ValueError(f"model_grid must be 0.2-0.6 mm, got {h}")
    for name in cfg["bones"]:
        plate = KINDS[BONES[name]["kind"]]["plate"] if name in BONES else None
        # Flying edges keeps a plate of thickness >= h connected (inside = negative); 1.2 h
        # leaves room for the interpolation of F across the plate.
        if cfg["plates"] and plate is not None and cfg["plate_scale"] * plate[0] < 1.2 * h:
            raise ValueError(f"{name}: thinnest plate {cfg['plate_scale'] * plate[0]:.2f} mm is below "
                             f"1.2 x model_grid ({1.2 * h:.2f} mm); use a finer model_grid")
    for key in ("pixel", "slice_spacing", "psf_sigma"):
        if not float(cfg[key]) > 0:
            raise ValueError(f"{key} must be > 0")
    return cfg


def _build_geometry(cfg, seed):
    """The model with every bone's F (steps 1-6), its CT frame, and the truths (Surface, LPS)."""
    t_start = time.perf_counter()
    model = _Model(cfg, seed)
    h = model.h
    sp = model.src_spacing
    pad = _crop_pad_mm(cfg)
    masks, boxes = {}, {}
    for name in cfg["bones"]:
        m, idx0 = _source_mask(model, name)
        nz = np.argwhere(m)  # (k, j, i)
        lo_idx = nz.min(0)[::-1] + idx0
        hi_idx = nz.max(0)[::-1] + idx0
        masks[name] = (m, idx0)
        boxes[name] = (sp * (lo_idx - 0.5), sp * (hi_idx + 0.5))  # voxel extents, q mm
    lo_all = np.min([b[0] for b in boxes.values()], axis=0)
    hi_all = np.max([b[1] for b in boxes.values()], axis=0)
    fov_lo = lo_all - cfg["margin_mm"]
    fov_hi = hi_all + cfg["margin_mm"]
    model.g0 = np.minimum(fov_lo, lo_all - pad) - 2 * h
    model.fov = (fov_lo, fov_hi)
    t_bones = {}
    for index, name in enumerate(cfg["bones"]):
        t0 = time.perf_counter()
        lo, hi = boxes[name]
        start = np.floor((lo - pad - model.g0) / h).astype(int)
        stop = np.ceil((hi + pad - model.g0) / h).astype(int) + 1
        shape = tuple(int(v) for v in (stop - start)[::-1])
        b = _make_bone(model, index, name, masks[name][0], masks[name][1], start, shape)
        model.bones.append(b)
        t_bones[name] = time.perf_counter() - t0
    del masks
    # genus of the smoothed label (before thinning and joints): thinning must not open holes
    genus0 = {}
    for b in model.bones:
        v, f = _zero_set_mesh(b.sdf0, h, model.node_q(b.start))
        genus0[b.name] = _genus(v, f)
    t0 = time.perf_counter()
    joints = _carve_joints(model)
    t_joints = time.perf_counter() - t0
    for b in model.bones:
        if not cfg.get("_keep_sdf0"):
            b.sdf0 = None  # only the carving needed it
        _cleanup(b, h)
    # CT frame
    spacing = np.array([cfg["pixel"], cfg["pixel"], cfg["slice_spacing"]], float)
    size = np.floor((fov_hi - fov_lo) / spacing).astype(int) + 1
    model.ct_spacing = spacing
    model.ct_size = size
    model.q_ct0 = fov_lo
    model.direction = model.src_dir @ _rotation(cfg["direction_angles_deg"])
    model.x0 = model.src_origin + model.src_dir @ fov_lo
    truths, meta = {}, {}
    t0 = time.perf_counter()
    for b in model.bones:
        v, f = _zero_set_mesh(b.F, h, model.node_q(b.start))
        vp = model.to_physical(v)
        if np.linalg.det(model.direction) < 0:  # a left-handed frame turns the faces inside out
            f = f[:, ::-1].copy()
        truths[b.label] = Surface(vp, f, "LPS")
        g, nc = _genus(v, f)
        meta[b.name] = {"label": b.label, "genus": g, "n_components": nc,
                        "genus_smoothed_label": genus0[b.name][0],
                        "n_faces": int(len(f)), "crop_nodes": [int(s) for s in b.F.shape[::-1]],
                        **b.stats}
    t_truth = time.perf_counter() - t0
    model.timing = {"bones": t_bones, "joints": t_joints, "truth_meshes": t_truth,
                    "geometry_total": time.perf_counter() - t_start}
    return model, truths, meta, joints


# ---------------------------------------------------------------------------- CT formation

SOFT_TISSUE_HU = 45.0


def _background(model):
    """The source CT as a soft-tissue background on its own grid (z, y, x) float32: every
    labelled bone (dilated by one voxel) and everything above 120 HU (unlabelled bone,
    calcifications, contrast) set to 45 HU, clipped to [-1000, 100], smoothed by one voxel."""
    from scipy import ndimage

    ct = sitk.GetArrayFromImage(model.src_ct).astype(np.float32)
    if ct.shape != model.lab.shape:
        raise ValueError("the source CT and its labels must share one grid")
    bone = ndimage.binary_dilation(model.lab > 0, iterations=1) | (ct > 120.0)
    ct[bone] = SOFT_TISSUE_HU
    np.clip(ct, -1000.0, 100.0, out=ct)
    return ndimage.gaussian_filter(ct, 1.0, mode="nearest")


def _texture_tile(rng, hf, n=64, sigma_mm=0.8):
    """Periodic (n, n, n) trabecular texture of unit std at the fine step hf (wrap-smoothed
    white noise): indexed by the fine node index modulo n."""
    from scipy import ndimage

    t = ndimage.gaussian_filter(rng.normal(size=(n, n, n)).astype(np.float32), sigma_mm / hf, mode="wrap")
    return (t / max(float(t.std()), 1e-6)).astype(np.float32)


def _fill_pairs(model):
    """(a, b, L, HU mean, HU amplitude) of every pair of bones: the space where F_a + F_b < L is
    joint filler (cartilage; a disc between vertebrae)."""
    cfg = model.cfg
    out = []
    for i in range(len(model.bones)):
        for j in range(i + 1, len(model.bones)):
            a, b = model.bones[i], model.bones[j]
            if _overlap(a, b) is None:
                continue
            if a.kind == "vertebra" and b.kind == "vertebra":
                out.append((a, b, float(cfg["disc_mm"]), float(cfg["disc_hu"]), 12.0))
            else:
                out.append((a, b, _pair_gap(cfg, a.name, b.name) + 1.0, float(cfg["cartilage_hu"]), 18.0))
    return out


def _form_ct(model):
    """Fine HU image -> pixel aperture * PSF in-plane, slice profile along z, sampled at the CT
    voxel centres (one separable linear operator), + noise -> int16 (z, y, x)."""
    cfg, h = model.cfg, model.h
    t0 = time.perf_counter()
    px = float(cfg["pixel"])
    thick = float(cfg["slice_thickness"] or cfg["slice_spacing"])
    psf = float(cfg["psf_sigma"])
    f = 2 if min(px, thick) >= 3.0 * h else 1
    hf = f * h
    sz_sigma = 0.15 * thick
    n_ct = model.ct_size
    ct_axes = [model.q_ct0[a] + model.ct_spacing[a] * np.arange(n_ct[a]) for a in range(3)]
    reach = np.array([0.5 * px + 3.5 * psf, 0.5 * px + 3.5 * psf, 0.5 * thick + 3.5 * sz_sigma]) + hf
    # fine nodes: global model nodes whose index is a multiple of f
    m_lo = np.floor((model.q_ct0 - reach - model.g0) / hf).astype(int)
    m_hi = np.ceil((model.q_ct0 + model.ct_spacing * (n_ct - 1) + reach - model.g0) / hf).astype(int) + 1
    fine_axes = [model.g0[a] + hf * np.arange(m_lo[a], m_hi[a]) for a in range(3)]
    nxf, nyf, nzf = (len(a) for a in fine_axes)
    fine_axes_q0 = np.array([a[0] for a in fine_axes])
    kx = _box_gauss_matrix(ct_axes[0], fine_axes[0], px, psf, step=True)
    ky = _box_gauss_matrix(ct_axes[1], fine_axes[1], px, psf, step=True)
    kz = _box_gauss_matrix(ct_axes[2], fine_axes[2], thick, sz_sigma, step=True)
    # background: the source CT, linearly interpolated onto the fine nodes
    bg = _background(model)
    sp = model.src_spacing
    lx = _linear_matrix(fine_axes[0], 0.0, sp[0], bg.shape[2])
    ly = _linear_matrix(fine_axes[1], 0.0, sp[1], bg.shape[1])
    lz = _linear_matrix(fine_axes[2], 0.0, sp[2], bg.shape[0])
    bg_xy = ly[None] @ (bg @ lx.T)  # (source z, fine y, fine x)
    del bg
    nzs = bg_xy.shape[0]
    tile = _texture_tile(model.rng(3, 99), hf)
    nt = tile.shape[0]
    # per bone: the fine sub-grid of its crop and its smooth HU fields
    parts = []
    for index, b in enumerate(model.bones):
        kind = KINDS[b.kind]
        g_first = -(-b.start // f) * f  # first global node index >= start that is a multiple of f
        loc0 = g_first - b.start  # offset in the crop (x-y-z)
        fidx0 = g_first // f - m_lo  # its fine-grid index
        n_sub = np.maximum(0, (np.array(b.F.shape[::-1]) - loc0 + f - 1) // f)
        lo_q = fine_axes_q0 + hf * fidx0
        hi_q = fine_axes_q0 + hf * (fidx0 + n_sub - 1)
        rng = model.rng(3, index)
        fields = {"tc": _Lattice(rng, lo_q, hi_q, 20.0), "chu": _Lattice(rng, lo_q, hi_q, 25.0),
                  "thu": _Lattice(rng, lo_q, hi_q, 18.0)}
        nf = np.array([nxf, nyf, nzf])
        clo = np.clip(fidx0, 0, nf)
        chi = np.clip(fidx0 + n_sub, 0, nf)
        parts.append(dict(bone=b, kind=kind, loc0=loc0, fidx0=fidx0, lo=clo, hi=chi, fields=fields))
    pairs = []
    for a, b, L, hu_mean, hu_amp in _fill_pairs(model):
        pa = parts[model.bones.index(a)]
        pb = parts[model.bones.index(b)]
        lo = np.maximum(pa["lo"], pb["lo"])
        hi = np.minimum(pa["hi"], pb["hi"])
        if np.any(hi <= lo):
            continue
        lat = _Lattice(model.rng(3, 50 + len(pairs)), _fine_q(fine_axes, lo), _fine_q(fine_axes, hi - 1), 15.0)
        pairs.append(dict(a=pa, b=pb, lo=lo, hi=hi, L=L, hu=hu_mean, amp=hu_amp, field=lat))
    out = np.zeros((n_ct[2], n_ct[1], n_ct[0]), np.float32)
    slab = max(8, int(3e6 // (nxf * nyf)))
    for z0 in range(0, nzf, slab):
        z1 = min(nzf, z0 + slab)
        rows = np.flatnonzero(kz[:, z0:z1].any(axis=1))
        if not len(rows):
            continue
        hu = (lz[z0:z1] @ bg_xy.reshape(nzs, -1)).reshape(z1 - z0, nyf, nxf)
        for pr in pairs:
            zl, zh = max(z0, pr["lo"][2]), min(z1, pr["hi"][2])
            if zh <= zl:
                continue
            fa = _bone_sub(pr["a"], f, (pr["lo"][0], pr["hi"][0]), (pr["lo"][1], pr["hi"][1]), (zl, zh))
            fb = _bone_sub(pr["b"], f, (pr["lo"][0], pr["hi"][0]), (pr["lo"][1], pr["hi"][1]), (zl, zh))
            occ = (np.clip(0.5 - (fa + fb - pr["L"]) / hf, 0.0, 1.0) * np.clip(0.5 + fa / hf, 0.0, 1.0)
                   * np.clip(0.5 + fb / hf, 0.0, 1.0))
            if not occ.any():
                continue
            xs = fine_axes[0][pr["lo"][0]:pr["hi"][0]]
            ys = fine_axes[1][pr["lo"][1]:pr["hi"][1]]
            zs = fine_axes[2][zl:zh]
            fill = pr["hu"] + pr["amp"] * np.clip(pr["field"].grid(xs, ys, zs), -1.5, 1.5)
            reg = hu[zl - z0:zh - z0, pr["lo"][1]:pr["hi"][1], pr["lo"][0]:pr["hi"][0]]
            reg += occ * (fill - reg)
        for part in parts:
            b, kind = part["bone"], part["kind"]
            lo, hi = part["lo"], part["hi"]
            zl, zh = max(z0, lo[2]), min(z1, hi[2])
            if zh <= zl or hi[0] <= lo[0] or hi[1] <= lo[1]:
                continue
            Fb = _bone_sub(part, f, (lo[0], hi[0]), (lo[1], hi[1]), (zl, zh))
            occ = np.clip(0.5 - Fb / hf, 0.0, 1.0)
            if not occ.any():
                continue
            # only the box of the bone's nodes in this slab (the fields are functions of
            # position: the same values, fewer nodes)
            nzr = [np.flatnonzero(occ.any(axis=ax)) for ax in ((1, 2), (0, 2), (0, 1))]
            bz, by, bx = ((r[0], r[-1] + 1) for r in nzr)
            Fb = Fb[bz[0]:bz[1], by[0]:by[1], bx[0]:bx[1]]
            occ = occ[bz[0]:bz[1], by[0]:by[1], bx[0]:bx[1]]
            zl, zh = zl + bz[0], zl + bz[1]
            lo = (lo[0] + bx[0], lo[1] + by[0])
            hi = (lo[0] + (bx[1] - bx[0]), lo[1] + (by[1] - by[0]))
            xs, ys = fine_axes[0][lo[0]:hi[0]], fine_axes[1][lo[1]:hi[1]]
            zs = fine_axes[2][zl:zh]
            fl = part["fields"]
            tc = np.clip(kind["cortex"] * (1.0 + 0.35 * fl["tc"].grid(xs, ys, zs)), 0.3, 3.0)
            chu = kind["cortex_hu"] + 220.0 * fl["chu"].grid(xs, ys, zs)
            if b.w is not None:
                # thin plates are less dense than the cortex of the bodies
                chu -= 350.0 * _bone_sub(part, f, (lo[0], hi[0]), (lo[1], hi[1]), (zl, zh), key="w")
            chu = np.clip(chu, 1000.0, 1800.0)
            tex = tile[np.ix_(np.arange(zl, zh) % nt, np.arange(lo[1], hi[1]) % nt,
                              np.arange(lo[0], hi[0]) % nt)]
            depth = -Fb
            thu = (kind["trab_hu"] + 50.0 * np.clip(fl["thu"].grid(xs, ys, zs), -1.5, 1.5) + 35.0 * tex
                   + 60.0 * np.exp(-np.maximum(depth - tc, 0.0) / 1.5))
            occ_c = np.clip(0.5 - (Fb + tc) / hf, 0.0, 1.0)
            reg = hu[zl - z0:zh - z0, lo[1]:hi[1], lo[0]:hi[0]]
            reg += occ * (chu - reg) + occ_c * (thu - chu)
        t = hu @ kx.T
        t = ky[None] @ t
        ns_, ny_, nx_ = t.shape
        out[rows] += (kz[rows, z0:z1] @ t.reshape(ns_, ny_ * nx_)).reshape(len(rows), ny_, nx_)
    t_form = time.perf_counter() - t0
    out += model.rng(4).normal(0.0, float(cfg["noise"]), size=out.shape).astype(np.float32)
    arr = np.clip(np.rint(out), -1024, 3071).astype(np.int16)
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing([float(v) for v in model.ct_spacing])
    img.SetOrigin([float(v) for v in model.x0])
    img.SetDirection([float(v) for v in model.direction.ravel()])
    return img, {"fine_step_mm": hf, "seconds": t_form, "fine_nodes": [nxf, nyf, nzf]}


def _fine_q(fine_axes, idx):
    """q (mm) of the fine node with fine indices idx (x-y-z), clamped to the grid."""
    return np.array([fine_axes[a][int(np.clip(idx[a], 0, len(fine_axes[a]) - 1))] for a in range(3)])


def _bone_sub(part, f, xr, yr, zr, key="F"):
    """A field of a part's bone (F, or w) at the fine nodes with fine indices xr, yr, zr
    (half-open ranges, inside the part's fine sub-grid): a strided view of the crop, as float32."""
    b, loc0, lo = part["bone"], part["loc0"], part["fidx0"]
    sl = []
    for a, r in zip((2, 1, 0), (zr, yr, xr)):
        i0 = loc0[a] + f * (r[0] - lo[a])
        i1 = loc0[a] + f * (r[1] - lo[a])
        sl.append(slice(i0, i1, f))
    return np.asarray(getattr(b, key)[tuple(sl)], np.float32)


# ---------------------------------------------------------------------------- labels

def labels_ai(phantom, grid_mm=None, steal_mm=None, subsamples: int = 3, seed: int | None = None,
              on_ct_grid: bool = True) -> sitk.Image:
    """All bones as an AI segmentation brings them: coarse, stair-stepped, optionally wrong at
    a joint.

    Every voxel of a coarse grid (aligned with the CT's axes, spacing ``grid_mm``, its first
    voxel centre 0 to half a voxel inside the CT's field of view at random per axis) takes the
    majority of the truth over subsamples**3 points spread evenly in it (bone k where its F < 0,
    F trilinear on the model grid; else background; ties to the lower value). Voxels whose
    centre is farther than twice the half-diagonal + 0.2 mm from every bone surface are decided
    by the centre alone.

    Parameters
    ----------
    phantom : AnatomicalPhantom
    grid_mm : float or (3,) floats (x, y, z), optional
        Coarse grid spacing (mm, 1.5-3 for AI masks); default ``info["label_grid"]``.
    steal_mm : (str, str, float), optional
        (bone a, bone b, d): voxels of a whose centre lies within d mm of b's surface (F_b < d)
        become b, as an AI mask that gives the top of the femoral head to the hip bone.
        Default ``info["steal_mm"]``.
    subsamples : int
        Points per axis and voxel (3 -> 27 votes).
    seed : int, optional
        Seeds the grid's phase; default the phantom's seed.
    on_ct_grid : bool
        True: resampled nearest-neighbour onto the CT grid (as a consumer puts the AI mask on
        the CT); False: the coarse grid itself.

    Returns
    -------
    sitk.Image
        uint8 label map (array (z, y, x)); values = the bones' label values (``names``), 0
        background; the CT's direction.
    """
    model = phantom.info["_model"]
    cfg = model.cfg
    grid = np.broadcast_to(np.asarray(cfg["label_grid"] if grid_mm is None else grid_mm, float), (3,)).copy()
    if np.any(grid <= 0) or subsamples < 1:
        raise ValueError("grid_mm must be > 0 and subsamples >= 1")
    steal = cfg["steal_mm"] if steal_mm is None else steal_mm
    rng = model.rng(5, 0) if seed is None else np.random.default_rng([int(seed), 5, 0])
    ct_sp = model.ct_spacing
    box_lo = model.q_ct0 - 0.5 * ct_sp
    box_hi = model.q_ct0 + (model.ct_size - 0.5) * ct_sp
    start = box_lo + (1.0 - rng.uniform(0.0, 1.0, 3)) * 0.5 * grid
    size = np.ceil((box_hi - start) / grid + 0.5).astype(int)
    axes = [start[a] + grid[a] * np.arange(size[a]) for a in range(3)]
    Z, Y, X = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    p = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    del X, Y, Z
    values = np.array([0] + [b.label for b in model.bones])
    d = np.stack([model.sample_F(b, p) for b in model.bones], axis=1)  # (n, bones)
    inside = d < 0
    lab = np.where(inside.any(axis=1), np.argmax(inside, axis=1) + 1, 0)
    r = 2.0 * 0.5 * float(np.linalg.norm(grid)) + 0.2
    near = np.flatnonzero((np.abs(d) < r).any(axis=1))
    if subsamples > 1 and len(near):
        t = (np.arange(subsamples) + 0.5) / subsamples - 0.5
        off = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3) * grid
        n_off = len(off)
        step = max(1, int(1.5e6 // n_off))
        for a0 in range(0, len(near), step):
            idx = near[a0:a0 + step]
            q = (p[idx][:, None, :] + off[None]).reshape(-1, 3)
            votes = np.zeros((len(idx), len(values)), np.int32)
            for k, b in enumerate(model.bones):
                votes[:, k + 1] = (model.sample_F(b, q) < 0).reshape(-1, n_off).sum(axis=1)
            votes[:, 0] = n_off - votes[:, 1:].sum(axis=1)
            lab[idx] = np.argmax(votes, axis=1)
    if steal:
        a_name, b_name, mm = steal
        ka = 1 + [b.name for b in model.bones].index(a_name)
        kb = 1 + [b.name for b in model.bones].index(b_name)
        lab[(lab == ka) & (d[:, kb - 1] < float(mm))] = kb
    arr = values[lab].astype(np.uint8).reshape(tuple(size[::-1]))
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing([float(v) for v in grid])
    img.SetDirection([float(v) for v in model.direction.ravel()])
    img.SetOrigin([float(v) for v in model.to_physical(start[None])[0]])
    if not on_ct_grid:
        return img
    from phantoms import resample_nearest
    return resample_nearest(img, phantom.ct)


# ---------------------------------------------------------------------------- measurements

def _area_samples(surface: Surface, n: int, rng):
    """n points uniformly over a mesh's area with their faces' outward unit normals."""
    tri = surface.vertices[surface.faces]
    cr = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cr, axis=1)
    t = rng.choice(len(tri), size=n, p=area / area.sum())
    r1 = np.sqrt(rng.random(n))
    r2 = rng.random(n)
    p = (tri[t, 0] * (1 - r1)[:, None] + tri[t, 1] * (r1 * (1 - r2))[:, None]
         + tri[t, 2] * (r1 * r2)[:, None])
    nrm = cr[t] / np.maximum(2.0 * area[t], 1e-300)[:, None]
    return p, nrm, float(area.sum())


def thickness_samples(surface: Surface, n: int = 20000, seed: int = 0, max_mm: float = 8.0):
    """Wall thickness of a closed surface at n area-uniform points, by ray casting (open3d):
    from each point along the inward normal to the first hit; counted as a wall (a plate) when
    the hit face looks the opposite way (normals' dot < -0.5) within ``max_mm``.

    Returns
    -------
    points (n, 3), inward normals (n, 3), thickness (n,) mm (inf where no opposite wall within
    max_mm), total area (mm^2).
    """
    import open3d as o3d

    rng = np.random.default_rng(seed)
    p, nrm, area = _area_samples(surface, n, rng)
    shift = surface.vertices.mean(axis=0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((surface.vertices - shift).astype(np.float32)),
                        o3d.core.Tensor(surface.faces.astype(np.uint32)))
    org = p - shift - 1e-3 * nrm
    rays = np.concatenate([org, -nrm], axis=1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy().astype(float) + 1e-3
    n2 = hit["primitive_normals"].numpy().astype(float)
    ok = np.isfinite(t) & (t < max_mm) & (np.einsum("ij,ij->i", n2, nrm) < -0.5)
    return p, -nrm, np.where(ok, t, np.inf), area


def _node_values(model, b: _Bone, arr, q):
    """Nearest-node values of a field on bone b's crop at points q (n, 3) (0 outside)."""
    idx = np.rint((q - model.g0) / model.h).astype(int) - b.start
    ok = np.all((idx >= 0) & (idx < np.array(arr.shape[::-1])), axis=1)
    out = np.zeros(len(q), np.float32)
    out[ok] = arr[idx[ok, 2], idx[ok, 1], idx[ok, 0]]
    return out


def _thickness_all(model, truths, n=20000):
    """thickness_samples of every bone's truth (seeded by the bone's index), by bone name."""
    return {b.name: thickness_samples(truths[b.label], n=n, seed=index) for index, b in enumerate(model.bones)}


def _plate_figures(model, samples):
    """info["plates"]: per bone, the thickness distribution of the truth in its plate zone
    (w >= 0.5 at the wall's middle) and over the whole bone, and the agreement with the
    construction's target 2 rho where the bone is fully thinned (w >= 0.95)."""
    out = {}
    for b in model.bones:
        p, inward, t, area = samples[b.name]
        wall = np.isfinite(t)
        res = {"area_mm2": area,
               "whole_bone_area_frac_thinner_than_1mm": float((t < 1.0).mean()),
               "whole_bone_area_frac_thinner_than_2mm": float((t < 2.0).mean()),
               "whole_bone_area_frac_thinner_than_3mm": float((t < 3.0).mean())}
        if b.w is not None:
            mid = model.to_local(p[wall] + 0.5 * t[wall, None] * inward[wall])
            w = _node_values(model, b, b.w, mid)
            rho = _node_values(model, b, b.rho, mid)
            zone = w >= 0.5
            tz = t[wall][zone]
            res["plate_zone_area_frac"] = float(zone.sum() / len(t))
            if len(tz):
                res["plate_thickness_mm_p5_p25_p50_p75_p95"] = [float(v) for v in np.percentile(tz, [5, 25, 50, 75, 95])]
                res["plate_thickness_min_mm"] = float(tz.min())
                res["plate_frac_thinner_than_1mm"] = float((tz < 1.0).mean())
            full = w >= 0.95  # fully thinned: the wall should be 2 rho thick
            if full.sum() >= 20:
                res["plate_full_target_abs_err_mm_median_p95"] = [
                    float(v) for v in np.percentile(np.abs(t[wall][full] - 2.0 * rho[full]), [50, 95])]
        out[b.name] = res
    return out


def _joint_figures(model, truths, joints):
    """The smallest distance between the truths of every pair that was carved (exact
    point-to-triangle, both ways), beside the requested gap."""
    from metrics import TriangleLocator

    by_name = {b.name: b for b in model.bones}
    out = []
    for j in joints:
        row = dict(j)
        if j["carved"]:
            a, b = by_name[j["a"]], by_name[j["b"]]
            sa, sb = truths[a.label], truths[b.label]
            best = np.inf
            for s, other, s_other in ((sa, b, sb), (sb, a, sa)):
                # Only the vertices near the other bone (its F, a distance near its surface,
                # below g + 3 mm) can be the closest: the exact query runs on those.
                near = model.sample_F(other, model.to_local(s.vertices)) < j["gap_mm"] + 3.0
                if near.any():
                    best = min(best, float(TriangleLocator(s_other).query(s.vertices[near])[0].min()))
            row["min_distance_mm"] = best
        out.append(row)
    return out


def sample_ct(ct: sitk.Image, points) -> np.ndarray:
    """CT values (HU) at physical points (n, 3) by trilinear interpolation."""
    from scipy import ndimage

    arr = sitk.GetArrayViewFromImage(ct)
    D = np.array(ct.GetDirection()).reshape(3, 3)
    idx = ((np.asarray(points, float) - np.array(ct.GetOrigin())) @ D) / np.array(ct.GetSpacing())
    return ndimage.map_coordinates(np.asarray(arr, np.float32), idx[:, ::-1].T, order=1, mode="nearest")


def _ct_figures(model, ct, samples):
    """What the CT shows of the bones: the blurred peak of plates by thickness class (HU at the
    wall's middle), and the cortex peak of thick parts (the largest HU within 3 mm under the
    surface where the wall is thicker than 8 mm)."""
    out = {}
    for b in model.bones:
        p, inward, t, _ = samples[b.name]
        res = {}
        wall = np.isfinite(t)
        for lo, hi in ((0.0, 1.0), (1.0, 2.0), (2.0, 3.0)):
            sel = wall & (t >= lo) & (t < hi)
            if sel.sum() >= 20:
                mid = p[sel] + 0.5 * t[sel, None] * inward[sel]
                v = sample_ct(ct, mid)
                res[f"plate_{lo:g}-{hi:g}mm_mid_HU_p10_p50_p90"] = [float(x) for x in np.percentile(v, [10, 50, 90])]
                res[f"plate_{lo:g}-{hi:g}mm_frac_below_300HU"] = float((v < 300).mean())
                res[f"plate_{lo:g}-{hi:g}mm_n"] = int(sel.sum())
        thick = ~wall
        if thick.sum() >= 20:
            depths = np.linspace(0.0, 3.0, 7)
            v = np.max([sample_ct(ct, p[thick] + d * inward[thick]) for d in depths], axis=0)
            res["thick_cortex_peak_HU_p10_p50_p90"] = [float(x) for x in np.percentile(v, [10, 50, 90])]
        out[b.name] = res
    return out


# ---------------------------------------------------------------------------- entry points

@dataclass
class AnatomicalPhantom:
    """ct: int16 HU (array (z, y, x)), physical LPS geometry (the real CT's place, possibly
    oblique); labels: uint8 AI-style label map of every bone of the case on the CT grid;
    truths: {label value: Surface (LPS mm, closed, outward)}; names: {label value: bone name};
    info: the case parameters and derived figures (``info["_model"]`` is the geometry, not
    JSON-serialisable: drop keys starting with "_")."""

    ct: sitk.Image | None
    labels: sitk.Image | None
    truths: dict
    names: dict
    info: dict = field(default_factory=dict)

    def sdf(self, label: int, physical_points) -> np.ndarray:
        """F of a bone (mm, negative inside; a distance near the surface) at physical LPS points
        (n, 3) -> (n,): the trilinear interpolant of its model-grid values, whose zero set the
        truth is; large positive beyond the bone's crop."""
        model = self.info["_model"]
        b = next(b for b in model.bones if b.label == int(label))
        return model.sample_F(b, model.to_local(physical_points))

    def labels_ai(self, grid_mm=None, steal_mm=None, subsamples: int = 3, seed: int | None = None,
                  on_ct_grid: bool = True) -> sitk.Image:
        """See :func:`labels_ai`."""
        return labels_ai(self, grid_mm=grid_mm, steal_mm=steal_mm, subsamples=subsamples, seed=seed,
                         on_ct_grid=on_ct_grid)


def _info(case, seed, cfg, model, meta, joints, truths, samples):
    from BoneWatertightLib.mesh import enclosed_volume

    info = {k: (list(v) if isinstance(v, tuple) else v) for k, v in cfg.items() if not k.startswith("_")}
    if info.get("joint_gaps"):
        info["joint_gaps"] = {f"{a}/{b}": g for (a, b), g in info["joint_gaps"].items()}
    for b in model.bones:
        meta[b.name]["volume_ml"] = float(enclosed_volume(truths[b.label].vertices, truths[b.label].faces) / 1000.0)
        meta[b.name]["label_ml"] = float(np.isin(model.lab, BONES[b.name]["values"]).sum()
                                         * np.prod(model.src_spacing) / 1000.0)
    info.update(
        case=case, seed=int(seed), slice_thickness=cfg["slice_thickness"] or cfg["slice_spacing"],
        ct_size=[int(v) for v in model.ct_size], ct_spacing=[float(v) for v in model.ct_spacing],
        bones_info=meta, joints=_joint_figures(model, truths, joints),
        plates=_plate_figures(model, samples),
        truth_note=("zero set of F (flying edges of its samples on the model grid, vertices on the "
                    "zero set of F's trilinear interpolant)"),
        source_folder=SOURCES[cfg["source"]][0] or os.path.relpath(SAMPLE_DIR, ROOT),
        timing=dict(model.timing), _model=model)
    return info


def make_truth(case: str = "pelvis_3mm", seed: int = 0, **overrides) -> AnatomicalPhantom:
    """The truths of a case without the CT and the labels (``ct`` and ``labels`` are None):
    the same meshes as :func:`make_anatomical` gives, for the geometry's figures (info: bones,
    joints, plates)."""
    t0 = time.perf_counter()
    cfg = _config(case, overrides)
    model, truths, meta, joints = _build_geometry(cfg, seed)
    names = {b.label: b.name for b in model.bones}
    info = _info(case, seed, cfg, model, meta, joints, truths, _thickness_all(model, truths))
    info["timing"]["total"] = time.perf_counter() - t0
    info["peak_rss_mb"] = _peak_mb()
    return AnatomicalPhantom(ct=None, labels=None, truths=truths, names=names, info=info)


def make_anatomical(case: str = "pelvis_3mm", seed: int = 0, **overrides) -> AnatomicalPhantom:
    """An anatomical CT phantom with exact truths (see the module doc).

    Parameters
    ----------
    case : str
        A key of :data:`CASES`.
    seed : int
        Seeds the shape perturbation, the plate thickness field, the HU fields, the noise and
        the label grid's phase (held-out seeds change all of them).
    **overrides
        Any key of ``_BASE`` (e.g. ``pixel=1.0``, ``joint_gap_mm=2.0``, ``noise=30``,
        ``direction_angles_deg=(10, 0, 5)``, ``steal_mm=("femur_right", "hip_right", 3.0)``).

    Returns
    -------
    AnatomicalPhantom
        ct (int16, array (z, y, x)), labels (uint8, on the CT grid), truths, names, info
        (``info["bones_info"]``: per bone genus (and the smoothed label's), volume, faces;
        ``info["joints"]``: per pair the requested gap and the truths' smallest distance;
        ``info["plates"]``: thickness distributions; ``info["ct_figures"]``: plate and cortex
        peaks on the CT; ``info["timing"]``, ``info["peak_rss_mb"]``).

    Raises
    ------
    DataMissing
        The case's source data (../shared/data) is absent.
    ValueError
        Unknown case or parameter, or a plate thinner than the model grid can hold.
    """
    t0 = time.perf_counter()
    cfg = _config(case, overrides)
    model, truths, meta, joints = _build_geometry(cfg, seed)
    names = {b.label: b.name for b in model.bones}
    ct, form = _form_ct(model)
    t1 = time.perf_counter()
    samples = _thickness_all(model, truths)
    info = _info(case, seed, cfg, model, meta, joints, truths, samples)
    info["timing"]["figures"] = time.perf_counter() - t1
    ph = AnatomicalPhantom(ct=ct, labels=None, truths=truths, names=names, info=info)
    t1 = time.perf_counter()
    ph.labels = labels_ai(ph)
    info["timing"]["labels"] = time.perf_counter() - t1
    info["timing"]["ct"] = form["seconds"]
    info["ct_fine_step_mm"] = form["fine_step_mm"]
    info["ct_figures"] = _ct_figures(model, ct, samples)
    info["timing"]["total"] = time.perf_counter() - t0
    info["peak_rss_mb"] = _peak_mb()
    return ph


if __name__ == "__main__":
    import json

    for name in (sys.argv[1:] or ["sample_L3L4"]):
        ph = make_anatomical(name)
        info = {k: v for k, v in ph.info.items() if not k.startswith("_")}
        print(name, ph.ct.GetSize(), ph.ct.GetSpacing(), json.dumps(info, indent=1, default=str))
