"""Exception types of BoneWatertightLib.

Every message says what is wrong and which input or parameter to change, because the
messages are shown verbatim in the Slicer panel, the console and the CLI.
"""


class BoneWatertightError(Exception):
    """Base class of every error this library raises on purpose."""


class InputError(BoneWatertightError, ValueError):
    """The CT, the segment or a parameter cannot be used as given (SPEC §5)."""


class EmptySegmentError(InputError):
    """The rough segment has no voxel (after resampling onto the CT grid)."""


class NoOverlapError(InputError):
    """Segment and CT volume do not overlap in physical space."""


class ThresholdError(InputError):
    """Threshold window out of order, or no voxel of the region in the window."""


class VolumeTypeError(InputError):
    """The volume is not a scalar 3-D CT (label map, RGB, 2-D, 4-D, ...)."""


class BorderError(InputError):
    """The bone is cut by the border of the CT volume."""


class MemoryLimitError(InputError):
    """The requested resample spacing would need more memory than allowed."""


class SeparationError(BoneWatertightError):
    """Erosion never separated the target bone from its neighbours."""


class ReconstructionError(BoneWatertightError):
    """Poisson reconstruction or deformation could not produce a valid surface."""


class SurfaceCheckError(ReconstructionError):
    """A surface failed the watertight 2-manifold checks of SPEC §4.

    ``report`` holds the :class:`~BoneWatertightLib.checks.SurfaceReport` that failed.
    """

    def __init__(self, message, report=None):
        super().__init__(message)
        self.report = report


class DependencyError(BoneWatertightError, ImportError):
    """A required package (open3d) is missing or unusable."""


class CancelledError(BoneWatertightError):
    """The user cancelled the run through the progress callback."""
