"""The cross-method mixes (configs/mix/): what each composes, that they stream and export, and an impossible mix.

Every mix also trains on the tiny world in ``tests/test_configs.py`` (every recipe under ``configs/``, phases too).
"""

from __future__ import annotations

import json
from pathlib import Path

import lightning as L
import pytest
import torch

from occplug.cli import main
from occplug.config import phase_specs
from occplug.run import runner
from occplug.streams import set_stream_stage

ROOT = Path(__file__).resolve().parents[1]
MIX = ROOT / "configs" / "mix"
LABEL_FREE, LABEL_FREE_T0 = str(MIX / "label_free_stream.yaml"), str(MIX / "label_free_stream_t0.yaml")
THREE_PHASE, QUERIES_10PCT = str(MIX / "duocc_b_three_phase_10pct.yaml"), str(MIX / "duocc_b_10pct_queries.yaml")
#: 20 x 20 x 8 label voxels and a narrow encoder (DuOcc's tests' shrink): the tiny world, quickly
SMALL = [
    "data.preset=tiny",
    "grid.range=[-8.0,-8.0,-1.0,8.0,8.0,5.4]",
    "model.encoder.out_channels=16",
    "model.encoder.width=16",
]
VOXEL_LABEL_LOSSES = {"voxel_ce", "duocc_forecast", "duocc_occupied"}


def _built(recipe: str, *overrides: str):
    dm, model = runner.build_run(runner.load_config([recipe, "occplug/trainer/debug"], [*SMALL, *overrides]))
    return model, dm


def _batch(dm, indices, split="train"):
    data = dm.dataset(split)
    return dm.collate([data[i] for i in indices])


def _losses(model, batch) -> dict[str, torch.Tensor]:
    torch.manual_seed(0)  # the query sampler draws: the same draws for both batches
    return model.losses(batch, model(batch))


def test_label_free_stream_is_query_supervision_alone_on_the_concat_stream():
    model, dm = _built(LABEL_FREE)
    cfg = runner.load_config([LABEL_FREE])
    assert {s["type"] for s in cfg["model"]["supervision"].values() if s} == {"queryocc_query_points"}
    assert cfg["model"]["supervision"]["queries"]["frame_offsets"] == [-1, 0, 1]
    assert model.scene.stateful and model.scene.agg.fusion == "concat"
    assert type(model.heads["occupancy"]).__name__ == "QueryDecoder" and model.heads["occupancy"].temporal
    # no loss reads a voxel label: the same losses with the labels scrambled
    batch = _batch(dm, [0, 1])
    clean = _losses(model, batch)
    batch.voxel_labels = torch.randint_like(batch.voxel_labels, 0, 18)
    scrambled = _losses(model, batch)
    assert clean.keys() == scrambled.keys() and all(torch.equal(clean[k], scrambled[k]) for k in clean)
    assert all(v.item() > 0 for v in clean.values())
    # T = {0}: the same model, queries of the current frame only
    t0 = runner.load_config([LABEL_FREE_T0])
    assert t0["model"]["supervision"]["queries"].pop("frame_offsets") == [0]
    assert t0["data"].pop("adjacent_offsets") == []
    cfg["model"]["supervision"]["queries"].pop("frame_offsets")
    cfg["data"].pop("adjacent_offsets")
    assert t0 == cfg


def test_the_label_free_stream_carries_its_history_and_validates_alike_twice():
    torch.manual_seed(0)
    model, dm = _built(LABEL_FREE, "data.frames_per_scene=3", "data.batch_size=1")
    model.eval()
    set_stream_stage(model, "val")
    with torch.no_grad():
        model(_batch(dm, [0], "val"))
        streamed = model.head_logits(_batch(dm, [1], "val"), "occupancy")
        cut = _batch(dm, [1], "val")
        cut.is_sequence_start[:] = True
        alone = model.head_logits(cut, "occupancy")
    assert not torch.allclose(streamed, alone)  # frame 1 reads frame 0's V_fin
    trainer = L.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False, enable_progress_bar=False)
    results = []
    for _ in range(2):  # a stale store from the first pass must not leak into the second
        trainer.validate(model, datamodule=dm, verbose=False)
        results.append(json.dumps(model.last_results["val"], sort_keys=True))
    assert results[0] == results[1] and "RayIoU" in model.last_results["val"]


def test_queries_at_10pct_train_the_stream_on_unlabelled_frames_and_evaluate_duoccs_decoder():
    model, dm = _built(QUERIES_10PCT)
    assert type(model.heads["occupancy"]).__name__ == "DuOccDecoder"  # evaluated; `queries` is auxiliary
    assert model.supervision["queries"].query_head == "queries" and model.heads["queries"].temporal
    batch = _batch(dm, [0, 1])
    batch.has_voxel_labels[:] = False  # frames of the 90 %: only the queries train
    losses = _losses(model, batch)
    types = {name: spec["type"] for name, spec in runner.load_config([QUERIES_10PCT])["model"]["supervision"].items()}
    voxel = [k for k in losses if types[k.split("/")[0]] in VOXEL_LABEL_LOSSES]
    assert voxel and all(losses[k].item() == 0 for k in voxel)
    queries = sum(v for k, v in losses.items() if k.startswith("queries/"))
    queries.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.scene.parameters())


def test_the_three_phase_mix_starts_from_duocc_b_at_10pct_and_labels_from_its_occupancy_head():
    specs = {s.name: s for s in phase_specs(runner.load_config([THREE_PHASE]))}
    assert list(specs) == ["teacher", "student", "finetune"]
    parent = runner.load_config(["duocc/stream_agg_concat"], ["data.label_fraction=0.1"])
    teacher = specs["teacher"].config
    assert teacher["model"] == parent["model"] and teacher["data"] == parent["data"]  # the teacher is the parent row
    source = specs["student"].pseudo_labels_from
    assert (source.phase, source.head, source.subset) == ("teacher", "occupancy", "unlabelled")
    assert specs["student"].config["data"]["augment"] == "strong"
    assert list(specs["finetune"].freeze) == ["model.encoder", "model.view_transform"]
    assert all(s.config["data"].get("subset", "all") == "all" for s in specs.values())  # streams need whole scenes


def test_an_impossible_mix_is_one_line_naming_both_components(tmp_path, capsys):
    """QueryOcc's queries at t - 1 and t + 1 read by DuOcc's decoder, which answers the current frame only."""
    run = tmp_path / "run"
    code = main(["fit", "-c", LABEL_FREE, *SMALL, "model.heads.occupancy.type=duocc_decoder", "--run-dir", str(run)])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("error: model.supervision.queries (queryocc_query_points): queries at times t != 0")
    assert "model.heads.occupancy (duocc_decoder) is not temporal" in lines[0]
    assert not run.exists()


@pytest.mark.parametrize(
    "mix, fmt",
    [(LABEL_FREE, "torch_export"), (LABEL_FREE, "onnx"), (QUERIES_10PCT, "onnx")],
    ids=["label_free-torch_export", "label_free-onnx", "queries_10pct-onnx"],
)
def test_a_streaming_mix_exports_with_parity(mix, fmt, tmp_path, tmp_path_factory, capsys):
    """QueryOcc's decoder over DuOcc's stream (mix 1), and DuOcc B with QueryOcc's auxiliary decoder (mix 3): the
    stream's state an input and an output, as DuOcc B's export (its level)."""
    if fmt == "onnx":
        pytest.importorskip("onnxruntime")
    ckpt = tmp_path_factory.getbasetemp() / f"mix_{Path(mix).stem}" / "checkpoints" / "last.ckpt"
    if not ckpt.is_file():
        assert main(["fit", "-c", mix, "-c", "occplug/trainer/debug", *SMALL, "--run-dir", str(ckpt.parents[1])]) == 0
    capsys.readouterr()
    out = tmp_path / ("mix.pt2" if fmt == "torch_export" else "mix.onnx")
    assert main(["export", "--ckpt", str(ckpt), "--format", fmt, "--out", str(out), "--samples", "2"]) == 0
    report = json.loads((tmp_path / f"{out.name}.parity.json").read_text())
    assert report["passed"] and report["class_agreement"] >= 0.9999 and report["max_abs_logit_diff"] <= 1e-4
    assert "state fed back" in capsys.readouterr().out
