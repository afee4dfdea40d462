"""Stage 9: is the checked surface the right shape? Compared with its segment and neighbours.

A surface can pass every topological check of SPEC §4 and still be wrong: a vertebra without its
body, a femur fused with its acetabulum, thresholds that see nothing. Measured on the working
grid, with tolerances that follow the segmentation's own coarseness ``c`` (a 3 mm AI mask is
stair-stepped by up to c; a rough user segment is smaller than the bone):

- ``missing_fraction``: of the segment's voxels deeper than c/2 inside it, the fraction outside
  the surface (the body of a vertebra that was lost); pieces of the segment the surface does not
  touch at all (islands a rough segment has in the soft tissue) are left out and reported as
  ``untouched_segment_ml``;
- ``extra_fraction``: of the surface's voxels, the fraction farther than band + c outside the
  segment (a fused neighbour, a leak);
- ``max_excursion_mm``: the farthest a vertex lies outside the segment;
- ``neighbour_core_overlap``: the fraction of the surface's voxels inside the core of another
  label (it entered a neighbour);
- ``edge_support``: the fraction of vertices at which the edge refinement found the CT's edge
  (thresholds that select nothing of the bone find none);
- ``volume_ratio`` and ``segment_inside_fraction`` for the report.

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
MAX_EXTRA_FRACTION = 0.25
MAX_CORE_OVERLAP = 0.02
MIN_EDGE_SUPPORT = 0.5
# The comparison runs on blocks of about this size (mm).
COARSE_MM = 1.0
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
    extra_fraction: float = 0.0
    max_excursion_mm: float = 0.0
    p95_excursion_mm: float = 0.0
    neighbour_label_overlap: float = 0.0
    neighbour_core_overlap: float = 0.0
    edge_support: float = 1.0
    untouched_segment_ml: float = 0.0
    bounds: dict = field(default_factory=dict)
    problems: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


def measure(inside: np.ndarray, vertices: np.ndarray, label: np.ndarray, neighbours: np.ndarray,
            neighbour_cores: np.ndarray, in_image: np.ndarray, spacing: float, *,
            volume_mm3: float, coarseness: float, band_mm: float,
            edge_support: float) -> Plausibility:
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
    """
    label = label & in_image
    # Bounds of a few mm need no sub-millimetre grid: measure on blocks of about 1 mm.
    f = max(1, int(round(COARSE_MM / spacing)))
    if f > 1:
        label = _block_majority(label, f)
        inside = _block_majority(inside, f)
        neighbours = _block_majority(neighbours, f)
        neighbour_cores = _block_majority(neighbour_cores, f)
        in_image = _block_majority(in_image, f)
        spacing = spacing * f
        vertices = vertices - 0.5 * (spacing - spacing / f)  # block centres are offset
        label &= in_image
    voxel = spacing ** 3
    seg_n = int(label.sum())
    in_n = int(inside.sum())
    d_in = distance_inside(np.pad(label, 1))[1:-1, 1:-1, 1:-1] * spacing
    d_out = distance_outside(label) * spacing
    # Pieces of the segment that the surface does not touch at all (islands of a rough segment
    # in the soft tissue) are reported, not counted as missing bone.
    pieces, n_pieces = ndimage.label(label, structure=np.ones((3, 3, 3), bool))
    touched = np.zeros(n_pieces + 1, bool)
    touched[np.unique(pieces[inside & label])] = True
    touched[0] = False
    islands = label & ~touched[pieces]
    part = label & ~islands
    deep = part & (d_in > 0.5 * coarseness)
    if not deep.any():
        deep = part if part.any() else label
    missing = float((deep & ~inside).sum() / max(deep.sum(), 1))
    extra = float((inside & in_image & (d_out > band_mm + coarseness)).sum() / max(in_n, 1))
    exc = sample_field(d_out.astype(np.float32), vertices, spacing, cval=0.0)
    p = Plausibility(
        segment_ml=seg_n * voxel / 1000.0, surface_ml=volume_mm3 / 1000.0,
        volume_ratio=float(volume_mm3 / max(seg_n * voxel, 1e-9)),
        segment_inside_fraction=float((label & inside).sum() / max(seg_n, 1)),
        missing_fraction=missing, extra_fraction=extra,
        max_excursion_mm=float(exc.max()) if len(exc) else 0.0,
        p95_excursion_mm=float(np.percentile(exc, 95)) if len(exc) else 0.0,
        neighbour_label_overlap=float((inside & neighbours).sum() / max(in_n, 1)),
        neighbour_core_overlap=float((inside & neighbour_cores).sum() / max(in_n, 1)),
        edge_support=float(edge_support),
        untouched_segment_ml=float(islands.sum() * voxel / 1000.0))
    return p


def _block_majority(mask: np.ndarray, f: int) -> np.ndarray:
    """``mask`` on blocks of f^3 voxels: a block is set when at least half of it is."""
    pad = [(0, (-s) % f) for s in mask.shape]
    m = np.pad(mask, pad).astype(np.uint16)
    z, y, x = (s // f for s in m.shape)
    return m.reshape(z, f, y, f, x, f).sum(axis=(1, 3, 5)) * 2 >= f ** 3


def gate(p: Plausibility, *, coarseness: float, band_mm: float, name: str) -> Plausibility:
    """Fill ``p.bounds`` and ``p.problems`` (each problem says what is wrong and what to do)."""
    max_exc = band_mm + EXCURSION_COARSENESS * coarseness + EXCURSION_MM
    p.bounds = {"missing_fraction_max": MAX_MISSING_FRACTION, "extra_fraction_max": MAX_EXTRA_FRACTION,
                "max_excursion_mm": max_exc, "neighbour_core_overlap_max": MAX_CORE_OVERLAP,
                "edge_support_min": MIN_EDGE_SUPPORT}
    problems = []
    if p.missing_fraction > MAX_MISSING_FRACTION:
        problems.append(
            f"{name}: {100 * p.missing_fraction:.0f} % of what the segment clearly covers is "
            f"outside the surface (at most {100 * MAX_MISSING_FRACTION:.0f} %): part of the bone "
            "is missing. Use automatic thresholds (h0/ht auto) or lower H0/HT, or check that the "
            "segment is this bone")
    if p.extra_fraction > MAX_EXTRA_FRACTION:
        problems.append(
            f"{name}: {100 * p.extra_fraction:.0f} % of the surface's volume lies more than "
            f"{band_mm + coarseness:.1f} mm outside the segment (at most "
            f"{100 * MAX_EXTRA_FRACTION:.0f} %): it grew into a neighbour or soft tissue. Label "
            "the neighbouring bone (every other label is a neighbour), raise H0, or correct the "
            "segment")
    if p.max_excursion_mm > max_exc:
        problems.append(
            f"{name}: the surface reaches {p.max_excursion_mm:.1f} mm outside the segment (at most "
            f"{max_exc:.1f} mm): it is probably fused with a neighbour there. Label the "
            "neighbouring bone or correct the segment")
    if p.neighbour_core_overlap > MAX_CORE_OVERLAP:
        problems.append(
            f"{name}: {100 * p.neighbour_core_overlap:.1f} % of the surface's volume is inside "
            "another label's core (it entered a neighbouring bone). Check the labels at the joint")
    if np.isfinite(p.edge_support) and p.edge_support < MIN_EDGE_SUPPORT:
        problems.append(
            f"{name}: the CT shows a bone edge at only {100 * p.edge_support:.0f} % of the surface "
            f"(at least {100 * MIN_EDGE_SUPPORT:.0f} %): the thresholds select almost none of the "
            "bone's border. Use automatic thresholds (h0/ht auto) or lower H0/HT")
    p.problems = problems
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
