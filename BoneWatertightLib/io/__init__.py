"""File input and output: CT volumes, segments, surfaces, atomic writes.

- :mod:`.files`: atomic writes (umask-respecting), extensions.
- :mod:`.images`: CT volumes from files or DICOM folders (physical LPS, (z, y, x) arrays).
- :mod:`.segmentations`: one segment of a label map or a 3D Slicer ``.seg.nrrd`` as a mask.
- :mod:`.meshes`: surface and point-cloud files that state their coordinate system.
"""

from .files import atomic_path, ensure_folder, extension, write_text  # noqa: F401
from .images import dicom_series, read_ct  # noqa: F401
from .meshes import (COORDINATE_SYSTEMS, SURFACE_EXTENSIONS, read_surface,  # noqa: F401
                     write_points, write_surface)
from .segmentations import is_slicer_segmentation, read_segment, slicer_segments  # noqa: F401
