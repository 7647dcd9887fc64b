"""The switches that reproduce DuOcc's public code (StreamAgg warp and reset, occupied loss, recipes): the public
values do what the code does, the defaults stay what they were."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
import torch.nn.functional as F

from occplug.config import compose, validate
from occplug.geometry import GridSpec, warp_volume
from occplug.interfaces import ModelOutputs
from occplug.plugins import get_registry
from occplug.testing import label_batch
from occplug_duocc.blocks.stream_agg import StreamAggregation, occupied_loss, public_linspace_warp
from occplug_duocc.scene import OCCUPIED_KEY, DuOccStream
from occplug_duocc.supervision.auxiliary import DuOccOccupied
from occplug_duocc.tools.class_weights import CODE_EPS, duocc_class_weights

#: the public code's StreamAgg grid: x, y in [-40, 40] and z in [-1, 5.4] at 0.8 m, 100 x 100 x 8 voxels
CODE_GRID = GridSpec((-40.0, -40.0, -1.0, 40.0, 40.0, 5.4), 0.8)


def _ramps(grid: GridSpec) -> torch.Tensor:
    """``(1, 3, X, Y, Z)``: channel ``a`` holds each voxel's index along axis ``a`` (trilinear reads it exactly)."""
    idx = torch.meshgrid(*[torch.arange(n, dtype=torch.float32) for n in grid.shape], indexing="ij")
    return torch.stack(idx)[None]


def _translation(t: tuple[float, float, float]) -> torch.Tensor:
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, 3] = torch.tensor(t, dtype=torch.float64)
    return pose[None]


@pytest.mark.parametrize(("sampling", "factors"), [("voxel_centres", (1.0, 1.0, 1.0)), ("public_linspace", None)])
def test_a_translation_moves_the_content_by_the_sampling_s_factor(sampling, factors):
    grid = CODE_GRID
    n = torch.tensor(grid.shape, dtype=torch.float64)
    if factors is None:  # the code's linspace pitch (hi - lo) / (N - 1): (N - 1) / N of the true voxel count
        factors = tuple((n - 1).div(n).tolist())
        assert factors == pytest.approx((0.99, 0.99, 0.875), abs=1e-12)  # the comparison's 0.99 x / 0.875 x
    voxels = (4.0, -3.0, 1.0)  # prev -> current moves the content by this many true voxels per axis
    agg = StreamAggregation(3, 4, grid, refine=False, occupied_head=False, forecast_head=False, warp_sampling=sampling)
    ramps = _ramps(grid)
    pose = _translation(tuple(v * s for v, s in zip(voxels, grid.voxel_size, strict=True)))
    warped = agg.eval()(torch.zeros_like(ramps), ramps, pose).warped
    # destination voxel i reads the source at i - moved: the ramps hold that source index where it is inside
    moved = torch.tensor([v * f for v, f in zip(voxels, factors, strict=True)], dtype=torch.float64)
    expected = ramps.double() - moved.view(1, 3, 1, 1, 1)
    inside = ((expected >= 0) & (expected <= (n - 1).view(1, 3, 1, 1, 1))).all(dim=1, keepdim=True)
    assert inside.sum() > 0.5 * inside.numel()
    assert torch.allclose(warped.double()[inside.expand_as(warped)], expected[inside.expand_as(expected)], atol=2e-4)
    for axis in range(3):  # the factor read back from the content's shift
        shift = (ramps[0, axis] - warped[0, axis]).double()[inside[0, 0]].mean()
        assert float(shift) / voxels[axis] == pytest.approx(factors[axis], abs=1e-5)


def test_the_public_warp_is_exact_for_the_identity_and_refuses_a_grid_it_cannot_sample():
    g = torch.Generator().manual_seed(0)
    volume = torch.randn(2, 3, *CODE_GRID.shape, generator=g)
    same = public_linspace_warp(volume, CODE_GRID, torch.eye(4, dtype=torch.float64).expand(2, 4, 4))
    assert torch.allclose(same, volume, atol=1e-4)  # float32 rounding of the linspace points only
    # a 90 degree turn about z maps the code's (centred, square) linspace points onto themselves
    turn = torch.tensor([[0.0, -1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    turned = public_linspace_warp(volume, CODE_GRID, turn.double().expand(2, 4, 4))
    assert torch.allclose(turned, torch.rot90(volume, 1, dims=(2, 3)), atol=1e-4)
    wide = GridSpec((-40.0, -24.0, -1.0, 40.0, 24.0, 5.4), 0.8)  # 100 x 60
    with pytest.raises(ValueError, match=r"warp_sampling='public_linspace' needs a square x-y grid.*100 x 60"):
        StreamAggregation(3, 4, wide, warp_sampling="public_linspace")
    with pytest.raises(ValueError, match="warp_sampling must be"):
        StreamAggregation(3, 4, CODE_GRID, warp_sampling="linspace")


def test_the_default_warp_is_bit_equal_to_the_core_warp():
    grid = GridSpec((-8.0, -8.0, -1.0, 8.0, 8.0, 5.4), 0.8)
    g = torch.Generator().manual_seed(3)
    v_curr, v_hist = torch.randn(2, 2, 4, *grid.shape, generator=g)
    yaw = 0.3
    pose = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    pose[0, :2, :2] = torch.tensor([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    pose[:, :3, 3] = torch.tensor([[1.3, -0.7, 0.2], [-2.1, 0.4, 0.0]])
    reset = torch.tensor([False, True])
    for agg in (StreamAggregation(4, 5, grid), StreamAggregation(4, 5, grid, warp_sampling="voxel_centres")):
        warped = agg.eval()(v_curr, v_hist, pose, reset).warped
        assert torch.equal(warped[0], warp_volume(v_hist, grid, pose)[0])
        assert torch.equal(warped[1], v_curr[1])  # a reset sample reads V_curr itself


# (timestamp s, frame index, scene, sequence start) of one batch slot, and whether the history continues
# under the paper's rule (0 < dt <= 2 s, the frame index one ahead) and the public code's (0 < |dt| <= 2 s)
SEQUENCE = [
    ((10.0, 20, "a", True), False, False),  # first frame
    ((10.5, 21, "a", False), True, True),  # dt +0.5
    ((10.5, 21, "a", False), False, False),  # dt 0
    ((9.0, 18, "a", False), False, True),  # dt -1.5: a step back
    ((11.0, 22, "a", False), False, True),  # dt +2.0, four frames ahead
    ((13.5, 27, "a", False), False, False),  # dt +2.5
    ((11.5, 23, "a", False), False, True),  # dt -2.0
    ((9.0, 18, "a", False), False, False),  # dt -2.5
    ((9.5, 19, "a", False), True, True),  # dt +0.5
    ((10.0, 20, "b", False), False, False),  # another scene
    ((10.5, 21, "b", True), False, False),  # a sequence start
]


@pytest.mark.parametrize("rule", ["paper", "public"])
def test_history_reset_rules_on_a_hand_made_sequence(rule):
    grid = GridSpec.from_config({"range": [-4.0, -4.0, -1.0, 4.0, 4.0, 5.4], "voxel_size": 0.8})
    scene = DuOccStream(4, grid, 18, channels=8, history_reset=rule)
    state = scene.history
    previous = None
    for (t, frame, name, start), paper, public in SEQUENCE:
        pose = torch.eye(4, dtype=torch.float64)
        pose[0, 3] = t  # the ego drives 1 m per second along x
        batch = SimpleNamespace(
            scene=[name],
            frame_index=torch.tensor([frame]),
            timestamp=torch.tensor([t], dtype=torch.float64),
            is_sequence_start=torch.tensor([start]),
            ego_to_global=pose[None],
        )
        current = torch.full((1, 2), t)
        read = state.get(batch, current)
        keeps = paper if rule == "paper" else public
        assert bool(read.reset[0]) is (not keeps), (rule, t, frame, name)
        if keeps:  # the stored frame, with its time difference and motion (a step back in time moves back)
            assert torch.equal(read.value, torch.full((1, 2), previous))
            assert float(read.dt[0]) == pytest.approx(t - previous)
            assert float(read.prev_to_current[0, 0, 3]) == pytest.approx(previous - t)
        else:
            assert torch.equal(read.value, current) and float(read.dt[0]) == 0.0
        state.update(batch, current)
        previous = t
    with pytest.raises(ValueError, match="history_reset must be"):
        DuOccStream(4, grid, 18, channels=8, history_reset="code")


def _occupied_case():
    g = torch.Generator().manual_seed(5)
    logits = torch.randn(2, 4, 3, 2, generator=g)
    labels = torch.randint(0, 4, (2, 4, 3, 2), generator=g)
    labels[0, 0, 0, 0], labels[1, 0, 0, 0] = 3, 1  # both kinds present
    mask = torch.rand(2, 4, 3, 2, generator=g) > 0.3
    return logits, labels, mask


def test_occupied_loss_public_mean_is_the_batch_factor_times_the_mean_bce():
    logits, labels, mask = _occupied_case()
    free = 3
    target = (labels != free).float()
    bce = F.binary_cross_entropy_with_logits(logits[mask], target[mask])
    fraction = target[mask].mean()
    assert 0.2 < float(fraction) < 0.9
    public = occupied_loss(logits, labels, free, mask, weighting="public_mean")
    assert torch.allclose(public, bce * (0.1 + 0.9 * fraction), rtol=1e-6)
    # the code's own expression: the averaged loss times the per-voxel weights, then averaged again
    code = (bce * torch.where(target[mask] == 1, 1.0, 0.1)).mean()
    assert torch.allclose(public, code, rtol=1e-6)
    # the default is the plain mean over the counted voxels, bit for bit
    assert torch.equal(occupied_loss(logits, labels, free, mask), bce)
    assert torch.equal(occupied_loss(logits, labels, free, mask, weighting="per_voxel"), bce)
    with pytest.raises(ValueError, match="weighting must be"):
        occupied_loss(logits, labels, free, mask, weighting="mean")


def test_duocc_occupied_source_applies_the_code_s_weighting_and_its_second_sigmoid():
    logits, labels, mask = _occupied_case()
    batch = label_batch(labels, mask_camera=mask)
    outputs = ModelOutputs(None, None, None, {}, lambda *a, **k: None, extras={OCCUPIED_KEY: logits})
    kwargs = {"free_label": 3, "ignore_label": 255}
    default = DuOccOccupied(**kwargs).train()(batch, outputs)["occupied_bce"]
    assert torch.equal(default, occupied_loss(logits, labels, 3, mask))
    code = DuOccOccupied(weighting="public_mean", head_sigmoid=True, **kwargs).train()(batch, outputs)["occupied_bce"]
    probs, target = torch.sigmoid(logits)[mask], (labels != 3).float()[mask]
    expected = (F.binary_cross_entropy_with_logits(probs, target) * torch.where(target == 1, 1.0, 0.1)).mean()
    assert torch.allclose(code, expected, rtol=1e-6)
    with pytest.raises(ValueError, match="duocc_occupied weighting must be"):
        DuOccOccupied(weighting="mean")


def test_code_recipe_sets_the_public_switches_and_validates():
    cfg = compose(["duocc/code_recipe"]).resolved()
    scene, supervision = cfg["model"]["scene"], cfg["model"]["supervision"]
    assert scene["warp_sampling"] == "public_linspace" and scene["history_reset"] == "public" and scene["residual_relu"]
    assert supervision["occupied"]["weighting"] == "public_mean" and supervision["occupied"]["head_sigmoid"] is True
    validate(cfg, get_registry())
    for recipe in ("full", "stream_agg", "occ3d_nuscenes"):  # the defaults elsewhere
        other = compose([f"duocc/{recipe}"]).resolved()["model"]
        assert not {"warp_sampling", "history_reset"} & set(other["scene"])
        assert not {"weighting", "head_sigmoid"} & set(other["supervision"]["occupied"])


def _header_counts(ref: str) -> list[int]:
    import ast
    from importlib.resources import files

    text = (files("occplug_duocc") / "configs" / "class_weights" / f"{ref}.yaml").read_text()
    return ast.literal_eval(next(ln[2:] for ln in text.splitlines() if ln.startswith("# [")))


def test_the_code_s_class_weights_are_its_rule_unrounded():
    # code_recipe: the rule with the code's + 0.001 over the default world's counts, to float32 precision
    weights = compose(["duocc/code_recipe"]).resolved()["model"]["supervision"]["occupancy"]["class_weights"]
    rule = duocc_class_weights(_header_counts("synthetic_code"), eps=CODE_EPS)
    assert torch.equal(torch.tensor(weights, dtype=torch.float32), rule)
    assert weights != compose(["duocc/full"]).resolved()["model"]["supervision"]["occupancy"]["class_weights"]
    # Occ3D-nuScenes: the overlay is the rule over the code's nusc_class_frequencies; the recipe keeps them rounded
    nusc = compose(["duocc/occ3d_nuscenes", "duocc/class_weights/occ3d_nuscenes"]).resolved()
    exact = nusc["model"]["supervision"]["occupancy"]["class_weights"]
    counts = _header_counts("occ3d_nuscenes")
    assert torch.equal(torch.tensor(exact, dtype=torch.float32), duocc_class_weights(counts, eps=CODE_EPS))
    assert torch.equal(torch.tensor(exact, dtype=torch.float32), duocc_class_weights(counts))  # eps below float32 here
    rounded = compose(["duocc/occ3d_nuscenes"]).resolved()["model"]["supervision"]["occupancy"]["class_weights"]
    assert rounded == [round(w, 3) for w in exact]
    assert compose(["duocc/occ3d_nuscenes"]).resolved()["model"]["heads"]["occupancy"]["mlp_hidden"] == 256
