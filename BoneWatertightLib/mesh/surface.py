"""Triangle-mesh container, measures and conversions (numpy <-> vtkPolyData).

Vertices are (n, 3) float64 x-y-z points in millimetres (physical LPS unless the
``coordinate_system`` says RAS, or grid millimetres inside the pipeline); faces are (m, 3) int64
vertex indices, counter-clockwise seen from outside.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .operators import face_normals, vertex_normals


@dataclass
class Surface:
    """A triangle mesh in physical coordinates (mm).

    ``vertices`` (n, 3) float64, ``faces`` (m, 3) int64 with counter-clockwise order seen
    from outside. ``coordinate_system`` is "LPS" (ITK, the library's default) or "RAS".
    ``point_data`` holds per-vertex arrays (e.g. "DistanceToConstraints"), ``cell_data``
    per-face arrays (e.g. "Cap": 1 on the faces of a cap where the bone leaves the image).
    """

    vertices: np.ndarray
    faces: np.ndarray
    coordinate_system: str = "LPS"
    point_data: dict = field(default_factory=dict)
    cell_data: dict = field(default_factory=dict)

    def __post_init__(self):
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64).reshape(-1, 3)

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    def copy(self) -> "Surface":
        return Surface(self.vertices.copy(), self.faces.copy(), self.coordinate_system,
                       {k: np.array(v, copy=True) for k, v in self.point_data.items()},
                       {k: np.array(v, copy=True) for k, v in self.cell_data.items()})

    def vertex_normals(self) -> np.ndarray:
        return vertex_normals(self.vertices, self.faces)

    def to_ras(self) -> "Surface":
        """The same surface in RAS (x and y negated); a no-op if already RAS."""
        if self.coordinate_system == "RAS":
            return self.copy()
        out = self.copy()
        out.vertices[:, :2] *= -1.0
        out.coordinate_system = "RAS"
        return out

    def to_lps(self) -> "Surface":
        if self.coordinate_system == "LPS":
            return self.copy()
        out = self.copy()
        out.vertices[:, :2] *= -1.0
        out.coordinate_system = "LPS"
        return out


def enclosed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume (positive for a closed, outward-oriented surface)."""
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() / 6.0)


def surface_area(vertices: np.ndarray, faces: np.ndarray) -> float:
    return float(0.5 * np.linalg.norm(face_normals(vertices, faces, normalize=False), axis=1).sum())


def mean_edge_length(vertices: np.ndarray, faces: np.ndarray) -> float:
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return float(np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1).mean())


def to_polydata(surface: Surface, normals: bool = True):
    """vtkPolyData with points, triangles, point normals and the point_data arrays."""
    from .. import _vtk as vtk
    from .._vtk import numpy_support as ns

    pts = vtk.vtkPoints()
    pts.SetData(ns.numpy_to_vtk(surface.vertices.astype(np.float64), deep=True))
    n = len(surface.faces)
    cells = vtk.vtkCellArray()
    offsets = np.arange(0, 3 * n + 1, 3, dtype=np.int64)
    cells.SetData(ns.numpy_to_vtkIdTypeArray(offsets, deep=True),
                  ns.numpy_to_vtkIdTypeArray(surface.faces.ravel().astype(np.int64), deep=True))
    poly = vtk.vtkPolyData()
    poly.SetPoints(pts)
    poly.SetPolys(cells)
    if normals and len(surface.faces):
        arr = ns.numpy_to_vtk(surface.vertex_normals(), deep=True)
        arr.SetName("Normals")
        poly.GetPointData().SetNormals(arr)
    for name, values in surface.point_data.items():
        arr = ns.numpy_to_vtk(np.ascontiguousarray(values, dtype=np.float64), deep=True)
        arr.SetName(name)
        poly.GetPointData().AddArray(arr)
    for name, values in surface.cell_data.items():
        values = np.ascontiguousarray(values)
        if values.dtype.kind in "bu" or values.dtype.kind == "i":
            arr = ns.numpy_to_vtk(values.astype(np.uint8 if values.max(initial=0) < 256 else np.int32),
                                  deep=True)
        else:
            arr = ns.numpy_to_vtk(values.astype(np.float64), deep=True)
        arr.SetName(name)
        poly.GetCellData().AddArray(arr)
    return poly


def inside_mask(surface: Surface, shape: tuple, spacing: float, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    """The voxel centres inside a closed surface.

    Rays along x through the voxel centres count the faces they cross (:func:`_ray_parity`);
    where a ray meets the surface an odd number of times (a ray through a vertex of a fold,
    or a surface that is not closed) VTK's polygon stencil decides instead.

    Parameters
    ----------
    surface : Surface
        Closed; its vertices in the grid's frame (x-y-z mm).
    shape : tuple of 3 int
        (z, y, x) size of the grid.
    spacing : float
        Isotropic step of the grid (mm).
    origin : sequence of 3 float
        x-y-z position of voxel (0, 0, 0).

    Returns
    -------
    (z, y, x) bool array of ``shape``
    """
    shape = tuple(int(v) for v in shape)
    inside = _ray_parity(surface.vertices, surface.faces, shape, spacing, origin)
    if inside is None:
        inside = _stencil_mask(surface, shape, spacing, origin)
    return inside


def _ray_parity(vertices, faces, shape, spacing, origin):
    """Voxel centres inside a closed surface by the parity of the faces a ray along x crosses
    before them; None when some ray crosses an odd number of faces.

    A ray through an edge or a vertex counts each crossing once: seen along x, a point on the
    border of a face's shadow belongs to it only on its top-left edges (the rasteriser's rule),
    and two faces on either side of a shared edge see it in opposite directions. (z, y, x) bool
    array of ``shape``, or None.
    """
    nz, ny, nx = shape
    q = (np.asarray(vertices, np.float64) - np.asarray(origin, np.float64)) / float(spacing)
    f = np.asarray(faces, np.int64)
    a, b, c = q[f[:, 0]], q[f[:, 1]], q[f[:, 2]]
    area = (b[:, 1] - a[:, 1]) * (c[:, 2] - a[:, 2]) - (b[:, 2] - a[:, 2]) * (c[:, 1] - a[:, 1])
    # Faces parallel to the rays have no shadow: their neighbours' edges hold it.
    keep = area != 0.0
    a, b, c, area = a[keep], b[keep], c[keep], area[keep]
    flip = area < 0  # each shadow counter-clockwise in (y, z)
    b, c = np.where(flip[:, None], c, b), np.where(flip[:, None], b, c)
    area = np.abs(area)
    tri_y = np.stack([a[:, 1], b[:, 1], c[:, 1]], axis=1)
    tri_z = np.stack([a[:, 2], b[:, 2], c[:, 2]], axis=1)
    j0 = np.maximum(np.ceil(tri_y.min(axis=1)), 0).astype(np.int64)
    j1 = np.minimum(np.floor(tri_y.max(axis=1)), ny - 1).astype(np.int64)
    k0 = np.maximum(np.ceil(tri_z.min(axis=1)), 0).astype(np.int64)
    k1 = np.minimum(np.floor(tri_z.max(axis=1)), nz - 1).astype(np.int64)
    sy = np.maximum(j1 - j0 + 1, 0)
    count = sy * np.maximum(k1 - k0 + 1, 0)
    t = np.repeat(np.arange(len(area)), count)
    local = np.arange(len(t)) - np.repeat(np.cumsum(count) - count, count)
    jy = j0[t] + local % sy[t]
    kz = k0[t] + local // sy[t]
    py, pz = jy.astype(np.float64), kz.astype(np.float64)
    corners = (a[t], b[t], c[t])
    covered = np.ones(len(t), bool)
    weight = []
    for e in range(3):
        u, v = corners[e], corners[(e + 1) % 3]
        dy, dz = v[:, 1] - u[:, 1], v[:, 2] - u[:, 2]
        side = dy * (pz - u[:, 2]) - dz * (py - u[:, 1])
        top_left = (dz < 0) | ((dz == 0) & (dy > 0))
        covered &= (side > 0) | ((side == 0) & top_left)
        weight.append(side)  # the barycentric weight of the corner opposite this edge
    t, jy, kz = t[covered], jy[covered], kz[covered]
    w = [x[covered] / area[t] for x in weight]
    x = w[1] * a[t, 0] + w[2] * b[t, 0] + w[0] * c[t, 0]
    ray = kz * ny + jy
    if np.any(np.bincount(ray, minlength=nz * ny) % 2):
        return None
    # A crossing at x toggles every voxel centre beyond it (none beyond the grid): the running
    # exclusive-or along each ray.
    first = np.maximum(np.floor(x).astype(np.int64) + 1, 0)
    beyond = first >= nx
    cell, times = np.unique(ray[~beyond] * nx + first[~beyond], return_counts=True)
    toggles = np.zeros(nz * ny * nx, np.uint8)
    toggles[cell] = times & 1
    inside = np.bitwise_xor.accumulate(toggles.reshape(nz * ny, nx), axis=1)
    return inside.view(bool).reshape(nz, ny, nx)


def _stencil_mask(surface: Surface, shape: tuple, spacing: float, origin) -> np.ndarray:
    """:func:`inside_mask` by VTK's polygon stencil (slices the surface at every z)."""
    from .. import _vtk as vtk
    from .._vtk import numpy_support as ns

    image = vtk.vtkImageData()
    image.SetDimensions(int(shape[2]), int(shape[1]), int(shape[0]))
    image.SetOrigin(*[float(v) for v in origin])
    image.SetSpacing(spacing, spacing, spacing)
    image.AllocateScalars(vtk.VTK_UNSIGNED_CHAR, 1)
    image.GetPointData().GetScalars().Fill(1)
    stencil = vtk.vtkPolyDataToImageStencil()
    stencil.SetInputData(to_polydata(surface, normals=False))
    stencil.SetOutputOrigin(*[float(v) for v in origin])
    stencil.SetOutputSpacing(spacing, spacing, spacing)
    stencil.SetOutputWholeExtent(image.GetExtent())
    stencil.Update()
    cut = vtk.vtkImageStencil()
    cut.SetInputData(image)
    cut.SetStencilConnection(stencil.GetOutputPort())
    cut.ReverseStencilOff()
    cut.SetBackgroundValue(0)
    cut.Update()
    return ns.vtk_to_numpy(cut.GetOutput().GetPointData().GetScalars()).reshape(tuple(shape)) > 0


def from_polydata(poly, coordinate_system: str = "LPS") -> Surface:
    """Surface from a vtkPolyData of triangles (other polygons are triangulated)."""
    from .. import _vtk as vtk
    from .._vtk import numpy_support as ns

    if poly.GetNumberOfPolys() and poly.GetPolys().GetMaxCellSize() > 3:
        tri = vtk.vtkTriangleFilter()
        tri.SetInputData(poly)
        tri.PassVertsOff()
        tri.PassLinesOff()
        tri.Update()
        poly = tri.GetOutput()
    pts = ns.vtk_to_numpy(poly.GetPoints().GetData()).astype(np.float64) if poly.GetPoints() else np.zeros((0, 3))
    polys = poly.GetPolys()
    if polys.GetNumberOfCells():
        conn = ns.vtk_to_numpy(polys.GetConnectivityArray()).astype(np.int64)
        faces = conn.reshape(-1, 3)
    else:
        faces = np.zeros((0, 3), dtype=np.int64)
    pd = poly.GetPointData()
    point_data = {}
    for i in range(pd.GetNumberOfArrays()):
        arr = pd.GetArray(i)
        if arr is None or arr.GetName() in (None, "Normals"):
            continue
        if arr.GetNumberOfComponents() == 1:
            point_data[arr.GetName()] = ns.vtk_to_numpy(arr).astype(np.float64)
    cell_data = {}
    cd = poly.GetCellData()
    if len(faces) == poly.GetNumberOfCells():
        for i in range(cd.GetNumberOfArrays()):
            arr = cd.GetArray(i)
            if arr is not None and arr.GetName() and arr.GetNumberOfComponents() == 1:
                cell_data[arr.GetName()] = ns.vtk_to_numpy(arr).copy()
    return Surface(pts, faces, coordinate_system, point_data, cell_data)
