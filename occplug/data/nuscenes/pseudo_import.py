"""Per-image pseudo-label maps -> occplug's per-sample layout (``occplug data pseudo-labels nuscenes``).

Depth and segmentation models run on nuScenes images (Metric3D, Grounded-SAM, ...) write one file per
image, named by the image's ``sample_data`` token or by the image file's name. occplug reads pseudo labels
per sample and camera (:mod:`occplug.data.pseudo_labels`)::

    <depth dir>/<sample_data token>.npy            (or <image file stem>.npy / .png; any sub-folders)
      ->  <out>/depth/<sample token>/<CAMERA>.npy|.png
    <semantics dir>/<sample_data token>.png        (or .npy)
      ->  <out>/semantics/<sample token>/<CAMERA>.png
    --mapping FILE  ->  <out>/semantics_mapping.yaml

:func:`import_pseudo_labels` takes the images a prepared index reads (``occplug data prepare nuscenes``:
every camera of every sample, of all splits or the ones named) and looks each one's ``sample_data``
token up in the ``sample_data`` table of the data root. occplug's temporal windows
(``data.adjacent_offsets``, QueryOcc's ``t - 1`` and ``t + 1``) are the neighbouring *key frames* of the
same scene, each read under its own sample token, so the maps of the samples of a split cover every
window of that split. Non-key camera frames (``sweeps/``) are never read: maps of them, like maps of
samples outside the chosen splits, are counted as "not needed" and left out.

Every map is read and checked before the output exists:

* depth ``.npy``: floating point metres, finite and ``>= 0`` (0 = no prediction); ``float16`` /
  ``float32`` files are copied, ``float64`` ones written as ``float32``.
* depth ``.png``: 16-bit, metres * scale (the scale goes into the data config, ``depth: {dir, scale}``);
  copied.
* semantics ``.png``: single-channel 8- or 16-bit class ids, copied; ``.npy``: integer ids in 0..65535,
  written as a PNG (``uint8`` if the ids fit, else ``uint16``).
* every map 2-D (a singleton axis, ``(1, H, W)`` or ``(H, W, 1)``, is dropped) with the image's aspect
  ratio within 1 % (the reader resizes a map of another resolution to the image; a transposed or padded
  map would be stretched); with a mapping table, every semantic id a class of its ``classes:``.

Where one folder holds ``<name>.npy`` and ``<name>.png``, the ``.npy`` is taken (as the reader does). The
output is written into a temporary folder beside ``out`` and renamed to it at the end, so a failure
leaves nothing behind. Every bad input raises :class:`~occplug.data.formats.FormatError` with one line
naming the file and what was expected.
"""

from __future__ import annotations

import os
import secrets
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from tqdm.auto import tqdm

from ..classes import OCC3D_CLASSES
from ..formats import FormatError
from ..imageio import png_bit_depth, read_map, write_map, write_npy
from ..pseudo_labels import load_mapping
from .index import _load_table, read_index

__all__ = ["ASPECT_TOLERANCE", "KINDS", "MAPPING_NAME", "NAMINGS", "ImportSummary", "import_pseudo_labels"]

#: The map kinds converted, each written to ``<out>/<kind>/``.
KINDS = ("depth", "semantics")
#: How input files are named: by the image's ``sample_data`` token, or by the image file's stem.
NAMINGS = ("token", "stem")
#: The mapping table's name in the output folder.
MAPPING_NAME = "semantics_mapping.yaml"
#: Largest relative difference between a map's and its image's aspect ratio (height / width).
ASPECT_TOLERANCE = 0.01
_EXTS = (".npy", ".png")  # in the reader's order of precedence


@dataclass(frozen=True)
class _Image:
    """One camera image the index reads: where its maps go and how its input files are named."""

    token: str  # sample token
    camera: str
    file: str  # image path relative to the data root
    name: str  # sample_data token or file stem (the input files' stem)
    hw: tuple[int, int]  # image height, width in pixels (0, 0 when the table does not say)


@dataclass
class ImportSummary:
    """What :func:`import_pseudo_labels` wrote.

    Attributes:
        out: the output folder.
        samples: samples written (each with every camera).
        splits: samples per split.
        cameras: camera channels, in the index's order.
        inputs: input folder per kind.
        written: per kind, maps written per output extension (``{"depth": {".npy": 30}}``).
        converted: per kind, maps rewritten (dtype, shape or format changed) rather than copied or linked.
        unused: per kind, input maps no image of the chosen splits needs (sweeps, other splits).
        depth_scale: the 16-bit depth PNGs' scale (metres * scale).
        mapping: the copied mapping table in ``out``, or None.
    """

    out: Path
    samples: int
    splits: dict[str, int]
    cameras: tuple[str, ...]
    inputs: dict[str, Path]
    written: dict[str, dict[str, int]] = field(default_factory=dict)
    converted: dict[str, int] = field(default_factory=dict)
    unused: dict[str, int] = field(default_factory=dict)
    depth_scale: float = 256.0
    mapping: Path | None = None

    def data_node(self) -> dict[str, Any]:
        """The ``data.pseudo_labels`` node that reads the output (``MAPPING.yaml`` where no table was given)."""
        node: dict[str, Any] = {}
        if "depth" in self.inputs:
            node["depth"] = {"dir": str(self.out / "depth"), "scale": self.depth_scale}
        if "semantics" in self.inputs:
            node["semantics"] = {
                "dir": str(self.out / "semantics"),
                "mapping": str(self.mapping) if self.mapping else "MAPPING.yaml",
            }
        return node

    def lines(self) -> list[str]:
        """The report the CLI prints."""
        splits = ", ".join(f"{k} {v}" for k, v in self.splits.items())
        lines = [
            f"wrote the pseudo labels of {self.samples} samples x {len(self.cameras)} cameras ({splits}) to {self.out}"
        ]
        for kind, folder in self.inputs.items():
            by_ext = ", ".join(f"{n} {ext}" for ext, n in sorted(self.written[kind].items()))
            lines.append(
                f"  {kind}: {sum(self.written[kind].values())} maps ({by_ext}; {self.converted[kind]} converted) "
                f"from {folder}; {self.unused[kind]} maps there not needed (sweeps or samples outside the splits)"
            )
        node = yaml.safe_dump(self.data_node(), default_flow_style=True, width=1 << 16).strip()
        lines.append(f'read them with: "data.pseudo_labels={node}"')
        return lines


def import_pseudo_labels(
    index: str | Path,
    out: str | Path,
    *,
    depth: str | Path | None = None,
    semantics: str | Path | None = None,
    root: str | Path | None = None,
    name_by: str = "token",
    depth_scale: float = 256.0,
    mapping: str | Path | None = None,
    splits: Sequence[str] | None = None,
    link: bool = False,
    progress: bool = True,
) -> ImportSummary:
    """Check per-image depth / semantic maps and write them in occplug's layout (see the module docstring).

    Args:
        index: a prepared index (its folder or ``nuscenes_index.npz``).
        out: the output folder: absent, or an empty folder (replaced).
        depth: folder of per-image depth maps (searched recursively), or None.
        semantics: folder of per-image semantic maps (searched recursively), or None.
        root: the nuScenes data root whose ``<version>/sample_data.json`` names the images (default: the
            root recorded in the index).
        name_by: ``token`` (files named ``<sample_data token>.npy|.png``) or ``stem`` (named as the image
            file, e.g. ``n015-...__CAM_FRONT__1533151603512404.png``).
        depth_scale: metres * ``depth_scale`` is the value of a 16-bit depth PNG (recorded in the report's
            data node; the files are copied unchanged).
        mapping: the semantic maps' class-mapping table (checked against the Occ3D classes, every id checked
            against its ``classes``, copied to ``<out>/semantics_mapping.yaml``), or None.
        splits: the splits whose samples are written (default: every sample of the index).
        link: hard-link the files that are copied unchanged instead of copying them (same file system).
        progress: show a progress bar.

    Returns:
        The summary of what was written.

    Raises:
        FormatError: a bad index, table, mapping table or map, a map missing for an image, or a file named by
            no image of the tables (one line naming the file).
        ValueError: bad arguments, or ``out`` exists and is not an empty folder.
    """
    inputs = {k: Path(v) for k, v in (("depth", depth), ("semantics", semantics)) if v is not None}
    if not inputs:
        raise ValueError("import_pseudo_labels: give depth and/or semantics, the folders of per-image maps")
    if name_by not in NAMINGS:
        raise ValueError(f"name_by: expected one of {', '.join(NAMINGS)}, got {name_by!r}")
    if not depth_scale > 0:
        raise ValueError(f"depth_scale: expected a positive number, got {depth_scale}")
    if mapping is not None and semantics is None:
        raise ValueError("mapping: a class-mapping table goes with semantic maps (give semantics too)")
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"{out}: exists and is not an empty folder")
    for kind, folder in inputs.items():
        if not folder.is_dir():
            raise FormatError(f"{folder}: no such folder of {kind} maps")

    idx = read_index(index)
    images, known, table, counts = _images(idx, Path(root) if root else Path(idx.meta["root"]), name_by, splits)
    class_ids = None
    if mapping is not None:
        load_mapping(mapping, OCC3D_CLASSES)  # the table's own errors, one line naming it
        class_ids = np.asarray(sorted(yaml.safe_load(Path(mapping).read_text())["classes"]), dtype=np.int64)
    files = {kind: _match(kind, folder, images, known, table, name_by) for kind, folder in inputs.items()}
    needed = {im.name for im in images}
    summary = ImportSummary(
        out=out,
        samples=sum(counts.values()),
        splits=counts,
        cameras=tuple(idx.cameras),
        inputs=inputs,
        written={k: {} for k in inputs},
        converted=dict.fromkeys(inputs, 0),
        unused={k: sum(n not in needed for n in files[k]) for k in inputs},
        depth_scale=float(depth_scale),
    )

    tmp = out.absolute().parent / f".{out.name}.{secrets.token_hex(4)}.tmp"
    tmp.mkdir()
    try:
        for im in tqdm(images, desc="pseudo labels", unit="image", disable=not progress):
            for kind in inputs:
                src, dst = files[kind][im.name], tmp / kind / im.token / im.camera
                ext, converted = _convert(kind, src, dst, im, link, class_ids, mapping)
                summary.written[kind][ext] = summary.written[kind].get(ext, 0) + 1
                summary.converted[kind] += converted
        if mapping is not None:
            shutil.copyfile(mapping, tmp / MAPPING_NAME)
            summary.mapping = out / MAPPING_NAME
        if out.exists():
            out.rmdir()  # empty (checked above)
        os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return summary


def _images(
    idx: Any, root: Path, name_by: str, splits: Sequence[str] | None
) -> tuple[list[_Image], set[str], Path, dict[str, int]]:
    """The images of the chosen samples, every name an input file may have, the table and samples per split."""
    present = sorted({s["split"] for s in idx.samples})
    for split in splits or ():
        if split not in present:
            raise FormatError(f"{idx.path}: no sample of split {split!r} (splits: {', '.join(present) or 'none'})")
    folder = root / idx.meta["version"]
    if not folder.is_dir():
        raise FormatError(f"{folder}: no such folder (expected the nuScenes tables of the index's data root there)")
    table = folder / "sample_data.json"
    rows = _load_table(folder, "sample_data")
    by_file = {r["filename"]: r for r in rows if "filename" in r}
    known = {str(r["token"]) if name_by == "token" else Path(str(r.get("filename", ""))).stem for r in rows}
    images: list[_Image] = []
    counts: dict[str, int] = {}
    hw = idx.arrays["image_hw"]
    for s, rec in enumerate(idx.samples):
        if splits and rec["split"] not in splits:
            continue
        counts[rec["split"]] = counts.get(rec["split"], 0) + 1
        for c, camera in enumerate(idx.cameras):
            file = rec["cams"][c]
            sd = by_file.get(file)
            if sd is None:
                raise FormatError(
                    f"{table}: no record of image {file} ({camera} of sample {rec['token']} in {idx.path}); "
                    "expected the tables the index was prepared from (--root)"
                )
            name = str(sd["token"]) if name_by == "token" else Path(file).stem
            images.append(_Image(rec["token"], camera, file, name, (int(hw[s, c, 0]), int(hw[s, c, 1]))))
    return images, known, table, counts


def _match(
    kind: str, folder: Path, images: list[_Image], known: set[str], table: Path, name_by: str
) -> dict[str, Path]:
    """``{name: file}`` of the maps in ``folder``; every file named by an image of the tables, every image given one."""
    files: dict[str, Path] = {}
    for path in sorted(folder.rglob("*")):
        if path.suffix not in _EXTS or path.name.startswith(".") or not path.is_file():
            continue
        other = files.get(path.stem)
        if other is None or (other.parent == path.parent and path.suffix == ".npy"):
            files[path.stem] = path
        elif other.parent != path.parent:
            raise FormatError(f"{path}: a second {kind} map named {path.stem!r} (also {other}); expected one per image")
    unknown = [n for n in files if n not in known]
    if unknown:
        what, hint = ("sample_data token", "stem") if name_by == "token" else ("image file stem", "token")
        more = f" ({len(unknown) - 1} more files like it)" if len(unknown) > 1 else ""
        raise FormatError(
            f"{files[unknown[0]]}: {unknown[0]!r} is no {what} of {table}{more}; expected files named "
            f"<{what}>.npy|.png (named the other way: --name-by {hint})"
        )
    missing = [im for im in images if im.name not in files]
    if missing:
        im = missing[0]
        more = f"; {len(missing) - 1} more images lack one" if len(missing) > 1 else ""
        raise FormatError(
            f"{folder}: no {kind} map for image {im.file} ({im.camera} of sample {im.token}); expected "
            f"{im.name}.npy or {im.name}.png there or in a sub-folder{more}"
        )
    return files


def _convert(
    kind: str,
    src: Path,
    dst: Path,
    image: _Image,
    link: bool,
    class_ids: np.ndarray | None = None,
    mapping: str | Path | None = None,
) -> tuple[str, bool]:
    """Check the map ``src`` of ``image`` and write it as ``dst`` + extension.

    ``class_ids`` (sorted int64, the ``classes`` of the table ``mapping``): the ids a semantic map may hold.

    Returns:
        The extension written and whether the map was rewritten (rather than copied or linked).
    """
    array = read_map(src)
    squeezed = _check_shape(kind, src, array, image)
    if kind == "depth":
        if src.suffix == ".png":
            bits = png_bit_depth(src)
            if bits != 16:
                raise FormatError(
                    f"{src}: PNG of {bits}-bit samples; expected a 16-bit depth PNG (metres * --depth-scale, 0 = no depth)"
                )
            return _place(src, dst.with_suffix(".png"), link), False
        if not np.issubdtype(array.dtype, np.floating):
            raise FormatError(
                f"{src}: depth map of dtype {array.dtype}; expected float16/32/64 metres "
                "(or a 16-bit .png of metres * --depth-scale)"
            )
        bad = int((~np.isfinite(array) | (array < 0)).sum())
        if bad:
            raise FormatError(f"{src}: {bad} depth values are negative, NaN or infinite; expected metres >= 0")
        if squeezed is None and array.dtype in (np.float16, np.float32):
            return _place(src, dst.with_suffix(".npy"), link), False
        write_npy(dst.with_suffix(".npy"), (array if squeezed is None else squeezed).astype(np.float32))
        return ".npy", True
    if not np.issubdtype(array.dtype, np.integer):
        raise FormatError(f"{src}: semantic map of dtype {array.dtype}; expected integer class ids")
    if array.size and (array.min() < 0 or array.max() > 65535):
        raise FormatError(f"{src}: semantic ids {array.min()}..{array.max()}; expected class ids in 0..65535")
    if class_ids is not None:
        extra = np.setdiff1d(np.unique(array), class_ids)
        if extra.size:
            ids = ", ".join(map(str, extra[:8].tolist())) + (", ..." if extra.size > 8 else "")
            raise FormatError(
                f"{src}: class ids {ids} are not in the 'classes' of {mapping}; expected only ids it lists"
            )
    if src.suffix == ".png":
        return _place(src, dst.with_suffix(".png"), link), False
    write_map(dst.with_suffix(".png"), array if squeezed is None else squeezed)
    return ".png", True


def _check_shape(kind: str, src: Path, array: np.ndarray, image: _Image) -> np.ndarray | None:
    """Raise unless ``array`` is a non-empty 2-D map with the image's aspect ratio; the 2-D view of a map
    with one singleton axis ``(1, H, W)`` / ``(H, W, 1)``, None for a 2-D one."""
    squeezed = None
    if array.ndim == 3 and 1 in (array.shape[0], array.shape[2]):
        squeezed = array.reshape(array.shape[1:] if array.shape[0] == 1 else array.shape[:2])
    hw = (squeezed if squeezed is not None else array).shape
    if len(hw) != 2 or 0 in hw:
        raise FormatError(f"{src}: {kind} map of shape {tuple(array.shape)}; expected (H', W') for image {image.file}")
    h, w = image.hw
    if h > 0 and w > 0 and abs(hw[0] * w / (hw[1] * h) - 1) > ASPECT_TOLERANCE:
        raise FormatError(
            f"{src}: {kind} map of shape {tuple(array.shape)} for image {image.file} of {h} x {w}; expected "
            f"the image's aspect ratio (within {ASPECT_TOLERANCE:.0%}; a transposed, cropped or padded map?)"
        )
    return squeezed


def _place(src: Path, dst: Path, link: bool) -> str:
    """Copy (or hard-link) ``src`` to ``dst``; returns ``dst``'s extension."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    if link:
        try:
            os.link(src, dst)
        except OSError as exc:
            raise FormatError(
                f"{src}: cannot hard-link it into the output ({exc.strerror}); copy it instead (no --link)"
            ) from None
    else:
        shutil.copyfile(src, dst)
    return dst.suffix
