"""Image encoders: output shapes and strides, input checks, the optional timm path."""

from __future__ import annotations

import pickle
import sys

import pytest
import torch

from occplug.components import SmallCNN, TimmEncoder
from occplug.components.encoders import load_state_dict_file
from occplug.errors import UserError


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


def test_timm_encoder_whose_timm_does_not_import_names_the_install(tmp_path, monkeypatch) -> None:
    """PyPI's torchvision beside the CPU torch makes ``import timm`` raise RuntimeError: one line says what works."""
    broken = tmp_path / "timm"
    broken.mkdir()
    (broken / "__init__.py").write_text("raise RuntimeError('operator torchvision::nms does not exist')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "timm", raising=False)
    with pytest.raises(UserError) as info:
        TimmEncoder(model_name="resnet18")
    message = str(info.value)
    assert "\n" not in message and "operator torchvision::nms does not exist" in message
    assert "pip install torch==2.14.1 torchvision==0.29.1" in message


def test_timm_encoder_shapes_and_freeze() -> None:
    torch.manual_seed(0)
    images = torch.rand(1, 2, 3, 64, 96)
    deep = TimmEncoder(model_name="resnet18", out_channels=16)
    assert deep.stride == 32
    assert deep(images).shape == (1, 2, 16, 2, 3)
    mid = TimmEncoder(model_name="resnet18", out_channels=16, feature_level=2)
    assert mid.stride == 8
    assert mid(images).shape == (1, 2, 16, 8, 12)
    with pytest.raises(ValueError, match="divisible"):
        mid(torch.rand(1, 1, 3, 60, 96))

    frozen = TimmEncoder(model_name="resnet18", out_channels=16, feature_level=1, freeze=True)
    frozen.train()
    assert not frozen.backbone.training and frozen.neck.training
    frozen(images).sum().backward()
    assert all(p.grad is None for p in frozen.backbone.parameters())
    assert frozen.neck.weight.grad is not None


def _save(state: dict[str, torch.Tensor], path) -> str:
    if str(path).endswith(".safetensors"):
        from safetensors.torch import save_file

        save_file({k: v.contiguous() for k, v in state.items()}, str(path))
    else:
        torch.save(state, path)
    return str(path)


@pytest.mark.parametrize(
    ("name", "level", "suffix"),
    [("convnext_atto", 1, "pth"), ("convnext_atto", -1, "safetensors"), ("resnet18", 2, "pth")],
)
def test_a_timm_state_dict_saved_as_a_user_saves_it_loads(tmp_path, name, level, suffix) -> None:
    """``torch.save(timm.create_model(name).state_dict(), f)`` (ImageNet's classifier included) loads into the
    ``features_only`` backbone, whose names differ for ConvNeXt (``stem_0``); the features are timm's own."""
    import timm

    torch.manual_seed(0)
    source = timm.create_model(name).eval()
    path = _save(source.state_dict(), tmp_path / f"{name}.{suffix}")
    torch.manual_seed(1)  # another random init, overwritten by the file
    encoder = TimmEncoder(model_name=name, out_channels=8, feature_level=level, weights=path).eval()
    if name.startswith("convnext"):
        assert "stem_0.weight" in encoder.backbone.state_dict()  # the wrapper's names are not the file's
    x = torch.rand(2, 3, 64, 96)
    with torch.no_grad():
        (expected,) = source.forward_intermediates(encoder.standardise(x), indices=[level], intermediates_only=True)
        (got,) = encoder.backbone(encoder.standardise(x))
    torch.testing.assert_close(got, expected, rtol=0, atol=0)
    # a file without the classifier (saved with num_classes=0) loads too
    headless = _save(timm.create_model(name, num_classes=0).state_dict(), tmp_path / f"headless.{suffix}")
    TimmEncoder(model_name=name, feature_level=level, weights=headless)


def test_a_timm_file_of_another_model_is_one_error_line(tmp_path) -> None:
    import timm

    resnet = _save(timm.create_model("resnet18").state_dict(), tmp_path / "resnet18.pth")
    with pytest.raises(UserError) as info:
        TimmEncoder(model_name="convnext_atto", weights=resnet)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"model.encoder.weights: {resnet} is not a state dict of timm's 'convnext_atto' (")
    assert "missing key(s): stem.0.weight" in message and "unexpected key(s): conv1.weight" in message

    state = timm.create_model("convnext_atto").state_dict()
    partial = _save({k: v for k, v in state.items() if not k.startswith("stages.3")}, tmp_path / "partial.pth")
    with pytest.raises(UserError, match=r"partial.pth is not a state dict .*\(\d+ missing key\(s\): stages.3"):
        TimmEncoder(model_name="convnext_atto", weights=partial)
    # same names, other widths: the first tensor whose shape differs
    femto = _save(timm.create_model("convnext_femto").state_dict(), tmp_path / "femto.pth")
    with pytest.raises(UserError, match=r"femto.pth: stem.0.weight is \(48, 3, 4, 4\) but timm's 'convnext_atto' has"):
        TimmEncoder(model_name="convnext_atto", weights=femto)
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(UserError, match=r"junk.pth cannot be read as a state dict"):
        TimmEncoder(model_name="convnext_atto", weights=str(tmp_path / "junk.pth"))
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        TimmEncoder(model_name="resnet18", weights=str(tmp_path / "missing.pt"))
