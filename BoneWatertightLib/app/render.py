"""PNG pictures of a reconstructed surface: shaded views and CT slices with the contour.

Only numpy and matplotlib are used. matplotlib is optional (a CLI/development dependency):
it is imported inside the functions, with the Agg canvas attached to a private ``Figure`` so
the global pyplot backend (e.g. inside 3D Slicer or a notebook) is never touched. Without
matplotlib the functions raise :class:`~BoneWatertightLib.errors.DependencyError`.

Geometry conventions: surfaces are drawn in physical LPS millimetres (a RAS surface is
converted first). CT slices are the CT's own index planes nearest to the surface centroid;
the surface's cross-section is computed by intersecting the triangles with that plane, which
is exact in index space because the index <-> physical map is affine. Slices are shown in
radiological orientation: axial and coronal with the patient's left on the right of the
picture, axial with anterior up, coronal and sagittal with superior up, sagittal with
anterior on the left.
"""

from __future__ import annotations

import os
from typing import Optional, Sequence, Union

import numpy as np

from ..errors import DependencyError, InputError
from ..mesh.surface import Surface

# Bone window (HU) for the CT slices: soft tissue grey, cortical bone white.
DEFAULT_WINDOW = (-350.0, 1250.0)
# Beyond this many front-facing triangles per view, draw a random subset (drawing only:
# at that density each triangle is below one pixel in a ~500 px view, so the look is unchanged).
MAX_DRAWN_FACES = 120_000
BONE_RGB = np.array([0.93, 0.87, 0.74])
CONTOUR_COLORS = ("#ff3b30", "#00c8ff", "#ffd60a", "#34c759", "#bf5af2", "#ff9f0a",
                  "#ffffff", "#ff2d92")

# Camera of each mesh view: (name, direction the camera looks along, screen-up), in LPS.
# screen-right = look x up, so no view is mirrored (anterior view: patient's left on the right).
_VIEWS = {
    "anterior": ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    "left": ((-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "superior": ((0.0, 0.0, -1.0), (0.0, -1.0, 0.0)),
    "posterior": ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    "right": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "inferior": ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
}

# Slice kinds by the LPS axis the plane is normal to: (name, horizontal LPS axis, its sign
# pointing right, vertical LPS axis, its sign pointing up).
_SLICE_LAYOUT = {
    2: ("axial", 0, +1, 1, -1),
    1: ("coronal", 0, +1, 2, +1),
    0: ("sagittal", 1, +1, 2, +1),
}
_AXIS_LETTERS = {0: ("R", "L"), 1: ("A", "P"), 2: ("I", "S")}


# ----------------------------------------------------------------------------------------
# matplotlib

def require_matplotlib():
    """Import matplotlib or raise DependencyError (call it early to fail before a long run)."""
    try:
        import matplotlib  # noqa: F401
        from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: F401
        from matplotlib.figure import Figure  # noqa: F401
    except ImportError as exc:
        raise DependencyError(
            "Pictures need matplotlib, which is not installed ({}). Install it with "
            "'python -m pip install matplotlib' or leave out --picture.".format(exc)) from None


def _new_figure(width_in: float, height_in: float, dpi: int):
    require_matplotlib()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=dpi, facecolor="white")
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path) -> None:
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise InputError(f"Output folder does not exist: {folder}")
    # format given explicitly: the CLI writes to a temporary name before renaming it.
    fig.savefig(path, format="png", dpi=fig.dpi, facecolor=fig.get_facecolor())


# ----------------------------------------------------------------------------------------
# mesh views

def _as_lps(surface: Surface) -> Surface:
    if not isinstance(surface, Surface):
        raise InputError("render: expected a BoneWatertightLib.mesh.Surface.")
    if surface.n_faces == 0:
        raise InputError("render: the surface has no triangles.")
    return surface.to_lps() if surface.coordinate_system == "RAS" else surface


def _camera(view: Union[str, tuple]):
    if isinstance(view, str):
        if view not in _VIEWS:
            raise InputError(f"Unknown view '{view}'. Choose from: {', '.join(_VIEWS)}.")
        look, up = _VIEWS[view]
    else:
        look, up = view
    look = np.asarray(look, dtype=np.float64)
    look = look / np.linalg.norm(look)
    up = np.asarray(up, dtype=np.float64)
    up = up - look * (up @ look)
    up = up / np.linalg.norm(up)
    right = np.cross(look, up)
    return look, up, right


def _resolve_scalars(surface: Surface, scalars) -> Optional[np.ndarray]:
    if scalars is None:
        return None
    if isinstance(scalars, str):
        if scalars == "auto":
            scalars = "DistanceToConstraints"
            if scalars not in surface.point_data:
                return None
        if scalars not in surface.point_data:
            raise InputError(f"render: the surface has no point data '{scalars}' "
                             f"(it has: {', '.join(surface.point_data) or 'none'}).")
        scalars = surface.point_data[scalars]
    values = np.asarray(scalars, dtype=np.float64).ravel()
    if values.size != surface.n_vertices:
        raise InputError(f"render: {values.size} scalar values for {surface.n_vertices} "
                         "vertices; give one value per vertex.")
    return values


def shade_faces(vertices: np.ndarray, faces: np.ndarray, look: np.ndarray, up: np.ndarray,
                face_values: Optional[np.ndarray] = None, cmap=None, norm=None,
                max_faces: int = MAX_DRAWN_FACES, seed: int = 0):
    """Polygons (k, 3, 3) in view order (far to near) and their RGB colours (k, 3).

    ``look``/``up``: unit camera direction and screen-up. Flat Lambert shading with the light
    from behind the viewer's upper left, so creases read in relief; back faces of a closed,
    outward-oriented surface are hidden by the front ones and are culled. The painter's
    algorithm (sort by depth) replaces a z-buffer.
    """
    tri = vertices[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1)
    normal = normal / np.maximum(length, 1e-300)[:, None]
    facing = -(normal @ look)
    keep = np.flatnonzero((facing > 0.0) & (length > 0.0))
    if keep.size > max_faces:
        keep = np.sort(np.random.default_rng(seed).choice(keep, max_faces, replace=False))
    tri, normal = tri[keep], normal[keep]
    depth = tri.mean(axis=1) @ look
    order = np.argsort(-depth, kind="stable")  # farthest first
    tri, normal, keep = tri[order], normal[order], keep[order]

    right = np.cross(look, up)
    light = -look + 0.45 * up - 0.35 * right
    light = light / np.linalg.norm(light)
    lambert = np.clip(normal @ light, 0.0, 1.0)
    intensity = 0.28 + 0.72 * lambert
    if face_values is None:
        base = np.broadcast_to(BONE_RGB, (len(keep), 3))
    else:
        base = np.asarray(cmap(norm(face_values[keep])))[:, :3]
    colors = np.clip(base * intensity[:, None], 0.0, 1.0)
    return tri, colors


def _draw_mesh_view(ax, surface: Surface, view, values, cmap, norm, max_faces):
    from matplotlib.collections import PolyCollection

    look, up, right = _camera(view)
    face_values = None if values is None else values[surface.faces].mean(axis=1)
    tri, colors = shade_faces(surface.vertices, surface.faces, look, up, face_values, cmap,
                              norm, max_faces)
    xy = np.stack([tri @ right, tri @ up], axis=-1)
    coll = PolyCollection(xy, facecolors=colors, edgecolors="none", linewidths=0.0,
                          antialiased=False)
    ax.add_collection(coll)
    proj = np.stack([surface.vertices @ right, surface.vertices @ up], axis=-1)
    lo, hi = proj.min(axis=0), proj.max(axis=0)
    pad = 0.04 * max(hi - lo) + 1e-6
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    # Room below the mesh for the scale bar.
    ax.set_ylim(lo[1] - 4.0 * pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    for spine in ax.spines.values():
        spine.set_visible(False)
    name = view if isinstance(view, str) else "view"
    ax.set_title(f"{name}  ({_direction_letter(right)}\u2192, {_direction_letter(up)}\u2191)",
                 fontsize=9)
    _scale_bar(ax, lo, hi, pad)


def _direction_letter(vector: np.ndarray) -> str:
    axis = int(np.argmax(np.abs(vector)))
    return _AXIS_LETTERS[axis][1 if vector[axis] > 0 else 0]


def _scale_bar(ax, lo, hi, pad):
    span = float(max(hi - lo))
    if span <= 0:
        return
    nice = [1, 2, 5, 10, 20, 25, 50, 100, 200, 500]
    length = max([n for n in nice if n <= span / 3.0] or [nice[0]])
    x0, y0 = lo[0], lo[1] - 3.0 * pad
    ax.plot([x0, x0 + length], [y0, y0], color="black", linewidth=2, solid_capstyle="butt")
    ax.text(x0 + length + 0.3 * pad, y0, f"{length:g} mm", ha="left", va="center",
            fontsize=7)


# ----------------------------------------------------------------------------------------
# CT slices and cross-sections

def _index_matrix(ct):
    """(M, origin): continuous index = M^-1 (p - origin), M = direction @ diag(spacing)."""
    direction = np.array(ct.GetDirection(), dtype=np.float64).reshape(3, 3)
    spacing = np.array(ct.GetSpacing(), dtype=np.float64)
    return direction * spacing[None, :], np.array(ct.GetOrigin(), dtype=np.float64)


def physical_to_index(ct, points: np.ndarray) -> np.ndarray:
    """Continuous (i, j, k) index of physical LPS points (n, 3) in ``ct``."""
    m, origin = _index_matrix(ct)
    return np.linalg.solve(m, (np.asarray(points, dtype=np.float64) - origin).T).T


def index_to_physical(ct, index: np.ndarray) -> np.ndarray:
    m, origin = _index_matrix(ct)
    return np.asarray(index, dtype=np.float64) @ m.T + origin


def plane_section(index_vertices: np.ndarray, faces: np.ndarray, axis: int,
                  value: float) -> np.ndarray:
    """Segments (s, 2, 3) where the triangles cross the index plane ``index[axis] == value``.

    Vertices on the plane count as above it, so every crossed triangle has exactly two
    crossing edges and no segment is produced twice or degenerates.
    """
    f = index_vertices[:, axis] - value
    above = f[faces] >= 0.0
    count = above.sum(axis=1)
    crossed = np.flatnonzero((count == 1) | (count == 2))
    if crossed.size == 0:
        return np.zeros((0, 2, 3))
    tri = faces[crossed]
    ab = above[crossed]
    points = []
    for a, b in ((0, 1), (1, 2), (2, 0)):
        va, vb = tri[:, a], tri[:, b]
        cut = ab[:, a] != ab[:, b]
        fa, fb = f[va], f[vb]
        t = np.where(cut, fa / np.where(cut, fa - fb, 1.0), 0.0)
        p = index_vertices[va] + t[:, None] * (index_vertices[vb] - index_vertices[va])
        points.append((cut, p))
    # Two of the three edges are cut: pick them in edge order.
    cuts = np.stack([c for c, _ in points], axis=1)           # (s, 3)
    pts = np.stack([p for _, p in points], axis=1)            # (s, 3, 3)
    first = np.argmax(cuts, axis=1)
    second = 2 - np.argmax(cuts[:, ::-1], axis=1)
    rows = np.arange(len(tri))
    return np.stack([pts[rows, first], pts[rows, second]], axis=1)


def surface_section(ct, surface: Surface, axis: int, index_value: float) -> np.ndarray:
    """Physical LPS segments (s, 2, 3) of the surface in the CT index plane axis = value."""
    surface = _as_lps(surface)
    idx = physical_to_index(ct, surface.vertices)
    seg = plane_section(idx, surface.faces, axis, index_value)
    if len(seg) == 0:
        return seg
    return index_to_physical(ct, seg.reshape(-1, 3)).reshape(-1, 2, 3)


class _SliceFrame:
    """Display coordinates (mm, origin lower-left) of one index plane of a CT."""

    def __init__(self, ct, axis: int, index_value: int):
        self.axis = axis
        self.index_value = int(index_value)
        direction = np.array(ct.GetDirection(), dtype=np.float64).reshape(3, 3)
        self.size = np.array(ct.GetSize())
        self.spacing = np.array(ct.GetSpacing(), dtype=np.float64)
        dominant = np.argmax(np.abs(direction), axis=0)         # image axis -> LPS axis
        signs = np.sign(direction[dominant, np.arange(3)])
        in_plane = [a for a in range(3) if a != axis]
        name, h_lps, h_sign, v_lps, v_sign = _SLICE_LAYOUT[int(dominant[axis])]
        # Oblique volumes may map two image axes to the same LPS axis: fall back to order.
        h = next((a for a in in_plane if dominant[a] == h_lps), in_plane[0])
        v = next(a for a in in_plane if a != h)
        self.name = name
        self.h, self.v = h, v
        self.flip_h = signs[h] * h_sign < 0
        self.flip_v = signs[v] * v_sign < 0
        self.h_letters = _AXIS_LETTERS[h_lps] if h_sign > 0 else _AXIS_LETTERS[h_lps][::-1]
        self.v_letters = _AXIS_LETTERS[v_lps] if v_sign > 0 else _AXIS_LETTERS[v_lps][::-1]

    def display(self, index_points: np.ndarray) -> np.ndarray:
        """(n, 3) continuous indices -> (n, 2) display mm."""
        out = np.empty((len(index_points), 2))
        for col, (a, flip) in enumerate(((self.h, self.flip_h), (self.v, self.flip_v))):
            i = index_points[:, a]
            out[:, col] = ((self.size[a] - 1 - i) if flip else i) * self.spacing[a]
        return out

    def image(self, array_zyx: np.ndarray) -> np.ndarray:
        """The plane as a 2-D array with rows = vertical (bottom first), cols = horizontal."""
        plane = np.take(array_zyx, self.index_value, axis=2 - self.axis)
        # Remaining array axes are the image axes in decreasing order (numpy is z, y, x).
        remaining = [a for a in (2, 1, 0) if a != self.axis]
        if remaining.index(self.v) != 0:
            plane = plane.T
        if self.flip_v:
            plane = plane[::-1]
        if self.flip_h:
            plane = plane[:, ::-1]
        return plane

    def extent(self):
        sh, sv = self.spacing[self.h], self.spacing[self.v]
        nh, nv = self.size[self.h], self.size[self.v]
        return (-0.5 * sh, (nh - 0.5) * sh, -0.5 * sv, (nv - 0.5) * sv)


def _centre_index(ct, centre_lps) -> np.ndarray:
    idx = np.rint(physical_to_index(ct, np.asarray(centre_lps, dtype=np.float64)[None])[0])
    return np.clip(idx, 0, np.array(ct.GetSize()) - 1).astype(int)


def _draw_slice(ax, ct, array_zyx, axis, centre_idx, surfaces, colors, window, margin_mm,
                show_legend=False):
    from matplotlib.collections import LineCollection

    frame = _SliceFrame(ct, axis, centre_idx[axis])
    ax.imshow(frame.image(array_zyx), cmap="gray", vmin=window[0], vmax=window[1],
              origin="lower", extent=frame.extent(), interpolation="nearest")
    boxes = []
    handles = []
    for (name, surface), color in zip(surfaces.items(), colors):
        idx = physical_to_index(ct, surface.vertices)
        seg = plane_section(idx, surface.faces, axis, float(frame.index_value))
        disp_all = frame.display(idx)
        boxes.append((disp_all.min(axis=0), disp_all.max(axis=0)))
        if len(seg):
            lines = frame.display(seg.reshape(-1, 3)).reshape(-1, 2, 2)
            ax.add_collection(LineCollection(lines, colors=color, linewidths=1.3))
        handles.append((name, color))
    if boxes:
        lo = np.min([b[0] for b in boxes], axis=0) - margin_mm
        hi = np.max([b[1] for b in boxes], axis=0) + margin_mm
        ext = frame.extent()
        lo = np.maximum(lo, [ext[0], ext[2]])
        hi = np.minimum(hi, [ext[1], ext[3]])
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    ijk = "ijk"[axis]
    ax.set_title(f"{frame.name}, {ijk} = {frame.index_value}", fontsize=9)
    # Orientation letters at the picture edges.
    style = dict(transform=ax.transAxes, color="yellow", fontsize=8, fontweight="bold")
    ax.text(0.01, 0.5, frame.h_letters[0], ha="left", va="center", **style)
    ax.text(0.99, 0.5, frame.h_letters[1], ha="right", va="center", **style)
    ax.text(0.5, 0.01, frame.v_letters[0], ha="center", va="bottom", **style)
    ax.text(0.5, 0.99, frame.v_letters[1], ha="center", va="top", **style)
    if show_legend and handles:
        from matplotlib.lines import Line2D

        ax.legend([Line2D([0], [0], color=c, linewidth=2) for _, c in handles],
                  [n for n, _ in handles], loc="lower right", fontsize=7, framealpha=0.7)


def _ct_array(ct) -> np.ndarray:
    import SimpleITK as sitk

    if ct.GetDimension() != 3 or ct.GetNumberOfComponentsPerPixel() != 1:
        raise InputError("render: the CT must be a scalar 3-D image.")
    return sitk.GetArrayViewFromImage(ct)


# ----------------------------------------------------------------------------------------
# public

def render_surface(surface: Surface, path, ct=None, title: Optional[str] = None,
                   scalars="auto", scalar_label: Optional[str] = None,
                   scalar_range: Optional[Sequence[float]] = None,
                   views: Sequence = ("anterior", "left", "superior"),
                   window: Sequence[float] = DEFAULT_WINDOW, margin_mm: float = 15.0,
                   max_faces: int = MAX_DRAWN_FACES, dpi: int = 110,
                   cmap: str = "viridis") -> str:
    """Write one PNG: shaded views of ``surface`` and, with ``ct``, three CT slices.

    ``scalars``: per-vertex values (array of n_vertices, in mm) or the name of a point-data
    array to colour the views by, with a colour bar; ``"auto"`` (default) uses
    "DistanceToConstraints" when the surface has it, ``None`` draws plain bone colour.
    ``ct`` (SimpleITK image, LPS): the three index planes nearest the surface centroid are
    shown with the surface's cross-section drawn over them. Returns ``path``.
    """
    surface = _as_lps(surface)
    values = _resolve_scalars(surface, scalars)
    n_views = len(views)
    rows = 2 if ct is not None else 1
    fig = _new_figure(3.3 * max(n_views, 3) + (0.9 if values is not None else 0.0),
                      3.5 * rows + 0.5, dpi)
    import matplotlib

    cmap_obj = matplotlib.colormaps[cmap]
    norm = None
    if values is not None:
        from matplotlib.colors import Normalize

        finite = values[np.isfinite(values)]
        if scalar_range is not None:
            vmin, vmax = (float(v) for v in scalar_range)
        elif finite.size:
            vmin = min(0.0, float(finite.min()))
            vmax = float(np.percentile(finite, 99.0))
        else:
            vmin, vmax = 0.0, 1.0
        if not vmax > vmin:
            vmax = vmin + 1.0
        norm = Normalize(vmin=vmin, vmax=vmax, clip=True)
        values = np.where(np.isfinite(values), values, vmax)

    grid = fig.add_gridspec(rows, max(n_views, 3), left=0.02, right=0.9 if values is not None
                            else 0.98, top=0.9 if rows == 2 else 0.84, bottom=0.03, wspace=0.08,
                            hspace=0.18)
    mesh_axes = []
    for col, view in enumerate(views):
        ax = fig.add_subplot(grid[0, col])
        _draw_mesh_view(ax, surface, view, values, cmap_obj, norm, max_faces)
        mesh_axes.append(ax)
    if values is not None:
        from matplotlib.cm import ScalarMappable

        mappable = ScalarMappable(norm=norm, cmap=cmap_obj)
        cax = fig.add_axes([0.915, 0.55 if rows == 2 else 0.12, 0.015,
                            0.33 if rows == 2 else 0.7])
        label = scalar_label or (scalars if isinstance(scalars, str) and scalars != "auto"
                                 else ("distance to constraints" if isinstance(scalars, str)
                                       else "scalar"))
        fig.colorbar(mappable, cax=cax).set_label(f"{label} (mm)", fontsize=8)
        cax.tick_params(labelsize=7)

    if ct is not None:
        array = _ct_array(ct)
        centre = surface.vertices.mean(axis=0)
        centre_idx = _centre_index(ct, centre)
        # k plane first: for the usual axial CT that is the axial slice.
        for col, axis in enumerate((2, 1, 0)):
            ax = fig.add_subplot(grid[1, col])
            _draw_slice(ax, ct, array, axis, centre_idx, {"surface": surface},
                        [CONTOUR_COLORS[0]], window, margin_mm)

    heading = title or "surface"
    fig.suptitle(f"{heading}: {surface.n_vertices} vertices, {surface.n_faces} triangles "
                 f"({surface.coordinate_system} mm)", fontsize=11)
    _save(fig, path)
    return os.fspath(path)


def render_cross_sections(ct, surfaces: dict, path, center=None, title: Optional[str] = None,
                          colors: Optional[Sequence[str]] = None,
                          window: Sequence[float] = DEFAULT_WINDOW, margin_mm: float = 15.0,
                          axes: Sequence[int] = (2, 1, 0), dpi: int = 110) -> str:
    """Write one PNG with the contours of several surfaces over the same CT slices.

    ``surfaces``: name -> Surface (e.g. one per method). The slices are the CT index planes
    nearest ``center`` (physical LPS; default: the centroid of the first surface's
    vertices). ``axes``: which index planes (0 = i, 1 = j, 2 = k). Returns ``path``.
    """
    if not surfaces:
        raise InputError("render_cross_sections: no surface given.")
    named = {str(name): _as_lps(s) for name, s in surfaces.items()}
    colors = list(colors or CONTOUR_COLORS)
    while len(colors) < len(named):
        colors += colors
    array = _ct_array(ct)
    if center is None:
        center = next(iter(named.values())).vertices.mean(axis=0)
    centre_idx = _centre_index(ct, center)
    fig = _new_figure(3.6 * len(axes), 4.0, dpi)
    grid = fig.add_gridspec(1, len(axes), left=0.02, right=0.98, top=0.86, bottom=0.03,
                            wspace=0.06)
    for col, axis in enumerate(axes):
        ax = fig.add_subplot(grid[0, col])
        _draw_slice(ax, ct, array, int(axis), centre_idx, named, colors, window, margin_mm,
                    show_legend=(col == 0))
    if title:
        fig.suptitle(title, fontsize=11)
    _save(fig, path)
    return os.fspath(path)


class RenderUnavailable(DependencyError):
    """Pictures cannot be rendered on this machine (the run goes on without one)."""
