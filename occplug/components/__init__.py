"""The core's generic, method-free components (registered by :mod:`occplug.builtin`).

========================  ==================  ==========================
registry name             kind                class
========================  ==================  ==========================
``small_cnn``             encoder             :class:`SmallCNN`
``timm``                  encoder             :class:`TimmEncoder`
``lss``                   view_transform      :class:`LSSViewTransform`
``backward_projection``   view_transform      :class:`BackwardProjection`
``voxel_points``          point_encoder       :class:`VoxelPoints`
``dense_voxels``          scene               :class:`DenseVoxels`
``voxel_classifier``      head                :class:`VoxelClassifier`
``voxel_ce``              supervision         :class:`VoxelCrossEntropy`
``lidar_depth``           supervision         :class:`LidarDepthSupervision`
========================  ==================  ==========================
"""

from .depth_supervision import LidarDepthSupervision
from .encoders import SmallCNN, TimmEncoder
from .heads import VoxelClassifier
from .point_encoders import VoxelPoints
from .scenes import DenseVoxels, DenseVoxelScene
from .supervision import VoxelCrossEntropy
from .view_transforms import BackwardProjection, LSSViewTransform, splat

__all__ = [
    "BackwardProjection",
    "DenseVoxelScene",
    "DenseVoxels",
    "LSSViewTransform",
    "LidarDepthSupervision",
    "SmallCNN",
    "TimmEncoder",
    "VoxelClassifier",
    "VoxelCrossEntropy",
    "VoxelPoints",
    "splat",
]
