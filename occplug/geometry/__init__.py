"""Exact geometry: grids, rigid transforms, cameras, rays, volume warping, contraction."""

from .cameras import effective_intrinsics, pixel_centers, project_to_image, unproject_from_image
from .contraction import Contraction, contract, uncontract
from .grid import GridSpec
from .raycast import first_hit, first_hits, observed_mask, traversed_mask
from .rays import camera_rays, lidar_ray_directions
from .transforms import invert_pose, make_pose, relative_pose, rotation_z, transform_points, wrap_angle, yaw_of
from .volumes import class_fractions, sample_volume, warp_volume

__all__ = [
    "Contraction",
    "GridSpec",
    "camera_rays",
    "class_fractions",
    "contract",
    "effective_intrinsics",
    "first_hit",
    "first_hits",
    "invert_pose",
    "lidar_ray_directions",
    "make_pose",
    "observed_mask",
    "pixel_centers",
    "project_to_image",
    "relative_pose",
    "rotation_z",
    "sample_volume",
    "transform_points",
    "traversed_mask",
    "uncontract",
    "unproject_from_image",
    "wrap_angle",
    "warp_volume",
    "yaw_of",
]
