"""The plain alternatives to the pipeline, for benchmarks (same inputs, same crop).

* :func:`threshold_marching_cubes` - what a 3D Slicer user gets from a threshold segment:
  threshold [HT, theta_max], keep the components touching the (dilated) rough segment,
  discrete flying edges on the label map and the windowed-sinc smoothing of Slicer's
  binary-labelmap -> closed-surface conversion (smoothing factor 0.5 -> pass band
  10^(-4 * 0.5) = 0.01, 20 iterations, normalised coordinates, non-manifold smoothing on,
  boundary and feature-edge smoothing off).
* :func:`direct_poisson` - screened Poisson (open3d) on the boundary voxel centres of the
  threshold mask, normals from the gradient of the smoothed CT.
* :func:`closing_wrap` - morphological closing with a ball of ``gap_mm`` radius, hole
  filling, marching cubes and light smoothing (like a "wrap" with a gap-closing distance).

All three work on the pipeline's working grid (:func:`prepare.prepare`: crop to the segment
+ margin, B-spline resample to the isotropic spacing), so differences come from the method,
not the grid. Each returns a :class:`Surface` in physical LPS with faces oriented so the
enclosed volume is positive, and never checks topology: the benchmark reports the checks of
every method.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
from scipy import ndimage

from BoneWatertightLib.mesh import Surface, enclosed_volume, from_polydata
from BoneWatertightLib.params import Parameters
from BoneWatertightLib.stages.prepare import Prepared, prepare

# Slicer's default closed-surface smoothing factor and the iteration count it uses.
SLICER_SMOOTHING_FACTOR = 0.5
SLICER_SINC_ITERATIONS = 20


def _prepared(ct, mask, params: Optional[Parameters]) -> Prepared:
    params = (params or Parameters()).validate()
    return prepare(ct, mask, spacing=params.spacing, margin=params.margin,
                   max_memory_gb=params.max_memory_gb)


def threshold_mask(prep: Prepared, params: Parameters) -> np.ndarray:
    """Voxels in [HT, theta_max] in the connected components that touch the rough segment
    dilated by params.segment_dilation (so a missing chunk of the segment is still found)."""
    ct = prep.ct
    m = (ct >= params.ht) & (ct <= params.theta_max)
    r = max(1, int(round(params.segment_dilation / prep.grid.spacing)))
    near = _dilate_mm(prep.segment, r)
    lab, n = ndimage.label(m)
    if n == 0:
        return m
    hit = np.unique(lab[near & m])
    hit = hit[hit > 0]
    return np.isin(lab, hit)


def _dilate_mm(mask: np.ndarray, r_vox: float) -> np.ndarray:
    """Dilation by a ball of radius r_vox voxels (distance transform: cost independent of r)."""
    if not mask.any():
        return mask.copy()
    return ndimage.distance_transform_edt(~mask) <= r_vox


def _erode_mm(mask: np.ndarray, r_vox: float) -> np.ndarray:
    return ndimage.distance_transform_edt(mask) > r_vox


def _to_surface(poly, prep: Prepared) -> Surface:
    s = from_polydata(poly)
    if not s.n_faces:
        return Surface(np.zeros((0, 3)), np.zeros((0, 3), np.int64), "LPS")
    v = prep.grid.grid_to_physical(s.vertices)
    f = s.faces
    if enclosed_volume(v, f) < 0:
        f = f[:, ::-1].copy()
    return Surface(v, f, "LPS")


def _image(mask_zyx: np.ndarray, spacing: float, pad: int = 1):
    """vtkImageData of a (padded) uint8 mask in grid millimetres."""
    import vtk
    from vtk.util import numpy_support as ns

    arr = np.pad(mask_zyx.astype(np.uint8), pad)
    img = vtk.vtkImageData()
    img.SetDimensions(*[int(v) for v in arr.shape[::-1]])
    img.SetSpacing(spacing, spacing, spacing)
    img.SetOrigin(*([-pad * spacing] * 3))
    img.GetPointData().SetScalars(ns.numpy_to_vtk(arr.ravel(), deep=True))
    return img


def _sinc(port, pass_band: float, iterations: int):
    import vtk

    f = vtk.vtkWindowedSincPolyDataFilter()
    f.SetInputConnection(port)
    f.SetNumberOfIterations(iterations)
    f.SetPassBand(pass_band)
    f.BoundarySmoothingOff()
    f.FeatureEdgeSmoothingOff()
    f.NonManifoldSmoothingOn()
    f.NormalizeCoordinatesOn()
    return f


def labelmap_to_surface(mask_zyx: np.ndarray, spacing: float,
                        smoothing_factor: float = SLICER_SMOOTHING_FACTOR):
    """Slicer-like binary label map -> closed surface (vtkPolyData in grid millimetres)."""
    import vtk

    fe = vtk.vtkDiscreteFlyingEdges3D()
    fe.SetInputData(_image(mask_zyx, spacing))
    fe.SetValue(0, 1)
    fe.ComputeNormalsOff()
    fe.ComputeGradientsOff()
    fe.ComputeScalarsOff()
    last = fe
    if smoothing_factor > 0:
        last = _sinc(fe.GetOutputPort(), 10.0 ** (-4.0 * smoothing_factor), SLICER_SINC_ITERATIONS)
    tri = vtk.vtkTriangleFilter()
    tri.SetInputConnection(last.GetOutputPort())
    tri.Update()
    return tri.GetOutput()


def threshold_marching_cubes(ct, mask, params: Optional[Parameters] = None,
                             smoothing_factor: float = SLICER_SMOOTHING_FACTOR) -> Surface:
    """Threshold [HT, theta_max] + connected components + Slicer's closed-surface conversion."""
    params = (params or Parameters()).validate()
    prep = _prepared(ct, mask, params)
    m = threshold_mask(prep, params)
    return _to_surface(labelmap_to_surface(m, prep.grid.spacing, smoothing_factor), prep)


def direct_poisson(ct, mask, params: Optional[Parameters] = None, depth: int = 9) -> Surface:
    """Screened Poisson on the boundary voxel centres of the threshold mask (inner
    boundaries of pores and the marrow cavity included, as a plain use would have them),
    with normals = -gradient of the Gaussian-smoothed CT."""
    import open3d as o3d  # heavy; only this baseline needs it

    params = (params or Parameters()).validate()
    prep = _prepared(ct, mask, params)
    d = prep.grid.spacing
    m = threshold_mask(prep, params)
    boundary = m & ~ndimage.binary_erosion(m)
    idx = np.argwhere(boundary)  # (z, y, x)
    if not len(idx):
        return Surface(np.zeros((0, 3)), np.zeros((0, 3), np.int64), "LPS")
    sm = ndimage.gaussian_filter(prep.ct, sigma=max(1.0, 0.5 / d), mode="nearest")
    g = np.zeros((len(idx), 3))
    for axis_xyz, axis_zyx in ((0, 2), (1, 1), (2, 0)):
        hi = idx.copy()
        lo = idx.copy()
        hi[:, axis_zyx] = np.minimum(hi[:, axis_zyx] + 1, m.shape[axis_zyx] - 1)
        lo[:, axis_zyx] = np.maximum(lo[:, axis_zyx] - 1, 0)
        g[:, axis_xyz] = sm[tuple(hi.T)] - sm[tuple(lo.T)]
    n = -g
    length = np.linalg.norm(n, axis=1)
    keep = length > 1e-6
    pts = idx[keep][:, ::-1] * d
    n = n[keep] / length[keep, None]
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(pts.astype(np.float64))
    pcd.normals = o3d.utility.Vector3dVector(n)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            pcd, depth=depth, scale=1.1, linear_fit=False, n_threads=1)
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.triangles).astype(np.int64)
    if not len(f):
        return Surface(np.zeros((0, 3)), np.zeros((0, 3), np.int64), "LPS")
    v = prep.grid.grid_to_physical(v)
    if enclosed_volume(v, f) < 0:
        f = f[:, ::-1].copy()
    return Surface(v, f, "LPS")


def closing_wrap(ct, mask, params: Optional[Parameters] = None, gap_mm: float = 2.0,
                 smoothing_factor: float = 0.25) -> Surface:
    """Closing with a ball of radius gap_mm, hole filling, marching cubes, light smoothing."""
    params = (params or Parameters()).validate()
    prep = _prepared(ct, mask, params)
    d = prep.grid.spacing
    m = threshold_mask(prep, params)
    r = gap_mm / d
    pad = int(np.ceil(r)) + 2
    mp = np.pad(m, pad)
    closed = _erode_mm(_dilate_mm(mp, r), r)[pad:-pad, pad:-pad, pad:-pad] | m
    closed = ndimage.binary_fill_holes(closed)
    return _to_surface(labelmap_to_surface(closed, d, smoothing_factor), prep)


METHODS = {
    "threshold_mc": threshold_marching_cubes,
    "direct_poisson": direct_poisson,
    "closing_wrap": closing_wrap,
}
