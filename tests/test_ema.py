"""The core's ``ema`` callback (the average it keeps, what a checkpoint holds) and the ``constant`` schedule."""

import math
from pathlib import Path

import pytest
import torch
from lightning.pytorch.callbacks import Callback

from occplug.config import ConfigError
from occplug.run import runner
from occplug.run.ema import EMAWeights

BASELINE = str(Path(__file__).resolve().parents[1] / "configs" / "baseline.yaml")
RUN = [
    "data.preset=tiny",
    "data.num_workers=0",
    "trainer.accelerator=cpu",
    "trainer.enable_progress_bar=false",
    "trainer.max_epochs=1",
    "trainer.limit_train_batches=3",
    "trainer.limit_val_batches=1",
]


class _Weights(Callback):
    """The model's parameters after every optimiser step (on_train_batch_end runs after the step)."""

    def __init__(self) -> None:
        self.after_step: list[dict[str, torch.Tensor]] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.after_step.append({k: v.detach().clone() for k, v in pl_module.named_parameters()})


def test_the_ramp_and_the_schedule():
    ema = EMAWeights(decay=0.9, ramp_steps=10.0, every_n_steps=2, start_step=1)
    assert ema.decay_at(5) == pytest.approx(0.9 * (1 - math.exp(-0.5)))
    assert EMAWeights(decay=0.9).decay_at(1) == 0.9
    assert [ema.should_update(step_idx=i) for i in range(6)] == [False, True, False, True, False, True]
    assert not ema.should_update(epoch_idx=0)


def test_three_steps_give_the_hand_computed_average_in_the_checkpoint(tmp_path):
    cfg = runner.load_config([BASELINE], [*RUN, "callbacks={ema: {type: ema, decay: 0.5}}"])
    weights = _Weights()
    runner.fit(cfg, tmp_path / "run", callbacks=[weights])
    p1, p2, p3 = weights.after_step
    expected = {k: 0.5 * (0.5 * p1[k] + 0.5 * p2[k]) + 0.5 * p3[k] for k in p3}  # e1 = p1, e_n = d e + (1 - d) p
    ckpt = runner.load_checkpoint(tmp_path / "run" / "checkpoints" / "last.ckpt")
    assert set(expected) <= set(ckpt["state_dict"])
    for name, value in expected.items():
        assert torch.allclose(ckpt["state_dict"][name], value, atol=1e-6), name
        assert torch.equal(ckpt["current_model_state"][name], p3[name])  # the raw weights ride along
    assert any(not torch.allclose(expected[k], p3[k]) for k in p3)  # the average is not the last weights


def test_a_bad_decay_is_a_config_error():
    with pytest.raises(ConfigError, match=r"callbacks\.ema\.decay"):
        runner.load_config([BASELINE], ["callbacks={ema: {type: ema, decay: 1.0}}"])


def test_the_constant_schedule_warms_up_linearly_then_holds():
    from occplug.config.validate import SCHEDULERS
    from occplug.run import training

    for name in SCHEDULERS:  # every schedule the validator admits, the runner builds
        assert callable(training.scheduler_factory(name))
    opt = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=3.0)
    sched = training.scheduler_factory("constant")(opt, 100, warmup_steps=4, warmup_start=1 / 3)
    lrs = []
    for _ in range(6):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert lrs == pytest.approx([1.0, 1.5, 2.0, 2.5, 3.0, 3.0])
