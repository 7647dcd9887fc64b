"""nuScenes tables -> an occplug index, built once by ``occplug data prepare nuscenes``.

Reads the nuScenes devkit's JSON tables (``<root>/<version>/*.json``: ``scene``, ``sample``,
``sample_data``, ``ego_pose``, ``calibrated_sensor``, ``sensor``, ``sample_annotation``,
``instance``, ``category``; ``lidarseg`` when present) with the devkit's semantics, and writes
everything a training run needs into **one** file, so training never walks the tables again.
``nuscenes-devkit`` itself is not used: its release pins ``numpy < 2``, which cannot be installed
beside occplug's NumPy 2; the few devkit rules needed (keyframe sample data, the ``prev`` chain of
sweeps, box velocities by centred differences) are reimplemented here and named where they are.

The index ``<out>/nuscenes_index.npz`` (``numpy.savez_compressed``, no pickles) holds:

* ``meta``: UTF-8 JSON (as a ``uint8`` array): ``format``, ``version``, ``root``, ``occ_root``,
  ``cameras`` (channel order of the camera axis), ``categories``, ``lidarseg_categories`` (category
  name of each lidarseg id: the ``index`` field of ``category``), ``instances`` (instance tokens;
  a box's track id is its instance's position here), ``splits`` (split -> scene names) and
  ``samples``: per sample (scene-major, temporal order) ``token``, ``scene``, ``frame_index``,
  ``split``, ``lidar`` (``.pcd.bin`` path relative to ``root``), ``cams`` (image paths), ``occ``
  (``labels.npz`` path relative to ``occ_root`` or null), ``lidarseg`` (path or null), ``sweeps``
  (paths of up to ``--sweeps`` earlier LiDAR sweeps, newest first).
* arrays indexed by sample ``s`` (``S`` samples, ``N`` cameras): ``timestamp`` ``(S,)`` int64 µs;
  ``scene_start`` ``(S,)`` int64 µs of the scene's first sample; ``ego_to_global`` ``(S, 4, 4)``
  float64 (the LiDAR keyframe's ego pose); ``lidar_to_ego`` ``(S, 4, 4)``; ``cam_to_ego``
  ``(S, N, 4, 4)``: each camera in the **LiDAR keyframe's ego frame**, i.e.
  ``inv(E_lidar) @ E_cam @ C_cam`` with each sample data's own ego pose, exact for the ego motion
  between the camera's and the LiDAR's timestamps; ``intrinsics`` ``(S, N, 3, 3)``;
  ``image_hw`` ``(S, N, 2)`` int32; ``lidar_origin`` ``(S, 3)`` float64 global LiDAR positions (kept
  for older readers; RayIoU's origins are composed from the poses, see
  :meth:`NuScenesIndex.sequence_lidar_origins`).
* boxes, concatenated over samples with ``box_offsets`` ``(S + 1,)``: ``boxes`` ``(M, 9)``
  float64 in the ego frame (centre, length, width, height, yaw, vx, vy as ``Frame.boxes``;
  nuScenes stores sizes as width, length, height), ``box_labels`` (Occ3D ids by category,
  :data:`~occplug.data.classes.NUSCENES_TO_OCC3D`), ``box_track_ids``, ``box_num_lidar_pts``, ``box_category``
  (index into ``meta.categories``). Velocities follow ``NuScenes.box_velocity``: centred difference of the
  previous and next annotation of the instance (one-sided at the ends), NaN -> 0 when the instance
  has a single annotation or the gap exceeds 1.5 s (3 s centred), as mmdetection3d does.
* sweeps, concatenated with ``sweep_offsets`` ``(S + 1,)``: ``sweep_to_lidar`` ``(Q, 4, 4)``
  float64 (sweep LiDAR frame -> keyframe LiDAR frame through both ego poses) and
  ``sweep_time_lag`` ``(Q,)`` seconds.

The file is written atomically (a temporary file, then a rename) after everything was read and
checked, so an error leaves no index behind. Every bad input raises
:class:`~occplug.data.formats.FormatError` with one line naming the file.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from ..classes import NUSCENES_LIDARSEG_CATEGORIES, nuscenes_to_occ3d
from ..formats import FormatError, read_split_file

__all__ = [
    "CAMERAS",
    "INDEX_FORMAT",
    "INDEX_NAME",
    "OPTIONAL_TABLES",
    "REQUIRED_TABLES",
    "NuScenesIndex",
    "build_index",
    "collect_index",
    "index_path",
    "official_splits",
    "quaternion_to_matrix",
    "matrix_to_quaternion",
    "read_index",
    "split_lists",
]

INDEX_FORMAT = "occplug-nuscenes-index-1"
INDEX_NAME = "nuscenes_index.npz"
#: Camera channels in the order of ``Frame``'s camera axis (those present in the data set are used).
CAMERAS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")
LIDAR = "LIDAR_TOP"
REQUIRED_TABLES = (
    "scene",
    "sample",
    "sample_data",
    "ego_pose",
    "calibrated_sensor",
    "sensor",
    "sample_annotation",
    "instance",
    "category",
)
OPTIONAL_TABLES = ("lidarseg",)

# The official scene splits (nuscenes-devkit ``nuscenes/utils/splits.py``, Apache-2.0), as scene numbers.
_TRAIN = (
    1, 2, 4, 5, 6, 7, 8, 9, 10, 11, 19, 20, 21, 22, 23, 24, 25, 26, 27, 28, 29, 30, 31, 32, 33, 34, 41, 42,
    43, 44, 45, 46, 47, 48, 49, 50, 51, 52, 53, 54, 55, 56, 57, 58, 59, 60, 61, 62, 63, 64, 65, 66, 67, 68,
    69, 70, 71, 72, 73, 74, 75, 76, 120, 121, 122, 123, 124, 125, 126, 127, 128, 129, 130, 131, 132, 133, 134,
    135, 138, 139, 149, 150, 151, 152, 154, 155, 157, 158, 159, 160, 161, 162, 163, 164, 165, 166, 167, 168,
    170, 171, 172, 173, 174, 175, 176, 177, 178, 179, 180, 181, 182, 183, 184, 185, 187, 188, 190, 191, 192,
    193, 194, 195, 196, 199, 200, 202, 203, 204, 206, 207, 208, 209, 210, 211, 212, 213, 214, 218, 219, 220,
    222, 224, 225, 226, 227, 228, 229, 230, 231, 232, 233, 234, 235, 236, 237, 238, 239, 240, 241, 242, 243,
    244, 245, 246, 247, 248, 249, 250, 251, 252, 253, 254, 255, 256, 257, 258, 259, 260, 261, 262, 263, 264,
    283, 284, 285, 286, 287, 288, 289, 290, 291, 292, 293, 294, 295, 296, 297, 298, 299, 300, 301, 302, 303,
    304, 305, 306, 315, 316, 317, 318, 321, 323, 324, 328, 347, 348, 349, 350, 351, 352, 353, 354, 355, 356,
    357, 358, 359, 360, 361, 362, 363, 364, 365, 366, 367, 368, 369, 370, 371, 372, 373, 374, 375, 376, 377,
    378, 379, 380, 381, 382, 383, 384, 385, 386, 388, 389, 390, 391, 392, 393, 394, 395, 396, 397, 398, 399,
    400, 401, 402, 403, 405, 406, 407, 408, 410, 411, 412, 413, 414, 415, 416, 417, 418, 419, 420, 421, 422,
    423, 424, 425, 426, 427, 428, 429, 430, 431, 432, 433, 434, 435, 436, 437, 438, 439, 440, 441, 442, 443,
    444, 445, 446, 447, 448, 449, 450, 451, 452, 453, 454, 455, 456, 457, 458, 459, 461, 462, 463, 464, 465,
    467, 468, 469, 471, 472, 474, 475, 476, 477, 478, 479, 480, 499, 500, 501, 502, 504, 505, 506, 507, 508,
    509, 510, 511, 512, 513, 514, 515, 517, 518, 525, 526, 527, 528, 529, 530, 531, 532, 533, 534, 535, 536,
    537, 538, 539, 541, 542, 543, 544, 545, 546, 566, 568, 570, 571, 572, 573, 574, 575, 576, 577, 578, 580,
    582, 583, 584, 585, 586, 587, 588, 589, 590, 591, 592, 593, 594, 595, 596, 597, 598, 599, 600, 639, 640,
    641, 642, 643, 644, 645, 646, 647, 648, 649, 650, 651, 652, 653, 654, 655, 656, 657, 658, 659, 660, 661,
    662, 663, 664, 665, 666, 667, 668, 669, 670, 671, 672, 673, 674, 675, 676, 677, 678, 679, 681, 683, 684,
    685, 686, 687, 688, 689, 695, 696, 697, 698, 700, 701, 703, 704, 705, 706, 707, 708, 709, 710, 711, 712,
    713, 714, 715, 716, 717, 718, 719, 726, 727, 728, 730, 731, 733, 734, 735, 736, 737, 738, 739, 740, 741,
    744, 746, 747, 749, 750, 751, 752, 757, 758, 759, 760, 761, 762, 763, 764, 765, 767, 768, 769, 786, 787,
    789, 790, 791, 792, 803, 804, 805, 806, 808, 809, 810, 811, 812, 813, 815, 816, 817, 819, 820, 821, 822,
    847, 848, 849, 850, 851, 852, 853, 854, 855, 856, 858, 860, 861, 862, 863, 864, 865, 866, 868, 869, 870,
    871, 872, 873, 875, 876, 877, 878, 880, 882, 883, 884, 885, 886, 887, 888, 889, 890, 891, 892, 893, 894,
    895, 896, 897, 898, 899, 900, 901, 902, 903, 945, 947, 949, 952, 953, 955, 956, 957, 958, 959, 960, 961,
    975, 976, 977, 978, 979, 980, 981, 982, 983, 984, 988, 989, 990, 991, 992, 994, 995, 996, 997, 998, 999,
    1000, 1001, 1002, 1003, 1004, 1005, 1006, 1007, 1008, 1009, 1010, 1011, 1012, 1013, 1014, 1015, 1016,
    1017, 1018, 1019, 1020, 1021, 1022, 1023, 1024, 1025, 1044, 1045, 1046, 1047, 1048, 1049, 1050, 1051,
    1052, 1053, 1054, 1055, 1056, 1057, 1058, 1074, 1075, 1076, 1077, 1078, 1079, 1080, 1081, 1082, 1083,
    1084, 1085, 1086, 1087, 1088, 1089, 1090, 1091, 1092, 1093, 1094, 1095, 1096, 1097, 1098, 1099, 1100,
    1101, 1102, 1104, 1105, 1106, 1107, 1108, 1109, 1110,
)  # fmt: skip
_VAL = (
    3, 12, 13, 14, 15, 16, 17, 18, 35, 36, 38, 39, 92, 93, 94, 95, 96, 97, 98, 99, 100, 101, 102, 103, 104,
    105, 106, 107, 108, 109, 110, 221, 268, 269, 270, 271, 272, 273, 274, 275, 276, 277, 278, 329, 330, 331,
    332, 344, 345, 346, 519, 520, 521, 522, 523, 524, 552, 553, 554, 555, 556, 557, 558, 559, 560, 561, 562,
    563, 564, 565, 625, 626, 627, 629, 630, 632, 633, 634, 635, 636, 637, 638, 770, 771, 775, 777, 778, 780,
    781, 782, 783, 784, 794, 795, 796, 797, 798, 799, 800, 802, 904, 905, 906, 907, 908, 909, 910, 911, 912,
    913, 914, 915, 916, 917, 919, 920, 921, 922, 923, 924, 925, 926, 927, 928, 929, 930, 931, 962, 963, 966,
    967, 968, 969, 971, 972, 1059, 1060, 1061, 1062, 1063, 1064, 1065, 1066, 1067, 1068, 1069, 1070, 1071,
    1072, 1073,
)  # fmt: skip
_TEST = (
    77, 78, 79, 80, 81, 82, 83, 84, 85, 86, 87, 88, 89, 90, 91, 111, 112, 113, 114, 115, 116, 117, 118, 119,
    140, 142, 143, 144, 145, 146, 147, 148, 265, 266, 279, 280, 281, 282, 307, 308, 309, 310, 311, 312, 313,
    314, 333, 334, 335, 336, 337, 338, 339, 340, 341, 342, 343, 481, 482, 483, 484, 485, 486, 487, 488, 489,
    490, 491, 492, 493, 494, 495, 496, 497, 498, 547, 548, 549, 550, 551, 601, 602, 603, 604, 606, 607, 608,
    609, 610, 611, 612, 613, 614, 615, 616, 617, 618, 619, 620, 621, 622, 623, 624, 827, 828, 829, 830, 831,
    833, 834, 835, 836, 837, 838, 839, 840, 841, 842, 844, 845, 846, 932, 933, 935, 936, 937, 938, 939, 940,
    941, 942, 943, 1026, 1027, 1028, 1029, 1030, 1031, 1032, 1033, 1034, 1035, 1036, 1037, 1038, 1039, 1040,
    1041, 1042, 1043,
)  # fmt: skip
_MINI_TRAIN = (
    61, 553, 655, 757, 796, 1077, 1094, 1100,
)  # fmt: skip
_MINI_VAL = (
    103, 916,
)  # fmt: skip


def official_splits(version: str) -> dict[str, set[str]]:
    """``{split: scene names}`` of a nuScenes version (``v1.0-trainval``, ``v1.0-mini``, ``v1.0-test``)."""
    names = lambda nums: {f"scene-{n:04d}" for n in nums}  # noqa: E731
    if version == "v1.0-trainval":
        return {"train": names(_TRAIN), "val": names(_VAL)}
    if version == "v1.0-mini":
        return {"train": names(_MINI_TRAIN), "val": names(_MINI_VAL)}
    if version == "v1.0-test":
        return {"test": names(_TEST)}
    raise FormatError(
        f"unknown nuScenes version '{version}' (official splits exist for v1.0-trainval, v1.0-mini, v1.0-test)"
    )


# ---------------------------------------------------------------------------------------------
# rotations


def quaternion_to_matrix(q: Sequence[float]) -> np.ndarray:
    """``(3, 3)`` float64 rotation of a unit quaternion ``(w, x, y, z)`` (nuScenes / pyquaternion order)."""
    w, x, y, z = (float(v) for v in q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if n == 0:
        raise ValueError("zero quaternion")
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quaternion(r: np.ndarray) -> list[float]:
    """Inverse of :func:`quaternion_to_matrix` (``w >= 0``); ``r`` must be a rotation."""
    r = np.asarray(r, dtype=np.float64)
    t = np.trace(r)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif r[1, 1] > r[2, 2]:
        s = math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    if q[0] < 0:
        q = [-v for v in q]
    n = math.sqrt(sum(v * v for v in q))
    return [v / n for v in q]


def _pose(record: dict[str, Any]) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = quaternion_to_matrix(record["rotation"])
    out[:3, 3] = np.asarray(record["translation"], dtype=np.float64)
    return out


def _inv(pose: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = pose[:3, :3].T
    out[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return out


# ---------------------------------------------------------------------------------------------
# tables


def _load_table(folder: Path, name: str, required: bool = True) -> list[dict[str, Any]] | None:
    path = folder / f"{name}.json"
    if not path.is_file():
        if required:
            raise FormatError(f"{path}: missing nuScenes table '{name}'")
        return None
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise FormatError(f"{path}: not a valid JSON table ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, list) or not all(isinstance(r, dict) and "token" in r for r in data):
        raise FormatError(f"{path}: a nuScenes table is a JSON list of records with a 'token'")
    return data


class _Tables:
    def __init__(self, root: Path, version: str) -> None:
        folder = root / version
        if not folder.is_dir():
            raise FormatError(f"{folder}: no such folder (expected the nuScenes tables of version {version} there)")
        self.folder = folder
        self.rows: dict[str, list[dict[str, Any]]] = {}
        for name in REQUIRED_TABLES:
            self.rows[name] = _load_table(folder, name)  # type: ignore[assignment]
        for name in OPTIONAL_TABLES:
            rows = _load_table(folder, name, required=False)
            if rows is not None:
                self.rows[name] = rows
        self.by_token = {name: {r["token"]: r for r in rows} for name, rows in self.rows.items()}

    def get(self, table: str, token: str, context: str) -> dict[str, Any]:
        try:
            return self.by_token[table][token]
        except KeyError:
            raise FormatError(
                f"{self.folder / (table + '.json')}: no record with token {token!r} (referenced by {context})"
            ) from None

    def field(self, table: str, record: dict[str, Any], key: str) -> Any:
        try:
            return record[key]
        except KeyError:
            raise FormatError(
                f"{self.folder / (table + '.json')}: record {record.get('token')!r} has no field '{key}'"
            ) from None


def _check_split_file(path: Path) -> dict[str, set[str]]:
    return {k: set(v) for k, v in read_split_file(path, "scene names").items()}


@dataclass
class NuScenesIndex:
    """A prepared index (see the module docstring) as read back by :func:`read_index`.

    Attributes:
        path: the index file.
        meta: the decoded ``meta`` JSON.
        arrays: every numeric array, by name.
    """

    path: Path
    meta: dict[str, Any]
    arrays: dict[str, np.ndarray]

    @property
    def samples(self) -> list[dict[str, Any]]:
        """Per-sample records (scene-major, temporal order)."""
        return self.meta["samples"]

    @property
    def cameras(self) -> tuple[str, ...]:
        """Camera channels, in camera-axis order."""
        return tuple(self.meta["cameras"])

    def split_indices(self, split: str) -> list[int]:
        """Indices of the samples of ``split`` (``predict`` = ``val``), in index order."""
        split = "val" if split == "predict" else split
        return [i for i, s in enumerate(self.samples) if s["split"] == split]

    def scene_members(self) -> dict[str, list[int]]:
        """``{scene name: sample indices}`` in temporal order."""
        if not hasattr(self, "_members"):
            members: dict[str, list[int]] = {}
            for i, rec in enumerate(self.samples):
                members.setdefault(rec["scene"], []).append(i)
            self._members = members
        return self._members

    def sequence_lidar_origins(self, sample: int) -> np.ndarray:
        """``(S, 3)`` float64: the LiDAR positions of every sample of ``sample``'s scene, in ``sample``'s
        ego frame (metres) -- the origins RayIoU casts its query rays from.

        The sample's own row is its calibration translation exactly (``lidar_to_ego[:3, 3]``, e.g.
        nuScenes' y = 0.0, a voxel face of the Occ3D grid), never a round trip through the global frame,
        whose rounding (about 1e-14 m) decides on which side of that face a ray starts. Another frame
        ``j``'s LiDAR is ``R_s^T R_j l_j + R_s^T (t_j - t_s)`` (``R, t`` the ego poses, ``l`` the
        calibration translation): the global translations are differenced before anything is rotated,
        so no rounding of their large magnitudes enters, and a frame whose ego pose equals the
        sample's exactly (a parked ego) gets its calibration translation exactly too.
        """
        return lidar_origins_in_ego(
            self.arrays["ego_to_global"],
            self.arrays["lidar_to_ego"],
            self.scene_members()[self.samples[sample]["scene"]],
            sample,
        )


def lidar_origins_in_ego(
    ego_to_global: np.ndarray, lidar_to_ego: np.ndarray, members: Sequence[int], sample: int
) -> np.ndarray:
    """``(len(members), 3)`` float64: the LiDAR position of each of ``members`` in ``sample``'s ego frame.

    Args:
        ego_to_global: ``(S, 4, 4)`` float64 ego poses of all samples.
        lidar_to_ego: ``(S, 4, 4)`` float64 LiDAR calibrations of all samples.
        members: the samples whose origins are wanted (a scene's, in temporal order).
        sample: the sample whose ego frame they are expressed in.

    See :meth:`NuScenesIndex.sequence_lidar_origins` for the arithmetic (exact for ``sample`` itself
    and for frames with the same ego pose).
    """
    members = np.asarray(members, dtype=np.int64)
    ref = ego_to_global[sample]
    rot = ego_to_global[members, :3, :3]
    same = (rot == ref[:3, :3]).all(axis=(1, 2))
    relative = np.where(same[:, None, None], np.eye(3), ref[:3, :3].T @ rot)
    moved = (ego_to_global[members, :3, 3] - ref[:3, 3]) @ ref[:3, :3]
    lidar = lidar_to_ego[members, :3, 3]
    out = np.einsum("sij,sj->si", relative, lidar) + moved
    # R^T R l with R equal is not l in floating point: where the rotation is the sample's, rotate nothing
    out[same] = lidar[same] + moved[same]
    out[members == sample] = lidar_to_ego[sample, :3, 3]
    return out


def index_path(path: str | Path) -> Path:
    """The index file: ``path`` itself, or ``path / nuscenes_index.npz`` for a folder."""
    path = Path(path)
    return path / INDEX_NAME if path.is_dir() or not path.suffix else path


def read_index(path: str | Path) -> NuScenesIndex:
    """Load an index written by :func:`build_index` (``path`` may be its folder).

    Raises:
        FormatError: a missing or foreign file (one line naming it).
    """
    file = index_path(path)
    if not file.is_file():
        raise FormatError(f"{file}: no nuScenes index (build one with: occplug data prepare nuscenes ...)")
    try:
        with np.load(file, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
        meta = json.loads(arrays.pop("meta").tobytes().decode())
    except Exception as exc:  # zip, key, JSON and decode errors all mean "not an index"
        raise FormatError(f"{file}: not a readable occplug nuScenes index ({type(exc).__name__})") from None
    if meta.get("format") != INDEX_FORMAT:
        raise FormatError(f"{file}: index format {meta.get('format')!r}; expected {INDEX_FORMAT!r} (prepare it again)")
    return NuScenesIndex(file, meta, arrays)


def build_index(
    root: str | Path,
    version: str,
    out: str | Path,
    occ_root: str | Path | None = None,
    splits: str | Path = "official",
    sweeps: int = 10,
    check_files: bool = True,
    progress: bool = True,
) -> Path:
    """Read the nuScenes tables under ``root / version`` and write the index into ``out``.

    Args:
        root: the nuScenes data root (holding ``samples/``, ``sweeps/``, ``<version>/``).
        version: ``v1.0-trainval``, ``v1.0-mini``, ``v1.0-test`` or another folder of tables.
        out: folder to write ``nuscenes_index.npz`` into (created if needed).
        occ_root: the Occ3D-nuScenes folder holding ``gts/<scene>/<token>/labels.npz`` (or the ``gts``
            folder itself), or None for no occupancy labels.
        splits: ``official`` (the devkit's scene lists) or a JSON file ``{split: [scene names]}``.
        sweeps: how many earlier LiDAR sweeps to record per sample.
        check_files: check that every image, LiDAR file (keyframes and the recorded sweeps, with
            whole-point sizes), lidarseg file and ``labels.npz`` exists (``labels.npz`` are checked
            whenever ``occ_root`` is given).
        progress: show a progress bar.

    Returns:
        The index file.

    Raises:
        FormatError: a missing table or file, a broken reference, a scene in no split, a scene the split
            names that the tables lack (one line naming the file, as ``occplug data check`` words it).
    """
    index = collect_index(root, version, occ_root, splits, sweeps, progress, split_scenes_present=True)
    if check_files or occ_root is not None:
        root = Path(root)
        for rec in index.samples:
            to_check = [] if rec["occ"] is None or occ_root is None else [Path(occ_root) / rec["occ"]]
            if check_files:
                to_check.extend(
                    root / f for f in (*rec["cams"], rec["lidar"], *([rec["lidarseg"]] if rec["lidarseg"] else []))
                )
            for path in to_check:
                if not path.is_file():
                    what = "Occ3D labels.npz" if path.name == "labels.npz" else "file"
                    raise FormatError(f"{path}: missing {what}")
                if path.name.endswith(".pcd.bin") and path.stat().st_size % 20:
                    raise FormatError(
                        f"{path}: {path.stat().st_size} bytes is not a whole number of 5-float32 points (corrupt .bin?)"
                    )
            for rel in rec["sweeps"] if check_files else ():
                path = root / rel
                if not path.is_file():
                    raise FormatError(
                        f"{path}: missing LiDAR sweep (of sample {rec['token']}; --sweeps 0 records none)"
                    )
                if path.stat().st_size % 20:
                    raise FormatError(
                        f"{path}: {path.stat().st_size} bytes is not a whole number of 5-float32 points (corrupt .bin?)"
                    )
    return _write_index(Path(out), index.meta, index.arrays)


def collect_index(
    root: str | Path,
    version: str,
    occ_root: str | Path | None = None,
    splits: str | Path = "official",
    sweeps: int = 10,
    progress: bool = True,
    progress_delay: float = 0.0,
    split_scenes_present: bool = False,
) -> NuScenesIndex:
    """What :func:`build_index` writes, built in memory from the tables only (no data file is opened).

    Args: as :func:`build_index`; ``progress_delay``: seconds before the progress bar appears;
        ``split_scenes_present``: refuse a split list naming a scene the tables lack (before any sample is read).

    Returns:
        The index; its ``path`` is the folder of tables (``root / version``).

    Raises:
        FormatError: a missing or malformed table, a broken reference, a scene in no split (one line naming the file).
    """
    root = Path(root)
    tables = _Tables(root, version)
    occ = None
    if occ_root is not None:
        occ = Path(occ_root)
        if not occ.is_dir():
            raise FormatError(f"{occ}: no such Occ3D folder")
        occ_gts = occ / "gts" if (occ / "gts").is_dir() else occ
    scene_split = _scene_splits(tables, version, splits)
    if split_scenes_present:
        _require_split_scenes(tables, version, splits, scene_split)
    channel_of = {}
    for cs in tables.rows["calibrated_sensor"]:
        sensor = tables.get(
            "sensor", tables.field("calibrated_sensor", cs, "sensor_token"), f"calibrated_sensor {cs['token']}"
        )
        channel_of[cs["token"]] = tables.field("sensor", sensor, "channel")
    keyframes: dict[str, dict[str, dict[str, Any]]] = {}
    for sd in tables.rows["sample_data"]:
        if sd.get("is_key_frame"):
            channel = channel_of.get(tables.field("sample_data", sd, "calibrated_sensor_token"))
            if channel is None:
                raise FormatError(
                    f"{tables.folder / 'sample_data.json'}: record {sd['token']!r} names an unknown calibrated sensor"
                )
            keyframes.setdefault(sd["sample_token"], {})[channel] = sd
    anns: dict[str, list[dict[str, Any]]] = {}
    for ann in tables.rows["sample_annotation"]:
        anns.setdefault(tables.field("sample_annotation", ann, "sample_token"), []).append(ann)
    lidarseg = {r["sample_data_token"]: r["filename"] for r in tables.rows.get("lidarseg", [])}
    instances = [r["token"] for r in tables.rows["instance"]]
    instance_index = {t: i for i, t in enumerate(instances)}
    categories = [r["name"] for r in tables.rows["category"]]
    seg_index = {int(r["index"]): r["name"] for r in tables.rows["category"] if isinstance(r.get("index"), int)}
    lidarseg_names = (
        [seg_index.get(i, "noise") for i in range(max(seg_index) + 1)]
        if seg_index
        else list(NUSCENES_LIDARSEG_CATEGORIES)
    )
    category_index = {r["token"]: i for i, r in enumerate(tables.rows["category"])}
    instance_category = {r["token"]: category_index.get(r.get("category_token"), -1) for r in tables.rows["instance"]}

    ordered: list[tuple[dict[str, Any], int]] = []
    for scene in sorted(tables.rows["scene"], key=lambda s: s.get("name", "")):
        token = tables.field("scene", scene, "first_sample_token")
        k = 0
        while token:
            sample = tables.get("sample", token, f"scene {scene.get('name')}")
            ordered.append((sample, k))
            token = sample.get("next", "")
            k += 1
    present = set.intersection(*(set(keyframes.get(s["token"], {})) for s, _ in ordered)) if ordered else set()
    cameras = [c for c in CAMERAS if c in present]
    if LIDAR not in present:
        raise FormatError(f"{tables.folder / 'sample_data.json'}: not every sample has a {LIDAR} keyframe")
    if not cameras:
        raise FormatError(f"{tables.folder / 'sample_data.json'}: no camera channel is present in every sample")

    records: list[dict[str, Any]] = []
    cols: dict[str, list[Any]] = {
        k: []
        for k in (
            "timestamp",
            "scene_start",
            "ego_to_global",
            "lidar_to_ego",
            "cam_to_ego",
            "intrinsics",
            "image_hw",
            "lidar_origin",
        )
    }
    boxes: list[np.ndarray] = []
    box_cols: dict[str, list[Any]] = {
        k: [] for k in ("box_labels", "box_track_ids", "box_num_lidar_pts", "box_category")
    }
    box_offsets, sweep_offsets = [0], [0]
    sweep_to_lidar: list[np.ndarray] = []
    sweep_lag: list[float] = []
    scene_start = 0
    for sample, frame_index in tqdm(
        ordered, desc="nuScenes index", unit="sample", disable=not progress, delay=progress_delay
    ):
        scene = tables.get("scene", sample["scene_token"], f"sample {sample['token']}")
        name = scene["name"]
        if frame_index == 0:
            scene_start = int(sample["timestamp"])
        data = keyframes[sample["token"]]
        lidar_sd = data[LIDAR]
        ego = _pose(tables.get("ego_pose", lidar_sd["ego_pose_token"], f"sample_data {lidar_sd['token']}"))
        lidar = _pose(
            tables.get("calibrated_sensor", lidar_sd["calibrated_sensor_token"], f"sample_data {lidar_sd['token']}")
        )
        ego_inv = _inv(ego)
        cam_poses, ks, hws, cam_files = [], [], [], []
        for cam in cameras:
            sd = data[cam]
            cal = tables.get("calibrated_sensor", sd["calibrated_sensor_token"], f"sample_data {sd['token']}")
            cam_ego = _pose(tables.get("ego_pose", sd["ego_pose_token"], f"sample_data {sd['token']}"))
            cam_poses.append(ego_inv @ cam_ego @ _pose(cal))
            k = np.asarray(cal.get("camera_intrinsic") or [], dtype=np.float64)
            if k.shape != (3, 3):
                raise FormatError(
                    f"{tables.folder / 'calibrated_sensor.json'}: camera {cal['token']!r} has no 3x3 camera_intrinsic"
                )
            ks.append(k)
            hws.append([int(sd.get("height", 0)), int(sd.get("width", 0))])
            cam_files.append(sd["filename"])
        sweep_files = []
        prev = lidar_sd.get("prev", "")
        while prev and len(sweep_files) < sweeps:
            sw = tables.get("sample_data", prev, f"sample_data {lidar_sd['token']} (prev)")
            sw_ego = _pose(tables.get("ego_pose", sw["ego_pose_token"], f"sample_data {sw['token']}"))
            sw_lidar = _pose(
                tables.get("calibrated_sensor", sw["calibrated_sensor_token"], f"sample_data {sw['token']}")
            )
            sweep_to_lidar.append(_inv(lidar) @ ego_inv @ sw_ego @ sw_lidar)
            sweep_lag.append((int(lidar_sd["timestamp"]) - int(sw["timestamp"])) * 1e-6)
            sweep_files.append(sw["filename"])
            prev = sw.get("prev", "")
        sweep_offsets.append(len(sweep_to_lidar))
        for ann in anns.get(sample["token"], []):
            boxes.append(_box_in_ego(tables, ann, ego))
            box_cols["box_labels"].append(_occ3d_label(categories, instance_category.get(ann["instance_token"], -1)))
            box_cols["box_track_ids"].append(instance_index.get(ann["instance_token"], -1))
            box_cols["box_num_lidar_pts"].append(int(ann.get("num_lidar_pts", -1)))
            box_cols["box_category"].append(instance_category.get(ann["instance_token"], -1))
        box_offsets.append(len(boxes))
        occ_file = None
        if occ is not None:
            rel = Path(name) / sample["token"] / "labels.npz"
            occ_file = str((occ_gts / rel).relative_to(occ))
        seg = lidarseg.get(lidar_sd["token"])
        records.append(
            {
                "token": sample["token"],
                "scene": name,
                "frame_index": frame_index,
                "split": scene_split[name],
                "lidar": lidar_sd["filename"],
                "cams": cam_files,
                "occ": occ_file,
                "lidarseg": seg,
                "sweeps": sweep_files,
            }
        )
        cols["timestamp"].append(int(sample["timestamp"]))
        cols["scene_start"].append(scene_start)
        cols["ego_to_global"].append(ego)
        cols["lidar_to_ego"].append(lidar)
        cols["cam_to_ego"].append(np.stack(cam_poses))
        cols["intrinsics"].append(np.stack(ks))
        cols["image_hw"].append(hws)
        cols["lidar_origin"].append((ego @ lidar)[:3, 3])
    s = len(records)
    arrays: dict[str, np.ndarray] = {
        "timestamp": np.asarray(cols["timestamp"], dtype=np.int64).reshape(s),
        "scene_start": np.asarray(cols["scene_start"], dtype=np.int64).reshape(s),
        "ego_to_global": np.asarray(cols["ego_to_global"], dtype=np.float64).reshape(s, 4, 4),
        "lidar_to_ego": np.asarray(cols["lidar_to_ego"], dtype=np.float64).reshape(s, 4, 4),
        "cam_to_ego": np.asarray(cols["cam_to_ego"], dtype=np.float64).reshape(s, len(cameras), 4, 4),
        "intrinsics": np.asarray(cols["intrinsics"], dtype=np.float64).reshape(s, len(cameras), 3, 3),
        "image_hw": np.asarray(cols["image_hw"], dtype=np.int32).reshape(s, len(cameras), 2),
        "lidar_origin": np.asarray(cols["lidar_origin"], dtype=np.float64).reshape(s, 3),
        "box_offsets": np.asarray(box_offsets, dtype=np.int64),
        "boxes": np.asarray(boxes, dtype=np.float64).reshape(-1, 9),
        "box_labels": np.asarray(box_cols["box_labels"], dtype=np.int64),
        "box_track_ids": np.asarray(box_cols["box_track_ids"], dtype=np.int64),
        "box_num_lidar_pts": np.asarray(box_cols["box_num_lidar_pts"], dtype=np.int64),
        "box_category": np.asarray(box_cols["box_category"], dtype=np.int64),
        "sweep_offsets": np.asarray(sweep_offsets, dtype=np.int64),
        "sweep_to_lidar": np.asarray(sweep_to_lidar, dtype=np.float64).reshape(-1, 4, 4),
        "sweep_time_lag": np.asarray(sweep_lag, dtype=np.float64),
    }
    meta = {
        "format": INDEX_FORMAT,
        "version": version,
        "root": str(root.resolve()),
        "occ_root": None if occ is None else str(occ.resolve()),
        "cameras": cameras,
        "categories": categories,
        "lidarseg_categories": lidarseg_names,
        "instances": instances,
        "splits": {k: sorted(n for n, sp in scene_split.items() if sp == k) for k in ("train", "val", "test")},
        "samples": records,
    }
    return NuScenesIndex(tables.folder, meta, arrays)


def split_lists(version: str, splits: str | Path) -> tuple[dict[str, set[str]], str]:
    """``({split: scene names}, description)`` of ``official`` (the lists of ``version``) or a split JSON file.

    Raises:
        FormatError: an unknown version, or a missing or malformed split file (one line naming it).
    """
    source = str(splits)
    if source == "official":
        return official_splits(version), f"the official {version} split"
    return _check_split_file(Path(source)), source


def missing_split_scenes(
    lists: dict[str, set[str]], present: dict[str, Sequence[str]]
) -> tuple[list[tuple[str, str]], int]:
    """``([(split, scene)], named)``: the scenes the split lists name that ``present`` (an index's
    ``meta["splits"]``) lacks in that split, in split then name order, and how many scenes the lists name."""
    missing = [
        (split, name)
        for split in sorted(lists)
        for name in sorted(lists[split])
        if name not in set(present.get(split, ()))
    ]
    return missing, sum(len(names) for names in lists.values())


def _require_split_scenes(tables: _Tables, version: str, splits: str | Path, scene_split: dict[str, str]) -> None:
    """Raise the line ``occplug data check nuscenes`` reports for a scene the split lists name but the tables lack."""
    lists, where = split_lists(version, splits)
    present = {split: [n for n, s in scene_split.items() if s == split] for split in lists}
    missing, named = missing_split_scenes(lists, present)
    if missing:
        split, name = missing[0]
        raise FormatError(
            f"{tables.folder / 'scene.json'}: scene {name} of the {split} split is missing "
            f"({len(missing)} of {named} scenes of {where} affected)"
        )


def _scene_splits(tables: _Tables, version: str, splits: str | Path) -> dict[str, str]:
    lists, where = split_lists(version, splits)
    out = {}
    missing = []
    for scene in tables.rows["scene"]:
        name = tables.field("scene", scene, "name")
        found = [k for k, names in lists.items() if name in names]
        if len(found) > 1:
            raise FormatError(f"{where}: scene {name} is in several splits ({', '.join(found)})")
        if not found:
            missing.append(name)
        else:
            out[name] = found[0]
    if missing:
        more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
        raise FormatError(
            f"{tables.folder / 'scene.json'}: scene(s) {', '.join(sorted(missing)[:3])}{more} are in no split of "
            f"{where}; pass --splits FILE (a JSON {{split: [scene names]}})"
        )
    return out


def _occ3d_label(categories: list[str], category: int) -> int:
    return nuscenes_to_occ3d(categories[category]) if 0 <= category < len(categories) else 0


def _box_in_ego(tables: _Tables, ann: dict[str, Any], ego: np.ndarray) -> np.ndarray:
    """``(9,)`` box of an annotation in the ego frame of ``ego`` (see the module docstring)."""
    try:
        centre = np.asarray(ann["translation"], dtype=np.float64)
        w, l, h = (float(v) for v in ann["size"])  # noqa: E741
        rot = quaternion_to_matrix(ann["rotation"])
    except (KeyError, ValueError, TypeError):
        raise FormatError(
            f"{tables.folder / 'sample_annotation.json'}: record {ann.get('token')!r} lacks a valid "
            "translation, size or rotation"
        ) from None
    r_inv = ego[:3, :3].T
    c = r_inv @ (centre - ego[:3, 3])
    r = r_inv @ rot
    yaw = math.atan2(r[1, 0], r[0, 0])
    yaw = yaw - 2 * math.pi * math.floor((yaw + math.pi) / (2 * math.pi))
    v = r_inv @ _velocity(tables, ann)
    return np.array([c[0], c[1], c[2], l, w, h, yaw, v[0], v[1]])


def _velocity(tables: _Tables, ann: dict[str, Any], max_time_diff: float = 1.5) -> np.ndarray:
    """``NuScenes.box_velocity`` in the global frame; NaN (no estimate) -> 0, as mmdetection3d does."""
    has_prev, has_next = bool(ann.get("prev")), bool(ann.get("next"))
    if not has_prev and not has_next:
        return np.zeros(3)
    first = tables.get("sample_annotation", ann["prev"], f"sample_annotation {ann['token']}") if has_prev else ann
    last = tables.get("sample_annotation", ann["next"], f"sample_annotation {ann['token']}") if has_next else ann
    t_last = 1e-6 * tables.get("sample", last["sample_token"], "sample_annotation")["timestamp"]
    t_first = 1e-6 * tables.get("sample", first["sample_token"], "sample_annotation")["timestamp"]
    dt = t_last - t_first
    if has_prev and has_next:
        max_time_diff *= 2
    if dt <= 0 or dt > max_time_diff:
        return np.zeros(3)
    return (np.asarray(last["translation"], dtype=np.float64) - np.asarray(first["translation"], dtype=np.float64)) / dt


def _write_index(out: Path, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    target = out / INDEX_NAME
    fd, tmp = tempfile.mkstemp(prefix=f".{INDEX_NAME}.", suffix=".tmp.npz", dir=out)
    os.close(fd)
    try:
        payload = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
        np.savez_compressed(tmp, meta=payload, **arrays)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return target
