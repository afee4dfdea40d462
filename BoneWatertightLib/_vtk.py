"""The VTK classes the library's stages and file I/O use, imported from their own modules.

``import vtk`` loads every VTK module: 0.6 s and ~150 MB of resident memory in a command-line
run; the eleven modules below take 0.24 s and 68 MB (measured on the femur phantom's run, whose
peak memory is what issue 19 bounds). Used as ``from .. import _vtk as vtk`` inside functions
(lazily, as the Slicer extension catalogue wants); the pictures (app/render.py) and the MRML
adapter still use the whole ``vtk`` package.
"""

from vtkmodules.util import numpy_support  # noqa: F401
from vtkmodules.vtkCommonCore import (VTK_UNSIGNED_CHAR, reference,  # noqa: F401
                                      vtkDoubleArray, vtkObject, vtkPoints, vtkStringArray)
from vtkmodules.vtkCommonDataModel import (vtkCellArray, vtkCellLocator, vtkFieldData,  # noqa: F401
                                           vtkImageData, vtkPointData, vtkPolyData)
from vtkmodules.vtkCommonMisc import vtkErrorCode  # noqa: F401
from vtkmodules.vtkFiltersCore import (vtkCleanPolyData, vtkFlyingEdges3D,  # noqa: F401
                                       vtkImplicitPolyDataDistance,
                                       vtkPolyDataConnectivityFilter, vtkTriangleFilter,
                                       vtkWindowedSincPolyDataFilter)
from vtkmodules.vtkFiltersGeneral import vtkContourTriangulator  # noqa: F401
from vtkmodules.vtkFiltersModeling import vtkSelectEnclosedPoints  # noqa: F401
from vtkmodules.vtkImagingStencil import vtkImageStencil, vtkPolyDataToImageStencil  # noqa: F401
from vtkmodules.vtkIOGeometry import (vtkOBJReader, vtkOBJWriter, vtkSTLReader,  # noqa: F401
                                      vtkSTLWriter)
from vtkmodules.vtkIOLegacy import vtkPolyDataReader, vtkPolyDataWriter  # noqa: F401
from vtkmodules.vtkIOPLY import vtkPLYReader, vtkPLYWriter  # noqa: F401
from vtkmodules.vtkIOXML import vtkXMLPolyDataReader, vtkXMLPolyDataWriter  # noqa: F401
