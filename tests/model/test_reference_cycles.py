"""A training step leaves no reference cycle: its outputs are freed when the last reference goes, not at Python's
rare full garbage collection (a cycle per step held several GB of a long CPU run's memory)."""

from __future__ import annotations

import dataclasses
import gc
import weakref

import pytest
import torch

from occplug.run import runner


@pytest.fixture
def no_gc():
    gc.collect()
    gc.disable()
    try:
        yield
    finally:
        gc.enable()


def test_model_outputs_are_freed_by_reference_counting_and_query_keeps_only_the_scene(no_gc):
    cfg = runner.load_config(["configs/baseline.yaml", "occplug/trainer/debug"], [])
    dm, model = runner.build_run(cfg)
    data = dm.dataset("train")
    batch = dm.collate([data[0]])
    outputs = model(batch)
    points = torch.zeros(1, 4, 3)
    head = next(name for name, h in model.heads.items() if getattr(h, "queryable", False))
    answer = outputs.query(head, points)
    query, released, scene = outputs.query, weakref.ref(outputs), weakref.ref(outputs.scene)
    loss = torch.stack(list(model.losses(batch, outputs).values())).sum()
    loss.backward()
    del outputs, loss
    assert released() is None  # freed without the garbage collector
    assert scene() is not None  # the query holds the scene it answers from, and answers the same
    torch.testing.assert_close(query(head, points).features, answer.features, rtol=0, atol=0)
    del query
    assert scene() is None


def test_moving_a_batch_makes_no_garbage(no_gc):
    cfg = runner.load_config(["configs/baseline.yaml", "occplug/trainer/debug"], [])
    dm = runner.build_datamodule(cfg)
    data = dm.dataset("train")
    batch = dm.collate([data[0], data[1]])
    gc.collect()  # what building the data left
    moved = batch.to("cpu")
    del moved
    assert gc.collect() == 0


def test_pin_memory_reaches_every_tensor_of_a_batch(monkeypatch):
    """``Batch.pin_memory`` applies ``Tensor.pin_memory`` to every tensor, in lists and dicts too (pinning itself
    needs an accelerator, so a stand-in marks what it touched)."""
    cfg = runner.load_config(["configs/baseline.yaml", "occplug/trainer/debug"], [])
    dm = runner.build_datamodule(cfg)
    data = dm.dataset("train")
    batch = dm.collate([data[0], data[1]])
    touched = []
    monkeypatch.setattr(torch.Tensor, "pin_memory", lambda t: touched.append(t) or t.clone())
    pinned = batch.pin_memory()

    def tensors(v):
        if torch.is_tensor(v):
            return [v]
        if isinstance(v, (list, tuple)):
            return [t for x in v for t in tensors(x)]
        if isinstance(v, dict):
            return [t for x in v.values() for t in tensors(x)]
        return []

    before = [t for f in dataclasses.fields(batch) for t in tensors(getattr(batch, f.name))]
    after = [t for f in dataclasses.fields(pinned) for t in tensors(getattr(pinned, f.name))]
    assert len(touched) == len(before) == len(after) > 5
    assert all(a is not b and torch.equal(a, b) for a, b in zip(after, before, strict=True))


@pytest.mark.parametrize(
    ("recipe", "overrides"),
    [
        ("duocc/full", ["grid.range=[-8.0,-8.0,-1.0,8.0,8.0,5.4]", "model.encoder.out_channels=16"]),
        ("occle/base", ["grid.range=[0.0,-6.4,-1.0,12.8,6.4,5.4]", "model.scene.mamba_channels=[16,24]"]),
        ("queryocc/base", []),
    ],
)
def test_a_method_training_step_leaves_no_garbage(no_gc, recipe, overrides):
    """Each method plugin's model (its scene, heads, losses and stream state) frees a step's outputs by reference
    counting, and the step leaves nothing for the garbage collector."""
    cfg = runner.load_config([recipe, "occplug/trainer/debug"], ["data.preset=tiny", *overrides])
    dm, model = runner.build_run(cfg)
    data = dm.dataset("train")
    batch = dm.collate([data[0], data[1]])
    model.train()
    gc.collect()  # what building the model and the data left
    outputs = model(batch)
    released = weakref.ref(outputs)
    loss = torch.stack(list(model.losses(batch, outputs).values())).sum()
    loss.backward()
    del outputs, loss
    assert released() is None
    assert gc.collect() == 0
