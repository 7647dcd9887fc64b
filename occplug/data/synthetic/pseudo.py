"""The synthetic world's imperfect pseudo labels: what Metric3D / MSeg / DINO would give, with known noise.

From a generated frame's ground truth (``depth``, ``semantics_2d``, the camera geometry and pose)
this module makes the three pseudo-label kinds of :mod:`occplug.data.pseudo_labels`, with the
realism set by :class:`PseudoRealism`:

* **depth**: ``gt * scale * (1 + n)``: one scale error per image (log-normal, std
  ``depth_scale_error``, as monocular metric depth mis-estimates the focal scale) and a spatially
  smooth relative error ``n`` (std ``depth_noise``); 0 where the ground truth has no surface (sky) or
  beyond ``depth_max``.
* **semantics** in a *foreign taxonomy* (:data:`FOREIGN_CLASSES`, ids in the style of MSeg's universal
  taxonomy as OccLE's Table B.1 lists them), with the splits and merges of that table: man-made
  structure splits into ``building`` (above 2.5 m) and ``wall``; a bicycle / motorcycle splits into
  the vehicle and its ``bicyclist`` / ``motorcyclist`` rider (above 1 m); construction vehicles merge
  into ``truck`` and traffic cones into ``road_barrier`` (errors no mapping table can undo); sky and
  ``others`` have no target class. Label noise: blobs (``semantic_noise`` of the pixels) relabelled
  with a random foreign class; boundary errors: pixels within ``boundary_error`` px of a class
  boundary take a neighbour's label. :func:`mapping_table` writes the YAML table back to the target
  taxonomy (Occ3D or SemanticKITTI).
* **features**: ``feature_dim`` channels at ``1 / feature_stride`` resolution: a fixed random
  embedding of the pixel's true class plus half a fixed random Fourier embedding of its global
  position (so a static surface keeps its features across frames), area-averaged, plus Gaussian
  noise (std ``feature_noise``).

Everything is deterministic in ``(realism.seed, token, camera)``.
"""

from __future__ import annotations

import copy
import hashlib
import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
import yaml
from torch import Tensor

from occplug.data.classes import OCC3D_CLASSES, SEMANTIC_KITTI_CLASSES
from occplug.data.classes import OCC3D_TO_SEMANTIC_KITTI as OCC3D_TO_SSC
from occplug.data.frame import Frame
from occplug.geometry import camera_rays

__all__ = [
    "FOREIGN_CLASSES",
    "PSEUDO_PRESETS",
    "PseudoRealism",
    "SyntheticPseudoLabels",
    "mapping_table",
    "pseudo_realism",
]

#: The foreign 2D taxonomy of the synthetic segmenter: id -> name.
FOREIGN_CLASSES: dict[int, str] = {
    31: "road_barrier",
    35: "building",
    98: "road",
    100: "sidewalk_pavement",
    102: "terrain",
    103: "gravel",
    125: "person",
    127: "bicyclist",
    128: "motorcyclist",
    142: "sky",
    174: "vegetation",
    175: "bicycle",
    176: "car",
    178: "motorcycle",
    180: "bus",
    182: "truck",
    183: "trailer",
    191: "wall",
    194: "unlabeled",
}
_ID = {name: i for i, name in FOREIGN_CLASSES.items()}

# Occ3D id -> foreign name (before the height splits); 255 (no surface) -> sky.
_OCC3D_TO_FOREIGN = {
    0: "unlabeled", 1: "road_barrier", 2: "bicycle", 3: "bus", 4: "car", 5: "truck", 6: "motorcycle", 7: "person",
    8: "road_barrier", 9: "trailer", 10: "truck", 11: "road", 12: "gravel", 13: "sidewalk_pavement", 14: "terrain",
    15: "wall", 16: "vegetation", 255: "sky",
}  # fmt: skip
# (Occ3D id, foreign name below the height, foreign name at/above it, height in metres of the ego frame)
_HEIGHT_SPLITS = ((15, "wall", "building", 2.5), (2, "bicycle", "bicyclist", 1.0), (6, "motorcycle", "motorcyclist", 1.0))

#: Foreign name -> target class, per target taxonomy (``None``: no target class).
_TO_TARGET: dict[str, dict[str, str | None]] = {
    "occ3d": {
        "road_barrier": "barrier", "building": "manmade", "wall": "manmade", "road": "driveable_surface",
        "sidewalk_pavement": "sidewalk", "terrain": "terrain", "gravel": "other_flat", "person": "pedestrian",
        "bicyclist": "bicycle", "motorcyclist": "motorcycle", "sky": None, "vegetation": "vegetation",
        "bicycle": "bicycle", "car": "car", "motorcycle": "motorcycle", "bus": "bus", "truck": "truck",
        "trailer": "trailer", "unlabeled": None,
    },
    "semantickitti": {
        "road_barrier": "fence", "building": "building", "wall": "building", "road": "road",
        "sidewalk_pavement": "sidewalk", "terrain": "terrain", "gravel": "other-ground", "person": "person",
        "bicyclist": "bicyclist", "motorcyclist": "motorcyclist", "sky": None, "vegetation": "vegetation",
        "bicycle": "bicycle", "car": "car", "motorcycle": "motorcycle", "bus": "other-vehicle", "truck": "truck",
        "trailer": "other-vehicle", "unlabeled": None,
    },
}  # fmt: skip
_TAXONOMIES = {"occ3d": OCC3D_CLASSES, "semantickitti": SEMANTIC_KITTI_CLASSES}


@dataclass(frozen=True)
class PseudoRealism:
    """How far the synthetic pseudo labels are from the truth (see the module docstring).

    Attributes:
        depth_noise: std of the smooth relative depth error.
        depth_scale_error: std of the per-image log scale error.
        depth_max: metres; farther predictions are dropped (0).
        semantic_noise: fraction of pixels in relabelled blobs.
        boundary_error: pixels a class boundary may shift by.
        foreign_taxonomy: False writes target-class ids (identity table) instead of the foreign taxonomy.
        feature_dim: feature channels.
        feature_stride: image pixels per feature cell.
        feature_noise: std of the feature noise.
        seed: seed of the noise and of the fixed embeddings.
    """

    depth_noise: float = 0.05
    depth_scale_error: float = 0.05
    depth_max: float = 80.0
    semantic_noise: float = 0.03
    boundary_error: int = 1
    foreign_taxonomy: bool = True
    feature_dim: int = 16
    feature_stride: int = 4
    feature_noise: float = 0.1
    seed: int = 0


#: ``perfect`` (no noise; the foreign taxonomy's merges remain), ``default`` and ``noisy``.
PSEUDO_PRESETS: dict[str, PseudoRealism] = {
    "perfect": PseudoRealism(depth_noise=0.0, depth_scale_error=0.0, depth_max=1e9, semantic_noise=0.0, boundary_error=0,
                             feature_noise=0.0),
    "default": PseudoRealism(),
    "noisy": PseudoRealism(depth_noise=0.15, depth_scale_error=0.15, depth_max=60.0, semantic_noise=0.1, boundary_error=2,
                           feature_noise=0.3),
}


def pseudo_realism(spec: str | dict[str, Any] | PseudoRealism | None) -> PseudoRealism:
    """A preset name, a mapping ``{preset: name, <knob>: value, ...}`` or a :class:`PseudoRealism`."""
    if isinstance(spec, PseudoRealism):
        return spec
    if spec is None:
        return PSEUDO_PRESETS["default"]
    if isinstance(spec, str):
        if spec not in PSEUDO_PRESETS:
            raise ValueError(f"unknown pseudo-label realism preset '{spec}' (valid: {', '.join(PSEUDO_PRESETS)})")
        return PSEUDO_PRESETS[spec]
    spec = dict(spec)
    base = pseudo_realism(spec.pop("preset", "default"))
    valid = [f.name for f in fields(PseudoRealism)]
    for key in spec:
        if key not in valid:
            raise ValueError(f"pseudo-label realism: unknown knob '{key}' (valid: preset, {', '.join(valid)})")
    return PseudoRealism(**{**asdict(base), **spec})


def mapping_table(taxonomy: str = "occ3d", foreign: bool = True) -> str:
    """The YAML class-mapping table (see :mod:`occplug.data.pseudo_labels`) from the synthetic
    segmenter's maps to ``taxonomy`` (``occ3d`` or ``semantickitti``); ``foreign=False`` gives the
    identity table of maps written in target ids."""
    if taxonomy not in _TAXONOMIES:
        raise ValueError(f"unknown target taxonomy '{taxonomy}' (valid: {', '.join(_TAXONOMIES)})")
    if not foreign:
        names = _TAXONOMIES[taxonomy]
        data = {"classes": dict(enumerate(names)), "map": {n: n for n in names}}
        header = f"# identity table: the maps hold {taxonomy} class ids\n"
    else:
        data = {
            "classes": dict(sorted(FOREIGN_CLASSES.items())),
            "map": {name: (target or "ignore") for name, target in _TO_TARGET[taxonomy].items()},
        }
        header = (f"# the synthetic segmenter's foreign taxonomy -> {taxonomy} (splits and merges as in OccLE's Table B.1)\n")
    return header + yaml.safe_dump(data, sort_keys=False)


def _generator(seed: int, *parts: object) -> torch.Generator:
    digest = hashlib.sha256("/".join(str(p) for p in (seed, *parts)).encode()).digest()
    return torch.Generator().manual_seed(int.from_bytes(digest[:8], "little") & ((1 << 62) - 1))


def _smooth_noise(h: int, w: int, g: torch.Generator, cell: int = 8) -> Tensor:
    low = torch.randn(1, 1, max(1, math.ceil(h / cell)) + 1, max(1, math.ceil(w / cell)) + 1, generator=g)
    return F.interpolate(low, size=(h, w), mode="bilinear", align_corners=False)[0, 0]


class SyntheticPseudoLabels:
    """Makes (``attach``) or writes (``write``) the synthetic world's pseudo labels for a frame.

    The frame must carry its ground truth (``depth``, ``semantics_2d``) as the synthetic world
    generates it, before any resize or augmentation.

    Args:
        realism: a :class:`PseudoRealism`, a preset name or a knob mapping.
        kinds: which of ``depth``, ``semantics``, ``features`` to make.
        taxonomy: the target taxonomy (``occ3d`` or ``semantickitti``) that ``attach`` maps semantics
            to and, without the foreign taxonomy, that the maps are written in (Occ3D ground truth
            goes through :data:`~occplug.data.synthetic.export_semantickitti.OCC3D_TO_SSC`).
    """

    def __init__(self, realism: str | dict[str, Any] | PseudoRealism | None = None,
                 kinds: tuple[str, ...] = ("depth", "semantics", "features"), taxonomy: str = "occ3d") -> None:
        self.realism = pseudo_realism(realism)
        for kind in kinds:
            if kind not in ("depth", "semantics", "features"):
                raise ValueError(f"unknown pseudo-label kind '{kind}' (valid: depth, semantics, features)")
        self.kinds = tuple(kinds)
        if taxonomy not in _TAXONOMIES:
            raise ValueError(f"unknown target taxonomy '{taxonomy}' (valid: {', '.join(_TAXONOMIES)})")
        self.taxonomy = taxonomy
        lut = np.full(1 << 16, 255, dtype=np.uint8)
        if self.realism.foreign_taxonomy:
            targets = {n: i for i, n in enumerate(_TAXONOMIES[taxonomy])}
            for fid, name in FOREIGN_CLASSES.items():
                target = _TO_TARGET[taxonomy][name]
                if target is not None:
                    lut[fid] = targets[target]
        else:
            lut[: len(_TAXONOMIES[taxonomy])] = np.arange(len(_TAXONOMIES[taxonomy]))
        self._lut = torch.from_numpy(lut.astype(np.int64))
        g = _generator(self.realism.seed, "embeddings")
        dim = self.realism.feature_dim
        self._class_embedding = torch.randn(257, dim, generator=g)
        self._freq = torch.randn(3, max(1, dim // 2), generator=g, dtype=torch.float64) / 10.0
        self._phase = torch.rand(max(1, dim // 2), generator=g, dtype=torch.float64) * 2 * math.pi

    # ------------------------------------------------------------------ per camera
    def _points(self, frame: Frame) -> tuple[Tensor, Tensor]:
        """Ego-frame and global-frame ``(N, H, W, 3)`` float64 surface points of every pixel (NaN-free; 0 for sky)."""
        h, w = frame.image_size
        origins, dirs, z_per_m = camera_rays(frame.intrinsics.double(), frame.cam_to_ego.double(), h, w,
                                             frame.img_aug.double())
        rng = frame.depth.double() / z_per_m
        ego = origins[:, None, None, :] + dirs * rng[..., None]
        e = frame.ego_to_global.double()
        glob = ego @ e[:3, :3].T + e[:3, 3]
        return ego, glob

    def depth(self, frame: Frame, cam: int) -> Tensor:
        """``(H, W)`` float32 pseudo depth of camera ``cam``."""
        r = self.realism
        gt = frame.depth[cam]
        g = _generator(r.seed, frame.token, frame.camera_names[cam], "depth")
        scale = math.exp(r.depth_scale_error * float(torch.randn((), generator=g)))
        noise = _smooth_noise(*gt.shape, g) * r.depth_noise
        out = gt * scale * (1 + noise).clamp_min(0.05)
        return torch.where((gt > 0) & (out <= r.depth_max), out, torch.zeros_like(out)).float()

    def semantics(self, frame: Frame, cam: int, ego: Tensor | None = None) -> Tensor:
        """``(H, W)`` int64 foreign class ids (or target ids without the foreign taxonomy)."""
        r = self.realism
        truth = frame.semantics_2d[cam].long()
        if not r.foreign_taxonomy:
            out = truth.clone()
            if self.taxonomy == "semantickitti":
                out = torch.tensor(OCC3D_TO_SSC, dtype=torch.int64)[truth.clamp(0, 255)]
            pool = torch.tensor(sorted(set(range(len(_TAXONOMIES[self.taxonomy]))) - {0}))
        else:
            lut = torch.full((256,), _ID["unlabeled"], dtype=torch.int64)
            for occ, name in _OCC3D_TO_FOREIGN.items():
                lut[occ] = _ID[name]
            out = lut[truth.clamp(0, 255)]
            if ego is not None:
                z = ego[..., 2]
                for occ, low, high, height in _HEIGHT_SPLITS:
                    out = torch.where((truth == occ) & (z >= height), torch.full_like(out, _ID[high]), out)
                    out = torch.where((truth == occ) & (z < height), torch.full_like(out, _ID[low]), out)
            pool = torch.tensor(sorted(i for i, n in FOREIGN_CLASSES.items() if n not in ("sky", "unlabeled")))
        g = _generator(r.seed, frame.token, frame.camera_names[cam], "semantics")
        h, w = out.shape
        if r.boundary_error > 0:
            k = 2 * r.boundary_error + 1
            f = out[None, None].double()
            edge = (F.max_pool2d(f, k, 1, r.boundary_error) != -F.max_pool2d(-f, k, 1, r.boundary_error))[0, 0]
            dv = torch.randint(-r.boundary_error, r.boundary_error + 1, (h, w), generator=g)
            du = torch.randint(-r.boundary_error, r.boundary_error + 1, (h, w), generator=g)
            rows = (torch.arange(h)[:, None] + dv).clamp(0, h - 1)
            cols = (torch.arange(w)[None, :] + du).clamp(0, w - 1)
            out = torch.where(edge, out[rows, cols], out)
        if r.semantic_noise > 0:
            field = _smooth_noise(h, w, g, cell=6)
            threshold = torch.quantile(field.flatten(), 1 - r.semantic_noise)
            blobs = field > threshold
            cell = max(1, min(h, w) // 4)
            cls_low = pool[torch.randint(len(pool), (math.ceil(h / cell), math.ceil(w / cell)), generator=g)]
            replacement = cls_low.repeat_interleave(cell, 0).repeat_interleave(cell, 1)[:h, :w]
            out = torch.where(blobs, replacement, out)
        return out

    def features(self, frame: Frame, cam: int, glob: Tensor) -> Tensor:
        """``(F, h, w)`` float32 features of camera ``cam``."""
        r = self.realism
        truth = frame.semantics_2d[cam].long().clamp(0, 255)
        emb = self._class_embedding[truth]  # (H, W, F)
        surface = (frame.depth[cam] > 0)[..., None]
        phase = glob[cam] @ self._freq + self._phase
        pos = torch.cat([phase.sin(), phase.cos()], -1)[..., : r.feature_dim].float() / math.sqrt(max(1, r.feature_dim // 2))
        if pos.shape[-1] < r.feature_dim:
            pos = F.pad(pos, (0, r.feature_dim - pos.shape[-1]))
        full = (emb + 0.5 * pos * surface).permute(2, 0, 1)
        h, w = truth.shape
        size = (max(1, h // r.feature_stride), max(1, w // r.feature_stride))
        low = F.interpolate(full[None], size=size, mode="area")[0]
        g = _generator(r.seed, frame.token, frame.camera_names[cam], "features")
        return (low + r.feature_noise * torch.randn(low.shape, generator=g)).float()

    # ------------------------------------------------------------------ frames
    def _check(self, frame: Frame) -> None:
        if frame.depth is None or frame.semantics_2d is None:
            raise ValueError(f"frame {frame.token}: synthetic pseudo labels need the generated depth and semantics_2d")
        if not torch.equal(frame.img_aug, torch.eye(3).expand_as(frame.img_aug)):
            raise ValueError(f"frame {frame.token}: make synthetic pseudo labels before any image augmentation")

    def maps(self, frame: Frame) -> dict[str, Tensor]:
        """``{"depth": (N, H, W), "semantics": (N, H, W) raw ids, "features": (N, F, h, w)}`` (the configured kinds)."""
        self._check(frame)
        ego, glob = self._points(frame)
        n = frame.num_cameras
        out: dict[str, Tensor] = {}
        if "depth" in self.kinds:
            out["depth"] = torch.stack([self.depth(frame, c) for c in range(n)])
        if "semantics" in self.kinds:
            out["semantics"] = torch.stack([self.semantics(frame, c, ego[c]) for c in range(n)])
        if "features" in self.kinds:
            out["features"] = torch.stack([self.features(frame, c, glob) for c in range(n)])
        return out

    def attach(self, frame: Frame) -> Frame:
        """A copy of ``frame`` with its pseudo-label fields filled (semantics mapped to the target taxonomy)."""
        maps = self.maps(frame)
        out = copy.copy(frame)
        if "depth" in maps:
            out.pseudo_depth = maps["depth"]
        if "semantics" in maps:
            out.pseudo_semantics = self._lut[maps["semantics"].clamp(0, 65535)]
        if "features" in maps:
            out.pseudo_features = maps["features"]
        return out

    def write(self, frame: Frame, root: str | Path, cameras: tuple[int, ...] | None = None,
              names: tuple[str, ...] | None = None, token: str | None = None) -> None:
        """Write the frame's pseudo labels under ``root`` in the layout of :mod:`occplug.data.pseudo_labels`.

        ``root/depth/<token>/<camera>.npy`` (float32), ``root/semantics/<token>/<camera>.png``
        (uint8 foreign ids), ``root/features/<token>/<camera>.npy`` (float16).

        Args:
            frame: the generated frame.
            root: the pseudo-label root.
            cameras: which cameras (default all); names: their names in the written tree (default the frame's).
            token: the sample token in the written tree (default the frame's).
        """
        from occplug.data.imageio import write_map, write_npy

        maps = self.maps(frame)
        root = Path(root)
        cams = tuple(range(frame.num_cameras)) if cameras is None else cameras
        names = tuple(frame.camera_names[c] for c in cams) if names is None else names
        token = token or frame.token
        for c, name in zip(cams, names, strict=True):
            if "depth" in maps:
                write_npy(root / "depth" / token / f"{name}.npy", maps["depth"][c].numpy().astype(np.float32))
            if "semantics" in maps:
                write_map(root / "semantics" / token / f"{name}.png", maps["semantics"][c].numpy())
            if "features" in maps:
                write_npy(root / "features" / token / f"{name}.npy", maps["features"][c].numpy().astype(np.float16))
