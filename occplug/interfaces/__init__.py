"""The component kinds: small abstract classes every registered component subclasses."""

from .depth_net import DepthAndContext, DepthNet
from .encoder import ImageEncoder, PointEncoder, feature_levels
from .head import DEFAULT_QUERY_CHUNK, Head, OccupancyHead
from .query import QueryResult
from .scene import BevScene, DenseVoxelScene, Scene, SceneRepresentation
from .supervision import ModelOutputs, SupervisionSource
from .view_transform import Lifted, ViewTransform

__all__ = [
    "BevScene",
    "DenseVoxelScene",
    "DepthAndContext",
    "DepthNet",
    "DEFAULT_QUERY_CHUNK",
    "Head",
    "ImageEncoder",
    "Lifted",
    "ModelOutputs",
    "OccupancyHead",
    "PointEncoder",
    "QueryResult",
    "Scene",
    "SceneRepresentation",
    "SupervisionSource",
    "ViewTransform",
    "feature_levels",
]
