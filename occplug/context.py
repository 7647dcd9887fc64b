"""The run context: the values one run hands to every component that asks for them, built once by the runner.

A component asks for the context by declaring a constructor parameter named ``context`` (annotated
:class:`RunContext`); the builder (:meth:`occplug.Registry.build`) hands it in, and a component that builds
components of its own (the model its encoder, a view transform its depth net, a data module its label sources)
builds them through :meth:`RunContext.build`, so they receive the same context. A component that takes only
``grid`` or ``num_classes`` keeps receiving them as its kind's ``given`` arguments, from the same context.

A leaf module: it imports the geometry alone, so every layer of the core may read it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from occplug.geometry import GridSpec

if TYPE_CHECKING:
    from occplug.registry import Registry

__all__ = ["ComponentBuilder", "RunContext", "parse_grid"]


def parse_grid(value: GridSpec | Mapping[str, Any]) -> GridSpec:
    """A grid as a config writes it (``{range, voxel_size, contraction?}``) as a :class:`GridSpec` (one passes
    through): the one place a grid is parsed. The builder (:meth:`occplug.Registry.build`, for an argument annotated
    ``GridSpec``), the runner's run context, the config validator and the synthetic world's knobs call it; a
    component receives a ``GridSpec`` and parses nothing.

    Raises:
        ValueError: not a grid (the message names what is wrong).
    """
    return GridSpec.from_config(value)


@runtime_checkable
class ComponentBuilder(Protocol):
    """What a component that builds nested nodes needs of the registry (:class:`occplug.Registry` is one)."""

    def build(self, kind: str, spec: Mapping[str, Any] | str, /, **given: Any) -> Any: ...

    def has(self, kind: str, name: str) -> bool: ...

    def names(self, kind: str, pattern: str = "*") -> list[str]: ...


@dataclass(frozen=True)
class RunContext:
    """The run's grid, classes and masks, and the registry its components are built from (immutable).

    Attributes:
        grid: the label / evaluation grid (ego frame), parsed once from the config's top-level ``grid``.
        class_names: names of the label ids, index = id (the data set's taxonomy).
        free_label: id of empty space.
        ignore_label: id ignored by losses and metrics, or None.
        class_groups: group name -> ids of ``class_names`` (``free``, ``ignore``, ``dynamic``, ... of
            :func:`occplug.data.classes.class_groups`); empty for a taxonomy without groups.
        eval_mask: the run's evaluation mask (``none``, ``camera``, ``lidar``, ``camera_and_lidar``), or None.
        registry: where nested components are built from (not compared, not shown).
    """

    grid: GridSpec
    class_names: tuple[str, ...]
    free_label: int
    ignore_label: int | None = None
    class_groups: Mapping[str, tuple[int, ...]] = field(default_factory=dict)
    eval_mask: str | None = None
    registry: Registry | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.grid, GridSpec):
            raise TypeError(f"RunContext.grid must be a GridSpec, got {type(self.grid).__name__}")
        object.__setattr__(self, "class_names", tuple(str(n) for n in self.class_names))
        groups = {str(k): tuple(int(i) for i in v) for k, v in dict(self.class_groups).items()}
        object.__setattr__(self, "class_groups", MappingProxyType(groups))

    def __deepcopy__(self, memo: dict[int, Any]) -> RunContext:
        return self  # immutable: a copied model (the runner's first-batch probe) shares its run's context

    @property
    def num_classes(self) -> int:
        """``K``: the number of label ids."""
        return len(self.class_names)

    def ids(self, group: str) -> tuple[int, ...]:
        """The ids of class group ``group``.

        Raises:
            ValueError: the taxonomy has no such group (one line naming the groups it has).
        """
        if group not in self.class_groups:
            have = ", ".join(self.class_groups) or "none"
            raise ValueError(f"class group '{group}' is not defined for these classes (groups: {have})")
        return self.class_groups[group]

    def build(self, kind: str, spec: Mapping[str, Any] | str, **given: Any) -> Any:
        """Build a nested component of ``kind`` from ``spec``, handing it this context (where it declares one)."""
        if self.registry is None:
            raise RuntimeError("this RunContext has no registry to build components from")
        return self.registry.build(kind, spec, context=self, **given)
