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


class _FakeFeatureInfo:
    def __init__(self, reductions: list[int], channels: list[int]) -> None:
        self._reductions, self._channels = reductions, channels

    def reduction(self) -> list[int]:
        return self._reductions

    def channels(self) -> list[int]:
        return self._channels


class _FakeFeatures(torch.nn.Module):
    """timm's ``features_only`` contract in miniature: three stride-2 stages, ``out_indices`` picks the outputs."""

    def __init__(self, out_indices: tuple[int, ...]) -> None:
        super().__init__()
        widths = [3, 4, 8, 16]
        self.stages = torch.nn.ModuleList(
            torch.nn.Sequential(torch.nn.Conv2d(widths[i], widths[i + 1], 3, 2, 1), torch.nn.BatchNorm2d(widths[i + 1]))
            for i in range(3)
        )
        self.picked = [range(3)[i] for i in out_indices]
        self.feature_info = _FakeFeatureInfo([2 ** (i + 1) for i in self.picked], [widths[i + 1] for i in self.picked])

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for i, stage in enumerate(self.stages):
            x = stage(x)
            if i in self.picked:
                out.append(x)
        return out


def test_timm_wrapper_against_a_stand_in_timm(tmp_path, monkeypatch) -> None:
    """The wrapper's own logic (no download, local weights, strict keys, stride, neck, freeze) where timm is absent.

    CI cannot install timm beside the CPU torch build (timm pulls torchvision, which pulls another torch),
    so this stand-in holds timm's ``create_model(..., features_only=True, out_indices=...)`` contract.
    """
    import sys
    import types

    calls = []

    def create_model(name: str, pretrained: bool, features_only: bool, out_indices: tuple[int, ...]) -> _FakeFeatures:
        calls.append((name, pretrained, features_only, out_indices))
        return _FakeFeatures(out_indices)

    monkeypatch.setitem(sys.modules, "timm", types.SimpleNamespace(create_model=create_model))
    torch.manual_seed(0)
    images = torch.rand(1, 2, 3, 16, 24)
    deep = TimmEncoder(model_name="fake", out_channels=5)
    assert calls[-1] == ("fake", False, True, (-1,))  # never pretrained=True: nothing is downloaded
    assert deep.stride == 8 and deep(images).shape == (1, 2, 5, 2, 3)
    mid = TimmEncoder(model_name="fake", out_channels=5, feature_level=1)
    assert mid.stride == 4 and mid(images).shape == (1, 2, 5, 4, 6)

    path = tmp_path / "backbone.pt"
    torch.save({"model": {**mid.backbone.state_dict(), "head.fc.weight": torch.zeros(2)}}, path)  # extra head keys
    torch.manual_seed(1)
    loaded = TimmEncoder(model_name="fake", out_channels=5, feature_level=1, weights=str(path))
    loaded.neck.load_state_dict(mid.neck.state_dict())
    mid.eval()
    loaded.eval()
    torch.testing.assert_close(loaded(images), mid(images), rtol=0, atol=0)

    partial = tmp_path / "partial.pt"
    torch.save({k: v for k, v in mid.backbone.state_dict().items() if not k.startswith("stages.2")}, partial)
    with pytest.raises(ValueError, match=r"partial.pt does not fit timm model 'fake': \d+ missing key\(s\): stages.2"):
        TimmEncoder(model_name="fake", weights=str(partial))

    frozen = TimmEncoder(model_name="fake", out_channels=5, feature_level=1, freeze=True)
    frozen.train()
    assert not frozen.backbone.training and frozen.neck.training
    frozen(images).sum().backward()
    assert all(p.grad is None for p in frozen.backbone.parameters()) and frozen.neck.weight.grad is not None
    with pytest.raises(ValueError, match="divisible"):
        deep(torch.rand(1, 1, 3, 15, 24))
