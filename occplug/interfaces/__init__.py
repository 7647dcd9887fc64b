"""The component kinds: small abstract classes every registered component subclasses."""

from .depth_net import DepthAndContext, DepthNet
from .encoder import ImageEncoder, PointEncoder, feature_levels
from .head import Head, OccupancyHead
from .scene import Scene, SceneRepresentation
from .supervision import ModelOutputs, SupervisionSource
from .view_transform import Lifted, ViewTransform

__all__ = [
    "DepthAndContext",
    "DepthNet",
    "Head",
    "ImageEncoder",
    "Lifted",
    "ModelOutputs",
    "OccupancyHead",
    "PointEncoder",
    "Scene",
    "SceneRepresentation",
    "SupervisionSource",
    "ViewTransform",
    "feature_levels",
]
