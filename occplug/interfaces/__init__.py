"""The component kinds: small abstract classes every registered component subclasses."""

from .encoder import ImageEncoder
from .head import DEFAULT_QUERY_CHUNK, Head, OccupancyHead
from .query import QueryResult
from .scene import Scene, SceneRepresentation
from .supervision import ModelOutputs, SupervisionSource
from .view_transform import Lifted, ViewTransform

__all__ = [
    "DEFAULT_QUERY_CHUNK",
    "Head",
    "ImageEncoder",
    "Lifted",
    "ModelOutputs",
    "OccupancyHead",
    "QueryResult",
    "Scene",
    "SceneRepresentation",
    "SupervisionSource",
    "ViewTransform",
]
