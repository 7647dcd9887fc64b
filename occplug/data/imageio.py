"""Reading and writing images and per-pixel maps (kornia's Rust codecs; no extra dependency).

Every reader raises :class:`~occplug.data.formats.FormatError` (a ``ValueError``) with one line
naming the file when it is missing or cannot be decoded.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import torch
from kornia import io as kio
from torch import Tensor

from .formats import FormatError

__all__ = ["png_bit_depth", "read_map", "read_rgb", "write_map", "write_npy", "write_rgb"]


def _fail(path: Path, exc: BaseException) -> FormatError:
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return FormatError(f"{path}: cannot read ({text})")


def read_rgb(path: str | Path) -> Tensor:
    """An 8-bit colour image (JPEG, PNG, ...) as ``(3, H, W)`` float32 in [0, 1] (exact multiples of 1/255)."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: no such file")
    try:
        img = kio.load_image(path, kio.ImageLoadType.RGB8)
    except Exception as exc:  # kornia-rs raises ValueError or bare Exception for undecodable files
        raise _fail(path, exc) from None
    return img.to(torch.float32) / 255


def _atomic(path: Path, write) -> None:  # noqa: ANN001
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_rgb(path: str | Path, image: Tensor) -> None:
    """Write ``(3, H, W)`` float [0, 1] as an 8-bit image (the extension picks the codec: ``.png`` is lossless)."""
    data = torch.round(image.detach().cpu().clamp(0, 1) * 255).to(torch.uint8).contiguous()
    _atomic(Path(path), lambda tmp: kio.write_image(tmp, data))


def read_map(path: str | Path) -> np.ndarray:
    """A single-channel map: ``.npy`` (any dtype, 2-D or 3-D) or a 1-channel 8/16-bit ``.png`` (2-D)."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: no such file")
    if path.suffix == ".npy":
        try:
            return np.load(path, allow_pickle=False)
        except Exception as exc:
            raise _fail(path, exc) from None
    try:
        img = kio.load_image(path, kio.ImageLoadType.UNCHANGED)
    except Exception as exc:
        raise _fail(path, exc) from None
    if img.shape[0] != 1:
        raise FormatError(f"{path}: expected a single-channel image, got {img.shape[0]} channels")
    return img[0].to(torch.int32).numpy()


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_bit_depth(path: str | Path) -> int:
    """The bits per sample of a PNG (1, 2, 4, 8 or 16), read from its header alone (``IHDR``, bytes 8-25).

    :func:`read_map` returns every PNG as int32, so this is how a 16-bit map (depth in metres * scale) is told
    from an 8-bit one.

    Raises:
        FormatError: a missing file or one that does not start as a PNG (one line naming it).
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(26)
    except OSError as exc:
        raise _fail(path, exc) from None
    if len(head) < 26 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise FormatError(f"{path}: cannot read (not a PNG file)")
    return head[24]


def write_npy(path: str | Path, array: np.ndarray) -> None:
    """Write an ``.npy`` file atomically."""
    _atomic(Path(path), lambda tmp: np.save(tmp, array, allow_pickle=False))


def write_map(path: str | Path, array: np.ndarray | Tensor) -> None:
    """Write a 2-D integer map as a 1-channel PNG (``uint8`` if it fits, else ``uint16``) or any array as ``.npy``."""
    path = Path(path)
    arr = array.detach().cpu().numpy() if isinstance(array, Tensor) else np.asarray(array)
    if path.suffix == ".npy":
        write_npy(path, arr)
        return
    if arr.ndim != 2 or (arr.size and (arr.min() < 0 or arr.max() > 65535)):
        raise ValueError(f"{path}: a PNG map must be 2-D with values in 0..65535")
    dtype = torch.uint8 if not arr.size or arr.max() <= 255 else torch.uint16
    data = torch.from_numpy(arr.astype(np.int32)).to(dtype)[None].contiguous()
    _atomic(path, lambda tmp: kio.write_image(tmp, data))
