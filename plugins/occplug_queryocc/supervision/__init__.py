"""QueryOcc's two supervision sources over one queryable field, one module each: :mod:`.query_points`
(``queryocc_query_points``, the method, and the window's labelled points and sky rays both sources read) and
:mod:`.render_points` (``queryocc_render_points``, its rendering-only rival in the paper's supervision ablation)."""

from .query_points import (
    QuerySet,
    QuerySupervision,
    in_current_frame,
    sample_queries,
    sample_sky_negatives,
    sample_surface_negatives,
    sky_rays,
    supervision_points,
)
from .render_points import RaySet, Rendered, RenderSupervision, render_rays, sample_rays, transmittance_weights

__all__ = [
    "QuerySet",
    "QuerySupervision",
    "RaySet",
    "RenderSupervision",
    "Rendered",
    "in_current_frame",
    "render_rays",
    "sample_queries",
    "sample_rays",
    "sample_sky_negatives",
    "sample_surface_negatives",
    "sky_rays",
    "supervision_points",
    "transmittance_weights",
]
