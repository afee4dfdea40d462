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

    ``report`` holds the :class:`~BoneWatertightLib.mesh.checks.SurfaceReport` that failed.
    """

    def __init__(self, message, report=None):
        super().__init__(message)
        self.report = report


class PlausibilityError(ReconstructionError):
    """A watertight surface that disagrees with its segment or its neighbours beyond the stated
    bounds (part of the bone missing, grown into a neighbour, no CT edge): the wrong shape.

    ``report`` holds the :class:`~BoneWatertightLib.stages.plausibility.Plausibility` measured.
    """

    def __init__(self, message, report=None):
        super().__init__(message)
        self.report = report


class DependencyError(BoneWatertightError, ImportError):
    """A required package (open3d) is missing or unusable."""


class CancelledError(BoneWatertightError):
    """The user cancelled the run through the progress callback."""


class OutputError(BoneWatertightError, OSError):
    """An output file could not be written (disk full, permission, ...)."""


class CancelledBySignal(KeyboardInterrupt):
    """SIGINT, SIGTERM or SIGHUP arrived (handled like Ctrl-C: outputs aborted, exit 130).

    ``signum`` is the signal's number, ``name`` its name (``"SIGTERM"``).
    """

    def __init__(self, signum: int):
        import signal

        try:
            name = signal.Signals(signum).name
        except ValueError:
            name = f"signal {signum}"
        super().__init__(name)
        self.signum = signum
        self.name = name

    def __reduce__(self):  # travels back from a worker process intact
        return type(self), (self.signum,)


# ----------------------------------------------------------------------------------------
# The one exit-code table of every command line (bonewatertight / python -m BoneWatertightLib,
# its --cases batch, the Slicer batch script and the demo).

EXIT_OK = 0
EXIT_INTERNAL = 1      # an unexpected internal error (a bug: please report it)
EXIT_INPUT = 2         # bad input or usage; the message says what to change
EXIT_FAILED = 3        # the reconstruction failed (batch: at least one case failed)
EXIT_DEPENDENCY = 4    # a dependency or optional feature is missing
EXIT_OUTPUT = 5        # an output could not be written, or another operating-system error
EXIT_PARTIAL = 6       # partly done: of several bones, those that passed are written, others failed
EXIT_CANCELLED = 130   # cancelled (Ctrl-C or the progress callback)

EXIT_CODES = {
    EXIT_OK: "success",
    EXIT_INTERNAL: "internal error",
    EXIT_INPUT: "bad input",
    EXIT_FAILED: "reconstruction failed",
    EXIT_DEPENDENCY: "missing dependency",
    EXIT_OUTPUT: "output or OS error",
    EXIT_PARTIAL: "partly done",
    EXIT_CANCELLED: "cancelled",
}
"""Exit code -> short status (the batch summary's status column)."""


def exit_code_for(exc: BaseException) -> int:
    """The documented exit code of an exception raised while processing a case."""
    if isinstance(exc, (CancelledError, KeyboardInterrupt)):
        return EXIT_CANCELLED
    if isinstance(exc, DependencyError):
        return EXIT_DEPENDENCY
    if isinstance(exc, InputError):
        return EXIT_INPUT
    if isinstance(exc, BoneWatertightError) and not isinstance(exc, OutputError):
        return EXIT_FAILED
    if isinstance(exc, OSError):
        return EXIT_OUTPUT
    return EXIT_INTERNAL


def joint_exit_code(codes: list, n_written: int) -> int:
    """The exit code of a run of several bones: ``codes`` those of the bones that failed,
    ``n_written`` how many were written. EXIT_PARTIAL when some were written and some failed
    (an internal error or a cancel stays what it is); else as for one bone, an input error
    outranking a failed reconstruction."""
    codes = [c for c in codes if c != EXIT_OK]
    if not codes:
        return EXIT_OK
    for code in (EXIT_INTERNAL, EXIT_CANCELLED, EXIT_DEPENDENCY, EXIT_OUTPUT):
        if code in codes:
            return code
    if n_written:
        return EXIT_PARTIAL
    return EXIT_INPUT if EXIT_INPUT in codes else EXIT_FAILED


def one_line(exc: BaseException) -> str:
    """The exception's message on one line."""
    return " ".join(str(exc).split()) or type(exc).__name__
