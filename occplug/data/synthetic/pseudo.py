"""The synthetic world's imperfect pseudo labels: what Metric3D / MSeg / DINO would give, with known noise.

From a generated frame's ground truth (``depth``, ``semantics_2d``, the camera geometry and pose)
this module makes the three pseudo-label kinds of :mod:`occplug.data.pseudo_labels`, with the
realism set by :class:`PseudoRealism`:

* **depth**: ``gt * scale * (1 + n)``: one scale error per image (log-normal, std
  ``depth_scale_error``, as monocular metric depth mis-estimates the focal scale) and a spatially
  smooth relative error ``n`` (std ``depth_noise``); 0 where the ground truth has no surface (sky) or
  beyond ``depth_max``.
* **semantics** from two imperfect segmenters with different taxonomies, merged through their
  mapping tables by :func:`~occplug.data.pseudo_labels.merge_semantics` (the primary first):

  - the *primary*, dataset-specific one in a *foreign taxonomy* (:data:`FOREIGN_CLASSES`, ids in the
    style of MSeg's universal taxonomy as OccLE's Table B.1 lists them), with the splits and merges
    of that table: man-made structure splits into ``building`` (above 2.5 m) and ``wall``; a
    bicycle / motorcycle splits into the vehicle and its ``bicyclist`` / ``motorcyclist`` rider
    (above 1 m); construction vehicles merge into ``truck`` (an error no mapping table can undo);
    it has **no traffic-cone class** (cones are ``unlabeled``), nor a class for any of the world's
    classes named in ``primary_lacks`` (their pixels are ``unlabeled`` too); sky and ``others`` have no
    target class. Label noise: blobs (``semantic_noise`` of the pixels) relabelled with a random foreign
    class; boundary errors: pixels within ``boundary_error`` px of a class boundary take a
    neighbour's label. :func:`mapping_table` writes the YAML table back to the target taxonomy
    (Occ3D or SemanticKITTI).
  - the *auxiliary*, open-vocabulary one (``auxiliary``; :data:`AUXILIARY_CLASSES`, a few prompted
    names) that has the cone: coarse (every vehicle is ``vehicle``), with over-reaching masks
    (``auxiliary_boundary_error``) and missed regions (``auxiliary_miss`` of the pixels become
    ``background``). Its table (``mapping_table(..., source="auxiliary")``) maps only the prompts
    naming a class the primary lacks (``traffic cone`` always; ``person``, ``tree``, ``building``,
    ``road`` when ``primary_lacks`` names pedestrian, vegetation, manmade, driveable_surface), so it
    fills exactly those classes, where the primary leaves its pixels unknown.

* **features**: ``feature_dim`` channels at ``1 / feature_stride`` resolution, like a vision
  foundation model's: they cluster by class but are no one-to-one code of it. A fixed random
  embedding of the pixel's *coarse group* (vehicles, road users, flat ground, structure, nature)
  plus a smaller one of its class (``feature_class_weight``; classes of a group overlap), plus a
  fixed random Fourier embedding of its global position (weight ``feature_position_weight``; a
  static surface keeps its features across frames, and a class spreads out in space),
  area-averaged (boundary cells mix classes), plus Gaussian noise (std ``feature_noise``).

Everything is deterministic in ``(realism.seed, token, camera)``.
"""

from __future__ import annotations

import copy
import hashlib
import math
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
import yaml
from torch import Tensor

from occplug.data.classes import OCC3D_CLASSES, OCC3D_FREE, SEMANTIC_KITTI_CLASSES
from occplug.data.classes import OCC3D_TO_SEMANTIC_KITTI as OCC3D_TO_SSC
from occplug.data.frame import Frame
from occplug.geometry import camera_rays

__all__ = [
    "AUXILIARY_CLASSES",
    "FOREIGN_CLASSES",
    "LACKABLE_CLASSES",
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

# Occ3D id -> foreign name (before the height splits); 255 (no surface) -> sky. No cone class: unlabeled.
_OCC3D_TO_FOREIGN = {
    0: "unlabeled", 1: "road_barrier", 2: "bicycle", 3: "bus", 4: "car", 5: "truck", 6: "motorcycle", 7: "person",
    8: "unlabeled", 9: "trailer", 10: "truck", 11: "road", 12: "gravel", 13: "sidewalk_pavement", 14: "terrain",
    15: "wall", 16: "vegetation", 255: "sky",
}  # fmt: skip
# (Occ3D id, foreign name below the height, foreign name at/above it, height in metres of the ego frame)
_HEIGHT_SPLITS = (
    (15, "wall", "building", 2.5),
    (2, "bicycle", "bicyclist", 1.0),
    (6, "motorcycle", "motorcyclist", 1.0),
)

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
#: Each target taxonomy's free class, which the foreign ``sky`` maps to under ``sky_as_free``.
_FREE_CLASS = {"occ3d": "free", "semantickitti": "empty"}


def _target(taxonomy: str, name: str, sky_as_free: bool) -> str | None:
    """The target class name of foreign class ``name`` (``None``: no target class)."""
    if name == "sky" and sky_as_free:
        return _FREE_CLASS[taxonomy]
    return _TO_TARGET[taxonomy][name]


#: The open-vocabulary auxiliary segmenter's prompts: id -> name.
AUXILIARY_CLASSES: dict[int, str] = {
    0: "background", 1: "traffic cone", 2: "vehicle", 3: "person", 4: "tree", 5: "building", 6: "road",
}  # fmt: skip
_AUX_ID = {name: i for i, name in AUXILIARY_CLASSES.items()}
# Occ3D id -> auxiliary name (anything else: background).
_OCC3D_TO_AUX = {
    2: "vehicle", 3: "vehicle", 4: "vehicle", 5: "vehicle", 6: "vehicle", 9: "vehicle", 10: "vehicle", 7: "person",
    8: "traffic cone", 11: "road", 15: "building", 16: "tree",
}  # fmt: skip
#: Auxiliary prompt -> the one Occ3D class it names (``vehicle`` names many, so it never maps).
_AUX_NAMES_OCC3D = {"traffic cone": 8, "person": 7, "road": 11, "building": 15, "tree": 16}
#: The Occ3D classes the primary segmenter always lacks (its foreign taxonomy has no cone class).
_ALWAYS_LACKS = (8,)
#: The world's classes ``primary_lacks`` may name: the Occ3D classes its 2D maps hold.
LACKABLE_CLASSES = tuple(OCC3D_CLASSES[i] for i in range(1, 17) if i not in _ALWAYS_LACKS)

# Occ3D id -> coarse feature group (0 others, 1 vehicles, 2 road users, 3 flat ground, 4 structure, 5 nature).
_FEATURE_GROUP = {
    1: 4, 2: 2, 3: 1, 4: 1, 5: 1, 6: 2, 7: 2, 8: 4, 9: 1, 10: 1, 11: 3, 12: 3, 13: 3, 14: 5, 15: 4, 16: 5,
}  # fmt: skip


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
        auxiliary: also make the auxiliary open-vocabulary semantics (foreign taxonomy only) and merge
            them after the primary's.
        auxiliary_boundary_error: pixels the auxiliary's masks reach beyond their objects (into background).
        auxiliary_miss: fraction of pixels (in blobs) the auxiliary leaves as background.
        feature_dim: feature channels.
        feature_stride: image pixels per feature cell.
        feature_noise: std of the feature noise.
        feature_class_weight: weight of the class embedding against the (unit) group embedding.
        feature_position_weight: weight of the position embedding.
        sky_as_free: map the foreign ``sky`` to the target's free class (Occ3D ``free``, SemanticKITTI
            ``empty``) instead of leaving it unknown (255): a pixel that sees the sky is a ray free of
            surfaces, which a source supervising along rays may use (QueryOcc's sky negatives). Changes
            only the mapping, so the cached maps stay valid.
        primary_lacks: Occ3D class names (:data:`LACKABLE_CLASSES`) the primary segmenter has no class
            for, beyond the traffic cone it always lacks: their pixels are ``unlabeled`` in its maps, and
            so are the foreign classes mapping to them (``truck`` takes the construction vehicles with
            it); its noise never draws them. The auxiliary fills those its prompts name (its over-reaching
            masks spill onto sky, which has no voxel, as onto every pixel the primary leaves unknown; under
            ``sky_as_free`` the primary names the sky, so they do not).
            Without the foreign taxonomy there is no auxiliary: the lacked pixels are only unknown (255).
            Makes worlds where OccLE's label alignment (Tab. 3) has classes to supply.
        seed: seed of the noise and of the fixed embeddings.
    """

    depth_noise: float = 0.05
    depth_scale_error: float = 0.05
    depth_max: float = 80.0
    semantic_noise: float = 0.03
    boundary_error: int = 1
    foreign_taxonomy: bool = True
    auxiliary: bool = True
    auxiliary_boundary_error: int = 1
    auxiliary_miss: float = 0.1
    feature_dim: int = 16
    feature_stride: int = 4
    feature_noise: float = 0.4
    feature_class_weight: float = 0.4
    feature_position_weight: float = 0.9
    primary_lacks: tuple[str, ...] = ()
    sky_as_free: bool = False
    seed: int = 0

    def __post_init__(self) -> None:
        lacks = self.primary_lacks
        if isinstance(lacks, str) or not isinstance(lacks, Sequence):
            raise ValueError(f"pseudo-label realism: primary_lacks must be a list of class names, got {lacks!r}")
        for name in lacks:
            if name not in LACKABLE_CLASSES:
                raise ValueError(
                    f"pseudo-label realism: primary_lacks: unknown class {name!r} (valid: {', '.join(LACKABLE_CLASSES)})"
                )
        # one order (the taxonomy's), so equal sets give equal maps and cache keys
        object.__setattr__(self, "primary_lacks", tuple(n for n in LACKABLE_CLASSES if n in lacks))
        if self.sky_as_free and not self.foreign_taxonomy:
            raise ValueError(
                "pseudo-label realism: sky_as_free needs foreign_taxonomy (maps written in target ids hold sky as 255)"
            )

    def lacked_ids(self) -> tuple[int, ...]:
        """The Occ3D ids the primary segmenter has no class for in its foreign taxonomy: the cone and
        ``primary_lacks``, sorted (without the foreign taxonomy the maps lack only ``primary_lacks``)."""
        return tuple(sorted({*_ALWAYS_LACKS, *(OCC3D_CLASSES.index(n) for n in self.primary_lacks)}))


#: ``perfect`` (no noise; the foreign taxonomy's merges remain), ``default`` and ``noisy``.
PSEUDO_PRESETS: dict[str, PseudoRealism] = {
    "perfect": PseudoRealism(
        depth_noise=0.0,
        depth_scale_error=0.0,
        depth_max=1e9,
        semantic_noise=0.0,
        boundary_error=0,
        auxiliary_boundary_error=0,
        auxiliary_miss=0.0,
        feature_noise=0.0,
    ),
    "default": PseudoRealism(),
    "noisy": PseudoRealism(
        depth_noise=0.15,
        depth_scale_error=0.15,
        depth_max=60.0,
        semantic_noise=0.1,
        boundary_error=2,
        auxiliary_boundary_error=2,
        auxiliary_miss=0.25,
        feature_noise=0.6,
    ),
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


def _foreign_lacked(primary_lacks: Sequence[str]) -> set[str]:
    """The foreign class names the primary segmenter lacks: those whose Occ3D class is lacked (so
    lacking ``manmade`` drops ``building`` and ``wall``, lacking ``truck`` drops the ``truck`` that
    construction vehicles merge into)."""
    return {name for name, target in _TO_TARGET["occ3d"].items() if target in primary_lacks}


def _auxiliary_targets(taxonomy: str, lacked: tuple[int, ...]) -> dict[str, str]:
    """Auxiliary prompt -> target class name, for the prompts naming a class the primary lacks (and
    the target taxonomy has: SemanticKITTI has no cone class)."""
    out = {}
    for prompt, occ in _AUX_NAMES_OCC3D.items():
        target = occ if taxonomy == "occ3d" else OCC3D_TO_SSC[occ]
        if occ in lacked and target != 255:
            out[prompt] = _TAXONOMIES[taxonomy][target]
    return out


def mapping_table(
    taxonomy: str = "occ3d",
    foreign: bool = True,
    source: str = "primary",
    primary_lacks: Sequence[str] = (),
    sky_as_free: bool = False,
) -> str:
    """The YAML class-mapping table (see :mod:`occplug.data.pseudo_labels`) from the synthetic
    segmenter's maps to ``taxonomy`` (``occ3d`` or ``semantickitti``); ``foreign=False`` gives the
    identity table of maps written in target ids; ``source="auxiliary"`` the auxiliary segmenter's
    table (only the prompts naming a class the primary lacks are mapped). ``primary_lacks``: as
    :attr:`PseudoRealism.primary_lacks` (the primary's table leaves out the foreign classes it lacks);
    ``sky_as_free``: as :attr:`PseudoRealism.sky_as_free` (``sky`` maps to the free class, not ``ignore``)."""
    if taxonomy not in _TAXONOMIES:
        raise ValueError(f"unknown target taxonomy '{taxonomy}' (valid: {', '.join(_TAXONOMIES)})")
    if source not in ("primary", "auxiliary"):
        raise ValueError(f"unknown semantic source '{source}' (valid: primary, auxiliary)")
    checked = PseudoRealism(primary_lacks=primary_lacks, sky_as_free=sky_as_free and foreign)  # validates the names
    lacks, lacked = checked.primary_lacks, checked.lacked_ids()
    if source == "auxiliary":
        mapped = _auxiliary_targets(taxonomy, lacked)
        data = {
            "classes": dict(AUXILIARY_CLASSES),
            "map": {n: mapped.get(n, "ignore") for n in AUXILIARY_CLASSES.values()},
        }
        header = f"# the synthetic open-vocabulary segmenter -> {taxonomy}: only the classes the primary lacks\n"
        return header + yaml.safe_dump(data, sort_keys=False)
    if not foreign:
        names = _TAXONOMIES[taxonomy]
        data = {"classes": dict(enumerate(names)), "map": {n: n for n in names}}
        header = f"# identity table: the maps hold {taxonomy} class ids\n"
    else:
        missing = _foreign_lacked(lacks)
        data = {
            "classes": {i: n for i, n in sorted(FOREIGN_CLASSES.items()) if n not in missing},
            "map": {
                name: (_target(taxonomy, name, sky_as_free) or "ignore")
                for name in _TO_TARGET[taxonomy]
                if name not in missing
            },
        }
        header = (
            f"# the synthetic segmenter's foreign taxonomy -> {taxonomy} (splits and merges as in OccLE's Table B.1)\n"
        )
    return header + yaml.safe_dump(data, sort_keys=False)


def _generator(seed: int, *parts: object) -> torch.Generator:
    digest = hashlib.sha256("/".join(str(p) for p in (seed, *parts)).encode()).digest()
    return torch.Generator().manual_seed(int.from_bytes(digest[:8], "little") & ((1 << 62) - 1))


def _smooth_noise(h: int, w: int, g: torch.Generator, cell: int = 8) -> Tensor:
    low = torch.randn(1, 1, max(1, math.ceil(h / cell)) + 1, max(1, math.ceil(w / cell)) + 1, generator=g)
    return F.interpolate(low, size=(h, w), mode="bilinear", align_corners=False)[0, 0]


#: Bump when the maps made for a frame change (invalidates cached maps).
PSEUDO_CODE_VERSION = "synthetic-pseudo-1"


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
        cache_dir: where made maps are kept between runs (``None``: made every time they are read).
    """

    def __init__(
        self,
        realism: str | dict[str, Any] | PseudoRealism | None = None,
        kinds: tuple[str, ...] = ("depth", "semantics", "features"),
        taxonomy: str = "occ3d",
        cache_dir: str | Path | None = None,
    ) -> None:
        self.cache_dir = cache_dir
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
                target = _target(taxonomy, name, self.realism.sky_as_free)
                if target is not None:
                    lut[fid] = targets[target]
        else:
            lut[: len(_TAXONOMIES[taxonomy])] = np.arange(len(_TAXONOMIES[taxonomy]))
        self._lut = torch.from_numpy(lut.astype(np.int64))
        aux = torch.full((256,), 255, dtype=torch.int64)
        targets = {n: i for i, n in enumerate(_TAXONOMIES[taxonomy])}
        for name, target in _auxiliary_targets(taxonomy, self.realism.lacked_ids()).items():
            aux[_AUX_ID[name]] = targets[target]
        self._aux_lut = aux
        self._lacked_truth = torch.tensor(
            [OCC3D_CLASSES.index(n) for n in self.realism.primary_lacks], dtype=torch.int64
        )
        self._lacked_foreign = torch.tensor(
            sorted(_ID[n] for n in _foreign_lacked(self.realism.primary_lacks)), dtype=torch.int64
        )
        if self.realism.foreign_taxonomy:
            excluded = set(self._lacked_foreign.tolist()) | {_ID["sky"], _ID["unlabeled"]}
            self._noise_pool = torch.tensor(sorted(set(FOREIGN_CLASSES) - excluded))
        else:
            # target ids whose every world class is lacked (SemanticKITTI merges some: bus + trailer -> other-vehicle)
            to_target = range(OCC3D_FREE) if taxonomy == "occ3d" else OCC3D_TO_SSC[:OCC3D_FREE]
            sources: dict[int, set[int]] = {}
            for occ, t in enumerate(to_target):
                sources.setdefault(t, set()).add(occ)
            lacked = set(self._lacked_truth.tolist())
            missing = {t for t, occs in sources.items() if occs <= lacked}
            self._noise_pool = torch.tensor(sorted(set(range(1, len(_TAXONOMIES[taxonomy]))) - missing))
        g = _generator(self.realism.seed, "embeddings")
        dim = self.realism.feature_dim
        self._class_embedding = torch.randn(257, dim, generator=g)
        # group (unit) + weighted class embedding: classes of a group overlap
        groups = torch.tensor([_FEATURE_GROUP.get(c, 0) for c in range(257)])
        group_embedding = F.normalize(torch.randn(6, dim, generator=g), dim=-1) * math.sqrt(dim)
        self._class_embedding = group_embedding[groups] + self.realism.feature_class_weight * self._class_embedding
        self._freq = torch.randn(3, max(1, dim // 2), generator=g, dtype=torch.float64) / 10.0
        self._phase = torch.rand(max(1, dim // 2), generator=g, dtype=torch.float64) * 2 * math.pi

    # ------------------------------------------------------------------ per camera
    def _points(self, frame: Frame) -> tuple[Tensor, Tensor]:
        """Ego-frame and global-frame ``(N, H, W, 3)`` float64 surface points of every pixel (NaN-free; 0 for sky)."""
        h, w = frame.image_size
        origins, dirs, z_per_m = camera_rays(
            frame.intrinsics.double(), frame.cam_to_ego.double(), h, w, frame.img_aug.double()
        )
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
            out = torch.where(torch.isin(truth, self._lacked_truth), torch.full_like(out, 255), out)
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
            lacked = torch.isin(truth, self._lacked_truth) | torch.isin(out, self._lacked_foreign)
            out = torch.where(lacked, torch.full_like(out, _ID["unlabeled"]), out)
        pool = self._noise_pool
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

    @property
    def has_auxiliary(self) -> bool:
        """Whether the auxiliary semantics are made (``auxiliary`` with the foreign taxonomy)."""
        return self.realism.auxiliary and self.realism.foreign_taxonomy

    def auxiliary_semantics(self, frame: Frame, cam: int) -> Tensor:
        """``(H, W)`` int64 auxiliary (open-vocabulary) class ids (:data:`AUXILIARY_CLASSES`)."""
        r = self.realism
        truth = frame.semantics_2d[cam].long().clamp(0, 255)
        lut = torch.zeros(256, dtype=torch.int64)
        for occ, name in _OCC3D_TO_AUX.items():
            lut[occ] = _AUX_ID[name]
        out = lut[truth]
        g = _generator(r.seed, frame.token, frame.camera_names[cam], "auxiliary")
        h, w = out.shape
        b = r.auxiliary_boundary_error
        if b > 0:
            # over-reaching masks: background within b px of a prompted class takes its (largest) id
            grown = F.max_pool2d(out[None, None].double(), 2 * b + 1, 1, b)[0, 0].long()
            out = torch.where(out == 0, grown, out)
        if r.auxiliary_miss > 0:
            field = _smooth_noise(h, w, g, cell=6)
            missed = field > torch.quantile(field.flatten(), 1 - r.auxiliary_miss)
            out = torch.where(missed, torch.zeros_like(out), out)
        return out

    def features(self, frame: Frame, cam: int, glob: Tensor) -> Tensor:
        """``(F, h, w)`` float32 features of camera ``cam``."""
        r = self.realism
        truth = frame.semantics_2d[cam].long().clamp(0, 255)
        emb = self._class_embedding[truth]  # (H, W, F)
        surface = (frame.depth[cam] > 0)[..., None]
        phase = glob[cam] @ self._freq + self._phase
        pos = torch.cat([phase.sin(), phase.cos()], -1)[..., : r.feature_dim].float() / math.sqrt(
            max(1, r.feature_dim // 2)
        )
        if pos.shape[-1] < r.feature_dim:
            pos = F.pad(pos, (0, r.feature_dim - pos.shape[-1]))
        full = (emb + r.feature_position_weight * math.sqrt(r.feature_dim) * pos * surface).permute(2, 0, 1)
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

    def cache_key(self) -> str:
        """A short hash of everything that changes the maps of a given frame: realism, kinds, taxonomy, code."""
        realism = asdict(self.realism)
        if not realism["primary_lacks"]:  # the knob's default leaves the maps and so the caches made before it
            del realism["primary_lacks"]
        del realism["sky_as_free"]  # a mapping choice: the cached maps hold foreign ids
        text = repr((realism, self.kinds, self.taxonomy, PSEUDO_CODE_VERSION))
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def _cache_path(self, token: str) -> Path | None:
        return None if self.cache_dir is None else Path(self.cache_dir) / self.cache_key() / f"{token}.pt"

    def is_cached(self, token: str) -> bool:
        """Whether the maps of frame ``token`` are in the cache (always True without one: nothing to make ahead)."""
        path = self._cache_path(token)
        return path is None or path.is_file()

    def maps(self, frame: Frame) -> dict[str, Tensor]:
        """``{"depth": (N, H, W), "semantics": (N, H, W) raw ids, "semantics_aux": (N, H, W) auxiliary ids,
        "features": (N, F, h, w)}`` (the configured kinds; ``semantics_aux`` with :attr:`has_auxiliary`).

        With :attr:`cache_dir` set, the maps of a frame are read from ``<cache_dir>/<cache_key>/<token>.pt``
        when there, else made and stored (atomically): the maps are a pure function of the frame and the
        settings, and a frame and its neighbours' ``adjacent`` copies share one token.
        """
        self._check(frame)
        path = self._cache_path(frame.token)
        if path is not None and path.is_file():
            try:
                return torch.load(path, weights_only=True)
            except Exception:  # a damaged entry is made again
                pass
        out = self._make_maps(frame)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            torch.save(out, tmp)
            os.replace(tmp, path)
        return out

    def _make_maps(self, frame: Frame) -> dict[str, Tensor]:
        self._check(frame)
        ego, glob = self._points(frame)
        n = frame.num_cameras
        out: dict[str, Tensor] = {}
        if "depth" in self.kinds:
            out["depth"] = torch.stack([self.depth(frame, c) for c in range(n)])
        if "semantics" in self.kinds:
            out["semantics"] = torch.stack([self.semantics(frame, c, ego[c]) for c in range(n)])
            if self.has_auxiliary:
                out["semantics_aux"] = torch.stack([self.auxiliary_semantics(frame, c) for c in range(n)])
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
            from occplug.data.pseudo_labels import merge_semantics

            sources = [self._lut[maps["semantics"].clamp(0, 65535)]]
            if "semantics_aux" in maps:
                sources.append(self._aux_lut[maps["semantics_aux"].clamp(0, 255)])
            out.pseudo_semantics = merge_semantics(sources)
        if "features" in maps:
            out.pseudo_features = maps["features"]
        return out

    def write(
        self,
        frame: Frame,
        root: str | Path,
        cameras: tuple[int, ...] | None = None,
        names: tuple[str, ...] | None = None,
        token: str | None = None,
    ) -> None:
        """Write the frame's pseudo labels under ``root`` in the layout of :mod:`occplug.data.pseudo_labels`.

        ``root/depth/<token>/<camera>.npy`` (float32), ``root/semantics/<token>/<camera>.png``
        (uint8 foreign ids), ``root/semantics_aux/<token>/<camera>.png`` (uint8 auxiliary ids, with
        :attr:`has_auxiliary`), ``root/features/<token>/<camera>.npy`` (float16).

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
            if "semantics_aux" in maps:
                write_map(root / "semantics_aux" / token / f"{name}.png", maps["semantics_aux"][c].numpy())
            if "features" in maps:
                write_npy(root / "features" / token / f"{name}.npy", maps["features"][c].numpy().astype(np.float16))
