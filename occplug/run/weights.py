"""Initialising a built model's weights: from an earlier phase's checkpoint, or from a state-dict file with a key map.

The config (``init_from``, top level or in a phase's overlay; parsed by
:func:`occplug.config.phases.parse_init_from`)::

    init_from:
      - file: weights/bevdet-r50-4d-depth-cbgs.pth        # an mmdet detector checkpoint
        map: {"img_backbone.layer4.": null, "img_backbone.": model.encoder.backbone.}
        strict: true

The file is read with ``torch.load(..., map_location="cpu", weights_only=True)``; its state dict may be
the file itself or nested under ``state_dict`` / ``model``. Each key is renamed by the longest foreign
prefix it starts with (``img_backbone.layer1.0.bn1.running_mean`` ->
``encoder.backbone.layer1.0.bn1.running_mean``); keys no prefix matches, or mapped to null, are not
loaded. Without ``map`` the file's keys are the model's own (an occplug checkpoint). ``strict`` (the
default): every mapped key must name a tensor of the model, and every tensor of the model under a
mapped target must be loaded. Always an error (one line naming the file and the key, exit code 2
from the CLI, nothing trained): a missing or unreadable file, a map entry that loads nothing, a
shape that differs, two keys mapped onto one. Each entry reports one line; for that file and the
``timm`` encoder's ``resnet50`` at ``feature_level: 3`` (whose backbone ends at ``layer3``, hence
``layer4`` -> null) the count is ResNet-50's stem and first three stages with their BatchNorm
statistics, the rest of the detector not mapped::

    init_from[0]: weights/bevdet-r50-4d-depth-cbgs.pth: loaded 258 tensors; missing 0; unexpected U
    (U - 60 not mapped, 60 mapped to null, 0 not in the model)

Entries apply in order, later ones winning; ``fit`` applies them when a run (or a phase) starts
afresh, never on ``--resume``, and ``validate`` / ``test`` / ``predict`` read their checkpoint instead.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from torch import Tensor, nn

from occplug.config.phases import InitFrom, parse_init_from, state_prefix
from occplug.run.checkpoints import RunError, load_checkpoint

__all__ = ["init_from", "init_from_config", "matching", "read_state_file"]

#: A key's fate under an entry's map: (index of the map entry or prefix that took it, state-dict name or None).
Renamed = tuple[int, str | None]


def matching(names: Sequence[str], prefix: str) -> list[str]:
    """The parameter / state-dict names under ``prefix`` (``model`` or ``model.<attribute path>``)."""
    p = state_prefix(prefix)
    return [n for n in names if not p or n == p or n.startswith(p + ".")]


def read_state_file(path: str | Path, where: str) -> dict[str, Tensor]:
    """The tensors of a state-dict file (raw, or nested under ``state_dict`` / ``model``), read with ``weights_only``.

    Raises:
        RunError: one line naming ``where`` and the file (missing, unreadable, no state dict).
    """
    from occplug.components.encoders import load_state_dict_file

    path = Path(path)
    if not path.is_file():
        raise RunError(f"{where}.file: {path} does not exist")
    try:
        state = load_state_dict_file(str(path))
    except Exception as exc:
        raise RunError(
            f"{where}.file: {path} cannot be read as a state dict (torch.load, weights_only=True): "
            f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"
        ) from None
    tensors = {str(k): v for k, v in state.items() if isinstance(v, Tensor)}
    if not tensors:
        raise RunError(f"{where}.file: {path} holds no tensors")
    return tensors


def _first_segments(names: Sequence[str], limit: int = 6) -> str:
    """``img_backbone., img_neck., ...``: the distinct first name segments, for messages."""
    heads = list(dict.fromkeys(n.split(".")[0] + ("." if "." in n else "") for n in names))
    return ", ".join(heads[:limit]) + (", ..." if len(heads) > limit else "")


def _file_renamer(pairs: Sequence[tuple[str, str | None]]) -> Callable[[str], Renamed | None]:
    """Longest foreign prefix first (``pairs`` come sorted so); None for a key no prefix matches."""

    def rename(key: str) -> Renamed | None:
        for i, (source, into) in enumerate(pairs):
            if key.startswith(source):
                return i, None if into is None else into + key[len(source) :]
        return None

    return rename


def _phase_renamer(prefixes: Sequence[str]) -> Callable[[str], Renamed | None]:
    """The keys under one of ``prefixes`` keep their names."""

    def rename(key: str) -> Renamed | None:
        for i, prefix in enumerate(prefixes):
            if matching([key], prefix):
                return i, key
        return None

    return rename


def _select(
    state: dict[str, Tensor], own: dict[str, Tensor], entry: InitFrom, source: str, at: str
) -> tuple[dict[str, Tensor], str]:
    """The tensors of ``state`` that ``entry`` loads, by the model's names, and the entry's one-line report."""
    if entry.file is None:
        rename, rules = _phase_renamer(entry.prefixes), list(entry.prefixes)
        targets: list[str | None] = [state_prefix(p) for p in entry.prefixes]
    else:
        rename, rules = _file_renamer(entry.map), [source for source, _ in entry.map]
        targets = [into for _, into in entry.map]
    chosen: dict[str, Tensor] = {}
    origin: dict[str, str] = {}
    matched, landed = [0] * len(rules), [0] * len(rules)
    unmapped = dropped = 0
    absent: list[tuple[str, str, int]] = []  # (foreign key, model name, map entry)
    for key, tensor in state.items():
        renamed = rename(key)
        if renamed is None:
            unmapped += 1
            continue
        rule, target = renamed
        matched[rule] += 1
        if target is None:
            dropped += 1
        elif target not in own:
            absent.append((key, target, rule))
        elif tensor.shape != own[target].shape:
            raise RunError(
                f"{at}: {source}: {key} is {tuple(tensor.shape)} but model.{target} is {tuple(own[target].shape)}"
            )
        elif target in origin:
            raise RunError(f"{at}: {source}: {origin[target]} and {key} both map to model.{target}")
        else:
            chosen[target], origin[target] = tensor, key
            landed[rule] += 1
    for rule, name in enumerate(rules):
        if targets[rule] is None or landed[rule]:
            continue
        if entry.file is None:
            raise RunError(f"{at}: {name!r} names nothing that {source} and this phase share")
        if not matched[rule]:
            raise RunError(
                f"{at}.map: no key of {source} starts with {name!r} (its keys start with: {_first_segments(list(state))})"
            )
        example = next((k, t) for k, t, r in absent if r == rule)
        raise RunError(
            f"{at}.map: the {matched[rule]} keys of {source} under {name!r} map onto nothing in the model (e.g. "
            f"{example[0]} -> model.{example[1]}; the model's weights start with: {_first_segments(list(own))})"
        )
    under = [t for t in targets if t is not None]
    if entry.file is None:
        missing = [k for k in own if k not in chosen and any(matching([k], p) for p in entry.prefixes)]
    else:
        missing = [k for k in own if k not in chosen and any(k.startswith(t) for t in under)]
    if entry.strict and entry.file is not None:
        if absent:
            key, target, _ = absent[0]
            raise RunError(
                f"{at}: {source}: {key} maps to model.{target}, which the model does not have ({len(absent)} such "
                "keys; strict: map them to null or set strict: false)"
            )
        if missing:
            raise RunError(
                f"{at}: {source} gives no tensor for model.{missing[0]} ({len(missing)} such weights under the map's "
                "targets; strict: set strict: false to keep their initialisation)"
            )
    report = (
        f"{at}: {source}: loaded {len(chosen)} tensors; missing {len(missing)}; unexpected "
        f"{unmapped + dropped + len(absent)} ({unmapped} not mapped, {dropped} mapped to null, {len(absent)} not in the model)"
    )
    return chosen, report


def init_from(
    model: nn.Module, entries: Sequence[InitFrom], run_dir: Path, where: str, files_only: bool = False
) -> list[str]:
    """Load each entry's weights into ``model`` in order (later entries win); return one report line per entry.

    A phase entry copies the weights under its prefixes from ``run_dir/<phase>/checkpoints/last.ckpt``:
    parts of ``model`` the earlier phase lacks keep their initialisation (never strict). A file entry
    reads its file and renames the keys by its map (module docstring). A prefix or map entry that loads
    nothing, a shape that differs, and (strict) a mapped key the model lacks or a weight under a target
    the file does not give are one-line errors naming ``where[i]``, the source and the key.

    Args:
        model: the built model; state-dict names (``encoder.backbone.conv1.weight``) are config prefixes
            without ``model.``.
        entries: the parsed ``init_from`` entries.
        run_dir: the phased run's directory (phase entries read their checkpoints there).
        where: the config key of the list, for messages.
        files_only: skip the phase entries (checking a config before the phases have run).

    Raises:
        RunError: one line.
    """
    lines = []
    for i, entry in enumerate(entries):
        if entry.file is None and files_only:
            continue
        at = f"{where}[{i}]"
        own = model.state_dict()
        if entry.file is None:
            path = run_dir / str(entry.phase) / "checkpoints" / "last.ckpt"
            state, source = load_checkpoint(path)["state_dict"], f"phase '{entry.phase}'"
        else:
            state, source = read_state_file(entry.file, at), entry.file
        chosen, report = _select(state, own, entry, source, at)
        model.load_state_dict(chosen, strict=False)
        lines.append(report)
    return lines


def init_from_config(model: nn.Module, cfg: dict[str, Any]) -> list[str]:
    """Apply a run config's top-level ``init_from`` (file entries) to ``model``; the report lines (none without it)."""
    if cfg.get("init_from") is None:
        return []
    return init_from(model, parse_init_from(cfg["init_from"], None, "init_from"), Path(), "init_from")
