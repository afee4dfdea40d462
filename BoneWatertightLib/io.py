"""Reading CT volumes and segments, writing and reading surface files.

Outside Slicer the library works in physical LPS coordinates like ITK. Every surface file
states its coordinate system the way 3D Slicer does (``SPACE=LPS`` / ``SPACE=RAS`` in the STL
header, a PLY or OBJ comment, a ``SPACE`` field-data string in VTP/VTK), so Slicer and
:func:`read_surface` put the model back in the right place. Every file is written atomically:
a temporary file in the destination folder is renamed over the target only once it is complete.
"""

from __future__ import annotations

import contextlib
import csv
import os
import re
import tempfile
from typing import Optional, Tuple, Union

import numpy as np
import SimpleITK as sitk

from .errors import EmptySegmentError, InputError, VolumeTypeError
from .mesh import Surface, from_polydata, to_polydata

PathLike = Union[str, os.PathLike]

SURFACE_EXTENSIONS = (".stl", ".ply", ".vtp", ".vtk", ".obj")
COORDINATE_SYSTEMS = ("LPS", "RAS")

# Integer volumes with no negative value and fewer distinct values than LABEL_MAP_FEW are label
# maps, not CT. Up to LABEL_MAP_MANY values they are label maps when 0 (background) is the most
# frequent value: multi-organ label maps (TotalSegmentator: up to 117 classes) look like that,
# while a noisy CT crop without air can have ~100 distinct values but is never mostly exact 0.
LABEL_MAP_FEW = 16
LABEL_MAP_MANY = 256

_SPACE_RE = re.compile(r"SPACE\s*=\s*(LPS|RAS)", re.IGNORECASE)


# ----------------------------------------------------------------------------------------
# atomic writes

@contextlib.contextmanager
def atomic_path(path: PathLike):
    """Yield a temporary path beside ``path``; rename it onto ``path`` only on success.

    The temporary file keeps the target's extension because some writers choose the format
    by extension. On any exception (including KeyboardInterrupt) it is removed.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise InputError(f"Output folder does not exist: {folder}")
    base = os.path.basename(path)
    ext = _extension(base) or os.path.splitext(base)[1]
    fd, tmp = tempfile.mkstemp(prefix=f".{base}.", suffix=f".part{ext}", dir=folder)
    os.close(fd)
    try:
        yield tmp
        if not os.path.exists(tmp) or os.path.getsize(tmp) == 0:
            raise OSError(f"Writing {path} produced no data.")
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def write_text(text: str, path: PathLike) -> None:
    """Write a text file atomically (reports, summaries)."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as f:
            f.write(text)


def _extension(name: str) -> str:
    """Lower-case extension, with the double extensions this module knows (.seg.nrrd, .nii.gz)."""
    low = os.fspath(name).lower()
    for double in (".seg.nrrd", ".nii.gz"):
        if low.endswith(double):
            return double
    return os.path.splitext(low)[1]


# ----------------------------------------------------------------------------------------
# CT volumes

def dicom_series(folder: PathLike) -> dict:
    """Series instance UID -> sorted file names of every DICOM series directly in ``folder``."""
    folder = os.fspath(folder)
    reader = sitk.ImageSeriesReader()
    series = {}
    for uid in reader.GetGDCMSeriesIDs(folder) or ():
        series[uid] = list(reader.GetGDCMSeriesFileNames(folder, uid))
    return series


def read_ct(path: PathLike, series: Optional[str] = None) -> sitk.Image:
    """Read a CT volume (HU) from any SimpleITK file or a DICOM folder.

    ``series`` picks one series instance UID when a DICOM folder holds several; without it
    such a folder is refused (naming the series) rather than guessing which one is the CT.
    Raises InputError for a missing or unreadable input and VolumeTypeError for anything that
    is not a scalar 3-D grayscale volume.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputError(f"CT not found: {path}")
    if os.path.isdir(path):
        image = _read_dicom_folder(path, series)
    else:
        image = _read_image_file(path, "CT")
    return _validate_ct(image, path)


def _read_image_file(path: str, what: str) -> sitk.Image:
    try:
        return sitk.ReadImage(path)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        detail = next((line for line in first if "ERROR" in line or "Could not" in line), "")
        raise InputError(
            f"Cannot read the {what} file {path}: not an image format SimpleITK can read "
            f"(NRRD, NIfTI, MHA, ...). {detail}".strip()
        ) from None


def _read_dicom_folder(folder: str, series: Optional[str]) -> sitk.Image:
    found = dicom_series(folder)
    if not found:
        raise InputError(
            f"No DICOM series found in folder {folder}. Give the folder that directly holds the "
            "slice files of one CT series, or a volume file (NRRD, NIfTI, MHA)."
        )
    if series is not None:
        if series not in found:
            raise InputError(f"DICOM series {series} is not in {folder}. Series there: "
                             + _describe_series(found))
        uid = series
    elif len(found) > 1:
        raise InputError(
            f"Folder {folder} holds {len(found)} DICOM series: {_describe_series(found)}. "
            "Choose one with --ct-series UID (or move its files to a folder of their own)."
        )
    else:
        uid = next(iter(found))
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(found[uid])
    try:
        return reader.Execute()
    except RuntimeError as exc:
        raise InputError(f"Cannot read DICOM series {uid} in {folder}: "
                         f"{str(exc).strip().splitlines()[-1]}") from None


def _describe_series(found: dict) -> str:
    return "; ".join(f"{uid} ({len(files)} files)" for uid, files in
                     sorted(found.items(), key=lambda item: -len(item[1])))


def _validate_ct(image: sitk.Image, path: str) -> sitk.Image:
    ncomp = image.GetNumberOfComponentsPerPixel()
    if ncomp > 1:
        raise VolumeTypeError(
            f"{path} is a {ncomp}-component (RGB or vector) image, not a CT. Give the grayscale "
            "CT volume in Hounsfield units."
        )
    dim = image.GetDimension()
    if dim == 4:
        if image.GetSize()[3] != 1:
            raise VolumeTypeError(
                f"{path} is a 4-D image ({'x'.join(map(str, image.GetSize()))}), e.g. a time "
                "series. Extract the one 3-D CT frame you want and give that."
            )
        image = _drop_last_axis(image)
        dim = 3
    if dim != 3 or min(image.GetSize()) < 2:
        raise VolumeTypeError(
            f"{path} is a 2-D image ({'x'.join(map(str, image.GetSize()))}); a 3-D CT volume "
            "is needed. For DICOM, give the folder holding all slices of the series."
        )
    if _looks_like_label_map(image):
        values = np.unique(sitk.GetArrayViewFromImage(image))
        raise VolumeTypeError(
            f"{path} looks like a label map (integer values {_short_list(values)}), not a CT. "
            "Give the CT volume as --ct and the label map as --seg."
        )
    return image


def _looks_like_label_map(image: sitk.Image) -> bool:
    if image.GetPixelID() not in (sitk.sitkUInt8, sitk.sitkInt8, sitk.sitkUInt16,
                                  sitk.sitkInt16, sitk.sitkUInt32, sitk.sitkInt32,
                                  sitk.sitkUInt64, sitk.sitkInt64):
        return False
    stats = sitk.MinimumMaximumImageFilter()
    stats.Execute(image)
    # CT in HU has air near -1000: a negative minimum settles it without a full np.unique.
    if stats.GetMinimum() < 0:
        return False
    if stats.GetMaximum() - stats.GetMinimum() > 10000:
        return False
    values, counts = np.unique(sitk.GetArrayViewFromImage(image), return_counts=True)
    if len(values) < LABEL_MAP_FEW:
        return True
    return len(values) <= LABEL_MAP_MANY and values[np.argmax(counts)] == 0


def _drop_last_axis(image: sitk.Image) -> sitk.Image:
    size = list(image.GetSize())
    size[3] = 0
    return sitk.Extract(image, size, [0, 0, 0, 0])


def _short_list(values, limit: int = 20) -> str:
    values = [int(v) if float(v).is_integer() else float(v) for v in values]
    text = ", ".join(str(v) for v in values[:limit])
    if len(values) > limit:
        text += f", ... ({len(values)} in all)"
    return text


# ----------------------------------------------------------------------------------------
# segments

def is_slicer_segmentation(path: PathLike) -> bool:
    """True for a 3D Slicer segmentation file (``.seg.nrrd`` or NRRD with Segment* keys)."""
    path = os.fspath(path)
    if _extension(path) == ".seg.nrrd":
        return True
    if _extension(path) != ".nrrd" or not os.path.isfile(path):
        return False
    reader = sitk.ImageFileReader()
    reader.SetFileName(path)
    try:
        reader.ReadImageInformation()
    except RuntimeError:
        return False
    return reader.HasMetaDataKey("Segment0_ID")


def slicer_segments(image: sitk.Image) -> list:
    """The segments described in a .seg.nrrd header, in file order.

    Each is a dict with ``index``, ``id``, ``name``, ``label_value`` (int) and ``layer`` (int).
    """
    keys = set(image.GetMetaDataKeys())
    segments = []
    i = 0
    while f"Segment{i}_ID" in keys:
        def get(field, default=""):
            key = f"Segment{i}_{field}"
            return image.GetMetaData(key) if key in keys else default
        segments.append({
            "index": i,
            "id": get("ID"),
            "name": get("Name") or get("ID"),
            # Slicer files older than 4.11 have no LabelValue/Layer: one layer, value i + 1.
            "label_value": int(float(get("LabelValue", str(i + 1)))),
            "layer": int(float(get("Layer", "0"))),
        })
        i += 1
    return segments


def read_segment(path: PathLike, label: Union[int, str]) -> Tuple[sitk.Image, str]:
    """Read one segment as a uint8 mask (1 inside) on the segment file's own grid.

    ``path`` is a label map (any integer image; ``label`` is a label value, or a name listed in
    a ``labels.csv`` / ``<file stem>.csv`` beside it with columns value,name) or a Slicer
    ``.seg.nrrd`` (``label`` is a segment name, segment ID or label value).
    Returns (mask, segment name).
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputError(f"Segment file not found: {path}")
    if os.path.isdir(path):
        raise InputError(f"Segment must be a label-map file or a .seg.nrrd, not a folder: {path}")
    label = str(label).strip()
    if not label:
        raise InputError("No label given: pass a label value or a segment name.")
    if is_slicer_segmentation(path):
        image = _read_image_file(path, "segmentation")
        mask, name = _segment_from_slicer(image, label, path)
    else:
        image = _read_image_file(path, "label map")
        mask, name = _segment_from_label_map(image, label, path)
    if not np.any(sitk.GetArrayViewFromImage(mask)):
        raise EmptySegmentError(f"Segment '{name}' in {path} has no voxel. Pick a segment "
                                "that is painted, or paint this one first.")
    return mask, name


def _segment_from_slicer(image: sitk.Image, label: str, path: str) -> Tuple[sitk.Image, str]:
    segments = slicer_segments(image)
    if not segments:
        raise InputError(f"{path} holds no segment (no Segment0_ID in its header).")
    matches = ([s for s in segments if s["name"] == label]
               or [s for s in segments if s["id"] == label]
               or [s for s in segments if s["name"].lower() == label.lower()])
    if not matches and _is_int(label):
        matches = [s for s in segments if s["label_value"] == int(label)]
    if not matches:
        raise InputError(
            f"Segment '{label}' is not in {path}. Available (name / ID / label value): "
            + "; ".join(f"{s['name']} / {s['id']} / {s['label_value']}" for s in segments)
        )
    if len(matches) > 1:
        raise InputError(
            f"'{label}' matches {len(matches)} segments in {path} ("
            + ", ".join(f"{s['name']} ({s['id']})" for s in matches)
            + "). Use the segment ID to pick one."
        )
    seg = matches[0]
    layers = _layers(image, path)
    if not 0 <= seg["layer"] < len(layers):
        raise InputError(f"Segment '{seg['name']}' refers to layer {seg['layer']} but {path} "
                         f"has {len(layers)} layer(s); the file is damaged.")
    mask = sitk.Cast(sitk.Equal(layers[seg["layer"]], seg["label_value"]), sitk.sitkUInt8)
    return mask, seg["name"]


def _layers(image: sitk.Image, path: str) -> list:
    """The 3-D label layers of a segmentation image.

    Slicer writes several layers as a 4-D NRRD whose first axis (kind "list") is the layer;
    ITK reads that as a vector image with one component per layer. A plain 4-D scalar image
    with the layer on its first axis is handled too.
    """
    ncomp = image.GetNumberOfComponentsPerPixel()
    if image.GetDimension() == 3 and ncomp == 1:
        return [image]
    if image.GetDimension() == 3:
        return [sitk.VectorIndexSelectionCast(image, k) for k in range(ncomp)]
    if image.GetDimension() == 4 and ncomp == 1:
        array = sitk.GetArrayFromImage(image)  # (z, y, x, layer)
        spacing, origin = image.GetSpacing()[1:], image.GetOrigin()[1:]
        direction = np.array(image.GetDirection()).reshape(4, 4)[1:, 1:]
        layers = []
        for k in range(array.shape[3]):
            layer = sitk.GetImageFromArray(np.ascontiguousarray(array[..., k]))
            layer.SetSpacing(spacing)
            layer.SetOrigin(origin)
            layer.SetDirection(direction.ravel().tolist())
            layers.append(layer)
        return layers
    raise VolumeTypeError(f"{path} is a {image.GetDimension()}-D image with {ncomp} "
                          "components; expected a 3-D segmentation.")


def _segment_from_label_map(image: sitk.Image, label: str, path: str) -> Tuple[sitk.Image, str]:
    if image.GetNumberOfComponentsPerPixel() > 1 or image.GetDimension() != 3:
        raise VolumeTypeError(
            f"{path} is not a 3-D label map ({image.GetDimension()}-D, "
            f"{image.GetNumberOfComponentsPerPixel()} components). Give a 3-D label map or a "
            "Slicer .seg.nrrd."
        )
    array = sitk.GetArrayViewFromImage(image)
    if array.dtype.kind == "f":
        if not np.all(np.isfinite(array)) or not np.array_equal(array, np.round(array)):
            raise VolumeTypeError(
                f"{path} has non-integer values, so it looks like a CT rather than a label map. "
                "Give the label map (or a .seg.nrrd) as --seg."
            )
    names = _label_names_beside(path)
    if _is_int(label):
        value, name = int(label), names.get(int(label), str(int(label)))
    else:
        by_name = {n.lower(): v for v, n in names.items()}
        if label.lower() not in by_name:
            present = np.unique(array)
            hint = (f" Names in the labels table: {', '.join(names.values())}." if names else
                    " A name can be used when a labels.csv (value,name) is beside the file.")
            raise InputError(f"'{label}' is not a label value of the label map {path}; values "
                             f"present: {_short_list(present[present != 0])}.{hint}")
        value = by_name[label.lower()]
        name = names[value]
    mask = sitk.Cast(sitk.Equal(image, float(value)), sitk.sitkUInt8)
    if not np.any(sitk.GetArrayViewFromImage(mask)):
        present = np.unique(array)
        present = present[present != 0]
        if len(present) and value not in present:
            raise InputError(f"Label {value} is not in the label map {path}; labels present: "
                             f"{_short_list(present)}.")
        raise EmptySegmentError(f"Label map {path} has no voxel with label {value} "
                                "(the label map is empty).")
    return mask, name


def _label_names_beside(path: str) -> dict:
    """value -> name from labels.csv or <stem>.csv beside a label map (empty if none)."""
    folder = os.path.dirname(os.path.abspath(path))
    stem = os.path.basename(path)[: -len(_extension(path))] if _extension(path) else path
    for candidate in (os.path.join(folder, stem + ".csv"), os.path.join(folder, "labels.csv")):
        if os.path.isfile(candidate):
            try:
                with open(candidate, newline="", encoding="utf-8") as f:
                    rows = list(csv.DictReader(f))
                return {int(float(r["value"])): r["name"].strip() for r in rows
                        if r.get("value") not in (None, "") and r.get("name")}
            except (KeyError, ValueError, csv.Error):
                return {}
    return {}


def _is_int(text: str) -> bool:
    return re.fullmatch(r"[+-]?\d+", str(text).strip()) is not None


# ----------------------------------------------------------------------------------------
# surfaces

def write_surface(surface: Surface, path: PathLike, coordinate_system: str = "LPS") -> str:
    """Write ``surface`` to .stl/.ply/.vtp/.vtk/.obj in ``coordinate_system`` (LPS or RAS).

    The surface is converted from its own coordinate system if needed (x and y negated) and
    the file says which system it is in. Point-data arrays are kept in VTP and VTK; STL, OBJ
    and VTK's PLY writer cannot hold them. Returns the path written.
    """
    path = os.fspath(path)
    system = _check_system(coordinate_system)
    ext = _extension(path)
    if ext not in SURFACE_EXTENSIONS:
        raise InputError(f"Unsupported surface file type '{ext or path}'. Use one of: "
                         + ", ".join(SURFACE_EXTENSIONS) + ".")
    out = surface.to_ras() if system == "RAS" else surface.to_lps()
    poly = to_polydata(out)
    with atomic_path(path) as tmp:
        _WRITERS[ext](poly, tmp, system)
    return path


def write_points(points: np.ndarray, path: PathLike, coordinate_system: str = "LPS",
                 source_system: str = "LPS", point_data: Optional[dict] = None) -> str:
    """Write a point cloud (n, 3) as .ply or .vtp (vertices only), tagged with SPACE."""
    path = os.fspath(path)
    system = _check_system(coordinate_system)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3).copy()
    if system != _check_system(source_system):
        points[:, :2] *= -1.0
    ext = _extension(path)
    if ext not in (".ply", ".vtp"):
        raise InputError(f"Point clouds are written as .ply or .vtp, not '{ext}'.")
    import vtk
    from vtk.util import numpy_support as ns

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
    with atomic_path(path) as tmp:
        _WRITERS[ext](poly, tmp, system)
    return path


def _check_system(system: str) -> str:
    system = str(system).upper()
    if system not in COORDINATE_SYSTEMS:
        raise InputError(f"Coordinate system must be LPS or RAS, not '{system}'.")
    return system


def _space_array(system: str):
    import vtk

    arr = vtk.vtkStringArray()
    arr.SetName("SPACE")
    arr.InsertNextValue(system)
    return arr


def _write_stl(poly, path, system):
    import vtk

    writer = vtk.vtkSTLWriter()
    writer.SetInputData(poly)
    writer.SetFileName(path)
    writer.SetFileTypeToBinary()
    # Same text as Slicer's model storage node, so Slicer reads the coordinate system back.
    writer.SetHeader(f"BoneWatertight output. SPACE={system}")
    _run_writer(writer, path)


def _write_ply(poly, path, system):
    import vtk

    from vtk.util import numpy_support as ns

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
    import vtk

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
    import vtk

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
    import vtk

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
    ok = writer.Write()
    if not ok or writer.GetErrorCode():
        raise OSError(f"VTK could not write {path} (error code {writer.GetErrorCode()}).")


_WRITERS = {".stl": _write_stl, ".ply": _write_ply, ".vtp": _write_vtp,
            ".vtk": _write_vtk, ".obj": _write_obj}


def read_surface(path: PathLike, coordinate_system: str = "LPS") -> Surface:
    """Read a surface file and return it in ``coordinate_system`` (LPS by default).

    The coordinate system stated in the file (SPACE tag) is honoured; a file without one is
    taken to be LPS, as 3D Slicer does. The returned Surface's ``coordinate_system`` says
    which system its vertices are in.
    """
    import vtk

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
