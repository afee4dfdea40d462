"""The entry functions: CT + segment(s) -> checked, plausible watertight 2-manifold surfaces.

- :func:`reconstruct_many`: several bones of one segmentation *together*. Every other label
  of the segmentation is a neighbour: the bones compete for the voxels of their joints, and the
  surfaces are kept apart by ``min_gap`` (SPEC §5b).
- :func:`reconstruct`: one bone from a mask (the paper's case: a rough segment of bone k).

The only place that unpacks :class:`~BoneWatertightLib.params.Parameters`: each stage of
:mod:`BoneWatertightLib.stages` gets arrays and explicit keyword arguments. Volumes are (z, y, x)
arrays on the isotropic working grid, points (n, 3) x-y-z grid millimetres; results are mapped
to physical LPS millimetres at the end.

Stages: prepare (several labels, cut sides continued past the image) -> hybrid filter ->
automatic thresholds -> ownership (the segment as evidence, the neighbours as competitors, the
CT's joint valley) -> per bone: W_H0 / W_HT -> visible points (eq. 1) -> Poisson M0 -> the
territories between bones -> deformation (eq. 15) -> edge refinement -> joint gaps -> caps at
the image boundary -> checks (SPEC §4) -> plausibility against the segment -> pair checks.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np
import SimpleITK as sitk
from scipy import ndimage
from scipy.spatial import cKDTree

from . import __version__
from .errors import (BoneWatertightError, CancelledError, InputError, PlausibilityError,
                     ReconstructionError, SurfaceCheckError)
from .memory import release_free_memory
from .mesh import cap as _cap
from .mesh import checks as _checks, operators as _operators
from .mesh.cap import cap_plane
from .mesh.checks import check_surface
from .mesh.operators import sample_field
from .mesh.surface import Surface, enclosed_volume, mean_edge_length, surface_area
from .params import Parameters
from .progress import Progress, ProgressCallback
from .report import (Counts, DistanceSummary, FallbackLog, JointReport, PairReport,
                     PipelineReport, Refinement, StageTimes, constants_of)
from .stages import autothreshold as _auto, contacts as _contacts, deform as _deform
from .stages import evidence as _evidence
from .stages import filtering as _filtering, ownership as _ownership, plausibility as _plaus
from .stages import plates as _plates, poisson as _poisson, prepare as _prepare
from .stages import refine as _refine
from .stages import threshold as _threshold, visible as _visible
from .stages.autothreshold import auto_thresholds
from .stages.deform import Deformer
from .stages.filtering import hybrid_filter
from .stages.ownership import compute_ownership
from .stages.poisson import import_open3d, initial_surface, mask_normals
from .stages.prepare import prepare_labels
from .stages.refine import refine_to_edges
from .stages.threshold import (BoneMasks, bone_masks, boundary_voxels, crossing_points,
                               erosions_to_separate, voxel_points)
from .stages.visible import visible_points
from .threads import cpu_threads, helper_processes_allowed, thread_map

# The filter's percentile is taken within this distance (mm) of the targets.
FILTER_REGION_MM = 3.0
# Smoothing (voxels) of the occupancy whose 0.5 level is the deformation's inside test.
OCCUPANCY_SIGMA_VOXELS = 0.7
OCCUPANCY_LEVEL = 0.5
# The CT that the edge refinement samples is smoothed by max(REFINE_SIGMA_MIN_VOXELS,
# REFINE_SIGMA_MM / d) voxels.
REFINE_SIGMA_MM = 0.4
REFINE_SIGMA_MIN_VOXELS = 0.5
# A bone reaches at most max(segment_dilation, BAND_COARSENESS x coarseness) beyond its label.
BAND_COARSENESS = 1.0
# Bone that M0 left out (joining it added a tunnel) is warned about when it lies farther than
# this outside the finished surface: the thin-plate bones' bound on the largest error (issue 18:
# max <= 5 mm to the reference); nearer, the deformation and the refinement hold it. Pieces
# farther than it are joined one by one where they add no tunnel (poisson.remesh).
LEFT_OUT_WARN_MM = _poisson.JOIN_TRIAL_REACH_MM
# The bone's own CT edge (a deformation constraint) farther than this outside the finished
# surface, over a patch at least this wide, is warned (_missed_edge_warning): beyond the reach
# of the edge refinement's search (search_radius + search_offset, 2.25 mm at the defaults),
# so the surface stops short of bone the thresholds hold. Measured on the constraints of 19
# finished bones that follow their truth or reference (femur phantom, real L1-L5, 3 mm and
# 0.7 x 2.5 mm pelvis and lumbar phantoms): at most 3.0 mm out, on a patch of 1-2 mm^2; a
# faint sacral tip and an iliac crest cut 8.6 / 5.7 mm short: 4.8 / 3.9 mm out over 39 / 9
# mm^2.
MISSED_EDGE_WARN_MM = 3.0
# M0 is cut back out of what is neither bone nor segment: farther than CARVE_SEGMENT_COARSENESS
# x coarseness + d from the (trusted) segment and farther than CARVE_BONE_MM + d from the bone
# at HT (the segment's own uncertainty and the CT's partial-volume foot stay untouched).
CARVE_SEGMENT_COARSENESS = 0.5
CARVE_BONE_MM = 1.0
# ... and wherever the CT shows soft tissue (below the ownership's label level, its
# info["label_level_hu"]) outside the segment, whatever the segment's and the bone's distance:
# a canal or foramen that the segment leaves open and the CT shows dark is no part of M0's
# bone (the sacral canal on 3 mm slices: 6-9 mm across in the segment, so no voxel of it lay
# the segment's margin away - stop 37, the real 3 mm sacrum's genus 6 -> 8, its segment's 9).
# No margin from the bone: its closing and hole filling take in a lumen a few voxels across (the
# sacral canal's caudal tube, 3-4 mm of lumen on 0.7 x 2.5 mm slices), so within the bone's
# margin no voxel of it was carved. Measured without the margin (stop 41, 90 bones of the
# anatomical phantoms, seeds 0-41 and held-out 101/137): mean max 3.90 -> 3.44 mm, bones with
# max > 5 mm 14 -> 11 (sacra 0.7 x 2.5 mm 9.9-10.2 -> 3.1-4.0 on two seeds), bones with more
# tunnels than their truth 16 -> 8 (M0's false bridges over soft tissue cut away). A lumen the
# slices blur above the label level (a 5 mm canal on 2.5 mm slices) stays closed.
# Rounds of extra contact passes (each with one voxel more margin) while a pair still crosses;
# they move only the vertices within CONTACT_RETRY_REACH_MM (+ the extra margin) of a face
# that crosses (the passes' own rings of neighbours follow within that reach).
CONTACT_RETRIES = 3
CONTACT_RETRY_REACH_MM = 3.0
# Bones worked at once (threads) by the per-bone stages: numpy, scipy.ndimage, SimpleITK and edt
# release the GIL in their loops (two threads measured 1.5-2.3x on dilation, labelling, rank
# filters, interpolation and sorting on this project's volumes). At most this many, one per
# CPU, and only as many as max_memory_gb holds (bone_schedule).
MAX_BONE_THREADS = 4
# The exact gap step aims this far (mm) beyond min_gap: the pair check measures it again on the
# capped surfaces in physical coordinates.
GAP_MARGIN_MM = 0.005
# How often the calling thread passes the bones' progress on (s) while they run in threads.
RELAY_POLL_S = 0.2
# HT crossings within this distance (mm) of W_H0 are left out of B* (see _bone_surface).
HT_BEYOND_H0_MM = 1.0
# A pair whose bone evidence touches over more than JOINT_WARN_MIN_MM2 with a joint space
# visible on less than JOINT_WARN_SEEN of it gets a warning: there the boundary between them
# follows the labels alone (a narrow joint on thick slices), and wrong labels move it.
JOINT_WARN_SEEN = _plaus.JOINT_WARN_SEEN
JOINT_WARN_MIN_MM2 = _plaus.JOINT_WARN_MIN_MM2
# Vertices farther than this (mm) from every other bone's voxels are its free surface (where
# the edge refinement's support is measured).
FREE_SURFACE_MM = 2.0
# Cross-parameter limits, checked right after prepare: the smallest extent of each target's
# segment must span at least this many resample voxels d and this many edge lengths d*.
MIN_VOXELS_ACROSS = 4.0
MIN_EDGES_ACROSS = 4.0
# Bytes per voxel of M0's remeshing grid (step d* / REMESH_EDGE_RATIO over the bone's box):
# uint8 image and stencil, labels (int32), filled mask, smoothed float32 field, the contour
# (measured 40-49 B per voxel, mesh included).
REMESH_BYTES_PER_VOXEL = 64

# Overall progress fraction at the start and end of each stage.
STAGES = [("open3d", 0.0, 0.03), ("prepare", 0.03, 0.10), ("filter", 0.10, 0.14),
          ("thresholds", 0.14, 0.15), ("ownership", 0.15, 0.25), ("surfaces", 0.25, 0.50),
          ("territories", 0.50, 0.53), ("deform", 0.53, 0.78), ("contacts", 0.78, 0.86),
          ("checks", 0.86, 1.0)]


@dataclass
class ReconstructionResult:
    """One bone: the checked surface (physical LPS mm; cell array "Cap" on cap faces when the
    bone is cut by the image), its per-vertex distance to the constraint points (mm, (n,)),
    the typed report and, on request, the intermediate results."""

    surface: Surface
    distance_to_constraints: np.ndarray
    report: PipelineReport
    intermediates: dict = field(default_factory=dict)
    label: int = 0
    name: str = ""
    error: Optional[Exception] = None

    @property
    def ok(self) -> bool:
        return self.error is None


@dataclass
class JointResult:
    """Several bones reconstructed together: one result per target (in the order asked for),
    the pair checks and the shared report."""

    bones: list
    pairs: list
    report: JointReport


def _stage(progress: Progress, name: str) -> Progress:
    for n, a, b in STAGES:
        if n == name:
            release_free_memory()  # what the last stage freed: the peak is the live data's
            sub = progress.stage(a, b)
            sub(0.0, name)
            return sub
    raise KeyError(name)


def reconstruct(ct: sitk.Image, mask: sitk.Image, params: Optional[Parameters] = None,
                progress: Optional[ProgressCallback] = None) -> ReconstructionResult:
    """Reconstruct one bone from a mask.

    :param ct: CT volume in HU (SimpleITK image, any direction matrix). Not modified.
    :param mask: segment of bone k (non-zero = segment), any geometry. Not modified.
    :param params: pipeline parameters (defaults when None).
    :param progress: callback(fraction, message); returning False cancels (CancelledError).
    :return: the bone's result (see :class:`ReconstructionResult`).
    :raises InputError, ReconstructionError, SurfaceCheckError, PlausibilityError,
        CancelledError.
    """
    if not isinstance(mask, sitk.Image):
        from .errors import EmptySegmentError
        raise EmptySegmentError("No segment was given: select the segment of the bone.")
    labels = sitk.Cast(sitk.NotEqual(mask, 0), sitk.sitkUInt8)
    result = reconstruct_many(ct, labels, [1], params, progress, neighbours="none",
                              names={1: "segment"})
    return result.bones[0]


def _select_neighbours(labels: np.ndarray, values: list, targets: list, neighbours) -> tuple:
    """The label index map with only the targets and the chosen neighbours (indices)."""
    if neighbours == "auto" or neighbours is None:
        return labels, [v for i, v in enumerate(values, 1) if i not in targets]
    if neighbours == "none":
        keep = list(targets)
    else:
        wanted = [int(v) for v in neighbours]
        absent = [v for v in wanted if v not in values]
        if absent:
            raise InputError(
                f"Neighbour label(s) {', '.join(map(str, absent))} are not in the segmentation "
                f"near the bone (labels there: {', '.join(map(str, values))}). Give existing "
                "labels, or neighbours 'auto' (every other label) or 'none'.")
        keep = list(targets) + [values.index(v) + 1 for v in wanted]
    lut = np.zeros(len(values) + 1, labels.dtype)
    for i in keep:
        lut[i] = i
    return lut[labels], [values[i - 1] for i in keep if i not in targets]


@contextlib.contextmanager
def timed(times: StageTimes, stage: str, spans: Optional[list] = None, k: Optional[int] = None):
    """Add the seconds the block takes to ``times.<stage>`` (the one stage clock).

    Parameters
    ----------
    times : StageTimes
        The run's (shared stages) or a bone's stage times.
    stage : str
        A field of :class:`StageTimes`.
    spans : list, optional
        When given, ``(stage, k, start, end)`` (``time.perf_counter`` seconds) is appended to
        it once the block ends (see :func:`_stage_spans`).
    k : int, optional
        The bone's label index on the working grid (None: a stage the bones share).
    """
    t0 = time.perf_counter()
    try:
        yield
    finally:
        t1 = time.perf_counter()
        setattr(times, stage, getattr(times, stage) + t1 - t0)
        if spans is not None:
            spans.append((stage, k, t0, t1))  # one append: safe from the bones' threads


@dataclass
class BoneWork:
    """One bone between the stages of :func:`reconstruct_many`.

    Points and vertices are (n, 3) x-y-z grid millimetres of the working grid; ``faces``
    (m, 3) vertex indices of M0 (every later stage moves vertices only).
    """

    k: int                                   # label index on the working grid
    name: str
    times: StageTimes = field(default_factory=StageTimes)
    masks: Optional[BoneMasks] = None        # the threshold windows, on the bone's box
    separation: Optional[int] = None         # erosions that separate it (None: never)
    n_candidates: int = 0                    # W_H0 boundary points seen by eq. (1)
    visible: Optional[np.ndarray] = None     # the thinned visible points: Poisson's input
    visible_all: Optional[np.ndarray] = None # every visible point: S(P_H0) of B*
    b_ht: Optional[np.ndarray] = None        # HT crossings beyond W_H0: P_HT - P_H0 of B*
    vis_info: dict = field(default_factory=dict)
    m0: Optional[Surface] = None
    raw_vertices: int = 0                    # Poisson's own vertex count
    # (z, y, x) float32 distance (mm) to other bones' owned voxels, on the masks' box
    others_distance: Optional[np.ndarray] = None
    constraints: Optional[np.ndarray] = None # B* on this bone's side of every joint
    deformed: Optional[np.ndarray] = None    # vertices after eq. (15)
    vertices: Optional[np.ndarray] = None    # current vertices
    history: list = field(default_factory=list)
    refinement: Refinement = field(default_factory=Refinement)
    contacts: dict = field(default_factory=dict)
    fallbacks: FallbackLog = field(default_factory=FallbackLog)  # what fell back, and where
    plates: Optional[_plates.Plates] = None  # thin plates the thresholds miss (grid mm)
    processes: Optional[np.ndarray] = None  # thin processes of the segment joined (masks' box)
    # M0's tunnels through a thin plate the CT shows (_plate_holes; box mm)
    plate_holes: dict = field(default_factory=dict)
    plate_ct: Optional[np.ndarray] = None  # the masks' box of the CT at the plates' scale

    fusion: Optional[_poisson.Fusion] = None  # what M0 joined to the Poisson surface
    own_reference: float = float("nan")      # its cortex's contrast after eq. (15) (HU)
    profiles: Optional[tuple] = None         # its CT profiles then (refine.sample_profiles)

    @property
    def faces(self) -> np.ndarray:
        return self.m0.faces


@dataclass
class Workspace:
    """What the bones of one working grid share: the prepared grid, the label index map
    with the targets and the chosen neighbours, the filtered CT, the thresholds, the
    ownership, the fixed masks of the bones not reconstructed and the territories. Arrays
    are (z, y, x) on the working grid."""

    prep: object                             # stages.prepare.PreparedLabels
    labels: np.ndarray
    neighbour_values: list
    names: dict
    band: float                              # how far a bone may reach beyond its label (mm)
    ct_f: Optional[np.ndarray] = None
    h0: float = 0.0
    ht: float = 0.0
    thresholds: dict = field(default_factory=dict)
    own: object = None                       # stages.ownership.Ownership
    fixed: dict = field(default_factory=dict)
    territories: dict = field(default_factory=dict)
    ct_smooth: Optional[np.ndarray] = None
    ct_smooth_d: object = 0.0                # its step(s) (mm): d, or prepare.refine_spacing
    # The full cortical contrast of the bones reconstructed together (HU; NaN: none), and
    # the bone it came from (refine.full_contrast).
    shared_reference: float = float("nan")
    shared_reference_from: Optional[int] = None

    @property
    def d(self) -> float:
        return self.prep.grid.spacing

    @property
    def targets(self) -> list:
        return self.prep.targets

    def name_of(self, k: int) -> str:
        v = self.prep.values[k - 1]
        return str(self.names.get(v, v))

    def value_of(self, k: int) -> int:
        return int(self.prep.values[k - 1])


@dataclass
class _Run:
    """One call of :func:`reconstruct_many`: parameters, progress, the shared stage times and
    fallbacks, and the bones that failed ({label index: error})."""

    params: Parameters
    progress: Progress
    keep_going: bool
    times: StageTimes = field(default_factory=StageTimes)
    fallbacks: FallbackLog = field(default_factory=FallbackLog)
    failed: dict = field(default_factory=dict)
    threads: int = 1
    costs: dict = field(default_factory=dict)   # bone k -> bytes it may need (bone_schedule)
    budget: float = float("inf")                # bytes the bones at once may need
    spans: list = field(default_factory=list)   # (stage, k or None, start, end): see timed
    poisson_helper: object = None               # stages.poisson.PoissonHelper, or None

    def stage(self, name: str) -> Progress:
        return _stage(self.progress, name)

    def fail(self, k: int, exc: BaseException) -> None:
        """Record bone k's failure (keep_going), else raise it."""
        if (not self.keep_going or not isinstance(exc, BoneWatertightError)
                or isinstance(exc, CancelledError)):
            raise exc
        self.failed[k] = exc

    def each(self, keys: list, progress: Progress, work, slots: Optional[int] = None) -> dict:
        """{k: work(k, part)} for each key of ``keys`` that has not failed; ``part`` is k's
        share of ``progress`` (1 / ``slots`` of it); a failure is recorded by :meth:`fail`.
        With ``threads`` > 1 that many bones are worked at once (see :class:`_Relay`)."""
        slots = slots or len(keys)
        todo = [(i, k) for i, k in enumerate(keys) if k not in self.failed]
        if min(self.threads, len(todo)) > 1:
            return self._each_threaded(todo, slots, progress, work)
        out = {}
        for i, k in todo:
            part = progress.stage(i / slots, (i + 1) / slots)
            try:
                out[k] = work(k, part)
            except Exception as exc:  # noqa: BLE001 - fail() re-raises unless keep_going
                self.fail(k, exc)
        return out

    def _each_threaded(self, todo: list, slots: int, progress: Progress, work) -> dict:
        """:meth:`each` on a pool of ``threads`` threads. The caller's progress callback is
        called from this (the calling) thread only, at least every RELAY_POLL_S; when it
        cancels, the bones still running stop at their next progress step. Failures are
        recorded (or raised) in the keys' order once every bone has stopped."""
        from concurrent.futures import ThreadPoolExecutor, wait

        relay = _Relay(len(todo))
        futures = []
        cancelled = None
        with ThreadPoolExecutor(min(self.threads, len(todo)),
                                thread_name_prefix="bonewatertight") as pool:
            budget = _Budget(self.budget)
            for j, (_, k) in enumerate(todo):
                futures.append(pool.submit(budget.run, self.costs.get(k, 0.0), work, k,
                                           Progress(relay.callback(j))))
            pending = set(futures)
            while pending:
                finished, pending = wait(pending, timeout=RELAY_POLL_S)
                if not self.keep_going and any(
                        f.exception() is not None and not isinstance(f.exception(), CancelledError)
                        for f in finished):
                    relay.cancel()  # the run fails with this error: stop the other bones
                for fraction, message in relay.events():
                    if cancelled is not None:
                        break
                    try:
                        # the keys skipped (failed before) count as done
                        progress((slots - len(todo) + fraction * len(todo)) / slots, message)
                    except CancelledError as exc:
                        cancelled = exc
                        relay.cancel()
        if cancelled is not None:
            raise cancelled
        out = {}
        for (_, k), fut in zip(todo, futures):
            exc = fut.exception()
            if exc is None:
                out[k] = fut.result()
            elif not (isinstance(exc, CancelledError) and relay.stopped):
                self.fail(k, exc)
        return out


class _Budget:
    """Bones start only while the costs of those running fit the budget (one always may)."""

    def __init__(self, budget: float):
        self._budget = budget
        self._running = 0.0
        self._count = 0
        self._free = threading.Condition()

    def run(self, cost: float, work, *args):
        with self._free:
            self._free.wait_for(lambda: self._count == 0
                                or self._running + cost <= self._budget)
            self._running += cost
            self._count += 1
        try:
            return work(*args)
        finally:
            with self._free:
                self._running -= cost
                self._count -= 1
                self._free.notify_all()


class _Relay:
    """Progress of bones worked at once: each worker's callback queues its bone's fraction
    and message (and says stop once :meth:`cancel` was called); the calling thread takes
    them in order (:meth:`events`), each with the mean fraction over the bones by then."""

    def __init__(self, n: int):
        self._lock = threading.Lock()
        self._fractions = [0.0] * n
        self._queue: list = []
        self._message = ""
        self._stop = threading.Event()

    def callback(self, j: int):
        def report(fraction: float, message: str = ""):
            with self._lock:
                self._queue.append((j, fraction, message))
            return not self._stop.is_set()
        return report

    def events(self) -> list:
        """[(mean fraction, message)] of the reports since the last call, in order; when
        there were none, the current state once (so the caller still hears from the run)."""
        with self._lock:
            queue, self._queue = self._queue, []
        out = []
        for j, fraction, message in queue:
            self._fractions[j] = max(self._fractions[j], fraction)
            self._message = message or self._message
            out.append((sum(self._fractions) / len(self._fractions), self._message))
        return out or [(sum(self._fractions) / len(self._fractions), self._message)]

    def cancel(self) -> None:
        self._stop.set()

    @property
    def stopped(self) -> bool:
        return self._stop.is_set()


def reconstruct_many(ct: sitk.Image, labels: sitk.Image, targets: Sequence[int],
                     params: Optional[Parameters] = None,
                     progress: Optional[ProgressCallback] = None, *, neighbours="auto",
                     names: Optional[dict] = None, keep_going: bool = False) -> JointResult:
    """Reconstruct several bones of one segmentation together.

    Parameters
    ----------
    ct : SimpleITK.Image
        CT volume in HU, any orthonormal direction matrix. Not modified.
    labels : SimpleITK.Image
        Integer label map (0 = background), any geometry: every label is a bone. Not modified.
    targets : sequence of int
        Label values to reconstruct (each once).
    params : Parameters, optional
    progress : callable, optional
        callback(fraction, message); returning False cancels (CancelledError).
    neighbours : "auto", "none" or sequence of int
        Which other labels compete as neighbours: every other label (auto), none, or these.
    names : dict, optional
        Label value -> name, for reports and messages.
    keep_going : bool
        When a bone fails (its checks, its plausibility, its threshold windows), go on with the
        others: its result has ``error`` set and no surface (default: raise).

    Returns
    -------
    JointResult
        ``bones[i]`` for ``targets[i]``; ``pairs``: every pair of targets that succeeded,
        checked exactly.

    Raises
    ------
    InputError, ReconstructionError, SurfaceCheckError, PlausibilityError, CancelledError
    """
    t_all = time.perf_counter()
    run = _Run((params or Parameters()).validate(), Progress(progress), keep_going)
    run.stage("open3d")
    with timed(run.times, "import_open3d", run.spans):
        import_open3d()  # first: a missing dependency fails before minutes of work
    try:
        return _reconstruct_many(run, t_all, ct, labels, targets, neighbours, names)
    finally:
        if run.poisson_helper is not None:
            run.poisson_helper.close()


def _reconstruct_many(run: _Run, t_all: float, ct, labels, targets, neighbours,
                      names) -> JointResult:
    ws = prepare_stage(run, ct, labels, targets, neighbours, dict(names or {}))
    filter_stage(run, ws)
    threshold_stage(run, ws)
    ownership_stage(run, ws)
    run.threads, run.costs, run.budget = bone_schedule(ws, run.params.max_memory_gb)
    ws.prep.info["bone_threads"] = run.threads
    # Bones on two threads: their Poisson surfaces in a helper process where this process
    # allows one (open3d holds the GIL; see PoissonHelper) and the memory limit has room for
    # it beside the two largest bones (the bones' budget is then what it leaves). Started
    # now, its start-up (~1.5 s) overlaps the bones' threshold windows and visible points.
    top_two = sum(sorted(run.costs.values())[-2:])
    if (helper_processes_allowed() and min(run.threads, len(ws.targets)) > 1
            and run.budget - top_two >= _poisson.HELPER_MEMORY_GB * 1024 ** 3):
        run.budget -= _poisson.HELPER_MEMORY_GB * 1024 ** 3
        run.poisson_helper = _poisson.PoissonHelper()
    bones = run.each(ws.targets, run.stage("surfaces"),
                     lambda k, part: initial_surface_stage(run, ws, k, part))
    helper = run.poisson_helper
    ws.prep.info["poisson_process"] = \
        "helper" if helper is not None and helper.error is None else "this"
    if helper is not None:
        helper.close()  # every M0 is made
        if helper.error is not None:
            run.fallbacks.add("poisson", f"the Poisson helper process failed ({helper.error}): "
                              "the Poisson surfaces were computed in this process instead")
    territory_stage(run, ws, bones)
    deform_stage(run, ws, bones)
    release_grids(run, ws, bones)
    contact_stage(run, ws, bones)
    sub = run.stage("checks")
    done = run.each(ws.targets, sub, lambda k, part: finish_bone(run, ws, bones[k], part),
                    slots=len(ws.targets) + 1)
    results = [done[k] if k in done else _failed_result(ws, k, run.failed[k])
               for k in ws.targets]
    pairs = pair_stage(ws, results, keep_going=run.keep_going, min_gap=run.params.min_gap)
    run.times.total = time.perf_counter() - t_all
    spans = _stage_spans(run.spans, t_all, ws)
    for r in results:
        if r.ok:
            _shared_times(r.report.timings, run.times)
            r.report.stage_spans = [s for s in spans if s["label"] in (None, r.label)]
    report = JointReport(
        version=__version__, parameters=run.params.to_dict(), input=ws.prep.info,
        thresholds=ws.thresholds, ownership=_ownership_info(ws), pairs=pairs,
        timings=run.times, neighbours=[str(ws.names.get(v, v)) for v in ws.neighbour_values],
        fallbacks=list(run.fallbacks), stage_spans=spans)
    run.progress(1.0, "done")
    return JointResult(bones=results, pairs=pairs, report=report)


# ----------------------------------------------------------------------------------------
# the stages of reconstruct_many, in order

def prepare_stage(run: _Run, ct, labels, targets, neighbours, names: dict) -> Workspace:
    """Validate, crop and resample (stages.prepare), check the sizes, choose the neighbours."""
    params = run.params
    sub = run.stage("prepare")
    with timed(run.times, "prepare", run.spans):
        band_guess = max(params.segment_dilation, 3.0)
        prep = prepare_labels(ct, labels, targets, spacing=params.spacing, margin=params.margin,
                              band_mm=band_guess, max_memory_gb=params.max_memory_gb,
                              at_border=params.at_border, progress=sub)
        size_errors = size_problems(prep, params, names)
        if size_errors and not run.keep_going:
            raise next(iter(size_errors.values()))
        lab, neighbour_values = _select_neighbours(prep.labels, prep.values, prep.targets,
                                                   neighbours)
        band = max(params.segment_dilation, BAND_COARSENESS * prep.coarseness)
    coarsened = prep.info.get("spacing_coarsened_for_memory_from_mm")
    if coarsened is not None:
        run.fallbacks.add("prepare", f"automatic spacing {prep.grid.spacing:g} mm instead of the "
                          f"measured rule's {coarsened:g} mm, to fit max_memory_gb = "
                          f"{params.max_memory_gb:g}", 1, "grid")
    run.failed.update(size_errors)
    return Workspace(prep=prep, labels=lab, neighbour_values=neighbour_values, names=names,
                     band=band)


def filter_stage(run: _Run, ws: Workspace) -> None:
    """The hybrid filter (paper §2.1), its percentile taken near the targets."""
    params = run.params
    run.stage("filter")
    with timed(run.times, "filter", run.spans):
        d = ws.d
        near = _threshold.dilate6(np.isin(ws.labels, ws.targets),
                                  max(1, int(round(FILTER_REGION_MM / d))))
        ws.ct_f = hybrid_filter(ws.prep.ct, d, sigma=params.sigma, rho=params.rho, region=near)


def threshold_stage(run: _Run, ws: Workspace) -> None:
    """H0 and HT (given, or estimated from the CT on its own grid), the tissue levels, and a
    failure for each target with no voxel in [HT, theta_max]."""
    params = run.params
    run.stage("thresholds")
    with timed(run.times, "thresholds", run.spans):
        _estimate_thresholds(run, ws)


def _estimate_thresholds(run: _Run, ws: Workspace) -> None:
    """threshold_stage's work: ``ws.h0``, ``ws.ht``, ``ws.thresholds``, the targets' check."""
    params = run.params
    prep = ws.prep
    nct, nlab, nsp = prep.native
    values = [prep.values[t - 1] for t in prep.targets]
    c = prep.coarseness
    estimate = auto_thresholds(nct, nlab, values, nsp, c, params.theta_max, run.fallbacks) \
        if (params.h0 is None or params.ht is None) else None
    h0 = params.h0 if params.h0 is not None else estimate["h0"]
    ht = params.ht if params.ht is not None else estimate["ht"]
    if estimate is not None:
        # an explicit value must stay in order with the estimated one
        h0 = max(h0, ht + _auto.H0_MIN_ABOVE_HT) if params.h0 is None else h0
        ht = min(ht, h0 - _auto.H0_MIN_ABOVE_HT) if params.ht is None else ht
    params.check_thresholds(h0, ht)
    if estimate is not None:
        soft, cortex = estimate["soft_tissue"], estimate["cortex"]
    else:
        soft, cortex = _auto.tissue_levels(nct, np.isin(nlab, values), nlab > 0, nsp, c,
                                           run.fallbacks)
    ws.h0, ws.ht = h0, ht
    ws.thresholds = {"h0": float(h0), "ht": float(ht), "theta_max": float(params.theta_max),
                     "h0_auto": params.h0 is None, "ht_auto": params.ht is None,
                     "soft_tissue_hu": float(soft), "cortex_hu": float(cortex)}
    for t in prep.targets:
        seg = ws.labels == t
        window = (ws.ct_f[seg] >= ht) & (ws.ct_f[seg] <= params.theta_max)
        if not window.any():
            run.fail(t, _threshold_error(ws.name_of(t), ht, params.theta_max, ws.ct_f[seg]))


def ownership_stage(run: _Run, ws: Workspace) -> None:
    """Which voxels belong to which bone (stages.ownership)."""
    params = run.params
    sub = run.stage("ownership")
    with timed(run.times, "ownership", run.spans):
        th = ws.thresholds
        ws.own = compute_ownership(
            ws.ct_f, ws.labels, len(ws.prep.values), ws.d, h0=ws.h0, ht=ws.ht,
            theta_max=params.theta_max, soft=th["soft_tissue_hu"],
            contrast=max(th["cortex_hu"] - th["soft_tissue_hu"], 1.0),
            coarseness=ws.prep.coarseness, band_mm=ws.band,
            ct_resolution=float(np.prod(ws.prep.ct_spacing)) ** (1.0 / 3.0), progress=sub)
        if ws.own.labels is not None:
            # The segment as the CT corrected it (a copy): every later stage and the gate
            # judge each bone against it.
            ws.labels = ws.own.labels
            ws.own.labels = None


def bone_schedule(ws: Workspace, max_memory_gb: float) -> tuple:
    """(threads, costs, budget) for the per-bone stages: one thread per CPU up to
    MAX_BONE_THREADS; a bone's cost is the memory estimate's bytes per voxel over its box
    (prepare.BYTES_PER_VOXEL, all included, so an upper bound); the budget is what
    ``max_memory_gb`` leaves beside what the process holds now. Bones run at once only while
    their costs fit the budget (one always runs)."""
    threads = min(os.cpu_count() or 1, MAX_BONE_THREADS, len(ws.targets))
    costs = {k: float(np.prod([s.stop - s.start for s in sl])) * _prepare.BYTES_PER_VOXEL
             for k, (sl, _) in ws.own.regions.items() if k in ws.targets}
    held = _held_bytes()
    if held is None:  # no measure of the process: the run's own estimate
        held = float(ws.prep.info.get("estimated_memory_gb") or 0.0) * 1024 ** 3
    return max(threads, 1), costs, max_memory_gb * 1024 ** 3 - held


def _held_bytes() -> Optional[float]:
    """The process's resident memory (bytes) now (Linux) or its peak so far (other Unix);
    None where neither is available."""
    try:
        with open("/proc/self/statm") as fh:
            return float(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        pass
    try:
        import resource

        peak = float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
        return peak if sys.platform == "darwin" else peak * 1024.0  # bytes on macOS, KB else
    except (ImportError, OSError):
        return None


def initial_surface_stage(run: _Run, ws: Workspace, k: int, progress: Progress) -> BoneWork:
    """Bone k's threshold windows (§2.1), visible points (eq. 1) and M0 (§2.3)."""
    bone = BoneWork(k=k, name=ws.name_of(k))
    threshold_windows(run, ws, bone)
    progress(0.2, f"{bone.name}: visible points")
    with timed(bone.times, "visible", run.spans, k):
        local = visible_points_of(run, ws, bone, progress.stage(0.2, 0.5))
    progress(0.5, f"{bone.name}: Poisson surface M0")
    with timed(bone.times, "poisson", run.spans, k):
        poisson_m0(run, ws, bone, local)
    progress(1.0, f"{bone.name}: M0 done")
    bone.others_distance = _others_distance(ws, bone)
    return bone


def threshold_windows(run: _Run, ws: Workspace, bone: BoneWork) -> None:
    """W_H0 and W_HT of the bone's owned voxels, and the paper's separation test."""
    params, own, d = run.params, ws.own, ws.d
    # Unlabelled bone taken in by the merge's special cases (ownership.merged_unlabelled).
    for flag, what, why in (
            ("thin_plate_beyond_reach", "a thin plate of unlabelled bone beyond the segment's "
             "reach but inside its span, continuing this bone without a joint space,",
             "the segment missed it"),
            ("small_piece_beyond_reach", "a small piece of unlabelled bone beyond the segment's "
             "reach, touching only this bone and without a joint space,",
             "the segment stopped short of a process"),
            ("beside_a_joint_space", "unlabelled bone on this bone's side of a seen joint "
             "space, with part of a joint space toward this bone too,",
             "counted as unlabelled bone by the plausibility gate")):
        taken = [m for m in own.info.get("merged_unlabelled", ())
                 if m.get(flag) and m["into"] == bone.k]
        if taken:
            bone.fallbacks.add("ownership", f"{what} was taken in as this bone's "
                               f"({sum(m['ml'] for m in taken):.2f} ml; {why})", len(taken),
                               "pieces")
    with timed(bone.times, "threshold", run.spans, bone.k):
        bone.masks = bone_masks(ws.ct_f, own.owner, own.cores, ws.labels, bone.k, d, h0=ws.h0,
                                theta_max=params.theta_max, coarseness=ws.prep.coarseness,
                                opening=params.opening, closing=params.closing,
                                unsupported=own.unsupported, fallbacks=bone.fallbacks,
                                foreground=own.foreground)
        step_voxels = max(1, int(round(min(ws.prep.ct_spacing) / d)))
        bone.separation = erosions_to_separate(ws.ct_f, own.owner, bone.k, d, h0=ws.h0,
                                               theta_max=params.theta_max,
                                               step_voxels=step_voxels,
                                               max_erosions=params.max_erosions)
        thin_plates(run, ws, bone)


def thin_plates(run: _Run, ws: Workspace, bone: BoneWork) -> None:
    """Plates thinner than the CT resolves (stages.plates) join the bone as slabs of the
    model's thickness: in the visible-point candidates and the deformation's inside test
    (here), in M0 (fused by poisson_m0) and as the edge refinement's targets."""
    masks, d, own, k = bone.masks, ws.d, ws.own, bone.k
    soft, cortex = ws.thresholds["soft_tissue_hu"], ws.thresholds["cortex_hu"]
    sl, reg = own.regions[k]
    region = np.zeros(ws.labels.shape, bool)
    region[sl] = reg
    box = masks.box
    # Inside or right along the segment (within half its coarseness), not another bone's.
    along = _threshold.dilate6(ws.labels[box] == k,
                               max(1, int(round(0.5 * ws.prep.coarseness / d))))
    region = region[box] & along & ((own.owner[box] == 0) | (own.owner[box] == k))
    t_min = _plate_min_thickness(run.params, d)
    resolved = _threshold.erode6(masks.occupancy, max(1, int(round(0.5 * t_min / d))))
    # A ridge as high as the label level always counts; fainter ones where the noise allows.
    # The smoothed CT is kept for M0's plate holes (_plate_holes: the same box and scale).
    bone.plate_ct = _plates.smooth_ct(ws.prep.ct[box], d, ws.prep.ct_spacing)
    bone.plates = _plates.find_plates(
        ws.prep.ct[box], region, masks.w_ht, resolved, d, native_spacing=ws.prep.ct_spacing,
        soft=soft, cortex=cortex,
        max_contrast=_ownership.LABEL_LEVEL_FRACTION * (ws.ht - soft), min_thickness=t_min,
        origin=masks.origin, smoothed=bone.plate_ct)
    if bone.plates.n:
        slab = bone.plates.mask(masks.w_ht.shape, masks.origin)
        masks.w_ht |= slab
        masks.far |= slab & ~masks.w_h0
        masks.solid_h0 |= slab
        masks.occupancy |= slab
        masks.info["voxels_plate"] = int(slab.sum())
    segment_processes(run, ws, bone)


def segment_processes(run: _Run, ws: Workspace, bone: BoneWork) -> None:
    """Thin processes of the segment beyond the thresholded bone that the CT shows as a faint
    bright structure (stages.plates.segment_processes) join the bone's masks as the plates do,
    as label-only bone (the segment gives their shape)."""
    masks, d, k = bone.masks, ws.d, bone.k
    box = masks.box
    label = _trusted_segment(ws, k, box)
    planes = ws.prep.caps.get(k, [])
    if planes:
        label &= _plaus.image_mask(box, planes, d)
    soft = ws.thresholds["soft_tissue_hu"]
    max_contrast = _ownership.LABEL_LEVEL_FRACTION * (ws.ht - soft)
    min_contrast = bone.plates.info.get("min_contrast_hu")
    if min_contrast is None:
        noise = _plates.soft_tissue_noise(bone.plate_ct, label | masks.w_ht, soft)
        min_contrast = min(max_contrast, _plates.PLATE_NOISE_FACTOR * noise)
    procs, records = _plates.segment_processes(
        label, masks.occupancy, bone.plate_ct, d,
        reach_mm=_plaus.reach_bound_mm(ws.prep.coarseness), margin_mm=ws.prep.coarseness,
        soft=soft, min_contrast=float(min_contrast))
    masks.info["segment_processes"] = records
    if procs.any():
        bone.processes = procs
        masks.w_ht |= procs
        masks.far |= procs & ~masks.w_h0
        masks.solid_h0 |= procs
        masks.occupancy |= procs
        masks.info["voxels_process"] = int(procs.sum())
        joined = [r for r in records if r["joined"]]
        where = "; ".join(_lps_text(ws.prep.grid, np.asarray(r["at"]) + masks.origin)
                          for r in joined[:3])
        bone.fallbacks.add("threshold", "thin processes of the segment reaching up to "
                           f"{max(r['reach_mm'] for r in joined):.0f} mm beyond the thresholded "
                           "bone, which the CT shows brighter than the tissue around them but "
                           "below HT (a tail or a tip thinner than the CT resolves), were joined "
                           f"with the segment's shape ({float(procs.sum()) * d ** 3:.0f} mm^3)",
                           len(joined), "processes", where)


def _trusted_segment(ws: Workspace, k: int, box: tuple) -> np.ndarray:
    """Bone k's segment on ``box`` (slices of the working grid) as far as it is evidence:
    not given to another bone, not a part the CT shows as soft tissue. (z, y, x) bool."""
    own = ws.own
    trusted = (ws.labels[box] == k) & ((own.owner[box] == 0) | (own.owner[box] == k))
    if own.unsupported is not None:
        trusted &= ~own.unsupported[box]
    return trusted


def _lps_text(grid, point_grid_mm: np.ndarray) -> str:
    """'LPS (x, y, z)' of a point of the working grid (x, y, z mm), for a message."""
    return _lps_of(grid.grid_to_physical(np.asarray(point_grid_mm, np.float64)[None, :])[0])


def _lps_of(p: np.ndarray) -> str:
    """'LPS (x, y, z)' of a physical (LPS mm) point, for a message."""
    return f"LPS ({p[0]:.0f}, {p[1]:.0f}, {p[2]:.0f})"


def _left_out_warning(name: str, fusion, grid, origin: np.ndarray, phys: np.ndarray,
                      faces: np.ndarray, planes=()) -> list:
    """A warning when bone that M0 left out (joining it added a tunnel, see
    poisson.remesh) lies outside the finished surface by more than LEFT_OUT_WARN_MM at its
    farthest point: the surface stops short of bone the CT shows (a thin process or the tip of
    a plate cut off). ``fusion``: M0's (poisson.Fusion, or None); ``grid``: the working grid;
    ``origin``: the bone box's origin (x, y, z grid mm); ``phys``: the surface's vertices (n, 3)
    in LPS mm; ``faces`` (m, 3); ``planes``: the cap planes (prepare.CapPlane) - beyond them
    the grid continues the image's border, which shows no bone of its own."""
    if fusion is None or fusion.dropped_far is None:
        return []
    at = np.asarray(fusion.dropped_far, np.float64) + origin
    if any((at[p.axis] - p.position) * p.side > 0 for p in planes):
        return []
    far = grid.grid_to_physical(at[None, :])
    gap = float(cKDTree(phys).query(far)[0][0])
    if gap <= LEFT_OUT_WARN_MM or _inside(phys, faces, far[0]):
        return []
    return [f"{name}: bone the CT shows ({fusion.info['join_dropped_mm3'] / 1000:.2f} ml, "
            f"thresholded) lies up to {gap:.1f} mm outside the surface near "
            f"{_lps_text(grid, at)}: it was left out because joining it added a tunnel (the lace "
            "of a thin plate, or a process on a thread), so the surface stops short of it there. "
            "Check the surface against the CT there"]


def _missed_edge_warning(name: str, grid, constraints: np.ndarray, phys: np.ndarray,
                         faces: np.ndarray, d: float, planes=()) -> list:
    """A warning when the bone's own CT edge lies outside the finished surface by more than
    MISSED_EDGE_WARN_MM over a patch at least that wide: the surface stops short of bone the
    thresholds hold (a faint tip, crest or plate that M0 did not reach and the deformation's
    search radius could not pull it to).

    ``constraints``: the deformation's targets (the visible H0 and the HT boundary points of
    the bone's territory, (k, 3) grid mm); ``phys``, ``faces``: the outward surface in LPS mm;
    ``d``: the working grid's step (a boundary point stands for about d^2 of edge);
    ``planes``: the cap planes - beyond them the grid continues the image's border slice."""
    if not len(constraints):
        return []
    keep = np.ones(len(constraints), bool)
    for p in planes:
        keep &= (constraints[:, p.axis] - p.position) * p.side <= 0
    constraints = constraints[keep]
    points = grid.grid_to_physical(constraints)
    gap, near = cKDTree(phys).query(points, workers=-1)
    far = np.flatnonzero(gap > MISSED_EDGE_WARN_MM)
    if not len(far):
        return []
    normals = _operators.vertex_normals(phys, faces)
    # Outside: on the outer side of the nearest vertex (a point that far from the surface
    # lies well off its tangent plane); the farthest point is checked exactly below.
    far = far[np.einsum("ij,ij->i", points[far] - phys[near[far]], normals[near[far]]) > 0]
    if not len(far):
        return []
    constraints, points, gap = constraints[far], points[far], gap[far]
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    pairs = cKDTree(points).query_pairs(2.0 * d, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                       shape=(len(points), len(points)))
    _, patch = connected_components(graph, directed=False)
    best = None
    for c in np.unique(patch):
        sel = np.flatnonzero(patch == c)
        area = len(np.unique(np.floor(points[sel] / d).astype(np.int64), axis=0)) * d * d
        top = sel[np.argmax(gap[sel])]
        if area >= MISSED_EDGE_WARN_MM ** 2 and (best is None or gap[top] > gap[best[1]]):
            best = (area, top)
    if best is None or _inside(phys, faces, points[best[1]]):
        return []
    area, top = best
    return [f"{name}: the CT shows this bone's edge (thresholded) up to {gap[top]:.1f} mm outside "
            f"the surface over about {area:.0f} mm^2 near {_lps_text(grid, constraints[top])}: a "
            "faint tip, crest or plate that the surface stops short of. Check the surface against "
            "the CT there; a segment that covers it, or a finer CT, helps"]


def _plate_holes(ws: Workspace, bone: BoneWork, m0: Surface) -> dict:
    """stages.plates.holes_across_plates of M0 (``m0``: vertices in the masks' box millimetres;
    its tunnels are the finished surface's, as every later stage moves vertices only): its
    tunnels through which the CT shows a thin plate; plug centres and ``mask`` on the box."""
    genus = _poisson.surface_genus(m0)
    if genus <= 0:
        return {"tunnels": 0, "plugs": []}
    from .mesh.surface import inside_mask

    k, own, masks, d = bone.k, ws.own, bone.masks, ws.d
    box = masks.box
    inside = inside_mask(m0, tuple(s.stop - s.start for s in box), d)
    soft = ws.thresholds["soft_tissue_hu"]
    exclude = ((own.owner[box] > 0) & (own.owner[box] != k)) \
        | ~_plaus.image_mask(box, ws.prep.caps.get(k, []), d)
    return _plates.holes_across_plates(
        inside, ws.prep.ct[box], d, native_spacing=ws.prep.ct_spacing, soft=soft,
        cortex=ws.thresholds["cortex_hu"],
        max_contrast=_ownership.LABEL_LEVEL_FRACTION * (ws.ht - soft), exclude=exclude,
        surface_genus=int(genus),
        noise=(bone.plates.info.get("noise_hu") if bone.plates is not None else None),
        smoothed=bone.plate_ct)


def _mask_field(mask: np.ndarray, d: float, shape: tuple, lo, h: float) -> np.ndarray:
    """A (z, y, x) bool ``mask`` on a grid of step ``d`` from the origin, as a [0, 1] occupancy
    on the grid of ``shape`` and step ``h`` whose voxel (0, 0, 0) is at ``lo`` (x, y, z mm):
    trilinear, so its 0.5 level is the mask's boundary; 0 beyond the mask's box."""
    out = np.zeros(shape, np.float32)
    at = np.argwhere(mask)
    if not len(at):
        return out
    lo = np.asarray(lo, np.float64)
    first = np.maximum(np.floor(((at.min(axis=0)[::-1] - 1) * d - lo) / h), 0).astype(int)
    last = np.minimum(np.ceil(((at.max(axis=0)[::-1] + 1) * d - lo) / h),
                      np.array(shape[::-1]) - 1).astype(int)
    if np.any(last < first):
        return out
    axes = [lo[i] + h * np.arange(first[i], last[i] + 1) for i in range(3)]  # x, y, z mm
    zz, yy, xx = np.meshgrid(axes[2] / d, axes[1] / d, axes[0] / d, indexing="ij")
    vals = ndimage.map_coordinates(mask.astype(np.float32), [zz, yy, xx], order=1, cval=0.0)
    out[first[2]:last[2] + 1, first[1]:last[1] + 1, first[0]:last[0] + 1] = vals
    return out


def _inside(vertices: np.ndarray, faces: np.ndarray, point: np.ndarray) -> bool:
    """Is ``point`` (3,) inside the closed surface (vertices (n, 3), faces (m, 3))?"""
    from .mesh.surface import inside_mask

    return bool(inside_mask(Surface(vertices, faces), (1, 1, 1), 1.0, point)[0, 0, 0])


def _plate_min_thickness(params: Parameters, d: float) -> float:
    """t_min (mm): the thinnest slab the working grid and M0's remeshing grid resolve."""
    edge = params.edge_length if params.edge_length is not None else d
    return _plates.PLATE_MIN_STEPS * max(d, edge / _poisson.REMESH_EDGE_RATIO)


def visible_points_of(run: _Run, ws: Workspace, bone: BoneWork,
                      progress: Progress) -> np.ndarray:
    """The visible points of W_H0 (eq. 1) and B*'s HT part; returns Poisson's input, the
    thinned visible points, in the masks' box coordinates (grid mm - ``masks.origin``)."""
    params, masks, d = run.params, bone.masks, ws.d
    # The hyper-spherical mapping sees W_H0's own boundary (inner walls of cavities and pores
    # included: eq. (1) hides them), joined by the low-density bone out of reach of W_H0.
    candidates = voxel_points(boundary_voxels(masks.w_h0 | masks.far), d)
    if len(candidates) < 10:
        raise ReconstructionError(
            f"Almost nothing of {bone.name} is in the threshold windows ({len(candidates)} "
            "boundary points): lower H0/HT or leave them on auto, and check the segment.")
    vis_idx, bone.vis_info, every = visible_points(
        candidates, d, views=params.views, view_distance=params.view_distance,
        log_radius=params.log_radius, progress=progress, full=True)
    bone.n_candidates = len(candidates)
    bone.visible = candidates[vis_idx] + masks.origin       # Poisson's input: thinned
    bone.visible_all = candidates[every] + masks.origin     # S(P_H0) of B*: all of them
    # B* = S(P_H0) U (P_HT - P_H0); of P_HT - P_H0 only the outer boundary can be reached by
    # the directional search, placed sub-voxel where the CT crosses HT.
    b_ht, crossed = crossing_points(ws.ct_f[masks.box], masks.occupancy, ws.ht, d, crossed=True)
    # Of P_HT - P_H0 the deformation needs the bone that W_H0 misses (low-density bone, a
    # cortex below H0): HT crossings more than HT_BEYOND_H0_MM beyond W_H0. Nearer ones are the
    # partial-volume foot of dense cortex, which would only pull the surface outward.
    if len(b_ht):
        from .mesh.distance import distance_outside

        gap_to_h0 = distance_outside(masks.w_h0) * d
        keep = sample_field(gap_to_h0, b_ht, d) > HT_BEYOND_H0_MM
        b_ht, crossed = b_ht[keep], crossed[keep]
    if not crossed.all():
        bone.fallbacks.add("visible", "HT points of B* where the CT does not cross HT between "
                           "the boundary voxel and its outside neighbour: placed mid-edge "
                           "(t = 0.5)", int((~crossed).sum()), "points")
    bone.b_ht = b_ht + masks.origin
    return candidates[vis_idx]


def poisson_m0(run: _Run, ws: Workspace, bone: BoneWork, points: np.ndarray) -> None:
    """M0: screened Poisson of the visible ``points`` (box coordinates), remeshed closed at
    edge length d*."""
    params, d, masks, own, k = run.params, ws.d, bone.masks, ws.own, bone.k
    origin = masks.origin
    edge = params.edge_length if params.edge_length is not None else d
    # M0 joins what Poisson at depth <= 7 cannot resolve (a plate of a few voxels in a long
    # bone) and, where it then has tunnels its segment does not have, the segment (box
    # coordinates).
    trusted = _trusted_segment(ws, k, masks.box)
    # The segment's tunnels counted at its own resolution (its stair steps and holes smaller
    # than that are no tunnels of the bone: plausibility.segment_genus), on a thread beside the
    # normals and the carved region, which do not depend on it. The carve: where neither the
    # CT nor the segment has bone, M0 has none either (Poisson closes over what the views do
    # not see into: a curved canal, a deep notch).
    ct_box = ws.ct_f[masks.box]

    def part(i):
        if i == 0:
            return _plaus.segment_genus(trusted, d, ws.prep.coarseness)
        bone_ct = masks.occupancy | masks.w_ht | masks.w_h0
        lumen = ct_box < own.info["label_level_hu"]
        if bone.processes is not None:
            # A thin process joined from the segment is darker than the label level but no
            # lumen: the carve's soft edge beside it would shave it to a thread.
            lumen &= ~_threshold.dilate_cube(
                bone.processes, int(np.ceil((CARVE_BONE_MM + d) / d)))
        return mask_normals(masks.solid_h0, points, d), _poisson.carve_region(
            trusted, bone_ct, d,
            segment_margin_mm=CARVE_SEGMENT_COARSENESS * ws.prep.coarseness + d,
            bone_margin_mm=CARVE_BONE_MM + d, soft_tissue=lumen)

    genus, (normals, carve) = thread_map(part, range(2), cpu_threads(2), "m0-inputs")
    # The fill takes its material from the segment itself (smoothing would thin its thin parts
    # away); tunnels it cannot close, the thresholded bone may (W_HT holds W_H0 and the thin
    # plates).
    # A thin process of the bone's own (a sacral tip at 3 mm) that Poisson at depth 7
    # detaches as a small component is joined back from the bone the thresholds hold -
    # inside the image: beyond a cap plane the grid only continues the border slice.
    planes = ws.prep.caps.get(bone.k, [])
    plates = bone.plates

    def new_fusion(plugs=None):
        """M0's evidence; ``plugs`` (box mask): plates across tunnels, fused as the slabs are."""
        fusion = _poisson.Fusion(label=trusted, label_origin=np.zeros(3), label_spacing=d,
                                 genus=genus, close_mm=(ws.prep.coarseness,), bone=masks.w_ht,
                                 carve=carve,
                                 strong=(ct_box >= ws.h0) & (ct_box <= params.theta_max))
        fusion.solid = (masks.occupancy & _plaus.image_mask(masks.box, planes, d) if planes
                        else masks.occupancy)
        fusion.solid_reach_mm = ws.prep.coarseness
        fields, boxes = [], []
        if plates is not None and plates.n:
            fields.append(lambda shape, lo, h: plates.field(shape, np.asarray(lo) + origin, h))
            boxes.append((plates.points.min(axis=0) - origin, plates.points.max(axis=0) - origin))
        if plugs is not None:
            fields.append(lambda shape, lo, h: _mask_field(plugs, d, shape, lo, h))
            at = np.argwhere(plugs)[:, ::-1] * d
            boxes.append((at.min(axis=0) - d, at.max(axis=0) + d))
        if fields:
            fusion.plates = fields[0] if len(fields) == 1 else \
                (lambda shape, lo, h: np.maximum.reduce([f(shape, lo, h) for f in fields]))
            fusion.plates_box = (np.min([b[0] for b in boxes], axis=0),
                                 np.max([b[1] for b in boxes], axis=0))
        return fusion

    fusion = new_fusion()
    m0, raw = initial_surface(points, normals, params.poisson_depth, edge, fusion=fusion,
                              helper=run.poisson_helper)
    # M0's tunnels through a plate the CT shows across them (a wall the opening thinned away,
    # a plate below the thresholds): remeshed once more with the plates' plugs fused, kept
    # when that closes them.
    holes = _plate_holes(ws, bone, m0)
    plugs = holes.pop("mask", None)
    if plugs is not None:
        retry = new_fusion(plugs)
        again = _poisson.remesh(raw, edge, fusion=retry)
        closed = max(0, _poisson.surface_genus(m0) - _poisson.surface_genus(again))
        where = "; ".join(_lps_text(ws.prep.grid, np.asarray(p["centre"]) + origin)
                          for p in holes["plugs"][:3])
        if closed:
            m0, fusion = again, retry
            bone.fallbacks.add("poisson", "tunnels of M0 through a thin plate that the CT shows "
                               "across them (a ridge above the soft tissue that the thresholds "
                               "or the opening lost) were closed with the plate's crest "
                               f"({float(plugs.sum()) * d ** 3:.0f} mm^3)", closed, "tunnels",
                               where)
        holes["closed"] = int(closed)
        holes["tunnels"] = max(0, holes["tunnels"] - closed)
        if holes["tunnels"]:
            # (measured: sacral foramina whose blurred content reads as a faint ridge, which
            # the remeshing with M0's other evidence leaves open)
            bone.fallbacks.add("poisson", "tunnels of M0 across which the CT shows a faint ridge "
                               "stay open: remeshed with the ridge's plug, M0 kept them (its "
                               "other evidence has no bone there; a foramen the slices blur, or "
                               "a hole in a plate)", holes["tunnels"], "tunnels", where)
    bone.plate_holes = holes
    bone.plate_ct = None
    if fusion.info.get("joined_pieces"):
        bone.fallbacks.add("poisson", "bone the thresholds hold that the Poisson surface missed "
                           f"by more than {fusion.solid_reach_mm:g} mm (a thin process it "
                           "detached, or thinned to a thread the remeshing cuts) was joined to M0 "
                           f"({fusion.info['joined_bone_mm3']:.0f} mm^3)",
                           int(fusion.info["joined_pieces"]), "pieces")
    if fusion.info.get("join_dropped_mm3"):
        bone.fallbacks.add("poisson", "bone the thresholds hold that the Poisson surface missed "
                           f"by more than {fusion.solid_reach_mm:g} mm was left out: joining it to "
                           "M0 added a tunnel (the lace of a thin plate, or a process on a "
                           f"thread); it reaches {fusion.info['join_dropped_reach_mm']:.1f} mm "
                           "beyond M0", int(round(fusion.info["join_dropped_mm3"])), "mm^3",
                           _lps_text(ws.prep.grid, fusion.dropped_far + origin))
    if fusion.info.get("narrow_plugs"):
        bone.fallbacks.add("poisson", "tunnels narrower than the CT resolves (closed by a ball of "
                           f"{fusion.info['narrow_radius_mm']:.2f} mm at most), which the "
                           "segment does not have, were closed "
                           f"({fusion.info['narrow_fill_mm3']:.0f} mm^3; evidence: label only)",
                           int(fusion.info["narrow_plugs"]), "tunnels")
    if fusion.info.get("smoothing_backed_off"):
        kept = ("the unsmoothed contour was kept" if fusion.info.get("smoothing_dropped")
                else "those vertices were put back toward the unsmoothed contour")
        bone.fallbacks.add("poisson", "the smoothing of M0's contour made it pass through itself "
                           f"(a narrow canal or two close sheets): {kept}",
                           int(fusion.info["smoothing_backed_off"]), "vertices")
    bone.fusion = fusion
    bone.m0 = Surface(m0.vertices + origin, m0.faces)
    bone.raw_vertices = raw.n_vertices
    bone.vertices = bone.m0.vertices.copy()


def _others_distance(ws: Workspace, bone: BoneWork) -> Optional[np.ndarray]:
    """Distance (mm, float32, on the masks' box) to the voxels other bones own: where the
    bone touches another no CT edge is expected (see refine_stage)."""
    box = bone.masks.box
    owner = ws.own.owner[box]
    others = (owner > 0) & (owner != bone.k)
    if not others.any():
        return None
    dist, f = _threshold.coarse_distance(others, ws.d)
    idx = [np.minimum(np.arange(n) // f, dist.shape[a] - 1) for a, n in enumerate(others.shape)]
    return dist[np.ix_(*idx)].astype(np.float32)


def territory_stage(run: _Run, ws: Workspace, bones: dict) -> None:
    """The midway surfaces between bones, from the M0s (stages.contacts.territories)."""
    run.stage("territories")
    with timed(run.times, "territories", run.spans):
        ws.fixed = _fixed_masks(ws.own, ws.labels, ws.targets, len(ws.prep.values))
        if len(bones) > 1 or ws.fixed:
            ws.territories = _contacts.territories(
                {k: (b.m0.vertices, b.m0.faces) for k, b in bones.items()}, ws.fixed,
                ws.labels.shape, ws.d, threads=run.threads)


def _refine_field(ws: Workspace) -> None:
    """The refinement's smoothed CT (``ws.ct_smooth`` on steps ``ws.ct_smooth_d``)."""
    steps = tuple(ws.prep.refine_spacing) or (ws.d,) * 3
    if min(steps) < ws.d:
        # A finer grid of its own, made from the crop on the CT's grid once the working
        # grid's CT volumes are gone, and smoothed in place.
        ws.ct_f = ws.prep.ct = None
        release_free_memory()
        field = _prepare.refine_ct(ws.prep)
        sigma = [max(REFINE_SIGMA_MIN_VOXELS, REFINE_SIGMA_MM / st) for st in steps[::-1]]
        ws.ct_smooth = ndimage.gaussian_filter(field, sigma=sigma, mode="nearest",
                                               output=field)
        ws.ct_smooth_d = steps
        del field
    else:
        ws.ct_smooth = ndimage.gaussian_filter(
            ws.prep.ct, sigma=max(REFINE_SIGMA_MIN_VOXELS, REFINE_SIGMA_MM / ws.d),
            mode="nearest")
        ws.ct_smooth_d = ws.d


def deform_stage(run: _Run, ws: Workspace, bones: dict) -> None:
    """Per bone: the deformation (eq. 15) and the edge refinement, never toward another
    bone's side of a joint."""
    params = run.params
    sub = run.stage("deform")
    if params.refine_edges:
        with timed(run.times, "refine_field", run.spans):
            _refine_field(ws)
    # No later stage reads the resampled or the filtered CT, or the crop on the CT's own grid.
    ws.ct_f = ws.prep.ct = ws.prep.native = None

    def allowed_of(k):
        return _contacts.allowed_test(ws.territories.get(k), ws.d, params.min_gap)

    def shape(k, part):
        bone = bones[k]
        with timed(bone.times, "deform", run.spans, k):
            deform(run, ws, bone, allowed_of(k), part.stage(0.0, 0.9 if several else 0.6))
            if several:
                # The contrast this bone's cortex shows, for the run's shared reference.
                # (Its profiles are the refinement's first ones: kept for it.)
                bone.profiles = _refine.sample_profiles(bone.vertices, bone.faces,
                                                        ws.ct_smooth, ws.ct_smooth_d)
                bone.own_reference = _refine.contrast_reference(
                    bone.vertices, bone.faces, ws.ct_smooth, ws.ct_smooth_d, ws.ht,
                    profiles=bone.profiles, peak_max=params.theta_max)
        if params.refine_edges and not several:
            with timed(bone.times, "refine", run.spans, k):
                refine(run, ws, bone, allowed_of(k), part.stage(0.6, 1.0))

    # Several bones: all are deformed first, so that each is refined against the full
    # cortical contrast of the thickest cortex among them (refine.full_contrast).
    several = params.refine_edges and len(ws.targets) > 1
    run.each(ws.targets, sub.stage(0.0, 0.5 if several else 1.0), shape)
    if several:
        refs = {k: b.own_reference for k, b in bones.items()
                if k not in run.failed and np.isfinite(b.own_reference)}
        if refs:
            ws.shared_reference_from = max(refs, key=refs.get)
            ws.shared_reference = float(refs[ws.shared_reference_from])

        def edges(k, part):
            with timed(bones[k].times, "refine", run.spans, k):
                refine(run, ws, bones[k], allowed_of(k), part)

        run.each([k for k in ws.targets if k in bones and k not in run.failed],
                 sub.stage(0.5, 1.0), edges)
    for k in [k for k in bones if k in run.failed]:
        del bones[k]


def deform(run: _Run, ws: Workspace, bone: BoneWork, allowed, progress: Progress) -> None:
    """The paper's deformation of M0 toward B* (stages.deform)."""
    params, d, masks, m0 = run.params, ws.d, bone.masks, bone.m0
    origin = masks.origin
    constraints = np.vstack([bone.visible_all, bone.b_ht])
    if allowed is not None:
        constraints = constraints[allowed(constraints)]
    bone.constraints = constraints
    verts = m0.vertices.copy()
    if params.iterations > 0 and len(constraints):
        occ = ndimage.gaussian_filter(masks.occupancy.astype(np.float32),
                                      sigma=OCCUPANCY_SIGMA_VOXELS)
        deformer = Deformer(m0.vertices - origin, m0.faces, constraints - origin,
                            lambda p: sample_field(occ, p, d) >= OCCUPANCY_LEVEL,
                            mean_edge_length(m0.vertices, m0.faces),
                            iterations=params.iterations, alpha=params.alpha, beta=params.beta,
                            search_radius=params.search_radius,
                            search_offset=params.search_offset, fallbacks=bone.fallbacks)
        verts = deformer.run(progress=progress) + origin
        bone.history = deformer.history
    elif params.iterations > 0:
        bone.fallbacks.add("deform", "no constraint point on the bone's side of its joints: "
                           "M0 is kept undeformed", params.iterations, "iterations")
    bone.deformed = verts
    bone.vertices = verts


def _release_between_steps(ws: Workspace) -> None:
    """Free heap back to the system inside one bone's work - for a run of one bone only: with
    several, on threads, it returns what the other bones are about to reuse, and their pages
    come back zeroed (time spent for memory no target bounds)."""
    if len(ws.targets) == 1:
        release_free_memory()


def refine(run: _Run, ws: Workspace, bone: BoneWork, allowed, progress: Progress) -> None:
    """Our sub-voxel edge refinement (stages.refine) and its support on the free surface."""
    _release_between_steps(ws)  # the deformation's freed arrays: the profiles come on top
    params, d = run.params, ws.d
    before = bone.vertices
    plates = bone.plates
    levels: dict = {}
    verts, shift, frac, found = refine_to_edges(
        before, bone.faces, ws.ct_smooth, ws.ct_smooth_d, ws.ht, edge_level=params.edge_level,
        allowed=allowed, progress=progress, fallbacks=bone.fallbacks,
        plate_targets=plates.targets if plates is not None and plates.n else None,
        shared_reference=ws.shared_reference, info=levels, profiles=bone.profiles)
    bone.profiles = None
    # Edge support on the free surface: where the bone touches another one (no joint space
    # on the CT) no edge is expected.
    free = np.ones(len(verts), bool)
    if bone.others_distance is not None:
        free = sample_field(bone.others_distance, before - bone.masks.origin, d,
                            cval=1e3) > FREE_SURFACE_MM
    support = float(found[free].mean()) if free.any() else float(found.mean())
    # Applied: some of the refinement survived its checks (else the input came back).
    own, used = levels.get("own_reference_hu"), levels.get("reference_hu")
    # Another bone's contrast was used when it exceeds this one's own (or that is unknown).
    shared_from = (ws.name_of(ws.shared_reference_from)
                   if used is not None and np.isfinite(used) and not own >= used else None)
    bone.refinement = Refinement(applied=not np.array_equal(verts, before),
                                 fraction_with_edge=support,
                                 mean_shift_mm=float(shift.mean()),
                                 mean_abs_shift_mm=float(np.abs(shift).mean()),
                                 own_contrast_hu=_finite_or_none(own),
                                 contrast_hu=_finite_or_none(used),
                                 contrast_from=shared_from)
    bone.vertices = verts


def release_grids(run: _Run, ws: Workspace, bones: dict) -> None:
    """Drop the volumes no later stage reads once the bones are deformed: each bone's threshold
    masks and the fields M0 was fused with (the deformation drops the CT's copies but the
    refinement's smoothed one). The contacts and the finishing stages measure on volumes of
    their own. With ``keep_intermediates`` the masks stay (they are reported)."""
    for bone in bones.values():
        if bone.masks is not None and not run.params.keep_intermediates:
            masks = bone.masks
            masks.w_h0 = masks.w_ht = masks.solid_h0 = masks.occupancy = masks.far = None
        bone.processes = None
        if bone.fusion is not None:
            bone.fusion.carve = bone.fusion.bone = bone.fusion.solid = None


def contact_stage(run: _Run, ws: Workspace, bones: dict) -> None:
    """Joint gaps from the final surfaces: every vertex beyond its territory moved back, then
    the exact test; pairs that still cross get passes with a wider margin, then the exact
    push-apart (stages.contacts)."""
    sub = run.stage("contacts")
    with timed(run.times, "contacts", run.spans):
        terr = ws.territories
        if not (terr and any(v is not None for v in terr.values())):
            return
        surfaces = {k: [b.vertices, b.faces] for k, b in bones.items()}
        history = _resolve_with_retries(surfaces, ws.fixed, ws.labels.shape, ws.d,
                                        run.params.min_gap, sub,
                                        {k: b.fallbacks for k, b in bones.items()},
                                        {k: b.name for k, b in bones.items()},
                                        threads=run.threads)
        exact = _keep_gaps_exact(surfaces, run.params.min_gap, sub)
        for k, b in bones.items():
            b.vertices = surfaces[k][0]
            b.contacts = {"passes": [{"moved": rec[k][0], "still_closer_than_gap": rec[k][1]}
                                     for rec in history if k in rec]}
            if k in exact:
                b.contacts["exact_gap"] = exact[k]
            discarded = sum(rec[k][2] for rec in history if k in rec)
            if discarded:
                b.fallbacks.add("contacts", "a contact pass failed the self-intersection check: "
                                "its moves were discarded", discarded, "vertices")
            relaxed = sum(rec[k][3] for rec in history if k in rec)
            if relaxed:
                b.fallbacks.add("contacts", "moves back into the bone's territory kept flipping "
                                "faces (a fold or spike of the surface): the neighbourhood was "
                                "relaxed towards its neighbours' mean first", relaxed, "vertices")


def _resolve_with_retries(surfaces: dict, fixed: dict, shape: tuple, d: float, min_gap: float,
                          progress: Progress, fallbacks: dict, names: dict,
                          threads: int = 1) -> list:
    """stages.contacts.resolve_contacts on ``surfaces`` ({key: [vertices, faces]}, updated
    in place); the fields are voxel-accurate and the exact test decides: pairs that still
    cross get more passes with a wider margin, and a sub-voxel sliver left after those is
    moved apart exactly. Both are noted in ``fallbacks`` ({key: FallbackLog}; ``names``:
    {key: name}; ``threads``: bones worked at once). Returns the passes' records."""
    cache = {}
    history = _contacts.resolve_contacts(surfaces, fixed, shape, d, min_gap,
                                         progress=progress.stage(0.0, 0.6), cache=cache,
                                         threads=threads)
    for extra in range(1, CONTACT_RETRIES + 1):
        crossing = _crossing_pairs(surfaces)
        if not crossing:
            break
        involved = {k for pair in crossing for k in pair}
        for a, b in crossing:
            for k, other in ((a, b), (b, a)):
                fallbacks[k].add("contacts", "the surfaces still crossed after the contact "
                                 "passes: more passes with a wider margin near the crossing "
                                 "faces", 1, "passes", f"with {names[other]}")
        # The other bones hold their place (their voxelised surfaces are cached); the wider
        # margin moves only the vertices near the faces that cross: a local sliver or spike
        # must not push the whole contact apart (a margin of up to three voxels over a ball
        # joint took 0.6 mm off the cup of the 2.5 mm joint phantom all round).
        near = _near_crossings(surfaces, crossing, CONTACT_RETRY_REACH_MM + extra * d)
        history += _contacts.resolve_contacts(surfaces, fixed, shape, d, min_gap + extra * d,
                                              progress=progress.stage(0.6, 1.0),
                                              active=involved, cache=cache, threads=threads,
                                              pinned={k: ~m for k, m in near.items()})
    else:
        # Still crossing after the field passes: a sub-voxel sliver; moved apart exactly.
        for a, b in _crossing_pairs(surfaces):
            va, vb, _ = _contacts.push_apart_exact(surfaces[a][0], surfaces[a][1],
                                                  surfaces[b][0], surfaces[b][1], d)
            for k, other, new in ((a, b, va), (b, a, vb)):
                fallbacks[k].add("contacts", "a sub-voxel crossing left after the field passes "
                                 "was moved apart exactly (last resort)",
                                 int(np.any(new != surfaces[k][0], axis=1).sum()), "vertices",
                                 f"with {names[other]}")
            surfaces[a][0], surfaces[b][0] = va, vb
    return history


def _near_crossings(surfaces: dict, crossing: list, reach: float) -> dict:
    """{key: (n,) bool}: the vertices of each surface within ``reach`` mm of a vertex of one
    of its faces that cross a face of another surface (``crossing``: the pairs that cross)."""
    seeds: dict = {}
    for a, b in crossing:
        fa_ids, fb_ids = _contacts.crossing_faces(surfaces[a][0], surfaces[a][1],
                                                  surfaces[b][0], surfaces[b][1])
        for k, ids in ((a, fa_ids), (b, fb_ids)):
            seeds.setdefault(k, []).append(np.unique(surfaces[k][1][ids].ravel()))
    out = {}
    for k, parts in seeds.items():
        v = surfaces[k][0]
        idx = np.unique(np.concatenate(parts))
        m = np.zeros(len(v), bool)
        if len(idx):
            dist, _ = cKDTree(v[idx]).query(v, distance_upper_bound=reach)
            m = np.isfinite(dist)
        out[k] = m
    return out


def _keep_gaps_exact(surfaces: dict, min_gap: float,
                     progress: Optional[Progress] = None) -> dict:
    """stages.contacts.keep_gap_exact on every pair of ``surfaces`` ({key: [vertices,
    faces]}, updated in place) whose boxes come within the gap and the search distance;
    returns {key: {"moved": vertices moved, "with": {other key: smallest gap left mm}}}.
    ``progress`` is told before each pair (so a cancel stops it there)."""
    reach = min_gap + _contacts.GAP_SEARCH_MM
    boxes = {k: (v.min(axis=0) - reach, v.max(axis=0) + reach) for k, (v, _) in surfaces.items()}
    out = {}
    keys = list(surfaces)
    for i, a in enumerate(keys):
        for b in keys[i + 1:]:
            if np.any(boxes[a][1] < boxes[b][0]) or np.any(boxes[b][1] < boxes[a][0]):
                continue
            if progress is not None:
                progress(1.0, "exact joint gaps")
            va, vb, na, nb, gap = _contacts.keep_gap_exact(
                surfaces[a][0], surfaces[a][1], surfaces[b][0], surfaces[b][1],
                min_gap + GAP_MARGIN_MM)
            if gap is None:
                continue
            surfaces[a][0], surfaces[b][0] = va, vb
            for k, other, n in ((a, b, na), (b, a, nb)):
                rec = out.setdefault(k, {"moved": 0, "with": {}})
                rec["moved"] += n
                rec["with"][other] = round(gap, 4)
    return out


def finish_bone(run: _Run, ws: Workspace, bone: BoneWork,
                progress: Progress) -> ReconstructionResult:
    """Caps at the image boundary, the checks (SPEC §4), plausibility, the report."""
    name, grid = bone.name, ws.prep.grid
    planes = ws.prep.caps.get(bone.k, [])
    with timed(bone.times, "cap", run.spans, bone.k):
        verts, faces, flags, cap_area = cap_bone(bone.vertices, bone.faces, planes,
                                                 bone.fallbacks)
        if planes:
            verts, faces, flags = drop_cap_slivers(verts, faces, flags, ws.d ** 3,
                                                   bone.fallbacks)
    progress(0.3, f"{name}: checks")
    with timed(bone.times, "checks", run.spans, bone.k):
        phys = grid.grid_to_physical(verts)
        if enclosed_volume(phys, faces) < 0:  # a reflecting direction matrix flips orientation
            faces = faces[:, ::-1].copy()
        checks = check_surface(phys, faces)
    _raise_failed_checks(checks, phys, faces, planes, name)
    progress(0.6, f"{name}: plausibility")
    _release_between_steps(ws)  # its distance maps come on top of what the checks freed
    with timed(bone.times, "plausibility", run.spans, bone.k):
        evidence, confidence, summary = evidence_of(run, ws, bone, verts, faces, flags)
        plaus, box, segment = plausibility_of(run, ws, bone, verts, faces, phys, planes,
                                              edges=verts[evidence == _evidence.EDGE],
                                              reach=summary["threshold_reach"])
    warnings = _plausibility_warnings(run, plaus) + _relabelled_warnings(ws, bone.k)
    fusion = bone.fusion
    if not planes and fusion is not None and fusion.genus is not None \
            and int(fusion.label.sum()) == int(segment.sum()):
        # M0's fill measured the same voxels (its trusted segment is a subset of the label,
        # both boxes hold all of it, and the genus does not depend on the box).
        plaus.segment_genus = int(fusion.genus)
    else:
        plaus.segment_genus = _plaus.segment_genus(
            segment & _plaus.image_mask(box, planes, ws.d), ws.d, ws.prep.coarseness)
    plugged = None
    if checks.genus > plaus.segment_genus:
        plugged = _plugged_tunnels(ws, bone.k, verts, faces, planes)
    warnings += _plaus.tunnel_warning(name, checks.genus, plaus.segment_genus, plugged)
    plaus.plate_holes = bone.plate_holes
    warnings += _left_out_warning(name, bone.fusion, grid, bone.masks.origin, phys, faces,
                                  planes)
    constraints = bone.constraints
    dist, _ = cKDTree(grid.grid_to_physical(constraints)).query(phys, workers=-1) \
        if len(constraints) else (np.zeros(len(phys)), None)
    warnings += _missed_edge_warning(name, grid, constraints, phys, faces, ws.d, planes)
    for patch in summary.get("label_only_patches", ()):
        patch["lps_mm"] = [round(float(v), 1) for v in phys[patch["vertex"]]]
    warnings += _evidence.evidence_warnings(name, summary,
                                            _plate_min_thickness(run.params, ws.d),
                                            where=lambda v: _lps_of(phys[v]))
    surface = Surface(phys, faces, "LPS", {"DistanceToConstraints": dist, "Evidence": evidence,
                                           "Confidence": confidence},
                      {"Cap": flags} if planes else {})
    report = bone_report(run, ws, bone, checks, phys, faces, dist, plaus, warnings,
                         {"planes": [p.to_dict() for p in planes], "area_mm2": cap_area,
                          "faces": int(flags.sum())})
    report.evidence = summary
    progress(1.0, f"{name}: done")
    return ReconstructionResult(surface=surface, distance_to_constraints=dist, report=report,
                                intermediates=_intermediates(run, ws, bone),
                                label=ws.value_of(bone.k), name=name)


def evidence_of(run: _Run, ws: Workspace, bone: BoneWork, verts, faces, flags) -> tuple:
    """Per-vertex evidence class and confidence of the finished surface (stages.evidence).
    ``verts`` are grid mm; ``faces`` are oriented outward in physical space, which a reflecting
    direction matrix turns inward on the grid."""
    origin = bone.masks.origin
    if enclosed_volume(verts, faces) < 0:
        faces = faces[:, ::-1]
    fill = None
    if bone.fusion is not None and bone.fusion.fill_mask is not None:
        mask, lo, h = bone.fusion.fill_mask
        fill = (mask, np.asarray(lo) + origin, h)
    return _evidence.vertex_evidence(
        verts, faces, flags, ct_smooth=ws.ct_smooth, field_spacing=ws.ct_smooth_d,
        spacing=ws.d, ht=ws.ht,
        soft=ws.thresholds["soft_tissue_hu"],
        min_contrast=_ownership.LABEL_LEVEL_FRACTION * (ws.ht - ws.thresholds["soft_tissue_hu"]),
        edge_level=run.params.edge_level, plates=bone.plates,
        others_distance=bone.others_distance, others_origin=origin, fill=fill,
        free_mm=FREE_SURFACE_MM, resolution=float(max(ws.prep.ct_spacing)),
        shared_reference=ws.shared_reference)


def cap_bone(vertices: np.ndarray, faces: np.ndarray, planes: list,
             fallbacks: Optional[FallbackLog] = None) -> tuple:
    """(vertices, faces, cap flags (m,) uint8, cap area mm^2): the surface clipped and capped
    at each plane where the image cuts the bone (mesh.cap)."""
    flags = np.zeros(len(faces), np.uint8)
    area = 0.0
    for plane in planes:
        vertices, faces, flags, a = cap_plane(vertices, faces, flags, plane.axis, plane.side,
                                              plane.position, mean_edge_length(vertices, faces),
                                              fallbacks)
        area += a
    return vertices, faces, flags, area


def drop_cap_slivers(vertices: np.ndarray, faces: np.ndarray, flags: np.ndarray,
                     min_volume: float, fallbacks: Optional[FallbackLog] = None) -> tuple:
    """(vertices, faces, flags) without the closed pieces of the surface that enclose less than
    ``min_volume`` (mm^3; one voxel of the working grid): where a cap plane clips a tiny bump,
    it can leave a sliver of its own, which no CT could show as bone. Every other piece stays
    (a bone the image cuts into real pieces is refused by the checks). Noted in ``fallbacks``."""
    face_comp, volumes = _pieces(vertices, faces)
    small = np.flatnonzero((volumes < min_volume) & (volumes < volumes.max())) \
        if len(volumes) > 1 else np.zeros(0, int)
    if not len(small):
        return vertices, faces, flags
    keep = ~np.isin(face_comp, small)
    used = np.zeros(len(vertices), bool)
    used[faces[keep].ravel()] = True
    index = np.cumsum(used) - 1
    if fallbacks is not None:
        fallbacks.add("cap", "closed pieces smaller than one voxel that a cap plane cut off the "
                      "surface were dropped", int(len(small)), "pieces")
    return vertices[used], index[faces[keep]], flags[keep]


def _raise_failed_checks(checks, phys, faces, planes, name) -> None:
    if not checks.ok and planes and checks.n_components > 1:
        pieces = _component_volumes(phys, faces)
        raise SurfaceCheckError(
            f"{name} is cut by the image boundary into {len(pieces)} separate pieces inside the "
            f"image ({', '.join(f'{v / 1000:.1f}' for v in pieces)} ml): they join outside the "
            "field of view, so one closed surface cannot hold them. Use a CT that contains more "
            "of the bone, or split the segment into one segment per piece.", report=checks)
    if not checks.ok:
        raise SurfaceCheckError(
            f"The surface of {name} failed the watertight 2-manifold checks: "
            + "; ".join(checks.problems)
            + ". Try a finer resample spacing, more deformation stiffness (alpha), or fewer "
            "iterations.", report=checks)


def plausibility_of(run: _Run, ws: Workspace, bone: BoneWork, verts, faces, phys,
                    planes, edges=None, reach=None) -> tuple:
    """(stages.plausibility's measures, gated; the box they were measured on (slices of the
    working grid); the bone's segment on that box, (z, y, x) bool). ``edges``: the vertices
    with a CT edge (grid mm); ``reach``: the evidence summary's ``threshold_reach``."""
    k, d, own, lab = bone.k, ws.d, ws.own, ws.labels
    seg_all = lab == k
    box = _threshold.bbox_slices(seg_all | (own.owner == k),
                                 int(np.ceil((ws.band + 3 * d) / d)) + 2)
    corner = np.array([s.start for s in box][::-1], dtype=np.float64) * d
    inside = _contacts.voxelize(verts - corner, faces, tuple(s.stop - s.start for s in box), d)
    lab_b = lab[box]
    cores_b = own.cores[box]
    frac = bone.refinement.fraction_with_edge
    soft_tissue = None
    if ws.ct_smooth is not None:
        # Below the level at which the ownership takes a label's voxels for bone, the CT shows
        # soft tissue: a generous segment's margin there is not missing bone.
        level = own.info["label_level_hu"]
        if np.isscalar(ws.ct_smooth_d):
            soft_tissue = ws.ct_smooth[box] < level
        else:
            # On the refinement's own grid, sampled where it matters: the segment outside the
            # surface (all of the box's points at once were the run's peak of memory, +0.4 GB,
            # and 0.6 s, on the femur).
            out_seg = np.argwhere(seg_all[box] & ~inside)
            soft_tissue = np.zeros(inside.shape, bool)
            if len(out_seg):
                pts = (out_seg[:, ::-1] + np.array([s.start for s in box][::-1])) * d
                soft_tissue[tuple(out_seg.T)] = sample_field(
                    ws.ct_smooth, pts, ws.ct_smooth_d, cval=-1000.0) < level
    plaus = _plaus.measure(
        inside, verts - corner, seg_all[box], (lab_b > 0) & (lab_b != k),
        (cores_b > 0) & (cores_b != k), _plaus.image_mask(box, planes, d), d,
        volume_mm3=enclosed_volume(phys, faces), coarseness=ws.prep.coarseness,
        band_mm=ws.band, edge_support=float("nan") if frac is None else frac,
        threshold_reach=float("nan") if reach is None else reach["fraction"],
        owned=own.owner[box] == k,
        unsupported=None if own.unsupported is None else own.unsupported[box],
        unsupported_pieces=len(own.info.get("unsupported", {}).get(k, [])),
        unlabelled=None if own.merged is None else own.merged[box] & (own.owner[box] == k),
        added=None if own.added is None else own.added[box] & (own.owner[box] == k),
        others_owned=(own.owner[box] > 0) & (own.owner[box] != k),
        contact_mm=float(own.info.get("contact_zone_mm", 0.0)), soft_tissue=soft_tissue,
        edge_points=None if edges is None else edges - corner)
    for cc in own.contacts:
        if cc["a"] == k and cc["b"] == own.other:
            plaus.unlabelled_contact_mm2 = float(cc["contact_area_mm2"])
            plaus.unlabelled_contact_seen = float(cc["valley_seen_fraction"])
    plaus.surface_area_mm2 = surface_area(phys, faces)
    th = ws.thresholds
    _plaus.gate(plaus, coarseness=ws.prep.coarseness, band_mm=ws.band, name=bone.name,
                estimated=((th["h0"], th["ht"]) if th.get("h0_auto") and th.get("ht_auto")
                           else None),
                where_text=lambda at: _lps_text(ws.prep.grid, np.asarray(at) + corner))
    return plaus, box, seg_all[box]


def _plugged_tunnels(ws: Workspace, k: int, verts, faces, planes) -> int:
    """plausibility.plugged_tunnels of bone k's surface (``verts`` grid mm) and its segment on
    a box of the working grid holding both (and the reach of the segment's plugs)."""
    d, lab = ws.d, ws.labels
    pad = int(np.ceil(_plaus.PLUG_REACH_COARSENESS * ws.prep.coarseness / d)) + 2
    seg = lab == k
    # The segment's box and the surface's (z, y, x voxels), together, grown by the pad.
    own_box = _threshold.bbox_slices(seg, 0)
    lo = np.minimum([s.start for s in own_box], np.floor(verts.min(axis=0) / d).astype(int)[::-1])
    hi = np.maximum([s.stop for s in own_box], np.ceil(verts.max(axis=0) / d).astype(int)[::-1] + 1)
    box = tuple(slice(max(0, int(a) - pad), min(n, int(b) + pad))
                for a, b, n in zip(lo, hi, lab.shape))
    corner = np.array([s.start for s in box][::-1], dtype=np.float64) * d
    inside = _contacts.voxelize(verts - corner, faces, tuple(s.stop - s.start for s in box), d)
    segment = seg[box] & _plaus.image_mask(box, planes, d)
    return _plaus.plugged_tunnels(inside, segment, d, ws.prep.coarseness)


def _relabelled_warnings(ws: Workspace, k: int) -> list:
    """Bone k's warnings for the parts of a segment the ownership gave to a neighbour
    (ownership.info["relabelled"]): on both bones."""
    out = []
    for rec in ws.own.info.get("relabelled", []):
        if k not in (rec["from"], rec["to"]):
            continue
        a, b = ws.name_of(rec["from"]), ws.name_of(rec["to"])
        out.append(
            f"{rec['label_ml']:.1f} ml of {a}'s segment lies in {b}'s bone: the CT joins it "
            f"to {b} without a joint space ({b} took {100 * rec['taken_fraction']:.0f} % of "
            f"its core when {a}'s label there was not trusted, {a} "
            f"{100 * rec['kept_fraction']:.0f} %), so it was reconstructed as {b}'s. Check "
            f"both segments there and correct {a}'s if the CT is right")
    return out


def _plausibility_warnings(run: _Run, plaus) -> list:
    """The gate's problems as an error (on_implausible = fail) or warnings, and its warnings."""
    warnings = []
    if plaus.problems:
        if run.params.on_implausible == "fail":
            raise PlausibilityError(
                "The surface is watertight but not plausible: " + "; ".join(plaus.problems)
                + ". (on_implausible = warn returns it with these warnings.)", report=plaus)
        warnings = list(plaus.problems)
    return warnings + plaus.warnings


def bone_report(run: _Run, ws: Workspace, bone: BoneWork, checks, phys, faces, dist, plaus,
                warnings, cap: dict) -> PipelineReport:
    """The typed report of one finished bone."""
    prep, own, sep = ws.prep, ws.own, bone.separation
    return PipelineReport(
        version=__version__, parameters=run.params.to_dict(), input=prep.info,
        timings=bone.times, threshold=dict(
            bone.masks.info, h0=ws.thresholds["h0"], ht=ws.thresholds["ht"],
            plates=bone.plates.info if bone.plates is not None else {},
            fusion=dict(bone.fusion.info) if bone.fusion is not None else {}),
        counts=Counts(p_h0_surface_points=int(bone.n_candidates),
                      visible_points=int(len(bone.visible)),
                      ht_boundary_points=int(len(bone.b_ht)),
                      constraint_points=int(len(bone.constraints)),
                      poisson_raw_vertices=int(bone.raw_vertices),
                      m0_vertices=int(bone.m0.n_vertices), m0_faces=int(bone.m0.n_faces),
                      vertices=int(len(phys)), faces=int(len(faces))),
        visible=bone.vis_info, deformation=bone.history, refinement=bone.refinement,
        checks=checks, distance_to_constraints_mm=DistanceSummary.of(dist),
        mean_edge_length_mm=mean_edge_length(phys, faces), area_mm2=surface_area(phys, faces),
        volume_mm3=enclosed_volume(phys, faces), constants=pipeline_constants(),
        label=ws.value_of(bone.k), name=bone.name, thresholds=dict(ws.thresholds),
        ownership={"core_depth_mm": own.info["core_depth_mm"].get(bone.k),
                   "owned_voxels": int((own.owner == bone.k).sum()),
                   # its joint zone with unlabelled neighbours (a second flood ran without them)
                   "unlabelled_contact_voxels_unmarked": int(own.info.get(
                       "unlabelled_contact_unmarked_by_label", {}).get(bone.k, 0)),
                   # parts of a segment the CT showed in a neighbour's bone (given to it)
                   "segment_given_ml": round(sum(r["label_ml"] for r in own.info.get(
                       "relabelled", []) if r["from"] == bone.k), 3),
                   "segment_taken_ml": round(sum(r["label_ml"] for r in own.info.get(
                       "relabelled", []) if r["to"] == bone.k), 3)},
        separation={"erosions_to_separate": sep,
                    "by": ("threshold" if sep == 0 else f"erosion ({sep} CT voxels)" if sep
                           else "competition at the CT's valley and the labels")},
        cap=cap, contacts=bone.contacts, plausibility=plaus, warnings=warnings,
        fallbacks=list(run.fallbacks) + list(bone.fallbacks))


def _intermediates(run: _Run, ws: Workspace, bone: BoneWork) -> dict:
    """The intermediate results in physical LPS, on request (keep_intermediates)."""
    if not run.params.keep_intermediates:
        return {}
    grid, masks, d = ws.prep.grid, bone.masks, ws.d
    o = masks.origin
    m0p = grid.grid_to_physical(bone.m0.vertices)
    return {
        "P_H0": grid.grid_to_physical(voxel_points(masks.w_h0, d) + o),
        "P_HT": grid.grid_to_physical(voxel_points(masks.w_ht & ~masks.w_h0, d) + o),
        "visible_points": grid.grid_to_physical(bone.visible),
        "constraints": grid.grid_to_physical(bone.constraints),
        "M0": Surface(m0p, bone.m0.faces if enclosed_volume(m0p, bone.m0.faces) > 0
                      else bone.m0.faces[:, ::-1].copy()),
        "deformed": Surface(grid.grid_to_physical(bone.deformed), bone.faces),
    }


def _failed_result(ws: Workspace, k: int, error: BaseException) -> ReconstructionResult:
    return ReconstructionResult(surface=None, distance_to_constraints=None, report=None,
                                label=ws.value_of(k), name=ws.name_of(k), error=error)


def pair_stage(ws: Workspace, results: list, keep_going: bool = False,
               min_gap: float = 0.0) -> list:
    """Every pair of finished bones checked exactly (PairReport), the joint warnings; an
    interpenetrating pair fails the run (ReconstructionError) or, with ``keep_going``, both
    of its bones (their entries of ``results`` are replaced by failed results naming the
    pair; the pairs returned are those of the bones that still stand)."""
    own = ws.own
    contact_of = {(cc["a"], cc["b"]): cc for cc in own.contacts}
    by_k = dict(zip(ws.targets, results))
    good = [k for k in ws.targets if by_k[k].ok]
    pairs, keys = [], []
    for i, a in enumerate(good):
        for b in good[i + 1:]:
            keys.append((a, b))
            ra, rb = by_k[a], by_k[b]
            rep = _contacts.pair_report(ra.surface.vertices, ra.surface.faces,
                                        rb.surface.vertices, rb.surface.faces)
            joint = contact_of.get((min(a, b), max(a, b)))
            pairs.append(PairReport(
                a=ws.name_of(a), b=ws.name_of(b), **rep,
                joint_contact_mm2=float(joint["contact_area_mm2"]) if joint else 0.0,
                joint_valley_seen_fraction=(float(joint["valley_seen_fraction"])
                                            if joint else None)))
    def warn(p, text):  # on the pair and on both of its bones
        p.warnings.append(text)
        for k in good:
            if by_k[k].name in (p.a, p.b):
                by_k[k].report.warnings.append(text)

    for p, (a, b) in zip(pairs, keys):
        if p.ok and p.min_gap_mm is not None and p.min_gap_mm < min_gap:
            # The contact passes work on voxel fields: a sub-voxel approach can be left.
            warn(p, f"{p.a} | {p.b}: the surfaces come within {p.min_gap_mm:.2f} mm of each "
                    f"other (min_gap {min_gap:g} mm), without crossing: check the joint, or use "
                    "a finer resample spacing")
        seen = p.joint_valley_seen_fraction
        if seen is not None and seen < JOINT_WARN_SEEN and p.joint_contact_mm2 > JOINT_WARN_MIN_MM2:
            warn(p, f"{p.a} | {p.b}: the CT shows a joint space on only "
                    f"{_plaus.percent_text(seen)} of their {p.joint_contact_mm2:.0f} mm^2 contact; "
                    f"{_hidden_part_text(own, a, b)} (a narrow joint on thick "
                    "slices, or no joint space at all): check both surfaces at the joint")
    # The same for a bone and a neighbour label that is not reconstructed in this run.
    for cc in own.contacts:
        for k, other in ((cc["a"], cc["b"]), (cc["b"], cc["a"])):
            seen = cc.get("valley_seen_fraction")
            if (k in good and other not in ws.targets and other < own.other and seen is not None
                    and seen < JOINT_WARN_SEEN and cc["contact_area_mm2"] > JOINT_WARN_MIN_MM2):
                by_k[k].report.warnings.append(
                    f"{ws.name_of(k)} | {ws.name_of(other)} (neighbour): the CT shows a joint "
                    f"space on only {_plaus.percent_text(seen)} of their "
                    f"{cc['contact_area_mm2']:.0f} mm^2 contact; "
                    f"{_hidden_part_text(own, k, other)}: check the surface at the joint")
    bad = [p for p in pairs if not p.ok]
    if not bad:
        return pairs
    if not keep_going:
        raise _interpenetration_error(bad)
    # One pair that crosses does not discard the other bones: both of its bones fail.
    failed = {}
    for p in bad:
        for name in (p.a, p.b):
            failed.setdefault(name, []).append(p)
    for i, r in enumerate(results):
        if r.ok and r.name in failed:
            results[i] = ReconstructionResult(surface=None, distance_to_constraints=None,
                                              report=None, label=r.label, name=r.name,
                                              error=_interpenetration_error(failed[r.name]))
    return [p for p in pairs if p.a not in failed and p.b not in failed]


def _interpenetration_error(bad: list) -> ReconstructionError:
    text = "; ".join(f"{p.a} and {p.b}: {p.crossing_face_pairs} crossing face pairs, "
                     f"{p.a_inside_b + p.b_inside_a} vertices inside the other" for p in bad)
    return ReconstructionError(
        f"The surfaces of neighbouring bones interpenetrate ({text}). Check the labels at the "
        "joint, or use a finer resample spacing.")


def _shared_times(times: StageTimes, shared: StageTimes) -> None:
    """The shared stages' seconds (and the total) into a bone's own times."""
    for stage in ("import_open3d", "prepare", "filter", "thresholds", "ownership", "territories",
                  "refine_field", "contacts", "total"):
        setattr(times, stage, getattr(shared, stage))


def _stage_spans(records: list, origin: float, ws: Workspace) -> list:
    """When each timed stage ran, for the reports' ``stage_spans``.

    Parameters
    ----------
    records : list
        ``(stage, k, start, end)`` as :func:`timed` appended them (k: label index on the
        working grid, None for a stage the bones share; ``time.perf_counter`` seconds).
    origin : float
        ``time.perf_counter()`` at the start of the run (the zero of ``timings.total``).
    ws : Workspace
        Names and label values of the label indices.

    Returns
    -------
    list of dict
        ``{"stage", "bone", "label", "start_s", "end_s"}`` in order of start, seconds from the
        start of the run; ``bone`` / ``label`` None for a shared stage. The durations of a
        stage's spans of one bone (or the shared ones) add up to its ``timings`` entry.
    """
    out = [{"stage": stage, "bone": None if k is None else ws.name_of(k),
            "label": None if k is None else ws.value_of(k),
            "start_s": start - origin, "end_s": end - origin}
           for stage, k, start, end in records]
    return sorted(out, key=lambda s: (s["start_s"], s["end_s"]))


def _ownership_info(ws: Workspace) -> dict:
    own = ws.own

    def named(records):
        return [dict(r, a=_pair_name(r["a"], own, ws.name_of),
                     b=_pair_name(r["b"], own, ws.name_of)) for r in records]

    return dict(own.info, contacts=named(own.contacts),
                joint_cuts=named(own.info.get("joint_cuts", [])),
                joint_fits=named(own.info.get("joint_fits", [])))


def _hidden_part_text(own, a: int, b: int) -> str:
    """How the boundary of bones a, b was decided where the CT shows no joint space."""
    for f in own.info.get("joint_fits", []):
        if {f["a"], f["b"]} == {a, b} and f.get("used"):
            # (its points: the joint space the CT shows between the two bones' basins, which
            # may lie beside the final contact - a contact seen on under 1 % can carry a fit)
            return (f"elsewhere the boundary between them follows a {f['model']} fitted to the "
                    f"{f['points']} voxels of joint space the CT shows between them (RMS "
                    f"{f['rms_mm']:.2f} mm) as far as it is carried, and the segments' labels "
                    "beyond")
    return "elsewhere the boundary between them follows the segments' labels"


def size_problems(prep, params: Parameters, names: Optional[dict] = None) -> dict:
    """Cross-parameter limits, checked before the long work: {target index: error} for each
    target whose segment's smallest extent on the working grid spans fewer than
    MIN_VOXELS_ACROSS voxels d (InputError) or MIN_EDGES_ACROSS edge lengths d* (InputError),
    or whose M0 remeshing grid (step d* / REMESH_EDGE_RATIO over its box grown by the band)
    would exceed ``max_memory_gb`` or the element limit (MemoryLimitError)."""
    from .errors import MemoryLimitError

    d = prep.grid.spacing
    edge = params.edge_length if params.edge_length is not None else d
    h = edge / _poisson.REMESH_EDGE_RATIO
    band = max(params.segment_dilation, BAND_COARSENESS * prep.coarseness)
    limit = params.max_memory_gb * 1024 ** 3
    problems = {}
    for k in prep.targets:
        value = prep.values[k - 1]
        name = str((names or {}).get(value, value))
        box = _threshold.bbox_slices(prep.labels == k, 0)
        extent = np.array([(s.stop - s.start) * d for s in box][::-1])
        smallest = float(extent.min())
        dims = " x ".join(f"{v:.1f}" for v in extent)
        remesh = float(np.prod(np.ceil((extent + 2 * band) / h)
                               + 2 * _poisson.REMESH_PAD_STEPS + 1))
        over = max(remesh * REMESH_BYTES_PER_VOXEL / limit, remesh / _prepare.MAX_GRID_VOXELS)
        if d * MIN_VOXELS_ACROSS > smallest:
            problems[k] = InputError(
                f"The resample spacing {d:g} mm is too coarse for segment {name}: its smallest "
                f"extent is {smallest:.1f} mm (box {dims} mm), fewer than "
                f"{MIN_VOXELS_ACROSS:g} voxels. Use a spacing of at most "
                f"{np.floor(smallest / MIN_VOXELS_ACROSS * 100) / 100:g} mm, or check the "
                "segment.")
        elif edge * MIN_EDGES_ACROSS > smallest:
            problems[k] = InputError(
                f"edge_length {edge:g} mm is too long for segment {name}: its smallest extent "
                f"is {smallest:.1f} mm (box {dims} mm), fewer than {MIN_EDGES_ACROSS:g} edges. "
                f"Use an edge_length of at most "
                f"{np.floor(smallest / MIN_EDGES_ACROSS * 100) / 100:g} mm (or auto).")
        elif over > 1.0:
            problems[k] = MemoryLimitError(
                f"edge_length {edge:g} mm is too short for segment {name} (box {dims} mm): "
                f"remeshing its surface needs a grid of {remesh / 1e6:.0f} M voxels, about "
                f"{remesh * REMESH_BYTES_PER_VOXEL / 1024 ** 3:.1f} GB (limit "
                f"{params.max_memory_gb:g} GB). Use an edge_length of at least "
                f"{np.ceil(edge * over ** (1 / 3) * 100) / 100:g} mm (or auto), or raise "
                "max_memory_gb.")
    return problems


def _crossing_pairs(surfaces: dict) -> list:
    """The pairs (a, b) of {key: [vertices, faces]} whose faces cross (exact test)."""
    keys = list(surfaces)
    return [(a, b) for i, a in enumerate(keys) for b in keys[i + 1:]
            if _contacts.pair_report(surfaces[a][0], surfaces[a][1], surfaces[b][0],
                                     surfaces[b][1], crossing_only=True)["crossing_face_pairs"]]


def _pieces(vertices, faces) -> tuple:
    """(piece index of each face (m,), enclosed volume mm^3 of each piece): the connected
    pieces of a surface."""
    comp = _operators.vertex_components(len(vertices), faces)
    face_comp = np.unique(comp[faces[:, 0]], return_inverse=True)[1].ravel()
    volumes = np.array([abs(enclosed_volume(vertices, faces[face_comp == c]))
                        for c in range(int(face_comp.max()) + 1)] if len(faces) else [])
    return face_comp, volumes


def _component_volumes(vertices, faces) -> list:
    """Enclosed volume (mm^3) of each connected piece of a surface, largest first."""
    return sorted(_pieces(vertices, faces)[1].tolist(), reverse=True)


def _finite_or_none(x) -> Optional[float]:
    return float(x) if x is not None and np.isfinite(x) else None


def _pair_name(k, own, name_of):
    return "unlabelled bone" if k >= own.other else name_of(k)


def _threshold_error(name, ht, theta_max, vals):
    from .errors import ThresholdError

    lo = float(np.min(vals)) if len(vals) else float("nan")
    hi = float(np.max(vals)) if len(vals) else float("nan")
    if hi < ht:
        # Nothing inside the segment is bone-like at all: the segment is off the bone.
        what = "air" if hi < -200 else "fat" if hi < -30 else "soft tissue"
        return ThresholdError(
            f"Segment {name} covers no bone on this CT: its HU range is {lo:.0f} to {hi:.0f} "
            f"({what}), all below HT = {ht:g} HU. Check that the segment belongs to this CT and "
            "lies on the bone (a misplaced or wrong segment), or lower HT if the bone is this "
            "faint.")
    return ThresholdError(
        f"No voxel of segment {name} lies in [HT, theta_max] = [{ht:g}, {theta_max:g}] HU "
        f"(the segment's HU range is {lo:.0f} to {hi:.0f}): lower HT (or leave it on auto), or "
        "check that the volume is a CT in Hounsfield units.")


def _fixed_masks(own, lab, targets, n) -> dict:
    """Owned voxels of the bones that are not reconstructed (neighbours, unlabelled bone)."""
    fixed = {}
    others = [i for i in range(1, n + 1) if i not in targets and (lab == i).any()]
    if others:
        m = np.isin(own.owner, others)
        if m.any():
            fixed["neighbours"] = m
    m = own.owner >= own.other
    if m.any():
        fixed["unlabelled"] = m
    return fixed


def pipeline_constants() -> dict:
    """The fixed settings of the pipeline and its stages ({module: {NAME: value}})."""
    import sys

    return constants_of(sys.modules[__name__], _prepare, _filtering, _auto, _ownership,
                        _threshold, _plates, _visible, _poisson, _deform, _refine, _contacts,
                        _plaus, _evidence, _cap, _operators, _checks)
