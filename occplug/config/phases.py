"""Named phases: a run as a sequence of trainings, each an overlay on the run's config.

::

    phases:                                  # run order
      teacher:
        data: {label_fraction: 0.1, subset: labelled, augment: weak}
        trainer: {max_epochs: 30}
      student:
        data: {label_fraction: 0.1, augment: strong}
        init_from: [{phase: teacher, prefixes: [model]}]
        pseudo_labels_from: {phase: teacher, head: occupancy, subset: unlabelled, confidence_threshold: 0.7}
      finetune:
        data: {label_fraction: 0.1, subset: labelled}
        init_from: [{phase: student, prefixes: [model]}]
        freeze: [model.encoder, model.view_transform]

A phase's config is the run's config (without ``phases``) with the phase's overlay merged in:
mappings merge key by key, anything else replaces, and a key written ``~name`` removes ``name``
(``model: {supervision: {~depth: null}}`` drops one loss). Three keys belong to phases only:

* ``freeze``: parameter prefixes (``model.<attribute path>``) trained by no optimizer; modules under
  them stay in eval mode (BatchNorm statistics untouched).
* ``init_from``: ``[{phase, prefixes}]``: before the phase trains, copy the weights under ``prefixes``
  from an earlier phase's last checkpoint (later entries win; parts the earlier phase lacks keep their
  initialisation). An entry may instead read a state-dict file, ``{file, map, strict}``, as the
  top-level ``init_from`` does (:func:`parse_init_from`); a top-level ``init_from`` applies to every
  phase that starts afresh, before the phase's own entries (``~init_from: null`` in an overlay drops it).
* ``pseudo_labels_from``: ``{phase, head, subset, confidence_threshold}``: the earlier phase's model
  predicts the named head's classes and confidence once, offline, on un-augmented frames of the
  training ``subset`` (default ``unlabelled``); the phase trains on them where a frame has no real
  labels, voxels below the threshold ignored (:mod:`occplug.data.teacher_labels`).
"""

from __future__ import annotations

import copy
import re
from dataclasses import dataclass, field
from typing import Any

from occplug.errors import ConfigError

__all__ = [
    "PHASE_KEYS",
    "InitFrom",
    "PhaseSpec",
    "PseudoLabelsFrom",
    "merge_overlay",
    "parse_init_from",
    "phase_specs",
    "state_prefix",
]

#: Keys of a phase overlay that are not run-config keys.
PHASE_KEYS = ("freeze", "init_from", "pseudo_labels_from")

#: Names a phase cannot take (files and folders of the run directory).
RESERVED = frozenset({"pseudo_labels", "checkpoints", "logs", "tensorboard", "mlruns", "wandb"})

_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]*")  # matched whole (fullmatch: no trailing newline slips past '$')


@dataclass(frozen=True)
class InitFrom:
    """Weights copied into a freshly built model before it trains (:func:`occplug.run.weights.init_from`).

    From an earlier phase: ``phase`` names it and ``prefixes`` (``model`` or ``model.<attribute path>``)
    the weights copied from its last checkpoint. From a state-dict file: ``phase`` is None, ``file`` is
    the path and ``map`` the key map, ``(foreign key prefix, state-dict prefix or None)`` pairs, longest
    foreign prefix first; the state-dict prefix is the target without ``model.`` (``encoder.backbone.``),
    None drops the keys. ``strict``: every mapped key must name a tensor of the model, and every tensor
    under a mapped target must be loaded.
    """

    phase: str | None
    prefixes: tuple[str, ...] = ("model",)
    file: str | None = None
    map: tuple[tuple[str, str | None], ...] = ()
    strict: bool = True


@dataclass(frozen=True)
class PseudoLabelsFrom:
    """Teacher pseudo labels: phase ``phase``'s head ``head`` on the training ``subset``, kept at
    confidence >= ``confidence_threshold``."""

    phase: str
    head: str
    subset: str = "unlabelled"
    confidence_threshold: float = 0.0

    @property
    def folder_name(self) -> str:
        """The folder under ``<run>/pseudo_labels/`` holding these labels."""
        return f"{self.phase}.{self.head}.{self.subset}"


@dataclass
class PhaseSpec:
    """One phase: its name, its whole run config, and the phase-only settings."""

    name: str
    config: dict[str, Any]
    freeze: tuple[str, ...] = ()
    init_from: tuple[InitFrom, ...] = ()
    pseudo_labels_from: PseudoLabelsFrom | None = None
    overlay: dict[str, Any] = field(default_factory=dict)


def merge_overlay(base: dict[str, Any], overlay: dict[str, Any], path: str = "") -> dict[str, Any]:
    """``base`` with ``overlay`` merged in (mappings by key, ``~key`` removes, other values replace); new dict."""
    out = copy.deepcopy(base)
    for key, value in overlay.items():
        key = str(key)
        if key.startswith("~"):
            name = key[1:]
            if name not in out:
                raise ConfigError(f"{path}{key}: nothing named '{name}' to remove")
            del out[name]
        elif isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge_overlay(out[key], value, f"{path}{key}.")
        else:
            out[key] = copy.deepcopy(value)
    return out


def _prefixes(value: Any, where: str) -> tuple[str, ...]:
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not value or not all(isinstance(p, str) and p for p in value):
        raise ConfigError(
            f"{where}: expected a non-empty list of parameter prefixes (e.g. [model.encoder]), got {value!r}"
        )
    for p in value:
        if p != "model" and not p.startswith("model."):
            raise ConfigError(f"{where}: prefix {p!r} must start with 'model' (e.g. model.encoder)")
    return tuple(value)


def _earlier(name: Any, before: list[str], where: str) -> str:
    if not isinstance(name, str) or name not in before:
        shown = ", ".join(before) or "none"
        raise ConfigError(f"{where}: {name!r} is not an earlier phase (earlier phases: {shown})")
    return name


def state_prefix(prefix: str) -> str:
    """``model.encoder`` -> ``encoder`` (state-dict keys have no ``model.``); ``model`` / ``model.`` -> ``""``."""
    return "" if prefix in ("model", "model.") else prefix[len("model.") :]


def _key_map(value: Any, where: str) -> tuple[tuple[str, str | None], ...]:
    """A file entry's ``map`` (foreign prefix -> ``model...`` prefix or null) as state-dict pairs, longest first."""
    if value is None:
        return (("", ""),)
    if not isinstance(value, dict) or not value:
        raise ConfigError(
            f"{where}: expected a mapping of foreign key prefix -> model prefix or null "
            f"(e.g. {{'img_backbone.': model.encoder.backbone.}}), got {value!r}"
        )
    pairs: list[tuple[str, str | None]] = []
    for source, target in value.items():
        at = f"{where}.{source}"
        if not isinstance(source, str):
            raise ConfigError(f"{at}: a foreign key prefix is a string, got {source!r}")
        if target is None:
            pairs.append((source, None))
            continue
        if not isinstance(target, str) or not (target == "model" or target.startswith("model.")):
            raise ConfigError(
                f"{at}: expected a prefix of the model's weights starting with 'model.' "
                f"(e.g. model.encoder.backbone.) or null to drop these keys, got {target!r}"
            )
        into = state_prefix(target)
        if into and source and source.endswith(".") != into.endswith("."):
            raise ConfigError(
                f"{at}: {source!r} -> {target!r}: a prefix ending in '.' maps onto one ending in '.' (and a whole key "
                "onto a whole key)"
            )
        if (not into and source and not source.endswith(".")) or (not source and into and not into.endswith(".")):
            raise ConfigError(f"{at}: {source!r} -> {target!r}: every key moves under a prefix ending in '.'")
        pairs.append((source, into))
    return tuple(sorted(pairs, key=lambda pair: -len(pair[0])))


def parse_init_from(value: Any, before: list[str] | None, where: str) -> tuple[InitFrom, ...]:
    """Read an ``init_from`` list: ``{phase, prefixes}`` and ``{file, map, strict}`` entries.

    Args:
        value: the list as written.
        before: the earlier phases (a phase overlay), or None at the top level, where only file
            entries are allowed.
        where: the config key, for messages.

    A file entry ``{file: PATH, map: {FOREIGN_PREFIX: model.PREFIX | null, ...}, strict: true}`` renames
    each key of the file's state dict by the longest foreign prefix it starts with (``map`` absent: the
    file's keys are the model's own, as in an occplug checkpoint); keys no prefix matches, or mapped to
    null, are not loaded.

    Raises:
        ConfigError: one line naming the entry's key.
    """
    if not isinstance(value, list):
        shape = "{file, map, strict}" if before is None else "{phase, prefixes} or {file, map, strict}"
        raise ConfigError(f"{where}: expected a list of {shape}, got {value!r}")
    out = []
    for i, item in enumerate(value):
        at = f"{where}[{i}]"
        if isinstance(item, dict) and "file" in item and not set(item) - {"file", "map", "strict"}:
            if not isinstance(item["file"], str) or not item["file"]:
                raise ConfigError(f"{at}.file: expected the path of a state-dict file, got {item['file']!r}")
            strict = item.get("strict", True)
            if not isinstance(strict, bool):
                raise ConfigError(f"{at}.strict: expected true or false, got {strict!r}")
            out.append(InitFrom(None, file=item["file"], map=_key_map(item.get("map"), f"{at}.map"), strict=strict))
        elif before is None:
            raise ConfigError(
                f"{at}: expected {{file: PATH, map: {{FOREIGN_PREFIX: model.PREFIX}}, strict: true}}, got {item!r}"
                + (
                    " ({phase, prefixes} entries belong in a phase's overlay)"
                    if isinstance(item, dict) and "phase" in item
                    else ""
                )
            )
        elif not isinstance(item, dict) or set(item) - {"phase", "prefixes"} or "phase" not in item:
            raise ConfigError(
                f"{at}: expected {{phase: NAME, prefixes: [model...]}} or {{file: PATH, map: {{...}}, strict: true}}, "
                f"got {item!r}"
            )
        else:
            out.append(
                InitFrom(
                    _earlier(item["phase"], before, f"{at}.phase"),
                    _prefixes(item.get("prefixes", ["model"]), f"{at}.prefixes"),
                )
            )
    return tuple(out)


def _pseudo(value: Any, before: list[str], specs: dict[str, PhaseSpec], where: str) -> PseudoLabelsFrom:
    from occplug.data.label_fraction import SUBSETS

    allowed = {"phase", "head", "subset", "confidence_threshold"}
    if not isinstance(value, dict) or set(value) - allowed or not {"phase", "head"} <= set(value):
        raise ConfigError(f"{where}: expected {{phase, head, subset, confidence_threshold}}, got {value!r}")
    phase = _earlier(value["phase"], before, f"{where}.phase")
    head = value["head"]
    heads = (specs[phase].config.get("model") or {}).get("heads")
    if not isinstance(head, str) or (isinstance(heads, dict) and head not in heads):
        raise ConfigError(
            f"{where}.head: phase '{phase}' has no head {head!r}"
            + (f" (heads: {', '.join(heads)})" if isinstance(heads, dict) else "")
        )
    subset = value.get("subset", "unlabelled")
    if subset not in SUBSETS:
        raise ConfigError(f"{where}.subset: expected one of {', '.join(SUBSETS)}, got {subset!r}")
    tau = value.get("confidence_threshold", 0.0)
    if isinstance(tau, bool) or not isinstance(tau, (int, float)) or not 0.0 <= tau <= 1.0:
        raise ConfigError(f"{where}.confidence_threshold: expected a number in [0, 1], got {tau!r}")
    return PseudoLabelsFrom(phase, head, subset, float(tau))


def phase_specs(config: dict[str, Any]) -> list[PhaseSpec]:
    """The phases of a resolved config in run order (empty without ``phases``).

    Raises:
        ConfigError: one line naming the phase key at fault.
    """
    phases = config.get("phases")
    if phases is None:
        return []
    if not isinstance(phases, dict) or not phases:
        raise ConfigError(f"phases: expected a non-empty mapping of phase name -> overlay, got {phases!r}")
    base = {k: v for k, v in config.items() if k != "phases"}
    specs: dict[str, PhaseSpec] = {}
    for name, overlay in phases.items():
        name = str(name)
        where = f"phases.{name}"
        if not _NAME.fullmatch(name) or name in RESERVED:
            raise ConfigError(
                f"phases: phase name {name!r}: a phase name is letters, digits, '_' and '-' (nothing else, no "
                f"trailing newline), and not one of {', '.join(sorted(RESERVED))}"
            )
        overlay = {} if overlay is None else overlay
        if not isinstance(overlay, dict):
            raise ConfigError(f"{where}: expected a mapping (the phase's overlay on the run config), got {overlay!r}")
        if "phases" in overlay:
            raise ConfigError(f"{where}.phases: phases do not nest")
        before = list(specs)
        run_keys = {k: v for k, v in overlay.items() if k not in PHASE_KEYS}
        spec = PhaseSpec(name=name, config=merge_overlay(base, run_keys, f"{where}."), overlay=dict(overlay))
        if "freeze" in overlay:
            spec.freeze = _prefixes(overlay["freeze"], f"{where}.freeze")
        if "init_from" in overlay:
            spec.init_from = parse_init_from(overlay["init_from"], before, f"{where}.init_from")
        if overlay.get("pseudo_labels_from") is not None:
            spec.pseudo_labels_from = _pseudo(
                overlay["pseudo_labels_from"], before, specs, f"{where}.pseudo_labels_from"
            )
            data = spec.config.get("data") or {}
            if float(data.get("label_fraction", 1.0)) >= 1.0 and spec.pseudo_labels_from.subset == "unlabelled":
                raise ConfigError(
                    f"{where}.pseudo_labels_from: the phase's data has no unlabelled frames (data.label_fraction is 1); "
                    "set data.label_fraction below 1"
                )
        specs[name] = spec
    return list(specs.values())
