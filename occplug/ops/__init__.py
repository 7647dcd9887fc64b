"""Performance-critical operators shared by components (pure PyTorch first; see :mod:`occplug.ops.splat`)."""

from .splat import (
    FrustumSplatter,
    PointToIndex,
    SplatPlan,
    SplatPlanCache,
    build_splat_plan,
    feature_cell_centers,
    frustum_points,
    geometry_key,
    splat,
    splat_outer,
    splat_points,
)

__all__ = [
    "FrustumSplatter",
    "PointToIndex",
    "SplatPlan",
    "SplatPlanCache",
    "build_splat_plan",
    "feature_cell_centers",
    "frustum_points",
    "geometry_key",
    "splat",
    "splat_outer",
    "splat_points",
]
