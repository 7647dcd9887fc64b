"""Every argument with its default (issue 56 item 6): the run's ``config.yaml``, ``config show --defaults``,
``plugins --kind``."""

from __future__ import annotations

import inspect
import json
from pathlib import Path

import pytest
import torch

from occplug.cli import main
from occplug.components.view_transforms import LSSViewTransform
from occplug.config import compose, read_config, validate
from occplug.config.defaults import arguments, run_config_text, with_defaults
from occplug.config.validate import check_type, out_of_range, validate_component
from occplug.config.yamlio import parse_yaml
from occplug.constraints import violated
from occplug.kinds import KINDS
from occplug.plugins import config_dirs, get_registry
from occplug.run import runner
from occplug.slots import component_params

ROOT = Path(__file__).resolve().parents[2]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
TINY = ["data.preset=tiny", "trainer.accelerator=cpu", "trainer.enable_progress_bar=false"]


def _lss_default(name: str):
    return inspect.signature(LSSViewTransform).parameters[name].default


def test_with_defaults_fills_every_left_out_argument_but_not_what_the_parent_gives():
    registry = get_registry()
    cfg = compose([BASELINE]).resolved()
    assert "splat" not in cfg["model"]["view_transform"]  # the case: LSS's defaults were absent
    full = with_defaults(cfg, registry)
    lss = full["model"]["view_transform"]
    for name in ("hidden", "splat"):
        assert lss[name] == _lss_default(name)
    assert lss["depth_bins"] == cfg["model"]["view_transform"]["depth_bins"]  # what the config set stays
    assert "in_channels" not in lss and "grid" not in lss  # given by the model at build time
    assert "depth_net" not in lss  # an optional nested component left unset stays unset
    assert list(lss)[0] == "type"
    validate(full, registry)
    assert with_defaults(full, registry) == full  # idempotent
    assert full["metrics"][0]["type"] == "occ3d_miou" and "exclude_classes" in full["metrics"][0]


@pytest.mark.parametrize("refs", [[BASELINE], ["queryocc/base"], ["duocc/full"], ["occle/base"]], ids=lambda r: r[0])
def test_a_dump_reads_back_equal_and_builds_the_same_model(refs):
    registry = get_registry()
    cfg = runner.load_config(refs, TINY)
    text = run_config_text(cfg, registry)
    assert text.startswith("# resolved occplug config")
    dumped = parse_yaml(text, "dump")
    assert dumped == with_defaults(cfg, registry)
    again = runner.load_config([], [], saved=dumped)
    assert again == {**dumped, "eval_mask": cfg["eval_mask"]}
    torch.manual_seed(0)
    _, model = runner.build_run(cfg)
    torch.manual_seed(0)
    _, rebuilt = runner.build_run(again)
    a, b = model.state_dict(), rebuilt.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert repr(model) == repr(rebuilt)


def _recipes():
    """Every full config: ./configs and the plugins' recipes (those with a data and a model section)."""
    files = sorted((ROOT / "configs").rglob("*.yaml"))
    for name, folder in sorted(config_dirs().items()):
        if name != "occplug":
            files += [
                p for p in sorted(Path(folder).rglob("*.yaml")) if {"data", "model"} <= set(compose([str(p)]).data)
            ]
    return files


@pytest.mark.parametrize("path", _recipes(), ids=lambda p: p.stem)
def test_every_recipe_with_defaults_validates_and_round_trips(path):
    registry = get_registry()
    cfg = compose([str(path)]).resolved()
    full = with_defaults(cfg, registry)
    validate(full, registry)
    assert parse_yaml(run_config_text(cfg, registry), str(path)) == full


def _documented_defaults():
    registry = get_registry()
    for kind in KINDS:
        for name in registry.names(kind):
            factory = registry.get(kind, name).factory
            for arg in arguments(factory, kind):
                yield kind, name, factory, arg


def test_every_default_that_a_dump_writes_validates():
    """A run's config.yaml holds each component's defaults, so every default must pass its own argument's
    checks (type, declared rule, finiteness); else a dump would not load back."""
    count = 0
    for kind, name, factory, arg in _documented_defaults():
        if arg.given or arg.required or not arg.representable or (arg.slot is not None and arg.default is None):
            continue
        annotation = component_params(factory)[arg.name][1]
        where = f"{kind} {name}.{arg.name} = {arg.default!r}"
        if arg.slot is not None:
            nodes = arg.default.values() if arg.slot.mapping else arg.default if arg.slot.sequence else [arg.default]
            for node in nodes:
                validate_component(node, arg.slot.kind, where, get_registry())
        else:
            assert check_type(arg.default, annotation), where
            assert violated(arg.default, annotation) is None, where
            assert out_of_range(arg.default) is None, where
        count += 1
    assert count > 100


def test_config_show_defaults_prints_each_argument_with_its_rule_and_default(capsys):
    assert main(["config", "show", "-c", BASELINE, "--defaults"]) == 0
    out = capsys.readouterr().out
    by_name = {a.name: a for a in arguments(LSSViewTransform, "view_transform")}
    assert by_name["splat"].describe() == "one of 'fast', 'reference'; default fast"
    assert f"    splat: fast # {by_name['splat'].describe()}" in out
    assert f"    hidden: {_lss_default('hidden')} # {by_name['hidden'].describe()}" in out
    assert "    type: lss  # view_transform; given by its parent: in_channels, image_stride, grid" in out
    cfg = compose([BASELINE]).resolved()
    assert parse_yaml(out, "show") == with_defaults(cfg, get_registry())  # comments aside, the same config


def test_plugins_kind_lists_constructor_arguments(capsys):
    assert main(["plugins", "--kind", "view_transform"]) == 0
    out = capsys.readouterr().out.splitlines()
    at = next(i for i, line in enumerate(out) if " lss " in line)
    block = []
    for line in out[at + 1 :]:
        if not line.startswith("      "):
            break
        block.append(line.strip())
    assert block == [f"{a.name}: {a.describe()}" for a in arguments(LSSViewTransform, "view_transform")]
    assert "splat: one of 'fast', 'reference'; default fast" in block
    assert "in_channels: int; given by its parent" in block
    assert main(["plugins", "--kind", "view_transform", "--json"]) == 0
    reports = json.loads(capsys.readouterr().out)
    lss = next(
        r["arguments"]["view_transform"]["lss"] for r in reports if "lss" in r["components"].get("view_transform", [])
    )
    by_name = {a["name"]: a for a in lss}
    assert (
        by_name["splat"]["default"] == _lss_default("splat")
        and by_name["splat"]["type"] == "one of 'fast', 'reference'"
    )
    assert by_name["out_channels"]["rule"] == "> 0" and by_name["in_channels"]["given"] is True


def test_a_run_s_config_yaml_holds_the_defaults_and_resumes(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["fit", "-c", BASELINE, *TINY, "trainer.max_steps=2", "--run-dir", str(run)]) == 0
    saved = read_config(run / "config.yaml")
    assert saved["model"]["view_transform"]["splat"] == _lss_default("splat")
    assert main(["config", "validate", "-c", str(run / "config.yaml")]) == 0
    assert main(["fit", "--resume", str(run), "trainer.max_steps=3"]) == 0
    assert json.loads((run / "metrics.json").read_text())["global_step"] == 3
    assert read_config(run / "config.yaml") == {**saved, "trainer": {**saved["trainer"], "max_steps": 3}}
