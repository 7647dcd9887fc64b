"""QueryOcc's hook implementations (the only module that uses ``@occplug.hookimpl``)."""

from __future__ import annotations

from importlib.resources import files
from importlib.resources.abc import Traversable

import occplug


@occplug.hookimpl
def occplug_register_components(registry: occplug.Registry) -> None:
    from .heads import QueryDecoder
    from .scene import QueryOccBev
    from .supervision import QuerySupervision, RenderSupervision
    from .view_transform import LiftContractSplat

    registry.add("view_transform", "queryocc_lift_contract_splat", LiftContractSplat)
    registry.add("scene", "queryocc_bev", QueryOccBev)
    registry.add("head", "queryocc_decoder", QueryDecoder)
    registry.add("supervision", "queryocc_query_points", QuerySupervision)
    registry.add("supervision", "queryocc_render_points", RenderSupervision)


@occplug.hookimpl
def occplug_config_dir() -> Traversable:
    return files("occplug_queryocc") / "configs"
