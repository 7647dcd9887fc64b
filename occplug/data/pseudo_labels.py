"""Pseudo labels read from files: per-camera depth maps, 2D semantics in a foreign taxonomy, feature maps.

occplug never runs or downloads a foundation model. A user runs Metric3D / MSeg / SAM2 / DINO (or
anything else) on the data set's images, writes the outputs in this layout, and points the data
module's ``pseudo_labels`` argument at them. ``<token>`` is ``Frame.token`` (the nuScenes sample
token, ``08_000123`` for SemanticKITTI) and ``<camera>`` a name of ``Frame.camera_names``
(``CAM_FRONT``, ..., ``image_2``)::

    <depth dir>/<token>/<camera>.npy       (H', W') float16/float32 metres; 0 = no prediction
    <depth dir>/<token>/<camera>.png       (H', W') uint16 PNG, metres * scale (default 256, KITTI's
                                           depth-map convention); 0 = no prediction
    <semantics dir>/<token>/<camera>.png   (H', W') uint8 or uint16 single-channel PNG of foreign class ids
    <semantics dir>/<token>/<camera>.npy   (H', W') integer foreign class ids
    <features dir>/<token>/<camera>.npy    (F, h, w) float16/float32 low-resolution features
    <features dir>/<token>/<camera>.npz    the same array under the key ``features`` (e.g. written with
                                           ``numpy.savez_compressed(path, features=array)``)

Where both ``<camera>.npy`` and another extension exist, ``.npy`` is read. Depth and semantic maps may have another resolution than the image: they are resized to the
original image (nearest neighbour, pixel-centre convention) and then follow every image
augmentation. Feature maps keep their resolution (they must cover the whole original image).

The foreign taxonomy is mapped to the data set's classes with a YAML table::

    classes:                 # every foreign id the maps may contain -> its name
      98: road
      100: sidewalk_pavement
      142: sky
    map:                     # foreign name (or id) -> target class name, or "ignore"
      road: driveable_surface
      sidewalk_pavement: sidewalk
      sky: ignore

Foreign ids missing from ``map`` (or mapped to ``ignore``) become 255 in ``Frame.pseudo_semantics``.
Several foreign classes may map to one target class (a split in the foreign taxonomy); one foreign
class covering several target classes (a merge) cannot be undone and is the table's author's choice,
as in OccLE's Table B.1.

The ``pseudo_labels`` argument::

    pseudo_labels:
      depth: DIR                      # or {dir: DIR, scale: 256.0}
      semantics: {dir: DIR, mapping: FILE.yaml}
      features: DIR                   # or {dir: DIR}
      missing: error                  # error | empty (a missing file gives an empty map instead)

Every problem (a missing file, an unknown class in the table, a wrong shape) raises
:class:`~occplug.data.formats.FormatError` (a ``ValueError``) with one line naming the file.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from torch import Tensor

from occplug.registry import closest

from .formats import FormatError, load_npz
from .frame import Frame
from .imageio import read_map

__all__ = ["FEATURES_KEY", "IGNORE", "PseudoLabelSource", "load_mapping"]

#: ``Frame.pseudo_semantics`` id of pixels without a target class.
IGNORE = 255
_KINDS = ("depth", "semantics", "features")
#: The array of a feature map stored as ``.npz``.
FEATURES_KEY = "features"


def load_mapping(path: str | Path, class_names: Sequence[str]) -> np.ndarray:
    """Read a class-mapping table (see the module docstring) as a lookup table.

    Args:
        path: the YAML file.
        class_names: the target taxonomy (index = id).

    Returns:
        ``(65536,)`` uint8: ``lut[foreign id]`` = target id or 255.

    Raises:
        FormatError: one line naming the file (unreadable, malformed, an unknown foreign or target class).
    """
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: no such class-mapping file")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise FormatError(f"{path}: invalid YAML ({getattr(exc, 'problem', None) or str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict) or not isinstance(data.get("classes"), dict) or not isinstance(data.get("map"), dict):
        raise FormatError(f"{path}: a class-mapping table needs 'classes' (foreign id -> name) and 'map' (foreign class -> target class)")
    names: dict[str, int] = {}
    for key, name in data["classes"].items():
        if not isinstance(key, int) or not 0 <= key < 65536:
            raise FormatError(f"{path}: classes: foreign ids must be integers 0..65535, got {key!r}")
        if str(name) in names:
            raise FormatError(f"{path}: classes: name '{name}' is used by ids {names[str(name)]} and {key}")
        names[str(name)] = key
    targets = {name: i for i, name in enumerate(class_names)}
    lut = np.full(1 << 16, IGNORE, dtype=np.uint8)
    for source, target in data["map"].items():
        if isinstance(source, int) and source in data["classes"]:
            fid = source
        elif str(source) in names:
            fid = names[str(source)]
        else:
            hint = closest(str(source), list(names))
            raise FormatError(
                f"{path}: map: unknown foreign class '{source}' (not in 'classes'{f'; did you mean {hint!r}?' if hint else ''})"
            )
        if target == "ignore" or target is None:
            continue
        if str(target) not in targets:
            hint = closest(str(target), list(targets))
            raise FormatError(
                f"{path}: map.{source}: unknown target class '{target}'"
                f"{f'; did you mean {hint!r}?' if hint else ''} (target classes: {', '.join(class_names)}, or ignore)"
            )
        lut[fid] = targets[str(target)]
    return lut


@dataclass(frozen=True)
class _Source:
    kind: str
    dir: Path
    scale: float = 256.0
    lut: np.ndarray | None = None

    def path(self, token: str, camera: str) -> Path:
        folder = self.dir / token
        for ext in ((".npy", ".npz") if self.kind == "features" else (".npy", ".png")):
            candidate = folder / f"{camera}{ext}"
            if candidate.is_file():
                return candidate
        return folder / f"{camera}{'.npy' if self.kind == 'features' else '.png'}"


class PseudoLabelSource:
    """Attaches file-based pseudo labels to frames (see the module docstring for layouts and config).

    Args:
        sources: the ``pseudo_labels`` mapping.
        class_names: the target taxonomy, for the semantic mapping table.
        base: folder that relative paths in ``sources`` are resolved against (default: the working directory).
    """

    def __init__(self, sources: dict[str, Any], class_names: Sequence[str], base: str | Path | None = None) -> None:
        if not isinstance(sources, dict):
            raise ValueError(f"pseudo_labels: expected a mapping of {', '.join(_KINDS)}, got {type(sources).__name__}")
        for key in sources:
            if key not in (*_KINDS, "missing"):
                hint = closest(str(key), [*_KINDS, "missing"])
                raise ValueError(f"pseudo_labels.{key}: unknown key{f'; did you mean {hint!r}?' if hint else ''} "
                                 f"(valid: {', '.join(_KINDS)}, missing)")
        self.missing = sources.get("missing", "error")
        if self.missing not in ("error", "empty"):
            raise ValueError(f"pseudo_labels.missing: expected 'error' or 'empty', got {self.missing!r}")
        root = Path(base) if base else Path()
        self.sources: dict[str, _Source] = {}
        for kind in _KINDS:
            spec = sources.get(kind)
            if spec is None or spec is False:
                continue
            cfg = {"dir": spec} if isinstance(spec, str) else dict(spec)
            valid = {"depth": ("dir", "scale"), "semantics": ("dir", "mapping"), "features": ("dir",)}[kind]
            for key in cfg:
                if key not in valid:
                    raise ValueError(f"pseudo_labels.{kind}.{key}: unknown key (valid: {', '.join(valid)})")
            if "dir" not in cfg:
                raise ValueError(f"pseudo_labels.{kind}: needs 'dir', the folder holding <token>/<camera> files")
            folder = root / str(cfg["dir"])
            if not folder.is_dir():
                raise FileNotFoundError(f"pseudo_labels.{kind}.dir: {folder} is not a folder")
            lut = None
            if kind == "semantics":
                if "mapping" not in cfg:
                    raise ValueError("pseudo_labels.semantics: needs 'mapping', the YAML class-mapping table")
                lut = load_mapping(root / str(cfg["mapping"]), class_names)
            self.sources[kind] = _Source(kind, folder, float(cfg.get("scale", 256.0)), lut)

    @classmethod
    def from_config(cls, sources: dict[str, Any] | None, class_names: Sequence[str],
                    base: str | Path | None = None) -> PseudoLabelSource | None:
        """None for an empty config, else a source (validated now: bad config fails at construction)."""
        return cls(sources, class_names, base) if sources else None

    def _read(self, src: _Source, token: str, camera: str) -> np.ndarray | None:
        path = src.path(token, camera)
        if not path.is_file() and self.missing == "empty":
            return None
        if path.suffix == ".npz":
            data = load_npz(path)
            if FEATURES_KEY not in data:
                raise FormatError(f"{path}: no '{FEATURES_KEY}' array (keys: {', '.join(sorted(data)) or 'none'})")
            array = data[FEATURES_KEY]
        else:
            array = read_map(path)
        expected = 3 if src.kind == "features" else 2
        if array.ndim != expected:
            layout = "(F, h, w)" if expected == 3 else "(H, W)"
            raise FormatError(f"{path}: {src.kind} map has shape {tuple(array.shape)}; expected {layout}")
        if src.kind == "depth" and path.suffix == ".png":
            return array.astype(np.float32) / src.scale
        if src.kind == "semantics" and not np.issubdtype(array.dtype, np.integer):
            raise FormatError(f"{path}: semantic map has dtype {array.dtype}; expected integer class ids")
        return array

    def attach(self, frame: Frame) -> Frame:
        """A copy of ``frame`` with ``pseudo_depth`` / ``pseudo_semantics`` / ``pseudo_features`` filled.

        Call it on frames as decoded (before any resize or augmentation): maps are resized to the
        current image size, which must still be the original one.
        """
        if not self.sources:
            return frame
        out = copy.copy(frame)
        h, w = frame.image_size
        if "depth" in self.sources:
            maps = [self._read(self.sources["depth"], frame.token, cam) for cam in frame.camera_names]
            out.pseudo_depth = torch.stack([
                torch.zeros(h, w) if m is None else _resize_nearest(torch.from_numpy(m.astype(np.float32)), (h, w))
                for m in maps
            ])
        if "semantics" in self.sources:
            src = self.sources["semantics"]
            assert src.lut is not None
            maps = [self._read(src, frame.token, cam) for cam in frame.camera_names]
            sem = []
            for m in maps:
                if m is None:
                    sem.append(torch.full((h, w), IGNORE, dtype=torch.int64))
                    continue
                ids = m.astype(np.int64)
                if ids.size and (ids.min() < 0 or ids.max() > 65535):
                    raise FormatError(f"{src.dir / frame.token}: semantic ids outside 0..65535")
                mapped = torch.from_numpy(src.lut[ids].astype(np.int64))
                sem.append(_resize_nearest(mapped, (h, w)))
            out.pseudo_semantics = torch.stack(sem)
        if "features" in self.sources:
            maps = [self._read(self.sources["features"], frame.token, cam) for cam in frame.camera_names]
            shapes = {m.shape for m in maps if m is not None}
            if len(shapes) > 1:
                raise FormatError(f"{self.sources['features'].dir / frame.token}: cameras have feature maps of different shapes {sorted(shapes)}")
            if not shapes:
                out.pseudo_features = None
            else:
                shape = shapes.pop()
                out.pseudo_features = torch.stack([
                    torch.zeros(shape) if m is None else torch.from_numpy(m.astype(np.float32)) for m in maps
                ])
        return out


def _resize_nearest(x: Tensor, hw: tuple[int, int]) -> Tensor:
    """Nearest-neighbour resize of a 2-D map with the pixel-centre convention (source ``floor((v + 0.5) * H / H')``)."""
    if tuple(x.shape) == tuple(hw):
        return x
    rows = ((torch.arange(hw[0], dtype=torch.float64) + 0.5) * x.shape[0] / hw[0]).floor().long().clamp(max=x.shape[0] - 1)
    cols = ((torch.arange(hw[1], dtype=torch.float64) + 0.5) * x.shape[1] / hw[1]).floor().long().clamp(max=x.shape[1] - 1)
    return x[rows][:, cols]
