"""The typed reports of a run, their one summary line and the one (NaN-safe) JSON writer.

Consumers read reports by attribute (``report.timings.total``), so a renamed field fails loudly
instead of printing null. :func:`to_json` turns any report into JSON with NaN/inf as null.

- :class:`PipelineReport`: what :func:`BoneWatertightLib.pipeline.reconstruct` measured.
- :class:`CaseReport`: one case run by :mod:`BoneWatertightLib.app.run` (files written, timings).
- :class:`Fallback`: a stage that could not take its normal step and took a safer one; the
  stages note them in a :class:`FallbackLog` they are given, the reports list them and the
  summary line counts them, so a report never claims a stage that did not run.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
from dataclasses import dataclass, field
from typing import Optional

import numpy as np


# The summary line names the bone taken in beyond the segment from this volume (ml) on: below
# it the pieces are a few stair steps of a coarse label.
ADDED_SHOWN_ML = 0.05


@dataclass
class StageTimes:
    """Seconds spent in each pipeline stage (``total`` includes everything)."""

    import_open3d: float = 0.0
    prepare: float = 0.0
    filter: float = 0.0
    thresholds: float = 0.0     # H0 and HT estimated (shared)
    ownership: float = 0.0
    threshold: float = 0.0
    visible: float = 0.0
    poisson: float = 0.0
    territories: float = 0.0
    refine_field: float = 0.0   # the refinement's smoothed CT on its own grid (shared)
    deform: float = 0.0
    refine: float = 0.0
    contacts: float = 0.0
    cap: float = 0.0
    checks: float = 0.0
    plausibility: float = 0.0
    total: float = 0.0


@dataclass
class Counts:
    """Point and mesh sizes along the pipeline."""

    p_h0_surface_points: int = 0
    visible_points: int = 0
    ht_boundary_points: int = 0
    constraint_points: int = 0
    poisson_raw_vertices: int = 0
    m0_vertices: int = 0
    m0_faces: int = 0
    vertices: int = 0
    faces: int = 0


@dataclass
class DistanceSummary:
    """Statistics of per-vertex distances in mm (``n`` = 0: no finite value)."""

    n: int = 0
    mean: Optional[float] = None
    median: Optional[float] = None
    rms: Optional[float] = None
    p95: Optional[float] = None
    max: Optional[float] = None

    @classmethod
    def of(cls, distances) -> "DistanceSummary":
        d = np.asarray(distances if distances is not None else [], dtype=np.float64).ravel()
        d = d[np.isfinite(d)]
        if d.size == 0:
            return cls()
        return cls(n=int(d.size), mean=float(d.mean()), median=float(np.median(d)),
                   rms=float(np.sqrt(np.mean(d * d))), p95=float(np.percentile(d, 95)),
                   max=float(d.max()))


@dataclass
class Refinement:
    """Outcome of the edge refinement stage."""

    applied: bool = False
    fraction_with_edge: Optional[float] = None
    mean_shift_mm: Optional[float] = None
    mean_abs_shift_mm: Optional[float] = None
    # The blurred-slab model's full cortical contrast (HU): the bone's own, the one used, and
    # the bone of the run it came from when that was another one's (None: its own).
    own_contrast_hu: Optional[float] = None
    contrast_hu: Optional[float] = None
    contrast_from: Optional[str] = None


@dataclass
class Fallback:
    """A stage that could not take its normal step and took a safer one.

    ``stage``: the stage (a :class:`StageTimes` field where there is one: "refine",
    "deform", "thresholds", ...); ``what``: what fell back to what, one line; ``count``:
    how many times or elements (``unit``: "vertices", "points", "solves", "passes", ...);
    ``where``: which part (a mask, a cap plane, the other bone of a pair, ...).
    """

    stage: str
    what: str
    count: int = 1
    unit: str = ""
    where: str = ""

    def text(self) -> str:
        """'stage (where): what, count unit'."""
        place = f" ({self.where})" if self.where else ""
        n = f", {self.count} {self.unit}" if self.unit else ""
        return f"{self.stage}{place}: {self.what}{n}"


class FallbackLog:
    """The collector a stage is given to note its fallbacks.

    :meth:`add` merges notes of the same stage, what and where (their counts add up), so
    a step that falls back in every iteration is one record with its total. Iterating
    gives the :class:`Fallback` records in the order they first happened.
    """

    def __init__(self):
        self.records: list = []

    def add(self, stage: str, what: str, count: int = 1, unit: str = "",
            where: str = "") -> None:
        for r in self.records:
            if (r.stage, r.what, r.where, r.unit) == (stage, what, where, unit):
                r.count += int(count)
                return
        self.records.append(Fallback(stage, what, int(count), unit, where))

    def __iter__(self):
        return iter(self.records)

    def __len__(self) -> int:
        return len(self.records)


def fallbacks_text(fallbacks) -> str:
    """'fallbacks: 2 (refine: ...; deform: ...)', or '' when there is none."""
    records = list(fallbacks or [])
    if not records:
        return ""
    return f"fallbacks: {len(records)} (" + "; ".join(r.text() for r in records) + ")"


@dataclass
class PipelineReport:
    """Everything the pipeline measured for one surface (physical LPS, mm)."""

    version: str
    parameters: dict
    input: dict
    timings: StageTimes
    threshold: dict
    counts: Counts
    visible: dict
    deformation: list
    refinement: Refinement
    checks: object  # BoneWatertightLib.mesh.checks.SurfaceReport
    distance_to_constraints_mm: DistanceSummary
    mean_edge_length_mm: float = 0.0
    area_mm2: float = 0.0
    volume_mm3: float = 0.0
    constants: dict = field(default_factory=dict)
    coordinate_system: str = "LPS"
    units: str = "mm"
    label: int = 0
    name: str = ""
    thresholds: dict = field(default_factory=dict)
    ownership: dict = field(default_factory=dict)
    separation: dict = field(default_factory=dict)
    cap: dict = field(default_factory=dict)
    contacts: dict = field(default_factory=dict)
    plausibility: object = None  # BoneWatertightLib.stages.plausibility.Plausibility
    warnings: list = field(default_factory=list)
    # Per evidence class (stages.evidence): area and fraction of the surface, mean confidence
    evidence: dict = field(default_factory=dict)
    fallbacks: list = field(default_factory=list)  # Fallback records, the run's shared ones first
    # When the timed stages of this bone and the shared ones ran: {"stage", "bone", "label",
    # "start_s", "end_s"}, seconds from the start of the run (bone and label None: shared).
    stage_spans: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return to_plain(self)


@dataclass
class PairReport:
    """Two reconstructed bones checked against each other (exactly, on the final surfaces).

    ``crossing_face_pairs`` and the vertex counts inside the other must be 0; ``min_gap_mm`` is
    the smallest vertex-to-surface distance; ``contact_area_mm2`` the area of the first bone's
    surface within 1 mm of the second; ``joint_contact_mm2`` / ``joint_valley_seen_fraction``:
    where their bone evidence touched, and in what fraction of it the CT showed a joint space
    (the rest was split by the labels)."""

    a: str
    b: str
    crossing_face_pairs: int = 0
    a_inside_b: int = 0
    b_inside_a: int = 0
    min_gap_mm: Optional[float] = None
    contact_area_mm2: float = 0.0
    joint_contact_mm2: float = 0.0
    joint_valley_seen_fraction: Optional[float] = None
    warnings: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.crossing_face_pairs == 0 and self.a_inside_b == 0 and self.b_inside_a == 0


@dataclass
class JointReport:
    """What a several-bone run shares: grid, thresholds, ownership, per-pair checks, times."""

    version: str
    parameters: dict
    input: dict
    thresholds: dict
    ownership: dict
    pairs: list
    timings: StageTimes
    neighbours: list = field(default_factory=list)
    coordinate_system: str = "LPS"
    units: str = "mm"
    fallbacks: list = field(default_factory=list)  # the shared stages' Fallback records
    # When every timed stage of the run ran, the bones' included (see PipelineReport)
    stage_spans: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return to_plain(self)


@dataclass
class OutputInfo:
    """The files one case wrote. ``picture`` is None when no picture was made; then
    ``picture_error`` says why (if one was asked for)."""

    path: str
    format: str
    coordinate_system: str
    n_vertices: int
    n_faces: int
    picture: Optional[str] = None
    picture_error: Optional[str] = None
    intermediates: list = field(default_factory=list)
    also: list = field(default_factory=list)
    report: Optional[str] = None


@dataclass
class CaseTimes:
    """Seconds of one case: reading, reconstruction (with the pipeline's stages), writing."""

    read: float = 0.0
    reconstruct: float = 0.0
    render: float = 0.0
    write: float = 0.0
    total: float = 0.0
    stages: StageTimes = field(default_factory=StageTimes)


@dataclass
class CaseReport:
    """One case run by the run service: inputs, outputs, checks, distances, timings."""

    inputs: dict
    output: OutputInfo
    checks: object  # SurfaceReport
    distance_to_constraints_mm: DistanceSummary
    parameters: dict
    timings_s: CaseTimes
    pipeline: PipelineReport
    coordinate_system: str = "LPS"
    tool: str = "BoneWatertight"
    version: str = ""
    pairs: list = field(default_factory=list)

    @property
    def segment_name(self) -> str:
        return str(self.inputs.get("segment_name", ""))

    def to_dict(self) -> dict:
        return to_plain(self)


# ----------------------------------------------------------------------------------------
# named constants

def constants_of(*modules: types.ModuleType) -> dict:
    """{module name: {CONSTANT: value}} of the module-level UPPER_CASE numbers (and tuples of
    numbers) of each module: the stages' fixed settings, for the report."""
    out = {}
    for module in modules:
        values = {}
        for name, value in vars(module).items():
            if not name.isupper() or name.startswith("_"):
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float, tuple)):
                continue
            if isinstance(value, tuple) and not all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
                continue
            values[name] = list(value) if isinstance(value, tuple) else value
        out[module.__name__.rsplit(".", 1)[-1]] = values
    return out


# ----------------------------------------------------------------------------------------
# the one summary line

def summary_line(name: str, checks, distances: DistanceSummary, seconds: Optional[float],
                 n_vertices: int, n_faces: int, out: Optional[str] = None,
                 coordinate_system: Optional[str] = None,
                 picture_error: Optional[str] = None,
                 segment_genus: Optional[int] = None) -> str:
    """'<name>: V vertices, F faces, checks passed (...), distance ..., T s -> out (LPS)';
    with ``segment_genus`` (the segment's tunnels at its own resolution) where it differs from
    the surface's: both counts (a foramen or canal closed, or a segment's lace left out)."""
    if getattr(checks, "ok", False):
        genus = getattr(checks, "genus", None)
        if genus is None:
            tunnels = ""
        elif segment_genus is None or segment_genus == genus:
            tunnels = f", genus {genus}"
        else:
            tunnels = f", genus {genus}: the segment has {segment_genus} at its resolution"
        state = ("checks passed (closed, manifold, "
                 f"{getattr(checks, 'n_components', 1)} component" + tunnels + ")")
    else:
        state = "CHECKS FAILED: " + "; ".join(map(str, getattr(checks, "problems", [])))
    text = f"{name + ': ' if name else ''}{n_vertices} vertices, {n_faces} faces, {state}"
    if distances.n:
        text += (f", distance to constraints mean {distances.mean:.2f} / p95 "
                 f"{distances.p95:.2f} / max {distances.max:.2f} mm")
    if seconds is not None:
        text += f", {seconds:.1f} s"
    if out:
        text += f" -> {out}" + (f" ({coordinate_system})" if coordinate_system else "")
    if picture_error:
        text += f"; no picture: {picture_error}"
    return text


def shape_text(pipeline) -> str:
    """'volume 54.9 ml (segment 66.0 ml, 95 % of it inside), cap 120 mm^2, 1 warning: ...,
    fallbacks: 1 (...)'."""
    plaus = getattr(pipeline, "plausibility", None)
    parts = []
    if plaus is not None:
        parts.append(f"volume {plaus.surface_ml:.1f} ml (segment {plaus.segment_ml:.1f} ml, "
                     f"{100 * plaus.segment_inside_fraction:.0f} % of it inside)")
    own = getattr(pipeline, "ownership", None) or {}
    if own.get("segment_taken_ml"):
        parts.append(f"the segment includes {own['segment_taken_ml']:.1f} ml of a neighbour's "
                     "segment that lies in this bone")
    if own.get("segment_given_ml"):
        parts.append(f"{own['segment_given_ml']:.1f} ml of the segment lies in a neighbour's bone "
                     "and went to it")
    if plaus is not None and getattr(plaus, "unsupported_pieces", 0):
        n = plaus.unsupported_pieces
        parts.append(f"left out {n} part{'s' if n > 1 else ''} of the segment that the CT shows "
                     f"as soft tissue ({plaus.unsupported_segment_ml:.1f} ml)")
    if plaus is not None and getattr(plaus, "untouched_pieces", 0):
        n = plaus.untouched_pieces
        parts.append(f"left out {n} island{'s' if n > 1 else ''} of the segment that the surface "
                     f"does not reach and the CT does not show as this bone "
                     f"({plaus.untouched_segment_ml:.2f} ml)")
    if plaus is not None and getattr(plaus, "added_bone_ml", 0.0) >= ADDED_SHOWN_ML:
        parts.append(f"took in {plaus.added_bone_ml:.2f} ml of bone beyond the segment that "
                     "continues this bone without a joint space (the segment missed it)")
    evidence = (getattr(pipeline, "evidence", None) or {}).get("fraction")
    if evidence:
        shown = [f"{name} {100 * f:.0f} %" for name, f in evidence.items()
                 if f >= 0.005 and name != "cap"]
        parts.append("under the surface: " + ", ".join(shown))
    cap = getattr(pipeline, "cap", None) or {}
    if cap.get("area_mm2"):
        parts.append(f"capped at the image border ({cap['area_mm2']:.0f} mm^2)")
    warnings = getattr(pipeline, "warnings", None) or []
    if warnings:
        parts.append(f"{len(warnings)} WARNING{'S' if len(warnings) > 1 else ''}: "
                     + "; ".join(warnings))
    fallbacks = fallbacks_text(getattr(pipeline, "fallbacks", None))
    if fallbacks:
        parts.append(fallbacks)
    return ", ".join(parts)


def segment_genus_of(pipeline) -> Optional[int]:
    """The segment's tunnels at its own resolution (a pipeline report's plausibility), or None."""
    return getattr(getattr(pipeline, "plausibility", None), "segment_genus", None)


def case_summary_line(report: CaseReport) -> str:
    """The summary line of a case report."""
    out = report.output
    line = summary_line(report.segment_name, report.checks, report.distance_to_constraints_mm,
                        report.timings_s.total, out.n_vertices, out.n_faces, out.path,
                        out.coordinate_system, out.picture_error,
                        segment_genus=segment_genus_of(report.pipeline))
    shape = shape_text(report.pipeline)
    return line + (f"; {shape}" if shape else "")


def pair_summary_line(pair) -> str:
    """'<a> | <b>: smallest gap 0.31 mm, no interpenetration, joint space seen on 62 % of
    their contact'."""
    gap = "no contact" if pair.min_gap_mm is None else f"smallest gap {pair.min_gap_mm:.2f} mm"
    state = "no interpenetration" if pair.ok else (
        f"INTERPENETRATE ({pair.crossing_face_pairs} crossing face pairs)")
    seen = ""
    if pair.joint_valley_seen_fraction is not None and pair.joint_contact_mm2 > 0:
        seen = (f", joint space seen on {100 * pair.joint_valley_seen_fraction:.0f} % of their "
                f"{pair.joint_contact_mm2:.0f} mm^2 contact")
    return f"{pair.a} | {pair.b}: {gap}, {state}{seen}"


# ----------------------------------------------------------------------------------------
# JSON

def to_plain(obj):
    """Plain JSON types (dict, list, str, int, float, bool, None) from reports, numpy values,
    arrays and dataclasses; NaN and infinities become None."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): to_plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_plain(obj.tolist())
    if isinstance(obj, np.generic):
        return to_plain(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if obj is None or isinstance(obj, (str, int, bool)):
        return obj
    if hasattr(obj, "to_dict"):
        return to_plain(obj.to_dict())
    return str(obj)


def to_json(obj) -> str:
    """Indented JSON text of ``obj`` (see :func:`to_plain`); always valid JSON (no NaN)."""
    return json.dumps(to_plain(obj), indent=2, allow_nan=False) + "\n"
