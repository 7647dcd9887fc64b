"""voxel_ce: equals a hand-computed cross-entropy on the counted voxels, and trains."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from torch import Tensor

from occplug.components import DenseVoxels, DenseVoxelScene, VoxelClassifier, VoxelCrossEntropy
from occplug.data.frame import Batch
from occplug.geometry import GridSpec
from occplug.interfaces import Lifted, ModelOutputs
from occplug.testing import label_batch

GRID = GridSpec(range=(0.0, 0.0, 0.0, 4.0, 3.0, 2.0), voxel_size=1.0)  # (4, 3, 2)
K = 5


def make_batch(labels: Tensor, has: list[bool], mask_camera: Tensor | None = None) -> Batch:
    return label_batch(
        labels.to(torch.uint8), image_hw=(8, 8), has_voxel_labels=torch.tensor(has), mask_camera=mask_camera
    )


def outputs_with(logits: Tensor, head: str = "occupancy") -> ModelOutputs:
    scene = DenseVoxelScene(torch.zeros(logits.shape[0], 1, *GRID.shape), GRID)
    return ModelOutputs(
        image_features=torch.zeros(1),
        lifted=Lifted(volume=scene.features, grid=GRID),
        scene=scene,
        heads={head: {"logits": logits}},
        query=lambda name, pts: torch.zeros(0),
    )


def problem(seed: int = 0, b: int = 3) -> tuple[Tensor, Tensor, Tensor]:
    g = torch.Generator().manual_seed(seed)
    logits = torch.randn(b, K, *GRID.shape, generator=g)
    labels = torch.randint(0, K, (b, *GRID.shape), generator=g)
    labels[0, 0, 0, :] = 255  # ignored
    camera = torch.rand(b, *GRID.shape, generator=g) > 0.4
    return logits, labels, camera


def by_hand(logits: Tensor, labels: Tensor, keep: Tensor, **kwargs) -> Tensor:
    return F.cross_entropy(logits.movedim(1, -1)[keep], labels[keep], **kwargs)


def test_equals_cross_entropy_on_the_counted_voxels() -> None:
    logits, labels, camera = problem()
    batch = make_batch(labels, [True, False, True], camera)
    labeled = torch.tensor([True, False, True]).view(3, 1, 1, 1)
    valid = labeled & (labels != 255)

    loss = VoxelCrossEntropy()(batch, outputs_with(logits))["voxel_ce"]
    torch.testing.assert_close(loss, by_hand(logits, labels, valid))

    masked = VoxelCrossEntropy(camera_mask=True)(batch, outputs_with(logits))["voxel_ce"]
    torch.testing.assert_close(masked, by_hand(logits, labels, valid & camera))
    assert not torch.allclose(masked, loss), "camera_mask must change which voxels count"

    cw = [0.5, 1.0, 2.0, 0.1, 3.0]
    weighted = VoxelCrossEntropy(class_weights=cw, label_smoothing=0.1)(batch, outputs_with(logits))["voxel_ce"]
    expected = by_hand(logits, labels, valid, weight=torch.tensor(cw), label_smoothing=0.1)
    torch.testing.assert_close(weighted, expected)

    # normalize=count: the same weighted sum over the number of counted voxels (the DuOcc / FlashOcc code's rule)
    per_voxel = by_hand(logits, labels, valid, weight=torch.tensor(cw), label_smoothing=0.1, reduction="none")
    by_count = VoxelCrossEntropy(class_weights=cw, label_smoothing=0.1, normalize="count")(batch, outputs_with(logits))
    torch.testing.assert_close(by_count["voxel_ce"], per_voxel.sum() / valid.sum())
    assert not torch.allclose(by_count["voxel_ce"], weighted)
    unweighted = VoxelCrossEntropy(normalize="count")(batch, outputs_with(logits))["voxel_ce"]
    torch.testing.assert_close(unweighted, loss)  # without class weights the two rules agree


def test_unlabeled_samples_do_not_count() -> None:
    logits, labels, _ = problem()
    batch = make_batch(labels, [True, False, True])
    ce = VoxelCrossEntropy()
    changed = logits.clone()
    changed[1] = torch.randn_like(changed[1]) * 10  # the unlabeled sample
    assert torch.equal(ce(batch, outputs_with(logits))["voxel_ce"], ce(batch, outputs_with(changed))["voxel_ce"])


def test_no_labeled_sample_gives_zero_loss_with_a_gradient_path() -> None:
    logits, labels, _ = problem()
    logits.requires_grad_(True)
    loss = VoxelCrossEntropy()(make_batch(labels, [False, False, False]), outputs_with(logits))["voxel_ce"]
    assert loss.item() == 0.0 and loss.requires_grad
    loss.backward()
    assert logits.grad is not None and torch.all(logits.grad == 0)


def test_clear_errors() -> None:
    logits, labels, _ = problem()
    batch = make_batch(labels, [True, True, True])
    with pytest.raises(ValueError, match=r"logits \(3, 5, 2, 3, 2\).*labels \(3, 4, 3, 2\)"):
        VoxelCrossEntropy()(batch, outputs_with(logits[:, :, :2]))
    with pytest.raises(ValueError, match="reads head 'occupancy'.*heads are: other"):
        VoxelCrossEntropy()(batch, outputs_with(logits, head="other"))
    with pytest.raises(ValueError, match="mask_camera"):
        VoxelCrossEntropy(camera_mask=True)(batch, outputs_with(logits))
    with pytest.raises(ValueError, match="class_weights has 2 entries"):
        VoxelCrossEntropy(class_weights=[1.0, 2.0])(batch, outputs_with(logits))


def test_loss_goes_down_training_scene_and_head() -> None:
    torch.manual_seed(0)
    _, labels, camera = problem(seed=1, b=2)
    batch = make_batch(labels, [True, True], camera)
    volume = torch.randn(2, 4, *GRID.shape)
    rep, head = (
        DenseVoxels(in_channels=4, out_channels=8, num_blocks=1),
        VoxelClassifier(in_channels=8, num_classes=K, hidden=16),
    )
    ce = VoxelCrossEntropy(camera_mask=True)
    opt = torch.optim.Adam([*rep.parameters(), *head.parameters()], lr=0.02)
    losses = []
    for _ in range(20):
        scene = rep(Lifted(volume=volume, grid=GRID), batch)
        loss = ce(batch, outputs_with(head(scene, batch)["logits"]))["voxel_ce"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0], losses
