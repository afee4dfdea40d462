"""The typed parameter object of the pipeline, with the paper's defaults and presets.

Units: HU for thresholds, millimetres for lengths. ``None`` means "choose automatically".
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Optional

from .errors import InputError


@dataclass
class Parameters:
    # --- crop + resample (paper §2.1, §3.1)
    spacing: Optional[float] = None
    """Isotropic resample spacing d in mm. None: auto from the CT (finest in-plane spacing
    divided by 2, clamped to [0.3, 1.0] mm); the paper uses 0.2-0.3 mm for long bones."""
    margin: float = 5.0
    """Margin in mm added around the rough segment's bounding box before cropping."""
    segment_dilation: float = 3.0
    """How far (mm) bone k may extend beyond the rough segment; covers missing chunks."""
    max_memory_gb: float = 4.0
    """Refuse a resample that is estimated to need more than this much memory."""

    # --- hybrid filter (paper §2.1)
    sigma: float = 0.0
    """Gaussian sigma in mm of the hybrid filter; 0 = auto (0.5 * resample spacing)."""
    rho: float = 80.0
    """Percentile of the gradient magnitude: voxels above it are edge voxels that get
    sharpened (toggle-contrast), see filtering.py. 100 disables sharpening."""

    # --- two-step threshold (paper §2.1)
    theta_max: float = 2500.0
    h0: float = 300.0
    ht: float = 150.0
    max_erosions: int = 3
    """m: the most erosions tried to separate bone k from its neighbours."""
    opening: int = 1
    """l: opening iterations on the final masks."""
    closing: int = 2
    """n: closing iterations on the final masks (fills pores and small holes)."""

    # --- visible points (paper §2.2)
    views: int = 14
    """Number of viewpoints: the 6 PCA axis directions plus 8 diagonals (up to 26)."""
    view_distance: float = 20.0
    """Viewpoint distance from the centroid in units of the bone's bounding radius. Far viewpoints
    (20) keep hidden layers 2 mm behind the surface out of the hull at R = 10^3.6 (measured)."""
    log_radius: float = 3.6
    """R = 10**log_radius times the largest point distance from the viewpoint (paper: 3.5-3.8).
    R is relative: the points are scaled to unit max distance before the flip."""

    # --- initial surface M0 (paper §2.3)
    poisson_depth: int = 7
    edge_length: Optional[float] = None
    """Target edge length d* of M0 in mm; None: 1.0 * resample spacing."""

    # --- deformation (paper §2.4, §3.3)
    iterations: int = 8
    """N: number of deformation iterations (paper: 6-10)."""
    alpha: float = 1.0
    beta: float = 1.0
    search_radius: float = 1.5
    """Directional search radius in units of d* (paper: 1 - sqrt(3))."""
    search_offset: float = 0.75
    """|delta| of the search centre along the normal, in units of d* (paper: 0.5 - 1)."""
    refine_edges: bool = True
    """After deformation, move vertices along the normal to the half-maximum edge of the
    filtered CT (sub-voxel). An addition to the paper; off gives the paper's HT surface."""

    edge_level: float = 0.6
    """Where between the outside valley (0) and the bone peak (1) the refined edge sits
    (0.5 = half maximum). 0.6 measured best over the phantoms: thin cortex blurred by the PSF puts
    the half maximum outside the true border (0.7 is best for thin, 0.5 for thick cortex)."""

    keep_intermediates: bool = False

    def validate(self) -> "Parameters":
        """Raise InputError naming the parameter to change; return self."""
        if not (self.ht < self.h0 < self.theta_max):
            raise InputError(
                f"Thresholds out of order: need HT < H0 < theta_max, got HT={self.ht:g}, "
                f"H0={self.h0:g}, theta_max={self.theta_max:g}. Lower HT or raise theta_max."
            )
        if self.spacing is not None and not (0.05 <= self.spacing <= 5.0):
            raise InputError(f"Resample spacing {self.spacing:g} mm is outside 0.05-5 mm.")
        if not 1 <= self.max_erosions <= 10:
            raise InputError("max_erosions (m) must be between 1 and 10.")
        if self.opening < 0 or self.closing < 0:
            raise InputError("opening (l) and closing (n) iterations must be >= 0.")
        if not 1 <= self.views <= 26:
            raise InputError("views must be between 1 and 26.")
        if not 4 <= self.poisson_depth <= 10:
            raise InputError("poisson_depth must be between 4 and 10 (paper: 7).")
        if not 0 <= self.iterations <= 50:
            raise InputError("iterations (N) must be between 0 and 50 (paper: 6-10).")
        if self.alpha < 0 or self.beta < 0:
            raise InputError("alpha and beta must be >= 0.")
        if not 0.5 <= self.search_radius <= 4:
            raise InputError("search_radius must be between 0.5 and 4 (units of d*).")
        if not 1.0 <= self.log_radius <= 6.0:
            raise InputError("log_radius must be between 1 and 6 (paper: 3.5-3.8).")
        if self.margin < 0:
            raise InputError("margin must be >= 0 mm.")
        return self

    def replace(self, **changes) -> "Parameters":
        unknown = set(changes) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise InputError(f"Unknown parameter(s): {', '.join(sorted(unknown))}.")
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


PRESETS = {
    # Paper §3: femur [300, 2500] / [150, 2500], long bones resampled finer than vertebrae.
    "femur": dict(h0=300.0, ht=150.0, theta_max=2500.0, max_erosions=2),
    # Paper Fig. 11: hip bone H0 = 350.
    "hip": dict(h0=350.0, ht=150.0, theta_max=2500.0, max_erosions=3),
    # Short bones / vertebrae: narrow gaps, so erode more and resample finer.
    "vertebra": dict(h0=300.0, ht=150.0, theta_max=2500.0, max_erosions=3, views=18),
}


def preset(name: str, **overrides) -> Parameters:
    """Parameters of a named preset ('femur', 'hip', 'vertebra'), with overrides."""
    key = name.lower().replace("short_bone", "vertebra").replace("short bone", "vertebra")
    if key not in PRESETS:
        raise InputError(f"Unknown preset '{name}'. Choose one of: {', '.join(PRESETS)}.")
    return Parameters(**PRESETS[key]).replace(**overrides)
