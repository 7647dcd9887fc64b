"""occplug-queryocc: QueryOcc (4D query self-supervision on a contracted BEV) as occplug components.

Loaded through the ``occplug`` entry point ``queryocc = occplug_queryocc.plugin``, exactly as a
third-party plugin; it imports only occplug's public API.
"""

from .bev import DeformableAttention2d, DynamicConv2d, QueryOccBev
from .decoder import QueryDecoder
from .query_supervision import QuerySupervision, sample_queries, supervision_points
from .render_supervision import RenderSupervision
from .view_transform import LiftContractSplat, log_linear_depths, visibility

__all__ = [
    "DeformableAttention2d",
    "DynamicConv2d",
    "LiftContractSplat",
    "QueryDecoder",
    "QueryOccBev",
    "QuerySupervision",
    "RenderSupervision",
    "log_linear_depths",
    "sample_queries",
    "supervision_points",
    "visibility",
]
