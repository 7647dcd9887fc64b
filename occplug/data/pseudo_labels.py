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

Where both ``<camera>.npy`` and another extension exist, ``.npy`` is read. Depth and semantic maps
may have another resolution than the image: they are resized to the original image (nearest
neighbour, pixel-centre convention) and then follow every image
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

**Several 2D semantic sources** (OccLE: a dataset-specific segmenter for the classes it shares with
the target taxonomy, an open-vocabulary one for the classes it lacks) are a list in precedence
order, each with its own mapping table. Every map is mapped to the target classes first; then each
pixel takes the first source (in list order) that gives it a target class (:func:`merge_semantics`).
The tables decide what each source may supply: an auxiliary table that maps only the classes the
primary lacks fills exactly those pixels where the primary is silent (the primary first); to let an
auxiliary class override the primary (OccLE's SAM2 trunk masks drawn over MSeg), list that source
first with a table mapping only that class.

The ``pseudo_labels`` argument::

    pseudo_labels:
      depth: DIR                      # or {dir: DIR, scale: 256.0}
      semantics: {dir: DIR, mapping: FILE.yaml}
                                      # or a list [{dir, mapping}, {dir, mapping}, ...], in precedence order
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

from occplug.errors import closest

from .formats import FormatError, load_npz
from .frame import Frame
from .imageio import read_map

__all__ = ["FEATURES_KEY", "IGNORE", "PseudoLabelSource", "load_mapping", "merge_semantics"]

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
        raise FormatError(
            f"{path}: invalid YAML ({getattr(exc, 'problem', None) or str(exc).splitlines()[0]})"
        ) from None
    if not isinstance(data, dict) or not isinstance(data.get("classes"), dict) or not isinstance(data.get("map"), dict):
        raise FormatError(
            f"{path}: a class-mapping table needs 'classes' (foreign id -> name) and 'map' (foreign class -> target class)"
        )
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


def merge_semantics(maps: Sequence[Tensor], ignore: int = IGNORE) -> Tensor:
    """Merge semantic maps already in the target taxonomy, by precedence.

    Args:
        maps: equal-shape integer maps (any shape, e.g. ``(N, H, W)``), highest precedence first;
            ``ignore`` marks a pixel the source says nothing about.
        ignore: the id of "no class".

    Returns:
        The maps' shape and dtype: each pixel's value from the first map that is not ``ignore`` there
        (``ignore`` where none speaks).
    """
    if not maps:
        raise ValueError("merge_semantics: no maps")
    shapes = {tuple(m.shape) for m in maps}
    if len(shapes) > 1:
        raise ValueError(f"merge_semantics: maps of different shapes {sorted(shapes)}")
    out = maps[0].clone()
    for m in maps[1:]:
        out = torch.where(out == ignore, m.to(out.dtype), out)
    return out


@dataclass(frozen=True)
class _Source:
    kind: str
    dir: Path
    scale: float = 256.0
    lut: np.ndarray | None = None

    def path(self, token: str, camera: str) -> Path:
        folder = self.dir / token
        for ext in (".npy", ".npz") if self.kind == "features" else (".npy", ".png"):
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
                raise ValueError(
                    f"pseudo_labels.{key}: unknown key{f'; did you mean {hint!r}?' if hint else ''} "
                    f"(valid: {', '.join(_KINDS)}, missing)"
                )
        self.missing = sources.get("missing", "error")
        if self.missing not in ("error", "empty"):
            raise ValueError(f"pseudo_labels.missing: expected 'error' or 'empty', got {self.missing!r}")
        root = Path(base) if base else Path()
        self.sources: dict[str, _Source] = {}
        #: The semantic sources in precedence order (``sources["semantics"]`` is the first).
        self.semantic_sources: list[_Source] = []
        for kind in _KINDS:
            spec = sources.get(kind)
            if spec is None or spec is False:
                continue
            if kind == "semantics" and isinstance(spec, list):
                if not spec:
                    raise ValueError("pseudo_labels.semantics: an empty list (give at least one {dir, mapping})")
                for i, item in enumerate(spec):
                    self.semantic_sources.append(
                        self._source(kind, item, root, class_names, f"pseudo_labels.semantics[{i}]")
                    )
            else:
                source = self._source(kind, spec, root, class_names, f"pseudo_labels.{kind}")
                if kind == "semantics":
                    self.semantic_sources.append(source)
                else:
                    self.sources[kind] = source
        if self.semantic_sources:
            self.sources["semantics"] = self.semantic_sources[0]

    @staticmethod
    def _source(kind: str, spec: Any, root: Path, class_names: Sequence[str], where: str) -> _Source:
        if not isinstance(spec, (str, dict)):
            raise ValueError(f"{where}: expected a folder or a mapping {{dir, ...}}, got {type(spec).__name__}")
        cfg = {"dir": spec} if isinstance(spec, str) else dict(spec)
        valid = {"depth": ("dir", "scale"), "semantics": ("dir", "mapping"), "features": ("dir",)}[kind]
        for key in cfg:
            if key not in valid:
                raise ValueError(f"{where}.{key}: unknown key (valid: {', '.join(valid)})")
        if "dir" not in cfg:
            raise ValueError(f"{where}: needs 'dir', the folder holding <token>/<camera> files")
        folder = root / str(cfg["dir"])
        if not folder.is_dir():
            raise FileNotFoundError(f"{where}.dir: {folder} is not a folder")
        lut = None
        if kind == "semantics":
            if "mapping" not in cfg:
                raise ValueError(f"{where}: needs 'mapping', the YAML class-mapping table")
            lut = load_mapping(root / str(cfg["mapping"]), class_names)
        return _Source(kind, folder, float(cfg.get("scale", 256.0)), lut)

    @classmethod
    def from_config(
        cls, sources: dict[str, Any] | None, class_names: Sequence[str], base: str | Path | None = None
    ) -> PseudoLabelSource | None:
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
            out.pseudo_depth = torch.stack(
                [
                    torch.zeros(h, w) if m is None else _resize_nearest(torch.from_numpy(m.astype(np.float32)), (h, w))
                    for m in maps
                ]
            )
        if self.semantic_sources:
            out.pseudo_semantics = merge_semantics([self._semantics(src, frame) for src in self.semantic_sources])
        if "features" in self.sources:
            maps = [self._read(self.sources["features"], frame.token, cam) for cam in frame.camera_names]
            shapes = {m.shape for m in maps if m is not None}
            if len(shapes) > 1:
                raise FormatError(
                    f"{self.sources['features'].dir / frame.token}: cameras have feature maps of different shapes {sorted(shapes)}"
                )
            if not shapes:
                out.pseudo_features = None
            else:
                shape = shapes.pop()
                out.pseudo_features = torch.stack(
                    [torch.zeros(shape) if m is None else torch.from_numpy(m.astype(np.float32)) for m in maps]
                )
        return out

    def _semantics(self, src: _Source, frame: Frame) -> Tensor:
        """``(N, H, W)`` int64 target ids of one semantic source (255 where it has no target class)."""
        assert src.lut is not None
        h, w = frame.image_size
        sem = []
        for cam in frame.camera_names:
            m = self._read(src, frame.token, cam)
            if m is None:
                sem.append(torch.full((h, w), IGNORE, dtype=torch.int64))
                continue
            ids = m.astype(np.int64)
            if ids.size and (ids.min() < 0 or ids.max() > 65535):
                raise FormatError(f"{src.dir / frame.token}: semantic ids outside 0..65535")
            mapped = torch.from_numpy(src.lut[ids].astype(np.int64))
            sem.append(_resize_nearest(mapped, (h, w)))
        return torch.stack(sem)


def _resize_nearest(x: Tensor, hw: tuple[int, int]) -> Tensor:
    """Nearest-neighbour resize of a 2-D map with the pixel-centre convention (source ``floor((v + 0.5) * H / H')``)."""
    if tuple(x.shape) == tuple(hw):
        return x
    rows = (
        ((torch.arange(hw[0], dtype=torch.float64) + 0.5) * x.shape[0] / hw[0]).floor().long().clamp(max=x.shape[0] - 1)
    )
    cols = (
        ((torch.arange(hw[1], dtype=torch.float64) + 0.5) * x.shape[1] / hw[1]).floor().long().clamp(max=x.shape[1] - 1)
    )
    return x[rows][:, cols]
