"""What a plugin adds to every data module without subclassing one: frame transforms, label sources, fields.

A plugin registers its classes like any component (``occplug_register_components``)::

    registry.add("label_source", "my_boxes_2d", MyBoxes2D)     # a LabelSource subclass
    registry.add("transform", "point_subsample", PointSub)     # a FrameTransform subclass

and a config names them by registered ``type:`` under the data node, for every data module
(``synthetic``, ``occ3d_nuscenes``, ``semantickitti``)::

    data:
      label_sources:                       # name -> node (null: off); attached in this order
        boxes_2d: {type: my_boxes_2d, dir: boxes2d/}
      transforms:                          # applied in this order, after the augmentation
        - {type: point_subsample, max_points: 20000, splits: [train]}
      fields:                              # collate rules of extra fields (see FieldRule)
        my_ids: list

Where they run (:class:`~occplug.data.pipeline.FramePipeline`): label sources right after the
pseudo labels, on the frame and each adjacent frame as decoded (original image resolution, no
augmentation yet); transforms last, on the finished sample (adjacent frames included, which a
transform may read or change), in the splits its ``splits:`` key names (default all).

Both may write any :class:`~occplug.data.Frame` field or a new per-sample field in
``Frame.extras[name]``. A new field's collate rule (its class attribute ``fields``, or
``data.fields``) decides its place in the :class:`~occplug.data.Batch`: ``stack`` a tensor with a
leading batch axis, ``pad`` a ``(B, L_max, ...)`` tensor padded with ``pad_value`` along the first
axis plus ``Batch.extras[name + "_mask"]`` ``(B, L_max)`` bool (True = real entry), ``list`` a list
of ``B`` values (also the rule of any undeclared extra). Extra fields are not resized or augmented:
a pixel-aligned one is at the original image resolution (``Frame.img_aug`` relates the two).

Factories receive ``class_names``, ``grid``, ``free_label`` and ``ignore_label`` of the data module
when their constructor takes them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

from occplug.context import ComponentBuilder
from occplug.errors import ComponentArgumentError, closest
from occplug.geometry import GridSpec

from .frame import FieldRule, Frame, field_rule

__all__ = ["SPLIT_NAMES", "DataExtensions", "FrameTransform", "LabelSource"]

#: The splits a transform may be restricted to.
SPLIT_NAMES = ("train", "val", "test", "predict")


class LabelSource:
    """Base of a registered ``label_source``: attaches labels to a frame as decoded.

    Contract:
        given: ``class_names``, ``grid``, ``free_label``, ``ignore_label`` (the data module's), where
        the constructor takes them.

    Attributes:
        fields: collate rules of the ``Frame.extras`` fields it writes (name -> :class:`FieldRule`).
    """

    given: ClassVar[tuple[str, ...]] = ("class_names", "grid", "free_label", "ignore_label")
    fields: ClassVar[Mapping[str, FieldRule]] = {}

    def attach(self, frame: Frame) -> Frame:
        """The frame with the labels filled in (called once per frame and adjacent frame)."""
        raise NotImplementedError


class FrameTransform:
    """Base of a registered ``transform``: changes a finished sample (after augmentation).

    Contract:
        given: ``class_names``, ``grid``, ``free_label``, ``ignore_label`` (the data module's), where
        the constructor takes them.

    Attributes:
        fields: collate rules of the ``Frame.extras`` fields it writes (name -> :class:`FieldRule`).
    """

    given: ClassVar[tuple[str, ...]] = ("class_names", "grid", "free_label", "ignore_label")
    fields: ClassVar[Mapping[str, FieldRule]] = {}

    def __call__(self, frame: Frame) -> Frame:
        """The transformed sample (its ``adjacent`` frames included)."""
        raise NotImplementedError


def _build(kind: str, node: Any, path: str, context: Mapping[str, Any], registry: ComponentBuilder | None) -> Any:
    if not isinstance(node, Mapping) or "type" not in node:
        raise ValueError(f"{path}: expected a mapping with a 'type:' naming a registered {kind}, got {node!r}")
    if registry is None:
        raise ValueError(f"{path}: the data module was built without a registry (build it with Registry.build)")
    name = str(node["type"])
    if not registry.has(kind, name):
        names = registry.names(kind)
        hint = closest(name, names)
        raise ValueError(
            f"{path}.type: no {kind} '{name}'{f'; did you mean {hint!r}?' if hint else ''} "
            f"(registered: {', '.join(names) or 'none'})"
        )
    try:
        return registry.build(kind, node, **context)
    except ComponentArgumentError as exc:
        raise ValueError(f"{path}.{exc.key}: {exc}") from None
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: {exc}") from None


class DataExtensions:
    """The ``label_sources``, ``transforms`` and ``fields`` of a data module, built from its config.

    Args:
        label_sources: name -> ``{type: <label_source>, ...}``.
        transforms: list of ``{type: <transform>, splits: [...], ...}``.
        fields: name -> collate rule (``stack`` / ``list`` / ``pad`` or ``{collate, pad_value}``).
        registry: the registry the label sources and transforms are built from (the one the data module was
            built from; the builder hands it in).
        class_names, grid, free_label, ignore_label: the data module's, passed to factories that take them.

    Raises:
        ValueError: one line naming the config key (``data.transforms[1].type: no transform 'x' ...``).
    """

    def __init__(
        self,
        label_sources: Mapping[str, Any] | None = None,
        transforms: Sequence[Any] | None = None,
        fields: Mapping[str, Any] | None = None,
        *,
        registry: ComponentBuilder | None = None,
        class_names: Sequence[str] = (),
        grid: GridSpec | None = None,
        free_label: int | None = None,
        ignore_label: int | None = None,
    ) -> None:
        context = {
            "class_names": tuple(class_names),
            "grid": grid,
            "free_label": free_label,
            "ignore_label": ignore_label,
        }
        if label_sources is not None and not isinstance(label_sources, Mapping):
            raise ValueError(
                f"data.label_sources: expected a mapping name -> {{type: ...}}, got {type(label_sources).__name__}"
            )
        if transforms is not None and (isinstance(transforms, (str, Mapping)) or not isinstance(transforms, Sequence)):
            raise ValueError(
                f"data.transforms: expected a list of {{type: ...}} nodes, got {type(transforms).__name__}"
            )
        self.label_sources: dict[str, Any] = {}
        for name, node in (label_sources or {}).items():
            if node is None:  # `name: null` switches a layered entry off
                continue
            source = _build("label_source", node, f"data.label_sources.{name}", context, registry)
            if not callable(getattr(source, "attach", None)):
                raise ValueError(f"data.label_sources.{name}: '{node['type']}' has no attach(frame) method")
            self.label_sources[str(name)] = source
        self.transforms: list[tuple[Any, frozenset[str]]] = []
        for i, node in enumerate(transforms or ()):
            path = f"data.transforms[{i}]"
            node = dict(node) if isinstance(node, Mapping) else node
            splits = node.pop("splits", None) if isinstance(node, dict) else None
            chosen = frozenset(SPLIT_NAMES if splits is None else ([splits] if isinstance(splits, str) else splits))
            bad = sorted(chosen - set(SPLIT_NAMES))
            if bad:
                raise ValueError(f"{path}.splits: unknown split '{bad[0]}' (valid: {', '.join(SPLIT_NAMES)})")
            transform = _build("transform", node, path, context, registry)
            if not callable(transform):
                raise ValueError(f"{path}: '{node['type']}' is not callable on a frame")
            self.transforms.append((transform, chosen))
        rules: dict[str, FieldRule] = {}
        for part in [*self.label_sources.values(), *(t for t, _ in self.transforms)]:
            for name, rule in dict(getattr(part, "fields", {}) or {}).items():
                rules[str(name)] = field_rule(rule, f"{type(part).__name__}.fields.{name}")
        for name, rule in (fields or {}).items():
            rules[str(name)] = field_rule(rule, f"data.fields.{name}")
        self.fields = rules

    def transforms_for(self, split: str) -> list[Any]:
        """The transforms that run in ``split``, in config order."""
        return [t for t, splits in self.transforms if split in splits]
