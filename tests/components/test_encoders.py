"""Image encoders: output shapes and strides, input checks, the optional timm path."""

from __future__ import annotations

import pickle
import sys

import pytest
import torch

from occplug.components import SmallCNN, TimmEncoder
from occplug.components.encoders import load_state_dict_file


@pytest.mark.parametrize("stride", [4, 8, 16])
def test_small_cnn_shape_and_stride(stride: int) -> None:
    torch.manual_seed(0)
    enc = SmallCNN(out_channels=24, width=8, stride=stride)
    images = torch.rand(2, 3, 3, 32, 48)
    out = enc(images)
    assert enc.stride == stride and enc.out_channels == 24
    assert out.shape == (2, 3, 24, 32 // stride, 48 // stride)
    assert torch.isfinite(out).all()


def test_small_cnn_views_are_independent_and_trainable() -> None:
    """Each view is encoded on its own (eval mode), and every parameter gets a gradient."""
    torch.manual_seed(0)
    enc = SmallCNN(out_channels=16, width=8, stride=8, num_blocks=2, norm="group")
    images = torch.rand(1, 2, 3, 32, 32)
    enc.eval()
    both = enc(images)
    alone = enc(images[:, 1:])
    torch.testing.assert_close(both[:, 1:], alone)
    enc.train()
    enc(images).square().mean().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in enc.parameters())
    pickle.loads(pickle.dumps(enc))


def test_small_cnn_rejects_indivisible_images_and_bad_stride() -> None:
    enc = SmallCNN(width=8, stride=8)
    with pytest.raises(ValueError, match="not divisible by the encoder stride 8"):
        enc(torch.rand(1, 1, 3, 36, 48))
    with pytest.raises(ValueError, match="stride must be 4, 8 or 16"):
        SmallCNN(stride=2)  # type: ignore[arg-type]


def test_timm_encoder_without_timm_says_how_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "timm", None)  # makes `import timm` fail even where it is installed
    with pytest.raises(ImportError) as info:
        TimmEncoder(model_name="resnet18")
    assert str(info.value) == "the 'timm' encoder needs timm: pip install 'occplug[timm]'"


def test_weights_file_loading(tmp_path) -> None:
    missing = tmp_path / "nope.pt"
    with pytest.raises(FileNotFoundError, match="nope.pt"):
        load_state_dict_file(str(missing))
    state = {"a": torch.arange(3.0)}
    torch.save({"state_dict": state}, tmp_path / "wrapped.pt")
    torch.testing.assert_close(load_state_dict_file(str(tmp_path / "wrapped.pt")), state)


def test_timm_encoder_shapes_weights_round_trip_and_freeze(tmp_path) -> None:
    pytest.importorskip("timm")
    torch.manual_seed(0)
    images = torch.rand(1, 2, 3, 64, 96)
    deep = TimmEncoder(model_name="resnet18", out_channels=16)
    assert deep.stride == 32
    assert deep(images).shape == (1, 2, 16, 2, 3)
    mid = TimmEncoder(model_name="resnet18", out_channels=16, feature_level=2)
    assert mid.stride == 8
    assert mid(images).shape == (1, 2, 16, 8, 12)

    path = tmp_path / "backbone.pt"
    torch.save(mid.backbone.state_dict(), path)
    torch.manual_seed(1)  # a different random init, overwritten by the file
    loaded = TimmEncoder(model_name="resnet18", out_channels=16, feature_level=2, weights=str(path))
    loaded.neck.load_state_dict(mid.neck.state_dict())
    mid.eval()
    loaded.eval()
    torch.testing.assert_close(loaded(images), mid(images), rtol=0, atol=0)

    with pytest.raises(FileNotFoundError, match="missing.pt"):
        TimmEncoder(model_name="resnet18", weights=str(tmp_path / "missing.pt"))

    frozen = TimmEncoder(model_name="resnet18", out_channels=16, feature_level=1, freeze=True)
    frozen.train()
    assert not frozen.backbone.training and frozen.neck.training
    frozen(images).sum().backward()
    assert all(p.grad is None for p in frozen.backbone.parameters())
    assert frozen.neck.weight.grad is not None
