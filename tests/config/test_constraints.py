"""Declared argument constraints: known verdicts, error lines naming key, value and rule."""

from __future__ import annotations

import math
from typing import Annotated

import pytest

import occplug
from occplug.config import ConfigError, validate
from occplug.constraints import Fraction, Length, NonNegative, Positive, Range, UnitInterval, violated
from occplug.plugins import isolated
from occplug.run.runner import load_config


@pytest.mark.parametrize(
    ("rule", "good", "bad"),
    [
        (Positive, [1e-9, 1, 3.5], [0, -1, math.nan, -math.inf]),
        (NonNegative, [0, 0.0, 7], [-1e-9, -1, math.nan]),
        (UnitInterval, [0, 0.5, 1], [-0.1, 1.01, math.nan]),
        (Fraction, [1e-6, 0.1, 1], [0, -0.5, 1.5, math.nan]),
        (Range(low=-1), [-1, 0, 100], [-2, math.nan]),
        (Range(low=0, high=10, high_open=True), [0, 9.99], [10, 11, -1]),
    ],
)
def test_ranges_have_known_verdicts(rule, good, bad):
    assert all(rule.holds(v) for v in good)
    assert not any(rule.holds(v) for v in bad)
    assert not any(rule.holds(v) for v in rule.violations())  # generated violations really violate


def test_descriptions():
    assert Positive.describe() == "> 0"
    assert NonNegative.describe() == ">= 0"
    assert UnitInterval.describe() == "in [0, 1]"
    assert Fraction.describe() == "in (0, 1]"
    assert Length(exact=3).describe() == "a list of 3"


def test_lengths_and_elements():
    ann = Annotated[list[Annotated[float, Positive]], Length(exact=3)]
    assert violated([1.0, 2.0, 3.0], ann) is None
    assert violated([1.0, 2.0], ann) == "a list of 3"
    assert violated([1.0, -2.0, 3.0], ann) == "every element a number > 0"
    assert violated(None, Annotated[int | None, Positive]) is None  # an optional argument switched off
    assert violated(0, Annotated[int | None, Positive]) == "an int > 0"
    for bad in Length(exact=3).violations():
        assert not Length(exact=3).holds(bad)


class Declared(occplug.ImageEncoder):
    """An encoder declaring its argument rules."""

    def __init__(
        self,
        channels: Annotated[int, Positive] = 4,
        sizes: Annotated[list[Annotated[float, Positive]], Length(exact=2)] = (1.0, 2.0),
        dropout: Annotated[float, UnitInterval] = 0.0,
    ) -> None:
        super().__init__()
        self.out_channels, self.stride = channels, 1

    def forward(self, images):
        return images


class DeclaringPlugin:
    @occplug.hookimpl
    def occplug_register_components(self, registry):
        registry.add("encoder", "declared", Declared)


@pytest.mark.parametrize(
    ("override", "line"),
    [
        ("model.encoder.channels=0", "model.encoder.channels: expected an int > 0, got int 0"),
        ("model.encoder.channels=-1", "model.encoder.channels: expected an int > 0, got int -1"),
        ("model.encoder.sizes=[1.0]", "model.encoder.sizes: expected a list of 2, got list [1.0]"),
        (
            "model.encoder.sizes=[1.0,-3.0]",
            "model.encoder.sizes: expected every element a number > 0, got list [1.0, -3.0]",
        ),
        ("model.encoder.dropout=1.5", "model.encoder.dropout: expected a number in [0, 1], got float 1.5"),
    ],
)
def test_a_plugin_components_rules_are_checked_by_validation(override, line):
    with isolated(plugins=[("declaring", DeclaringPlugin())]) as reg:
        with pytest.raises(ConfigError) as err:
            validate(load_config(["configs/baseline.yaml"], ["model.encoder={type: declared}", override]), reg)
        assert str(err.value) == line


@pytest.mark.parametrize(
    ("override", "line"),
    [
        ("optimizer.lr=-0.001", "optimizer.lr: expected a number > 0, got float -0.001"),
        ("optimizer.lr=0", "optimizer.lr: expected an int > 0, got int 0"),
        ("optimizer.weight_decay=-1.0", "optimizer.weight_decay: expected a number >= 0, got float -1.0"),
        ("scheduler.warmup_steps=-5", "scheduler.warmup_steps: expected an int >= 0, got int -5"),
        ("trainer.max_epochs=-2", "trainer.max_epochs: expected an int >= -1, got int -2"),
        ("trainer.accumulate_grad_batches=0", "trainer.accumulate_grad_batches: expected an int >= 1, got int 0"),
    ],
)
def test_the_runs_own_numbers_are_checked(override, line):
    with pytest.raises(ConfigError) as err:  # load_config validates
        load_config(["configs/baseline.yaml"], [override])
    assert str(err.value) == line


#: What a run-number key needs beside it to reach its check (its optimizer or scheduler type).
_CONTEXT = {
    "optimizer.momentum": ["optimizer={type: sgd, lr: 0.1}"],
    "optimizer.dampening": ["optimizer={type: sgd, lr: 0.1}"],
    "scheduler.step_size": ["scheduler={type: step}"],
    "scheduler.gamma": ["scheduler={type: step}"],
    "scheduler.warmup_start": ["scheduler={type: constant}"],
}


def _run_number_cases():
    from occplug.config.validate import RUN_CONSTRAINTS

    for key, rule in RUN_CONSTRAINTS.items():
        for bad in rule.violations():
            value = [bad, 0.9] if key == "optimizer.betas" else bad
            yield pytest.param(key, value, id=f"{key}={bad!r}")


@pytest.mark.parametrize(("key", "value"), list(_run_number_cases()))
def test_every_run_number_rule_is_one_line_naming_the_key(key, value):
    """Generated from ``RUN_CONSTRAINTS``: each rule's violating values (NaN included where it applies)."""
    shown = ".nan" if isinstance(value, float) and value != value else repr(value).replace("'", "")  # YAML NaN
    with pytest.raises(ConfigError) as err:
        load_config(["configs/baseline.yaml"], [*_CONTEXT.get(key, []), f"{key}={shown}"])
    line = str(err.value)
    assert line.startswith(f"{key}: expected ") and "\n" not in line, line
