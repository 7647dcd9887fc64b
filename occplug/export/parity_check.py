"""The parity check: the eager model against an exported one on the same frames, and on perturbed ones.

:func:`perturb` (the frames seen by another rig), :func:`parity` (frame by frame) and :func:`stream_parity` (a
streaming model: the frames in order, the exported state fed back), and the report they return: within the
thresholds or not (:func:`passes`), as the one line ``occplug export`` prints (:func:`one_line`), and where it is
written beside the artefact (:func:`report_path`).
"""

from __future__ import annotations

import dataclasses
import math
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from occplug.data.frame import Batch
from occplug.interfaces.model import OccupancyModel
from occplug.streams import StreamState, set_stream_stage, tree_leaves

from .graph import (
    STREAM_INPUTS,
    _graph,
    _stream_holders,
    graph_inputs,
    inputs_of,
    is_streaming,
    occupancy_logits,
    stream_inputs,
)


def perturb(batch: Batch, seed: int) -> Batch:
    """``batch`` seen by another rig: perturbed intrinsics and extrinsics, and an image augmentation.

    Focal lengths scale by up to +-8 %, the principal point moves by up to 4 % of the image size,
    every camera (and the LiDAR, where the batch has one) turns by up to 2 degrees of yaw and moves by up to
    0.2 m, and the images are
    flipped left-right and rescaled about the centre by up to 10 %, recorded in ``img_aug`` (the
    flip mirrors the image tensor too, so image and calibration stay consistent).
    """
    g = torch.Generator().manual_seed(int(seed))
    b, n, _, h, w = batch.images.shape

    def u(*shape: int) -> Tensor:
        return torch.rand(*shape, generator=g) * 2 - 1

    k = batch.intrinsics.clone().float()
    k[..., 0, 0] *= 1 + 0.08 * u(b, n)
    k[..., 1, 1] *= 1 + 0.08 * u(b, n)
    k[..., 0, 2] += 0.04 * w * u(b, n)
    k[..., 1, 2] += 0.04 * h * u(b, n)
    def turn(*shape: int) -> Tensor:  # (*shape, 4, 4): up to 2 degrees of yaw and 0.2 m
        yaw = math.radians(2.0) * u(*shape)
        out = torch.eye(4).repeat(*shape, 1, 1)
        out[..., 0, 0], out[..., 0, 1] = torch.cos(yaw), -torch.sin(yaw)
        out[..., 1, 0], out[..., 1, 1] = torch.sin(yaw), torch.cos(yaw)
        out[..., :3, 3] = 0.2 * u(*shape, 3)
        return out

    cam_to_ego = turn(b, n) @ batch.cam_to_ego.float()
    scale = 1 + 0.1 * u(b, n)
    aug = torch.eye(3).repeat(b, n, 1, 1)  # pixel u -> (w - 1) - u, then scale about the image centre
    aug[..., 0, 0], aug[..., 0, 2] = -scale, (w - 1) / 2 * (1 + scale)
    aug[..., 1, 1], aug[..., 1, 2] = scale, (h - 1) / 2 * (1 - scale)
    img_aug = aug @ batch.img_aug.float()
    lidar = {}
    if batch.lidar_to_ego is not None:  # the LiDAR turns and moves like a camera
        lidar["lidar_to_ego"] = turn(b).to(batch.lidar_to_ego.dtype) @ batch.lidar_to_ego
    return dataclasses.replace(
        batch, images=batch.images.flip(-1).contiguous(), intrinsics=k, cam_to_ego=cam_to_ego, img_aug=img_aug,
        **lidar,
    )


def report_path(out: Path) -> Path:
    """Where the parity report of artefact ``out`` goes: ``<out>.parity.json`` beside it."""
    out = Path(out)
    return out.with_name(out.name + ".parity.json")


def _report(
    fmt: str, frames: int, perturbed: int, voxels: int, max_diff: float, agree: int, eager_ms: list, exported_ms: list
) -> dict[str, Any]:
    """The parity report's common entries (see :func:`parity`)."""
    return {
        "format": fmt,
        "frames": frames,
        "frames_perturbed": perturbed,
        "voxels": voxels,
        "max_abs_logit_diff": max_diff,
        "class_agreement": agree / max(voxels, 1),
        "eager_latency_ms": statistics.median(eager_ms),
        "exported_latency_ms": statistics.median(exported_ms),
        "versions": _versions(fmt),
    }


def _versions(fmt: str) -> dict[str, str | None]:
    out: dict[str, str | None] = {"torch": torch.__version__}
    if fmt == "onnx":
        for name in ("onnx", "onnxruntime", "onnxscript"):
            try:
                out[name] = __import__(name).__version__
            except ImportError:
                out[name] = None
    return out


def parity(
    model: OccupancyModel,
    exported: Callable[..., tuple[Tensor, Tensor]],
    batches: Sequence[Batch],
    fmt: str,
    repeats: int = 3,
) -> dict[str, Any]:
    """Compare the eager model with an exported one on ``batches`` (each also :func:`perturb`-ed).

    The eager side is the model as it runs in ``validate``/``predict`` (fast splat with cached
    plans); the exported side gets the same tensors. Latencies are the median over frames of the
    best of ``repeats`` calls (the first call of each side is a warm-up), milliseconds per call.

    Returns:
        ``{"format", "frames", "frames_perturbed", "voxels", "max_abs_logit_diff", "class_agreement"
        (share of voxels whose class ids agree, in [0, 1]), "eager_latency_ms", "exported_latency_ms",
        "versions"}``; a streaming model's (:func:`stream_parity`) also ``"stream"``.
    """
    if is_streaming(model):
        return stream_parity(model, exported, batches, fmt, repeats)
    model.eval()
    names = graph_inputs(model)
    frames = [f for i, batch in enumerate(batches) for f in (batch, perturb(batch, seed=i))]
    max_diff, agree, voxels = 0.0, 0, 0
    eager_ms: list[float] = []
    exported_ms: list[float] = []
    with torch.no_grad():
        for batch in frames[:1]:  # warm-up (first calls allocate, build plans)
            model.predict_occupancy(batch)
            exported(*inputs_of(batch, names))
        for batch in frames:
            args = inputs_of(batch, names)
            eager_t, got_t = [], []
            for _ in range(max(1, repeats)):
                t0 = time.perf_counter()
                outputs = model(batch)
                eager_ids = model.occupancy_from(outputs) if hasattr(model, "occupancy_from") else None
                eager_logits = occupancy_logits(model, outputs)
                t1 = time.perf_counter()
                ids, logits = exported(*args)
                t2 = time.perf_counter()
                eager_t.append(t1 - t0)
                got_t.append(t2 - t1)
            if eager_ids is None:
                eager_ids = eager_logits.argmax(dim=1)
            eager_ms.append(min(eager_t) * 1e3)
            exported_ms.append(min(got_t) * 1e3)
            max_diff = max(max_diff, float((logits.float() - eager_logits.float()).abs().max()))
            agree += int((ids.long() == eager_ids.long()).sum())
            voxels += int(eager_ids.numel())
    return _report(fmt, len(batches), len(frames) - len(batches), voxels, max_diff, agree, eager_ms, exported_ms)


def _eager_outputs(model: OccupancyModel, batch: Batch) -> tuple[Tensor, Tensor]:
    outputs = model(batch)
    logits = occupancy_logits(model, outputs)
    ids = model.occupancy_from(outputs) if hasattr(model, "occupancy_from") else logits.argmax(dim=1)
    return ids, logits


def _stored(states: Sequence[StreamState], stage: str) -> list[Tensor]:
    """The values ``states`` hold for ``stage``, as the graph's state tensors (slots stacked, leaves in order)."""
    out: list[Tensor] = []
    for state in states:
        store = state.state_dict().get(stage, {})
        per_slot = [tree_leaves(store[b]["value"]) for b in sorted(store)]
        out += [torch.stack(leaves) for leaves in zip(*per_slot, strict=True)]
    return out


def stream_parity(
    model: OccupancyModel,
    exported: Callable[..., tuple[Tensor, ...]],
    batches: Sequence[Batch],
    fmt: str,
    repeats: int = 3,
) -> dict[str, Any]:
    """:func:`parity` of a streaming model: ``batches`` run in order as a sequence, then again perturbed.

    The eager model keeps its state in its own :class:`~occplug.streams.StreamState` (the
    ``predict`` store, emptied before each sequence); the exported one gets the previous frame's
    state outputs back as inputs (the zero state and ``is_start`` at the first frame, see
    :func:`stream_inputs`). Every frame compares logits, classes and the new state. Each timed
    repeat of the eager step first restores the state it started from.

    Returns:
        :func:`parity`'s keys, plus ``"stream": {"states" (the state tensors' names), "sequence_starts"
        (frames fed with ``is_start``), "max_abs_state_diff"}``.
    """
    model.eval()
    states = [state for *_, state in _stream_holders(model)]
    with _graph(model, batches[0]) as graph:  # the state tensors' names and zero initial values
        names, initial = list(graph.state_names), list(graph.initial_state)
    saved = [(state.stage, state.state_dict()) for state in states]
    sequences = [list(batches), [perturb(batch, seed=i) for i, batch in enumerate(batches)]]
    max_diff, state_diff, agree, voxels, starts = 0.0, 0.0, 0, 0, 0
    eager_ms: list[float] = []
    exported_ms: list[float] = []
    inputs = graph_inputs(model)
    start_at = len(inputs) + STREAM_INPUTS.index("is_start")
    try:
        set_stream_stage(model, "predict")
        with torch.no_grad():
            _eager_outputs(model, batches[0])  # warm-up (first calls allocate, build plans)
            exported(*inputs_of(batches[0], inputs), *stream_inputs(batches[0], None), *initial)
            for sequence in sequences:
                for state in states:
                    state.clear("predict")
                carried, previous = list(initial), None
                for batch in sequence:
                    args = (*inputs_of(batch, inputs), *stream_inputs(batch, previous), *carried)
                    starts += int(args[start_at].sum())
                    before = [state.state_dict() for state in states]
                    eager_t, got_t = [], []
                    for r in range(max(1, repeats)):
                        if r:  # the same step again, from the same state
                            for state, entries in zip(states, before, strict=True):
                                state.load_state_dict(entries)
                        t0 = time.perf_counter()
                        eager_ids, eager_logits = _eager_outputs(model, batch)
                        t1 = time.perf_counter()
                        got = exported(*args)
                        t2 = time.perf_counter()
                        eager_t.append(t1 - t0)
                        got_t.append(t2 - t1)
                    eager_ms.append(min(eager_t) * 1e3)
                    exported_ms.append(min(got_t) * 1e3)
                    ids, logits, *carried = got
                    max_diff = max(max_diff, float((logits.float() - eager_logits.float()).abs().max()))
                    agree += int((ids.long() == eager_ids.long()).sum())
                    voxels += int(eager_ids.numel())
                    for mine, theirs in zip(carried, _stored(states, "predict"), strict=True):
                        state_diff = max(state_diff, float((mine.float() - theirs.float()).abs().max()))
                    previous = batch
    finally:
        for state, (stage, entries) in zip(states, saved, strict=True):
            state.load_state_dict(entries)
            state.set_stage(stage)
    report = _report(fmt, len(batches), len(batches), voxels, max_diff, agree, eager_ms, exported_ms)
    report["stream"] = {"states": names, "sequence_starts": starts, "max_abs_state_diff": state_diff}
    return report


#: What the baseline reaches (README, Export); ``occplug export`` fails a report outside them.
MIN_CLASS_AGREEMENT = 0.9999
MAX_LOGIT_DIFF = 1e-4


def passes(report: dict[str, Any]) -> bool:
    """Whether a :func:`parity` report is within :data:`MIN_CLASS_AGREEMENT` and :data:`MAX_LOGIT_DIFF`."""
    return report["class_agreement"] >= MIN_CLASS_AGREEMENT and report["max_abs_logit_diff"] <= MAX_LOGIT_DIFF


def one_line(report: dict[str, Any]) -> str:
    """The report as the one line ``occplug export`` prints."""
    versions = " ".join(f"{k}={v}" for k, v in report["versions"].items())
    stream = report.get("stream")
    order = (
        f" (in order, state fed back, {stream['sequence_starts']} stream starts, max |state diff| "
        f"{stream['max_abs_state_diff']:.3g})"
        if stream else ""
    )
    return (
        f"parity {report['format']}: {report['frames']} frames + {report['frames_perturbed']} perturbed{order}, "
        f"classes agree on {100 * report['class_agreement']:.4f} % of {report['voxels']} voxels, "
        f"max |logit diff| {report['max_abs_logit_diff']:.3g}, latency eager {report['eager_latency_ms']:.1f} ms "
        f"vs exported {report['exported_latency_ms']:.1f} ms ({versions})"
    )
