"""Stage 3a: which voxels belong to which bone - the segment as evidence, neighbours compete.

Inputs on the working grid: the filtered CT and the label index map of the segmentation (every
label is a bone: the targets and their neighbours). Axis order (z, y, x) throughout.

1. **Bone evidence F**: voxels in [HT, theta_max] connected to a voxel in [H0, theta_max]
   (hysteresis), voxels inside a label down to a lower level ``t_low`` (partial volume lowers
   thin cortex and processes, and the segment already says bone is there), and the **cores**:
   what a segment clearly covers (deeper than ``r_core`` inside it) is bone whatever its HU -
   the trabecular body of a vertebra on 3 mm CT lies far below H0 - unless the CT is
   unambiguous: a soft-tissue part of the label with soft tissue all around it (a false blob
   stuck to the bone) is no core (:func:`unsupported_parts`; reported per label).
2. **Markers**: each label's voxels in [H0, theta_max] and its core, except in the **joint
   zone** (its voxels within ``r_contact`` of another label), where labels are not trusted (AI
   masks are often wrong by a few mm at a joint), in a joint space the CT shows, and in a part
   of the label that such a joint space cuts off from its core and whose bone continues into
   unlabelled bone (:func:`_beyond_a_joint_space`: a coarse label over an unlabelled
   neighbour's rim); and "other bone": H0 voxels outside every label's region (an unlabelled
   neighbour), one marker per connected piece.
2b. **A label's part in a neighbour's bone** (:func:`_misplaced_cores`): a part of a label's
   core cut off from the rest of it, lying in another label's region, is tried by one flood
   without the label's markers there; when a labelled neighbour fills most of it (the CT joins
   it to that bone without a joint space, parts it from its own by one), that part of the label
   is given to the neighbour and the ownership is computed again on the labels so corrected
   (``Ownership.labels``; an AI label that took a block of the next vertebra's body).
3. **Flooding** (:func:`flood_from_markers`) inside F in the order of the CT's valley-ness
   V = closing(CT) - CT (a black top-hat, quantised): V is high in thin dark gaps between
   bright cortices - joint spaces - and about zero in trabecular bone and soft tissue. So
   where two bones meet, the split follows the joint's low-HU valley; where no valley shows,
   it falls midway between the markers (breadth-first on the plateau) - for touching labels,
   their own boundary.
3b. **Joint cut** (:func:`cut_joint_zones`): flooding splits a plateau at the geodesic midpoint
   between markers, so where thick slices hide part of a joint space the bone whose markers
   lie nearer (a label that took a few mm of its neighbour) floods through the hidden part into
   the other's cortex and along it, around the whole joint. The zone of each pair of touching
   labelled bones is therefore re-split by a minimum cut between the basins outside it: through
   the joint space wherever the CT shows it, at the labels' boundary where it does not.
4. A piece of unlabelled bone whose basin meets bone k without a valley between them is k's
   own bone that the segment missed (a bitten-off end of a rough segment): merged into k. With
   a valley between them it stays a neighbour (this is where a separation can fail: it is
   reported per pair with the fraction of the contact where a joint space was seen). A merged
   piece that continues into unlabelled bone not merged, or whose contact shows part of a
   joint space, is a neighbour's fragment fused with k (the plausibility gate counts it); one
   that touches only k and other merged pieces without a valley is k's.
4b. Where a piece stays a neighbour across a joint space (a valley on at least
   MERGE_MAX_VALLEY_FRACTION of its contact with a label), the label's voxels (outside its
   core, and in a valley even in it) within ``r_contact`` of the neighbour's strong bone
   outside every label are its joint zone with that unlabelled neighbour, as with a labelled
   one: when the flood gave a label some of the neighbour's bone, they give no markers and
   steps 3-4 run again (:func:`_unlabelled_contact`: a label over an unlabelled neighbour's
   cortex beyond a joint space blurred above H0).
5. Bone k owns its basin's part within its region (segment closed + dilated by the band, see
   :func:`threshold.segment_region`) connected to its markers.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull

from .threshold import (SIX, bbox_slices, dilate6, erode6, paste_box, segment_region,
                        six_max)
from ..mesh.distance import distance_inside, distance_outside
from ..threads import cpu_threads, thread_map

# The valley filters run on up to this many threads (scipy's filters release the GIL).
MAX_FILTER_THREADS = 4
# A core is deeper than max(CORE_MIN_MM, coarseness) inside its label, but at most this
# fraction of the label's deepest point (thin bones keep a core).
CORE_MIN_MM = 1.5
CORE_MAX_DEPTH_FRACTION = 0.4
# Joint zone: label voxels within max(CONTACT_MIN_MM, coarseness) of another label.
CONTACT_MIN_MM = 3.0
# Inside a label, bone evidence reaches down to soft + LABEL_LEVEL_FRACTION * (HT - soft).
LABEL_LEVEL_FRACTION = 0.5
# Valley-ness: black top-hat with a cube of half-width VALLEY_GAP_MM / 2 + one voxel,
# quantised in steps of max(VALLEY_QUANTUM_MIN_HU, VALLEY_QUANTUM_FRACTION * bone contrast).
VALLEY_GAP_MM = 3.0
VALLEY_QUANTUM_MIN_HU = 40.0
VALLEY_QUANTUM_FRACTION = 0.1
# A valley "seen" across an interface is at least this many quanta deep.
SEEN_VALLEY_QUANTA = 2
# Unlabelled pieces below this volume (mm^3) are noise, not neighbours.
MIN_OTHER_PIECE_MM3 = 1.0
# An unlabelled piece is merged into a bone when less than this fraction of their contact
# shows a valley and the contact is at least MERGE_MIN_AREA_MM2.
MERGE_MAX_VALLEY_FRACTION = 0.3
MERGE_MIN_AREA_MM2 = 2.0
# A merged piece counts as the bone's own (not as a fused neighbour's fragment, see
# _foreign_pieces) only where its contact shows a valley on less than this fraction: bone that
# continues shows none, a joint the slices hide still shows its space on part of the contact.
# Measured: an AI label's missed scapular blade (3 mm) 0.00-0.10 on every merged piece above
# 0.01 ml; the unlabelled cup of the femur phantom at 2.5 mm slices 0.29-0.41 (rough and AI
# labels), the whole cup merged with rough labels 0.29.
OWN_MAX_VALLEY_FRACTION = 0.15
# ... and when it lies within band + MERGE_REACH_COARSENESS x coarseness + MERGE_REACH_MM of the
# label (the plausibility gate's excursion bound).
MERGE_REACH_COARSENESS = 2.0
MERGE_REACH_MM = 2.0
# Beyond that reach a piece is merged only as the bone's own process (it touches the bone alone,
# no joint space, see _small_own_piece) and at most this fraction of the label's volume - the
# plausibility gate's bound on merged unlabelled bone (MAX_UNLABELLED_FRACTION), so that a
# neighbour's piece merged by mistake is no more than the gate accepts. Measured (stop 41): of
# the 90 bones of the anatomical phantoms one took a piece in, the 3 mm L3's spinous tip (seed
# 41; 0.49 ml against the label's 53 ml, 12.0 mm beyond it, the reach 11.0 mm): max 11.7 -> 3.2
# mm; on the real CT none (a rib's head at the 1.5 mm T12, 0.89 ml, is cut by the grid's border).
SMALL_PIECE_FRACTION = 0.03
# A basin fragment not connected to its bone's markers is kept when at least this fraction of
# it lies inside the label (thin bone broken up by partial volume).
FRAGMENT_IN_LABEL_FRACTION = 0.5
# Region of a label: closing radius (capped at a fraction of its size); it is dilated by the
# band (labelled neighbours compete by their labels, so a small bone needs no smaller band).
REGION_CLOSE_MM = 10.0
REGION_CLOSE_FRACTION = 0.15
# The CT outranks the segment where it is unambiguous: a part of a label whose CT is soft
# tissue (below the label level after smoothing by SUPPORT_SMOOTH_MM) and which reaches the
# label's core is bone only when at least SUPPORT_MIN_FRACTION of its surroundings is not soft
# tissue (a marrow cavity or a low-density body inside its cortex: most of it; a false blob of
# the segment stuck to the bone from the soft tissue: only the contact). Measured (support of
# the parts reaching the core): false blobs of 3 mm radius on femur phantoms 0.15-0.21; marrow
# and low-density heads of the phantoms 0.58-0.94; the trabecular bodies of real vertebrae and
# the sacrum on the 3 mm CT 0.44-0.47 (discs above and below) - 0.5 removed 2.1 ml of L5 there.
SUPPORT_SMOOTH_MM = 1.0
SUPPORT_MIN_FRACTION = 0.3
# Joint cut (:func:`cut_joint_zones`): cutting through a voxel costs CUT_SCALE / (1 + g)^2 x
# (1 + CUT_LABEL_WEIGHT x delta^2 / (1 + g)^2), g = its gap valley (the deepest 1-D black
# top-hat of the three axes) beyond the first quantum, in quanta (less is the texture of spongy
# bone), delta = its distance from the labels' midway surface / r_contact (capped at
# CUT_LABEL_CAP); an edge between two voxels costs their mean, so the cut falls in the middle of
# a seen joint space, not at one cortex (with the smaller of the two the 1.0 mm joint phantom's
# smallest gap was 0.10 mm, with the mean 0.25). A seen joint space is the cheapest cut and there
# the labels' pull fades; where the CT shows no gap the cut keeps to the labels' boundary rather
# than take the shortest way through one bone (a weak pull, 8 without the fading, flattened the
# hidden pole of the femoral head by up to 4 mm on the 2.5 mm joint phantom). Measured on the
# joint phantoms at 2.0 and 2.5 mm slices (seed 1, held out), femur p95 without -> with the cut:
# 3 mm-stolen labels refused -> 1.88 and 1.11 -> 0.70, rough 2.61 -> 2.46 and 0.59 -> 0.53, AI
# 0.50 -> 0.51 and 0.41 -> 0.44; anatomical phantoms (3 mm): the hip bone's fin into the
# sacro-iliac joint max 7.70 -> 3.74 mm (seed 1), the femur's max 13.2 -> 2.34 mm (seed 2).
# A label's part cut off from its core by a seen joint space, whose strong bone continues into
# unlabelled bone, gives no markers (a neighbour's rim under a coarse label) when at least this
# fraction of its shell within the label is that joint space (see _beyond_a_joint_space).
RIM_JOINT_FRACTION = 0.5
# A label's core cut off from the rest of its core (a component other than its largest, of at
# least MISPLACED_MIN_MM3 and of a ball as deep as the core: a smaller one is a speck the
# erosion left where the label is barely thicker than twice the core depth) that lies mostly
# (MISPLACED_IN_REGION_FRACTION) in another label's region is tried: without the label's
# markers in its part of the label, the flooding fills it from the neighbour's bone when the CT
# joins it to that bone without a joint space and parts it from its own. When the neighbour's
# own bone (its basin joined to its largest core) takes at least MISPLACED_TAKEN_FRACTION of it,
# and more than the label, that part of the label is the neighbour's (see _misplaced_cores).
# Measured on the real 20-slice chest CT: TotalSegmentator's T11 label holds a block of T12's
# body below T12's upper endplate (a core of 0.93 ml, 6 mm of disc above it): T12 takes 0.80
# of it, T11 0.07; T12's own small core part there 1.00 T12's. On a 3 mm lumbar phantom whose
# L3 label holds 12 mm of L4's body, L3's block floods the speck of L4's core left beside it
# (0.06 ml, 0.11 ml the ball): the ball's bound keeps it L4's.
MISPLACED_MIN_MM3 = 50.0
MISPLACED_IN_REGION_FRACTION = 0.5
MISPLACED_TAKEN_FRACTION = 0.5
# A joint surface fitted to the seen joint space (carry_joint_fits) is used only when clearly
# more of the bone voxels beside the seen joint space lie on their own side of it than chance
# (0.5) would put there: at least this fraction, measured over both bones. Not all of them: the
# flooding may have given one bone's cortex beside the seen part to the other, which is what the
# fit repairs (the 2.5 mm joint phantoms with rough labels: 0.88-0.92).
FIT_MIN_AGREEMENT = 0.75
CUT_SCALE = 100.0
CUT_LABEL_WEIGHT = 30.0
CUT_LABEL_CAP = 1.5


@dataclass
class Ownership:
    """Result of :func:`compute_ownership`; arrays are (z, y, x) on the working grid.

    ``owner``: label index owning each voxel (0 none; ``other`` = n + 1 unlabelled bone).
    ``cores``: label index of the core (0 none). ``regions``: label index -> (slices, bool
    region within those slices).
    ``foreground``: F. ``contacts``: list of per-pair contact records (see module doc).
    ``unsupported``: the labels' parts that the CT shows to be soft tissue (no core, not bone).
    ``merged``: the unlabelled bone merged into a bone (step 4) that continues into unlabelled
    bone the merge did not take - a fragment of a neighbour fused with the bone - or None. (The
    merged pieces that touch only their bone are its own: ``added``, or None.)
    ``labels``: the label index map as corrected by the CT (parts of a label inside a
    neighbour's bone given to the neighbour, ``info["relabelled"]``), or None when unchanged.
    """

    owner: np.ndarray
    cores: np.ndarray
    regions: dict
    foreground: np.ndarray
    other: int
    contacts: list = field(default_factory=list)
    info: dict = field(default_factory=dict)
    unsupported: np.ndarray = None
    merged: np.ndarray = None
    added: np.ndarray = None
    labels: np.ndarray = None


def unsupported_parts(ct: np.ndarray, label: np.ndarray, core: np.ndarray, spacing: float, *,
                      level: float, smooth_mm: float = SUPPORT_SMOOTH_MM,
                      min_fraction: float = SUPPORT_MIN_FRACTION) -> tuple:
    """Parts of a label that the CT shows to be soft tissue outside the bone.

    A connected part of the label whose smoothed CT is below ``level`` and which reaches the
    label's core is *supported* when at least ``min_fraction`` of the voxels around it (its
    6-connected outer shell) are not soft tissue - bone or the soft-tissue-free inside of a
    cortex - and *unsupported* otherwise: then the segment says bone where the CT shows soft
    tissue with no bone around it (a false blob of an AI or hand segmentation).

    Parameters
    ----------
    ct : (z, y, x) float array
        The filtered CT (HU) on the label's box.
    label, core : (z, y, x) bool arrays
        The label and its core on the same box.
    spacing : float
        Voxel size in mm.
    level : float
        Soft tissue is below this (HU): the label level of the bone evidence.
    smooth_mm, min_fraction : float
        See SUPPORT_SMOOTH_MM, SUPPORT_MIN_FRACTION.

    Returns
    -------
    mask : (z, y, x) bool array
        The unsupported parts (within the label).
    pieces : list of dict
        Per unsupported part: ``voxels`` and ``support`` (the fraction of its shell that is
        not soft tissue).
    """
    sigma = max(smooth_mm / spacing, 0.5)
    soft = _in_slabs(lambda part: ndimage.gaussian_filter(part, sigma=sigma, mode="nearest"),
                     ct.astype(np.float32), int(4.0 * sigma + 0.5)) < level
    cand = label & soft
    if not (cand & core).any():
        return np.zeros(label.shape, bool), []
    parts, n = ndimage.label(cand, structure=SIX)
    reach = np.unique(parts[cand & core])
    reach = reach[reach > 0]
    # Each shell voxel (not in any part, 6-adjacent to one) counts for the part it touches.
    shell_of = six_max(parts)
    shell = (parts == 0) & (shell_of > 0)
    total = np.bincount(shell_of[shell], minlength=n + 1)
    bone = np.bincount(shell_of[shell & ~soft], minlength=n + 1)
    support = bone / np.maximum(total, 1)
    bad = np.zeros(n + 1, bool)
    bad[reach] = support[reach] < min_fraction
    size = np.bincount(parts.ravel(), minlength=n + 1)
    pieces = [{"voxels": int(size[i]), "support": round(float(support[i]), 3)}
              for i in np.flatnonzero(bad)]
    return bad[parts], pieces


def valley_map(ct: np.ndarray, spacing: float, radius_mm: float) -> np.ndarray:
    """Black top-hat closing(ct) - ct with a cube of half-width ``radius_mm`` (separable)."""
    k = 2 * max(1, int(round(radius_mm / spacing))) + 1

    def tophat(part):
        closed = ndimage.minimum_filter(ndimage.maximum_filter(part, size=k, mode="nearest"),
                                        size=k, mode="nearest")
        return closed - part

    return _in_slabs(tophat, ct, 2 * (k // 2))


def _in_slabs(func, arr: np.ndarray, halo: int) -> np.ndarray:
    """``func(arr)`` for a filter whose output at a voxel depends on the input within ``halo``
    voxels only: computed in slabs along axis 0 (each with ``halo`` slices of its neighbours'
    input, then cut back), one per CPU on threads (scipy's filters release the GIL). The same
    values as one call: the borders of the array are the array's own in every slab."""
    threads = cpu_threads(MAX_FILTER_THREADS)
    n = arr.shape[0]
    if threads <= 1 or n < threads * max(2 * halo, 8):
        return func(arr)
    cuts = np.linspace(0, n, threads + 1).round().astype(int)

    def part(i):
        lo, hi = max(0, cuts[i] - halo), min(n, cuts[i + 1] + halo)
        return func(arr[lo:hi])[cuts[i] - lo:cuts[i + 1] - lo]

    return np.concatenate(thread_map(part, range(threads), threads, "slabs"), axis=0)


def _tophat_1d(ct: np.ndarray, k: int, axis: int) -> np.ndarray:
    """The 1-D black top-hat of ``ct`` along ``axis`` (segments of ``k`` voxels)."""
    return ndimage.minimum_filter1d(ndimage.maximum_filter1d(ct, k, axis=axis, mode="nearest"),
                                    k, axis=axis, mode="nearest") - ct


def _tophats(ct: np.ndarray, k: int, axes) -> dict:
    """{axis: :func:`_tophat_1d`} for each of ``axes``, computed at once on threads."""
    axes = list(axes)
    return dict(zip(axes, thread_map(lambda a: _tophat_1d(ct, k, a), axes,
                                     cpu_threads(MAX_FILTER_THREADS), "tophat")))


def gap_valley(ct: np.ndarray, spacing: float, radius_mm: float) -> np.ndarray:
    """The deepest 1-D black top-hat of the three axes (segments of half-width ``radius_mm``):
    a thin dark gap between two bright walls, seen across it. Unlike the cube's top-hat
    (:func:`valley_map`) it stays about zero in the concave inside of a curved cortex, which a
    cube does not fit into (float32, HU)."""
    k = 2 * max(1, int(round(radius_mm / spacing))) + 1
    out = np.zeros(ct.shape, np.float32)
    for top in _tophats(ct, k, range(3)).values():
        np.maximum(out, top, out=out)
    return out


def flood_from_markers(markers: np.ndarray, levels: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Marker-controlled flooding in level order, breadth-first within a level.

    Parameters
    ----------
    markers : (z, y, x) uint array
        Seeds (0 = unlabelled).
    levels : (z, y, x) int array
        The level at which a voxel can be claimed.
    mask : (z, y, x) bool array
        Voxels that may be claimed.

    Returns
    -------
    (z, y, x) int32 array
        Each voxel of ``mask`` reached from a seed gets the label of the flood that reaches it
        first; floods expand over every voxel of level <= L, one 6-connected layer per step and
        all labels at once, before any voxel of level L + 1 is claimed - so on a plateau the
        split is the geodesic midpoint between the seeds. Voxels no flood reaches stay 0.
    """
    shape = markers.shape
    pad = ((1, 1), (1, 1), (1, 1))
    lab = np.pad(markers.astype(np.int32), pad).ravel()
    ok = np.pad(mask, pad).ravel()
    lev = np.pad(levels.astype(np.int32), pad, constant_values=np.iinfo(np.int32).max).ravel()
    sy, sx = shape[1] + 2, shape[2] + 2
    offsets = np.array([1, -1, sx, -sx, sx * sy, -sx * sy], dtype=np.int64)
    buckets: dict = {}

    def expand(idx, lbl, level):
        nb = (idx[:, None] + offsets[None, :]).ravel()
        nl = np.repeat(lbl, 6)
        free = ok[nb] & (lab[nb] == 0)
        nb, nl = nb[free], nl[free]
        e = lev[nb]
        now = e <= level
        if not now.all():
            nbl, nll, el = nb[~now], nl[~now], e[~now]
            order = np.argsort(el, kind="stable")
            nbl, nll, el = nbl[order], nll[order], el[order]
            cut = np.flatnonzero(np.diff(el)) + 1
            for a, b in zip(np.r_[0, cut], np.r_[cut, len(el)]):
                buckets.setdefault(int(el[a]), []).append((nbl[a:b], nll[a:b]))
        return nb[now], nl[now]

    seeds = np.flatnonzero(lab)
    expand(seeds, lab[seeds], -1)
    while buckets:
        level = min(buckets)
        claims = buckets.pop(level)
        idx = np.concatenate([c[0] for c in claims])
        lbl = np.concatenate([c[1] for c in claims])
        while len(idx):
            free = lab[idx] == 0
            idx, lbl = idx[free], lbl[free]
            idx, first = np.unique(idx, return_index=True)
            lbl = lbl[first]
            lab[idx] = lbl
            idx, lbl = expand(idx, lbl, level)
    return lab.reshape(shape[0] + 2, sy, sx)[1:-1, 1:-1, 1:-1]


def _touching_labels(ws: np.ndarray, n: int, *, piece_faces: int | None = None) -> list:
    """The pairs (a, b), a < b <= n, of labelled basins that share a voxel face; with
    ``piece_faces`` then the pairs of a labelled basin a <= n and an unlabelled piece b > n
    that share at least that many voxel faces. Each group sorted."""
    counts: dict = {}
    for axis in range(3):
        a = [slice(None)] * 3
        b = [slice(None)] * 3
        a[axis] = slice(0, -1)
        b[axis] = slice(1, None)
        wa, wb = ws[tuple(a)], ws[tuple(b)]
        lo = np.minimum(wa, wb)
        hi = np.maximum(wa, wb)
        sel = (lo != hi) & (lo > 0) & (lo <= n)
        if piece_faces is None:
            sel &= hi <= n
        if sel.any():
            keys, cnt = np.unique(lo[sel].astype(np.int64) * 100000 + hi[sel], return_counts=True)
            for k, c in zip(keys.tolist(), cnt.tolist()):
                counts[k] = counts.get(k, 0) + c
    pairs = sorted((int(k // 100000), int(k % 100000)) for k in counts)
    return ([p for p in pairs if p[1] <= n]
            + [p for p in pairs if p[1] > n and counts[p[0] * 100000 + p[1]] >= piece_faces])


def cut_joint_zones(ws: np.ndarray, fg: np.ndarray, labels: np.ndarray, ct: np.ndarray,
                    n: int, spacing: float, r_contact: float, quantum: float,
                    radius_mm: float, only: set | None = None) -> list:
    """Re-decide, in place, the voxels of ``ws`` where two labelled bones meet by a minimum cut.

    The flooding splits a joint zone at the geodesic midpoint between the two bones' markers
    wherever no valley stops it: where the slices hide a joint space, the bone whose markers
    lie nearer (a label that took a few mm of its neighbour) floods into the other's cortex and
    along it, around the whole joint. Here the zone of a pair - the voxels of both basins
    within ``r_contact`` of both labels - is split by the cut of least cost between the basins'
    voxels outside it: through the joint space where the CT shows it (cheap), continued over
    the part the slices hide by the smallest surface near the labels' boundary (see CUT_*).

    Parameters
    ----------
    ws : (z, y, x) int array
        The flooding's basins (label index), changed in place.
    fg : (z, y, x) bool array
        The bone evidence F.
    labels : (z, y, x) uint array
        The label index map (1..n).
    ct : (z, y, x) float32 array
        The filtered CT (HU).
    n : int
        Number of labels.
    spacing, r_contact : float
        Voxel size and the joint zone's reach (mm).
    quantum, radius_mm : float
        The valley quantum (HU) and the valley filter's half-width (mm), as for the flooding.
    only : set of int, optional
        Only the pairs with one of these labels (default: every pair).

    Returns
    -------
    list of dict
        Per pair: ``a``, ``b``, ``seen_fraction`` (of the flooding's interface, where a joint
        space shows), ``zone_voxels``, ``changed_voxels`` (moved to the other bone).
    """
    from scipy import sparse
    from scipy.sparse.csgraph import breadth_first_order, maximum_flow

    out = []
    pad = int(np.ceil(r_contact / spacing)) + 3
    boxes = ndimage.find_objects(labels, max_label=n)
    for a, b in _touching_labels(ws, n):
        if boxes[a - 1] is None or boxes[b - 1] is None:
            continue
        if only is not None and a not in only and b not in only:
            continue
        # Voxels within r_contact of both labels lie in their boxes grown by pad; their nearest
        # voxels of either label within one pad more.
        sl = tuple(slice(max(0, max(p.start, q.start) - 2 * pad),
                         min(size, min(p.stop, q.stop) + 2 * pad))
                   for p, q, size in zip(boxes[a - 1], boxes[b - 1], labels.shape))
        if any(x.start >= x.stop for x in sl):
            continue
        lab = labels[sl]
        if not ((lab == a).any() and (lab == b).any()):
            continue  # their boxes overlap where one of them has no voxel
        w = ws[sl]
        # the flooding's interface and how much of it shows a joint space (for the report)
        total, seen = _interfaces(w, fg[sl], ct[sl], spacing, quantum,
                                  radius_mm).get((a, b), (0, 0))
        seen_fraction = seen / total if total else 0.0
        da = distance_outside(lab == a) * spacing
        db = distance_outside(lab == b) * spacing
        # One voxel more than r_contact: a joint space at the zone's edge lies in it whole.
        reach = r_contact + spacing
        zone = fg[sl] & ((w == a) | (w == b)) & (da <= reach) & (db <= reach)
        side_a = (w == a) & ~zone
        side_b = (w == b) & ~zone
        nz = int(zone.sum())
        if not nz:
            continue
        ids = np.full(zone.shape, -1, np.int64)
        ids[zone] = np.arange(nz)
        src, snk = nz, nz + 1
        delta = np.minimum(0.5 * np.abs(da - db) / r_contact, CUT_LABEL_CAP)
        # Less than a quantum is the texture of spongy bone, not a gap: it does not count.
        gaps = np.clip(gap_valley(ct[sl], spacing, radius_mm) / quantum - 1.0, 0, None)
        # The labels' pull fades where a gap is seen: there the CT decides.
        cost = CUT_SCALE / (1.0 + gaps) ** 2 * (1.0 + CUT_LABEL_WEIGHT * delta ** 2
                                                 / (1.0 + gaps) ** 2)
        # Integer capacities; every flow stays below 2^31 (scaled down for a very large zone).
        scale = max(1.0, 6.0 * nz * float(cost.max()) / 2.0e9)
        cost = np.maximum(np.round(cost / scale), 1).astype(np.int64)
        big = 6 * int(cost.max()) + 1  # more than all of a voxel's own edges: never cut
        rows, cols, caps = [], [], []
        for axis in range(3):
            lo = [slice(None)] * 3
            hi = [slice(None)] * 3
            lo[axis] = slice(0, -1)
            hi[axis] = slice(1, None)
            for p, q in ((tuple(lo), tuple(hi)), (tuple(hi), tuple(lo))):
                m = zone[p] & zone[q]
                rows.append(ids[p][m])
                cols.append(ids[q][m])
                caps.append((cost[p][m] + cost[q][m] + 1) // 2)
                m = zone[p] & side_a[q]
                rows.append(np.full(int(m.sum()), src))
                cols.append(ids[p][m])
                caps.append(np.full(int(m.sum()), big))
                m = zone[p] & side_b[q]
                rows.append(ids[p][m])
                cols.append(np.full(int(m.sum()), snk))
                caps.append(np.full(int(m.sum()), big))
        rows, cols, caps = (np.concatenate(x) for x in (rows, cols, caps))
        if not ((rows == src).any() and (cols == snk).any()):
            continue  # the zone does not lie between the two bones
        graph = sparse.csr_matrix((caps.astype(np.int32), (rows, cols)), shape=(nz + 2, nz + 2))
        flow = maximum_flow(graph, src, snk, method="dinic").flow
        residual = graph - flow
        residual.data = np.clip(residual.data, 0, None)
        residual.eliminate_zeros()
        # a's side: reachable from a's voxels in the residual graph; b's: reaching b's. A part
        # of the zone joined to neither keeps the flooding's owner.
        to_a = np.zeros(nz + 2, bool)
        to_a[breadth_first_order(residual, src, directed=True, return_predecessors=False)] = True
        to_b = np.zeros(nz + 2, bool)
        to_b[breadth_first_order(residual.T.tocsr(), snk, directed=True,
                                 return_predecessors=False)] = True
        old = w[zone]
        new = np.where(to_a[:nz], a, np.where(to_b[:nz], b, old))
        w[zone] = new
        out.append({"a": int(a), "b": int(b), "seen_fraction": round(seen_fraction, 3),
                    "zone_voxels": nz, "changed_voxels": int((new != old).sum())})
    return out


def carry_joint_fits(ws: np.ndarray, fg: np.ndarray, ct: np.ndarray, cores: np.ndarray,
                     regions: dict, n: int, spacing: float, *, quantum: float,
                     radius_mm: float, reach_mm: float, margin_mm: float,
                     resolution_mm: float = 0.0,
                     only: set | None = None) -> list:
    """Carry the seen part of each joint over the part the slices hide (in place).

    Where thick slices run along a joint the CT shows no joint space and the flooding and the
    joint cut follow the labels; a label a few mm wrong there (the rough label of a femur that
    stops short of the head's pole, a hip label over it) puts the split a few mm wrong. For
    each pair of touching labelled basins, the mid-surface of the joint space the CT does show
    (voxels in a valley of at least SEEN_VALLEY_QUANTA quanta, midway between the two bones)
    is fitted by a plane or a sphere (:func:`.jointfit.fit_joint_surface`); where the fit is
    trusted, voxels of either basin that lie clearly on the other bone's side of it (more than
    max(a voxel, 2 x the fit's RMS), at most ``reach_mm`` from it, within the part of the
    surface the seen points surround) and that touch that bone are given to it, with their
    cores and regions. An irregular joint (no fit within FIT_MAX_RMS_VOXELS voxels), a joint
    seen nowhere, or a fit that does not separate the two bones where the joint is seen leaves
    the cut's result as it is.

    Parameters
    ----------
    ws : (z, y, x) int array
        The basins after the joint cut (label index), changed in place.
    fg : (z, y, x) bool array
        The bone evidence F.
    ct : (z, y, x) float32 array
        The filtered CT (HU).
    cores : (z, y, x) uint array
        The labels' cores; a core of one bone moved to the other is dropped (in place).
    regions : dict
        Label index -> (slices, region); grown by the voxels a bone is given (in place).
    n : int
        Number of labels.
    spacing : float
        Voxel size (mm).
    quantum, radius_mm : float
        The valley quantum (HU) and the valley filter's half-width (mm).
    reach_mm : float
        How far from the fitted surface voxels may move: the joint zone's reach plus how far a
        bone may reach beyond its label.
    margin_mm : float
        How far beyond the seen points (along the fitted surface) the fit is carried: the
        joint zone's reach, where the labels are not trusted either (a hidden part at the edge
        of a joint, beside a cup's rim, has seen joint space on one side only).
    resolution_mm : float
        The CT's voxel size (mm, a cube of its volume): how closely a ball joint's sphere must
        follow the seen joint space scales with it where it is coarser than the grid
        (jointfit.FIT_MAX_RMS_VOXELS).
    only : set of int, optional
        Only the pairs with one of these labels (default: every pair).

    Returns
    -------
    list of dict
        Per pair with a fit: ``a``, ``b``, ``model`` (plane / sphere), ``rms_mm``,
        ``radius_mm``, ``points``, ``inliers``, ``agreement``, ``to_a`` / ``to_b`` (voxels
        moved), ``used`` (False with a ``reason`` when the fit was not trusted); per pair
        whose seen joint space has enough points but no fit, and for the smaller patches of
        a pair's seen joint space (not fitted): ``model`` None and the ``reason``.
    """
    from .jointfit import FIT_MIN_POINTS, fit_joint_surface

    out = []
    pad = int(np.ceil(reach_mm / spacing)) + 2
    boxes = ndimage.find_objects(ws)
    # Labelled pairs, then a labelled bone and an unlabelled piece of bone that meet over at
    # least as many voxel faces as a fit needs points (a hip bone nobody labelled, whose piece
    # took the pole of a femoral head that the femur's label stops short of).
    for a, b in _touching_labels(ws, n, piece_faces=FIT_MIN_POINTS):
        ba, bb = boxes[a - 1], boxes[b - 1]
        if ba is None or bb is None:
            continue
        if only is not None and a not in only and b not in only:
            continue
        sl = tuple(slice(max(0, max(p.start, q.start) - pad), min(size, min(p.stop, q.stop) + pad))
                   for p, q, size in zip(ba, bb, ws.shape))
        if any(x.start >= x.stop for x in sl):
            continue
        w = ws[sl]
        f = fg[sl]
        in_a = f & (w == a)
        in_b = f & (w == b)
        if not (in_a.any() and in_b.any()):
            continue
        seen = gap_valley(ct[sl], spacing, radius_mm) >= SEEN_VALLEY_QUANTA * quantum
        if np.count_nonzero(seen) < FIT_MIN_POINTS:
            continue  # the mid-surface below is part of it: too few points for a fit
        # the seen joint space's mid-surface: in a valley, midway between the two bones
        within = radius_mm + spacing
        da = _distance_near(in_a, seen, within, spacing)
        db = _distance_near(in_b, seen, within, spacing)
        mid = seen & (da <= within) & (db <= within)
        mid[mid] = np.abs(da[mid] - db[mid]) <= spacing
        if np.count_nonzero(mid) < FIT_MIN_POINTS:
            continue
        offset = np.array([x.start for x in sl], float)
        # A joint is one patch of seen joint space: seen parts nearer each other than twice
        # the margin the fit is carried beyond its points are one joint (the ring round a
        # hidden pole); parts farther apart are separate joints of the same two bones (the disc
        # and the two facet joints of two vertebrae). Only the largest is fitted: one plane
        # through a disc and its facets gave one vertebra's articular process to the other,
        # and a facet's own sphere, carried over its contact, cut the process beyond it.
        patches, n_patches = ndimage.label(_distance_near(mid, mid, margin_mm, spacing)
                                           <= margin_mm, structure=np.ones((3, 3, 3), bool))
        part = mid
        if n_patches > 1:
            sizes = np.bincount(patches[mid], minlength=n_patches + 1)
            largest = int(np.argmax(sizes[1:])) + 1
            part = mid & (patches == largest)
            rest = int(sizes.sum() - sizes[largest])
            if rest >= FIT_MIN_POINTS:
                out.append(_no_fit(a, b, rest, f"{n_patches - 1} smaller patches of seen joint "
                                   "space of the same two bones (not fitted)"))
        pts = (np.argwhere(part) + offset) * spacing
        why: list = []
        surf = fit_joint_surface(pts, spacing, resolution_mm, reasons=why)
        if surf is None:
            if len(pts) >= FIT_MIN_POINTS:
                out.append(_no_fit(a, b, len(pts), why[0] if why else "no fit"))
            continue
        rec = {"a": int(a), "b": int(b), "model": surf.kind, "rms_mm": round(surf.rms, 3),
               "radius_mm": round(surf.radius, 2) if np.isfinite(surf.radius) else None,
               "points": surf.n_points, "inliers": round(surf.n_points / len(pts), 3),
               "extent_mm": round(surf.extent, 1),
               "to_a": 0, "to_b": 0, "used": False}
        out.append(rec)
        # Orient the fit by the bones beside the seen joint space; it must separate them there.
        near = _distance_near(part, part, radius_mm, spacing) <= radius_mm
        pa = (np.argwhere(in_a & near) + offset) * spacing
        pb = (np.argwhere(in_b & near) + offset) * spacing
        if len(pa) < 10 or len(pb) < 10:
            rec["reason"] = "too little bone beside the seen joint space"
            continue
        sa = surf.distance(pa)
        sb = surf.distance(pb)
        surf.sign = -1.0 if np.median(sa) > np.median(sb) else 1.0
        sa, sb = surf.sign * sa, surf.sign * sb
        agree = 0.5 * (np.mean(sa < 0) + np.mean(sb > 0))
        rec["agreement"] = round(float(agree), 3)
        if agree < FIT_MIN_AGREEMENT:
            rec["reason"] = "the fit does not separate the two bones where the joint is seen"
            continue
        tol = max(spacing, 2.0 * surf.rms)
        idx = np.argwhere(in_a | in_b)
        pos = (idx + offset) * spacing
        s = surf.signed(pos)
        ok = np.abs(s) <= reach_mm
        if surf.determined:
            # A ball joint whose seen part spans a good part of the ball: its surface continues
            # over the whole contact, and the fit holds within reach of where the two bones
            # touch or the joint space is seen.
            # (the bones' distances over the whole box: those above are exact near the seen
            # joint space only)
            touching = (in_a & (distance_outside(in_b) * spacing <= spacing)) \
                | (in_b & (distance_outside(in_a) * spacing <= spacing)) | part
            ok &= (distance_outside(touching) * spacing)[tuple(idx.T)] <= reach_mm
        else:
            # A plane, or a sphere seen on a small patch (its curvature poorly known), holds
            # where the seen joint space surrounds the hidden part and a margin beyond it.
            ok[ok] = surf.supported(pos[ok], margin_mm=margin_mm)
        rec["used"] = True
        side = np.zeros(w.shape, np.int8)   # 1: clearly on a's side, 2: on b's
        sel = idx[ok]
        sv = s[ok]
        side[tuple(sel.T)] = np.where(sv < -tol, 1, np.where(sv > tol, 2, 0))
        # Bone of a basin that lies clearly on its own side of the fit belongs to it even where
        # its label stops short (a rough femur label short of the head at the cup's rim): its
        # region grows over it, or no bone would own it and the neighbour's closing would take
        # it (a tongue of the cup into the head).
        for mine, code in ((a, 1), (b, 2)):
            if mine > n:
                continue
            stay = (side == code) & (w == mine) & f
            if stay.any():
                _grow_region(regions, mine, stay, sl)
        for mine, other, key in ((a, b, "to_a"), (b, a, "to_b")):
            flip = (side == (1 if mine == a else 2)) & (w == other) & f
            if not flip.any():
                continue
            comp, nc = ndimage.label(flip, structure=SIX)
            touch = dilate6(f & (w == mine)) & flip
            keep = np.zeros(nc + 1, bool)
            keep[np.unique(comp[touch])] = True
            keep[0] = False
            flip = keep[comp]
            if not flip.any():
                continue
            w[flip] = mine
            c = cores[sl]
            c[flip & (c == other)] = 0
            if mine <= n:  # an unlabelled piece has no region
                _grow_region(regions, mine, flip, sl)
            rec[key] = int(flip.sum())
    return out



def _distance_near(mask: np.ndarray, where: np.ndarray, reach_mm: float,
                   spacing: float) -> np.ndarray:
    """Distance (mm, float32) of each voxel to the nearest True voxel of ``mask``, measured
    on the box of ``where`` grown by ``reach_mm``: exact at the voxels of ``where`` whose
    distance is at most ``reach_mm`` (at every voxel within ``reach_mm`` of ``mask`` when
    ``where`` is ``mask``), larger (or inf) elsewhere - the values of
    ``distance_outside(mask) * spacing`` wherever a caller compares them with ``reach_mm``,
    without a transform of the whole volume. (z, y, x) arrays."""
    out = np.full(mask.shape, np.inf, np.float32)
    if not where.any():
        return out
    box = bbox_slices(where, int(np.ceil(reach_mm / spacing)) + 1)
    part = mask[box]
    if part.any():
        out[box] = distance_outside(part) * spacing
    return out


def _no_fit(a: int, b: int, points: int, reason: str) -> dict:
    """:func:`carry_joint_fits`'s record of seen joint space that got no fit."""
    return {"a": int(a), "b": int(b), "model": None, "rms_mm": None, "radius_mm": None,
            "points": int(points), "to_a": 0, "to_b": 0, "used": False, "reason": reason}


def _grow_region(regions: dict, k: int, add: np.ndarray, sl: tuple) -> None:
    """Add the voxels ``add`` (a mask on the box ``sl``) to label k's region."""
    pos = np.argwhere(add) + np.array([x.start for x in sl])
    lo, hi = pos.min(axis=0), pos.max(axis=0) + 1
    old_sl, old = regions[k]
    new_sl = tuple(slice(min(o.start, int(l)), max(o.stop, int(h)))
                   for o, l, h in zip(old_sl, lo, hi))
    reg = np.zeros(tuple(x.stop - x.start for x in new_sl), bool)
    reg[tuple(slice(o.start - s.start, o.stop - s.start) for o, s in zip(old_sl, new_sl))] = old
    pos -= np.array([x.start for x in new_sl])
    reg[tuple(pos.T)] = True
    regions[k] = (new_sl, reg)


def _interfaces(ws: np.ndarray, fg: np.ndarray, ct: np.ndarray, spacing: float, quantum: float,
                radius_mm: float) -> dict:
    """(label a, label b) with a < b -> (contact voxel faces, of which with a valley seen).

    A face between two F voxels of different basins is "seen" when the CT along the axis that
    crosses it dips by at least SEEN_VALLEY_QUANTA quanta (1-D black top-hat): a joint gap is a
    minimum of the CT between two cortices; a bone cut across its marrow is not."""
    k = 2 * max(1, int(round(radius_mm / spacing))) + 1
    out: dict = {}
    faces = {}
    for axis in range(3):
        a = [slice(None)] * 3
        b = [slice(None)] * 3
        a[axis] = slice(0, -1)
        b[axis] = slice(1, None)
        a, b = tuple(a), tuple(b)
        wa, wb = ws[a], ws[b]
        sel = (wa != wb) & (wa > 0) & (wb > 0) & fg[a] & fg[b]
        if sel.any():
            faces[axis] = (a, b, wa, wb, sel)
    tops = _tophats(ct, k, faces)
    for axis, (a, b, wa, wb, sel) in faces.items():
        top = tops[axis]
        seen = np.maximum(top[a][sel], top[b][sel]) >= SEEN_VALLEY_QUANTA * quantum
        la = np.minimum(wa[sel], wb[sel]).astype(np.int64)
        lb = np.maximum(wa[sel], wb[sel]).astype(np.int64)
        key = la * 100000 + lb
        for kk in np.unique(key):
            m = key == kk
            pair = (int(kk // 100000), int(kk % 100000))
            tot, vis = out.get(pair, (0, 0))
            out[pair] = (tot + int(m.sum()), vis + int(seen[m].sum()))
    return out


def compute_ownership(ct: np.ndarray, labels: np.ndarray, n: int, spacing: float, *,
                      h0: float, ht: float, theta_max: float, soft: float, contrast: float,
                      coarseness: float, band_mm: float, ct_resolution: float = 0.0,
                      progress=None, check_misplaced: bool = True) -> Ownership:
    """Assign the bone voxels of the working grid to the labels (see the module doc).

    Parameters
    ----------
    ct : (z, y, x) float32 array
        The filtered CT (HU).
    labels : (z, y, x) uint array
        Label index 1..n of each voxel (0 background).
    n : int
        Number of labels.
    spacing : float
        Voxel size in mm.
    h0, ht, theta_max : float
        The two threshold windows (HU).
    soft, contrast : float
        Soft-tissue level and bone contrast (cortex - soft tissue), HU.
    coarseness : float
        How coarse the segmentation is (mm): its own voxel size or the CT's slice spacing.
    band_mm : float
        How far a bone may reach beyond its label (the region's dilation).
    ct_resolution : float
        The CT's voxel size (mm, a cube of its volume), for the joint fits
        (:func:`carry_joint_fits`).
    check_misplaced : bool
        Look for parts of a label that the CT gives to a labelled neighbour
        (:func:`_misplaced_cores`); when there are any, the whole computation runs again on
        the labels so corrected (a copy: ``labels`` is not modified), returned as
        ``Ownership.labels`` and listed in ``info["relabelled"]``.

    Returns
    -------
    Ownership
    """
    r_core = max(CORE_MIN_MM, coarseness)
    r_contact = max(CONTACT_MIN_MM, coarseness)
    t_low = soft + LABEL_LEVEL_FRACTION * (ht - soft)
    seg = _label_parts(ct, labels, n, spacing, r_core=r_core, r_contact=r_contact,
                       band_mm=band_mm, t_low=t_low, progress=progress)
    labelled = labels > 0
    fg, strong = _bone_foreground(ct, labelled, seg.cores, h0=h0, ht=ht, t_low=t_low,
                                  theta_max=theta_max)
    if progress:
        progress(0.5, "bone evidence")
    other = n + 1
    quantum = max(VALLEY_QUANTUM_MIN_HU, VALLEY_QUANTUM_FRACTION * contrast)
    radius = 0.5 * VALLEY_GAP_MM + spacing
    # (uint8: the flood's order only; a valley of 255 quanta is deeper than any CT's)
    levels = np.minimum(np.floor(np.clip(valley_map(ct, spacing, radius), 0, None) / quantum),
                        255).astype(np.uint8)
    # A visible joint space: below H0 in a valley of at least SEEN_VALLEY_QUANTA quanta.
    seen = ~strong & (levels >= SEEN_VALLEY_QUANTA)
    markers, n_pieces, dropped = _markers(fg, strong, labels, seg, other, spacing, seen=seen)

    def split_joints(ws, cores, regions, only=None):
        # On the basins ``ws`` (in place): the joint cut, then the seen joint
        # space carried over the part the slices hide (moves cores, grows regions, in place).
        cut = cut_joint_zones(ws, fg, labels, ct, n, spacing, r_contact, quantum=quantum,
                              radius_mm=radius, only=only)
        fits = carry_joint_fits(ws, fg, ct, cores, regions, n, spacing, quantum=quantum,
                                radius_mm=radius, reach_mm=r_contact + band_mm,
                                margin_mm=r_contact, resolution_mm=ct_resolution, only=only)
        return cut, fits

    if check_misplaced and n > 1:
        moved = _misplaced_cores(fg, levels, markers, labels, seg, n, spacing,
                                 margin_vox=int(np.ceil(2 * r_core / spacing)) + 1,
                                 min_mm3=max(MISPLACED_MIN_MM3, 4.0 / 3.0 * np.pi * r_core ** 3),
                                 split_joints=split_joints)
        if moved:
            del fg, strong, levels, seen, markers, seg
            fixed = labels.copy()
            for rec, box, where in moved:
                fixed[box][where] = rec["to"]
            own = compute_ownership(ct, fixed, n, spacing, h0=h0, ht=ht, theta_max=theta_max,
                                    soft=soft, contrast=contrast, coarseness=coarseness,
                                    band_mm=band_mm, ct_resolution=ct_resolution,
                                    progress=None if progress is None else
                                    (lambda f, msg: progress(0.5 + 0.5 * f, msg)),
                                    check_misplaced=False)
            own.labels = fixed
            own.info["relabelled"] = [rec for rec, _, _ in moved]
            return own
    pieces = range(other, other + n_pieces)
    reach_mm = band_mm + MERGE_REACH_COARSENESS * coarseness + MERGE_REACH_MM

    def split():
        # Steps 3-4 (the joint fits grow the regions and drop moved cores: on seg, in place).
        if progress:
            progress(0.6, "flooding from the markers")
        ws = flood_from_markers(markers, levels, fg)
        cut, fits = split_joints(ws, seg.cores, seg.regions)
        if progress:
            progress(0.8, "contacts between bones")
        faces = _interfaces(ws, fg, ct, spacing, quantum, radius)
        boxes = ndimage.find_objects(ws)
        sets = {"beyond": set(), "sided": set(), "plates": set()}
        merged = _merged_pieces(faces, ws, labels, n, pieces, spacing, reach_mm=reach_mm,
                                boxes=boxes, beyond=sets["beyond"], sided=sets["sided"])
        merged += _enclosed_pieces(faces, merged, pieces, n, ws, labels, spacing,
                                   reach_mm=reach_mm, boxes=boxes,
                                   plate_depth_mm=max(coarseness, spacing), plates=sets["plates"])
        return ws, cut, fits, faces, boxes, merged, sets

    first = (seg.cores.copy(), dict(seg.regions)) if n_pieces else None
    ws, cut_info, fit_info, faces, boxes, merged, sets = split()
    near_unlabelled = 0
    unmarked_by_label: dict = {}
    if n_pieces:
        taken = {p for p, _, _, _ in merged}
        # A neighbour across a joint space: a valley on at least MERGE_MAX_VALLEY_FRACTION of
        # its contact with a label (without one the label is all there is to go by: an AI
        # label that stops short along a bone the CT shows whole, the slab's humerus).
        across = {y for (x, y), (tot, vis) in faces.items()
                  if x <= n < y and y not in taken and vis >= MERGE_MAX_VALLEY_FRACTION * tot}
        near = _unlabelled_contact(markers, across, taken, fg & strong, labels > 0, spacing,
                                   r_contact, ws=ws, n=n)
        if near is not None:
            cores0, regions0 = first
            # The core keeps its markers but for a valley (a joint space blurred above H0).
            near &= (markers > 0) & (markers <= n)
            near &= (cores0 == 0) | (levels >= SEEN_VALLEY_QUANTA)
            near_unlabelled = int(np.count_nonzero(near))
        if near_unlabelled:
            per_label = np.bincount(markers[near], minlength=n + 1)
            unmarked_by_label = {int(k): int(per_label[k]) for k in np.flatnonzero(per_label)}
            markers[near] = 0
            seg.cores[...] = cores0
            seg.regions = regions0
            del ws, faces, boxes
            ws, cut_info, fit_info, faces, boxes, merged, sets = split()
        del near
    del first
    beyond, sided, plates = sets["beyond"], sets["sided"], sets["plates"]
    # A visible joint space (cartilage between two cortices, below H0, in a valley of at least
    # SEEN_VALLEY_QUANTA quanta) is no bone: it joins no bone's W_HT (removed here, after the
    # contacts between the basins are measured).
    joint_space = fg & seen & (seg.cores == 0)
    del levels, seen
    ws[joint_space] = 0
    owner = _owners(ws, seg.regions, markers, labels, merged, boxes)
    merged_ids = {p for p, _, _, _ in merged}
    foreign = _foreign_pieces(faces, merged_ids, set(range(other, other + n_pieces)) - merged_ids)
    foreign |= {p for p, _, f, _ in merged if f >= OWN_MAX_VALLEY_FRACTION}
    # One pass over the grid: 1 = a neighbour's merged fragment, 2 = the bone's own.
    kind_of = np.zeros(int(ws.max()) + 1, np.uint8)
    kind_of[list(foreign)] = 1
    kind_of[list(merged_ids - foreign)] = 2
    kind = kind_of[ws]
    in_merged = kind > 0
    owner[(ws >= other) & ~in_merged & (owner == 0)] = other
    taken = (kind == 1) & (owner > 0) if foreign else None
    added = (kind == 2) & (owner > 0) if merged_ids - foreign else None
    del kind
    sizes = np.bincount(ws[in_merged], minlength=max(merged_ids, default=0) + 1)
    merged_ml = {p: float(sizes[p] * spacing ** 3 / 1000.0) for p in merged_ids}
    contacts = _pair_contacts(faces, n, other, merged_ids, spacing ** 2,
                              fragments={p: a for p, a, _, _ in merged if p in foreign})
    info = {"core_depth_mm": {int(k): float(v) for k, v in seg.core_depth.items()},
            "contact_zone_mm": r_contact, "valley_quantum_hu": quantum, "label_level_hu": t_low,
            "foreground_voxels": int(fg.sum()), "unlabelled_pieces": n_pieces,
            "joint_space_voxels": int(joint_space.sum()), "joint_cuts": cut_info,
            "joint_fits": fit_info,
            "rim_voxels_unmarked": dropped, "relabelled": [],
            "unlabelled_contact_voxels_unmarked": near_unlabelled,
            "unlabelled_contact_unmarked_by_label": unmarked_by_label,
            "unsupported": {int(k): v for k, v in seg.unsupported_info.items()},
            "merged_unlabelled": [{"piece": int(p), "into": int(a), "valley_fraction": round(f, 3),
                                   "contact_mm2": round(s, 1), "ml": round(merged_ml[p], 2),
                                   "part_of_unlabelled_bone": p in foreign,
                                   "thin_plate_beyond_reach": p in plates,
                                   "small_piece_beyond_reach": p in beyond,
                                   "beside_a_joint_space": p in sided}
                                  for p, a, f, s in merged]}
    if progress:
        progress(1.0, "ownership done")
    return Ownership(owner=owner, cores=seg.cores, regions=seg.regions, foreground=fg,
                     other=other, contacts=contacts, info=info, unsupported=seg.unsupported,
                     merged=taken, added=added)


@dataclass
class _LabelParts:
    """Per label of :func:`compute_ownership`: cores (uint16 label index, 0 elsewhere), the
    contact zone near other labels, regions ({i: (slices, bool region)}) and their union, the
    core depth (mm), and the parts the CT shows to be soft tissue."""

    cores: np.ndarray
    contact: np.ndarray
    regions: dict
    union: np.ndarray
    core_depth: dict
    unsupported: np.ndarray
    unsupported_info: dict


def _label_parts(ct, labels, n, spacing, *, r_core, r_contact, band_mm, t_low,
                 progress=None) -> _LabelParts:
    """Each label's core (deeper than ``r_core``, without the parts the CT shows to be soft
    tissue), region (closed, dilated by ``band_mm``) and contact zone (within ``r_contact`` of
    another label)."""
    shape = ct.shape
    labelled = labels > 0
    out = _LabelParts(cores=np.zeros(shape, np.uint16), contact=np.zeros(shape, bool),
                      regions={}, union=np.zeros(shape, bool), core_depth={},
                      unsupported=np.zeros(shape, bool), unsupported_info={})

    def part(i):
        m = labels == i
        if not m.any():
            return None
        sl = bbox_slices(m, int(np.ceil(max(r_contact, band_mm) / spacing)) + 2)
        sub = m[sl]
        depth = distance_inside(np.pad(sub, 1))[1:-1, 1:-1, 1:-1] * spacing
        r = min(r_core, CORE_MAX_DEPTH_FRACTION * float(depth.max()))
        core = depth > r if (depth > r).any() else depth >= depth.max()
        # The CT outranks the segment: a soft-tissue part of it with no bone around is no core.
        bad, pieces = unsupported_parts(ct[sl], sub, core, spacing, level=t_low)
        if pieces:
            core &= ~bad
        ext = [np.nonzero(sub.any(axis=tuple(a for a in range(3) if a != ax)))[0] for ax in range(3)]
        extent = max(int(e.max() - e.min() + 1) for e in ext) * spacing
        reg = segment_region(sub, spacing, close_mm=min(REGION_CLOSE_MM, REGION_CLOSE_FRACTION * extent),
                             dilate_mm=band_mm)
        others = labelled[sl] & ~sub
        contact = None
        if others.any():
            contact = sub & (distance_outside(others) * spacing <= r_contact)
        return sl, core, r, bad, pieces, reg, contact

    # The labels' parts are independent (their transforms and filters release the GIL): on
    # threads, merged in label order (the progress callback only from this thread).
    parts = thread_map(part, range(1, n + 1), cpu_threads(MAX_FILTER_THREADS), "labels")
    for i, res in zip(range(1, n + 1), parts):
        if progress:
            progress(0.4 * i / n, "segment regions")
        if res is None:
            continue
        sl, core, r, bad, pieces, reg, contact = res
        if pieces:
            out.unsupported[sl] |= bad
            out.unsupported_info[i] = pieces
        out.cores[sl][core] = i
        out.core_depth[i] = r
        out.regions[i] = (sl, reg)
        out.union[sl] |= reg
        if contact is not None:
            out.contact[sl] |= contact
    return out


def _bone_foreground(ct, labelled, cores, *, h0, ht, t_low, theta_max) -> tuple:
    """(fg, strong): the bone evidence - the components of [HT, theta_max] (in a label:
    [t_low, theta_max]) that hold [H0, theta_max] or a core, with the cores - and [H0,
    theta_max] itself."""
    in_window = ((ct >= ht) | (labelled & (ct >= t_low))) & (ct <= theta_max)
    strong = (ct >= h0) & (ct <= theta_max)
    lab, nl = ndimage.label(in_window, structure=SIX)
    keep = np.zeros(nl + 1, bool)
    keep[np.unique(lab[(strong | (cores > 0)) & in_window])] = True
    keep[0] = False
    fg = keep[lab] | (cores > 0) | (labelled & in_window)
    return fg, strong


def _markers(fg, strong, labels, seg: _LabelParts, other: int, spacing: float,
             seen=None) -> tuple:
    """The flooding's markers (uint16): each label's strong bone and core outside the contact
    zones, and the unlabelled pieces of strong bone outside every region (of at least
    MIN_OTHER_PIECE_MM3) numbered from ``other``; returns (markers, number of pieces, voxels
    of label bone that are no marker: see :func:`_beyond_a_joint_space`).

    ``seen``: (z, y, x) bool, the voxels of a seen joint space (below H0 in a valley of
    SEEN_VALLEY_QUANTA or more), or None."""
    mine = fg & strong & (labels > 0) & ~seg.contact
    om = fg & strong & ~seg.union
    dropped = 0
    if seen is not None:
        beyond = _beyond_a_joint_space(fg, strong, labels, seg, om, seen)
        dropped = int(np.count_nonzero(beyond & mine))
        mine &= ~beyond
    markers = np.where(mine, labels, 0).astype(np.uint16)
    core_marker = (seg.cores > 0) & ~seg.contact
    if seen is not None:
        # A joint space the CT shows is no marker even deep in a label (the flood decides it;
        # a pore of a trabecular core is claimed at its level by the bone around it).
        core_marker &= ~seen & ~beyond
    markers[core_marker] = seg.cores[core_marker]
    om &= markers == 0
    olab, no = ndimage.label(om, structure=SIX)
    n_pieces = 0
    if no:
        size = np.bincount(olab.ravel(), minlength=no + 1)
        ok = size * spacing ** 3 >= MIN_OTHER_PIECE_MM3
        ok[0] = False
        n_pieces = int(ok.sum())
        remap = np.zeros(no + 1, np.uint32)
        remap[ok] = np.arange(n_pieces) + other
        markers[om] = remap[olab[om]].astype(np.uint16)
    return markers, n_pieces, dropped


def _unlabelled_contact(markers, neighbours: set, taken: set, bone, labelled, spacing: float,
                        r_contact: float, ws=None, n: int = 0):
    """The labels' joint zone with unlabelled neighbours: labelled voxels within ``r_contact``
    of strong bone outside every label that continues, outside every label, to the markers of
    ``neighbours`` (unlabelled pieces the merge left as neighbours) and to none of ``taken``
    (the pieces it took in). ``bone``: the strong bone evidence. (z, y, x) bool, or None when
    there is none - or, given the first flood's basins ``ws`` (labels 1..n), when no label's
    basin holds any of that bone (what the zone is there to prevent did not happen, and a second
    flood costs as much as the first).

    Between two labels the joint zone gives no markers because a label may be a few mm wrong at
    a joint (the flood and the joint cut decide there). A neighbour nobody labelled has no label
    to mark such a zone, and a label that overlaps it (an AI femur label on a 1.5 mm grid across
    a 1 mm joint space, over the cup's inner cortex) made the neighbour's cortex the bone's own
    marker: the flood gave the bone the neighbour's cortex beyond the joint space the CT shows.
    Unlabelled bone that the merge takes in (the bone's own end that a rough label misses) is
    no neighbour, and where it continues into a neighbour's bone without a label between them
    (a joint that thick slices hide) the zone is not known: near both the label keeps its
    markers."""
    if not neighbours or not labelled.any():
        return None
    free, nfree = ndimage.label(bone & ~labelled, structure=SIX)
    kind = np.zeros(int(markers.max()) + 1, np.uint8)
    kind[list(neighbours)] = 1
    kind[list(taken)] = 2
    of = kind[markers]
    reach = np.zeros(nfree + 1, bool)
    reach[np.unique(free[of == 1])] = True
    reach[np.unique(free[of == 2])] = False
    reach[0] = False
    sl = bbox_slices(labelled, int(np.ceil(r_contact / spacing)) + 2)
    theirs = reach[free[sl]]
    if not theirs.any():
        return None
    if ws is not None:
        held = ws[sl][theirs]
        if not ((held > 0) & (held <= n)).any():
            return None
    out = np.zeros(labelled.shape, bool)
    out[sl] = labelled[sl] & (distance_outside(theirs) * spacing <= r_contact)
    return out


def _beyond_a_joint_space(fg, strong, labels, seg: _LabelParts, om, seen) -> np.ndarray:
    """Bone inside a label that a joint space the CT shows separates from the label's core,
    and that continues (as strong bone) into unlabelled bone outside every region: a
    neighbour's rim that a coarse label covers (the cup's rim under a rough femur label).
    Its strong voxels are no markers of the label, so the flooding gives it to the bone it
    continues into unless the label's own bone reaches it first over the valley map.
    (z, y, x) bool."""
    out = np.zeros(labels.shape, bool)
    if not om.any():
        return out
    # Strong bone that continues into unlabelled strong bone outside every region.
    slab, ns = ndimage.label(fg & strong, structure=SIX)
    shared = np.zeros(ns + 1, bool)
    shared[np.unique(slab[om])] = True
    shared[0] = False
    for i, (sl, _) in seg.regions.items():
        lab_i = labels[sl] == i
        core_i = seg.cores[sl] == i
        if not core_i.any():
            continue
        # The label's bone evidence less the seen joint space: the parts its core reaches.
        # Every part holding core voxels counts (anchored on the largest core part alone, a
        # femoral head whose core the marrow's valleys part from the shaft's was cut off).
        parts, npart = ndimage.label(lab_i & fg[sl] & ~seen[sl], structure=SIX)
        if npart < 2:
            continue
        reached = np.zeros(npart + 1, bool)
        reached[np.unique(parts[core_i])] = True
        reached[0] = True
        # A part cut off whose strong bone continues into unlabelled bone is a neighbour's
        # when a joint space bounds it: most of its shell inside the label is the seen joint
        # space (a sheet of cartilage between two cortices). A piece of a thin plate that the
        # holes of its lace cut off lies in soft tissue the label covers instead.
        hit = ~reached[parts] & shared[slab[sl]]
        cand = np.unique(parts[hit])
        cand = cand[cand > 0]
        if not len(cand):
            continue
        is_cand = np.zeros(npart + 1, bool)
        is_cand[cand] = True
        grown = ndimage.grey_dilation(np.where(is_cand[parts], parts, 0), footprint=SIX,
                                      mode="constant", cval=0)
        shell = (grown > 0) & (parts == 0) & lab_i
        total = np.bincount(grown[shell], minlength=npart + 1)
        joint = np.bincount(grown[shell & seen[sl]], minlength=npart + 1)
        foreign = is_cand & (joint >= RIM_JOINT_FRACTION * np.maximum(total, 1))
        foreign[0] = False
        out[sl] |= foreign[parts]
    return out


def _misplaced_cores(fg, levels, markers, labels, seg: _LabelParts, n: int, spacing: float,
                     *, margin_vox: int, min_mm3: float = MISPLACED_MIN_MM3,
                     split_joints=None) -> list:
    """Parts of a label that lie in a labelled neighbour's bone (an AI label that took a block
    of the next vertebra's body across the disc): [(record, (z, y, x) bool voxels to give to
    the neighbour: slices of the grid, bool on them)], empty when there are none.

    A candidate is a connected part of label a's core other than its largest, of at least
    ``min_mm3``, lying mostly (MISPLACED_IN_REGION_FRACTION) in another label's region.
    Its territory is the part of the label nearer to it than to the rest of a's core (within
    ``margin_vox`` of it). One trial flood runs without a's markers in the territories (every
    candidate at once), its basins split at the joints as the run's own are
    (``split_joints(ws, cores, regions, only)``: the run's joint cut and carried fits, see
    :func:`compute_ownership`; None: the flood alone); a candidate whose core a labelled
    neighbour b then fills to at least
    MISPLACED_TAKEN_FRACTION, and more than a, is b's bone: the CT joins it to b's bone without
    a joint space, while a reaches it only across one (or not at all). Bone the label has no
    rival for, or that continues into its own core, comes back to a in the trial."""
    mains = {}  # label -> (its region's slices, its largest core part there or None)
    cands = []
    for a, (sl, _) in seg.regions.items():
        comp, nc = ndimage.label(seg.cores[sl] == a, structure=SIX)
        size = np.bincount(comp.ravel(), minlength=nc + 1)
        size[0] = 0
        main = int(np.argmax(size))
        mains[a] = (sl, comp == main if nc else None)
        if nc < 2:
            continue
        ids = [c for c in range(1, nc + 1)
               if c != main and size[c] * spacing ** 3 >= min_mm3]
        if not ids:
            continue
        others = np.zeros(comp.shape, bool)
        for b, entry in seg.regions.items():
            part = paste_box(entry, sl) if b != a else None
            if part is not None:
                others |= part
        inside = np.bincount(comp[others], minlength=nc + 1)
        boxes = ndimage.find_objects(comp)
        for c in ids:
            if inside[c] < MISPLACED_IN_REGION_FRACTION * size[c]:
                continue
            # The territory on the candidate's box grown by the margin: label voxels whose
            # nearest core voxel of a is the candidate's.
            box = tuple(slice(max(q.start - margin_vox, 0), min(q.stop + margin_vox, dim))
                        for q, dim in zip(boxes[c - 1], comp.shape))
            cbox = comp[box]
            _, idx = ndimage.distance_transform_edt(cbox == 0, return_indices=True)
            near = cbox[tuple(idx)] == c
            del idx
            gbox = tuple(slice(p.start + q.start, p.start + q.stop) for p, q in zip(sl, box))
            terr = near & (labels[gbox] == a)
            cands.append((a, c, terr, gbox, cbox == c, int(size[c]), int(size[main])))
    if not cands:
        return []
    trial = markers.copy()
    for a, _, terr, gbox, _, _, _ in cands:
        t = trial[gbox]
        t[terr & (t == a)] = 0
    ws = flood_from_markers(trial, levels, fg)
    del trial
    if split_joints is not None:
        # The joints as the run itself splits them: a label's own bone across a joint the
        # slices hide (the dome of an acetabulum over the femoral head's pole on thick slices)
        # would otherwise flood from the neighbour as if it were the neighbour's. On copies of
        # the cores and regions; only the joints of the labels tried (the others do not reach
        # the candidates).
        split_joints(ws, seg.cores.copy(), dict(seg.regions), only={a for a, *_ in cands})
    basins = {}
    moved = []
    for a, c, terr, gbox, mine, n_core, n_main in cands:
        got = np.bincount(ws[gbox][mine], minlength=n + 2)[:n + 1]
        got[0] = 0
        rivals = got.copy()
        rivals[a] = 0
        b = int(np.argmax(rivals))
        if b == 0 or rivals[b] < MISPLACED_TAKEN_FRACTION * n_core or rivals[b] <= got[a]:
            continue
        # Only b's own bone counts: the part of b's basin joined to b's largest core part (not
        # a block that b's label itself took from a neighbour, which floods the same way).
        if b not in basins:
            basins[b] = _main_basin(ws, b, *mains[b]) if b in mains else None
        main_b = basins[b]
        rivals[b] = int(np.count_nonzero(main_b[gbox][mine])) if main_b is not None else 0
        if rivals[b] < MISPLACED_TAKEN_FRACTION * n_core or rivals[b] <= got[a]:
            continue
        moved.append(({"from": int(a), "to": b,
                       "core_ml": round(n_core * spacing ** 3 / 1000.0, 3),
                       "label_ml": round(float(terr.sum()) * spacing ** 3 / 1000.0, 3),
                       "main_core_ml": round(n_main * spacing ** 3 / 1000.0, 3),
                       "taken_fraction": round(float(rivals[b]) / n_core, 3),
                       "kept_fraction": round(float(got[a]) / n_core, 3)}, gbox, terr))
    return moved


def _main_basin(ws, b: int, sl: tuple, main) -> np.ndarray:
    """The part of label b's basin in ``ws`` joined to ``main`` (b's largest core part: a bool
    mask on the slices ``sl``), (z, y, x) bool; None when b has no core."""
    if main is None:
        return None
    basin, _ = ndimage.label(ws == b, structure=SIX)
    ids = np.unique(basin[sl][main])
    return np.isin(basin, ids[ids > 0])


def _foreign_pieces(faces: dict, merged: set, kept: set) -> set:
    """The merged pieces that belong to a larger unlabelled bone: those connected (through
    contacts between unlabelled pieces) to a piece that was not merged. A merged piece that
    touches only its bone and other merged pieces is enclosed by that bone - its own, missed by
    the segment (a thin plate an AI label left out); one that continues into unlabelled bone
    the merge did not take is a fragment of a neighbour cut off by the bone's region (fused
    with it across a joint the CT does not resolve). Only the latter (and the merged pieces
    whose contact shows a valley on OWN_MAX_VALLEY_FRACTION of it or more) count as fused bone
    in the plausibility gate."""
    if not merged or not kept:
        return set()
    pieces = merged | kept
    adjacent: dict = {}
    for a, b in faces:
        if a in pieces and b in pieces:
            adjacent.setdefault(a, []).append(b)
            adjacent.setdefault(b, []).append(a)
    reached = set(kept)
    todo = list(kept)
    while todo:
        for q in adjacent.get(todo.pop(), ()):
            if q not in reached:
                reached.add(q)
                todo.append(q)
    return reached & merged


def _within_reach(piece: int, a: int, ws, labels, spacing: float, reach_mm: float,
                  boxes: list) -> bool:
    """Does every voxel of unlabelled piece ``piece`` lie within ``reach_mm`` of label ``a``?"""
    pad = int(np.ceil(reach_mm / spacing)) + 1
    # The label within reach of the piece lies in its box grown by the reach: the distance
    # measured there is exact up to the reach, and beyond it only larger.
    box = tuple(slice(max(0, b.start - pad), min(size, b.stop + pad))
                for b, size in zip(boxes[piece - 1], ws.shape))
    lab_a = labels[box] == a
    if not lab_a.any():
        return False
    return bool((distance_outside(lab_a) * spacing)[ws[box] == piece].max() <= reach_mm)


def _enclosed_pieces(faces: dict, merged: list, pieces, n: int, ws, labels, spacing: float,
                     reach_mm: float, boxes: list, plate_depth_mm: float = 0.0,
                     plates: set | None = None) -> list:
    """Unlabelled pieces that the first merge (:func:`_merged_pieces`) left out but that lie
    enclosed in one bone's merged bone - a crumb of the bone's own cortex between its merged
    pieces that touches the bone itself over too little (the trochanter of a femur whose rough
    label stops short of it). Left unmerged, such a crumb made every merged piece around it
    count as a neighbour's fragment (the plausibility gate refused the bone) and kept the
    surface out of itself (a dent).

    The candidates are grouped into clusters (touching each other); a cluster joins bone a when
    every contact it has outside itself is with a or with pieces merged into a, a valley shows
    on less than OWN_MAX_VALLEY_FRACTION of those contacts (and on less than
    MERGE_MAX_VALLEY_FRACTION of each direct contact with a of at least MERGE_MIN_AREA_MM2),
    and each of its pieces lies within ``reach_mm`` of a's label - or is a thin plate within
    the label's span (:func:`_plate_in_span`, thinner than ``plate_depth_mm`` deep: a plate
    the CT barely resolves, which a coarse or AI segment leaves out between its labelled parts;
    left out, it became a hole in the surface that the segment does not have). A cluster that
    fails is no candidate any more, so the clusters touching it fail in turn: nothing joins
    that is connected to unlabelled bone left out (a neighbour the segment does not label).
    [(piece, bone, valley fraction, contact mm^2)] as :func:`_merged_pieces`; the pieces that
    joined as such a plate (beyond the reach) are added to ``plates``."""
    area = spacing ** 2
    into = {p: a for p, a, _, _ in merged}
    cand = {p for p in pieces if p not in into and p <= len(boxes) and boxes[p - 1] is not None}
    touching: dict = {}
    for (a, b), (tot, vis) in faces.items():
        touching.setdefault(a, []).append((b, tot, vis))
        touching.setdefault(b, []).append((a, tot, vis))
    reach_ok: dict = {}
    hulls: dict = {}
    as_plate: set = set()
    verdict: dict = {}
    changed = True
    while changed and cand:
        changed = False
        seen: set = set()
        for start in sorted(cand):
            if start in seen:
                continue
            cluster, stack = {start}, [start]
            while stack:
                for q, _, _ in touching.get(stack.pop(), ()):
                    if q in cand and q not in cluster:
                        cluster.add(q)
                        stack.append(q)
            seen |= cluster
            outside = [(q, t, v) for p in cluster for q, t, v in touching.get(p, ()) if q not in cluster]
            bones = {into.get(q, q) for q, _, _ in outside}
            tot = sum(t for _, t, _ in outside)
            vis = sum(v for _, _, v in outside)
            # A direct contact with the bone shows a joint space only where it is as large as
            # a contact the first merge counts (a face or two in a valley is a crumb's corner).
            ok = (len(bones) == 1 and min(bones) <= n and tot > 0
                  and all(q <= n or q in into for q, _, _ in outside)
                  and vis / tot < OWN_MAX_VALLEY_FRACTION
                  and all(v < MERGE_MAX_VALLEY_FRACTION * t for q, t, v in outside
                          if q <= n and t * area >= MERGE_MIN_AREA_MM2))
            if ok:
                (bone,) = bones
                for p in sorted(cluster):
                    if (p, bone) not in reach_ok:
                        reach_ok[(p, bone)] = _within_reach(p, bone, ws, labels, spacing,
                                                            reach_mm, boxes)
                        if (not reach_ok[(p, bone)] and plate_depth_mm > 0
                                and _plate_in_span(p, bone, ws, labels, spacing, plate_depth_mm,
                                                   boxes, hulls, margin_mm=plate_depth_mm)):
                            reach_ok[(p, bone)] = True
                            as_plate.add(p)
                    ok = ok and reach_ok[(p, bone)]
            if ok:
                verdict[frozenset(cluster)] = (bone, vis / tot, tot * area)
            else:
                cand -= cluster
                changed = True
        verdict = {c: v for c, v in verdict.items() if c <= cand}
    out = []
    for cluster, (bone, frac, contact) in verdict.items():
        out += [(p, bone, frac, contact) for p in sorted(cluster)]
        if plates is not None:
            plates.update(cluster & as_plate)
    return sorted(out)


def _plate_in_span(piece: int, a: int, ws, labels, spacing: float, max_depth_mm: float,
                   boxes: list, hulls: dict, margin_mm: float = 0.0) -> bool:
    """Is unlabelled piece ``piece`` a thin plate inside label ``a``'s span: no voxel deeper
    than ``max_depth_mm`` inside it (it is nowhere thicker than about twice the CT's coarseness)
    and every voxel inside the convex hull of a's label grown by ``margin_mm`` (a coarse label's
    voxels outline the bone only to within their size, and the blurred plate's edge reaches
    beyond the bone's; at least one voxel)? A neighbouring bone is thicker somewhere (a body,
    a head, a joint's rim) or reaches beyond the bone it touches; a plate that a segment missed
    between its labelled parts does neither. ``hulls`` caches the hull's planes per label."""
    box = boxes[piece - 1]
    m = ws[box] == piece
    if distance_inside(np.pad(m, 1)).max() * spacing > max_depth_mm:
        return False
    if a not in hulls:
        lab = labels == a
        sl = bbox_slices(lab, 0)
        lab = lab[sl]
        # The hull of the label's outer voxels is the label's hull (eroded on its own box,
        # whose edge voxels are outer ones).
        shell = lab & ~erode6(lab)
        pts = np.argwhere(shell) + np.array([s.start for s in sl])
        try:
            hulls[a] = ConvexHull(pts.astype(float)).equations if len(pts) >= 4 else None
        except Exception:  # noqa: BLE001 - a flat or degenerate label spans no volume
            hulls[a] = None
    eq = hulls[a]
    if eq is None:
        return False
    q = np.argwhere(m) + np.array([s.start for s in box])
    # Plane offsets are in voxels.
    return bool(np.all(q @ eq[:, :3].T + eq[:, 3] <= max(1.0, margin_mm / spacing)))


def _merged_pieces(faces: dict, ws, labels, n: int, pieces, spacing: float,
                   reach_mm: float, boxes: list, beyond: set | None = None,
                   sided: set | None = None) -> list:
    """Unlabelled pieces meeting a bone without a valley: the bone's own, missed by the
    segment - only what lies within ``reach_mm`` of its label (a whole neighbouring bone
    without a visible joint space does not), or a small piece beyond the reach that continues
    the bone alone (:func:`_small_own_piece`; added to ``beyond`` when given). With ``sided``,
    also a piece with a valley toward the bone that lies on the bone's side of a seen joint
    space (:func:`_on_the_bones_side`; added to ``sided``), then, repeated until none joins, such
    a piece whose contact with unlabelled bone is partly with pieces taken in already.
    ``boxes``: ``ndimage.find_objects(ws)``. [(piece, bone, valley fraction, contact mm^2)]"""
    area = spacing ** 2
    merged = []
    label_voxels: dict = {}
    best_of = {}
    for piece in pieces:
        best = None
        for (a, b), (tot, vis) in faces.items():
            if b != piece or a > n:
                continue
            if best is None or tot - vis > best[1] - best[2]:
                best = (a, tot, vis)
        if best is None or piece > len(boxes) or boxes[piece - 1] is None:
            continue
        a, tot, vis = best
        if tot * area < MERGE_MIN_AREA_MM2:
            continue
        best_of[piece] = best
        side = vis / tot >= MERGE_MAX_VALLEY_FRACTION
        if side and (sided is None or not _on_the_bones_side(piece, a, faces, n)):
            continue
        if _within_reach(piece, a, ws, labels, spacing, reach_mm, boxes):
            merged.append((piece, a, vis / tot, tot * area))
            if side:
                sided.add(piece)
        elif beyond is not None and _small_own_piece(piece, a, faces, n, ws, labels, boxes,
                                                     label_voxels):
            merged.append((piece, a, vis / tot, tot * area))
            beyond.add(piece)
    if sided is None:
        return merged
    # A crumb of the cortex beside a joint may touch another crumb of it that is the bone's
    # own (merged above): that contact is the bone's, not a joint space toward unlabelled bone
    # (femur phantom, held-out seed 89: a 96-voxel crumb of the head's cortex under the cup's
    # rim, 50 % valley toward a merged crumb, stayed unlabelled bone and dented the head 1.1 mm).
    grown = True
    while grown:
        grown = False
        own_of = {p: b for p, b, _, _ in merged}
        for piece, (a, tot, vis) in best_of.items():
            if piece in own_of or vis / tot < MERGE_MAX_VALLEY_FRACTION:
                continue
            siblings = {p for p, b in own_of.items() if b == a}
            if (siblings and _on_the_bones_side(piece, a, faces, n, siblings)
                    and _within_reach(piece, a, ws, labels, spacing, reach_mm, boxes)):
                merged.append((piece, a, vis / tot, tot * area))
                sided.add(piece)
                grown = True
    return merged


def _contacts_of(piece: int, faces: dict, n: int) -> tuple:
    """The contacts of unlabelled ``piece`` (``faces`` of :func:`_interfaces`): ({label:
    (faces, of which with a valley)}, {other unlabelled piece: (faces, with a valley)})."""
    labels_: dict = {}
    pieces: dict = {}
    for (x, y), tv in faces.items():
        if piece in (x, y):
            other = y if x == piece else x
            (labels_ if other <= n else pieces)[other] = tv
    return labels_, pieces


def _on_the_bones_side(piece: int, a: int, faces: dict, n: int, siblings=frozenset()) -> bool:
    """Does unlabelled ``piece``, which shows a valley toward label ``a`` on part of their
    contact, lie on a's side of a joint space the CT shows? It touches no label but ``a``,
    touches unlabelled bone, is separated from each unlabelled piece it touches by a seen
    joint space (on at least 1 - OWN_MAX_VALLEY_FRACTION of that contact), and shows less of
    one toward ``a``: a crumb of a's own cortex beside the joint, outside a label that stops
    short of it (the femoral head's rim facing an unlabelled cup: valley 34-47 % toward the
    femur, 97-100 % toward the cup), whose valley toward ``a`` is the joint space running
    along the cortex on thick slices. ``siblings``: unlabelled pieces already taken in as a's
    own; a contact with one counts as a contact with ``a``."""
    labels_, pieces = _contacts_of(piece, faces, n)
    if set(labels_) != {a}:
        return False
    for s in siblings & set(pieces):  # unlabelled pieces already taken in as a's own
        t, v = pieces.pop(s)
        labels_[a] = (labels_[a][0] + t, labels_[a][1] + v)
    if not pieces:
        return False
    across = min(v / t for t, v in pieces.values())
    t, v = labels_[a]
    return across >= 1.0 - OWN_MAX_VALLEY_FRACTION and v / t < across


def _small_own_piece(piece: int, a: int, faces: dict, n: int, ws, labels, boxes: list,
                     label_voxels: dict) -> bool:
    """Is unlabelled ``piece`` (beyond the merge's reach of label ``a``) a's own process that
    the segment stopped short of - a spinous tip 12 mm beyond a 3 mm vertebra's label? It
    touches bone ``a`` alone (no other label, no other unlabelled piece), a joint space shows
    on less than OWN_MAX_VALLEY_FRACTION of the contact (bone that continues), it ends inside
    the working grid (a piece the grid's border cuts may go on into a neighbour: the head of a
    rib at a 1.5 mm T12, 0.89 ml, cut by the crop 11 mm from the label), and it is at most
    SMALL_PIECE_FRACTION of a's label: a whole neighbouring bone is not that small, and a
    neighbour's piece that small, merged, stays within what the plausibility gate accepts of
    unlabelled bone. ``label_voxels``: a cache of the labels' voxel counts."""
    box = boxes[piece - 1]
    if any(b.start == 0 or b.stop == size for b, size in zip(box, ws.shape)):
        return False
    labels_, pieces = _contacts_of(piece, faces, n)
    if pieces or set(labels_) != {a}:
        return False
    tot, vis = labels_[a]
    if vis / tot >= OWN_MAX_VALLEY_FRACTION:
        return False
    if a not in label_voxels:
        label_voxels[a] = int(np.count_nonzero(labels == a))
    size = int(np.count_nonzero(ws[box] == piece))
    return size <= SMALL_PIECE_FRACTION * label_voxels[a]


def _owners(ws, regions: dict, markers, labels, merged: list, boxes: list) -> np.ndarray:
    """Owner (uint16 label index, 0 none) of each voxel: label i's basin within its region
    (with the pieces merged into it), its fragments kept when they hold a marker of i or lie
    mostly in the label. ``boxes``: ``ndimage.find_objects(ws)`` (or boxes holding them).
    Each label is worked on the box of its region and its merged pieces."""
    grow: dict = {}
    for piece, a, _, _ in merged:
        grow.setdefault(a, []).append(piece)
    owner = np.zeros(ws.shape, np.uint16)
    for i, (sl, reg) in regions.items():
        pieces = grow.get(i, [])
        box = sl
        for p in pieces:
            if p <= len(boxes) and boxes[p - 1] is not None:
                box = tuple(slice(min(a.start, b.start), max(a.stop, b.stop))
                            for a, b in zip(box, boxes[p - 1]))
        w = ws[box]
        inner = tuple(slice(s.start - b.start, s.stop - b.start) for s, b in zip(sl, box))
        own = np.zeros(w.shape, bool)
        own[inner] = (w[inner] == i) & reg
        if pieces:
            own |= np.isin(w, pieces)
        lab_i, n_i = ndimage.label(own, structure=SIX)
        if n_i > 1:
            ok = np.zeros(n_i + 1, bool)
            ok[np.unique(lab_i[(markers[box] == i) & own])] = True
            size = np.bincount(lab_i.ravel(), minlength=n_i + 1)
            inlab = np.bincount(lab_i[labels[box] == i], minlength=n_i + 1)
            ok |= inlab >= FRAGMENT_IN_LABEL_FRACTION * size
            ok[0] = False
            own = ok[lab_i]
        owner[box][own] = i
    return owner


def _pair_contacts(faces: dict, n: int, other: int, merged_ids: set, area: float,
                   fragments: dict | None = None) -> list:
    """Per pair of labels (the unlabelled pieces pooled as ``other``): contact area (mm^2)
    and the fraction of it where a joint space is seen. ``fragments`` ({piece: label}): merged
    pieces that are a neighbour's fragments (:func:`_foreign_pieces`); where one meets the rest
    of that unlabelled neighbour, the bone it was merged into meets it (the merge moved the
    bone's boundary there: a femur whose region cut a fragment off an unlabelled cup touches
    the cup beyond the fragment too)."""
    fragments = fragments or {}
    pooled: dict = {}
    for (a, b), (tot, vis) in faces.items():
        if a in fragments and b > n and b not in merged_ids:
            a2, b2 = fragments[a], other
        elif b in fragments and a > n and a not in merged_ids:
            a2, b2 = fragments[b], other
        elif (b in merged_ids) or (a in merged_ids):
            continue
        else:
            a2 = a if a <= n else other
            b2 = b if b <= n else other
        if a2 == b2:
            continue
        key = (min(a2, b2), max(a2, b2))
        t0, v0 = pooled.get(key, (0, 0))
        pooled[key] = (t0 + tot, v0 + vis)
    return [{"a": a, "b": b, "contact_area_mm2": tot * area,
             "valley_seen_fraction": vis / tot if tot else 0.0}
            for (a, b), (tot, vis) in sorted(pooled.items())]
