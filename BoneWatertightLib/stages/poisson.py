"""Stage 5: the initial watertight surface M0 (paper §2.3).

Oriented normals come from the bone mask itself (minus the gradient of the smoothed H0 mask), so
they point outward without any propagation heuristic. open3d's screened Poisson at octree depth
<= 7 gives a smooth closed surface that fills holes of the visible points. Poisson's marching-cubes
output is neither uniform nor guaranteed 2-manifold, so we remesh it through a voxel grid: rasterise
the Poisson surface at spacing h, smooth the occupancy slightly and extract the 0.5 isosurface
(flying edges), keep the largest component and relax it with a windowed-sinc filter. A contour of
a smooth scalar field on a padded grid is closed and manifold; the checker confirms it anyway.
"""

from __future__ import annotations

import contextlib
import os

import numpy as np
from scipy import ndimage

from ..errors import DependencyError, ReconstructionError
from ..mesh.operators import tangential_relax
from ..mesh.surface import Surface, enclosed_volume, from_polydata, to_polydata

# Sigma (voxels) of the smoothed mask whose gradient gives the oriented normals.
NORMAL_MASK_SIGMA_VOXELS = 1.5
# open3d screened Poisson: bounding-box scale of the octree.
POISSON_SCALE = 1.1
# Flying edges on a smoothed mask gives mean edges ~REMESH_EDGE_RATIO x the grid step.
REMESH_EDGE_RATIO = 0.75
# Grid padding (grid steps) around the Poisson surface when remeshing.
REMESH_PAD_STEPS = 4
# Sigma (grid steps) of the occupancy smoothing before contouring.
REMESH_SMOOTH_SIGMA = 0.8
# Windowed-sinc relaxation of the contour.
SINC_ITERATIONS = 15
SINC_PASS_BAND = 0.1
# Fewest triangles of a remeshed M0 (a tetrahedron); fewer: the surface was lost.
MIN_REMESH_FACES = 4


def import_open3d():
    try:
        import open3d as o3d  # noqa: F401  (heavy; imported only when needed)
    except ImportError as exc:  # pragma: no cover - depends on the machine
        raise DependencyError(
            "open3d is not installed; it provides the Poisson reconstruction. Install it with "
            "'pip install open3d' (in 3D Slicer: the module offers to install it).") from exc
    except OSError as exc:  # pragma: no cover - missing system library
        raise DependencyError(
            f"open3d is installed but cannot load ({exc}); on Linux install the system library it "
            "names (e.g. 'apt-get install libusb-1.0-0 libgomp1').") from exc
    return o3d


def mask_normals(mask: np.ndarray, points_grid_mm: np.ndarray, spacing: float) -> np.ndarray:
    """Outward unit normals at points from the gradient of the smoothed mask.

    Parameters
    ----------
    mask : (z, y, x) bool array
        The solid bone on the working grid.
    points_grid_mm : (k, 3) float array
        x-y-z points in grid millimetres.
    spacing : float
        Voxel size in mm.

    Returns
    -------
    (k, 3) float64 array of unit x-y-z normals
    """
    smooth = ndimage.gaussian_filter(mask.astype(np.float32), sigma=NORMAL_MASK_SIGMA_VOXELS)
    shape_xyz = np.array(mask.shape[::-1])
    idx = np.clip(np.rint(points_grid_mm / spacing).astype(int), 0, shape_xyz - 1)
    # Central differences at the points only (three full-volume gradient arrays cost ~GBs).
    g = np.empty((len(idx), 3))
    for axis in range(3):
        lo, hi = idx.copy(), idx.copy()
        lo[:, axis] = np.maximum(idx[:, axis] - 1, 0)
        hi[:, axis] = np.minimum(idx[:, axis] + 1, shape_xyz[axis] - 1)
        g[:, axis] = (smooth[hi[:, 2], hi[:, 1], hi[:, 0]] - smooth[lo[:, 2], lo[:, 1], lo[:, 0]]) \
            / np.maximum(hi[:, axis] - lo[:, axis], 1)
    n = -g
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.maximum(length, 1e-12)


@contextlib.contextmanager
def native_stderr_silenced():
    """File descriptor 2 to /dev/null within the block: PoissonRecon prints its warnings
    ("getValue assumes leaf node", many lines) straight to the C stderr, past open3d's
    verbosity, and they would break the command line's one-line errors."""
    try:
        saved = os.dup(2)
    except OSError:  # no stderr at all
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def poisson_surface(points: np.ndarray, normals: np.ndarray, depth: int) -> Surface:
    """Screened Poisson (open3d) on oriented points; the largest connected component.

    Parameters
    ----------
    points, normals : (k, 3) float arrays
        Oriented points (x-y-z, any frame) and their outward unit normals.
    depth : int
        Octree depth.
    """
    # Points without a usable normal (a flat mask gradient, e.g. at the grid's edge) are no
    # evidence of the orientation: leave them out (open3d rejects them as "bad data").
    good = np.isfinite(points).all(axis=1) & (np.linalg.norm(normals, axis=1) > 0.5)
    points, normals = points[good], normals[good]
    o3d = import_open3d()
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(points)
    pcd.normals = o3d.utility.Vector3dVector(normals)
    # n_threads=-1 is ~10x slower than 1 thread here (thread oversubscription): measured.
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error), \
            native_stderr_silenced():
        mesh, _density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            pcd, depth=depth, scale=POISSON_SCALE, linear_fit=False, n_threads=1)
    tri = np.asarray(mesh.triangles)
    if len(tri) == 0:
        raise ReconstructionError(
            "Poisson reconstruction returned no surface: too few visible points. Lower H0 or use "
            "more views.")
    clusters, counts, _ = mesh.cluster_connected_triangles()
    clusters = np.asarray(clusters)
    biggest = int(np.argmax(np.asarray(counts)))
    faces = tri[clusters == biggest]
    verts = np.asarray(mesh.vertices)
    used, inv = np.unique(faces, return_inverse=True)
    return Surface(verts[used], inv.reshape(-1, 3))


def remesh(surface: Surface, edge_length: float, smooth_iterations: int = SINC_ITERATIONS) -> Surface:
    """Closed, manifold, near-uniform remesh of a (roughly closed) surface through a voxel grid."""
    import vtk
    from vtk.util import numpy_support as ns

    h = edge_length / REMESH_EDGE_RATIO
    lo = surface.vertices.min(axis=0) - REMESH_PAD_STEPS * h
    hi = surface.vertices.max(axis=0) + REMESH_PAD_STEPS * h
    dims = np.ceil((hi - lo) / h).astype(int) + 1
    image = vtk.vtkImageData()
    image.SetOrigin(*lo)
    image.SetSpacing(h, h, h)
    image.SetDimensions(*[int(v) for v in dims])
    image.AllocateScalars(vtk.VTK_UNSIGNED_CHAR, 1)
    image.GetPointData().GetScalars().Fill(1)
    stencil = vtk.vtkPolyDataToImageStencil()
    stencil.SetInputData(to_polydata(surface, normals=False))
    stencil.SetOutputOrigin(*lo)
    stencil.SetOutputSpacing(h, h, h)
    stencil.SetOutputWholeExtent(image.GetExtent())
    stencil.Update()
    to_image = vtk.vtkImageStencil()
    to_image.SetInputData(image)
    to_image.SetStencilConnection(stencil.GetOutputPort())
    to_image.ReverseStencilOff()
    to_image.SetBackgroundValue(0)
    to_image.Update()
    occ = ns.vtk_to_numpy(to_image.GetOutput().GetPointData().GetScalars()).reshape(dims[::-1])
    occ = occ > 0
    lab, n = ndimage.label(occ)
    if n == 0:
        raise ReconstructionError("Remeshing lost the surface (empty rasterisation).")
    if n > 1:
        sizes = np.bincount(lab.ravel())
        sizes[0] = 0
        occ = lab == int(np.argmax(sizes))
    occ = ndimage.binary_fill_holes(occ)
    field = ndimage.gaussian_filter(occ.astype(np.float32), sigma=REMESH_SMOOTH_SIGMA)
    out = contour(field, lo, h, 0.5, smooth_iterations) if field.max() > 0.5 else None
    if out is None or out.n_faces < MIN_REMESH_FACES:
        # A Poisson surface only a few grid steps across smooths away below the 0.5 level.
        raise ReconstructionError(
            f"Remeshing M0 at edge length {edge_length:g} mm left {out.n_faces if out else 0} "
            "triangles: the bone is too small for that edge length. Use a smaller edge_length "
            "(or leave it on auto) and a finer resample spacing.")
    return out


def contour(field_zyx: np.ndarray, origin, h: float, level: float,
            smooth_iterations: int = SINC_ITERATIONS) -> Surface:
    """Largest closed isosurface of a scalar field.

    Parameters
    ----------
    field_zyx : (z, y, x) float array
        On an isotropic grid of step ``h`` whose voxel (0, 0, 0) is at ``origin`` (x, y, z).
    origin : sequence of 3 floats
    h : float
    level : float
        Iso-value.
    smooth_iterations : int
        Windowed-sinc iterations (0: none).
    """
    import vtk
    from vtk.util import numpy_support as ns

    dims = field_zyx.shape[::-1]
    img = vtk.vtkImageData()
    img.SetOrigin(*[float(v) for v in origin])
    img.SetSpacing(h, h, h)
    img.SetDimensions(*[int(v) for v in dims])
    img.GetPointData().SetScalars(ns.numpy_to_vtk(np.ascontiguousarray(field_zyx, dtype=np.float32).ravel(), deep=True))
    fe = vtk.vtkFlyingEdges3D()
    fe.SetInputData(img)
    fe.SetValue(0, level)
    fe.ComputeNormalsOff()
    fe.ComputeGradientsOff()
    fe.ComputeScalarsOff()
    conn = vtk.vtkPolyDataConnectivityFilter()
    conn.SetInputConnection(fe.GetOutputPort())
    conn.SetExtractionModeToLargestRegion()
    clean = vtk.vtkCleanPolyData()
    clean.SetInputConnection(conn.GetOutputPort())
    clean.PointMergingOn()
    clean.SetTolerance(0.0)
    last = clean
    if smooth_iterations:
        sinc = vtk.vtkWindowedSincPolyDataFilter()
        sinc.SetInputConnection(clean.GetOutputPort())
        sinc.SetNumberOfIterations(smooth_iterations)
        sinc.SetPassBand(SINC_PASS_BAND)
        sinc.BoundarySmoothingOff()
        sinc.FeatureEdgeSmoothingOff()
        sinc.NonManifoldSmoothingOn()
        sinc.NormalizeCoordinatesOn()
        last = sinc
    last.Update()
    surf = from_polydata(last.GetOutput())
    surf = drop_degenerate(surf)
    surf.vertices = tangential_relax(surf.vertices, surf.faces)
    if enclosed_volume(surf.vertices, surf.faces) < 0:
        surf.faces = surf.faces[:, ::-1].copy()
    return surf


def drop_degenerate(surface: Surface) -> Surface:
    """Remove faces that repeat a vertex index (flying edges can emit them after merging)."""
    f = surface.faces
    ok = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    if ok.all():
        return surface
    faces = f[ok]
    used, inv = np.unique(faces, return_inverse=True)
    return Surface(surface.vertices[used], inv.reshape(-1, 3), surface.coordinate_system)


def initial_surface(points: np.ndarray, normals: np.ndarray, depth: int,
                    edge_length: float) -> tuple[Surface, Surface]:
    """M0: Poisson on the oriented visible points, remeshed closed and near-uniform.

    Parameters
    ----------
    points, normals : (k, 3) float arrays
        Visible points in grid millimetres (x-y-z) and their outward unit normals.
    depth : int
        Poisson octree depth.
    edge_length : float
        Target mean edge length d* in mm.

    Returns
    -------
    (M0, raw Poisson surface), both in grid millimetres
    """
    raw = poisson_surface(points, normals, depth)
    return remesh(raw, edge_length), raw

