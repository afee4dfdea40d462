"""File input and output: CT volumes, segments, surfaces, output transactions.

- :mod:`.files`: output transactions (all files of a case or none), atomic writes
  (umask-respecting), injective file-name parts, extensions.
- :mod:`.images`: CT volumes from files or DICOM folders (physical LPS, (z, y, x) arrays),
  checked: header against data size, one DICOM stack, finite voxels.
- :mod:`.segmentations`: one segment of a label map or a 3D Slicer ``.seg.nrrd`` as a mask,
  or all of them as one label image with their names.
- :mod:`.meshes`: surface and point-cloud files that state their coordinate system.
"""

from .files import (OutputTransaction, atomic_path, ensure_folder, extension,  # noqa: F401
                    name_part, write_text)
from .images import check_finite, dicom_series, read_ct  # noqa: F401
from .meshes import (COORDINATE_SYSTEMS, SURFACE_EXTENSIONS, read_surface,  # noqa: F401
                     write_points, write_surface)
from .segmentations import (LabelNames, is_slicer_segmentation, read_label_image,  # noqa: F401
                            read_segment, resolve_label, slicer_segments)
