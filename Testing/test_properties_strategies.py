"""Strategies and the checking harness of the property-based suite (issue 12).

Used by ``Testing/test_properties*.py``. A generated *scene* is a small CT (any pixel type,
anisotropic spacing 0.3-4 mm and a few extremes, oblique or left-handed direction matrices,
non-zero origins, sizes from 2 voxels to tens of thousands) holding 0-3 bone-like objects
(solid or hollow ellipsoids, boxes, thin sheets; cortical, weak, metal or extended-HU levels)
in air, soft tissue, a body or a flat or noise-only background, and a label map of those
objects (on the CT's grid or another one; empty, one voxel, touching the border, thin sheets,
holes, random voxels, several labels). Parameters are drawn from the schema: valid values in
every declared range and invalid ones (NaN, inf, out of range, wrong types, None where there
is no auto).

The harness runs one call and returns its outcome ("ok" or the library error's class name).
An invalid case must raise the typed error its inputs call for (:func:`expected_error`,
:func:`expected_error_many`: decided from the inputs alone, not from the library's answer).
Anything else fails the test: an exception that is not a
:class:`~BoneWatertightLib.errors.BoneWatertightError` (a ValueError only as InputError), a
returned surface that fails :func:`~BoneWatertightLib.mesh.checks.check_surface`, an input
image or parameter object that changed. A per-call watchdog (faulthandler) ends the process
with every thread's traceback when a call hangs.

Profiles (``BW_HYPOTHESIS_PROFILE``): ``ci`` (default: fixed example counts, derandomized,
bounded time), ``campaign`` (``BW_CAMPAIGN_FACTOR`` times as many examples, random, default
20), ``dev`` (a few examples). With ``BW_PROPERTY_LOG=FILE`` every case is logged (JSON lines,
a "start" before the call and an "end" after it), so a case that aborted the process or hung
is the "start" without an "end"; ``python Testing/test_properties_strategies.py FILE`` prints the figures.
"""

from __future__ import annotations

import dataclasses
import faulthandler
import json
import math
import os
import sys
import time
import traceback
from datetime import timedelta

import numpy as np
import SimpleITK as sitk
from hypothesis import HealthCheck, Phase, settings
from hypothesis import strategies as st

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from BoneWatertightLib.errors import BoneWatertightError, InputError  # noqa: E402
from BoneWatertightLib.mesh.checks import check_surface  # noqa: E402
from BoneWatertightLib.params import SCHEMA, Parameters  # noqa: E402

# ---------------------------------------------------------------------------- profiles

PROFILE = os.environ.get("BW_HYPOTHESIS_PROFILE", "ci")
CAMPAIGN_FACTOR = float(os.environ.get("BW_CAMPAIGN_FACTOR", "20"))
# A call that runs longer than this is a hang: the watchdog dumps every thread and exits.
HANG_SECONDS = float(os.environ.get("BW_HANG_SECONDS", "600"))
LOG_PATH = os.environ.get("BW_PROPERTY_LOG")
# In a campaign a failed case is logged and counted, and the run goes on (no shrinking), so
# its figures count every failure; BW_PROPERTY_COLLECT=0 makes it stop and shrink as in CI.
COLLECT = os.environ.get("BW_PROPERTY_COLLECT", "1" if PROFILE == "campaign" else "0") == "1"

_COMMON = dict(database=None, print_blob=True,
               suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                      HealthCheck.filter_too_much,
                                      HealthCheck.function_scoped_fixture])
settings.register_profile("ci", derandomize=True, deadline=timedelta(seconds=240), **_COMMON)
settings.register_profile("campaign", derandomize=False, deadline=None,
                          phases=[Phase.explicit, Phase.generate], **_COMMON)
settings.register_profile("dev", derandomize=False, deadline=timedelta(seconds=240),
                          **_COMMON)
settings.load_profile(PROFILE)


def examples(n_ci: int):
    """Settings with ``n_ci`` examples in CI, CAMPAIGN_FACTOR times more in a campaign."""
    n = {"ci": n_ci, "campaign": int(math.ceil(n_ci * CAMPAIGN_FACTOR)),
         "dev": max(2, n_ci // 4)}.get(PROFILE, n_ci)
    return settings(settings.get_profile(PROFILE), max_examples=n)


# Size budget of a generated case: CT voxels, and working-grid voxels at the run's spacing
# (examples are kept small and fast; huge grids have their own test, where they are refused).
MAX_CT_VOXELS = 60_000
MAX_WORK_VOXELS = 250_000

# ---------------------------------------------------------------------------- geometry


def rotation(angles_deg) -> np.ndarray:
    ax, ay, az = np.radians(angles_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


@st.composite
def directions(draw):
    kind = draw(st.sampled_from(["identity", "identity", "permuted", "oblique", "oblique",
                                 "left-handed", "sheared"]))
    if kind == "identity":
        return np.eye(3)
    if kind == "permuted":
        perm = draw(st.permutations([0, 1, 2]))
        signs = draw(st.lists(st.sampled_from([-1.0, 1.0]), min_size=3, max_size=3))
        return np.eye(3)[list(perm)] * np.array(signs)
    angles = draw(st.tuples(*[st.floats(-180, 180, allow_nan=False)] * 3))
    r = rotation(angles)
    if kind == "left-handed":
        r = r @ np.diag([1.0, 1.0, -1.0])
    if kind == "sheared":  # not orthonormal: refused (VolumeTypeError)
        r = r @ np.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    return r


@dataclasses.dataclass
class Obj:
    kind: str          # ellipsoid, box, sheet
    centre: np.ndarray  # CT-local mm (index * spacing, x-y-z)
    radii: np.ndarray   # mm
    hu: float
    shell: float        # cortex thickness (mm) of a hollow object; 0: solid
    normal: np.ndarray  # the sheet's normal

    def sdf(self, q: np.ndarray) -> np.ndarray:
        """Signed distance (approximate, mm, negative inside) at CT-local points q (..., 3)."""
        d = q - self.centre
        if self.kind == "ellipsoid":
            r = np.maximum(self.radii, 1e-3)
            k = np.linalg.norm(d / r, axis=-1)
            return (k - 1.0) * r.min()
        if self.kind == "box":
            return np.max(np.abs(d) - self.radii, axis=-1)
        # a thin sheet: a slab |d . n| < t/2, bounded by the box of its radii
        t = self.radii.min()
        slab = np.abs(d @ self.normal) - t / 2
        return np.maximum(slab, np.max(np.abs(d) - self.radii.max(), axis=-1))


@dataclasses.dataclass
class Scene:
    """Everything to build the CT and the label map (SimpleITK images are made fresh)."""

    size: tuple            # CT size (x, y, z)
    spacing: tuple         # CT spacing (x, y, z) mm
    origin: tuple
    direction: np.ndarray
    background: str
    background_hu: float
    noise: float
    pixel: str             # pixel type of the CT
    objects: list
    labels: list           # per object: label value, or 0 for none
    segment: str           # how the label map is made
    label_grid: str        # same, coarse, shifted, oblique, far
    label_pixel: str
    label_offset: float    # mm added to the objects' extent in the label map
    seed: int
    extra: dict = dataclasses.field(default_factory=dict)

    def describe(self) -> dict:
        d = dataclasses.asdict(self)
        d["direction"] = np.round(self.direction, 4).tolist()
        d["objects"] = [{"kind": o.kind, "centre": np.round(o.centre, 2).tolist(),
                         "radii": np.round(o.radii, 2).tolist(), "hu": round(o.hu, 1),
                         "shell": round(o.shell, 2), "normal": np.round(o.normal, 4).tolist()}
                        for o in self.objects]
        return d

    # --- the images

    def local_points(self, size, spacing, origin, direction) -> np.ndarray:
        """CT-local mm (x, y, z) of every voxel of a grid, array (z, y, x, 3)."""
        idx = np.stack(np.meshgrid(*[np.arange(n) for n in size[::-1]], indexing="ij"), -1)
        idx = idx[..., ::-1].astype(np.float64)  # x, y, z
        phys = np.asarray(origin) + (idx * np.asarray(spacing)) @ np.asarray(direction).T
        return (phys - np.asarray(self.origin)) @ self.direction  # direction is orthonormal-ish

    def ct(self) -> sitk.Image:
        rng = np.random.default_rng(self.seed)
        q = self.local_points(self.size, self.spacing, self.origin, self.direction)
        shape = q.shape[:-1]
        hu = np.full(shape, self.background_hu, np.float64)
        if self.background == "body":
            c = np.asarray(self.size) * np.asarray(self.spacing) / 2
            r = np.maximum(c * 0.8, 1.0)
            inside = (((q[..., 0] - c[0]) / r[0]) ** 2 + ((q[..., 1] - c[1]) / r[1]) ** 2) < 1
            hu = np.where(inside, 40.0, -1000.0)
        blur = 0.4 * min(self.spacing)
        for o in self.objects:
            s = o.sdf(q)
            w = 1.0 / (1.0 + np.exp(np.clip(s / max(blur, 1e-3), -50, 50)))
            level = np.full(shape, o.hu)
            if o.shell > 0:
                inner = 1.0 / (1.0 + np.exp(np.clip((s + o.shell) / max(blur, 1e-3), -50, 50)))
                level = o.hu * (1 - inner) + 60.0 * inner
            hu = hu * (1 - w) + level * w
        if self.noise > 0:
            hu = hu + rng.normal(0.0, self.noise, shape)
        arr = _to_pixel(hu, self.pixel)
        img = sitk.GetImageFromArray(arr)
        img.SetSpacing([float(v) for v in self.spacing])
        img.SetOrigin([float(v) for v in self.origin])
        img.SetDirection([float(v) for v in np.asarray(self.direction).ravel()])
        return img

    def label_geometry(self):
        sp = np.asarray(self.spacing, float)
        size = np.asarray(self.size, int)
        origin = np.asarray(self.origin, float)
        direction = np.asarray(self.direction, float)
        g = self.label_grid
        if g == "coarse":
            f = self.extra.get("factor", 2.0)
            size = np.maximum(np.ceil(size / f).astype(int), 1)
            sp = sp * f
        elif g == "shifted":
            origin = origin + direction @ (sp * np.asarray(self.extra.get("shift", (0.5, 0.5, 0.5))))
        elif g == "oblique":
            direction = rotation(self.extra.get("angles", (10.0, -20.0, 30.0)))
            ext = size * sp
            centre = origin + np.asarray(self.direction) @ (ext / 2)
            sp = np.full(3, max(sp.mean(), 0.3))
            size = np.maximum(np.ceil(ext.max() * 1.2 / sp).astype(int), 2)
            origin = centre - direction @ (size * sp / 2)
            if int(np.prod(size)) > 4 * MAX_CT_VOXELS:
                sp = sp * (np.prod(size) / (4 * MAX_CT_VOXELS)) ** (1 / 3)
                size = np.maximum(np.ceil(ext.max() * 1.2 / sp).astype(int), 2)
                origin = centre - direction @ (size * sp / 2)
        elif g == "far":
            origin = origin + direction @ (size * sp * 3.0)
        return tuple(int(v) for v in size), tuple(float(v) for v in sp), origin, direction

    def label_map(self) -> sitk.Image:
        rng = np.random.default_rng(self.seed + 1)
        size, sp, origin, direction = self.label_geometry()
        q = self.local_points(size, sp, origin, direction)
        shape = q.shape[:-1]
        lab = np.zeros(shape, np.int64)
        for o, value in zip(self.objects, self.labels):
            if value:
                lab[o.sdf(q) < self.label_offset] = value
        values = [v for v in self.labels if v] or [1]
        first = values[0]
        kind = self.segment
        if kind == "empty":
            lab[:] = 0
        elif kind == "voxel":
            lab[:] = 0
            lab[tuple(int(rng.integers(0, n)) for n in shape)] = first
        elif kind == "sheet":
            axis = int(rng.integers(0, 3))
            pos = int(rng.integers(0, shape[axis]))
            sl = [slice(None)] * 3
            sl[axis] = pos
            keep = lab[tuple(sl)].copy()
            lab[:] = 0
            lab[tuple(sl)] = np.where(keep > 0, keep, first) if keep.any() else first
        elif kind == "border":
            axis = int(rng.integers(0, 3))
            sl = [slice(None)] * 3
            sl[axis] = slice(0, max(1, shape[axis] // 3))
            sub = lab[tuple(sl)]
            sub[sub == 0] = first
        elif kind == "holes":
            hole = rng.random(shape) < 0.3
            lab[hole] = 0
        elif kind == "hollow":
            from scipy import ndimage
            inner = ndimage.binary_erosion(lab > 0, iterations=2)
            lab[inner] = 0
        elif kind == "random":
            lab[rng.random(shape) < 0.05] = first
        elif kind == "everything":
            lab[:] = first
        arr = _to_label_pixel(lab, self.label_pixel)
        img = sitk.GetImageFromArray(arr)
        img.SetSpacing([float(v) for v in sp])
        img.SetOrigin([float(v) for v in origin])
        img.SetDirection([float(v) for v in np.asarray(direction).ravel()])
        return img


def _to_pixel(hu: np.ndarray, pixel: str) -> np.ndarray:
    if pixel == "int16":
        return np.clip(np.rint(hu), -32768, 32767).astype(np.int16)
    if pixel == "float32":
        return hu.astype(np.float32)
    if pixel == "float64":
        return hu
    if pixel == "uint16+1024":  # stored value = HU + 1024 (the intercept lost)
        return np.clip(np.rint(hu + 1024), 0, 65535).astype(np.uint16)
    if pixel == "uint16":
        return np.clip(np.rint(hu), 0, 65535).astype(np.uint16)
    if pixel == "int32":
        return np.rint(hu).astype(np.int32)
    if pixel == "uint8":
        return np.clip(np.rint(hu), 0, 255).astype(np.uint8)
    raise ValueError(pixel)


def _to_label_pixel(lab: np.ndarray, pixel: str) -> np.ndarray:
    if pixel == "uint8":
        return np.clip(lab, 0, 255).astype(np.uint8)
    if pixel == "uint16":
        return lab.astype(np.uint16)
    if pixel == "int16":
        return lab.astype(np.int16)
    if pixel == "uint32":
        return lab.astype(np.uint32)
    if pixel == "float32":
        return lab.astype(np.float32)
    if pixel == "int64":
        return lab.astype(np.int64)
    raise ValueError(pixel)


def _phantomish_scene(**kw) -> Scene:
    """A hand-made scene: one ellipsoid bone (2 mm cortex at 1200 HU around marrow) in soft
    tissue, labelled 1 on the CT's grid."""
    base = dict(size=(36, 36, 30), spacing=(1.0, 1.0, 1.2), origin=(-12.0, 30.0, 100.0),
                direction=np.eye(3), background="soft", background_hu=40.0, noise=10.0,
                pixel="int16",
                objects=[Obj("ellipsoid", np.array([18.0, 18.0, 18.0]),
                             np.array([9.0, 8.0, 11.0]), 1200.0, 2.0, np.array([1.0, 0, 0]))],
                labels=[1], segment="objects", label_grid="same", label_pixel="uint8",
                label_offset=0.0, seed=1)
    base.update(kw)
    return Scene(**base)


# ---------------------------------------------------------------------------- strategies

PIXELS = ["int16", "int16", "int16", "float32", "float32", "float64", "uint16+1024", "uint16",
          "int32", "uint8"]
LABEL_PIXELS = ["uint8", "uint8", "uint16", "int16", "uint32", "float32"]
SEGMENTS = ["objects"] * 8 + ["empty", "voxel", "sheet", "border", "holes", "hollow", "random",
                              "everything"]
LABEL_GRIDS = ["same"] * 6 + ["coarse", "coarse", "shifted", "oblique", "far"]
BACKGROUNDS = ["air", "soft", "soft", "body", "body", "flat", "noise"]


def hu_level(draw) -> float:
    kind = draw(st.sampled_from(["cortical", "cortical", "cortical", "weak", "metal",
                                 "extended", "negative"]))
    lo, hi = {"cortical": (600, 2000), "weak": (120, 450), "metal": (2500, 4000),
              "extended": (4000, 30000), "negative": (-900, 100)}[kind]
    return draw(st.floats(lo, hi, allow_nan=False))


@st.composite
def scenes(draw, work_spacing=None, max_objects=3):
    """A scene whose working grid at ``work_spacing`` (mm; None: the library's auto) stays
    within MAX_WORK_VOXELS."""
    iso = draw(st.booleans())
    extreme = draw(st.sampled_from([False] * 12 + [True]))
    lo_sp, hi_sp = (0.01, 8.0) if extreme else (0.3, 4.0)
    if iso:
        s = draw(st.floats(lo_sp, hi_sp, allow_nan=False))
        spacing = np.array([s, s, s])
    else:
        spacing = np.array(draw(st.tuples(*[st.floats(lo_sp, hi_sp, allow_nan=False)] * 3)))
    d = work_spacing or float(np.clip(spacing.min() * 0.5, 0.3, 1.0))
    tiny = draw(st.sampled_from([False] * 8 + [True]))
    extent = np.array(draw(st.tuples(*[st.floats(2.0, 60.0, allow_nan=False)] * 3)))
    size = np.maximum(np.round(extent / spacing).astype(int), 2)
    if tiny:
        axis = draw(st.integers(0, 2))
        size[axis] = draw(st.integers(1, 3))
    size = np.minimum(size, 80)
    # keep the CT and the working grid small (scale the extent down, keep the spacing)
    for _ in range(40):
        work = np.prod(size * spacing / d + 1)
        if np.prod(size) <= MAX_CT_VOXELS and work <= MAX_WORK_VOXELS:
            break
        size = np.maximum((size * 0.85).astype(int), np.minimum(size, 2))
    ext = size * spacing
    origin = np.array(draw(st.tuples(*[st.floats(-600, 600, allow_nan=False)] * 3)))
    direction = draw(directions())
    background = draw(st.sampled_from(BACKGROUNDS))
    background_hu = {"air": -1000.0, "soft": 40.0, "body": 40.0}.get(background)
    if background_hu is None:
        background_hu = draw(st.floats(-1024, 3000, allow_nan=False))
    noise = draw(st.sampled_from([0.0, 5.0, 15.0, 30.0, 80.0]))
    if background == "noise":
        noise = draw(st.floats(50, 800, allow_nan=False))
    n_obj = 0 if background == "noise" else draw(st.integers(0, max_objects))
    n_obj = max(n_obj, draw(st.sampled_from([1] * 6 + [0])))
    objects = []
    for _ in range(n_obj):
        kind = draw(st.sampled_from(["ellipsoid", "ellipsoid", "ellipsoid", "box", "sheet"]))
        centre = np.array([draw(st.floats(-0.1, 1.1, allow_nan=False)) for _ in range(3)]) * ext
        frac = np.array([draw(st.floats(0.03, 0.45, allow_nan=False)) for _ in range(3)])
        radii = np.maximum(frac * ext.max(), 0.2)
        if kind == "sheet":
            radii[draw(st.integers(0, 2))] = draw(st.floats(0.1, 1.5, allow_nan=False))
        normal = rotation(draw(st.tuples(*[st.floats(-90, 90)] * 3)))[:, 0]
        shell = draw(st.sampled_from([0.0, 0.8, 1.5, 2.0, 3.0]))
        objects.append(Obj(kind, centre, radii, hu_level(draw), shell, normal))
    value_kind = draw(st.sampled_from(["small"] * 8 + ["big", "negative"]))
    if value_kind == "big":  # label values up to the pixel type's maximum
        label_pixel = draw(st.sampled_from(["uint16", "uint32", "int64", "float32"]))
        top = {"uint16": 2 ** 16 - 1, "uint32": 2 ** 32 - 1, "int64": 2 ** 40,
               "float32": 2 ** 24}[label_pixel]
        pool = st.one_of(st.integers(1, top), st.just(top))
    elif value_kind == "negative":
        label_pixel = draw(st.sampled_from(["int16", "int64", "float32"]))
        pool = st.integers(-300, 300).filter(bool)
    else:
        label_pixel = draw(st.sampled_from(LABEL_PIXELS))
        pool = st.integers(1, 255 if label_pixel == "uint8" else 300)
    values = draw(st.lists(pool, min_size=len(objects), max_size=len(objects), unique=True))
    if objects and draw(st.sampled_from([False] * 5 + [True])):
        values[-1] = 0  # an object without a label (unlabelled bone)
    label_grid = draw(st.sampled_from(LABEL_GRIDS))
    extra = {}
    if label_grid == "coarse":
        extra["factor"] = draw(st.floats(1.3, 3.0))
    elif label_grid == "shifted":
        extra["shift"] = tuple(draw(st.tuples(*[st.floats(-2.0, 2.0)] * 3)))
    elif label_grid == "oblique":
        extra["angles"] = tuple(draw(st.tuples(*[st.floats(-60, 60)] * 3)))
    return Scene(size=tuple(int(v) for v in size), spacing=tuple(float(v) for v in spacing),
                 origin=tuple(float(v) for v in origin), direction=direction,
                 background=background, background_hu=float(background_hu), noise=float(noise),
                 pixel=draw(st.sampled_from(PIXELS)), objects=objects, labels=values,
                 segment=draw(st.sampled_from(SEGMENTS)), label_grid=label_grid,
                 label_pixel=label_pixel,
                 label_offset=draw(st.sampled_from([0.0, 0.0, 1.0, 2.5, -0.5, -2.0])),
                 seed=draw(st.integers(0, 2 ** 31)), extra=extra)


@st.composite
def bone_scenes(draw, work_spacing=None, max_objects=2):
    """A scene that should mostly succeed: 1-2 bone-like objects (a 1-3 mm cortex of 700-1800
    HU around marrow, 5-20 mm semi-axes) well inside a CT of 0.4-2 mm voxels (anisotropic,
    any direction, non-zero origin), in soft tissue or a body, labelled by a segment that is
    exact, a little larger or smaller, on the CT's grid or a coarser or shifted one. Its
    working grid at ``work_spacing`` (None: auto) stays within MAX_WORK_VOXELS."""
    spacing = np.array(draw(st.tuples(*[st.floats(0.4, 2.0, allow_nan=False)] * 3)))
    if draw(st.booleans()):
        spacing[:] = spacing[0]
    d = work_spacing or float(np.clip(spacing.min() * 0.5, 0.3, 1.0))
    n_obj = draw(st.integers(1, max_objects))
    radii = [np.array(draw(st.tuples(*[st.floats(5.0, 14.0, allow_nan=False)] * 3)))
             for _ in range(n_obj)]
    gap = draw(st.floats(1.0, 6.0, allow_nan=False))
    margin = draw(st.floats(4.0, 10.0, allow_nan=False))
    # objects side by side along x
    width = sum(2 * r[0] for r in radii) + gap * (n_obj - 1) + 2 * margin
    ext = np.array([width, 2 * max(r[1] for r in radii) + 2 * margin,
                    2 * max(r[2] for r in radii) + 2 * margin])
    # keep the working grid (with the crop margin and the band) and the CT small
    scale = min(1.0, (MAX_WORK_VOXELS / np.prod((ext + 16.0) / d)) ** (1 / 3),
                (MAX_CT_VOXELS / np.prod(ext / spacing)) ** (1 / 3))
    radii = [np.maximum(r * scale, 3.0) for r in radii]
    ext = ext * scale
    size = np.maximum(np.ceil(ext / spacing).astype(int), 4)
    ext = size * spacing
    objects, x = [], (ext[0] - (sum(2 * r[0] for r in radii) + gap * (n_obj - 1))) / 2
    for r in radii:
        centre = np.array([x + r[0], ext[1] / 2, ext[2] / 2])
        x += 2 * r[0] + gap
        shell = draw(st.floats(1.0, 3.0, allow_nan=False))
        objects.append(Obj(draw(st.sampled_from(["ellipsoid"] * 4 + ["box"])), centre, r,
                           draw(st.floats(700, 1800, allow_nan=False)), shell,
                           np.array([1.0, 0.0, 0.0])))
    values = draw(st.lists(st.integers(1, 255), min_size=n_obj, max_size=n_obj, unique=True))
    label_grid = draw(st.sampled_from(["same"] * 4 + ["coarse", "shifted"]))
    extra = {}
    if label_grid == "coarse":
        extra["factor"] = draw(st.floats(1.3, 2.5))
    elif label_grid == "shifted":
        extra["shift"] = tuple(draw(st.tuples(*[st.floats(-1.0, 1.0)] * 3)))
    return Scene(size=tuple(int(v) for v in size), spacing=tuple(float(v) for v in spacing),
                 origin=tuple(draw(st.tuples(*[st.floats(-500, 500, allow_nan=False)] * 3))),
                 direction=draw(directions().filter(lambda m: abs(np.linalg.det(m)) > 0.99
                                                    and np.allclose(m.T @ m, np.eye(3)))),
                 background=draw(st.sampled_from(["soft", "body"])), background_hu=40.0,
                 noise=draw(st.sampled_from([0.0, 10.0, 20.0, 35.0])),
                 pixel=draw(st.sampled_from(["int16", "int16", "float32", "int32", "float64"])),
                 objects=objects, labels=values, segment="objects", label_grid=label_grid,
                 label_pixel=draw(st.sampled_from(["uint8", "uint16", "uint32", "int16"])),
                 label_offset=draw(st.sampled_from([0.0, 0.0, 0.5, 1.0, 2.0, -0.5])),
                 seed=draw(st.integers(0, 2 ** 31)), extra=extra)


def any_scenes(work_spacing=None, max_objects=3):
    """Bone-like scenes and wild ones, half and half."""
    return st.one_of(bone_scenes(work_spacing, min(max_objects, 2)),
                     scenes(work_spacing, max_objects))


# Parameters that make a run slow at their upper end: drawn mostly from a cheap sub-range.
CHEAP = {"iterations": 4, "poisson_depth": 7, "views": 8, "max_erosions": 4, "closing": 3,
         "opening": 2}


def valid_value(spec):
    """A strategy of valid values of one parameter (its whole declared range)."""
    if spec.kind is bool:
        return st.booleans()
    if spec.kind is str:
        return st.sampled_from(spec.choices)
    if spec.kind is int:
        full = st.integers(int(spec.minimum), int(spec.maximum))
        if spec.name in CHEAP:
            cheap = st.integers(int(spec.minimum), min(CHEAP[spec.name], int(spec.maximum)))
            values = st.one_of(cheap, cheap, cheap, full)
        else:
            values = full
        values = st.one_of(values, values.map(np.int64))
    else:
        values = st.floats(spec.minimum, spec.maximum, allow_nan=False)
        edges = st.sampled_from([spec.minimum, spec.maximum])
        values = st.one_of(values, values, edges, values.map(np.float32).filter(
            lambda v: spec.minimum <= v <= spec.maximum), values.map(int).filter(
            lambda v: spec.minimum <= v <= spec.maximum))
    if spec.allows_auto:
        values = st.one_of(st.none(), values)
    return values


def invalid_value(spec):
    """A strategy of values that validate() must refuse."""
    bad = [st.just(float("nan")), st.just(float("inf")), st.just(float("-inf")),
           st.just("abc"), st.just([1.0]), st.just(object())]
    if spec.kind in (int, float):
        bad += [st.just(True), st.just(False), st.just("1"), st.just(complex(1, 1))]
        bad.append(st.floats(-1e9, spec.minimum, exclude_max=True, allow_nan=False))
        bad.append(st.floats(spec.maximum, 1e12, exclude_min=True, allow_nan=False))
        bad.append(st.just(np.float64("nan")))
    if spec.kind is int:
        bad.append(st.floats(spec.minimum, spec.maximum, allow_nan=False).filter(
            lambda v: v != int(v)))
        bad.append(st.integers(int(spec.minimum), int(spec.maximum)).map(float))
        bad.append(st.integers(-10 ** 6, int(spec.minimum) - 1))
        bad.append(st.integers(int(spec.maximum) + 1, 10 ** 12))
    if spec.kind is bool:
        bad += [st.just(1), st.just(0), st.just("yes")]
    if spec.kind is str:
        bad += [st.just(""), st.just(spec.choices[0].upper()), st.just(1)]
    if not spec.allows_auto:
        bad.append(st.none())
    return st.one_of(bad)


FAST_BASE = dict(iterations=3, poisson_depth=6, views=6)


@st.composite
def parameter_sets(draw, invalid_rate=0.25, base=None):
    """(overrides dict, expected_valid) drawn from the schema."""
    names = sorted(SCHEMA)
    chosen = draw(st.lists(st.sampled_from(names), max_size=5, unique=True))
    overrides = dict(base if base is not None else draw(st.sampled_from([FAST_BASE, {}])))
    overrides.pop("keep_intermediates", None)
    valid = True
    for name in chosen:
        spec = SCHEMA[name]
        if name == "spacing":  # the working spacing is drawn with the scene
            continue
        if draw(st.floats(0, 1)) < invalid_rate:
            overrides[name] = draw(invalid_value(spec))
            valid = False
        else:
            overrides[name] = draw(valid_value(spec))
    return overrides, valid


def cli_text(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "auto"
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    return str(value)


# ---------------------------------------------------------------------------- harness

class Snapshot:
    """Array and geometry of a SimpleITK image, to tell whether a call changed it."""

    def __init__(self, image):
        self.image = image
        self.ok = isinstance(image, sitk.Image)
        if self.ok:
            self.array = sitk.GetArrayFromImage(image).copy()
            self.geometry = (image.GetSize(), image.GetOrigin(), image.GetSpacing(),
                             image.GetDirection(), image.GetPixelID(),
                             image.GetNumberOfComponentsPerPixel())
            self.meta = {k: image.GetMetaData(k) for k in image.GetMetaDataKeys()}

    def unchanged(self) -> bool:
        if not self.ok:
            return True
        img = self.image
        geometry = (img.GetSize(), img.GetOrigin(), img.GetSpacing(), img.GetDirection(),
                    img.GetPixelID(), img.GetNumberOfComponentsPerPixel())
        arr = sitk.GetArrayViewFromImage(img)
        meta = {k: img.GetMetaData(k) for k in img.GetMetaDataKeys()}
        same = arr.shape == self.array.shape and np.array_equal(
            arr, self.array, equal_nan=np.issubdtype(arr.dtype, np.floating))
        return geometry == self.geometry and same and meta == self.meta


def params_state(params) -> str:
    if isinstance(params, Parameters):
        return repr(sorted((k, repr(v)) for k, v in vars(params).items()))
    return repr(params)


class Outcomes:
    """Counts of this process's cases by outcome (the campaign's figures)."""

    counts: dict = {}

    @classmethod
    def add(cls, test, outcome):
        key = (test, outcome)
        cls.counts[key] = cls.counts.get(key, 0) + 1


def log(record: dict) -> None:
    if not LOG_PATH:
        return
    with open(LOG_PATH, "a") as fh:
        fh.write(json.dumps(record, default=str) + "\n")
        fh.flush()
        os.fsync(fh.fileno())


class Progress:
    """A progress callback that checks its fractions."""

    def __init__(self):
        self.bad = []

    def __call__(self, fraction, message=""):
        if not (isinstance(fraction, (int, float)) and 0.0 <= fraction <= 1.0 + 1e-9):
            self.bad.append((fraction, message))
        return True


def check_result_surfaces(result) -> int:
    """Assert every surface of a result passes every check; returns how many there are."""
    bones = getattr(result, "bones", None)
    if bones is None:
        bones = [result]
    n = 0
    for bone in bones:
        if getattr(bone, "error", None) is not None:
            assert isinstance(bone.error, BoneWatertightError), \
                f"bone {bone.name} failed with a non-library error {bone.error!r}"
            assert bone.surface is None
            continue
        s = bone.surface
        assert s is not None and len(s.faces) > 0, "a success without a surface"
        assert np.isfinite(s.vertices).all(), "non-finite vertices returned"
        rep = check_surface(s.vertices, s.faces)
        assert rep.ok, f"invalid surface returned as a success: {rep.problems}"
        assert bone.report.checks.ok
        dist = bone.distance_to_constraints
        assert dist is not None and len(dist) == len(s.vertices) and np.isfinite(dist).all()
        n += 1
    return n


def parameters_valid(overrides: dict) -> bool:
    """Whether ``Parameters(**overrides)`` passes validate() (each value, and the cross-checks)."""
    try:
        Parameters(**overrides).validate()
    except InputError:
        return False
    return True


def ct_refused(ct: sitk.Image) -> bool:
    """The CT is not a scalar 3-D CT in HU by the library's documented rules: a single slice
    along an axis, a direction that is not orthonormal, or a label map (integers, none
    negative, at most 16 distinct values)."""
    direction = np.array(ct.GetDirection()).reshape(3, 3)
    arr = sitk.GetArrayViewFromImage(ct)
    labelmap = (np.issubdtype(arr.dtype, np.integer) and arr.min() >= 0
                and len(np.unique(arr)) <= 16)
    return (min(ct.GetSize()) < 2 or not np.allclose(direction.T @ direction, np.eye(3), atol=1e-4)
            or labelmap)


def mask_on_ct(ct: sitk.Image, labels: sitk.Image) -> np.ndarray:
    """Which CT voxels the label map's non-zero voxels cover (nearest neighbour), (z, y, x)."""
    mask = sitk.Cast(sitk.NotEqual(labels, 0), sitk.sitkUInt8)
    on_ct = sitk.Resample(mask, ct, sitk.Transform(), sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8)
    return sitk.GetArrayFromImage(on_ct) > 0


def expected_error(ct: sitk.Image, labels: sitk.Image, overrides: dict) -> "str | None":
    """The typed error a one-bone case (``reconstruct(ct, labels != 0, params)``) must raise,
    decided from the inputs alone in the order the library checks them: invalid parameters
    -> InputError; a CT that is no CT -> VolumeTypeError; an empty segment ->
    EmptySegmentError; a segment outside the CT -> NoOverlapError. None where the inputs are
    valid: the reconstruction then decides (a surface, or a ReconstructionError)."""
    if not parameters_valid(overrides):
        return "InputError"
    if ct_refused(ct):
        return "VolumeTypeError"
    if not np.any(sitk.GetArrayViewFromImage(labels) != 0):
        return "EmptySegmentError"
    if not mask_on_ct(ct, labels).any():
        return "NoOverlapError"
    return None


def labels_refused(labels: sitk.Image) -> bool:
    """Label values a label map must not have: negative, non-integer, or beyond uint32."""
    arr = sitk.GetArrayViewFromImage(labels)
    return bool(arr.min() < 0 or arr.max() > 2 ** 32 - 1 or not np.array_equal(arr, np.round(arr)))


def expected_error_many(ct: sitk.Image, labels: sitk.Image, overrides: dict, targets) -> "str | None":
    """As :func:`expected_error` for ``reconstruct_many``: invalid parameters -> InputError; a
    CT that is no CT -> VolumeTypeError; label values it cannot hold, or a bone asked for twice
    -> InputError; none of the targets in the label map -> EmptySegmentError. None otherwise
    (the reconstruction, or a per-bone check, decides)."""
    if not parameters_valid(overrides):
        return "InputError"
    if ct_refused(ct):
        return "VolumeTypeError"
    if labels_refused(labels) or len(set(targets)) != len(targets):
        return "InputError"
    if not np.isin(sitk.GetArrayViewFromImage(labels), list(targets)).any():
        return "EmptySegmentError"
    return None


def run_case(test: str, describe: dict, call, images, params=None, check=None, expect=None):
    """Run ``call(progress)`` and check the properties; return the outcome string.

    ``images``: the input images (checked unchanged afterwards); ``params``: the parameter
    object handed in (checked unchanged); ``check(result, outcome)``: more assertions;
    ``expect``: the outcome the case must have (an error class name, or "ok"), when known.
    """
    snaps = [Snapshot(img) for img in images]
    before = params_state(params)
    progress = Progress()
    log({"event": "start", "test": test, "case": describe, "pid": os.getpid()})
    faulthandler.dump_traceback_later(HANG_SECONDS, exit=True)
    t0 = time.perf_counter()
    outcome = None
    detail = None
    try:
        try:
            result = call(progress)
        except BoneWatertightError as exc:
            message = str(exc)
            assert message.strip(), f"{type(exc).__name__} without a message"
            if isinstance(exc, ValueError):
                assert isinstance(exc, InputError)
            outcome = type(exc).__name__
            detail = message[:160]
            result = None
        except Exception as exc:
            outcome = f"NON-LIBRARY {type(exc).__name__}"
            raise AssertionError(
                f"non-library exception {type(exc).__name__}: {exc}\ncase: {describe}") from exc
        if isinstance(result, int):  # an exit code (the command line)
            outcome = f"exit {result}"
        elif result is not None:
            n = check_result_surfaces(result)
            outcome = "ok" if n else "all bones failed"
            bones = getattr(result, "bones", None)
            if bones is not None:
                errs = sorted({type(b.error).__name__ for b in bones if b.error is not None})
                if errs:
                    outcome += " (" + ", ".join(errs) + ")"
        for i, s in enumerate(snaps):
            assert s.unchanged(), f"input image {i} was modified\ncase: {describe}"
        assert params_state(params) == before, "the parameters were modified"
        assert not progress.bad, f"progress fractions out of [0, 1]: {progress.bad[:3]}"
        if expect is not None:
            assert outcome == expect, f"expected {expect}, got {outcome}: {detail}\ncase: {describe}"
        if check is not None:
            check(result, outcome)
    except AssertionError as exc:
        if outcome is None or not outcome.startswith("NON-LIBRARY"):
            outcome = f"PROPERTY FAILED: {str(exc).splitlines()[0][:200]}"
        detail = "".join(traceback.format_exception(exc.__cause__ or exc)[-6:])
        if not COLLECT:
            raise
    finally:
        faulthandler.cancel_dump_traceback_later()
        seconds = time.perf_counter() - t0
        Outcomes.add(test, outcome)
        log({"event": "end", "test": test, "outcome": outcome, "seconds": round(seconds, 3),
             "pid": os.getpid(), "detail": detail})
    return outcome


# ---------------------------------------------------------------------------- figures

def summarize(path: str) -> dict:
    """Figures of a campaign log: cases, outcomes, and the cases that never ended (an abort
    or a hang killed the process)."""
    open_cases = {}
    cases = 0
    by_outcome = {}
    failures = {"non-library exceptions": 0, "invalid surfaces": 0, "modified inputs": 0,
                "other property failures": 0, "aborts or hangs": 0}
    slowest = []
    with open(path) as fh:
        for line in fh:
            rec = json.loads(line)
            if rec.get("event") not in ("start", "end"):
                continue
            key = rec.get("pid")
            if rec["event"] == "start":
                if key in open_cases:  # the previous case of that process never ended
                    failures["aborts or hangs"] += 1
                open_cases[key] = rec
                continue
            open_cases.pop(key, None)
            cases += 1
            out = rec["outcome"] or "?"
            by_outcome[(rec["test"], out)] = by_outcome.get((rec["test"], out), 0) + 1
            slowest.append((rec["seconds"], rec["test"]))
            if out.startswith("NON-LIBRARY"):
                failures["non-library exceptions"] += 1
            elif out.startswith("PROPERTY FAILED"):
                if "invalid surface" in out:
                    failures["invalid surfaces"] += 1
                elif "modified" in out:
                    failures["modified inputs"] += 1
                else:
                    failures["other property failures"] += 1
    failures["aborts or hangs"] += len(open_cases)
    slowest.sort(reverse=True)
    return {"cases": cases, "failures": failures, "outcomes": by_outcome,
            "slowest": slowest[:5], "never_ended": list(open_cases.values())}


if __name__ == "__main__":  # python Testing/test_properties_strategies.py LOG...
    for p in sys.argv[1:]:
        s = summarize(p)
        print(f"{p}: {s['cases']} cases")
        for k, v in s["failures"].items():
            print(f"  {k}: {v}")
        for (test, out), n in sorted(s["outcomes"].items()):
            print(f"  {test:28s} {n:5d}  {out}")
        print("  slowest:", s["slowest"])
        for rec in s["never_ended"]:
            print("  never ended:", json.dumps(rec)[:2000])
