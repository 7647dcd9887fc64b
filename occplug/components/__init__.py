"""The core's generic, method-free components (registered by :mod:`occplug.builtin`).

========================  ==================  ==========================
registry name             kind                class
========================  ==================  ==========================
``small_cnn``             encoder             :class:`SmallCNN`
``timm``                  encoder             :class:`TimmEncoder`
``lss``                   view_transform      :class:`LSSViewTransform`
``backward_projection``   view_transform      :class:`BackwardProjection`
``voxel_points``          point_encoder       :class:`VoxelPoints`
``plain``                 depth_net           :class:`PlainDepthNet`
``camera_aware``          depth_net           :class:`CameraAwareDepthNet`
``oracle_depth``          depth_net           :class:`OracleDepthNet`
``dense_voxels``          scene               :class:`DenseVoxels`
``voxel_classifier``      head                :class:`VoxelClassifier`
``voxel_ce``              supervision         :class:`VoxelCrossEntropy`
``lidar_depth``           supervision         :class:`LidarDepthSupervision`
========================  ==================  ==========================
"""

from .depth_nets import CameraAwareDepthNet, DepthAndContext, DepthNet, OracleDepthNet, PlainDepthNet
from .depth_supervision import LidarDepthSupervision
from .encoders import SmallCNN, TimmEncoder
from .heads import VoxelClassifier
from .point_encoders import VoxelPoints
from .scenes import DenseVoxels, DenseVoxelScene
from .supervision import VoxelCrossEntropy
from .view_transforms import BackwardProjection, LSSViewTransform, build_depth_net, depth_bin_centers, splat

__all__ = [
    "BackwardProjection",
    "CameraAwareDepthNet",
    "DenseVoxelScene",
    "DenseVoxels",
    "DepthAndContext",
    "DepthNet",
    "LSSViewTransform",
    "LidarDepthSupervision",
    "OracleDepthNet",
    "PlainDepthNet",
    "SmallCNN",
    "TimmEncoder",
    "VoxelClassifier",
    "VoxelCrossEntropy",
    "VoxelPoints",
    "build_depth_net",
    "depth_bin_centers",
    "splat",
]
