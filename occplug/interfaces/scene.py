"""Kind ``scene``: the scene representation a head reads and a supervision source can query."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from occplug.data.frame import Batch
from occplug.geometry import GridSpec, sample_volume

from .checks import CHECK_CHANNELS, assert_finite, assert_gradient, eval_twice
from .view_transform import Lifted

__all__ = ["BevScene", "DenseVoxelScene", "Scene", "SceneRepresentation"]


class Scene(ABC):
    """A scene's features at one time step, queryable at continuous points.

    Attributes:
        features: the representation's main tensor (``(B, C, X, Y, Z)`` for dense voxels).
        grid: the grid ``features`` is defined on.
        channels: ``C``, feature size returned by :meth:`sample`.
    """

    features: Tensor
    grid: GridSpec
    channels: int

    @property
    def batch_size(self) -> int:
        """``B``: samples in this scene (``features``' first dimension unless a subclass says otherwise)."""
        return int(self.features.shape[0])

    @property
    def device(self) -> torch.device:
        """Where the scene's tensors live (query points are made there)."""
        return self.features.device

    @abstractmethod
    def sample(self, points: Tensor) -> Tensor:
        """Features at continuous ego-frame points.

        Args:
            points: ``(B, P, 3)`` ego-frame points of this time step, metres.

        Returns:
            ``(B, P, C)`` features (zero or the representation's "outside" value beyond its range).
        """


class DenseVoxelScene(Scene):
    """A dense feature volume, read trilinearly at continuous points.

    Attributes:
        features: ``(B, C, X, Y, Z)`` features on ``grid`` (voxel ``[i, j, k]``'s value at its centre).
        grid: the grid of ``features``, ego frame.
        channels: ``C``.
    """

    def __init__(self, features: Tensor, grid: GridSpec) -> None:
        if features.dim() != 5 or tuple(features.shape[2:]) != grid.shape:
            raise ValueError(f"DenseVoxelScene: features {tuple(features.shape)} do not match grid shape {grid.shape}")
        self.features = features
        self.grid = grid
        self.channels = int(features.shape[1])

    def sample(self, points: Tensor) -> Tensor:
        """``(B, P, C)`` trilinear reads at ``(B, P, 3)`` ego-frame points; zero outside the grid.

        Exactly the voxel's feature at a voxel centre (:func:`occplug.geometry.sample_volume`).
        """
        return sample_volume(self.features, self.grid, points)


class BevScene(Scene):
    """A bird's-eye-view feature plane, read bilinearly in x and y at continuous points (z is not resolved).

    On a contracted grid the plane covers the unbounded scene: far points read its border band
    (:func:`occplug.geometry.sample_volume` contracts them first). A head that needs height decodes it
    from the query point itself (e.g. an MLP over the sampled feature and ``z``).

    Attributes:
        features: ``(B, C, X, Y)`` features on ``grid``'s x-y cells (cell ``[i, j]``'s value at its centre).
        grid: the grid of ``features`` (its z range is what the plane was pooled over), ego frame.
        channels: ``C``.
    """

    def __init__(self, features: Tensor, grid: GridSpec) -> None:
        if features.dim() != 4 or tuple(features.shape[2:]) != grid.shape[:2]:
            raise ValueError(
                f"BevScene: features {tuple(features.shape)} do not match the grid's x-y shape {grid.shape[:2]}"
            )
        self.features = features
        self.grid = grid
        self.channels = int(features.shape[1])

    def sample(self, points: Tensor) -> Tensor:
        """``(B, P, C)`` bilinear reads at ``(B, P, 3)`` ego-frame points (z ignored); zero outside a metric grid."""
        return sample_volume(self.features, self.grid, points)


class SceneRepresentation(nn.Module, ABC):
    """Builds a :class:`Scene` from lifted features (and may hold state across a stream).

    Contract:
        given: ``in_channels`` (the view transform's ``out_channels`` when the config leaves it out) and, to a
        representation that takes them, ``level_channels`` (the image encoder's levels' channels, finest first:
        a scene that reads ``outputs.image_levels`` builds its layers for them) and ``point_channels``
        (``{point encoder name: its out_channels}``: the widths of ``outputs.encoded``).
        declares: ``out_channels``; ``reads_outputs = True`` to be called as
        ``forward(lifted, batch, outputs)`` with the model's outputs so far (e.g. a scene fusing
        the camera volume with a point encoder's volume from ``outputs.encoded``).
        conformance: :meth:`conformance_inputs` gives a dense ``(B, C, X, Y, Z)`` volume; a
        representation that needs another input (a BEV plane) overrides it.

    A stateful representation resets its state where ``batch.is_sequence_start`` is True.

    .. versionadded:: 0.1
    """

    #: Constructor arguments the model fills in when the config leaves them out.
    given: ClassVar[tuple[str, ...]] = ("in_channels", "level_channels", "grid", "num_classes", "point_channels")
    #: Whether ``forward`` takes a third argument, the :class:`~occplug.interfaces.ModelOutputs` so far.
    reads_outputs: ClassVar[bool] = False
    #: Whether it carries state from frame to frame (a :class:`~occplug.streams.StreamState`); a stateful model
    #: needs ``data.sequential``.
    stateful: ClassVar[bool] = False

    #: Optional :class:`~occplug.data.Frame` fields this component reads (e.g. ``{"points"}``):
    #: data modules skip loading what no component requires (a camera-only model opens no LiDAR file).
    requires: frozenset[str] = frozenset()

    out_channels: int

    @abstractmethod
    def forward(self, lifted: Lifted, batch: Batch) -> Scene:
        """Build the scene for ``batch``."""

    @classmethod
    def check_conformance(cls, component: SceneRepresentation, batch: Batch, grid: GridSpec) -> None:
        """The kind's contract, checked: a :class:`Scene` whose ``sample`` gives ``(B, P, channels)``,
        deterministic in eval, finite, with gradients.

        :func:`occplug.testing.check_component` runs it on every registered component of this kind.
        """
        rep = component
        inputs = type(rep).conformance_inputs(batch, grid, CHECK_CHANNELS)
        first, second = eval_twice(rep, lambda m: m(*inputs).features)
        assert torch.equal(first, second), "scene is not deterministic in eval mode"
        scene = rep(*inputs)
        assert isinstance(scene, Scene), "a scene representation returns a Scene"
        points = grid.centers()[::3, ::3, ::2].reshape(1, -1, 3).expand(len(batch), -1, -1)
        out = scene.sample(points)
        assert out.shape == (len(batch), points.shape[1], scene.channels), f"sample shape {tuple(out.shape)}"
        assert_finite(out, "scene sample")
        out.square().mean().backward()
        assert_gradient(rep, "scene")

    @classmethod
    def conformance_inputs(cls, batch: Batch, grid: GridSpec, channels: int) -> tuple[Any, ...]:
        """Positional ``forward`` inputs for the conformance check: a random dense volume on ``grid``
        wrapped as :class:`Lifted`, and the batch."""
        gen = torch.Generator().manual_seed(0)
        volume = torch.randn(len(batch), channels, *grid.shape, generator=gen)
        return (Lifted(volume=volume, grid=grid), batch)
