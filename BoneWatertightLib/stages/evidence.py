"""Stage 9b (ours): what the CT says under each vertex of the finished surface.

A surface that passes every check can still stand on little evidence in places: a thin plate
whose thickness was modelled, a stretch that follows the segment alone, a joint where the
boundary is the competition between two bones. Each vertex gets a class and a confidence in
[0, 1], measured on the final surface (after the caps and the joint gaps):

- ``edge`` (0): the CT profile along the normal has an edge (a peak at least ``min_contrast``
  above the valley outside it: weaker than the refinement needs to move a vertex, but still
  the CT's) and crosses its edge level within the CT's resolution of the vertex (EDGE_TOLERANCE_RESOLUTION x its coarsest spacing, at least one
  working voxel and EDGE_TOLERANCE_MM); confidence = the profile's contrast / the bone's full
  cortical contrast (the refinement's blurred-slab reference), at most 1;
- ``thin plate`` (1): no edge, but the vertex lies on the face of a thin plate's slab
  (:mod:`.plates`); confidence = the plate ridge's contrast / the full contrast;
- ``joint`` (2): no edge, within ``free_mm`` of another bone's voxels: the boundary there is
  where the two bones' competition put it; confidence JOINT_CONFIDENCE;
- ``label only`` (3): none of these - the vertex stands where the thresholds or the segment put
  it (the segment's fill of a hole included); confidence 0;
- ``cap`` (4): a vertex of the flat cap at the image boundary (exact by construction);
  confidence 1.
"""

from __future__ import annotations

import numpy as np

from ..mesh.operators import sample_field, vertex_components
from .plausibility import percent_text
from .refine import contrast_reference, edge_crossings, full_contrast, sample_profiles

EDGE, PLATE, JOINT, LABEL_ONLY, CAP = 0, 1, 2, 3, 4
CLASSES = ("edge", "thin plate", "joint", "label only", "cap")
# An edge supports a vertex within max(EDGE_TOLERANCE_MM, one working voxel,
# EDGE_TOLERANCE_RESOLUTION x the CT's coarsest spacing).
EDGE_TOLERANCE_MM = 0.5
EDGE_TOLERANCE_RESOLUTION = 0.5
JOINT_CONFIDENCE = 0.5
# Areas (mm^2) from which a label-only or thickened thin-plate part of the surface is warned.
WARN_AREA_MM2 = 100.0
# The label-only warning says where its largest patches (at least WARN_AREA_MM2 each) are.
PATCHES_LISTED = 3


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """A third of the area of each vertex's faces: (n,) mm^2 (sums to the surface's area)."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    fa = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    out = np.zeros(len(vertices))
    for i in range(3):
        np.add.at(out, faces[:, i], fa / 3.0)
    return out


def vertex_evidence(vertices: np.ndarray, faces: np.ndarray, cap_flags: np.ndarray, *,
                    ct_smooth, spacing: float, ht: float, soft: float, min_contrast: float,
                    field_spacing=None, edge_level=None, plates=None,
                    others_distance=None, others_origin=None, fill=None,
                    free_mm: float = 2.0, resolution: float = 0.0,
                    shared_reference=None) -> tuple:
    """Evidence class and confidence of each vertex (see the module doc).

    Parameters
    ----------
    vertices : (n, 3) float array
        The finished surface, x-y-z working-grid millimetres; ``faces`` (m, 3).
    cap_flags : (m,) uint8 array
        1 on cap faces.
    ct_smooth : (z, y, x) float array or None
        The refinement's smoothed CT (None: no edges are measured), on a grid of step
        ``field_spacing`` (a step or (x, y, z) steps; None: ``spacing``) from the working
        grid's first voxel.
    spacing, ht : float
        Working voxel size (mm) and HT (HU).
    soft, min_contrast : float
        Soft-tissue level and the least edge contrast (HU): an edge peaks at least
        ``soft + min_contrast`` and ``min_contrast`` above its outside valley.
    edge_level : float or None
        The refinement's edge level (None: the blurred-slab model).
    plates : stages.plates.Plates, optional
    others_distance : (z, y, x) float array, optional
        Distance (mm) to other bones' voxels on a box whose voxel (0, 0, 0) is at
        ``others_origin`` (x-y-z mm).
    fill : (mask (z, y, x) bool, origin (3,), step) or None
        Voxels the segment filled in M0 (:class:`.poisson.Fusion`), in the same frame.
    free_mm : float
        Within this distance of another bone a vertex is at a joint.
    resolution : float
        The CT's coarsest spacing (mm).
    shared_reference : float, optional
        The run's shared full contrast (HU), as the refinement used it
        (:func:`.refine.full_contrast`).

    Returns
    -------
    evidence : (n,) uint8 array
    confidence : (n,) float32 array
    summary : dict
        Area (mm^2) and fraction of the surface per class, ``thickened_plate_mm2``: the
        thin-plate area whose slab was given more than the CT's estimated thickness, and
        ``threshold_reach`` (:func:`_threshold_reach`): how much of the border the CT shows
        the thresholds select (the plausibility gate's measure).
    """
    n = len(vertices)
    tolerance = max(EDGE_TOLERANCE_MM, spacing, EDGE_TOLERANCE_RESOLUTION * resolution)
    offsets = np.zeros(0)
    shows = reaches = None
    evidence = np.full(n, LABEL_ONLY, np.uint8)
    confidence = np.zeros(n, np.float32)
    normals = None
    if ct_smooth is not None:
        step = spacing if field_spacing is None else field_spacing
        profiles = sample_profiles(vertices, faces, ct_smooth, step)
        reference = full_contrast(contrast_reference(vertices, faces, ct_smooth, step, ht,
                                                     profiles=profiles), shared_reference)
        level = edge_level if edge_level is not None else (
            0.5 if not np.isfinite(reference) else ("slab", reference))
        normals, t_cross, ok, contrast = edge_crossings(vertices, faces, ct_smooth, step,
                                                        soft + min_contrast, level, min_contrast,
                                                        profiles=profiles)
        edge = ok & (np.abs(t_cross) <= tolerance)
        # Where the profile shows the bone's edge, does its cortex reach HT (the thresholds
        # select that border)? The profile's brightest sample near the vertex decides.
        shows, reaches = ok, ok & (profiles[4] >= ht)
        offsets = np.abs(t_cross[ok])
        full = reference if np.isfinite(reference) and reference > 0 else np.nan
        evidence[edge] = EDGE
        confidence[edge] = np.clip(contrast[edge] / full, 0.0, 1.0) if np.isfinite(full) else 1.0
    else:
        full = np.nan
    thickened = np.zeros(n, bool)
    if plates is not None and plates.n:
        if normals is None:
            from ..mesh.operators import vertex_normals

            normals = vertex_normals(vertices, faces)
        shift = plates.targets(vertices, normals)
        on = np.isfinite(shift) & (np.abs(np.nan_to_num(shift)) <= tolerance)
        on &= evidence == LABEL_ONLY
        if on.any():
            j, _, _ = plates.offsets(vertices[on], 0.0)
            evidence[on] = PLATE
            c = plates.contrast[j] / full if np.isfinite(full) else 0.5
            confidence[on] = np.clip(c, 0.0, 1.0)
            thin = plates.thickness[j] < plates.model[j]
            thickened[np.flatnonzero(on)[thin]] = True
    near = np.zeros(n, bool)
    if others_distance is not None:
        near = sample_field(others_distance, vertices - others_origin, spacing,
                            cval=1e3) <= free_mm
        joint = near & (evidence == LABEL_ONLY)
        evidence[joint] = JOINT
        confidence[joint] = JOINT_CONFIDENCE
    if fill is not None:
        mask, origin, step = fill
        filled = sample_field(mask.astype(np.float32), vertices - origin, step, cval=0.0) >= 0.5
        evidence[filled] = LABEL_ONLY
        confidence[filled] = 0.0
        thickened[filled] = False
    on_cap = np.zeros(n, bool)
    if cap_flags is not None and np.any(cap_flags):
        on_cap[np.unique(faces[np.asarray(cap_flags) > 0])] = True
        evidence[on_cap] = CAP
        confidence[on_cap] = 1.0
        thickened[on_cap] = False
    area = vertex_areas(vertices, faces)
    total = float(area.sum()) or 1.0
    summary = {"area_mm2": {name: float(area[evidence == i].sum())
                            for i, name in enumerate(CLASSES)},
               "fraction": {name: float(area[evidence == i].sum() / total)
                            for i, name in enumerate(CLASSES)},
               "thickened_plate_mm2": float(area[thickened].sum()),
               "mean_confidence": float((area * confidence).sum() / total),
               "edge_tolerance_mm": float(tolerance),
               # how far the vertices with an edge on their profile are from it (mm)
               "edge_offset_mm": ({"p50": float(np.percentile(offsets, 50)),
                                   "p90": float(np.percentile(offsets, 90))}
                                  if offsets.size else None),
               "classes": {i: name for i, name in enumerate(CLASSES)},
               "threshold_reach": _threshold_reach(area, shows, reaches, ~near & ~on_cap, ht),
               "label_only_patches": label_only_patches(faces, evidence == LABEL_ONLY, area,
                                                        vertices)}
    return evidence, confidence, summary


def label_only_patches(faces: np.ndarray, mask: np.ndarray, area: np.ndarray,
                       vertices: np.ndarray, top: int = PATCHES_LISTED) -> list:
    """The largest edge-connected patches of the vertices in ``mask``, largest first: a list
    of {"area_mm2", "vertex"}, ``vertex`` the patch's vertex nearest its area-weighted centre
    (a point on the surface, where a user can look).

    Parameters
    ----------
    faces : (m, 3) int array
    mask : (n,) bool array
    area : (n,) float array
        Each vertex's share of the surface's area (:func:`vertex_areas`), mm^2.
    vertices : (n, 3) float array
    top : int
        How many patches are listed.
    """
    idx = np.flatnonzero(mask)
    if not len(idx):
        return []
    comp = vertex_components(len(mask), faces, mask)
    sums = np.bincount(comp[idx], weights=area[idx])
    out = []
    for k in np.argsort(sums)[::-1][:top]:
        if sums[k] <= 0:
            break
        sel = idx[comp[idx] == k]
        w = area[sel]
        centre = (vertices[sel] * w[:, None]).sum(axis=0) / w.sum()
        nearest = sel[np.argmin(np.linalg.norm(vertices[sel] - centre, axis=1))]
        out.append({"area_mm2": float(sums[k]), "vertex": int(nearest)})
    return out


def _threshold_reach(area, shows, reaches, free, ht) -> dict | None:
    """Of the free surface (away from other bones and caps) whose CT profile shows the
    bone's edge, the area and the fraction of it whose cortex reaches HT (0 when no edge is
    shown); None when no CT was sampled."""
    if shows is None:
        return None
    shown = float(area[shows & free].sum())
    return {"edge_area_mm2": shown, "free_area_mm2": float(area[free].sum()), "ht_hu": float(ht),
            "fraction": float(area[reaches & free].sum() / shown) if shown > 0 else 0.0}


def evidence_warnings(name: str, summary: dict, min_thickness: float, where=None) -> list:
    """Warnings for the parts of a surface that stand on the segment alone or on a modelled
    thin plate, with their areas (from WARN_AREA_MM2 on); ``where`` (vertex index -> text,
    e.g. "LPS (x, y, z)"): the label-only warning also says where its largest patches are."""
    out = []
    thick = summary.get("thickened_plate_mm2", 0.0)
    if thick >= WARN_AREA_MM2:
        out.append(f"{name}: {thick:.0f} mm^2 of the surface is a thin plate that the CT shows "
                   f"thinner than the {min_thickness:.1f} mm the surface gives it (the plate is "
                   "modelled, not seen: check it, or use a finer CT)")
    label = summary["area_mm2"].get("label only", 0.0)
    if label >= WARN_AREA_MM2:
        frac = summary["fraction"].get("label only", 0.0)
        text = (f"{name}: {label:.0f} mm^2 ({percent_text(frac)}) of the surface has no CT edge "
                "under it (it follows the thresholds or the segment alone): check it there "
                "(point array Evidence = 3)")
        big = [p for p in summary.get("label_only_patches", ())
               if p["area_mm2"] >= WARN_AREA_MM2]
        if where is not None and big:
            text += ("; the largest patch" + ("es" if len(big) > 1 else "") + ": "
                     + ", ".join(f"{p['area_mm2']:.0f} mm^2 near {where(p['vertex'])}"
                                 for p in big))
        out.append(text)
    return out
