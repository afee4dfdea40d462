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
* :func:`segment_closed_surface` - the segment itself through Slicer's closed-surface
  conversion: what a user gets today from an AI segment (one label of a label map).

The first three work on the pipeline's working grid (:func:`prepare.prepare_labels`, as the
pipeline calls it at the default segment_dilation: crop to the segment + margin + band,
B-spline resample to the isotropic spacing), so differences come from the method, not the
grid; a segment touching the CT's border is refused (BorderError), as plain thresholding has
no cap. :func:`segment_closed_surface` works on the label map's own grid and
needs nothing of the pipeline. Each returns a :class:`Surface` in physical LPS with faces
oriented so the enclosed volume is positive, and never checks topology: the benchmark
reports the checks of every method.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Optional

import numpy as np
from scipy import ndimage

from BoneWatertightLib.mesh import Surface, enclosed_volume, from_polydata

# The pipeline's parameters and preparation are imported where the first three baselines use
# them, so that segment_closed_surface (and importing this module) does not depend on them.
if TYPE_CHECKING:  # pragma: no cover
    from BoneWatertightLib.params import Parameters
    from BoneWatertightLib.stages.prepare import PreparedLabels

# Slicer's default closed-surface smoothing factor and the iteration count it uses.
SLICER_SMOOTHING_FACTOR = 0.5
SLICER_SINC_ITERATIONS = 20
# The paper's target threshold: what the threshold baselines use when the parameters leave HT
# to the pipeline's per-case estimate (ht=None), as they did before that estimate existed.
PAPER_HT = 150.0


def _params(params: Optional["Parameters"]) -> "Parameters":
    from BoneWatertightLib.params import Parameters

    return (params or Parameters()).validate()


def _prepared(ct, mask, params: Optional["Parameters"]) -> "PreparedLabels":
    """The working grid of the mask (non-zero = the bone) as label 1."""
    import SimpleITK as sitk

    from BoneWatertightLib.stages.prepare import prepare_labels

    params = _params(params)
    labels = sitk.Cast(sitk.NotEqual(mask, 0), sitk.sitkUInt8)
    return prepare_labels(ct, labels, [1], spacing=params.spacing, margin=params.margin,
                          max_memory_gb=params.max_memory_gb, at_border="error")


def _segment(prep: PreparedLabels) -> np.ndarray:
    """The rough segment on the working grid, (z, y, x) bool."""
    return prep.labels == prep.targets[0]


def threshold_mask(prep: PreparedLabels, params: Parameters) -> np.ndarray:
    """Voxels in [HT, theta_max] in the connected components that touch the rough segment
    dilated by params.segment_dilation (so a missing chunk of the segment is still found).
    HT = params.ht, or :data:`PAPER_HT` when it is None (the pipeline's "auto")."""
    ct = prep.ct
    ht = PAPER_HT if params.ht is None else params.ht
    m = (ct >= ht) & (ct <= params.theta_max)
    r = max(1, int(round(params.segment_dilation / prep.grid.spacing)))
    near = _dilate_mm(_segment(prep), r)
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


def _to_surface(poly, prep: PreparedLabels) -> Surface:
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
    params = _params(params)
    prep = _prepared(ct, mask, params)
    m = threshold_mask(prep, params)
    return _to_surface(labelmap_to_surface(m, prep.grid.spacing, smoothing_factor), prep)


def direct_poisson(ct, mask, params: Optional[Parameters] = None, depth: int = 9) -> Surface:
    """Screened Poisson on the boundary voxel centres of the threshold mask (inner
    boundaries of pores and the marrow cavity included, as a plain use would have them),
    with normals = -gradient of the Gaussian-smoothed CT."""
    import open3d as o3d  # heavy; only this baseline needs it

    params = _params(params)
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
    params = _params(params)
    prep = _prepared(ct, mask, params)
    d = prep.grid.spacing
    m = threshold_mask(prep, params)
    r = gap_mm / d
    pad = int(np.ceil(r)) + 2
    mp = np.pad(m, pad)
    closed = _erode_mm(_dilate_mm(mp, r), r)[pad:-pad, pad:-pad, pad:-pad] | m
    closed = ndimage.binary_fill_holes(closed)
    return _to_surface(labelmap_to_surface(closed, d, smoothing_factor), prep)


def segment_closed_surface(labels, value: int = 1,
                           smoothing: float = SLICER_SMOOTHING_FACTOR) -> Surface:
    """The segment itself as 3D Slicer shows it: one label of a label map through Slicer's
    binary-labelmap -> closed-surface conversion, in physical LPS.

    As Slicer's conversion rule does: the voxels equal to ``value`` in index space (IJK,
    padded by one voxel), discrete flying edges at 1, windowed-sinc smoothing with pass band
    10^(-4 * smoothing) (Slicer's default smoothing factor 0.5 -> 0.01; 20 iterations,
    normalised coordinates, non-manifold smoothing on, boundary and feature-edge smoothing
    off), no decimation; then index -> physical with the image's origin, spacing and
    direction. (The smoothing's umbrella weights are uniform, so smoothing in IJK and in
    millimetres give the same surface even on anisotropic grids.) Nothing of the pipeline is
    used: no crop, no resampling, no CT.

    Parameters
    ----------
    labels : SimpleITK.Image
        3-D integer label map (array (z, y, x)), any spacing, origin and direction.
    value : int
        The label to convert.
    smoothing : float
        Slicer's smoothing factor (0 = none: the stair-stepped flying-edges surface).

    Returns
    -------
    Surface
        Physical LPS mm, faces counter-clockwise seen from outside (enclosed volume > 0);
        empty (0 faces) when the label is absent. Not checked: the conversion gives a closed
        surface but neither manifoldness nor freedom from self-intersections is guaranteed
        (see Testing/test_baselines.py for what it gives on the phantoms).
    """
    import SimpleITK as sitk
    from vtk.util import numpy_support as ns

    arr = sitk.GetArrayViewFromImage(labels)
    if arr.ndim != 3:
        raise ValueError(f"segment_closed_surface needs a 3-D label map, got {arr.ndim}-D")
    sel = np.asarray(arr) == value
    empty = Surface(np.zeros((0, 3)), np.zeros((0, 3), np.int64), "LPS")
    if not sel.any():
        return empty
    # Crop to the label's bounding box (the surface is the same; the padding closes it where
    # the label touches the image border, as Slicer's padding does).
    nz = [np.flatnonzero(sel.any(axis=a)) for a in ((1, 2), (0, 2), (0, 1))]
    lo = np.array([nz[2][0], nz[1][0], nz[0][0]])  # (i, j, k)
    hi = np.array([nz[2][-1], nz[1][-1], nz[0][-1]]) + 1
    crop = sel[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
    poly = labelmap_to_surface(crop, 1.0, smoothing)  # vertex coordinates = crop indices
    if not poly.GetNumberOfPolys():
        return empty
    ijk = ns.vtk_to_numpy(poly.GetPoints().GetData()).astype(np.float64) + lo
    f = ns.vtk_to_numpy(poly.GetPolys().GetConnectivityArray()).astype(np.int64).reshape(-1, 3)
    D = np.array(labels.GetDirection(), float).reshape(3, 3)
    v = np.array(labels.GetOrigin(), float) + (ijk * np.array(labels.GetSpacing(), float)) @ D.T
    if enclosed_volume(v, f) < 0:  # a left-handed direction matrix flips the orientation
        f = f[:, ::-1].copy()
    return Surface(v, f, "LPS")


METHODS = {
    "threshold_mc": threshold_marching_cubes,
    "direct_poisson": direct_poisson,
    "closing_wrap": closing_wrap,
}
