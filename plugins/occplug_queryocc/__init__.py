"""occplug-queryocc: QueryOcc (4D query self-supervision on a contracted BEV) as occplug components.

Loaded through the ``occplug`` entry point ``queryocc = occplug_queryocc.plugin``, exactly as a third-party
plugin; it imports only occplug's public API (``occplug.PUBLIC_MODULES``). The same layout in every method plugin:

* ``plugin.py``: the hooks; the registry names (``queryocc_*``) and the classes they build;
* components by kind: ``view_transform.py`` (``queryocc_lift_contract_splat``), ``scene.py`` (``queryocc_bev``),
  ``heads.py`` (``queryocc_decoder``), ``supervision/`` (``query_points.py``: ``queryocc_query_points``;
  ``render_points.py``: ``queryocc_render_points``);
* ``tools/``, run as ``python -m occplug_queryocc.tools.<name>``: ``ablate`` (the supervision ablation), ``bench``,
  ``diagnose``; nothing in ``plugin.py`` imports them;
* ``configs/`` (addressed as ``queryocc/<name>``) and ``README.md``; the measurements are in the repository's
  ``results/queryocc/``, not in the package.
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
