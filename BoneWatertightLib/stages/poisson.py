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
import sys
import threading
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
from scipy import ndimage

from ..errors import DependencyError, ReconstructionError
from ..mesh.operators import tangential_relax
from ..mesh.surface import Surface, enclosed_volume, from_polydata, inside_mask
from .prepare import bbox_slices
from .threshold import dilate6, dilate_cube, fill_holes

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
# Back-off rounds that take a vertex half-way back to the unsmoothed contour before all the
# way, where the smoothing made the contour pass through itself (:func:`_verified_smoothing`).
SMOOTHING_BACKOFF_HALVINGS = 3
SINC_PASS_BAND = 0.1
# Filling tunnels the segment does not have (see _fill_tunnels): at most FILL_MAX_TRIALS
# plugs tried per source (each a trial, whether its box or a contour decided it); plugs of at
# least FILL_MIN_VOXELS grid voxels.
FILL_MAX_TRIALS = 8
FILL_MIN_VOXELS = 8
# A plug is grown this many grid steps into its source before it is tried (to meet the
# hole's rim).
PLUG_GROWTH_STEPS = 2
# The segment's plugs are tried first as the segment's middle sheet: depth within this many
# grid steps of the deepest nearby (:func:`_label_sheet`); then whole.
SHEET_DEPTH_STEPS = 1.5
# A plate of the segment (for the plugs' normals, see _ridge_normals): its smoothed indicator's
# Hessian has a negative eigenvalue PLUG_SHEETNESS times the others in magnitude and below
# -PLUG_MIN_CURVATURE / sigma^2 (a plate one voxel thick: about -0.4 / sigma^3).
PLUG_SHEETNESS = 2.0
PLUG_MIN_CURVATURE = 0.05
# ... and at most NARROW_MAX_TRIALS trials for the tunnels narrower than the CT resolves.
NARROW_MAX_TRIALS = 16
# Fewest triangles of a remeshed M0 (a tetrahedron); fewer: the surface was lost.
MIN_REMESH_FACES = 4


_OPEN3D = None
_POISSON_LOCK = threading.Lock()
_DLL_DIRECTORY = None  # Windows: kept open while the bindings are loaded


def import_open3d():
    """open3d's geometry and utility bindings (the Poisson reconstruction needs nothing else).

    ``import open3d`` also imports open3d.ml and the plotly visualiser, i.e. scikit-learn,
    pandas and dash: 1.9-3.8 s measured, against 0.4 s for the CPU bindings alone. Where open3d
    is not imported yet and is a CPU build, the bindings are loaded alone, registered under
    their own name (``open3d.cpu.pybind``) so that a later ``import open3d`` (by the user,
    in the same Slicer session) finds and reuses them; otherwise, and on any problem with
    that, open3d is imported whole.
    """
    global _OPEN3D
    if _OPEN3D is not None:
        return _OPEN3D
    module = sys.modules.get("open3d")
    if module is None:
        module = _open3d_bindings()
    if module is None:
        try:
            import open3d as module  # noqa: F401  (heavy; imported only when needed)
        except ImportError as exc:  # pragma: no cover - depends on the machine
            raise DependencyError(
                "open3d is not installed; it provides the Poisson reconstruction. Install it "
                "with 'pip install open3d' (in 3D Slicer: the module offers to install it)."
            ) from exc
        except OSError as exc:  # pragma: no cover - missing system library
            raise DependencyError(
                f"open3d is installed but cannot load ({exc}); on Linux install the system "
                "library it names (e.g. 'apt-get install libusb-1.0-0 libgomp1').") from exc
    _OPEN3D = module
    return module


def _open3d_bindings():
    """The CPU bindings of an installed open3d loaded without its package (None: not possible
    here, import the package)."""
    global _DLL_DIRECTORY
    import glob
    import importlib.util

    name = "open3d.cpu.pybind"
    if name in sys.modules:
        return sys.modules[name]
    try:
        spec = importlib.util.find_spec("open3d")
        if spec is None or not spec.origin:
            return None
        package = os.path.dirname(spec.origin)
        files = glob.glob(os.path.join(package, "cpu", "pybind*"))
        if len(files) != 1:
            return None
        if sys.platform == "win32" and _DLL_DIRECTORY is None:
            _DLL_DIRECTORY = os.add_dll_directory(package)
        cuda = glob.glob(os.path.join(package, "cuda", "pybind*"))
        if cuda:
            # A CUDA build (the Linux wheel) uses its CUDA bindings when a device is there, as
            # its __init__ decides: then import the package (CPU bindings registered first
            # would clash with the CUDA ones). The same probe as open3d's own, in that order.
            from ctypes import CDLL

            CDLL(files[0])
            try:
                if CDLL(cuda[0]).open3d_core_cuda_device_count() > 0:
                    return None
            except (OSError, AttributeError):
                pass  # no CUDA runtime: open3d falls back to the CPU bindings too
        binding_spec = importlib.util.spec_from_file_location(name, files[0])
        module = importlib.util.module_from_spec(binding_spec)
        sys.modules[name] = module
        try:
            binding_spec.loader.exec_module(module)
        except BaseException:
            del sys.modules[name]
            raise
        module.geometry.PointCloud  # the attributes used here exist
        module.utility.Vector3dVector
        return module
    except Exception:  # any surprise: the ordinary import decides (and reports)
        return None


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


def poisson_surface(points: np.ndarray, normals: np.ndarray, depth: int,
                    helper: Optional["PoissonHelper"] = None) -> Surface:
    """Screened Poisson (open3d) on oriented points; the largest connected component.

    Parameters
    ----------
    points, normals : (k, 3) float arrays
        Oriented points (x-y-z, any frame) and their outward unit normals.
    depth : int
        Octree depth.
    helper : PoissonHelper, optional
        Computes it in its process (the same surface); when the helper has failed, here.
    """
    # Points without a usable normal (a flat mask gradient, e.g. at the grid's edge) are no
    # evidence of the orientation: leave them out (open3d rejects them as "bad data").
    good = np.isfinite(points).all(axis=1) & (np.linalg.norm(normals, axis=1) > 0.5)
    points = np.ascontiguousarray(points[good], dtype=np.float64)
    normals = np.ascontiguousarray(normals[good], dtype=np.float64)
    mesh = helper.mesh(points, normals, depth) if helper is not None else None
    if mesh is None:
        mesh = _poisson_mesh(points, normals, depth)
    verts, faces = mesh
    if len(faces) == 0:
        raise ReconstructionError(
            "Poisson reconstruction returned no surface: too few visible points. Lower H0 or use "
            "more views.")
    return Surface(verts, faces)


def _poisson_mesh(points: np.ndarray, normals: np.ndarray, depth: int) -> tuple:
    """(vertices (v, 3), faces (f, 3)) of the largest connected component of open3d's screened
    Poisson surface of the oriented points (no faces: Poisson returned none)."""
    o3d = import_open3d()
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(points)
    pcd.normals = o3d.utility.Vector3dVector(normals)
    # n_threads=-1 is ~10x slower than 1 thread here (thread oversubscription): measured.
    # One Poisson at a time: the verbosity and file descriptor 2 are the process's, and bones
    # worked in threads would restore each other's.
    with _POISSON_LOCK, o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error), \
            native_stderr_silenced():
        mesh, _density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            pcd, depth=depth, scale=POISSON_SCALE, linear_fit=False, n_threads=1)
    tri = np.asarray(mesh.triangles)
    if len(tri) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    clusters, counts, _ = mesh.cluster_connected_triangles()
    clusters = np.asarray(clusters)
    biggest = int(np.argmax(np.asarray(counts)))
    faces = tri[clusters == biggest]
    verts = np.asarray(mesh.vertices)
    used, inv = np.unique(faces, return_inverse=True)
    return verts[used], inv.reshape(-1, 3)


# The helper's resident memory (GB), an upper bound: measured 0.34 GB after the five Poisson
# surfaces of the real 3 mm L1-L5 (VmHWM; 0.18 GB of it its own, the rest open3d's library
# pages shared with this process).
HELPER_MEMORY_GB = 0.35
# A helper not ready (its imports done) this long after it was started is given up (s): a
# process that is no Python of ours (an interpreter that starts an application) never answers.
HELPER_START_TIMEOUT_S = 60.0
# While it computes, the helper is checked alive this often (s).
HELPER_POLL_S = 0.2


class PoissonHelper:
    """A helper process that computes :func:`_poisson_mesh` for the bones of one run.

    open3d's Poisson holds the GIL for the whole computation (about a second a bone, during
    which the other bone's thread cannot run Python); in a process of its own it does not stop
    the other bone. Measured on the real 3 mm L1-L5 (5 bones on 2 threads), ten runs each,
    interleaved in pairs on a machine whose speed swings by +-6 s: faster in 7 of the 10 pairs,
    median of the pairs' differences 1.75 s, medians 48.1 s (43.5-57.5) against 51.9 s
    (47.8-55.6) in this process; the same surfaces. One surface at a time (a lock);
    the helper starts when made (its imports overlap the bones' first stages). Should it fail
    (it cannot start, dies, or answers with an error), :meth:`mesh` returns None from then on,
    ``error`` says why, and the caller computes the surface itself. :meth:`close` stops it.
    """

    def __init__(self):
        import multiprocessing

        self.error: Optional[str] = None
        self._lock = threading.Lock()
        self._conn = None
        self._process = None
        self._ready = False
        try:
            context = multiprocessing.get_context("spawn")
            self._conn, child = context.Pipe()
            self._process = context.Process(target=_helper_main, args=(child,),
                                            name="BoneWatertight Poisson", daemon=True)
            self._process.start()
            child.close()
        except Exception as exc:  # noqa: BLE001 - any failure: Poisson in the caller's process
            self._fail(f"it could not start ({type(exc).__name__}: {exc})")

    def mesh(self, points: np.ndarray, normals: np.ndarray, depth: int) -> Optional[tuple]:
        """(vertices, faces) as :func:`_poisson_mesh`, or None once the helper has failed."""
        with self._lock:
            if self.error is not None:
                return None
            try:
                if not self._ready:
                    # its first message says its imports are done
                    if self._answer(HELPER_START_TIMEOUT_S) is None:
                        return None
                    self._ready = True
                self._conn.send((points, normals, int(depth)))
                answer = self._answer(None)
            except (OSError, EOFError, ValueError) as exc:
                code = self._process.exitcode if self._process is not None else None
                self._fail(f"it stopped ({type(exc).__name__}; exit code {code})")
                return None
            if answer is None:
                return None
            status, value = answer
            if status != "ok":
                self._fail(f"it failed: {value}")
                return None
            return value

    def _answer(self, timeout: Optional[float]):
        """The helper's next message, polled while it is alive; None (and failed) when it
        stopped, or sent nothing within ``timeout`` seconds (None: no limit)."""
        waited = 0.0
        while not self._conn.poll(HELPER_POLL_S):
            waited += HELPER_POLL_S
            process = self._process
            if process is None or not process.is_alive():
                code = process.exitcode if process is not None else None
                self._fail(f"it stopped (exit code {code})")
                return None
            if timeout is not None and waited >= timeout:
                self._fail(f"it did not answer within {timeout:g} s")
                return None
        return self._conn.recv()

    def _fail(self, why: str) -> None:
        self.error = why
        self.close()

    def close(self) -> None:
        """Stop the helper (at once; safe to call more than once)."""
        if self._conn is not None:
            try:
                self._conn.close()
            except OSError:
                pass
            self._conn = None
        process, self._process = self._process, None
        if process is not None:
            if process.is_alive():
                process.terminate()
            process.join(5.0)
            if process.is_alive():  # pragma: no cover - terminate did not stop it
                process.kill()
                process.join(1.0)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def _helper_main(conn) -> None:
    """The helper process: ("ready", None) once open3d is imported, then (points, normals, depth)
    in, ("ok", (vertices, faces)) or ("error", message) out, until the pipe closes. Ctrl-C is the
    parent's to handle (it stops this)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        import_open3d()
    except Exception as exc:  # noqa: BLE001 - answered to the first request
        failure = f"{type(exc).__name__}: {exc}"
    else:
        failure = None
    try:
        conn.send(("ready", None))
    except (OSError, BrokenPipeError):
        return
    while True:
        try:
            points, normals, depth = conn.recv()
        except (EOFError, OSError):
            return
        try:
            if failure is not None:
                raise RuntimeError(failure)
            answer = ("ok", _poisson_mesh(points, normals, depth))
        except Exception as exc:  # noqa: BLE001 - the parent decides
            answer = ("error", f"{type(exc).__name__}: {exc}")
        try:
            conn.send(answer)
        except (OSError, BrokenPipeError):
            return


@dataclass
class Fusion:
    """Evidence joined to the Poisson surface when it is remeshed (:func:`remesh`).

    ``plates``: optional callable field(shape, origin, h) -> (z, y, x) float32 in [0, 1] (thin
    plates as slabs, :meth:`.plates.Plates.field`) with ``plates_box`` (lo, hi) x-y-z of what
    it covers. ``label``: optional (z, y, x) bool segment on a grid of step ``label_spacing``
    whose voxel (0, 0, 0) is at ``label_origin`` (x-y-z, the points' frame), with its
    ``genus``: where the surface has more tunnels than the segment, the segment fills them
    (:func:`_fill_tunnels`: a label-restricted closing by ``close_mm[0]``, then plugs of
    holes, :func:`_plugs`, reaching ``close_mm[0]`` to both sides).
    ``bone``: optional (z, y, x) bool on the label's grid, the bone the CT's thresholds hold
    (W_HT with the thin plates; not its solidified version, whose closing would also bridge a
    foramen): where tunnels remain after the segment's fill, plugs of them from it (a plate the
    thresholds hold two or three voxels thick, which Poisson at depth 7 cannot resolve and
    opens, while the segment is lace there too).
    ``strong``: optional (z, y, x) bool on the label's grid, where the CT is in the initial
    window [H0, theta_max]: with ``bone`` and inside the segment, the source of plugs for the
    tunnels left whatever the segment's genus (a plate a voxel thin, which the paper's opening
    takes out of W_H0 and W_HT, is still H0 on the CT).
    ``carve``: optional (z, y, x) bool on the label's grid, voxels that are neither bone on
    the CT nor the segment (:func:`carve_region`): the occupancy is cut back out of them before
    contouring (Poisson closes over tunnels and deep concavities it cannot see into, e.g. a
    curved canal).
    ``info`` is filled with what was done.
    """

    plates: object = None
    plates_box: tuple = None
    label: np.ndarray = None
    label_origin: np.ndarray = None
    label_spacing: float = 0.0
    genus: Optional[int] = None
    close_mm: tuple = ()
    info: dict = field(default_factory=dict)
    fill_mask: tuple = None  # (voxels the segment filled (z, y, x) bool, origin, step)
    # (z, y, x) bool on the label's grid: neither bone nor segment (see :func:`carve_region`);
    # the surface is kept out of it.
    carve: np.ndarray = None
    bone: np.ndarray = None
    strong: np.ndarray = None
    # (z, y, x) bool on the label's grid: the bone's own solid occupancy on the CT (owned W_HT,
    # solidified). Parts of it that the Poisson surface misses by more than ``solid_reach_mm``
    # are joined with the solid between them and the surface (a thin process that Poisson at
    # depth 7 detaches as a small component, which the largest-component rule drops).
    solid: np.ndarray = None
    solid_reach_mm: float = 3.0
    # The point (x, y, z mm, the surface's frame) of the missed solid farthest from the surface:
    # of the bone joined to M0 (``joined_far``), or of the bone left out because joining it
    # added a tunnel (``dropped_far``; its volume and reach in ``info``).
    joined_far: Optional[np.ndarray] = None
    dropped_far: Optional[np.ndarray] = None


def surface_genus(surface: Surface) -> int:
    """(2 - chi) / 2 of a closed surface (V - E + F), not checked for manifoldness."""
    f = np.asarray(surface.faces, np.int64)
    if not len(f):
        return 0
    return max(0, (2 - _euler_characteristic(f)) // 2)


def _euler_characteristic(faces: np.ndarray) -> int:
    """V - E + F of triangles ``faces`` (k, 3) int64 (k > 0): the vertices they use and their
    distinct undirected edges."""
    # Distinct vertices and undirected edges counted on one sorted key array (the fill's and
    # the join's trials count a contour's tunnels dozens of times: np.unique took 10 x longer).
    a, b = faces.ravel(), faces[:, [1, 2, 0]].ravel()
    keys = np.minimum(a, b) * (int(faces.max()) + 1) + np.maximum(a, b)
    keys.sort()
    n_edges = int(np.count_nonzero(keys[1:] != keys[:-1])) + 1
    n_vertices = int(np.count_nonzero(np.bincount(a)))
    return n_vertices - n_edges + len(faces)


def _label_on(fusion: Fusion, shape: tuple, lo: np.ndarray, h: float,
              mask: Optional[np.ndarray] = None) -> np.ndarray:
    """The fusion's label (or ``mask``, on the label's grid), nearest-neighbour on the
    remeshing grid (z, y, x)."""
    axes = []
    for a, n in zip(range(3), shape[::-1]):
        q = np.rint((lo[a] + h * np.arange(n) - fusion.label_origin[a]) / fusion.label_spacing)
        axes.append(q.astype(np.int64))
    lab = fusion.label if mask is None else mask
    valid = [(q >= 0) & (q < lab.shape[2 - a]) for a, q in enumerate(axes)]
    idx = [np.clip(q, 0, lab.shape[2 - a] - 1) for a, q in enumerate(axes)]
    out = lab[np.ix_(idx[2], idx[1], idx[0])]
    return out & valid[2][:, None, None] & valid[1][None, :, None] & valid[0][None, None, :]


def carve_region(segment: np.ndarray, bone: np.ndarray, spacing: float, segment_margin_mm: float,
                 bone_margin_mm: float, soft_tissue: Optional[np.ndarray] = None) -> np.ndarray:
    """Voxels that are neither bone nor segment: farther than ``bone_margin_mm`` from the bone
    the CT shows and farther than ``segment_margin_mm`` from the segment; with
    ``soft_tissue``, also wherever the CT shows soft tissue outside the segment, however near
    the bone: ``bone`` is closed and filled, so a narrow canal that the segment leaves open
    and the CT shows dark lies inside it (the sacral canal's caudal tube, 3-4 mm of lumen
    between its walls on 0.7 x 2.5 mm slices).

    Parameters
    ----------
    segment, bone : (z, y, x) bool arrays of one grid
        The (trusted) segment and the bone at HT with thin plates (filled).
    spacing : float
        Grid step (mm).
    segment_margin_mm, bone_margin_mm : float
    soft_tissue : (z, y, x) bool array, optional
        Where the CT shows soft tissue (a lumen the segment leaves open is carved however close
        to the segment and to the bone).

    Returns
    -------
    (z, y, x) bool array
    """
    from ..mesh.distance import distance_outside

    free = distance_outside(segment, spacing) > segment_margin_mm
    free &= distance_outside(bone, spacing) > bone_margin_mm
    if soft_tissue is not None:
        free |= soft_tissue & ~segment
    return free


def _closing_adds(field_zyx: np.ndarray, h: float, radius_mm: float) -> np.ndarray:
    """Voxels that a closing of the occupancy (field >= 0.5) by a ball of ``radius_mm`` adds."""
    from ..mesh.distance import distance_inside, distance_outside

    occ = field_zyx >= 0.5
    grown = distance_outside(occ, h) <= radius_mm
    return (distance_inside(grown, h) > radius_mm) & ~occ


def _label_sheet(label: np.ndarray, h: float, reach_mm: float) -> np.ndarray:
    """The middle of the segment where it is thick: voxels whose depth in it is within
    SHEET_DEPTH_STEPS grid steps of the largest depth within ``reach_mm`` (a segment up to about
    three steps thick is kept whole). A plug of a hole in a thin plate taken from this has about
    the plate's thickness where a coarse, generous segment is several times thicker than the
    plate (a real scapular blade under an AI-like label: 37.8 ml instead of 54 ml, the blade on
    the CT)."""
    from ..mesh.distance import distance_inside

    depth = distance_inside(np.pad(label, 1), h)[1:-1, 1:-1, 1:-1]
    size = 2 * max(1, int(np.ceil(reach_mm / h))) + 1
    top = ndimage.maximum_filter(depth, size=size)
    return label & (depth >= top - SHEET_DEPTH_STEPS * h)


def _close_with_label(field_zyx: np.ndarray, label: np.ndarray, h: float,
                      radius_mm: float) -> np.ndarray:
    """Voxels of ``label`` that a closing of the occupancy (field >= 0.5) by a ball of
    ``radius_mm`` adds: holes the segment does not have, bridged where the segment is."""
    return _closing_adds(field_zyx, h, radius_mm) & label


def remesh(surface: Surface, edge_length: float, smooth_iterations: int = SINC_ITERATIONS,
           fusion: Optional[Fusion] = None) -> Surface:
    """Closed, manifold, near-uniform remesh of a (roughly closed) surface through a voxel grid.

    ``fusion``: evidence joined to the surface's (smoothed) occupancy by the maximum before
    contouring (thin plates; the segment where the surface has tunnels it does not have)."""
    h = edge_length / REMESH_EDGE_RATIO
    lo = surface.vertices.min(axis=0)
    hi = surface.vertices.max(axis=0)
    if fusion is not None and fusion.plates is not None:
        lo = np.minimum(lo, fusion.plates_box[0])
        hi = np.maximum(hi, fusion.plates_box[1])
    lo = lo - REMESH_PAD_STEPS * h
    hi = hi + REMESH_PAD_STEPS * h
    if fusion is not None and fusion.solid is not None and fusion.solid.any():
        # Over the solid too, by whole steps: the lattice stays where it was, so a surface
        # that misses nothing is remeshed exactly as without the solid.
        nz = np.argwhere(fusion.solid)[:, ::-1] * fusion.label_spacing + fusion.label_origin
        pad = REMESH_PAD_STEPS * h
        lo = lo - np.ceil(np.maximum(lo - (nz.min(axis=0) - pad), 0.0) / h) * h
        hi = hi + np.ceil(np.maximum(nz.max(axis=0) + pad - hi, 0.0) / h) * h
    dims = np.ceil((hi - lo) / h).astype(int) + 1
    occ = inside_mask(surface, tuple(int(v) for v in dims[::-1]), h, lo)
    if not occ.any():
        if np.ptp(surface.vertices, axis=0).min() < 2 * h:
            # No grid centre inside a surface thinner than two grid steps: too small.
            raise _too_small(edge_length, 0)
        raise ReconstructionError("Remeshing lost the surface (empty rasterisation).")
    occ = fill_holes(_largest_component(occ))
    joined = occ
    smoothed = ndimage.gaussian_filter(occ.astype(np.float32), sigma=REMESH_SMOOTH_SIGMA)
    if fusion is not None and fusion.solid is not None:
        # What the contour keeps: the largest piece of the smoothed occupancy (a thin neck of a
        # process that Poisson made thinner than the smoothing cuts it off).
        joined = _join_missed_bone(occ, lo, h, fusion, _largest_component(smoothed >= 0.5))
    if joined is not occ:
        # The join is kept only when it adds no tunnel: the lace of a thin plate that the
        # thresholds hold and Poisson smoothed over is no process of the bone.
        before = dict(fusion.info)
        plain = _contour_fused(occ, lo, h, fusion, smoothed)
        plain_state = (dict(fusion.info), fusion.fill_mask)
        fusion.info, fusion.fill_mask = before, None
        out = _contour_fused(joined, lo, h, fusion)
        if plain is not None and (out is None or out.genus > plain.genus):
            # One piece's tunnel drops only that piece: a detached tip beside the lace of a
            # plate elsewhere is still joined.
            out = _join_piece_by_piece(occ, joined, plain.genus, lo, h, fusion, before,
                                       smoothed)
        if plain is not None and (out is None or out.genus > plain.genus):
            dropped = fusion.info.get("joined_bone_mm3", 0.0)
            reach = fusion.info.get("joined_reach_mm", 0.0)
            fusion.info, fusion.fill_mask = plain_state
            fusion.info.update(joined_bone_mm3=0.0, joined_pieces=0, join_dropped_mm3=dropped,
                               join_dropped_reach_mm=reach)
            fusion.dropped_far, fusion.joined_far = fusion.joined_far, None
            out = plain
    else:
        out = _contour_fused(occ, lo, h, fusion, smoothed)
    # Only the contour kept is smoothed (the variants above are told apart by their tunnels).
    out = None if out is None else out.smoothed(smooth_iterations,
                                                None if fusion is None else fusion.info)
    if out is None or out.n_faces < MIN_REMESH_FACES:
        # A Poisson surface only a few grid steps across smooths away below the 0.5 level.
        raise _too_small(edge_length, out.n_faces if out else 0)
    return out


class _Level:
    """The 0.5 level of a field on the remeshing grid (z, y, x, step ``h``, voxel (0, 0, 0) at
    ``lo``), contoured raw when its tunnels are asked for and smoothed only when kept."""

    def __init__(self, field_zyx: np.ndarray, lo, h: float, genus: Optional[int] = None):
        self.field, self.lo, self.h, self._genus = field_zyx, lo, h, genus

    @property
    def genus(self) -> int:
        """:func:`raw_genus` of the field."""
        if self._genus is None:
            self._genus = raw_genus(self.field)
        return self._genus

    def smoothed(self, iterations: int, info: Optional[dict] = None) -> Surface:
        """The contour as :func:`remesh` returns it (``info``: see :func:`contour`)."""
        return contour(self.field, self.lo, self.h, 0.5, iterations, info=info)


def _contour_fused(occ: np.ndarray, lo, h: float, fusion: Optional[Fusion],
                   smoothed: Optional[np.ndarray] = None) -> Optional[_Level]:
    """The 0.5 level of the smoothed occupancy ``occ`` with the fusion's plates, carve and
    tunnel fill (see :func:`remesh`); None when nothing reaches the level. ``smoothed``: occ
    already smoothed (REMESH_SMOOTH_SIGMA), when at hand; it is not modified."""
    field = (ndimage.gaussian_filter(occ.astype(np.float32), sigma=REMESH_SMOOTH_SIGMA)
             if smoothed is None else smoothed.copy())
    if fusion is not None and fusion.plates is not None:
        np.maximum(field, fusion.plates(field.shape, lo, h), out=field)
    if fusion is not None and fusion.carve is not None and fusion.label is not None:
        field = _carve(field, lo, h, fusion)
    if field.max() <= 0.5:
        return None
    if fusion is not None and fusion.label is not None and fusion.genus is not None:
        return _fill_tunnels(_Level(field, lo, h), fusion)
    return _Level(field, lo, h)


def _largest_component(mask: np.ndarray) -> np.ndarray:
    """The largest 6-connected component of ``mask`` (mask itself when it has one or none)."""
    lab, n = ndimage.label(mask)
    if n <= 1:
        return mask
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    return lab == int(np.argmax(sizes))


# The pieces of a join that adds a tunnel reaching farther than JOIN_TRIAL_REACH_MM beyond M0
# are tried one by one (largest first, at most JOIN_PIECES_TRIED: each costs a tunnel count
# and fill of the remesh grid); nearer ones are left out with the rest, as
# their loss is within the thin-plate bones' bound on the largest error (issue 18: 5 mm; the
# pipeline warns about left-out bone beyond it).
JOIN_TRIAL_REACH_MM = 5.0
JOIN_PIECES_TRIED = 6


def _join_piece_by_piece(occ: np.ndarray, joined: np.ndarray, genus: int, lo, h: float,
                         fusion: Fusion, before: dict, smoothed: np.ndarray
                         ) -> Optional[_Level]:
    """The contour of ``occ`` with those 26-connected pieces of ``joined & ~occ`` that reach
    farther than JOIN_TRIAL_REACH_MM beyond it and, added one at a time (largest first) to the
    pieces kept so far, leave at most ``genus`` tunnels; None when none does.
    ``fusion.info`` (reset to ``before`` for each trial), ``fill_mask``, ``joined_far`` and
    ``dropped_far`` are those of the surface returned, with the pieces left out as
    ``join_dropped_mm3`` / ``join_dropped_reach_mm``."""
    from ..mesh.distance import distance_outside

    pieces, n = ndimage.label(joined & ~occ, structure=np.ones((3, 3, 3), bool))
    if n < 2:
        return None
    dist = distance_outside(_largest_component(smoothed >= 0.5), h)
    reach = ndimage.maximum(dist, pieces, index=np.arange(1, n + 1))
    sizes = np.bincount(pieces.ravel(), minlength=n + 1)[1:]
    order = [int(i) + 1 for i in np.argsort(-sizes) if reach[i] > JOIN_TRIAL_REACH_MM]
    kept, out, state = np.zeros(n + 1, bool), None, None
    for i in order[:JOIN_PIECES_TRIED]:
        trial = kept.copy()
        trial[i] = True
        fusion.info, fusion.fill_mask = dict(before), None
        surface = _contour_fused(occ | trial[pieces], lo, h, fusion)
        if surface is not None and surface.genus <= genus:
            kept, out, state = trial, surface, (dict(fusion.info), fusion.fill_mask)
    if out is None:
        return None
    fusion.info, fusion.fill_mask = state

    def farthest(mask):
        if not mask.any():
            return 0.0, None
        k = int(np.argmax(np.where(mask, dist, -1.0)))
        return (float(dist.flat[k]),
                np.array(np.unravel_index(k, mask.shape)[::-1], np.float64) * h
                + np.asarray(lo, np.float64))

    mine, left = kept[pieces], (pieces > 0) & ~kept[pieces]
    (reach_in, fusion.joined_far), (reach_out, fusion.dropped_far) = farthest(mine), farthest(left)
    fusion.info.update(joined_bone_mm3=float(mine.sum() * h ** 3), joined_pieces=int(kept.sum()),
                       joined_reach_mm=reach_in, join_dropped_mm3=float(left.sum() * h ** 3),
                       join_dropped_reach_mm=reach_out)
    return out


def _join_missed_bone(occ: np.ndarray, lo, h: float, fusion: Fusion,
                      kept: np.ndarray) -> np.ndarray:
    """occ joined by the bone of ``fusion.solid`` it misses where that bone reaches farther
    than ``fusion.solid_reach_mm`` from it (a process, not the partial-volume shell along the
    surface), connected to occ through the solid, with at least reach^3 of it so far out, or
    a process about the reach across (thinner than the CT resolves) going on at least a grid
    step h beyond the reach: reach^2 x h of it so far out, and part of it farther than
    reach + h (reach^3 alone lost a 3 mm transverse process's last 5 mm): that far part with
    the solid between it and occ (within the reach of the far part).
    ``kept``: what of occ the contour keeps (the largest piece of its smoothed occupancy): the
    bone is measured against it (a process whose neck the smoothing cuts is missed beyond the
    neck, though occ still holds a thin thread of it)."""
    from ..mesh.distance import distance_outside

    solid = _label_on(fusion, occ.shape, np.asarray(lo, np.float64), h, fusion.solid)
    missed = solid & ~kept
    reach = max(fusion.solid_reach_mm, 2.0 * h)
    dist_occ = distance_outside(kept, h)
    far = missed & (dist_occ > reach)
    if not far.any():
        fusion.info.update(joined_bone_mm3=0.0, joined_pieces=0)
        return occ
    pieces, n = ndimage.label(missed, structure=np.ones((3, 3, 3), bool))
    touching = np.unique(pieces[missed & (dist_occ <= 1.5 * h)])
    far_mm3 = np.bincount(pieces[far], minlength=n + 1) * h ** 3
    farthest = np.zeros(n + 1)
    farthest[1:] = ndimage.maximum(np.where(far, dist_occ, 0.0), pieces, np.arange(1, n + 1))
    big = (far_mm3 >= reach ** 3) | ((far_mm3 >= reach * reach * h) & (farthest > reach + h))
    ids = np.intersect1d(np.flatnonzero(big), touching[touching > 0])
    if not len(ids):
        fusion.info.update(joined_bone_mm3=0.0, joined_pieces=0)
        return occ
    mine = np.isin(pieces, ids)
    keep = mine & (far | (distance_outside(far & mine, h) <= reach + h))
    fusion.info.update(joined_bone_mm3=float(keep.sum() * h ** 3), joined_pieces=int(len(ids)),
                       joined_reach_mm=float(dist_occ[keep].max()))
    k = int(np.argmax(np.where(keep, dist_occ, -1.0)))
    fusion.joined_far = np.array(np.unravel_index(k, keep.shape)[::-1], np.float64) * h \
        + np.asarray(lo, np.float64)
    return occ | keep


def _too_small(edge_length: float, n_faces: int) -> ReconstructionError:
    return ReconstructionError(
        f"Remeshing M0 at edge length {edge_length:g} mm left {n_faces} triangles: the bone is "
        "too small for that edge length. Use a smaller edge_length (or leave it on auto) and a "
        "finer resample spacing.")


def _carve(field_zyx: np.ndarray, lo, h: float, fusion: Fusion) -> np.ndarray:
    """The occupancy field cut back out of ``fusion.carve`` (a soft edge of the remesh's own
    smoothing, so the cut surface lies on the carve region's border); the carved volume in
    ``fusion.info``."""
    carve = _label_on(fusion, field_zyx.shape, np.asarray(lo, np.float64), h, fusion.carve)
    inside = field_zyx >= 0.5
    if not (carve & inside).any():
        fusion.info.update(carved_mm3=0.0)
        return field_zyx
    ramp = ndimage.gaussian_filter(carve.astype(np.float32), sigma=REMESH_SMOOTH_SIGMA)
    out = np.minimum(field_zyx, 1.0 - np.minimum(1.0, 2.0 * ramp))
    fusion.info.update(carved_mm3=float((inside & (out < 0.5)).sum() * h ** 3))
    return out


def _plugs(field_zyx: np.ndarray, label: np.ndarray, h: float, reach_mm: float,
           ridges: bool = False):
    """Pieces of the segment outside the occupancy (field >= 0.5) with no occupancy on
    either side along the segment's normal within ``reach_mm``: plugs of holes in a thin plate
    (the segment's margin beside the surface has the surface on its inner side). With
    ``ridges``, where the gradient gives no such normal, the normal of a plate thinner than the
    smoothing (:func:`_ridge_normals`). Returns the labelled pieces (z, y, x) and their sizes
    (voxels, index 0 unused)."""
    cand = label & (field_zyx < 0.5)
    idx = np.argwhere(cand)
    if not len(idx):
        return np.zeros(label.shape, np.int32), np.zeros(1, np.int64)
    sigma = max(0.5 * reach_mm / h, 1.0)
    indicator = label.astype(np.float32)
    sm = ndimage.gaussian_filter(indicator, sigma=sigma)
    # The segment's outward normal (z, y, x): down its smoothed indicator's gradient.
    n = -np.stack([ndimage.sobel(sm, axis=a)[tuple(idx.T)] for a in range(3)], axis=1)
    length = np.linalg.norm(n, axis=1)
    ok = length > 1e-6
    n[ok] /= length[ok, None]

    def free_along(normals, which):
        out = which.copy()
        for side in (-1.0, 1.0):
            q = idx[which] + side * (reach_mm / h) * normals[which]
            out[which] &= ndimage.map_coordinates(field_zyx, q.T, order=1, mode="constant",
                                                  cval=0.0) < 0.5
        return out

    free = free_along(n, ok)
    rest = ~free
    if ridges and rest.any():
        # In a plate of the segment about as thin as that smoothing, the gradient vanishes
        # mid-plate, or points along the plate (to its rim, where a hole narrower than the
        # reach meets the surface): there the plate's normal is the direction of the
        # smoothed indicator's strongest negative curvature, where it is a ridge across it.
        across, ridge = _ridge_normals(indicator, sigma, idx, rest)
        free |= free_along(across, ridge)
    plug = np.zeros(label.shape, bool)
    plug[tuple(idx[free].T)] = True
    pieces, count = ndimage.label(plug, structure=np.ones((3, 3, 3), bool))
    size = np.bincount(pieces.ravel(), minlength=count + 1)
    size[0] = 0
    return pieces, size


def _ridge_normals(indicator: np.ndarray, sigma: float, idx: np.ndarray,
                   which: np.ndarray) -> tuple:
    """(normals (k, 3), where they hold (k,) bool) of the plates of a segment (``indicator``:
    (z, y, x) float32, 1 inside) at
    its voxels ``idx[which]`` (``idx``: (k, 3) indices; ``which``: (k,) bool); on its
    indicator smoothed by ``sigma`` voxels, the eigenvector of the
    Hessian's most negative eigenvalue where that eigenvalue is at least PLUG_SHEETNESS times
    as large as the others in magnitude (a sheet; an edge of a thick part curves as much the
    other way), stronger than PLUG_MIN_CURVATURE / sigma^2 (not a flat face), and where the
    indicator is nearly level, |gradient| <= ``sigma`` x |curvature| (a ridge: its maximum
    across lies within ``sigma``; a plate's middle, not the edge or margin
    of a thick part, whose profile across only falls)."""
    at = tuple(idx[which].T)

    def derivative(order):
        return ndimage.gaussian_filter(indicator, sigma=sigma, order=order)[at].astype(np.float64)

    hess = np.empty((len(at[0]), 3, 3))
    grad = np.empty((len(at[0]), 3))
    for a in range(3):
        grad[:, a] = derivative([int(i == a) for i in range(3)])
        for b in range(a, 3):
            hess[:, a, b] = hess[:, b, a] = derivative([int(i == a) + int(i == b)
                                                       for i in range(3)])
    values, vectors = np.linalg.eigh(hess)
    across = vectors[:, :, 0]
    curv = values[:, 0]
    ridge = ((-curv >= PLUG_SHEETNESS * np.abs(values[:, 1:]).max(axis=1))
             & (curv < -PLUG_MIN_CURVATURE / sigma ** 2)
             & (np.linalg.norm(grad, axis=1) <= -curv * sigma))
    out = np.zeros((len(idx), 3))
    held = np.zeros(len(idx), bool)
    rows = np.flatnonzero(which)[ridge]
    out[rows] = across[ridge]
    held[rows] = True
    return out, held


def euler_number(mask: np.ndarray, connectivity: int = 26) -> int:
    """Euler characteristic of a (z, y, x) bool volume: for one solid without cavities,
    1 - genus. ``connectivity`` 26: the voxels as closed unit cubes (vertices - edges + faces -
    cubes of their union); 6: the voxels as points joined by an edge where they share a face,
    by a square where four share an edge and by a cube where eight share a corner. A contour
    at 0.5 of a smoothed occupancy joins voxels that touch at an edge or corner in some places
    and not in others, so its tunnels lie between the two counts. The characteristic is
    additive: the change that adding voxels makes is computed on a window around them (see
    :func:`_narrow_tunnel_plugs`)."""
    p = np.pad(np.asarray(mask, bool), 1)
    hi, lo = slice(1, None), slice(None, -1)

    def shifted(pattern):
        # every combination of high/low slices along the axes in ``pattern`` (all others whole)
        out = []
        for bits in range(2 ** len(pattern)):
            sl = [slice(None)] * 3
            for j, ax in enumerate(pattern):
                sl[ax] = hi if bits >> j & 1 else lo
            out.append(p[tuple(sl)])
        return out

    axes_pairs = [(1, 2), (0, 2), (0, 1)]
    if connectivity == 6:
        edges = sum(int(np.logical_and(*shifted((ax,))).sum()) for ax in range(3))
        squares = sum(int(np.logical_and.reduce(shifted(pair)).sum()) for pair in axes_pairs)
        cubes = int(np.logical_and.reduce(shifted((0, 1, 2))).sum())
        return int(p.sum()) - edges + squares - cubes
    faces = sum(int(np.logical_or(*shifted((ax,))).sum()) for ax in range(3))
    edges = sum(int(np.logical_or.reduce(shifted(pair)).sum()) for pair in axes_pairs)
    vertices = int(np.logical_or.reduce(shifted((0, 1, 2))).sum())
    return vertices - edges + faces - int(p.sum())


def _narrow_tunnel_plugs(field_zyx: np.ndarray, h: float, radius_mm: float) -> list:
    """Pieces ((z, y, x) bool masks, smallest first) that a closing of the occupancy (field >=
    0.5) by a ball of ``radius_mm`` adds and that each close a tunnel of the voxels (the Euler
    characteristic, counted with 6- or with 26-connected voxels, rises when the piece is
    added; computed on a window around it): plugs of tunnels about 2 x radius_mm across or
    narrower. A closing's other pieces (it also fills every concave crease and notch that
    narrow) leave the characteristic as it is."""
    occ = field_zyx >= 0.5
    pieces, _ = ndimage.label(_closing_adds(field_zyx, h, radius_mm),
                              structure=np.ones((3, 3, 3), bool))
    found = []
    for i, box in enumerate(ndimage.find_objects(pieces), start=1):
        if box is None:
            continue
        win = tuple(slice(max(0, b.start - 2), min(s, b.stop + 2)) for b, s in zip(box, occ.shape))
        piece = pieces[win] == i
        before = occ[win]
        after = before | piece
        if any(euler_number(after, c) > euler_number(before, c) for c in (6, 26)):
            mask = np.zeros(occ.shape, bool)
            mask[win] = piece
            found.append((int(piece.sum()), i, mask))
    return [m for _, _, m in sorted(found, key=lambda t: (t[0], t[1]))]


def _gaussian_reach(sigma: float, truncate: float = 4.0) -> int:
    """Voxels a Gaussian filter of ``sigma`` (scipy's ``truncate``) reaches from a voxel."""
    return int(truncate * float(sigma) + 0.5)


def _raise_to_ramp(field_zyx: np.ndarray, add: np.ndarray) -> None:
    """``field_zyx`` raised in place to min(1, 2 x ``add`` smoothed by REMESH_SMOOTH_SIGMA) (a
    soft plug). Computed on ``add``'s box grown by the kernel's reach: the same values as over
    the whole grid, where the ramp is zero farther out (and the field, never negative, stays)."""
    if not add.any():
        return
    sl = bbox_slices(add, _gaussian_reach(REMESH_SMOOTH_SIGMA))
    ramp = ndimage.gaussian_filter(add[sl].astype(np.float32), sigma=REMESH_SMOOTH_SIGMA)
    np.maximum(field_zyx[sl], np.minimum(1.0, 2.0 * ramp), out=field_zyx[sl])


def _flying_edges(field_zyx: np.ndarray, level: float, origin=(0.0, 0.0, 0.0), h: float = 1.0):
    """vtkFlyingEdges3D of ``field_zyx`` (z, y, x) at ``level`` (not updated), on a grid of step
    ``h`` whose voxel (0, 0, 0) is at ``origin`` (x, y, z)."""
    from .. import _vtk as vtk
    from .._vtk import numpy_support as ns

    img = vtk.vtkImageData()
    img.SetOrigin(*[float(v) for v in origin])
    img.SetSpacing(h, h, h)
    img.SetDimensions(*[int(v) for v in field_zyx.shape[::-1]])
    img.GetPointData().SetScalars(ns.numpy_to_vtk(
        np.ascontiguousarray(field_zyx, dtype=np.float32).ravel(), deep=True))
    fe = vtk.vtkFlyingEdges3D()
    fe.SetInputData(img)
    fe.SetValue(0, level)
    fe.ComputeNormalsOff()
    fe.ComputeGradientsOff()
    fe.ComputeScalarsOff()
    return fe


def _largest_piece(source):
    """A vtkPolyDataConnectivityFilter keeping the largest region of ``source``'s output
    (not updated)."""
    from .. import _vtk as vtk

    conn = vtk.vtkPolyDataConnectivityFilter()
    conn.SetInputConnection(source.GetOutputPort())
    conn.SetExtractionModeToLargestRegion()
    return conn


def _polys_euler(poly) -> Optional[int]:
    """V - E + F of a vtkPolyData's triangles (None when it has none)."""
    from .._vtk import numpy_support as ns

    polys = poly.GetPolys()
    if polys.GetNumberOfCells() == 0:
        return None
    return _euler_characteristic(
        ns.vtk_to_numpy(polys.GetConnectivityArray()).astype(np.int64).reshape(-1, 3))


def _contour_euler(field_zyx: np.ndarray, level: float) -> int:
    """Euler characteristic of the isosurface of ``field_zyx`` (z, y, x) at ``level`` as
    flying edges makes it: every piece, open where it meets the box's faces, one point per
    edge that crosses the level (nothing merged)."""
    fe = _flying_edges(field_zyx, level)
    fe.Update()
    chi = _polys_euler(fe.GetOutput())
    return 0 if chi is None else chi


def raw_genus(field_zyx: np.ndarray, level: float = 0.5) -> int:
    """Tunnels of the largest piece of the isosurface of ``field_zyx`` at ``level``: that of
    :func:`contour` without its smoothing, counted on flying edges' points as they are (one
    per edge that crosses the level; :func:`contour` also merges points that coincide in
    float32, which only a value within about 1e-4 of the level can make). Smoothing and
    relaxing do not change it. 0 when nothing reaches the level."""
    fe = _flying_edges(field_zyx, level)  # (kept: an output port does not keep its filter)
    conn = _largest_piece(fe)
    conn.Update()
    chi = _polys_euler(conn.GetOutput())
    return 0 if chi is None else max(0, (2 - chi) // 2)


def _may_lower_genus(before: np.ndarray, after: np.ndarray, level: float,
                     parts: np.ndarray) -> bool:
    """False when the largest piece of the contour of ``after`` at ``level`` certainly has no
    fewer tunnels than that of ``before`` (the same grid, ``after >= before`` everywhere):
    a plug whose contour :func:`_fill_tunnels` need not make. ``parts``: the pieces of
    ``before``'s inside (``>= level``), 6-connected (``ndimage.label``).

    Exact, not a guess: the contour's topology follows the signs of the values against
    ``level`` only, cell by cell, so the cells with a voxel that crossed it (the box of those
    voxels grown by one) hold the whole change, and the Euler characteristic is additive over
    the two parts of the grid, which meet along the same curves before and after: the
    change of chi = 2 (pieces) - 2 (tunnels) is that of the box's contours. Where the crossed
    voxels meet at most one piece of ``before`` (a piece 6-connected is in one piece of the
    contour) and each part of them meets it, no pieces merge and none is made, so the tunnels
    can drop only when chi grows. Counted as :func:`raw_genus` counts (flying edges' points,
    none merged). Boxes too thin to contour are left to the contour (True)."""
    crossed = (after >= level) & (before < level)
    if not crossed.any():
        return False  # the same signs everywhere: the same topology
    box = bbox_slices(crossed, 1)
    sub_before, sub_after = before[box], after[box]
    if min(sub_after.shape) < 2:
        return True
    sub_crossed, sub_parts = crossed[box], parts[box]
    near = sub_parts[dilate_cube(sub_crossed, 1)]
    if len(np.unique(near[near > 0])) != 1:
        return True  # pieces may merge, or the plug is a piece of its own
    # every 6-connected part of the crossed voxels 6-touches that piece: no new piece
    groups, n_groups = ndimage.label(sub_crossed)
    attached = np.unique(groups[dilate6(sub_parts > 0) & sub_crossed])
    if np.count_nonzero(attached) < n_groups:
        return True
    return _contour_euler(sub_after, level) > _contour_euler(sub_before, level)


def _grown_into(mask: np.ndarray, within: np.ndarray, steps: int, box=None) -> np.ndarray:
    """``mask`` dilated by ``steps`` steps of the 3 x 3 x 3 cube, within ``within``: computed
    on the mask's bounding box (``box``: its slices, when known) grown by ``steps`` - what a
    dilation of the whole grid gives, for the cost of the box."""
    if box is None:
        if not mask.any():
            return np.zeros(mask.shape, bool)
        sl = bbox_slices(mask, steps)
    else:
        sl = tuple(slice(max(0, b.start - steps), min(n, b.stop + steps))
                   for b, n in zip(box, mask.shape))
    out = np.zeros(mask.shape, bool)
    out[sl] = dilate_cube(mask[sl], steps) & within[sl]
    return out


def _fill_tunnels(level: _Level, fusion: Fusion) -> _Level:
    """Where the contour of ``level`` has more tunnels than the segment, close them with the
    segment; returned: the level of the field so filled (``level`` itself when nothing was).

    1. A label-restricted closing of the occupancy by ``fusion.close_mm[0]`` (small handles
       and gaps), kept if it lowers the genus.
    2. Plugs (:func:`_plugs`: the segment where a thin plate of the surface has a hole),
       tried one by one, largest first, each grown two steps into the segment (to meet the
       hole's rim) and kept when it lowers the genus - a plug of a hole does; a flap of the
       segment beside the bone does not, and stays out. Each is tried first as the segment's
       middle sheet (:func:`_label_sheet`: about the plate's thickness under a generous
       segment), then whole.
    3. The same plugs from ``fusion.bone`` (the bone the thresholds hold) for any tunnel left,
       whatever the segment's genus: a tunnel that thresholded bone plugs is no tunnel of the
       bone (a foramen or canal is dark on the CT), and a segment that is lace itself (an AI
       label of a thin blade) has tunnels of its own that say nothing of the bone's.
    4. While the surface still has more tunnels than the segment: the pieces of closings of
       the occupancy by growing balls (one grid step, 1.5, 2, ... up to half of ``close_mm[0]``,
       the segment's coarseness, plus half a step: holes up to a voxel of the CT and a grid
       step across) that each close a tunnel
       (:func:`_narrow_tunnel_plugs`), smallest first, kept when they lower the genus: a
       tunnel narrower than the CT resolves, where the segment at its own resolution has bone
       (thin necks of a vertebra's arch on 3 mm slices, pierced where they are a voxel thin).
       At most NARROW_MAX_TRIALS trials.
    5. While tunnels the segment does not have remain: plugs from ``fusion.bone`` again, now also
       of its plates thinner than the normals' smoothing (:func:`_plugs`' ``ridges``), all of
       them however small in the first trial (``thin_plate_plugs``).
    6. Whatever the segment's genus, while tunnels remain: the same plugs from the bone (and
       the CT in the initial window, ``fusion.strong``) that the segment also covers
       (``covered_plate_plugs``): a hole neither the CT nor the segment has there.
    At most FILL_MAX_TRIALS trials per source; a plug whose box shows it cannot close a
    tunnel (:func:`_may_lower_genus`) is decided without a contour of the whole grid (counted
    in ``fill_trials_local``). What was done is recorded in ``fusion.info`` (``narrow_plugs``,
    ``narrow_fill_mm3``, ``narrow_radius_mm``)."""
    field_zyx, lo, h = level.field, level.lo, level.h
    genus = level.genus
    fusion.info.update(genus_before=int(genus), segment_genus=int(fusion.genus),
                       label_fill_voxels=0, label_fill_mm3=0.0, plugs=0, fill_trials=0,
                       bone_plugs=0, bone_fill_mm3=0.0, narrow_plugs=0, narrow_fill_mm3=0.0,
                       thin_plate_plugs=0, covered_plate_plugs=0,
                       fill_trials_local=0)
    if genus <= fusion.genus and (fusion.bone is None or genus == 0):
        fusion.info["genus_after"] = int(genus)
        return level
    lo = np.asarray(lo, np.float64)
    label = _label_on(fusion, field_zyx.shape, lo, h)
    filled = np.zeros(field_zyx.shape, bool)
    trials = 0

    parts = None  # the pieces of the field's inside, for _may_lower_genus

    def attempt(add, soft):
        nonlocal trials, genus, field_zyx, parts
        trials += 1
        trial = field_zyx.copy()
        if soft:
            _raise_to_ramp(trial, add)
        else:
            trial[add] = 1.0
        if parts is None:
            parts = ndimage.label(field_zyx >= 0.5)[0]
        # Most plugs tried close nothing (a real foramen stays open); they are told apart
        # without a contour of the whole grid (the same decisions as with one).
        if not _may_lower_genus(field_zyx, trial, 0.5, parts):
            fusion.info["fill_trials_local"] += 1
            return False
        g = raw_genus(trial)
        if g < genus:
            genus, field_zyx, parts = g, trial, None
            filled[add] = True
            return True
        return False

    def plug_holes(source, last_trial, goal, thin=False, sheet=None):
        """Plugs of ``source`` (z, y, x bool) tried all at once, then one by one, largest
        first, up to contour number ``last_trial`` or genus ``goal``; returns how many were
        kept. Plugs of at least FILL_MIN_VOXELS voxels; with ``thin``, also those of plates
        thinner than the normals' smoothing (:func:`_plugs`' ``ridges``), and all of them,
        however small, in the first trial; with ``sheet`` (a dict, its "mask" made on first
        use: the segment's middle sheet), each tried as its part in that sheet first."""
        kept = 0
        pieces, size = _plugs(field_zyx, source, h, reach, ridges=thin)
        least_together = 1 if thin else FILL_MIN_VOXELS
        big = np.flatnonzero(size >= least_together)

        def attempt_thin_first(add):
            # the plug's middle sheet first (as thin as the plate), then the whole plug
            if sheet is not None:
                if "mask" not in sheet:  # made once, when a plug is first tried
                    sheet["mask"] = _label_sheet(label, h, reach)
                thin_add = add & sheet["mask"]
                if thin_add.any() and not np.array_equal(thin_add, add) \
                        and attempt(thin_add, soft=True):
                    return True
            return attempt(add, soft=True)

        if len(big) > 1:
            if attempt_thin_first(_grown_into(np.isin(pieces, big), source, PLUG_GROWTH_STEPS)):
                kept += int(len(big))
                size[big] = 0
        boxes = ndimage.find_objects(pieces)
        for p in np.argsort(size)[::-1]:
            if size[p] < FILL_MIN_VOXELS or trials >= last_trial or genus <= goal:
                break
            if attempt_thin_first(_grown_into(pieces == p, source, PLUG_GROWTH_STEPS,
                                              box=boxes[p - 1])):
                kept += 1
        return kept

    reach = fusion.close_mm[0] if fusion.close_mm else 2.0 * h
    if fusion.close_mm and genus > fusion.genus:
        add = _close_with_label(field_zyx, label, h, fusion.close_mm[0])
        if add.any():
            attempt(add, soft=False)
    if genus > fusion.genus:
        fusion.info["plugs"] += plug_holes(label, FILL_MAX_TRIALS, fusion.genus, sheet={})
    from_label = filled.copy()
    bone = None
    if genus > 0 and fusion.bone is not None:
        bone = _label_on(fusion, field_zyx.shape, lo, h, fusion.bone)
        fusion.info["bone_plugs"] = plug_holes(bone, trials + FILL_MAX_TRIALS, 0)
        fusion.info["bone_fill_mm3"] = float((filled & ~from_label).sum() * h ** 3)
    from_ct = filled.copy()
    if fusion.close_mm and genus > fusion.genus:
        last_trial = trials + NARROW_MAX_TRIALS
        # Balls of one grid step, 1.5, 2, ... up to r = (coarseness + h) / 2: a closing by r
        # closes holes up to 2 r across, i.e. one voxel of the segment's coarseness (the CT's
        # slice) and one step of the grid's own rounding; wider holes stay.
        top = 0.5 * (fusion.close_mm[0] + h)
        for radius in h * np.arange(1.0, max(top / h, 1.0) + 1e-9, 0.5):
            if genus <= fusion.genus or trials >= last_trial:
                break
            for plug in _narrow_tunnel_plugs(field_zyx, h, float(radius)):
                if genus <= fusion.genus or trials >= last_trial:
                    break
                # set whole (a plug of a voxel or two smoothed would not reach the level)
                if attempt(plug, soft=False):
                    fusion.info["narrow_plugs"] += 1
                    fusion.info["narrow_radius_mm"] = float(radius)
    narrow = filled & ~from_ct
    fusion.info["narrow_fill_mm3"] = float(narrow.sum() * h ** 3)
    if bone is not None and genus > fusion.genus:
        # Last, against tunnels the segment does not have: the bone's plates however thin,
        # every plug of them together however small. On the coarse grid of a large bone (1.3
        # mm for a hip bone) a hole in a plate a voxel thick is plugged by a few voxels.
        # Thresholded bone is the CT's evidence; a segment's thin parts and crumbs are not
        # (its plugs stay as they were).
        before = filled.copy()
        fusion.info["thin_plate_plugs"] = plug_holes(bone, trials + FILL_MAX_TRIALS,
                                                     fusion.genus, thin=True)
        fusion.info["bone_plugs"] += fusion.info["thin_plate_plugs"]
        fusion.info["bone_fill_mm3"] += float((filled & ~before).sum() * h ** 3)
    if bone is not None and genus > 0:
        # Whatever the segment's genus: a tunnel through a plate that the CT shows as bone and
        # the segment covers is a hole neither has there (the segment's own tunnels may lie
        # elsewhere: a lace-like label of a hip bone has 4 while the surface loses a 470-890 HU
        # acetabular floor a voxel thick). Plugs of that plate, however thin, all together first.
        before = filled.copy()
        covered = bone if fusion.strong is None else \
            bone | _label_on(fusion, field_zyx.shape, lo, h, fusion.strong)
        fusion.info["covered_plate_plugs"] = plug_holes(covered & label,
                                                        trials + FILL_MAX_TRIALS, 0, thin=True)
        fusion.info["bone_plugs"] += fusion.info["covered_plate_plugs"]
        fusion.info["bone_fill_mm3"] += float((filled & ~before).sum() * h ** 3)
    if from_label.any():
        fusion.info.update(label_fill_voxels=int(from_label.sum()),
                           label_fill_mm3=float(from_label.sum() * h ** 3))
    if from_label.any() or narrow.any():
        # the surface there follows neither a CT edge nor thresholded bone but the segment
        # (its fill, or its topology where a tunnel was closed): evidence "label only"
        fusion.fill_mask = (from_label | narrow, lo, h)
    fusion.info["genus_after"] = int(genus)
    fusion.info["fill_trials"] = int(trials)
    return _Level(field_zyx, lo, h, genus) if filled.any() else level


def contour(field_zyx: np.ndarray, origin, h: float, level: float,
            smooth_iterations: int = SINC_ITERATIONS, relax: bool = True,
            info: Optional[dict] = None) -> Surface:
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
    relax : bool
        Tangential relaxation of the vertices (near-uniform edges). The smoothed and relaxed
        surface is then verified free of self-intersections (:func:`_verified_smoothing`).
    info : dict, optional
        Gets ``smoothing_backed_off`` (vertices put back toward the unsmoothed contour) and
        ``smoothing_dropped`` (True when the unsmoothed contour itself was kept).
    """
    from .. import _vtk as vtk

    fe = _flying_edges(field_zyx, level, origin, h)  # (kept: a port does not keep its filter)
    conn = _largest_piece(fe)
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
    # The contour as flying edges made it (before the smoothing: the same points and faces)
    # does not pass through itself; the smoothing and the relaxation may, in a narrow place.
    raw = from_polydata(clean.GetOutput()).vertices if (relax and smooth_iterations) else None
    if raw is not None and raw.shape != surf.vertices.shape:
        raw = None  # not expected: the smoothing keeps the points; then the relaxation's check
    surf, used = _drop_degenerate(surf)
    if relax:
        raw = surf.vertices.copy() if raw is None else raw[used]
        surf.vertices = _verified_smoothing(
            raw, tangential_relax(surf.vertices, surf.faces), surf.faces, info)
    if enclosed_volume(surf.vertices, surf.faces) < 0:
        surf.faces = surf.faces[:, ::-1].copy()
    return surf


def drop_degenerate(surface: Surface) -> Surface:
    """Remove faces that repeat a vertex index (flying edges can emit them after merging)."""
    return _drop_degenerate(surface)[0]


def _drop_degenerate(surface: Surface) -> tuple:
    """(:func:`drop_degenerate`, the indices of the vertices it keeps, or a slice of all)."""
    f = surface.faces
    ok = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    if ok.all():
        return surface, slice(None)
    faces = f[ok]
    used, inv = np.unique(faces, return_inverse=True)
    return Surface(surface.vertices[used], inv.reshape(-1, 3), surface.coordinate_system), used


def _verified_smoothing(raw: np.ndarray, smooth: np.ndarray, faces: np.ndarray,
                        info: Optional[dict]) -> np.ndarray:
    """``smooth`` (n, 3), the smoothed and relaxed vertices of a contour whose flying-edges
    vertices were ``raw`` (n, 3) on the same ``faces``, free of self-intersections: where the
    smoothing made the surface pass through itself (in a narrow canal or between two close
    sheets), the vertices of the crossing faces go back toward ``raw`` (half-way first,
    :func:`..mesh.operators.safe_update`); ``raw`` itself when that does not clear them."""
    from ..mesh.checks import find_self_intersections
    from ..mesh.operators import safe_update

    if not len(find_self_intersections(smooth, faces, max_pairs=1)):
        return smooth
    out, ok, _ = safe_update(raw, smooth, faces, halvings=SMOOTHING_BACKOFF_HALVINGS)
    if not ok:
        out = raw
    if info is not None:
        info["smoothing_backed_off"] = info.get("smoothing_backed_off", 0) + int(
            np.any(out != smooth, axis=1).sum())
        info["smoothing_dropped"] = info.get("smoothing_dropped", False) or not ok
    return out


def initial_surface(points: np.ndarray, normals: np.ndarray, depth: int,
                    edge_length: float, fusion: Optional[Fusion] = None,
                    helper: Optional[PoissonHelper] = None) -> tuple[Surface, Surface]:
    """M0: Poisson on the oriented visible points, remeshed closed and near-uniform.

    Parameters
    ----------
    points, normals : (k, 3) float arrays
        Visible points in grid millimetres (x-y-z) and their outward unit normals.
    depth : int
        Poisson octree depth.
    edge_length : float
        Target mean edge length d* in mm.
    fusion : Fusion, optional
        Evidence joined to the Poisson surface when it is remeshed (see :func:`remesh`).
    helper : PoissonHelper, optional
        Where the Poisson surface is computed (see :func:`poisson_surface`).

    Returns
    -------
    (M0, raw Poisson surface), both in grid millimetres
    """
    raw = poisson_surface(points, normals, depth, helper)
    return remesh(raw, edge_length, fusion=fusion), raw

