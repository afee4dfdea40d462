"""BoneWatertightLib: watertight 2-manifold bone surfaces from CT (pure-Python core).

Method: "Watertight 2-manifold 3D bone surface model reconstruction from CT images based on
visual hyper-spherical mapping" (two-step thresholding, hyper-spherical visible points, Poisson,
iterative Laplacian deformation). Public surface: :func:`reconstruct`, :class:`Parameters` and
the error types; the stages are in :mod:`BoneWatertightLib.stages` in
pipeline order. Heavy modules (vtk, the pipeline) are imported only when used.
"""

__version__ = "0.1.0"

from .errors import *  # noqa: F401,F403  (the exception types are part of the API)
from .params import SCHEMA, Parameters  # noqa: F401


def reconstruct(*args, **kwargs):
    """See :func:`BoneWatertightLib.pipeline.reconstruct` (imported lazily: it pulls in vtk)."""
    from .pipeline import reconstruct as _reconstruct

    return _reconstruct(*args, **kwargs)
