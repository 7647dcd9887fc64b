"""A training callback that logs the BEV panel of fixed validation samples (kind ``callback``).

Switch it on in a config::

    callbacks:
      bev_panels: {type: bev_panel_logger, samples: [0, 1], every_n_epochs: 1}

At the end of every ``every_n_epochs``-th validation epoch (sanity checks excluded; rank zero
only) it predicts the listed validation samples and draws truth | prediction | error map
(:func:`occplug.viz.panels.bev_figure`). Each picture goes to every active logger: through its
image API when it has one (TensorBoard's ``experiment.add_image``, ``log_image`` of W&B-style
loggers, an MLflow run artifact ``bev/epoch_XXX_sample_Y.png``), otherwise as
``<logger.log_dir>/bev/epoch_XXX_sample_Y.png`` (CSVLogger, always on in ``occplug fit``). Name
``trainer.loggers: [csv, tensorboard]`` to see the pictures in TensorBoard.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import lightning as L
from lightning.pytorch.callbacks import Callback

from occplug.constraints import Positive

from .deps import require_matplotlib

__all__ = ["BevPanelLogger"]


class BevPanelLogger(Callback):
    """Logs the BEV panel (truth, prediction, error map) of fixed validation samples.

    Args:
        samples: indices into the validation data set.
        every_n_epochs: log at epochs ``0, n, 2n, ...``.
        dpi: resolution of the pictures.
    """

    def __init__(
        self,
        samples: list[int] | None = None,
        every_n_epochs: Annotated[int, Positive] = 1,
        dpi: Annotated[int, Positive] = 80,
    ) -> None:
        super().__init__()
        require_matplotlib("the bev_panel_logger callback")
        if every_n_epochs < 1:
            raise ValueError(f"callbacks: bev_panel_logger every_n_epochs must be >= 1, got {every_n_epochs}")
        self.samples = list(samples) if samples is not None else [0]
        if any(not isinstance(i, int) for i in self.samples):
            raise ValueError(f"callbacks: bev_panel_logger samples must be integers, got {self.samples}")
        self.every_n_epochs = every_n_epochs
        self.dpi = dpi
        self.written: list[Path] = []

    # ------------------------------------------------------------------ hooks
    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.sanity_checking or not trainer.is_global_zero:
            return
        epoch = trainer.current_epoch
        if epoch % self.every_n_epochs:
            return
        predict = getattr(pl_module, "predict_occupancy", None)
        dataset = self._dataset(trainer)
        if predict is None or dataset is None:
            return
        from occplug.data.frame import collate_frames

        from .panels import bev_figure, figure_to_rgb

        palette = self._palette(trainer, pl_module)
        grid = getattr(pl_module, "grid", None) or trainer.datamodule.grid  # type: ignore[attr-defined]
        was_training = pl_module.training
        pl_module.eval()
        try:
            for index in self.samples:
                if not -len(dataset) <= index < len(dataset):
                    continue
                frame = dataset[index]
                pred = predict(collate_frames([frame]).to(pl_module.device))[0].cpu()
                valid = None if frame.voxel_invalid is None else ~frame.voxel_invalid
                fig = bev_figure(
                    frame.voxel_labels,
                    pred,
                    palette,
                    grid,
                    mask=frame.mask_camera,
                    valid=valid,
                    title=f"epoch {epoch}, validation sample {index} ({frame.token})",
                    dpi=self.dpi,
                )
                self._log(trainer, fig, figure_to_rgb, epoch, index)
        finally:
            pl_module.train(was_training)

    # ------------------------------------------------------------------ helpers
    @staticmethod
    def _dataset(trainer: L.Trainer) -> Any:
        dm = getattr(trainer, "datamodule", None)
        if dm is not None and hasattr(dm, "dataset"):
            return dm.dataset("val")
        loaders = trainer.val_dataloaders
        loader = loaders[0] if isinstance(loaders, (list, tuple)) and loaders else loaders
        return getattr(loader, "dataset", None)

    @staticmethod
    def _palette(trainer: L.Trainer, pl_module: L.LightningModule) -> Any:
        """The data module's palette, else one from the model's class names and labels."""
        from .style import Palette

        dm = getattr(trainer, "datamodule", None)
        if dm is not None and getattr(dm, "class_names", None):
            return Palette.from_datamodule(dm)
        names = list(getattr(pl_module, "class_names", None) or []) or [f"class_{i}" for i in range(18)]
        hparams = getattr(pl_module, "hparams", {}) or {}
        return Palette.for_classes(names, getattr(pl_module, "free_label", 17), hparams.get("ignore_label", 255))

    def _log(self, trainer: L.Trainer, fig: Any, to_rgb: Any, epoch: int, index: int) -> None:
        from .panels import save_png

        tag = f"bev/sample_{index}"
        name = f"epoch_{epoch:03d}_sample_{index}.png"
        loggers = list(trainer.loggers)
        rgb = None
        for logger in loggers:
            experiment = getattr(logger, "experiment", None)
            if hasattr(experiment, "add_image"):  # TensorBoard's SummaryWriter: an image under the tag, per step
                rgb = to_rgb(fig) if rgb is None else rgb
                experiment.add_image(tag, rgb, global_step=trainer.global_step, dataformats="HWC")
            elif hasattr(logger, "log_image"):  # Weights & Biases and friends
                rgb = to_rgb(fig) if rgb is None else rgb
                logger.log_image(key=tag, images=[rgb], step=trainer.global_step)
            elif hasattr(experiment, "log_image") and getattr(logger, "run_id", None):  # MLflow: a run artifact
                rgb = to_rgb(fig) if rgb is None else rgb
                experiment.log_image(logger.run_id, rgb, artifact_file=f"bev/{name}")
            else:  # CSVLogger and loggers without images: PNG files beside the logs
                root = Path(getattr(logger, "log_dir", None) or trainer.default_root_dir)
                self.written.append(save_png(fig, root / "bev" / name))
        if not loggers:
            self.written.append(save_png(fig, Path(trainer.default_root_dir) / "bev" / name))
