"""Stage 9: is the checked surface the right shape? Compared with its segment and neighbours.

A surface can pass every topological check of SPEC §4 and still be wrong: a vertebra without its
body, a femur fused with its acetabulum, thresholds that see nothing. Measured on the working
grid, with tolerances that follow the segmentation's own coarseness ``c`` (a 3 mm AI mask is
stair-stepped by up to c; a rough user segment is smaller than the bone):

- ``missing_fraction``: of the segment's voxels deeper than c/2 inside it, the fraction outside
  the surface (the body of a vertebra that was lost); where the labels compete (within the
  ownership's contact zone of another label, or bone it gave to another bone: a label reaching
  across a joint) the CT decides, and that is not counted; pieces of the segment the surface does not
  touch at all (islands a rough segment has in the soft tissue) are left out and reported as
  ``untouched_segment_ml``, unless they are mostly bone this bone owns (``untouched_bone_ml``:
  a left-out piece of the bone, which fails the run beyond 15 % of the segment; the part of
  ``missing_fraction`` inside such pieces is ``missing_separate_fraction``, and when it alone
  takes the missing fraction over its bound the advice is about the segment, not thresholds);
- ``extra_fraction``: of the surface's voxels, the fraction farther than band + c outside the
  segment (a fused neighbour, a leak);
- ``max_excursion_mm``: the farthest a vertex lies outside the segment;
- ``neighbour_core_overlap``: the fraction of the surface's voxels inside the core of another
  label (it entered a neighbour);
- ``threshold_reach``: of the surface away from joints and caps where the CT profile shows
  the bone's edge (the evidence stage's edge), the fraction of the area whose cortex reaches
  HT: thresholds above the bone's cortex select little of its border (the surface then
  follows the segment or collapses inside the bone);
- ``edge_support`` (reported, not gated): the fraction of vertices at which the edge refinement
  found an edge it moves a vertex to (a cortex at HT and MIN_CONTRAST_HU of contrast; a thin
  cortex on thick slices has less: the real 3 mm sacrum 0.45-0.57);
- ``volume_ratio`` and ``segment_inside_fraction`` for the report;
- ``p95_excursion_mm`` beyond about 1.3 c: a warning (an unlabelled neighbour taken in?);
- ``core_missing_fraction``: as ``missing_fraction`` for the voxels deeper than c/2 + 1 mm;
  beyond 5 % a warning (a part of the bone lost, or a generous label);
- ``segment_reach_mm``: the farthest the segment (as for ``missing_fraction``, at any depth)
  lies outside the surface. The missing fractions count only the segment's thick parts, so a
  thin process that the surface stops short of (a coccygeal tail, a transverse process's tip or
  an iliac crest on thick slices, whose blurred cortex is below HT) passes them unseen; beyond
  the excursion bound's EXCURSION_COARSENESS x c + EXCURSION_MM (the farthest a segment that
  coarse misplaces the bone's border), by at least one of its voxels (c^3), it is a warning with
  its volume and place.

:func:`gate` turns them into problems with advice; the pipeline fails on them, or only warns when
the user allows it (``on_implausible = "warn"``). Cut faces (caps) lie at the image boundary: the
segment is compared inside the image only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from ..mesh.operators import sample_field
from .threshold import bbox_slices
from ..mesh.distance import distance_inside, distance_outside

# Bounds: a run outside them fails (or warns).
MAX_MISSING_FRACTION = 0.15
# A warning (not a failure) when more than MISSING_WARN_FRACTION of the segment's voxels deeper
# than c/2 + MISSING_WARN_DEPTH_MM inside it (and away from other labels) are outside the
# surface: a part of the bone lost, or a generous label. The surface and a label may disagree by
# about a millimetre on where a blurred edge lies, so the measure starts that much deeper than
# the failure bound's c/2. Measured on surfaces that follow the CT's edge (looked at over the
# CT): a 1.5 mm T12 10.5 % of the voxels deeper than c/2 outside, 0.4 % of those deeper than
# c/2 + 1 mm; humeri of a 0.98 x 2 mm slab whose AI label is 2-4 mm generous 10.4 / 7.6 % and
# 3.6 / 1.9 %; all 18 written bones of the 3 mm pelvis CT at most 4.3 %.
MISSING_WARN_FRACTION = 0.05
MISSING_WARN_DEPTH_MM = 1.0
# A piece of the segment that the surface does not touch is an island of a rough segment when
# it is smaller than UNTOUCHED_MIN_ML or less than UNTOUCHED_BONE_SHARE of it is bone this bone
# owns (an island of a rough mask may lie on an unlabelled neighbour); otherwise it is a piece
# of the bone that was left out, and more than MAX_UNTOUCHED_FRACTION of the segment in such
# pieces fails the run (a bone cut by the image boundary into two pieces lost one of them).
UNTOUCHED_BONE_SHARE = 0.5
UNTOUCHED_MIN_ML = 1.0
MAX_UNTOUCHED_FRACTION = 0.15
MAX_EXTRA_FRACTION = 0.25
# Unlabelled bone that touched the bone without a visible joint space and was merged into it
# (a bitten-off end of a rough segment, or a neighbour fused across a joint the CT does not
# resolve): more than MAX_UNLABELLED_FRACTION of the surface's volume and UNLABELLED_MIN_ML
# fails the run (label that bone, or extend the segment).
MAX_UNLABELLED_FRACTION = 0.03
UNLABELLED_MIN_ML = 1.0
MAX_CORE_OVERLAP = 0.02
# At least this fraction of the border the CT shows (free surface) reaches HT. Measured: at
# the automatic thresholds 0.81-1.0 (the femur phantoms 1.0, the 3 mm anatomical phantoms
# 0.92-1.0, real 3 mm L1-L5 0.91-0.97, the real 3 mm sacrum with its hip bone and femur 0.81);
# the real 3 mm L4 with H0/HT above its cortex: 300/250 0.71, 400/350 0.48 (p95 1.94 against
# 1.47 mm at the automatic ones), 600/550 0.30 and 900/850 0.36 (a piece of the bone left).
MIN_THRESHOLD_REACH = 0.5
# A bone whose contact with another bone (labelled or not) shows a joint space on less than
# JOINT_WARN_SEEN of it, over more than JOINT_WARN_MIN_MM2, gets a warning: there the boundary
# between them follows the labels alone (a narrow joint on thick slices).
JOINT_WARN_SEEN = 0.5
JOINT_WARN_MIN_MM2 = 25.0
# Against bone that no segment labels there are no labels to follow: the boundary is the
# flooding's guess. More than MAX_UNSEEN_UNLABELLED_CONTACT of the surface's area in such
# contact fails the run (label the neighbour). Measured (share of the surface, unseen contact
# with the unlabelled cup): femur phantoms at 1-1.5 mm slices 3.5-7.6 % (surfaces right, p95
# <= 0.14 mm); at 2.5 mm slices 20-24 % (fused with the cup, or cut off inside the head: p95
# 1.5-3.0 mm, max 5.3-9.6 mm).
MAX_UNSEEN_UNLABELLED_CONTACT = 0.15
# The comparison runs on blocks of about this size (mm).
COARSE_MM = 1.0
# A warning (not a failure) when the p95 of the vertices' distance outside the segment passes
# EXCURSION_WARN_COARSENESS x coarseness + EXCURSION_WARN_MM: a surface that follows its bone
# stays within about half the coarseness of a segment of it (measured: 0.45-1.1 c on the
# phantoms and real CT) and well beyond it when it took in an unlabelled neighbour (1.5-1.6 c
# on the 2.5 mm-slice joint phantom).
EXCURSION_WARN_COARSENESS = 1.3
EXCURSION_WARN_MM = 0.5
# A warning (not a failure) when the surface's enclosed volume differs from the segment's by
# more than VOLUME_WARN_FRACTION of it. A segment on a coarse grid commonly differs by that much
# from the bone the CT shows (the real 3 mm L1-L5: 0.89-0.93 of their labels, 0.94-0.98 at
# edge_level 0.5; the 3 mm lumbar phantoms built from those labels, whose AI-style labels are
# 0.98-1.01 x the exact truth: the surfaces 1.12-1.19 x the labels), so the run is not
# refused: the user is told, with the mean offset it amounts to.
VOLUME_WARN_FRACTION = 0.05
# The segment's genus is measured after smoothing by this many times its coarseness (sigma).
SEGMENT_GENUS_SIGMA = 0.5
# plugged_tunnels: the segment within this many times its coarseness of the surface may plug
# its holes (a hole in a plate of a few mm, the segment's plate over it).
PLUG_REACH_COARSENESS = 2.0
# Excursion allowed beyond the band, in units of the coarseness, plus a constant.
EXCURSION_COARSENESS = 2.0
EXCURSION_MM = 2.0


@dataclass
class Plausibility:
    """What a surface is compared with its segment (see the module doc); ``problems`` is the
    list of bounds it breaks, each with advice."""

    segment_ml: float = 0.0
    surface_ml: float = 0.0
    volume_ratio: float = 0.0
    segment_inside_fraction: float = 0.0
    missing_fraction: float = 0.0
    # The part of ``missing_fraction`` in pieces of the segment the surface does not reach
    # (``untouched_bone_ml``): a separate piece, not thresholds that miss the bone.
    missing_separate_fraction: float = 0.0
    core_missing_fraction: float = 0.0
    extra_fraction: float = 0.0
    max_excursion_mm: float = 0.0
    p95_excursion_mm: float = 0.0
    neighbour_label_overlap: float = 0.0
    neighbour_core_overlap: float = 0.0
    edge_support: float = 1.0
    threshold_reach: float = 1.0
    untouched_segment_ml: float = 0.0
    untouched_pieces: int = 0
    untouched_bone_ml: float = 0.0
    unsupported_segment_ml: float = 0.0
    # The segment's deep part outside the surface not counted as missing: beyond a CT edge of
    # the surface (within the coarseness) or soft tissue on the CT (a generous segment).
    segment_beyond_edge_ml: float = 0.0
    unsupported_pieces: int = 0
    # The farthest the segment lies outside the surface (mm), the segment's volume farther out
    # than the warning's bound (ml), and where its farthest voxel is (x-y-z mm of the box, the
    # pipeline gives it in LPS).
    segment_reach_mm: float = 0.0
    segment_reach_ml: float = 0.0
    segment_reach_at: list | None = None
    # The step (mm) of the grid the segment's reach was measured on.
    reach_grid_mm: float = 0.0
    unlabelled_bone_ml: float = 0.0
    # Bone outside every segment that continues this bone (merged, see ownership step 4) and
    # that the surface holds (ml): what the segment missed of it.
    added_bone_ml: float = 0.0
    # Contact with bone no segment labels (mm^2), the share of it where a joint space is seen,
    # and the surface's area (mm^2).
    unlabelled_contact_mm2: float = 0.0
    unlabelled_contact_seen: float = 1.0
    surface_area_mm2: float = 0.0
    segment_genus: int | None = None
    # Tunnels of the surface through a thin plate the CT shows (pipeline._plate_holes:
    # stages.plates.holes_across_plates' "tunnels" and "plugs").
    plate_holes: dict = field(default_factory=dict)
    bounds: dict = field(default_factory=dict)
    problems: list = field(default_factory=list)
    warnings: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


def measure(inside: np.ndarray, vertices: np.ndarray, label: np.ndarray, neighbours: np.ndarray,
            neighbour_cores: np.ndarray, in_image: np.ndarray, spacing: float, *,
            volume_mm3: float, coarseness: float, band_mm: float,
            edge_support: float, threshold_reach: float = float("nan"),
            owned: np.ndarray | None = None,
            unsupported: np.ndarray | None = None, unsupported_pieces: int = 0,
            unlabelled: np.ndarray | None = None,
            added: np.ndarray | None = None,
            others_owned: np.ndarray | None = None,
            contact_mm: float = 0.0,
            soft_tissue: np.ndarray | None = None,
            edge_points: np.ndarray | None = None) -> Plausibility:
    """Compare a surface with its segment on a box of the working grid.

    Parameters
    ----------
    inside : (z, y, x) bool array
        Voxels inside the surface (the box of ``label``).
    vertices : (n, 3) float array
        The surface's vertices, x-y-z millimetres relative to the box corner.
    label, neighbours, neighbour_cores, in_image : (z, y, x) bool arrays
        The bone's segment, the other labels, their cores, and the voxels inside the CT image.
    spacing : float
        Voxel size in mm.
    volume_mm3 : float
        The surface's enclosed volume.
    coarseness, band_mm : float
        The segmentation's coarseness and how far a bone may reach beyond its label (mm).
    edge_support : float
        Fraction of vertices with a CT edge (edge refinement); NaN when it did not run.
    threshold_reach : float
        Of the free surface whose CT profile shows the bone's edge, the fraction reaching HT
        (:func:`.evidence.vertex_evidence`); NaN when not measured (no gate).
    owned : (z, y, x) bool array, optional
        The bone evidence this bone owns: an untouched piece of the segment that is mostly
        owned bone is a left-out piece of the bone, not an island.
    unsupported : (z, y, x) bool array, optional
        Parts of the segment that the CT shows to be soft tissue (left out of the bone by
        :func:`.ownership.unsupported_parts`): not counted as missing, reported in ml with
        ``unsupported_pieces`` (their number).
    unlabelled : (z, y, x) bool array, optional
        Bone outside every segment that touched this bone without a joint space and was
        merged into it (:attr:`.ownership.Ownership.merged`): how much of it the surface holds
        is ``unlabelled_bone_ml``.
    added : (z, y, x) bool array, optional
        Bone outside every segment merged into this bone as its own (:attr:`.ownership.
        Ownership.added`: it continues the bone without a joint space): how much of it the
        surface holds is ``added_bone_ml``; the surface's excursion beyond the segment
        (``max_excursion_mm``, ``extra_fraction``) is measured from the segment and it.
    others_owned : (z, y, x) bool array, optional
        Bone that the ownership gave to another bone (a label reaching across a joint into
        its neighbour): not counted as missing.
    contact_mm : float
        Within this of another label the labels compete and the CT decides where one bone ends
        (the ownership's contact zone): not counted as missing either.
    soft_tissue : (z, y, x) bool array, optional
        Voxels the CT shows to be soft tissue (below the label's bone level): a generous
        segment's margin beside a plate thinner than it, not missing bone.
    edge_points : (k, 3) float array, optional
        The surface's vertices on a CT edge (x-y-z mm relative to the box corner): the segment
        outside the surface within ``coarseness`` of one lies beyond a cortical edge the CT
        shows - the segment's generosity, not missing bone.
    """
    unsupported_ml = 0.0
    unlabelled_ml = 0.0
    if unlabelled is not None:
        unlabelled_ml = float((unlabelled & inside).sum() * spacing ** 3 / 1000.0)
    added_ml = 0.0 if added is None else float((added & inside).sum() * spacing ** 3 / 1000.0)
    if unsupported is not None:
        unsupported = unsupported & label & in_image
        unsupported_ml = float(unsupported.sum() * spacing ** 3 / 1000.0)
        label = label & ~unsupported
    label = label & in_image
    # Bone merged as this bone's own continues it without a joint space (a part the segment
    # missed, such as a thin plate between its labelled parts): how far the surface reaches
    # beyond the segment is measured from the segment and that bone together.
    spanned = label if added is None else label | (added & in_image)
    # Depth in the segment, from a voxel's centre to the label's boundary (half a voxel less
    # than the distance to the nearest centre outside), on the working grid: measured on the
    # blocks below, a block at the label's edge counted as a block deep (its centre lies half
    # a block inside), and the outer layer of a coarse label that overhangs the bone's edge -
    # outside the bone, rightly outside the surface - counted as missing bone (15-16 % of a
    # 3 mm acetabular shell on 2.5 mm slices, every such block 0.26-1.2 mm outside the truth).
    depth = distance_inside(np.pad(label, 1))[1:-1, 1:-1, 1:-1]
    depth *= spacing  # in place: two fewer float volumes at the run's peak of memory
    depth -= 0.5 * spacing
    deep_enough = depth > 0.5 * coarseness
    core_deep = depth > 0.5 * coarseness + MISSING_WARN_DEPTH_MM
    del depth
    # Bounds of a few mm need no sub-millimetre grid: measure on blocks of about 1 mm.
    f = max(1, int(round(COARSE_MM / spacing)))
    if f > 1:
        deep_enough = _block_majority(deep_enough, f)
        core_deep = _block_majority(core_deep, f)
        label = _block_majority(label, f)
        spanned = _block_majority(spanned, f)
        inside = _block_majority(inside, f)
        neighbours = _block_majority(neighbours, f)
        neighbour_cores = _block_majority(neighbour_cores, f)
        in_image = _block_majority(in_image, f)
        if owned is not None:
            owned = _block_majority(owned, f)
        if others_owned is not None:
            others_owned = _block_majority(others_owned, f)
        if soft_tissue is not None:
            soft_tissue = _block_majority(soft_tissue, f)
        spacing = spacing * f
        vertices = vertices - 0.5 * (spacing - spacing / f)  # block centres are offset
        if edge_points is not None:
            edge_points = edge_points - 0.5 * (spacing - spacing / f)
        label &= in_image
        spanned |= label
    voxel = spacing ** 3
    seg_n = int(label.sum())
    in_n = int(inside.sum())
    d_out = distance_outside(spanned) * spacing
    # Pieces of the segment that the surface does not touch at all (islands of a rough segment
    # in the soft tissue) are reported, not counted as missing bone.
    pieces, n_pieces = ndimage.label(label, structure=np.ones((3, 3, 3), bool))
    touched = np.zeros(n_pieces + 1, bool)
    touched[np.unique(pieces[inside & label])] = True
    touched[0] = False
    untouched = label & ~touched[pieces]
    bone_piece = np.zeros(n_pieces + 1, bool)
    if owned is not None and untouched.any():
        size = np.bincount(pieces[untouched], minlength=n_pieces + 1)
        bone = np.bincount(pieces[untouched & owned], minlength=n_pieces + 1)
        bone_piece = ((bone >= UNTOUCHED_BONE_SHARE * np.maximum(size, 1))
                      & (size * voxel >= UNTOUCHED_MIN_ML * 1000.0))
        bone_piece[0] = False
    left_out = untouched & bone_piece[pieces]
    islands = untouched & ~left_out
    part = label & ~islands
    if others_owned is not None:
        part &= ~others_owned
    if contact_mm > 0 and neighbours.any():
        part &= distance_outside(neighbours) * spacing > contact_mm
    deep = part & deep_enough
    # The CT outranks a generous segment: what it shows as soft tissue, and what lies outside
    # the surface within the segment's coarseness of a vertex on a CT edge (a segment thicker
    # than the plate it covers), is the segment's margin, not missing bone. A part of the bone
    # left out lies farther from every edge, or is bright.
    excused = np.zeros(deep.shape, bool)
    if soft_tissue is not None:
        excused |= deep & soft_tissue & ~inside
    if edge_points is not None and len(edge_points) and (deep & ~inside & ~excused).any():
        from scipy.spatial import cKDTree

        cand = np.argwhere(deep & ~inside & ~excused)
        dist, _ = cKDTree(edge_points).query(cand[:, ::-1] * spacing, workers=-1)
        near = cand[dist <= coarseness]
        excused[tuple(near.T)] = True
    excused_ml = 0.0
    if (deep & ~excused).any():
        excused_ml = float(excused.sum() * voxel / 1000.0)
        deep &= ~excused
    if not deep.any():
        deep = part if part.any() else label
    missing = float((deep & ~inside).sum() / max(deep.sum(), 1))
    missing_separate = float((deep & ~inside & left_out).sum() / max(deep.sum(), 1))
    core = deep & core_deep
    core_missing = float((core & ~inside).sum() / max(core.sum(), 1))
    extra = float((inside & in_image & (d_out > band_mm + coarseness)).sum() / max(in_n, 1))
    reach_mm, reach_ml, reach_at = _segment_reach(part & ~inside, inside, spacing,
                                                  reach_bound_mm(coarseness))
    if reach_at is not None and f > 1:
        reach_at = [v + 0.5 * (spacing - spacing / f) for v in reach_at]  # the block's centre
    exc = sample_field(d_out.astype(np.float32), vertices, spacing, cval=0.0)
    p = Plausibility(
        segment_ml=seg_n * voxel / 1000.0, surface_ml=volume_mm3 / 1000.0,
        volume_ratio=float(volume_mm3 / max(seg_n * voxel, 1e-9)),
        segment_inside_fraction=float((label & inside).sum() / max(seg_n, 1)),
        missing_fraction=missing, missing_separate_fraction=missing_separate,
        core_missing_fraction=core_missing, extra_fraction=extra,
        max_excursion_mm=float(exc.max()) if len(exc) else 0.0,
        p95_excursion_mm=float(np.percentile(exc, 95)) if len(exc) else 0.0,
        neighbour_label_overlap=float((inside & neighbours).sum() / max(in_n, 1)),
        neighbour_core_overlap=float((inside & neighbour_cores).sum() / max(in_n, 1)),
        edge_support=float(edge_support), threshold_reach=float(threshold_reach),
        untouched_segment_ml=float(islands.sum() * voxel / 1000.0),
        untouched_pieces=int(len(np.unique(pieces[islands]))),
        untouched_bone_ml=float(left_out.sum() * voxel / 1000.0),
        unsupported_segment_ml=unsupported_ml, unsupported_pieces=int(unsupported_pieces),
        segment_beyond_edge_ml=excused_ml,
        segment_reach_mm=reach_mm, segment_reach_ml=reach_ml, segment_reach_at=reach_at,
        reach_grid_mm=float(spacing), unlabelled_bone_ml=unlabelled_ml, added_bone_ml=added_ml)
    return p


def percent_text(fraction: float) -> str:
    """A fraction as a whole percentage for a warning; "under 1 %" for a positive fraction
    below 1 % (it would round to 0: a contact seen on a few voxels is not seen nowhere)."""
    if 0.0 < fraction < 0.01:
        return "under 1 %"
    return f"{100 * fraction:.0f} %"


def reach_bound_mm(coarseness: float) -> float:
    """How far a segment this coarse (mm) may lie outside a surface that follows its bone
    before :func:`gate` warns (mm): the farthest it misplaces the bone's border."""
    return EXCURSION_COARSENESS * coarseness + EXCURSION_MM


def _segment_reach(outside: np.ndarray, inside: np.ndarray, spacing: float,
                   bound_mm: float) -> tuple:
    """(farthest distance (mm) of a voxel of ``outside`` (z, y, x bool: the segment outside
    the surface) from ``inside`` (the surface's voxels), the volume (ml) of those farther than
    ``bound_mm``, and the farthest voxel's centre (x-y-z mm of the box) or None)."""
    if not outside.any() or not inside.any():
        return 0.0, 0.0, None
    dist = distance_outside(inside)[outside] * spacing
    far = int(np.argmax(dist))
    at = np.argwhere(outside)[far][::-1] * spacing
    return (float(dist[far]), float((dist > bound_mm).sum() * spacing ** 3 / 1000.0),
            [float(v) for v in at])


def _block_majority(mask: np.ndarray, f: int) -> np.ndarray:
    """``mask`` on blocks of f^3 voxels: a block is set when at least half of it is."""
    pad = [(0, (-s) % f) for s in mask.shape]
    m = np.pad(np.asarray(mask, bool), pad).view(np.uint8)
    # The sum of the f^3 strided sub-grids: 10x faster than summing the blocks' axes of a
    # (z, f, y, f, x, f) view (5 against 59 ms on a 7 M-voxel box, f = 2).
    count = np.zeros(tuple(s // f for s in m.shape), np.uint8 if f ** 3 <= 255 else np.uint16)
    for i in range(f):
        for j in range(f):
            for k in range(f):
                count += m[i::f, j::f, k::f]
    return count.astype(np.uint32) * 2 >= f ** 3


def _threshold_advice(estimated) -> str:
    """What to do about thresholds that select too little of the bone: the user's own values
    can go back to the estimate; estimated ones (``estimated``: (H0, HT) HU) only lower."""
    if estimated is not None:
        return (f"Set H0 / HT below the estimated {estimated[0]:.0f} / {estimated[1]:.0f} HU "
                "(options h0, ht)")
    return "Use automatic thresholds (h0/ht auto) or lower H0/HT"


def gate(p: Plausibility, *, coarseness: float, band_mm: float, name: str,
         estimated=None, where_text=None) -> Plausibility:
    """Fill ``p.bounds`` and ``p.problems`` (each problem says what is wrong and what to do;
    ``estimated``: (H0, HT) in HU when both were estimated, not the user's; None otherwise;
    ``where_text``: optional callable giving a place of the box (x-y-z mm) as text for a
    message)."""
    advice = _threshold_advice(estimated)
    max_exc = band_mm + reach_bound_mm(coarseness)
    p.bounds = {"missing_fraction_max": MAX_MISSING_FRACTION,
                "unlabelled_fraction_max": MAX_UNLABELLED_FRACTION,
                "untouched_fraction_max": MAX_UNTOUCHED_FRACTION,
                "extra_fraction_max": MAX_EXTRA_FRACTION,
                "max_excursion_mm": max_exc, "neighbour_core_overlap_max": MAX_CORE_OVERLAP,
                "threshold_reach_min": MIN_THRESHOLD_REACH}
    problems = []
    untouched = p.untouched_bone_ml / max(p.segment_ml, 1e-9)
    separate = untouched > MAX_UNTOUCHED_FRACTION
    if separate:
        # First: a separate piece is the cause the user can act on, and it also counts in the
        # missing fraction below.
        problems.append(
            f"{name}: {p.untouched_bone_ml:.1f} ml of the segment ({100 * untouched:.0f} %) is a "
            "separate piece of bone that the surface does not reach (one closed surface holds one "
            "piece): where the bone is cut by the image boundary into pieces, use a CT that "
            "contains more of it; otherwise split the segment into one segment per piece or "
            "remove the stray piece")
    if p.missing_fraction > MAX_MISSING_FRACTION:
        rest = p.missing_fraction - p.missing_separate_fraction
        head = (f"{name}: {100 * p.missing_fraction:.0f} % of what the segment clearly covers is "
                f"outside the surface (at most {100 * MAX_MISSING_FRACTION:.0f} %)")
        if separate and rest <= MAX_MISSING_FRACTION:
            # The separate piece explains it: threshold advice would mislead.
            problems.append(
                f"{head}, {100 * p.missing_separate_fraction:.0f} % of it in the separate piece "
                f"above (without it {100 * rest:.0f} %): correct the segment as said there")
        else:
            problems.append(f"{head}: part of the bone is missing. {advice}, or check that the "
                            "segment is this bone")
    if p.extra_fraction > MAX_EXTRA_FRACTION:
        problems.append(
            f"{name}: {100 * p.extra_fraction:.0f} % of the surface's volume lies more than "
            f"{band_mm + coarseness:.1f} mm outside the segment (at most "
            f"{100 * MAX_EXTRA_FRACTION:.0f} %): it grew into a neighbour or soft tissue. Label "
            "the neighbouring bone (every other label is a neighbour), raise H0, or correct the "
            "segment")
    unlabelled = p.unlabelled_bone_ml / max(p.surface_ml, 1e-9)
    if unlabelled > MAX_UNLABELLED_FRACTION and p.unlabelled_bone_ml >= UNLABELLED_MIN_ML:
        problems.append(
            f"{name}: {p.unlabelled_bone_ml:.1f} ml ({100 * unlabelled:.0f} % of the surface's "
            "volume) is bone outside every segment that touches this bone without a joint space "
            "the CT resolves: the surface has probably fused with an unlabelled neighbouring "
            "bone. Label that bone (every other label competes as a neighbour), or, if it is "
            "part of this bone, extend the segment over it")
    unseen = p.unlabelled_contact_mm2 * (1.0 - p.unlabelled_contact_seen)
    p.bounds["unseen_unlabelled_contact_max"] = MAX_UNSEEN_UNLABELLED_CONTACT
    if p.surface_area_mm2 > 0 and unseen > MAX_UNSEEN_UNLABELLED_CONTACT * p.surface_area_mm2:
        problems.append(
            f"{name}: {unseen:.0f} mm^2 ({100 * unseen / p.surface_area_mm2:.0f} % of the surface, "
            f"at most {100 * MAX_UNSEEN_UNLABELLED_CONTACT:.0f} %) touch bone that no segment "
            "labels without a joint space the CT resolves: where this bone ends and the "
            "unlabelled bone begins is a guess there (the surface may have fused with it, or stop "
            "short inside this bone). Label the neighbouring bone (every other label competes as "
            "a neighbour) and run again")
    if p.max_excursion_mm > max_exc:
        problems.append(
            f"{name}: the surface reaches {p.max_excursion_mm:.1f} mm outside the segment (at most "
            f"{max_exc:.1f} mm): it is probably fused with a neighbour there. Label the "
            "neighbouring bone or correct the segment")
    if p.neighbour_core_overlap > MAX_CORE_OVERLAP:
        problems.append(
            f"{name}: {100 * p.neighbour_core_overlap:.1f} % of the surface's volume is inside "
            "another label's core (it entered a neighbouring bone). Check the labels at the joint")
    if np.isfinite(p.threshold_reach) and p.threshold_reach < MIN_THRESHOLD_REACH:
        problems.append(
            f"{name}: where the CT shows the bone's edge, its cortex reaches HT under only "
            f"{100 * p.threshold_reach:.0f} % of the surface (at least "
            f"{100 * MIN_THRESHOLD_REACH:.0f} %): the thresholds select little of the bone's "
            f"border. {advice}")
    p.problems = problems
    warn_exc = EXCURSION_WARN_COARSENESS * coarseness + EXCURSION_WARN_MM
    p.bounds["p95_excursion_warn_mm"] = warn_exc
    p.warnings = []
    p.bounds["core_missing_fraction_warn"] = MISSING_WARN_FRACTION
    core_warned = p.core_missing_fraction > MISSING_WARN_FRACTION and not problems
    if core_warned:
        p.warnings.append(
            f"{name}: {100 * p.core_missing_fraction:.0f} % of what the segment clearly covers "
            f"(more than {0.5 * coarseness + MISSING_WARN_DEPTH_MM:.1f} mm inside it) is outside "
            "the surface, which encloses "
            f"{p.surface_ml:.1f} ml against the segment's {p.segment_ml:.1f} ml "
            f"({100 * p.volume_ratio:.0f} %): part of the bone may be missing, or the segment is "
            "generous there. Compare the surface with the CT in the picture; where the CT shows "
            "bone the surface leaves out, use automatic thresholds or lower H0/HT")
    if (not problems and p.unlabelled_contact_mm2 > JOINT_WARN_MIN_MM2
            and p.unlabelled_contact_seen < JOINT_WARN_SEEN):
        p.warnings.append(
            f"{name} | unlabelled bone: the CT shows a joint space on only "
            f"{percent_text(p.unlabelled_contact_seen)} of their {p.unlabelled_contact_mm2:.0f} "
            "mm^2 contact; elsewhere the boundary is a guess: if that bone is a neighbour, "
            "label it; if it continues this bone (a part the segment missed, such as a thin "
            "blade beyond a coarse label), extend the segment over it; then check the surface "
            "there")
    if p.p95_excursion_mm > warn_exc and not problems:
        p.warnings.append(
            f"{name}: 5 % of the surface lies more than {p.p95_excursion_mm:.1f} mm outside the "
            f"segment (expected below {warn_exc:.1f} mm for a segment this coarse): it may have "
            "taken in an unlabelled neighbouring bone. Label the neighbours (every other label "
            "competes) and check the surface there")
    reach = reach_bound_mm(coarseness)
    p.bounds["segment_reach_warn_mm"] = reach
    # (less than one of the segment's own voxels out there is its stair step, not a process -
    # unless it is a process one of the segment's voxels across that goes on at least a grid
    # step beyond the bound: a 3 mm coccygeal tail 9.5 mm beyond the surface held 15 mm^3)
    step = p.reach_grid_mm
    far_enough = (1000.0 * p.segment_reach_ml >= coarseness ** 3
                  or (step > 0 and p.segment_reach_mm > reach + step
                      and 1000.0 * p.segment_reach_ml >= coarseness ** 2 * step))
    if p.segment_reach_mm > reach and far_enough and not problems:
        p.warnings.append(
            f"{name}: the segment reaches {p.segment_reach_mm:.1f} mm beyond the surface "
            f"({1000 * p.segment_reach_ml:.0f} mm^3 of it farther than {reach:.1f} mm, the most "
            "a segment this coarse misplaces the bone's border"
            + (f"; farthest at {where_text(p.segment_reach_at)}"
               if where_text is not None and p.segment_reach_at is not None else "")
            + "): the surface stops short of a part of the segment - a thin process whose "
            "blurred cortex the CT shows below HT (a tip cut off), or a part the segment has "
            "wrong. Compare the surface with the segment and the CT there")
    p.bounds["volume_ratio_warn"] = [1.0 - VOLUME_WARN_FRACTION, 1.0 + VOLUME_WARN_FRACTION]
    # (the core warning above already gives both volumes)
    if (not problems and not core_warned and p.segment_ml > 0 and p.surface_ml > 0
            and abs(p.volume_ratio - 1.0) > VOLUME_WARN_FRACTION):
        offset = (p.surface_ml - p.segment_ml) * 1000.0 / max(p.surface_area_mm2, 1e-9)
        where = (f": on average its boundary lies {abs(offset):.2f} mm "
                 f"{'inside' if offset < 0 else 'outside'} the segment's"
                 if p.surface_area_mm2 > 0 else "")
        p.warnings.append(
            f"{name}: the surface encloses {p.surface_ml:.1f} ml, {100 * p.volume_ratio:.0f} % "
            f"of the segment's {p.segment_ml:.1f} ml{where}. Either the segment is that much "
            f"{'generous' if offset < 0 else 'tight'} (common for a segment on a coarse grid) or "
            "the surface misses the bone's edge: compare both with the CT in the picture"
            + ("; edge_level 0.5 (the half maximum) puts the surface further out than the "
               "automatic level where the cortex is thin" if offset < 0 else ""))
    return p


def image_mask(box: tuple, caps, spacing: float) -> np.ndarray:
    """Voxels of ``box`` inside the CT image (the cap planes' inner side)."""
    shape = tuple(s.stop - s.start for s in box)
    inside = np.ones(shape, bool)
    idx = np.indices(shape, sparse=True)  # (z, y, x)
    for plane in caps:
        coord = (idx[2 - plane.axis] + box[2 - plane.axis].start) * spacing
        inside &= (coord - plane.position) * plane.side <= 0
    return inside


def box_of(mask: np.ndarray, pad: int) -> tuple:
    return bbox_slices(mask, pad)


def segment_genus(label: np.ndarray, spacing: float, coarseness: float = 0.0) -> int:
    """Genus of the largest closed surface of a binary segment (z, y, x): its tunnels, e.g. 1
    for a vertebra's canal or a hip bone's obturator foramen.

    The segment is contoured at 0.5 after smoothing by a Gaussian of SEGMENT_GENUS_SIGMA x
    ``coarseness`` (mm): a segment stair-stepped on its own coarse grid (an AI label resampled
    onto the CT) has tunnels of a voxel where its voxels touch at an edge, and holes smaller
    than its own resolution, which say nothing of the bone's tunnels."""
    from .poisson import raw_genus

    # (a 0 / 1 field: every point of the contour mid-edge, none to merge)
    return raw_genus(np.pad(smoothed_segment(label, spacing, coarseness), 1).astype(np.float32))


def smoothed_segment(label: np.ndarray, spacing: float, coarseness: float) -> np.ndarray:
    """The segment (z, y, x bool) at its own resolution: its indicator smoothed by a Gaussian
    of SEGMENT_GENUS_SIGMA x ``coarseness`` (mm), at the 0.5 level (bool, same shape)."""
    sigma = SEGMENT_GENUS_SIGMA * coarseness / spacing
    if sigma <= 0.3:
        return np.asarray(label, bool)
    pad = int(np.ceil(3 * sigma))
    field = ndimage.gaussian_filter(np.pad(label, pad).astype(np.float32), sigma)
    return field[pad:-pad, pad:-pad, pad:-pad] >= 0.5


def plugged_tunnels(inside: np.ndarray, segment: np.ndarray, spacing: float,
                    coarseness: float) -> int:
    """How many tunnels of a surface its segment plugs: holes of the surface where the segment
    has bone.

    The genus of the surface's voxels less that of their union with the segment (at its own
    resolution, :func:`smoothed_segment`) within ``PLUG_REACH_COARSENESS`` x ``coarseness``
    of them: a hole in a plate is covered by the segment's plate around it; farther parts of
    the segment could only bridge new tunnels. 0 when the surface has its extra tunnels
    through bone the segment leaves out (a vertebral arch the segment leaves open on thick
    slices closes a ring the segment does not have).

    Parameters
    ----------
    inside, segment : (z, y, x) bool arrays
        The surface's voxels and the bone's segment on one box of the working grid.
    spacing, coarseness : float
        The grid's step and the segment's coarseness (mm).
    """
    from .poisson import raw_genus

    near = smoothed_segment(segment, spacing, coarseness) & \
        (distance_outside(inside) * spacing <= PLUG_REACH_COARSENESS * coarseness)
    alone = raw_genus(np.pad(inside, 1).astype(np.float32))
    joined = raw_genus(np.pad(inside | near, 1).astype(np.float32))
    return max(0, alone - joined)


def tunnel_warning(name: str, surface_genus: int, segment_genus: int,
                   plugged: int | None = None) -> list:
    """A warning when the surface has more tunnels than its segment: bone too thin for the
    thresholds (an iliac wing or a sinus wall on thick slices) came out as a hole, or, when
    the segment plugs none of them (``plugged`` = 0, :func:`plugged_tunnels`), the surface
    closes a ring through bone the segment leaves out."""
    if surface_genus <= segment_genus:
        return []
    extra = surface_genus - segment_genus
    head = (f"{name}: the surface has {extra} tunnel{'s' if extra > 1 else ''} more than its "
            f"segment (genus {surface_genus} against {segment_genus})")
    if plugged == 0:
        return [f"{head}, through bone the segment leaves out: the segment covers none of them, "
                "the surface closes a ring the segment leaves open (a vertebral arch or the rim "
                "of a foramen the segment misses). Check the segment there"]
    return [f"{head}: where the bone is thinner than the CT resolves it may have come out as a "
            "hole. Check the surface; a lower HT or a finer CT closes it"]
