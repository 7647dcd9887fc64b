"""The synthetic world written as a SemanticKITTI-shaped tree (semantic scene completion).

:func:`write_semantickitti` writes, per scene, one sequence::

    <out>/sequences/<XX>/
      image_2/<NNNNNN>.png            the front camera (CAM_FRONT), 8-bit RGB, lossless
      velodyne/<NNNNNN>.bin           float32 x, y, z, reflectance in [0, 1] per point (LiDAR frame)
      labels/<NNNNNN>.label           uint32 per point: semantic raw id (low 16 bits), instance 0 (high 16)
      voxels/<NNNNNN>.label           uint16 raw ids per voxel, C order over (X, Y, Z)
      voxels/<NNNNNN>.invalid         bit-packed: voxels no sensor observed (~(mask_lidar | mask_camera))
      voxels/<NNNNNN>.bin             bit-packed: voxels holding a point of this scan
      voxels/<NNNNNN>.occluded        bit-packed: voxels the LiDAR did not observe (~mask_lidar)
      calib.txt                       P0..P3 ([K | 0], the front camera as cam0) and Tr (velodyne -> cam0)
      poses.txt                       per scan, cam0 pose in the sequence's first cam0 frame (3 x 4 row-major)
      times.txt                       per scan, seconds since the sequence start
    <out>/splits.json                 {"train": [sequences], "val": [...], "test": [...]}
    <out>/grid.json                   the voxel grid: {"shape", "range", "voxel_size"} (LiDAR frame;
                                      occplug.data.check.GRID_RECORD, read by occplug data check)
    <out>/pseudo/...                  (optional) pseudo labels of image_2 (see occplug.data.pseudo_labels),
                                      with semantics_mapping.yaml to the SemanticKITTI classes (and the
                                      auxiliary segmenter's semantics_aux/ with semantics_aux_mapping.yaml)

As in SemanticKITTI, scans run at 10 Hz and every 5th scan is labelled: with the world's 2 Hz frames,
frame ``k`` is scan ``5 k`` (other frame rates: stride ``round(10 / fps)``, at least 1); ``poses.txt``
and ``times.txt`` have a line for every scan (in-between poses come from the scene's ego path), the
other files exist for the labelled scans only. Sequences follow the standard split where the scene
counts fit (train 00-07, 09, 10; val 08; test 11-21), else they are numbered 00, 01, ... in split order
and ``splits.json`` is what the reader's ``splits`` argument needs.

The voxel grid is the world's label grid expressed in the LiDAR frame (the synthetic LiDAR is
axis-aligned with the ego frame, so that is a translation): :func:`semantickitti_world` gives a world
whose grid is SemanticKITTI's ``256 x 256 x 32`` at 0.2 m, the reader's default. Occ3D classes map to
the 20 SSC classes by :data:`OCC3D_TO_SSC` (free -> empty; traffic cones and ``others`` have no
SemanticKITTI class and are written as ``other-object``, which the benchmark ignores).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from occplug.context import parse_grid
from occplug.data.check import write_grid_record
from occplug.data.classes import OCC3D_TO_SEMANTIC_KITTI as OCC3D_TO_SSC
from occplug.data.classes import SEMANTIC_KITTI_LEARNING_MAP_INV as LEARNING_MAP_INV
from occplug.data.frame import Frame
from occplug.data.imageio import write_rgb
from occplug.data.semantickitti.format import SPLIT_SEQUENCES as STANDARD_SEQUENCES
from occplug.data.semantickitti.format import SSC_GRID, write_bits, write_raw_labels
from occplug.geometry import GridSpec, invert_pose

from .config import SPLITS, SyntheticWorldConfig
from .dataset import SyntheticDataset, default_cache_dir
from .pseudo import PseudoRealism, SyntheticPseudoLabels, mapping_table
from .render import LIDAR_TO_EGO

__all__ = ["OCC3D_TO_SSC", "STANDARD_SEQUENCES", "lidar_grid", "semantickitti_world", "write_semantickitti"]

_OTHER_OBJECT = 99  # raw id of SemanticKITTI's "other-object" (ignored by the SSC benchmark)


def _raw_lut() -> np.ndarray:
    """SSC class -> raw label id (``learning_map_inv``; 255 -> other-object)."""
    lut = np.full(256, _OTHER_OBJECT, dtype=np.uint16)
    for cls, raw in LEARNING_MAP_INV.items():
        lut[cls] = raw
    return lut


def lidar_grid(config: SyntheticWorldConfig) -> GridSpec:
    """The world's label grid in the LiDAR frame (what the written voxel files cover)."""
    _check_lidar_axes()
    t = LIDAR_TO_EGO[:3, 3].double().tolist()
    r = config.grid.range
    return GridSpec(
        _tidy([r[0] - t[0], r[1] - t[1], r[2] - t[2], r[3] - t[0], r[4] - t[1], r[5] - t[2]]), config.grid.voxel_size
    )


def semantickitti_world(config: SyntheticWorldConfig, grid: GridSpec | dict | None = None) -> SyntheticWorldConfig:
    """``config`` with its label grid set to ``grid`` (LiDAR frame; default SemanticKITTI's SSC grid)."""
    _check_lidar_axes()
    g = SSC_GRID if grid is None else parse_grid(grid)
    t = LIDAR_TO_EGO[:3, 3].double().tolist()
    r = g.range
    ego = GridSpec(_tidy([r[0] + t[0], r[1] + t[1], r[2] + t[2], r[3] + t[0], r[4] + t[1], r[5] + t[2]]), g.voxel_size)
    return config.replace(grid=ego)


def _tidy(values: list[float]) -> list[float]:
    """Round away float noise (-16.94 + 0.94 -> -16.0), so a round trip gives the same grid (and cache key)."""
    return [round(v, 6) + 0.0 for v in values]


def _check_lidar_axes() -> None:
    if not torch.equal(LIDAR_TO_EGO[:3, :3], torch.eye(3)):
        raise ValueError("the SemanticKITTI export needs a LiDAR whose axes are the ego's")


def _sequence_names(counts: dict[str, int]) -> dict[str, list[str]]:
    if all(counts.get(s, 0) <= len(STANDARD_SEQUENCES[s]) for s in counts):
        return {s: list(STANDARD_SEQUENCES[s][: counts[s]]) for s in counts}
    out, k = {}, 0
    for s in counts:
        out[s] = [f"{k + i:02d}" for i in range(counts[s])]
        k += counts[s]
    return out


def _row(m: np.ndarray) -> str:
    return " ".join(repr(float(v)) for v in m.reshape(-1))


def write_semantickitti(
    config: SyntheticWorldConfig,
    out: str | Path,
    splits: Sequence[str] = SPLITS,
    pseudo: str | dict | PseudoRealism | None = None,
    cache_dir: str | Path | None = "default",
    progress: bool = True,
) -> dict[str, list[str]]:
    """Write the world as a SemanticKITTI-shaped tree (see the module docstring).

    Args:
        config: the world (its first camera must be ``CAM_FRONT``); see :func:`semantickitti_world`.
        out: the tree's root (created).
        splits: which splits to write.
        pseudo: pseudo-label realism to also write ``pseudo/`` (image_2 only), or None.
        cache_dir: frame cache (``"default"``: the synthetic world's cache; None: generate).
        progress: show a progress bar.

    Returns:
        ``{split: [sequence names]}`` (also written to ``splits.json``).
    """
    out = Path(out)
    cache = default_cache_dir() if cache_dir == "default" else cache_dir
    grid = lidar_grid(config)
    datasets = {s: SyntheticDataset(config, s, cache_dir=cache, with_adjacent=False) for s in splits}
    names = _sequence_names({s: d.num_scenes for s, d in datasets.items()})
    labeler = None if pseudo is None else SyntheticPseudoLabels(pseudo, taxonomy="semantickitti")
    stride = max(1, round(10.0 / config.fps))
    total = sum(len(d) for d in datasets.values())
    with tqdm(total=total, desc="SemanticKITTI-shaped tree", unit="scan", disable=not progress) as bar:
        for split, ds in datasets.items():
            for scene_index, seq in enumerate(names[split]):
                frames = [ds.frame(scene_index, k) for k in range(ds.frames_per_scene)]
                if frames[0].camera_names[0] != "CAM_FRONT":
                    raise ValueError(
                        "the SemanticKITTI export writes the world's first camera, which must be CAM_FRONT"
                    )
                _write_sequence(
                    out / "sequences" / seq, frames, ds, scene_index, stride, config.fps, grid, labeler, out / "pseudo"
                )
                bar.update(len(frames))
    (out / "splits.json").write_text(json.dumps(names, indent=2))
    write_grid_record(out, grid.shape, grid.range, grid.voxel_size)
    if labeler is not None:
        lacks = labeler.realism.primary_lacks
        (out / "pseudo" / "semantics_mapping.yaml").write_text(
            mapping_table(
                "semantickitti",
                labeler.realism.foreign_taxonomy,
                primary_lacks=lacks,
                sky_as_free=labeler.realism.sky_as_free,
            )
        )
        if labeler.has_auxiliary:
            (out / "pseudo" / "semantics_aux_mapping.yaml").write_text(
                mapping_table("semantickitti", source="auxiliary", primary_lacks=lacks)
            )
    return names


def _write_sequence(
    folder: Path,
    frames: list[Frame],
    ds: SyntheticDataset,
    scene_index: int,
    stride: int,
    fps: float,
    grid: GridSpec,
    labeler: SyntheticPseudoLabels | None,
    pseudo_root: Path,
) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    first = frames[0]
    cam = first.cam_to_ego[0].double()
    lidar = first.lidar_to_ego.double()
    k = first.intrinsics[0].double().numpy()
    p = np.concatenate([k, np.zeros((3, 1))], 1)
    tr = (invert_pose(cam) @ lidar).numpy()
    (folder / "calib.txt").write_text("".join(f"P{i}: {_row(p)}\n" for i in range(4)) + f"Tr: {_row(tr[:3])}\n")
    scene = ds.scene(scene_index)
    world_to_global = scene.world_to_global.double()
    cam0_global = lambda t: world_to_global @ scene.ego_to_world(t) @ cam  # noqa: E731
    origin_inv = invert_pose(cam0_global(0.0))
    last_scan = (len(frames) - 1) * stride
    scan_dt = 1.0 / (fps * stride)
    poses = [(origin_inv @ cam0_global(s * scan_dt)).numpy() for s in range(last_scan + 1)]
    (folder / "poses.txt").write_text("".join(_row(m[:3]) + "\n" for m in poses))
    (folder / "times.txt").write_text("".join(f"{s * scan_dt!r}\n" for s in range(last_scan + 1)))
    raw = _raw_lut()
    ssc = np.asarray(OCC3D_TO_SSC, dtype=np.int64)
    for i, frame in enumerate(frames):
        name = f"{i * stride:06d}"
        write_rgb(folder / "image_2" / f"{name}.png", frame.images[0])
        (folder / "velodyne").mkdir(exist_ok=True)
        frame.points.numpy().astype(np.float32).reshape(-1).tofile(folder / "velodyne" / f"{name}.bin")
        (folder / "labels").mkdir(exist_ok=True)
        point_raw = raw[ssc[frame.point_labels.numpy().clip(0, 255)]].astype(np.uint32)
        point_raw.tofile(folder / "labels" / f"{name}.label")
        vox = folder / "voxels"
        write_raw_labels(vox / f"{name}.label", raw[ssc[frame.voxel_labels.numpy().astype(np.int64)]])
        write_bits(vox / f"{name}.invalid", ~(frame.mask_lidar | frame.mask_camera))
        write_bits(vox / f"{name}.occluded", ~frame.mask_lidar)
        write_bits(vox / f"{name}.bin", _scan_occupancy(frame.points[:, :3], grid))
        if labeler is not None:
            labeler.write(frame, pseudo_root, cameras=(0,), names=("image_2",), token=f"{folder.name}_{name}")


def _scan_occupancy(points: Tensor, grid: GridSpec) -> Tensor:
    idx = grid.coord_to_index(points)
    idx = idx[grid.index_in_bounds(idx)]
    occ = torch.zeros(grid.shape, dtype=torch.bool)
    occ[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    return occ
