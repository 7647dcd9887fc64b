"""occplug-queryocc: QueryOcc (4D query self-supervision on a contracted BEV) as occplug components.

Loaded through the ``occplug`` entry point ``queryocc = occplug_queryocc.plugin``, exactly as a third-party
plugin; it imports only occplug's public API (``occplug.PUBLIC_MODULES``). The same layout in every method plugin:

* ``plugin.py``: the hooks; the registry names (``queryocc_*``) and the classes they build;
* components by kind: ``view_transform.py`` (``queryocc_lift_contract_splat``), ``scene.py`` (``queryocc_bev``),
  ``heads.py`` (``queryocc_decoder``), ``supervision.py`` (``queryocc_query_points``, ``queryocc_render_points``);
* scripts, run as ``python -m occplug_queryocc.<name>``: ``ablate`` (the supervision ablation), ``bench``,
  ``window_coverage``;
* ``configs/`` (addressed as ``queryocc/<name>``), ``README.md`` and ``RESULTS.md``.
"""

from .heads import QueryDecoder
from .scene import DynamicConv2d, QueryOccBev
from .supervision import QuerySupervision, RenderSupervision, sample_queries, supervision_points
from .view_transform import LiftContractSplat, log_linear_depths, visibility

__all__ = [
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
