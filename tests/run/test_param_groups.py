"""``optimizer.param_groups`` / ``no_decay_norm_bias`` and ``optimizer.type`` as any ``torch.optim`` optimizer."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch import nn

from occplug.config import ConfigError
from occplug.run import runner
from occplug.run.training import (
    build_optimizer,
    build_scheduler,
    optimizer_class,
    optimizer_names,
    parameter_groups,
)

ROOT = Path(__file__).resolve().parents[2]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
DEBUG = "occplug/trainer/debug"


class Toy(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.encoder = nn.Sequential(nn.Conv2d(3, 4, 3), nn.BatchNorm2d(4), nn.Conv2d(4, 4, 1, bias=False))
        self.encoder_neck = nn.Linear(4, 4)  # "encoder" is not a prefix of "encoder_neck.*"
        self.head = nn.Sequential(nn.Linear(4, 8), nn.LayerNorm(8), nn.Linear(8, 2))
        self.frozen = nn.Linear(2, 2)
        self.frozen.requires_grad_(False)


SPEC = {
    "type": "adamw",
    "lr": 1e-3,
    "weight_decay": 0.05,
    "no_decay_norm_bias": True,
    "param_groups": [
        {"prefix": "encoder", "lr_mult": 0.1},
        {"prefix": "encoder.2", "lr_mult": 0.5, "weight_decay": 0.2},  # longer prefix wins
        {"prefix": "head", "weight_decay": 0.0},
    ],
}

#: By hand: each trainable parameter's (lr, weight decay) under SPEC.
EXPECTED = {
    "encoder.0.weight": (1e-4, 0.05),
    "encoder.0.bias": (1e-4, 0.0),
    "encoder.1.weight": (1e-4, 0.0),  # BatchNorm
    "encoder.1.bias": (1e-4, 0.0),
    "encoder.2.weight": (5e-4, 0.2),
    "encoder_neck.weight": (1e-3, 0.05),
    "encoder_neck.bias": (1e-3, 0.0),
    "head.0.weight": (1e-3, 0.0),
    "head.0.bias": (1e-3, 0.0),
    "head.1.weight": (1e-3, 0.0),  # LayerNorm
    "head.1.bias": (1e-3, 0.0),
    "head.2.weight": (1e-3, 0.0),
    "head.2.bias": (1e-3, 0.0),
}


def test_every_trainable_parameter_is_in_exactly_one_group_with_the_asked_lr_and_decay():
    model = Toy()
    groups = parameter_groups(model, SPEC, lr=1e-3)
    names = {id(p): n for n, p in model.named_parameters()}
    seen = [names[id(p)] for g in groups for p in g["params"]]
    assert sorted(seen) == sorted(EXPECTED)  # each trainable parameter once, the frozen one in none
    for group in groups:
        for p in group["params"]:
            lr, decay = EXPECTED[names[id(p)]]
            assert group["lr"] == pytest.approx(lr) and group["weight_decay"] == pytest.approx(decay), names[id(p)]
    assert all(g["params"] for g in groups)  # no empty group
    assert [g["name"] for g in groups] == [
        "encoder",
        "encoder (no decay)",
        "encoder.2",
        "head",
        "head (no decay)",
        "default",
        "default (no decay)",
    ]


def test_without_groups_one_group_decays_everything_as_torch_does():
    model = Toy()
    (group,) = parameter_groups(model, {"type": "adamw", "lr": 0.01}, lr=0.01)
    assert group["weight_decay"] == 0.01  # AdamW's own default
    assert len(group["params"]) == len(EXPECTED)
    opt = build_optimizer(model, {"type": "sgd", "lr": 0.1, "momentum": 0.9})
    assert isinstance(opt, torch.optim.SGD) and len(opt.param_groups) == 1 and opt.param_groups[0]["lr"] == 0.1


def test_the_schedule_keeps_each_groups_multiplier():
    opt = build_optimizer(Toy(), SPEC)
    sched = build_scheduler(opt, {"type": "cosine", "warmup_steps": 2}, total_steps=10)
    for _ in range(5):
        opt.step()
        sched.step()
    lrs = {g["name"]: g["lr"] for g in opt.param_groups}
    assert lrs["encoder"] == pytest.approx(0.1 * lrs["default"]) and lrs["encoder.2"] == pytest.approx(
        0.5 * lrs["default"]
    )
    assert 0 < lrs["default"] < 1e-3


@pytest.mark.parametrize("name", ["rmsprop", "adagrad", "radam", "nadam", "adamax", "asgd"])
def test_any_torch_optimizer_by_name(name):
    opt = build_optimizer(Toy(), {"type": name, "lr": 0.01, "no_decay_norm_bias": True})
    assert type(opt).__name__.lower() == name
    assert {g["weight_decay"] for g in opt.param_groups} == {0.0, opt.defaults["weight_decay"]}


def test_the_names_are_torch_optims_classes():
    names = optimizer_names()
    assert {"adamw", "adam", "sgd", "rmsprop", "lbfgs"} <= set(names)
    for name in names:
        cls = optimizer_class(name)
        assert getattr(torch.optim, cls.__name__) is cls and cls.__name__.lower() == name


@pytest.mark.parametrize(
    ("overrides", "line"),
    [
        (["optimizer.type=adamx"], "optimizer.type: unknown optimizer 'adamx'; did you mean 'adamax'?"),
        (
            ["optimizer={type: rmsprop, lr: 0.01, betas: [0.9, 0.99]}"],
            "optimizer.betas: unknown optimizer argument",
        ),
        (
            ["optimizer.param_groups=[{prefix: encoder, lr_mul: 0.1}]"],
            "optimizer.param_groups.0.lr_mul: unknown key; did you mean 'lr_mult'? (keys: prefix, lr_mult, weight_decay)",
        ),
        (
            ["optimizer.param_groups=[{prefix: encoder, lr_mult: 0}]"],
            "optimizer.param_groups.0.lr_mult: expected a number > 0, got 0",
        ),
        (
            ["optimizer.param_groups=[{prefix: encoder}, {prefix: encoder}]"],
            "optimizer.param_groups.1.prefix: 'encoder' is already the prefix of an earlier group",
        ),
        (["optimizer.no_decay_norm_bias=yes please"], "optimizer.no_decay_norm_bias: expected true or false"),
        (
            ["optimizer={type: rprop, lr: 0.01, no_decay_norm_bias: true}"],
            "optimizer: 'rprop' has no weight_decay, so no group can set or drop it",
        ),
    ],
)
def test_a_bad_optimizer_node_is_one_line(overrides, line):
    with pytest.raises(ConfigError) as err:
        runner.load_config([BASELINE, DEBUG], overrides)
    assert str(err.value).startswith(line) and "\n" not in str(err.value), str(err.value)


def test_a_prefix_matching_no_parameter_stops_fit_before_anything_is_written(tmp_path):
    cfg = runner.load_config([BASELINE, DEBUG], ["optimizer.param_groups=[{prefix: encodr.body, lr_mult: 0.1}]"])
    with pytest.raises(runner.RunError) as err:
        runner.fit(cfg, tmp_path / "run")
    assert str(err.value) == (
        "optimizer.param_groups.0.prefix: 'encodr.body' matches no parameter; did you mean 'encoder.body'?"
    )
    assert not (tmp_path / "run").exists()


def test_fit_trains_with_groups(tmp_path):
    spec = (
        "optimizer={type: adamw, lr: 0.002, no_decay_norm_bias: true, param_groups: [{prefix: encoder, lr_mult: 0.1}]}"
    )
    cfg = runner.load_config([BASELINE, DEBUG], [spec, "scheduler={type: none}"])
    seen = {}

    class Spy(runner.Callback):
        def on_train_end(self, trainer, pl_module):
            seen.update({g["name"]: g["lr"] for g in trainer.optimizers[0].param_groups})

    runner.fit(cfg, tmp_path / "run", callbacks=[Spy()])
    assert seen == pytest.approx(
        {"encoder": 2e-4, "encoder (no decay)": 2e-4, "default": 2e-3, "default (no decay)": 2e-3}
    )


def test_the_paper_recipes_optimizers_are_their_codes():
    """DuOcc as its public code (projects/configs/DuOcc.py): AdamW 2e-4, weight decay 0.01 on every parameter,
    warm-up from 1/3 over 200 iterations, then constant (the step epochs are never reached); SyncBN. QueryOcc's
    paper states none: the same AdamW on every parameter, no groups (the recipe says it is an assumption)."""
    duocc = runner.load_config(["duocc/occ3d_nuscenes"])
    assert duocc["optimizer"] == {
        "type": "adamw", "lr": 2e-4, "weight_decay": 0.01, "no_decay_norm_bias": False, "lr_scaling": "linear",
        "reference_batch": 8,
    }  # fmt: skip
    assert duocc["trainer"]["sync_batchnorm"] is True and duocc["trainer"]["gradient_clip_val"] == 5.0
    opt = build_optimizer(nn.Linear(2, 2), duocc["optimizer"])
    sched = build_scheduler(opt, duocc["scheduler"], total_steps=84_384)
    lrs = []
    for _ in range(1000):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert lrs[0] == pytest.approx(2e-4 / 3, rel=1e-6) and lrs[100] == pytest.approx(
        2e-4 * (1 / 3 + 2 / 3 / 2), rel=1e-6
    )
    assert lrs[200:] == pytest.approx([2e-4] * 800)
    queryocc = runner.load_config(["queryocc/occ3d_nuscenes"])
    assert queryocc["optimizer"]["type"] == "adamw" and queryocc["optimizer"]["weight_decay"] == 0.01
    assert "param_groups" not in queryocc["optimizer"] and queryocc["optimizer"]["no_decay_norm_bias"] is False
