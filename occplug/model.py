"""The model base class: a LightningModule composed from registered components."""

from __future__ import annotations

import dataclasses
import sys
import warnings
from typing import Annotated, Any

import torch
from torch import Tensor, nn

from occplug import interfaces as I
from occplug.constraints import NonNegative
from occplug.context import RunContext
from occplug.data.frame import Batch
from occplug.geometry import GridSpec, relative_pose
from occplug.interfaces.encoder import feature_levels
from occplug.interfaces.model import OccupancyModel
from occplug.metrics.base import EvalMask
from occplug.optim import EffectiveBatch, batch_notice, build_optimizer, build_scheduler, scaled_lr
from occplug.queries import check_query_support, registered_types
from occplug.slots import Slot

__all__ = ["OccModel", "frame_in_current_ego", "head_order"]


def head_order(heads: dict[str, Any], where: str = "model.heads") -> list[str]:
    """Head names in an order where each head comes after every head it ``reads``.

    At each step the earliest head in config order whose read heads have run comes next, so
    heads that read nothing keep their config order.

    Raises:
        ValueError: a head reads a name that is no head, or the reads form a cycle (one line
            naming the config key).
    """
    reads = {name: tuple(getattr(head, "reads", ()) or ()) for name, head in heads.items()}
    for name, wanted in reads.items():
        for other in wanted:
            if other not in heads:
                raise ValueError(f"{where}.{name}.reads: no head named '{other}'; heads are: {', '.join(heads)}")
            if other == name:
                raise ValueError(f"{where}.{name}.reads: a head cannot read its own outputs")
    order: list[str] = []
    done: set[str] = set()
    while len(order) < len(heads):
        ready = [n for n in heads if n not in done and all(o in done for o in reads[n])]
        if not ready:
            stuck = [n for n in heads if n not in done]
            raise ValueError(f"{where}: heads {', '.join(stuck)} read each other in a cycle")
        order.append(ready[0])
        done.add(ready[0])
    return order


def _call(component: nn.Module, outputs: I.ModelOutputs, *args: Any) -> Any:
    """``component(*args)``, plus the outputs so far where the component reads them."""
    if getattr(component, "reads_outputs", False) or getattr(component, "reads", ()):
        return component(*args, outputs)
    return component(*args)


def frame_in_current_ego(batch: Batch, offset: int) -> Batch:
    """Adjacent frame ``offset`` of ``batch`` with its sensors expressed in the current frame's ego frame.

    ``cam_to_ego`` and ``lidar_to_ego`` become ``T @ pose`` with ``T = relative_pose(past ego_to_global, current
    ego_to_global)`` (past ego -> current ego, computed in float64), and ``ego_to_global`` the current frame's, so
    a view transform or point encoder puts that frame's observations where they lie in the current ego frame (a
    static world lands on the same voxels).

    Raises:
        ValueError: the frame is not loaded (one line naming ``data.adjacent_offsets``).
    """
    past = batch.adjacent.get(offset)
    if past is None:
        raise ValueError(
            f"model.input_history: frame offset {offset} is not loaded; set data.adjacent_offsets to include it "
            f"(loaded: {sorted(batch.adjacent) or 'none'})"
        )
    to_current = relative_pose(past.ego_to_global.to(torch.float64), batch.ego_to_global.to(torch.float64))
    moved: dict[str, Any] = {
        "cam_to_ego": (to_current[:, None] @ past.cam_to_ego.to(torch.float64)).to(past.cam_to_ego.dtype),
        "ego_to_global": batch.ego_to_global,
    }
    if past.lidar_to_ego is not None:
        moved["lidar_to_ego"] = (to_current @ past.lidar_to_ego.to(torch.float64)).to(past.lidar_to_ego.dtype)
    return dataclasses.replace(past, **moved)


class OccModel(OccupancyModel):
    """Encoders -> view transform -> scene -> heads, trained by the summed supervision losses.

    The flow of one forward pass (:class:`~occplug.interfaces.ModelOutputs` collects it):

    1. the image ``encoder`` (one level or several) and every named ``point_encoders`` entry;
    2. the ``view_transform`` lifts the image encoder's primary level;
    3. the ``scene`` builds the representation;
    4. the ``heads`` run in an order where each comes after the heads it ``reads``.

    A view transform, scene or head that declares ``reads_outputs`` (or a head with ``reads``)
    also receives the outputs so far, so a LiDAR branch, multi-scale image features or another
    head's predictions reach it without a custom model. Training, evaluation, prediction,
    metrics and checkpoints are this class's (and the runner's): a method composes components
    instead of overriding steps.

    Args:
        encoder: the image ``encoder`` node.
        view_transform: the ``view_transform`` node (``in_channels``/``image_stride`` default to
            the encoder's primary level; ``level_channels``/``level_strides`` where it takes them).
        scene: the ``scene`` node (``in_channels`` defaults to the view transform's, ``level_channels`` to the
            encoder's where it takes them).
        heads: named ``head`` nodes; a ``null`` entry is switched off. A head that declares ``scene_downsample``
            (in its ``given``) receives the scene's ``downsample`` attribute (1 where the scene has none).
        point_encoders: named ``point_encoder`` nodes (a LiDAR branch); ``grid`` defaults to the
            evaluation grid; a ``null`` entry is switched off.
        supervision: named ``supervision`` nodes; each returns losses scaled by its ``weight``. A source that
            declares ``scene_downsample`` receives it as a head does.
        grid: the evaluation grid (filled from the config's top-level ``grid``), kept as a hyper-parameter; the
            model evaluates on the run context's grid, the same one.
        class_names: names of the label ids (filled from the run context; none given: the context's).
        free_label: id of empty space (filled from the data module).
        ignore_label: id ignored by losses and metrics (filled from the data module).
        occupancy_head: which head answers :meth:`predict_occupancy`.
        optimizer: the config's ``optimizer`` node.
        scheduler: the config's ``scheduler`` node.
        metrics: the config's ``metrics`` list (registered names or nodes); each is given, besides the grid and
            the classes, ``mask = eval_mask`` when it takes one and its node leaves it out.
        input_history: frame offsets (e.g. ``[-1]``) of past frames whose cameras and LiDAR the model also
            encodes -- encoder, point encoders and view transform, with their sensors moved into the current ego
            frame (:func:`frame_in_current_ego`) -- into ``outputs.history[offset]``, for a scene that fuses
            frames; each must be loaded (``data.adjacent_offsets``). Empty: the current frame only.
        eval_mask: the run's evaluation mask (filled by the runner from the top-level ``eval_mask``), given to the
            metrics that take a ``mask``; None: each metric's own default.
        context: the run context (handed in by the builder); every component is built through it
            (:meth:`~occplug.context.RunContext.build`), so a component that declares a ``context`` receives it.
    """

    def __init__(
        self,
        encoder: Annotated[dict, Slot("encoder")],
        view_transform: Annotated[dict, Slot("view_transform")],
        scene: Annotated[dict, Slot("scene")],
        heads: Annotated[dict, Slot("head", mapping=True)],
        supervision: Annotated[dict, Slot("supervision", mapping=True)],
        grid: GridSpec | dict,
        class_names: list[str] | None = None,
        free_label: Annotated[int, NonNegative] = 17,
        ignore_label: int | None = 255,
        occupancy_head: str = "occupancy",
        optimizer: dict | None = None,
        scheduler: dict | None = None,
        metrics: list | None = None,
        point_encoders: Annotated[dict, Slot("point_encoder", mapping=True)] | None = None,
        input_history: list[int] | None = None,
        eval_mask: EvalMask | None = None,
        context: RunContext | None = None,
    ) -> None:
        super().__init__()
        history = [int(k) for k in (input_history or [])]
        if 0 in history or len(set(history)) != len(history):
            raise ValueError(
                f"model.input_history: frame offsets other than 0, each once, got {list(input_history or [])}"
            )
        self.input_history = history
        if context is None or context.registry is None:
            raise ValueError("occ_model is built by the registry with a run context (RunContext.build), not called")
        self.grid = context.grid
        if isinstance(grid, GridSpec):  # hyper-parameters stay plain data (weights_only checkpoint loading)
            grid = grid.to_dict()
        self.save_hyperparameters(ignore=["context"])
        self.context = context
        build = context.build
        # the run's grid, one GridSpec: the one route by which it reaches every component that takes a `grid`
        run_grid = self.grid
        self.class_names = list(class_names) if class_names else list(context.class_names)
        if not self.class_names:
            raise ValueError("model.class_names: the run has no class names (its data module declares none)")
        self.num_classes = len(self.class_names)
        self.free_label = free_label
        self.eval_mask = eval_mask
        self.occupancy_head = occupancy_head
        self.encoder = build("encoder", encoder)
        self.point_encoders = nn.ModuleDict(
            {
                name: build("point_encoder", spec, grid=run_grid)
                for name, spec in (point_encoders or {}).items()
                if spec is not None
            }
        )
        self.view_transform = build(
            "view_transform",
            view_transform,
            in_channels=self.encoder.out_channels,
            image_stride=self.encoder.stride,
            level_channels=list(self.encoder.level_channels),
            level_strides=list(self.encoder.level_strides),
            grid=run_grid,
        )
        self.scene = build(
            "scene",
            scene,
            in_channels=self.view_transform.out_channels,
            level_channels=list(self.encoder.level_channels),
            grid=run_grid,
            num_classes=self.num_classes,
            point_channels={name: int(enc.out_channels) for name, enc in self.point_encoders.items()},
            **({"class_names": tuple(self.class_names)} if self.class_names else {}),
        )
        self.heads = nn.ModuleDict(
            {
                name: build(
                    "head",
                    spec,
                    in_channels=self.scene.out_channels,
                    num_classes=self.num_classes,
                    free_label=free_label,
                    grid=run_grid,
                    image_channels=self.encoder.out_channels,
                    # the scene's declared downsampling of the run grid (1 where it declares none), for a head
                    # that upsamples back to the grid and must not be told the factor a second time
                    scene_downsample=int(getattr(self.scene, "downsample", 1)),
                )
                for name, spec in heads.items()
                if spec is not None
            }
        )
        self.head_order = head_order(dict(self.heads))
        if occupancy_head not in self.heads or not isinstance(self.heads[occupancy_head], I.OccupancyHead):
            raise ValueError(
                f"model.heads.{occupancy_head}: the model evaluates through an occupancy head named "
                f"'{occupancy_head}'; heads are: {', '.join(self.heads) or '(none)'}"
            )
        self.supervision = nn.ModuleDict(
            {
                name: build(
                    "supervision",
                    spec,
                    free_label=free_label,
                    ignore_label=ignore_label,
                    grid=run_grid,
                    num_classes=self.num_classes,
                    in_channels=self.scene.out_channels,
                    scene_downsample=int(getattr(self.scene, "downsample", 1)),  # as the heads get it
                )
                for name, spec in supervision.items()
                if spec is not None
            }
        )
        # a queried head must answer (occplug/queries.py); the message names both by their type:
        check_query_support(
            self.heads, self.supervision, registered_types({"heads": heads, "supervision": supervision})
        )
        self.val_metrics = self._build_metrics(metrics, ignore_label)
        self.test_metrics = self._build_metrics(metrics, ignore_label)
        self.last_results: dict[str, dict[str, float]] = {}
        self.last_tables: dict[str, str] = {}
        #: samples per optimizer step and the learning rate used (set when training starts).
        self.effective_batch: EffectiveBatch | None = None
        self.effective_lr: float | None = None

    def training_masks(self) -> dict[str, str]:
        """``{supervision name: its training_mask}`` (``none``, ``camera``, ``lidar``, ...)."""
        return {name: str(getattr(source, "training_mask", "none")) for name, source in self.supervision.items()}

    def _build_metrics(self, specs: list | None, ignore_label: int | None) -> nn.ModuleDict:
        out = nn.ModuleDict()
        for spec in specs or []:
            node = {"type": spec} if isinstance(spec, str) else dict(spec)
            name = node["type"]
            key = name if name not in out else f"{name}_{len(out)}"
            out[key] = self.context.build(
                "metric",
                node,
                num_classes=self.num_classes,
                class_names=self.class_names or None,
                free_label=self.free_label,
                ignore_label=ignore_label,
                grid=self.grid,
                **({} if self.eval_mask is None else {"mask": self.eval_mask}),
            )
        return out

    # ---------------------------------------------------------------- forward
    def forward(self, batch: Batch) -> I.ModelOutputs:
        """Run every component on ``batch``; see :class:`~occplug.interfaces.ModelOutputs`."""

        # ``query`` reads the scene from a holder filled once the scene exists, not from ``outputs``: a closure over
        # ``outputs`` (which holds ``query``) is a reference cycle, and every step's outputs (features, scene, logits)
        # would then wait for Python's rare full garbage collection (several GB of a long CPU run's memory)
        built: dict[str, I.Scene] = {}

        def query(head_name: str, points: Tensor, times: Tensor | None = None) -> I.QueryResult:
            if "scene" not in built:
                raise RuntimeError("ModelOutputs.query was called before the model built its scene")
            return self.heads[head_name].query(built["scene"], points, times)

        outputs = I.ModelOutputs(image_features=None, lifted=None, scene=None, heads={}, query=query)
        for offset in self.input_history:
            past = I.ModelOutputs(image_features=None, lifted=None, scene=None, heads={}, query=query)
            self._encode(frame_in_current_ego(batch, offset), past)
            outputs.history[offset] = past
        self._encode(batch, outputs)
        outputs.scene = built["scene"] = _call(self.scene, outputs, outputs.lifted, batch)
        for name in self.head_order:
            outputs.heads[name] = _call(self.heads[name], outputs, outputs.scene, batch)
        return outputs

    def _encode(self, batch: Batch, outputs: I.ModelOutputs) -> None:
        """Encoders, point encoders and view transform on one frame, into ``outputs``."""
        levels = feature_levels(self.encoder(batch.images))
        outputs.image_levels = levels
        outputs.image_features = levels[self.encoder.primary_level]
        for name, point_encoder in self.point_encoders.items():
            outputs.encoded[name] = point_encoder(batch)
        outputs.lifted = _call(self.view_transform, outputs, outputs.image_features, batch)

    def occupancy_from(self, outputs: I.ModelOutputs) -> Tensor:
        """``(B, X, Y, Z)`` int64 class ids on the evaluation grid from a forward pass's outputs
        (the occupancy head's :meth:`logits_on_grid`)."""
        return self.logits_on_grid(outputs, self.occupancy_head).argmax(dim=1)

    def logits_on_grid(self, outputs: I.ModelOutputs, head_name: str) -> Tensor:
        """``(B, K, X, Y, Z)`` logits of head ``head_name`` on the evaluation grid from a forward pass's outputs.

        A head's forward ``logits`` live on the scene's grid: where that is the evaluation grid they
        are used as they are (no second pass, and a head that reads other heads is evaluated exactly as
        it trained); otherwise an occupancy head answers ``occupancy_logits`` at the evaluation grid's
        voxel centres.
        """
        if head_name not in self.heads:
            raise ValueError(f"model.heads has no head '{head_name}' (heads: {', '.join(self.heads)})")
        head = self.heads[head_name]
        logits = outputs.heads[head_name].get("logits")
        if (
            logits is not None
            and getattr(outputs.scene, "grid", None) == self.grid
            and tuple(logits.shape[2:]) == self.grid.shape
        ):
            return logits
        if getattr(head, "reads", ()) or getattr(head, "reads_outputs", False) or not isinstance(head, I.OccupancyHead):
            raise ValueError(
                f"model.heads.{head_name} is evaluated from its forward logits, which must lie on the evaluation grid "
                f"{self.grid.shape}; got {tuple(logits.shape[2:]) if logits is not None else 'none'}"
            )
        return head.occupancy_logits(outputs.scene, self.grid)

    @torch.no_grad()
    def head_logits(self, batch: Batch, head: str) -> Tensor:
        """``(B, K, X, Y, Z)`` logits of head ``head`` on the evaluation grid (teacher pseudo labels read this)."""
        return self.logits_on_grid(self(batch), head)

    @torch.no_grad()
    def predict_occupancy(self, batch: Batch) -> Tensor:
        """``(B, X, Y, Z)`` int64 class ids on the evaluation grid; every metric uses this."""
        return self.occupancy_from(self(batch))

    def loss_weights(self) -> dict[str, float]:
        """``{supervision name: weight}``."""
        return {name: float(source.weight) for name, source in self.supervision.items()}

    def dry_run(self, batch: Batch) -> None:
        """Forward, every loss and the evaluation path on ``batch`` (the runner's first-batch check)."""
        outputs = self(batch)
        self.losses(batch, outputs)
        self.occupancy_from(outputs)

    def losses(self, batch: Batch, outputs: I.ModelOutputs) -> dict[str, Tensor]:
        """Weighted losses named ``<supervision name>/<term>``."""
        out: dict[str, Tensor] = {}
        for name, source in self.supervision.items():
            for term, value in source(batch, outputs).items():
                out[f"{name}/{term}"] = value * source.weight
        return out

    # ---------------------------------------------------------------- steps
    def on_train_start(self) -> None:
        if self.effective_batch is not None and self.logger is not None:
            self.logger.log_metrics(
                {
                    "train/effective_batch": float(self.effective_batch.total),
                    "train/effective_lr": float(self.effective_lr or 0.0),
                },
                step=self.global_step,
            )

    def training_step(self, batch: Batch, batch_idx: int) -> Tensor:
        outputs = self(batch)
        losses = self.losses(batch, outputs)
        if not losses:
            raise ValueError("model.supervision is empty: nothing to train on")
        loss = torch.stack(list(losses.values())).sum()
        bs = len(batch)
        self.log("train/loss", loss, prog_bar=True, batch_size=bs)
        for name, value in losses.items():
            self.log(f"train/{name}", value, batch_size=bs)
        return loss

    def _eval_step(self, batch: Batch, stage: str, metrics: nn.ModuleDict) -> None:
        outputs = self(batch)
        losses = self.losses(batch, outputs) if self.supervision else {}
        if losses:
            self.log(f"{stage}/loss", torch.stack(list(losses.values())).sum(), batch_size=len(batch), sync_dist=True)
        pred = self.occupancy_from(outputs)
        for metric in metrics.values():
            metric.update(pred, batch)

    def _eval_epoch_end(self, stage: str, metrics: nn.ModuleDict) -> None:
        computed = {name: metric.compute() for name, metric in metrics.items()}  # torchmetrics syncs ranks here
        keys = [key for values in computed.values() for key in values]
        shared = {key for key in keys if keys.count(key) > 1}  # e.g. mIoU of occ3d_miou and of ssc
        results: dict[str, float] = {}
        for name, values in computed.items():
            for key, value in values.items():
                key = f"{name}/{key}" if key in shared else key
                with warnings.catch_warnings():  # Lightning's "use sync_dist=True" hint: the value is already synced
                    warnings.filterwarnings("ignore", message=".*sync_dist=True.*")
                    self.log(f"{stage}/{key}", value, sync_dist=False, prog_bar=key in ("mIoU", "RayIoU"))
                results[key] = float(value)
            self.last_tables[name] = metrics[name].table()
            metrics[name].reset()
        self.last_results[stage] = results

    def validation_step(self, batch: Batch, batch_idx: int) -> None:
        self._eval_step(batch, "val", self.val_metrics)

    def on_validation_epoch_end(self) -> None:
        self._eval_epoch_end("val", self.val_metrics)

    def test_step(self, batch: Batch, batch_idx: int) -> None:
        self._eval_step(batch, "test", self.test_metrics)

    def on_test_epoch_end(self) -> None:
        self._eval_epoch_end("test", self.test_metrics)

    # ---------------------------------------------------------------- optimisation
    def _effective_batch(self) -> EffectiveBatch | None:
        trainer = self._trainer
        per_device = getattr(getattr(trainer, "datamodule", None), "batch_size", None)
        if trainer is None or per_device is None:
            return None
        return EffectiveBatch(int(trainer.world_size), int(per_device), int(trainer.accumulate_grad_batches))

    def configure_optimizers(self) -> Any:
        spec = self.hparams.get("optimizer")
        self.effective_batch = self._effective_batch()
        self.effective_lr = scaled_lr(spec, self.effective_batch)
        if self.effective_batch is not None and self.trainer.is_global_zero:
            notice = batch_notice(spec, self.effective_batch)
            if notice:
                print(notice, file=sys.stderr)
        optimizer = build_optimizer(self, spec, self.effective_batch)  # trainable parameters only (frozen phases)
        total = int(self.trainer.estimated_stepping_batches) if self.trainer is not None else 1
        scheduler = build_scheduler(optimizer, self.hparams.get("scheduler"), max(total, 1))
        if scheduler is None:
            return optimizer
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}
