"""Triangle meshes: the :class:`Surface` container and its conversions, the operators the
stages share (:mod:`.operators`) and the watertight 2-manifold checks (:mod:`.checks`)."""

from .surface import (Surface, enclosed_volume, from_polydata, mean_edge_length,  # noqa: F401
                      surface_area, to_polydata)
from .operators import face_normals, vertex_normals  # noqa: F401
