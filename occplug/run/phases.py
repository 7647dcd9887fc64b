"""Running named phases (``phases:`` in a config; see :mod:`occplug.config.phases` for the keys).

A phased run directory::

    config.yaml, plugins.json      the whole config (with its phases), the plugins
    <phase>/                       one ordinary run directory per phase (config.yaml = the phase's
                                   resolved config, checkpoints/, logs/, metrics.json) + DONE when finished
    pseudo_labels/<phase>.<head>.<subset>/   a teacher's pseudo labels (occplug.data.teacher_labels)
    metrics.json                   {"phases": {name: that phase's metrics.json}, "final_phase": name,
                                   + the final phase's metrics at the top level}

``occplug fit --resume RUN`` skips the finished phases (their DONE marker), continues the first
unfinished one from its last checkpoint (mid-epoch too, as any run) and starts it afresh when it had
none. Every phase seeds the random-number generators itself, so a resumed run ends as the
uninterrupted one does.

Everything that can be checked before training is checked first, for every phase: each phase's data
module and model are built, ``freeze`` and ``init_from`` prefixes must name parameters of the models
involved (``init_from`` files are read and fitted: :mod:`occplug.run.weights`), a phase must train
something, and one batch runs through it (``runner.first_batch_check``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback

from occplug.config.phases import PhaseSpec, PseudoLabelsFrom, phase_specs
from occplug.config.yamlio import dump_yaml
from occplug.data.teacher_labels import DONE, META, write_teacher_file
from occplug.interfaces.model import OccupancyModel
from occplug.run import preflight, runner
from occplug.run.rundir import check_fresh_run_dir, run_lock
from occplug.run.weights import init_from, init_from_config, matching
from occplug.streams import find_streams, set_stream_stage

__all__ = ["FrozenModulesEval", "fit_phases", "freeze", "init_from", "matching", "write_teacher_labels"]


#: Entries of a phase's metrics.json that describe the run, not its validation metrics.
RUN_RECORD = frozenset(
    {"global_step", "epoch", "effective_batch", "effective_batch_parts", "lr", "label_fraction", "subset", "eval_mask"}
)


def freeze(model: OccupancyModel, prefixes: Sequence[str], where: str) -> list[str]:
    """Stop gradients of the parameters under ``prefixes``; return the frozen modules' names.

    Raises:
        runner.RunError: a prefix names no parameter, or nothing is left to train.
    """
    params = dict(model.named_parameters())
    for prefix in prefixes:
        if not matching(list(params), prefix):
            raise runner.RunError(f"{where}: {prefix!r} names no parameter of the model")
        for name in matching(list(params), prefix):
            params[name].requires_grad_(False)
    if not any(p.requires_grad for p in params.values()):
        raise runner.RunError(f"{where}: every parameter is frozen, so the phase would train nothing")
    return [n for n, _ in model.named_modules() if n and any(matching([n], p) for p in prefixes)]


class FrozenModulesEval(Callback):
    """Keeps the frozen modules in eval mode (BatchNorm statistics, dropout) while the rest trains.

    Lightning puts the whole model in train mode at each training epoch and after each validation,
    so this runs before every training batch.
    """

    def __init__(self, names: list[str]) -> None:
        self.names = names  # filled by the phase's set-up once the model is built

    def _apply(self, pl_module: L.LightningModule) -> None:
        modules = dict(pl_module.named_modules())
        for name in self.names:
            modules[name].eval()

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._apply(pl_module)

    def on_train_batch_start(
        self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int
    ) -> None:
        self._apply(pl_module)


def _last_checkpoint(run_dir: Path, phase: str) -> Path:
    return run_dir / phase / "checkpoints" / "last.ckpt"


def write_teacher_labels(teacher: PhaseSpec, consumer: PhaseSpec, source: PseudoLabelsFrom, run_dir: Path) -> Path:
    """The teacher's pseudo labels for ``consumer``'s training frames, written once (see the module docstring).

    The teacher phase's model (its last checkpoint) predicts head ``source.head`` on the training
    frames of ``source.subset`` under ``consumer``'s label fraction, un-augmented, in eval mode. A
    streaming teacher (one holding a :class:`~occplug.streams.StreamState`) runs every training frame in
    order, one frame at a time, so each frame is predicted with the history it has in a stream; files are
    written for the subset's frames only. A complete folder (DONE marker) is reused as it is.
    """
    folder = run_dir / "pseudo_labels" / source.folder_name
    if (folder / DONE).is_file():
        return folder
    data = dict(teacher.config["data"])
    consumer_data = consumer.config.get("data") or {}
    for key in ("label_fraction",):
        if key in consumer_data:
            data[key] = consumer_data[key]
        else:
            data.pop(key, None)
    data.update({"subset": "all", "augment": None})
    cfg = {**teacher.config, "data": data}
    dm, model = runner.build_run(cfg)
    where = f"phases.{consumer.name}.pseudo_labels_from"
    streamed = any(True for _ in find_streams(model))
    if not streamed and source.subset != "all":  # batches of the subset's frames alone
        dm = runner.build_datamodule({**cfg, "data": {**data, "subset": source.subset}})
        dm.require_fields(set(model.required_fields()) | runner.callback_requirements(cfg))
    if streamed:  # each frame predicted with its own history: every training frame in order, one slot
        set_stream_stage(model, "predict")
        for _, stream in find_streams(model):
            stream.clear("predict")
    state = runner.load_checkpoint(_last_checkpoint(run_dir, teacher.name))["state_dict"]
    model.load_state_dict(state)
    model.eval()
    folder.mkdir(parents=True, exist_ok=True)
    (folder / DONE).unlink(missing_ok=True)
    dataset = dm.dataset("train")
    size = 1 if streamed else max(1, int(dm.batch_size))
    count = 0
    with torch.no_grad(), runner.data_errors():
        for start in range(0, len(dataset), size):  # type: ignore[arg-type]
            frames = [dataset[i] for i in range(start, min(start + size, len(dataset)))]  # type: ignore[arg-type]
            batch = dm.collate(frames)
            try:
                logits = model.head_logits(batch, source.head).float()
            except ValueError as exc:
                raise runner.RunError(f"{where}: {runner._first_line(exc)}") from None
            confidence, labels = logits.softmax(dim=1).max(dim=1)
            for b, token in enumerate(batch.token):
                if streamed and not _in_subset(frames[b], source.subset):
                    continue  # a frame the stream ran through for its history only
                write_teacher_file(folder, token, labels[b].numpy(), confidence[b].numpy())
                count += 1
    k = int(logits.shape[1]) if count else 0
    meta = {
        "grid": list(model.grid.shape),
        "class_names": list(dm.class_names) if k == len(dm.class_names) else [f"class_{i}" for i in range(k)],
        "teacher": teacher.name,
        "head": source.head,
        "subset": source.subset,
        "label_fraction": dm.label_cut.fraction,
        "frames": count,
    }
    runner.write_text_atomic(folder / META, json.dumps(meta, indent=2) + "\n")
    runner.write_text_atomic(folder / DONE, f"{count} frames\n")
    return folder


def _in_subset(frame: Any, subset: str) -> bool:
    """Whether a training frame belongs to ``subset`` (``all``, ``labelled``, ``unlabelled``) of a label fraction."""
    return subset == "all" or bool(frame.has_voxel_labels) == (subset == "labelled")


def _with_teacher_labels(spec: PhaseSpec, folder: Path) -> dict[str, Any]:
    """The phase's config with the ``teacher_pseudo_labels`` label source reading ``folder``."""
    assert spec.pseudo_labels_from is not None
    data = dict(spec.config["data"])
    sources = dict(data.get("label_sources") or {})
    sources["teacher"] = {
        "type": "teacher_pseudo_labels",
        "folder": str(folder),
        "confidence_threshold": spec.pseudo_labels_from.confidence_threshold,
    }
    data["label_sources"] = sources
    return {**spec.config, "data": data}


def _setup(spec: PhaseSpec, run_dir: Path, fresh: bool) -> tuple[Any, list[str]]:
    """The model set-up of a phase (``init_from`` when it starts afresh, then ``freeze``) and the frozen modules."""
    frozen: list[str] = []

    def setup(model: OccupancyModel) -> None:
        if fresh and spec.init_from:
            lines = init_from(model, spec.init_from, run_dir, f"phases.{spec.name}.init_from")
            if runner.is_rank_zero():
                print("\n".join(lines))
        if spec.freeze:
            frozen[:] = freeze(model, spec.freeze, f"phases.{spec.name}.freeze")

    return setup, frozen


def check_phases(specs: Sequence[PhaseSpec]) -> None:
    """Build every phase before anything is written: trainable, prefixes that exist, one batch through it."""
    keys: dict[str, list[str]] = {}
    for spec in specs:
        where = f"phases.{spec.name}"
        try:
            dm, model = runner.build_run(spec.config)
            runner.check_trainable(model)
        except runner.RunError as exc:
            raise runner.RunError(f"{where}: {exc}") from None
        keys[spec.name] = list(model.state_dict())
        init_from_config(model, spec.config)  # the files: present, readable, fitting (the phases' checkpoints: below)
        init_from(model, spec.init_from, Path(), f"{where}.init_from", files_only=True)
        for i, entry in enumerate(spec.init_from):
            if entry.phase is None:
                continue
            for prefix in entry.prefixes:
                if not set(matching(keys[entry.phase], prefix)) & set(keys[spec.name]):
                    raise runner.RunError(
                        f"{where}.init_from[{i}]: {prefix!r} names nothing that phase '{entry.phase}' and this phase share"
                    )
        if spec.freeze:
            freeze(model, spec.freeze, f"{where}.freeze")
        try:
            runner.first_batch_check(model, dm)
        except runner.RunError as exc:
            raise runner.RunError(f"{where}: {exc}") from None


def _check_phase_settings(specs: Sequence[PhaseSpec]) -> None:
    """:func:`occplug.run.preflight.check_run` for each phase on a Trainer and data module built for it alone, so
    that a mistake in any phase is found before the run directory is made (the line names the phase). Lightning's
    start-up lines are held back here: each phase's own fit prints them."""
    log = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    level = log.level
    log.setLevel(logging.WARNING)
    try:
        for spec in specs:
            try:
                trainer = runner._trainer(spec.config, None, [])
                try:  # a phase's data may name files an earlier phase writes (teacher labels): its own fit checks
                    dm = runner.build_datamodule(spec.config)
                except (ValueError, TypeError, OSError):
                    dm = None
                if dm is not None:
                    preflight.check_run(spec.config, trainer, dm)
                elif (problem := preflight.check_plan(preflight.plan_of(trainer, spec.config))) is not None:
                    raise runner.RunError(problem)
            except runner.RunError as exc:
                raise runner.RunError(f"phases.{spec.name}: {exc}") from None
    finally:
        log.setLevel(level)


def fit_phases(
    cfg: dict[str, Any], run_dir: Path, resume: bool = False, callbacks: Sequence[Callback] = ()
) -> dict[str, float]:
    """Run the phases of ``cfg`` in order into ``run_dir``; return the final phase's validation metrics.

    ``callbacks`` join every phase's trainer (as :func:`occplug.run.runner.fit`'s do; e.g. a probe timing steps).
    """
    specs = phase_specs(cfg)
    fresh = runner.is_rank_zero() and not resume
    if fresh:
        check_fresh_run_dir(run_dir)
    if not resume:
        check_phases(specs)
    _check_phase_settings(specs)  # DDP / precision mistakes of any phase, before anything is written
    with run_lock(run_dir) if runner.is_rank_zero() else contextlib.nullcontext():
        if fresh:  # again under the lock: another fit may have started here meanwhile
            check_fresh_run_dir(run_dir)
        return _fit_phases(cfg, specs, run_dir, callbacks)


def _fit_phases(
    cfg: dict[str, Any], specs: Sequence[PhaseSpec], run_dir: Path, callbacks: Sequence[Callback]
) -> dict[str, float]:
    by_name = {s.name: s for s in specs}
    if runner.is_rank_zero():
        runner.write_text_atomic(
            run_dir / "config.yaml",
            "# resolved occplug config with phases; each phase's own config in <phase>/config.yaml\n" + dump_yaml(cfg),
        )
        runner.write_text_atomic(run_dir / "plugins.json", json.dumps(runner.plugin_versions(), indent=2) + "\n")
        runner.write_text_atomic(
            run_dir / "environment.json", json.dumps(runner.numeric_environment(), indent=2) + "\n"
        )
    results: dict[str, dict[str, Any]] = {}
    final: dict[str, float] | None = None
    for spec in specs:
        phase_dir = run_dir / spec.name
        if (phase_dir / DONE).is_file():
            results[spec.name] = json.loads((phase_dir / "metrics.json").read_text())
            continue
        config = spec.config
        if spec.pseudo_labels_from is not None:
            source = spec.pseudo_labels_from
            folder = write_teacher_labels(by_name[source.phase], spec, source, run_dir)
            config = _with_teacher_labels(spec, folder)
        has_checkpoint = _last_checkpoint(run_dir, spec.name).is_file()
        if not has_checkpoint and phase_dir.exists() and runner.is_rank_zero():
            shutil.rmtree(phase_dir)  # killed before its first checkpoint: start it again
        setup, frozen = _setup(spec, run_dir, fresh=not has_checkpoint)
        print(f"phase {spec.name} ({len(results) + 1}/{len(specs)})")
        final = runner.fit(
            config, phase_dir, resume=has_checkpoint, setup=setup, callbacks=[FrozenModulesEval(frozen), *callbacks]
        )
        if runner.is_rank_zero():
            results[spec.name] = json.loads((phase_dir / "metrics.json").read_text())
            runner.write_text_atomic(phase_dir / DONE, "finished\n")
            runner.write_json(
                run_dir / "metrics.json", {**results[spec.name], "final_phase": spec.name, "phases": results}
            )
    if final is None:  # every phase had finished before: the final phase's recorded metrics
        recorded = results.get(specs[-1].name, {})
        final = {k: v for k, v in recorded.items() if k not in RUN_RECORD and isinstance(v, (int, float))}
    return final
