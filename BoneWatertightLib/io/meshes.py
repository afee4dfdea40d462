"""Writing and reading surface files (and point clouds) with their coordinate system.

Outside Slicer the library works in physical LPS coordinates like ITK. Every surface file
states its coordinate system the way 3D Slicer does (``SPACE=LPS`` / ``SPACE=RAS`` in the STL
header, a PLY or OBJ comment, a ``SPACE`` field-data string in VTP/VTK), so Slicer and
:func:`read_surface` put the model back in the right place. Every file is written atomically
(:func:`~BoneWatertightLib.io.files.atomic_path`), or staged into the caller's
:class:`~BoneWatertightLib.io.files.OutputTransaction`.
"""

from __future__ import annotations

import errno
import os
import re
from typing import Optional

import numpy as np

from ..errors import InputError
from ..mesh.surface import Surface, from_polydata, to_polydata
from .files import OutputTransaction, PathLike, atomic_path, extension as _extension

SURFACE_EXTENSIONS = (".stl", ".ply", ".vtp", ".vtk", ".obj")
COORDINATE_SYSTEMS = ("LPS", "RAS")

_SPACE_RE = re.compile(r"SPACE\s*=\s*(LPS|RAS)", re.IGNORECASE)


# ----------------------------------------------------------------------------------------
# surfaces

def write_surface(surface: Surface, path: PathLike, coordinate_system: str = "LPS", *,
                  transaction: Optional[OutputTransaction] = None) -> str:
    """Write ``surface`` to .stl/.ply/.vtp/.vtk/.obj in ``coordinate_system`` (LPS or RAS).

    The surface is converted from its own coordinate system if needed (x and y negated) and
    the file says which system it is in. Point-data arrays are kept in VTP and VTK; STL, OBJ
    and VTK's PLY writer cannot hold them. Returns the path written.

    With ``transaction`` the file is only staged: it appears when the transaction commits.
    A failed write raises OSError (OutputError with a transaction, naming ``path``).
    """
    path = os.fspath(path)
    system = _check_system(coordinate_system)
    ext = _extension(path)
    if ext not in SURFACE_EXTENSIONS:
        raise InputError(f"Unsupported surface file type '{ext or path}'. Use one of: "
                         + ", ".join(SURFACE_EXTENSIONS) + ".")
    out = surface.to_ras() if system == "RAS" else surface.to_lps()
    poly = to_polydata(out)
    _write(path, lambda tmp: _WRITERS[ext](poly, tmp, system), transaction)
    return path


def write_points(points: np.ndarray, path: PathLike, coordinate_system: str = "LPS",
                 source_system: str = "LPS", point_data: Optional[dict] = None, *,
                 transaction: Optional[OutputTransaction] = None) -> str:
    """Write a point cloud (n, 3) as .ply or .vtp (vertices only), tagged with SPACE.

    With ``transaction`` the file is only staged (see :func:`write_surface`).
    """
    path = os.fspath(path)
    system = _check_system(coordinate_system)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3).copy()
    if system != _check_system(source_system):
        points[:, :2] *= -1.0
    ext = _extension(path)
    if ext not in (".ply", ".vtp"):
        raise InputError(f"Point clouds are written as .ply or .vtp, not '{ext}'.")
    from .. import _vtk as vtk
    from .._vtk import numpy_support as ns

    poly = vtk.vtkPolyData()
    vpts = vtk.vtkPoints()
    vpts.SetData(ns.numpy_to_vtk(points, deep=True))
    poly.SetPoints(vpts)
    ids = np.column_stack([np.ones(len(points), np.int64), np.arange(len(points))]).ravel()
    verts = vtk.vtkCellArray()
    verts.ImportLegacyFormat(ns.numpy_to_vtkIdTypeArray(ids, deep=True))
    poly.SetVerts(verts)
    for name, values in (point_data or {}).items():
        arr = ns.numpy_to_vtk(np.ascontiguousarray(values, dtype=np.float64), deep=True)
        arr.SetName(name)
        poly.GetPointData().AddArray(arr)
    _write(path, lambda tmp: _WRITERS[ext](poly, tmp, system), transaction)
    return path


def _write(path, writer, transaction: Optional[OutputTransaction]) -> None:
    """``writer(tmp)`` into a staged file of ``transaction``, or atomically on its own."""
    if transaction is not None:
        transaction.write(path, writer)
        return
    with atomic_path(path) as tmp:
        writer(tmp)


def _check_system(system: str) -> str:
    system = str(system).upper()
    if system not in COORDINATE_SYSTEMS:
        raise InputError(f"Coordinate system must be LPS or RAS, not '{system}'.")
    return system


def _space_array(system: str):
    from .. import _vtk as vtk

    arr = vtk.vtkStringArray()
    arr.SetName("SPACE")
    arr.InsertNextValue(system)
    return arr


def _write_stl(poly, path, system):
    from .. import _vtk as vtk

    writer = vtk.vtkSTLWriter()
    writer.SetInputData(poly)
    writer.SetFileName(path)
    writer.SetFileTypeToBinary()
    # Same text as Slicer's model storage node, so Slicer reads the coordinate system back.
    writer.SetHeader(f"BoneWatertight output. SPACE={system}")
    _run_writer(writer, path)


def _write_ply(poly, path, system):
    from .. import _vtk as vtk

    from .._vtk import numpy_support as ns

    data = vtk.vtkPolyData()
    data.ShallowCopy(poly)
    normals = poly.GetPointData().GetNormals()
    if normals is not None:
        # vtkPLYWriter only writes float32 normals (it skips doubles with a warning).
        as_float = ns.numpy_to_vtk(ns.vtk_to_numpy(normals).astype(np.float32), deep=True)
        as_float.SetName("Normals")
        point_data = vtk.vtkPointData()
        point_data.SetNormals(as_float)
        data.GetPointData().ShallowCopy(point_data)
    writer = vtk.vtkPLYWriter()
    writer.SetInputData(data)
    writer.SetFileName(path)
    writer.SetFileTypeToBinary()
    writer.AddComment(f"SPACE={system}")
    _run_writer(writer, path)


def _write_vtp(poly, path, system):
    from .. import _vtk as vtk

    data = vtk.vtkPolyData()
    data.ShallowCopy(poly)
    field = vtk.vtkFieldData()
    field.AddArray(_space_array(system))
    data.SetFieldData(field)
    writer = vtk.vtkXMLPolyDataWriter()
    writer.SetInputData(data)
    writer.SetFileName(path)
    writer.SetDataModeToAppended()
    writer.SetCompressorTypeToZLib()
    _run_writer(writer, path)


def _write_vtk(poly, path, system):
    from .. import _vtk as vtk

    data = vtk.vtkPolyData()
    data.ShallowCopy(poly)
    field = vtk.vtkFieldData()
    field.AddArray(_space_array(system))
    data.SetFieldData(field)
    writer = vtk.vtkPolyDataWriter()
    writer.SetInputData(data)
    writer.SetFileName(path)
    # Legacy 4.2: readable by VTK < 9 programs and older Slicer versions (as Slicer does).
    writer.SetFileVersion(42)
    writer.SetFileTypeToBinary()
    writer.SetHeader(f"BoneWatertight output. SPACE={system}")
    _run_writer(writer, path)


def _write_obj(poly, path, system):
    from .. import _vtk as vtk

    writer = vtk.vtkOBJWriter()
    writer.SetInputData(poly)
    writer.SetFileName(path)
    _run_writer(writer, path)
    # vtkOBJWriter has no comment option: put the tag first, where vtkOBJReader (and Slicer)
    # collect the leading comment lines.
    with open(path, "r", encoding="utf-8") as f:
        body = f.read()
    with open(path, "w", encoding="utf-8") as f:
        f.write(f"# SPACE={system}\n")
        f.write(body)


def _run_writer(writer, path):
    from .. import _vtk as vtk

    # VTK would print its own error (naming the temporary file) on stderr; the OSError below
    # says what happened instead.
    shown = vtk.vtkObject.GetGlobalWarningDisplay()
    vtk.vtkObject.GlobalWarningDisplayOff()
    try:
        ok = writer.Write()
    finally:
        vtk.vtkObject.SetGlobalWarningDisplay(shown)
    code = writer.GetErrorCode()
    if ok and not code:
        return
    raise vtk_write_error(code, path)


# Free space (bytes) below which a failed write is put down to a full disk.
DISK_FULL_BYTES = 1 << 20


def vtk_write_error(code: int, path) -> OSError:
    """OSError for a VTK writer's error code (below 20000 VTK stores the C errno).

    VTK reports every failed write as "out of disk space"; the file system's free space and
    the process's file-size limit tell a full disk (ENOSPC) from a size limit (EFBIG).
    """
    from .. import _vtk as vtk

    path = os.fspath(path)
    if 0 < code < 20000:
        return OSError(code, os.strerror(code), path)
    if code == vtk.vtkErrorCode.OutOfDiskSpaceError:
        number = errno.ENOSPC
        try:
            stats = os.statvfs(os.path.dirname(os.path.abspath(path)))
            full = stats.f_bavail * stats.f_frsize < DISK_FULL_BYTES
        except (OSError, AttributeError):
            full = True
        if not full and _file_size_limited():
            number = errno.EFBIG
        return OSError(number, os.strerror(number), path)
    text = vtk.vtkErrorCode.GetStringFromErrorCode(code) if code else "unknown error"
    return OSError(f"VTK could not write {path} ({text}, error code {code})")


def _file_size_limited() -> bool:
    try:
        import resource
    except ImportError:  # not POSIX
        return False
    soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
    return soft != resource.RLIM_INFINITY


_WRITERS = {".stl": _write_stl, ".ply": _write_ply, ".vtp": _write_vtp,
            ".vtk": _write_vtk, ".obj": _write_obj}


def read_surface(path: PathLike, coordinate_system: str = "LPS") -> Surface:
    """Read a surface file and return it in ``coordinate_system`` (LPS by default).

    The coordinate system stated in the file (SPACE tag) is honoured; a file without one is
    taken to be LPS, as 3D Slicer does. The returned Surface's ``coordinate_system`` says
    which system its vertices are in.
    """
    from .. import _vtk as vtk

    path = os.fspath(path)
    target = _check_system(coordinate_system)
    if not os.path.isfile(path):
        raise InputError(f"Surface file not found: {path}")
    ext = _extension(path)
    tag = None
    if ext == ".stl":
        reader = vtk.vtkSTLReader()
        reader.SetFileName(path)
        reader.Update()
        tag = _space_in(reader.GetHeader())
    elif ext == ".ply":
        reader = vtk.vtkPLYReader()
        reader.SetFileName(path)
        reader.Update()
        comments = reader.GetComments()
        for i in range(comments.GetNumberOfValues()):
            tag = tag or _space_in(comments.GetValue(i))
    elif ext == ".obj":
        reader = vtk.vtkOBJReader()
        reader.SetFileName(path)
        reader.Update()
        tag = _space_in(reader.GetComment())
    elif ext == ".vtp":
        reader = vtk.vtkXMLPolyDataReader()
        reader.SetFileName(path)
        reader.Update()
    elif ext == ".vtk":
        reader = vtk.vtkPolyDataReader()
        reader.SetFileName(path)
        reader.ReadAllScalarsOn()
        reader.ReadAllFieldsOn()
        reader.Update()
        tag = _space_in(reader.GetHeader())
    else:
        raise InputError(f"Unsupported surface file type '{ext}'. Use one of: "
                         + ", ".join(SURFACE_EXTENSIONS) + ".")
    poly = reader.GetOutput()
    if poly is None or poly.GetNumberOfPoints() == 0:
        raise InputError(f"No surface could be read from {path}.")
    field = poly.GetFieldData()
    space = field.GetAbstractArray("SPACE") if field is not None else None
    if space is not None and space.GetNumberOfValues():
        tag = _space_in("SPACE=" + str(space.GetValue(0))) or tag
    surface = from_polydata(poly, tag or "LPS")
    return surface.to_ras() if target == "RAS" else surface.to_lps()


def _space_in(text) -> Optional[str]:
    match = _SPACE_RE.search(str(text or ""))
    return match.group(1).upper() if match else None
