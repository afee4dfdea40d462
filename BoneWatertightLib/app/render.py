"""PNG pictures of a reconstructed surface, rendered with VTK offscreen.

One picture holds a title line, shaded and lit views of the surface coloured by a per-vertex
value (by default the distance to the constraint points, viridis colour map with a scale bar),
and, with the CT, three CT sections (axial, coronal, sagittal index planes through the surface
centroid) in a bone window with the surface's cross-section drawn over them.

Rendering needs an OpenGL context without a screen: on Linux without a display VTK's EGL window
(Mesa's software driver works), else OSMesa, else the platform's window offscreen. When none
works, :func:`offscreen_status` says why and :func:`render_surface` raises
:class:`RenderUnavailable`, which the run service turns into "no picture" while the run still
succeeds. ``BONEWATERTIGHT_OFFSCREEN=0`` switches rendering off.

Geometry conventions: surfaces are drawn in physical LPS millimetres (a RAS surface is
converted first). The CT sections are the CT's own index planes nearest to the surface
centroid; the surface's cross-section is computed by intersecting the triangles with that plane,
which is exact in index space because the index <-> physical map is affine. Sections are shown
in radiological orientation: axial and coronal with the patient's left on the right of the
picture, axial with anterior up, coronal and sagittal with superior up, sagittal with anterior
on the left. Mesh views are never mirrored (anterior view: the patient's left on the right).
"""

from __future__ import annotations

import os
import sys
from typing import Optional, Sequence, Union

import numpy as np

from ..errors import DependencyError, InputError
from ..mesh.surface import Surface, to_polydata

# Bone window (HU) for the CT slices: soft tissue grey, cortical bone white.
DEFAULT_WINDOW = (-350.0, 1250.0)
BONE_RGB = (0.93, 0.87, 0.74)
CONTOUR_COLORS = ((1.0, 0.23, 0.19), (0.0, 0.78, 1.0), (1.0, 0.84, 0.04), (0.2, 0.78, 0.35),
                  (0.75, 0.35, 0.95), (1.0, 0.62, 0.04), (1.0, 1.0, 1.0), (1.0, 0.18, 0.57))
# Size (pixels) of one view / section panel, of the title strip and of the colour-bar column.
PANEL_PX = 420
TITLE_PX = 46
COLORBAR_PX = 120
# Pictures are rendered at this many times their size and averaged down (anti-aliasing that
# works with every OpenGL driver; FXAA renders black with Mesa's EGL).
SUPERSAMPLE = 2
# Viridis (perceptually ordered, colour-blind safe): 9 samples of the published map.
VIRIDIS = ((0.267, 0.005, 0.329), (0.283, 0.141, 0.458), (0.254, 0.265, 0.530),
           (0.207, 0.372, 0.553), (0.164, 0.471, 0.558), (0.128, 0.567, 0.551),
           (0.135, 0.659, 0.518), (0.267, 0.749, 0.441), (0.478, 0.821, 0.318),
           (0.741, 0.873, 0.150), (0.993, 0.906, 0.144))

# Camera of each mesh view: (direction the camera looks along, screen-up), in LPS.
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
_OFFSCREEN_ENV = "BONEWATERTIGHT_OFFSCREEN"


class RenderUnavailable(DependencyError):
    """Pictures cannot be rendered on this machine (the run goes on without one)."""


# ----------------------------------------------------------------------------------------
# offscreen render windows

_STATUS = None


def _new_window(width: int, height: int):
    """An offscreen vtkRenderWindow with a working OpenGL context, or raise RenderUnavailable."""
    if os.environ.get(_OFFSCREEN_ENV, "").strip().lower() in ("0", "off", "no", "false"):
        raise RenderUnavailable(f"offscreen rendering is switched off ({_OFFSCREEN_ENV}=0)")
    try:
        import vtkmodules.vtkRenderingOpenGL2 as gl
        from vtkmodules.vtkRenderingCore import vtkRenderWindow
        import vtkmodules.vtkRenderingFreeType  # noqa: F401  (text actors)
        import vtkmodules.vtkInteractionStyle  # noqa: F401
    except ImportError as exc:
        raise RenderUnavailable(f"VTK has no OpenGL rendering here ({exc})") from None
    headless = sys.platform.startswith("linux") and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    factories = []
    if headless:
        # No X server: VTK's default (X) window would fail noisily; EGL works with Mesa.
        factories += [getattr(gl, "vtkEGLRenderWindow", None), getattr(gl, "vtkOSOpenGLRenderWindow", None)]
    factories.append(vtkRenderWindow)
    reasons = []
    for factory in factories:
        if factory is None:
            continue
        window = factory()
        window.SetOffScreenRendering(1)
        window.SetSize(int(width), int(height))
        try:
            ok = bool(window.SupportsOpenGL())
        except Exception as exc:  # pragma: no cover - depends on the machine's drivers
            ok, reasons = False, reasons + [f"{type(window).__name__}: {exc}"]
        if ok:
            return window
        reasons.append(f"{type(window).__name__}: no OpenGL context")
        window.Finalize()
    raise RenderUnavailable("no offscreen OpenGL context (" + "; ".join(reasons)
                            + "); on Linux install libegl1 libegl-mesa0 libgl1-mesa-dri")


def offscreen_status() -> tuple:
    """(available, reason): whether pictures can be rendered here (checked once)."""
    global _STATUS
    if os.environ.get(_OFFSCREEN_ENV, "").strip().lower() in ("0", "off", "no", "false"):
        return False, f"offscreen rendering is switched off ({_OFFSCREEN_ENV}=0)"
    if _STATUS is None:
        try:
            window = _new_window(8, 8)
            window.Finalize()
            _STATUS = (True, "")
        except RenderUnavailable as exc:
            _STATUS = (False, str(exc))
    return _STATUS


def _write_png(window, path) -> None:
    """Render, average SUPERSAMPLE x SUPERSAMPLE pixel blocks, write the PNG."""
    import vtk
    from vtk.util import numpy_support as ns

    window.Render()
    grab = vtk.vtkWindowToImageFilter()
    grab.SetInput(window)
    grab.SetInputBufferTypeToRGB()
    grab.ReadFrontBufferOff()
    grab.Update()
    big = grab.GetOutput()
    w, h, _ = big.GetDimensions()
    pixels = ns.vtk_to_numpy(big.GetPointData().GetScalars()).reshape(h, w, 3).astype(np.float32)
    f = SUPERSAMPLE
    small = pixels[: h - h % f, : w - w % f].reshape(h // f, f, w // f, f, 3).mean(axis=(1, 3))
    out = vtk.vtkImageData()
    out.SetDimensions(w // f, h // f, 1)
    out.GetPointData().SetScalars(ns.numpy_to_vtk(
        np.ascontiguousarray(np.rint(small).astype(np.uint8).reshape(-1, 3)), deep=True,
        array_type=vtk.VTK_UNSIGNED_CHAR))
    writer = vtk.vtkPNGWriter()
    writer.SetInputData(out)
    writer.SetFileName(os.fspath(path))
    writer.Write()
    if writer.GetErrorCode():
        raise OSError(f"VTK could not write {path} (error code {writer.GetErrorCode()}).")


# ----------------------------------------------------------------------------------------
# building blocks

def _text(renderer, text, x, y, size=14, color=(0.1, 0.1, 0.1), bold=False, align="left",
          valign="bottom"):
    """A text actor at normalized viewport position (x, y)."""
    import vtk

    actor = vtk.vtkTextActor()
    actor.SetInput(text)
    prop = actor.GetTextProperty()
    prop.SetFontSize(int(size * SUPERSAMPLE))
    prop.SetColor(*color)
    prop.SetBold(bool(bold))
    prop.SetJustification({"left": 0, "center": 1, "right": 2}[align])
    prop.SetVerticalJustification({"bottom": 0, "center": 1, "top": 2}[valign])
    actor.GetPositionCoordinate().SetCoordinateSystemToNormalizedViewport()
    actor.SetPosition(x, y)
    renderer.AddViewProp(actor)
    return actor


def _lookup_table(vmin: float, vmax: float):
    import vtk

    lut = vtk.vtkLookupTable()
    lut.SetNumberOfTableValues(256)
    lut.SetRange(vmin, vmax)
    xs = np.linspace(0.0, 1.0, len(VIRIDIS))
    rgb = np.array(VIRIDIS)
    for i, t in enumerate(np.linspace(0.0, 1.0, 256)):
        lut.SetTableValue(i, *[float(np.interp(t, xs, rgb[:, c])) for c in range(3)], 1.0)
    lut.SetBelowRangeColor(*VIRIDIS[0], 1.0)
    lut.SetAboveRangeColor(*VIRIDIS[-1], 1.0)
    lut.UseBelowRangeColorOn()
    lut.UseAboveRangeColorOn()
    lut.Build()
    return lut


def _scale_bar(renderer, span_mm: float, px_per_mm: float, panel_px: int):
    """A black scale bar (nice length) with its label at the lower left of a view."""
    import vtk

    nice = [1, 2, 5, 10, 20, 25, 50, 100, 200, 500]
    length = max([n for n in nice if n <= span_mm / 3.0] or [nice[0]])
    x0, y0 = 0.05, 0.06
    x1 = x0 + length * px_per_mm / panel_px
    points = vtk.vtkPoints()
    points.InsertNextPoint(x0, y0, 0.0)
    points.InsertNextPoint(x1, y0, 0.0)
    lines = vtk.vtkCellArray()
    lines.InsertNextCell(2)
    lines.InsertCellPoint(0)
    lines.InsertCellPoint(1)
    poly = vtk.vtkPolyData()
    poly.SetPoints(points)
    poly.SetLines(lines)
    coordinate = vtk.vtkCoordinate()
    coordinate.SetCoordinateSystemToNormalizedViewport()
    mapper = vtk.vtkPolyDataMapper2D()
    mapper.SetInputData(poly)
    mapper.SetTransformCoordinate(coordinate)
    actor = vtk.vtkActor2D()
    actor.SetMapper(mapper)
    actor.GetProperty().SetColor(0.05, 0.05, 0.05)
    actor.GetProperty().SetLineWidth(3.0 * SUPERSAMPLE)
    renderer.AddViewProp(actor)
    _text(renderer, f"{length:g} mm", x1 + 0.015, y0, size=12, valign="center")


def _surface_view(renderer, poly, surface: Surface, view, lut, panel_px: int):
    """Shaded, lit, parallel-projection view of the surface from one direction."""
    import vtk

    look, up, right = _camera(view)
    mapper = vtk.vtkPolyDataMapper()
    mapper.SetInputData(poly)
    if lut is not None:
        mapper.SetLookupTable(lut)
        mapper.SetScalarModeToUsePointFieldData()
        mapper.SelectColorArray("RenderScalars")
        mapper.SetUseLookupTableScalarRange(True)
        mapper.ScalarVisibilityOn()
    else:
        mapper.ScalarVisibilityOff()
    actor = vtk.vtkActor()
    actor.SetMapper(mapper)
    prop = actor.GetProperty()
    prop.SetInterpolationToPhong()
    prop.SetColor(*BONE_RGB)
    prop.SetAmbient(0.12)
    prop.SetDiffuse(0.82)
    prop.SetSpecular(0.18)
    prop.SetSpecularPower(25.0)
    renderer.AddActor(actor)
    renderer.SetBackground(1.0, 1.0, 1.0)
    renderer.SetBackground2(0.86, 0.88, 0.92)
    renderer.GradientBackgroundOn()

    centre = 0.5 * (surface.vertices.min(axis=0) + surface.vertices.max(axis=0))
    proj_r, proj_u = surface.vertices @ right, surface.vertices @ up
    width, height = np.ptp(proj_r), np.ptp(proj_u)
    mid = centre + right * (0.5 * (proj_r.max() + proj_r.min()) - centre @ right) \
        + up * (0.5 * (proj_u.max() + proj_u.min()) - centre @ up)
    radius = float(np.linalg.norm(surface.vertices - mid, axis=1).max())
    camera = renderer.GetActiveCamera()
    camera.ParallelProjectionOn()
    camera.SetFocalPoint(*(mid + up * 0.06 * max(width, height)))
    camera.SetPosition(*(mid + up * 0.06 * max(width, height) - look * (3.0 * radius + 10.0)))
    camera.SetViewUp(*up)
    half = 0.5 * max(height, width) * 1.22
    camera.SetParallelScale(half)
    renderer.ResetCameraClippingRange()
    # Light kit: key light from the viewer's upper left, fill and back lights, so creases
    # read in relief as in Slicer's 3D view.
    kit = vtk.vtkLightKit()
    kit.SetKeyLightIntensity(0.85)
    kit.AddLightsToRenderer(renderer)
    name = view if isinstance(view, str) else "view"
    _text(renderer, f"{name}   (right: {_direction_letter(right)}, up: {_direction_letter(up)})",
          0.5, 0.965, size=15, align="center", valign="top", bold=True)
    px_per_mm = panel_px / (2.0 * half)
    _scale_bar(renderer, max(width, height), px_per_mm, panel_px)


def _section_view(renderer, ct, array_zyx, axis, centre_idx, surfaces, colors, window,
                  margin_mm, show_legend=False):
    """One CT index plane in a bone window with the surfaces' cross-sections over it."""
    import vtk
    from vtk.util import numpy_support as ns

    frame = _SliceFrame(ct, axis, centre_idx[axis])
    plane = np.asarray(frame.image(array_zyx), dtype=np.float64)
    lo_w, hi_w = window
    grey = (np.clip((plane - lo_w) / (hi_w - lo_w), 0.0, 1.0) * 255.0).astype(np.uint8)
    rgb = np.repeat(grey[..., None], 3, axis=2)
    image = vtk.vtkImageData()
    image.SetDimensions(rgb.shape[1], rgb.shape[0], 1)
    image.SetSpacing(frame.spacing[frame.h], frame.spacing[frame.v], 1.0)
    image.SetOrigin(0.0, 0.0, 0.0)
    scalars = ns.numpy_to_vtk(np.ascontiguousarray(rgb).reshape(-1, 3), deep=True,
                              array_type=vtk.VTK_UNSIGNED_CHAR)
    image.GetPointData().SetScalars(scalars)
    slice_actor = vtk.vtkImageActor()
    slice_actor.GetMapper().SetInputData(image)
    slice_actor.InterpolateOff()
    renderer.AddActor(slice_actor)
    renderer.SetBackground(0.0, 0.0, 0.0)

    boxes = []
    for (name, surface), color in zip(surfaces.items(), colors):
        idx = physical_to_index(ct, surface.vertices)
        seg = plane_section(idx, surface.faces, axis, float(frame.index_value))
        disp_all = frame.display(idx)
        boxes.append((disp_all.min(axis=0), disp_all.max(axis=0)))
        if not len(seg):
            continue
        lines2d = frame.display(seg.reshape(-1, 3))
        points = vtk.vtkPoints()
        points.SetData(ns.numpy_to_vtk(np.column_stack([lines2d, np.full(len(lines2d), 0.5)]),
                                       deep=True))
        ids = np.column_stack([np.full(len(seg), 2), np.arange(0, 2 * len(seg), 2),
                               np.arange(1, 2 * len(seg), 2)]).ravel()
        cells = vtk.vtkCellArray()
        cells.ImportLegacyFormat(ns.numpy_to_vtkIdTypeArray(ids.astype(np.int64), deep=True))
        poly = vtk.vtkPolyData()
        poly.SetPoints(points)
        poly.SetLines(cells)
        mapper = vtk.vtkPolyDataMapper()
        mapper.SetInputData(poly)
        actor = vtk.vtkActor()
        actor.SetMapper(mapper)
        actor.GetProperty().SetColor(*color)
        actor.GetProperty().SetLineWidth(2.0 * SUPERSAMPLE)
        actor.GetProperty().LightingOff()
        renderer.AddActor(actor)
    ext = frame.extent()
    if boxes:
        lo = np.min([b[0] for b in boxes], axis=0) - margin_mm
        hi = np.max([b[1] for b in boxes], axis=0) + margin_mm
        lo = np.maximum(lo, [ext[0], ext[2]])
        hi = np.minimum(hi, [ext[1], ext[3]])
    else:
        lo, hi = np.array([ext[0], ext[2]]), np.array([ext[1], ext[3]])
    mid = 0.5 * (lo + hi)
    camera = renderer.GetActiveCamera()
    camera.ParallelProjectionOn()
    camera.SetFocalPoint(mid[0], mid[1], 0.0)
    camera.SetPosition(mid[0], mid[1], 100.0)
    camera.SetViewUp(0.0, 1.0, 0.0)
    camera.SetParallelScale(0.5 * max(hi[0] - lo[0], hi[1] - lo[1]) * 1.12)
    renderer.ResetCameraClippingRange()
    letters = dict(size=17, color=(1.0, 0.92, 0.1), bold=True)
    _text(renderer, frame.h_letters[0], 0.015, 0.5, valign="center", **letters)
    _text(renderer, frame.h_letters[1], 0.985, 0.5, align="right", valign="center", **letters)
    _text(renderer, frame.v_letters[0], 0.5, 0.015, align="center", **letters)
    _text(renderer, frame.v_letters[1], 0.5, 0.94, align="center", valign="top", **letters)
    _text(renderer, f"{frame.name}, {'ijk'[axis]} = {frame.index_value}", 0.03, 0.975, size=14,
          color=(1.0, 1.0, 1.0), bold=True, valign="top")
    if show_legend:
        for k, ((name, _), color) in enumerate(zip(surfaces.items(), colors)):
            _text(renderer, name, 0.97, 0.05 + 0.05 * k, size=13, color=color, bold=True,
                  align="right")


def _renderer(window, x0, y0, x1, y1):
    import vtk

    renderer = vtk.vtkRenderer()
    renderer.SetViewport(x0, y0, x1, y1)
    window.AddRenderer(renderer)
    return renderer


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


def _as_lps(surface: Surface) -> Surface:
    if not isinstance(surface, Surface):
        raise InputError("render: expected a BoneWatertightLib.mesh.Surface.")
    if surface.n_faces == 0:
        raise InputError("render: the surface has no triangles.")
    return surface.to_lps() if surface.coordinate_system == "RAS" else surface


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



def _direction_letter(vector: np.ndarray) -> str:
    axis = int(np.argmax(np.abs(vector)))
    return _AXIS_LETTERS[axis][1 if vector[axis] > 0 else 0]



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
                   panel_px: int = PANEL_PX) -> str:
    """Write one PNG: a title line, shaded views of ``surface`` and, with ``ct``, three CT
    sections with the surface's cross-section.

    Parameters
    ----------
    surface : Surface
        LPS or RAS (converted to LPS for drawing).
    path : str or os.PathLike
        The PNG to write (its folder must exist).
    ct : SimpleITK.Image, optional
        The CT (LPS). The three index planes nearest the surface centroid are shown.
    title : str, optional
        First words of the title line (e.g. the segment name).
    scalars : "auto", str, (n_vertices,) array or None
        Per-vertex values to colour the views by, with a colour bar: ``"auto"`` uses
        "Confidence" (0-1, the CT's support under each vertex) when the surface has it, else
        "DistanceToConstraints" (mm); a string names a point-data array, ``None`` draws
        plain bone colour.
    scalar_label : str, optional
        Colour-bar title.
    scalar_range : (min, max), optional
        Colour range; default 0 (or the minimum) to the 99th percentile.
    views : sequence of view names or (look, up) pairs
    window : (low, high)
        HU window of the CT sections.
    margin_mm : float
        Margin around the surface in the sections.
    panel_px : int
        Size of one view in pixels.

    Returns
    -------
    str
        ``path``.

    Raises
    ------
    RenderUnavailable
        No offscreen OpenGL context on this machine.
    """
    import vtk
    from vtk.util import numpy_support as ns

    surface = _as_lps(surface)
    if isinstance(scalars, str) and scalars == "auto" and "Confidence" in surface.point_data:
        # How much CT evidence stands under each vertex (stages.evidence), on its own 0-1 scale.
        scalars = "Confidence"
        scalar_label = scalar_label or "CT support"
        scalar_range = scalar_range or (0.0, 1.0)
    # The colour bar's last line: the scale's unit (confidence has none: 0-1).
    unit = "(confidence 0-1)" if isinstance(scalars, str) and scalars == "Confidence" else "(mm)"
    values = _resolve_scalars(surface, scalars)
    lut = None
    if values is not None:
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
        values = np.where(np.isfinite(values), values, vmax)
        lut = _lookup_table(vmin, vmax)
    columns = max(len(views), 3 if ct is not None else 1)
    rows = 2 if ct is not None else 1
    extra = COLORBAR_PX if lut is not None else 0
    width = columns * panel_px + extra
    height = rows * panel_px + TITLE_PX
    render_window = _new_window(width * SUPERSAMPLE, height * SUPERSAMPLE)
    try:
        poly = to_polydata(Surface(surface.vertices, surface.faces), normals=True)
        if values is not None:
            arr = ns.numpy_to_vtk(np.ascontiguousarray(values, dtype=np.float64), deep=True)
            arr.SetName("RenderScalars")
            poly.GetPointData().AddArray(arr)
        top = 1.0 - TITLE_PX / height
        row_h = (top - 0.0) / rows
        col_w = panel_px / width
        for col, view in enumerate(views):
            ren = _renderer(render_window, col * col_w, top - row_h, (col + 1) * col_w, top)
            _surface_view(ren, poly, surface, view, lut, panel_px * SUPERSAMPLE)
        if lut is not None:
            ren = _renderer(render_window, columns * col_w, top - row_h, 1.0, top)
            ren.SetBackground(1.0, 1.0, 1.0)
            bar = vtk.vtkScalarBarActor()
            bar.SetLookupTable(lut)
            label = scalar_label or (scalars if isinstance(scalars, str) and scalars != "auto"
                                     else ("distance to constraints" if isinstance(scalars, str)
                                           else "value"))
            bar.SetNumberOfLabels(6)
            bar.SetLabelFormat("%.2f")
            bar.SetBarRatio(0.3)
            bar.UnconstrainedFontSizeOn()
            for prop in (bar.GetLabelTextProperty(),):
                prop.SetColor(0.1, 0.1, 0.1)
                prop.SetFontSize(13 * SUPERSAMPLE)
                prop.ItalicOff()
                prop.ShadowOff()
            bar.GetPositionCoordinate().SetCoordinateSystemToNormalizedViewport()
            bar.SetPosition(0.1, 0.06)
            bar.SetWidth(0.85)
            bar.SetHeight(0.68)
            ren.AddViewProp(bar)
            for k, line in enumerate(label.split(" ", 1) + [unit]):
                _text(ren, line, 0.5, 0.93 - 0.045 * k, size=13, bold=True, align="center",
                      valign="top")
        if ct is not None:
            array = _ct_array(ct)
            centre_idx = _centre_index(ct, surface.vertices.mean(axis=0))
            # k plane first: for the usual axial CT that is the axial slice.
            for col, axis in enumerate((2, 1, 0)):
                ren = _renderer(render_window, col * col_w, 0.0, (col + 1) * col_w, row_h)
                _section_view(ren, ct, array, axis, centre_idx, {"surface": surface},
                              [CONTOUR_COLORS[0]], window, margin_mm)
            if extra:
                ren = _renderer(render_window, columns * col_w, 0.0, 1.0, row_h)
                ren.SetBackground(0.0, 0.0, 0.0)
                _text(ren, "surface", 0.5, 0.52, size=13, color=CONTOUR_COLORS[0], bold=True,
                      align="center")
                _text(ren, "over CT", 0.5, 0.46, size=13, color=(1.0, 1.0, 1.0), align="center")
                _text(ren, f"W {window[0]:g}..{window[1]:g}", 0.5, 0.40, size=11,
                      color=(0.8, 0.8, 0.8), align="center")
        ren = _renderer(render_window, 0.0, top, 1.0, 1.0)
        ren.SetBackground(1.0, 1.0, 1.0)
        heading = title or "surface"
        _text(ren, f"{heading}: {surface.n_vertices} vertices, {surface.n_faces} triangles "
                   f"({surface.coordinate_system} mm)", 0.01, 0.5, size=20, bold=True,
              valign="center")
        _write_png(render_window, path)
    finally:
        render_window.Finalize()
    return os.fspath(path)


def render_cross_sections(ct, surfaces: dict, path, center=None, title: Optional[str] = None,
                          colors: Optional[Sequence] = None,
                          window: Sequence[float] = DEFAULT_WINDOW, margin_mm: float = 15.0,
                          axes: Sequence[int] = (2, 1, 0), panel_px: int = PANEL_PX) -> str:
    """Write one PNG with the contours of several surfaces over the same CT sections.

    Parameters
    ----------
    ct : SimpleITK.Image
    surfaces : dict
        name -> Surface (e.g. one per method); the first section has a legend.
    path : str or os.PathLike
    center : (3,) array, optional
        Physical LPS point the sections pass through (default: the first surface's centroid).
    title : str, optional
    colors : sequence of RGB triples (0-1), optional
    window : (low, high)
    margin_mm : float
    axes : sequence of int
        Index planes to show (0 = i, 1 = j, 2 = k).
    panel_px : int

    Returns
    -------
    str
        ``path``.
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
    title_px = TITLE_PX if title else 0
    width, height = len(axes) * panel_px, panel_px + title_px
    render_window = _new_window(width * SUPERSAMPLE, height * SUPERSAMPLE)
    try:
        top = 1.0 - title_px / height
        for col, axis in enumerate(axes):
            ren = _renderer(render_window, col / len(axes), 0.0, (col + 1) / len(axes), top)
            _section_view(ren, ct, array, int(axis), centre_idx, named, colors, window,
                          margin_mm, show_legend=(col == 0))
        if title:
            ren = _renderer(render_window, 0.0, top, 1.0, 1.0)
            ren.SetBackground(1.0, 1.0, 1.0)
            _text(ren, title, 0.01, 0.5, size=18, bold=True, valign="center")
        _write_png(render_window, path)
    finally:
        render_window.Finalize()
    return os.fspath(path)
