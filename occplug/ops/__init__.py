"""Performance-critical operators shared by components (pure PyTorch first; see :mod:`occplug.ops.splat`)."""

from .splat import SplatPlan, SplatPlanCache, build_splat_plan, geometry_key, splat_outer

__all__ = ["SplatPlan", "SplatPlanCache", "build_splat_plan", "geometry_key", "splat_outer"]
