"""Training in phases: label fractions, teacher pseudo labels, freezing, init_from, run layout and resume."""

from __future__ import annotations

import json
import re
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch

from occplug.config import ConfigError
from occplug.config.phases import InitFrom, merge_overlay, phase_specs
from occplug.data.formats import FormatError
from occplug.data.label_fraction import LabelCut, labelled_indices
from occplug.data.synthetic.dataset import SyntheticDataset
from occplug.data.teacher_labels import DONE, META, TeacherPseudoLabels, write_teacher_file
from occplug.geometry import GridSpec
from occplug.run import runner
from occplug.run.phases import fit_phases, freeze, init_from

ROOT = Path(__file__).resolve().parents[1]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
SEMI = str(ROOT / "configs" / "semi" / "baseline_10pct.yaml")
#: The tiny world (6 training frames), a few steps per phase.
TINY = [
    "data.preset=tiny",
    "data.num_workers=0",
    "trainer.accelerator=cpu",
    "trainer.deterministic=true",
    "trainer.enable_progress_bar=false",
    "trainer.limit_val_batches=1",
]


# ----------------------------------------------------------------------------- label fractions
@pytest.mark.parametrize(
    ("n", "fraction", "expected"),
    [
        (10, 0.3, [0, 3, 6]),  # k = 3: floor(j * 10 / 3)
        (7, 0.5, [0, 1, 3, 5]),  # k = ceil(3.5) = 4: 0, 7/4, 14/4, 21/4
        (30, 0.1, [0, 10, 20]),  # 0.1 * 30 is 3.0000000000000004 in floating point: still k = 3
        (5, 1.0, [0, 1, 2, 3, 4]),
        (4, 0.01, [0]),  # at least one labelled frame
        (0, 0.5, []),
    ],
)
def test_interval_sampling_known_values(n, fraction, expected):
    assert labelled_indices(n, fraction) == expected


def test_label_cut_subsets_partition_the_split():
    cut = LabelCut(0.25, "labelled")
    assert cut.selected(12) == [0, 4, 8]
    assert LabelCut(0.25, "unlabelled").selected(12) == [1, 2, 3, 5, 6, 7, 9, 10, 11]
    assert LabelCut(0.25, "all").selected(12) == list(range(12))
    assert cut.unlabelled(12) == frozenset(range(12)) - {0, 4, 8}
    for bad in (0.0, -0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="data.label_fraction"):
            LabelCut(bad)
    with pytest.raises(ValueError, match="data.subset"):
        LabelCut(0.5, "some")
    with pytest.raises(ValueError, match="selects no frame"):
        LabelCut(1.0, "unlabelled")


def _datamodule(*overrides):
    cfg = runner.load_config([BASELINE], [*TINY, *overrides])
    dm, _ = runner.build_run(cfg)
    return dm


def test_unlabelled_frames_carry_no_voxel_labels_and_subsets_select():
    dm = _datamodule("data.label_fraction=0.5")
    train = dm.dataset("train")
    n = len(train)
    hidden = LabelCut(0.5).unlabelled(n)
    assert 0 < len(hidden) < n
    for i in range(n):
        frame = train[i]
        if i in hidden:
            assert not frame.has_voxel_labels and bool((frame.voxel_labels == 255).all())
        else:
            assert frame.has_voxel_labels and not bool((frame.voxel_labels == 255).all())
    assert len(_datamodule("data.label_fraction=0.5", "data.subset=labelled").dataset("train")) == n - len(hidden)
    unl = _datamodule("data.label_fraction=0.5", "data.subset=unlabelled").dataset("train")
    assert len(unl) == len(hidden) and not any(unl[i].has_voxel_labels for i in range(len(unl)))
    assert all(dm.dataset("val")[i].has_voxel_labels for i in range(2))  # evaluation splits are never cut


def test_label_fraction_values_are_checked(capsys):
    from occplug.cli import main

    assert main(["config", "validate", "-c", BASELINE, "data.label_fraction=0"]) == 2
    assert "data.label_fraction: expected an int in (0, 1], got int 0" in capsys.readouterr().err


# ----------------------------------------------------------------------------- teacher pseudo labels
def _teacher_folder(tmp_path, shape=(2, 2, 1), classes=("a", "b", "free")):
    folder = tmp_path / "labels"
    folder.mkdir()
    (folder / META).write_text(json.dumps({"grid": list(shape), "class_names": list(classes)}))
    (folder / DONE).write_text("")
    return folder


def _frame(token, labels=None, has=True):
    from occplug.data.frame import Frame

    eye = torch.eye(4)
    return Frame(
        images=torch.zeros(1, 3, 4, 4),
        intrinsics=torch.eye(3)[None],
        cam_to_ego=eye[None],
        img_aug=torch.eye(3)[None],
        ego_to_global=eye.double(),
        timestamp=0.0,
        scene="s",
        frame_index=0,
        token=token,
        voxel_labels=labels,
        has_voxel_labels=has,
    )


def test_confidence_filter_keeps_exactly_the_voxels_at_or_above_tau(tmp_path):
    folder = _teacher_folder(tmp_path)
    labels = np.array([0, 1, 2, 1], dtype=np.uint8).reshape(2, 2, 1)
    confidence = np.array([0.25, 0.5, 0.75, 0.4990234375], dtype=np.float16).reshape(2, 2, 1)
    write_teacher_file(folder, "t0", labels, confidence)
    source = TeacherPseudoLabels(
        str(folder), confidence_threshold=0.5, grid=None, class_names=("a", "b", "free"), ignore_label=255
    )
    out = source.attach(_frame("t0", torch.full((2, 2, 1), 7, dtype=torch.uint8), has=False))
    assert out.has_voxel_labels
    assert out.voxel_labels.flatten().tolist() == [255, 1, 2, 255]
    real = torch.zeros(2, 2, 1, dtype=torch.uint8)
    assert torch.equal(source.attach(_frame("t0", real.clone(), has=True)).voxel_labels, real)  # real labels win


def test_teacher_files_from_another_grid_or_taxonomy_are_one_line_errors(tmp_path):
    folder = _teacher_folder(tmp_path)
    grid = GridSpec.from_config({"range": [0, 0, 0, 2, 2, 1], "voxel_size": 1.0})
    with pytest.raises(FormatError, match="not the data's"):
        TeacherPseudoLabels(str(folder), class_names=("a", "b", "c", "free"), grid=grid, ignore_label=255)
    other = GridSpec.from_config({"range": [0, 0, 0, 4, 2, 1], "voxel_size": 1.0})
    with pytest.raises(FormatError, match=r"on grid \[2, 2, 1\], the data's is \[4, 2, 1\]"):
        TeacherPseudoLabels(str(folder), grid=other, ignore_label=255)
    np.savez(folder / "bad.npz", labels=np.zeros((3, 2, 1), np.uint8), confidence=np.zeros((3, 2, 1), np.float16))
    source = TeacherPseudoLabels(str(folder), grid=grid, ignore_label=255)
    with pytest.raises(FormatError, match=r"bad.npz: 'labels' is uint8 \(3, 2, 1\), expected uint8 \(2, 2, 1\)"):
        source.attach(_frame("bad", has=False))
    with pytest.raises(FormatError, match="no teacher pseudo labels for frame missing"):
        source.attach(_frame("missing", has=False))
    (folder / DONE).unlink()
    with pytest.raises(FormatError, match="no DONE marker"):
        TeacherPseudoLabels(str(folder), grid=grid, ignore_label=255)


# ----------------------------------------------------------------------------- the config
def test_overlay_merges_mappings_replaces_values_and_removes_tilde_keys():
    base = {"model": {"supervision": {"a": {"weight": 1.0}, "b": {"weight": 2.0}}}, "trainer": {"max_epochs": 3}}
    out = merge_overlay(
        base, {"model": {"supervision": {"~b": None, "a": {"weight": 0.5}}}, "trainer": {"max_epochs": 9}}
    )
    assert out == {"model": {"supervision": {"a": {"weight": 0.5}}}, "trainer": {"max_epochs": 9}}
    assert base["model"]["supervision"]["b"] == {"weight": 2.0}  # the base is untouched
    with pytest.raises(ConfigError, match=r"x\.~c: nothing named 'c' to remove"):
        merge_overlay(base, {"~c": None}, "x.")


def test_phase_specs_resolve_each_phase_and_name_mistakes():
    cfg = runner.load_config([SEMI], TINY)
    specs = phase_specs(cfg)
    assert [s.name for s in specs] == ["teacher", "student", "finetune"]
    teacher, student, finetune = specs
    assert teacher.config["data"]["subset"] == "labelled" and teacher.config["data"]["label_fraction"] == 0.1
    assert "phases" not in teacher.config
    assert student.init_from == (InitFrom("teacher", ("model",)),)
    assert student.pseudo_labels_from.confidence_threshold == 0.7
    assert finetune.freeze == ("model.encoder", "model.view_transform")
    bad = [
        (
            "phases.student.init_from=[{phase: finetune}]",
            "phases.student.init_from[0].phase: 'finetune' is not an earlier phase",
        ),
        (
            "phases.student.pseudo_labels_from.head=nohead",
            "phases.student.pseudo_labels_from.head: phase 'teacher' has no head 'nohead'",
        ),
        (
            "phases.student.pseudo_labels_from.confidence_threshold=1.5",
            "confidence_threshold: expected a number in [0, 1]",
        ),
        ("phases.finetune.freeze=[encoder]", "prefix 'encoder' must start with 'model'"),
        ("phases.teacher.trainer.max_epochs=-5", "phases.teacher: trainer.max_epochs: expected an int >= -1"),
        (
            "phases.teacher.model.encoder.out_channels=0",
            "phases.teacher: model.encoder.out_channels: expected an int > 0",
        ),
        ("data.label_fraction=1.0", "phases.student.pseudo_labels_from: the phase's data has no unlabelled frames"),
        (
            "phases.fintune.trainer.max_epochs=1",
            "override 'phases.fintune.trainer.max_epochs=1': the config has no phase 'fintune' "
            "(its phases: teacher, student, finetune)",
        ),
    ]
    for override, message in bad:
        with pytest.raises(ConfigError, match=re.escape(message)):
            runner.load_config([SEMI], [*TINY, override])


def test_config_show_prints_each_phase(capsys):
    from occplug.cli import main

    assert main(["config", "show", "-c", SEMI]) == 0
    out = capsys.readouterr().out
    assert "# phase 1/3: teacher" in out and "# phase 3/3: finetune" in out
    assert "subset: labelled" in out


# ----------------------------------------------------------------------------- freeze and init_from
def _model(seed, *overrides):
    torch.manual_seed(seed)
    cfg = runner.load_config([BASELINE], [*TINY, *overrides])
    return runner.build_run(cfg)[1]


def test_init_from_loads_exactly_the_prefixes_later_entries_winning(tmp_path):
    a, b, target = _model(1), _model(2), _model(3)
    for name, model in (("a", a), ("b", b)):
        ckpt = tmp_path / name / "checkpoints" / "last.ckpt"
        ckpt.parent.mkdir(parents=True)
        torch.save({"state_dict": model.state_dict()}, ckpt)
    before = {k: v.clone() for k, v in target.state_dict().items()}
    init_from(target, [InitFrom("a", ("model.encoder", "model.scene")), InitFrom("b", ("model.scene",))], tmp_path, "x")
    got = target.state_dict()
    for key, value in got.items():
        source = a if key.startswith("encoder.") else b if key.startswith("scene.") else None
        expected = before[key] if source is None else source.state_dict()[key]
        assert torch.equal(value, expected), key
    with pytest.raises(runner.RunError, match="'model.nothing' names nothing"):
        init_from(target, [InitFrom("a", ("model.nothing",))], tmp_path, "x")


def test_freeze_stops_gradients_and_refuses_freezing_everything():
    model = _model(0)
    frozen = freeze(model, ["model.encoder"], "phases.p.freeze")
    assert "encoder" in frozen
    assert all(not p.requires_grad for n, p in model.named_parameters() if n.startswith("encoder."))
    assert any(p.requires_grad for n, p in model.named_parameters() if not n.startswith("encoder."))
    with pytest.raises(runner.RunError, match="'model.encodr' names no parameter"):
        freeze(_model(0), ["model.encodr"], "phases.p.freeze")
    with pytest.raises(runner.RunError, match="every parameter is frozen"):
        freeze(_model(0), ["model"], "phases.p.freeze")


# ----------------------------------------------------------------------------- whole runs
SMALL = [
    *TINY,
    "data.label_fraction=0.5",
    "phases.teacher.trainer.max_epochs=2",
    "phases.student.trainer.max_epochs=1",
    "phases.finetune.trainer.max_epochs=1",
    "phases.student.pseudo_labels_from.confidence_threshold=0.3",
]


def _state(path: Path) -> dict[str, torch.Tensor]:
    return torch.load(path, map_location="cpu", weights_only=True)["state_dict"]


def test_three_phase_run_layout_freezing_and_pseudo_labels(tmp_path):
    cfg = runner.load_config([SEMI], SMALL)
    run = tmp_path / "run"

    class Seen(L.Callback):  # a caller's callback joins every phase's trainer
        folders: list[str] = []

        def on_fit_start(self, trainer, pl_module) -> None:
            self.folders.append(Path(trainer.default_root_dir).name)

    results = fit_phases(cfg, run, callbacks=[Seen()])
    assert "mIoU" in results
    assert Seen.folders == ["teacher", "student", "finetune"]
    for phase in ("teacher", "student", "finetune"):
        assert (run / phase / "DONE").is_file() and (run / phase / "checkpoints" / "last.ckpt").is_file()
    summary = json.loads((run / "metrics.json").read_text())
    assert list(summary["phases"]) == ["teacher", "student", "finetune"] and summary["final_phase"] == "finetune"
    assert (
        summary["phases"]["teacher"]["label_fraction"] == 0.5 and summary["phases"]["teacher"]["subset"] == "labelled"
    )
    assert summary["mIoU"] == summary["phases"]["finetune"]["mIoU"]
    # the teacher labelled exactly the unlabelled training frames
    n = len(SyntheticDataset(runner.build_run(phase_specs(cfg)[0].config)[0].world_config, "train"))
    folder = run / "pseudo_labels" / "teacher.occupancy.unlabelled"
    assert len(list(folder.glob("*.npz"))) == len(LabelCut(0.5).unlabelled(n))
    assert json.loads((folder / META).read_text())["frames"] == len(LabelCut(0.5).unlabelled(n))
    # finetune: encoder and view transform (parameters and BatchNorm buffers) bit-for-bit the student's
    student, finetune = (
        _state(run / "student" / "checkpoints" / "last.ckpt"),
        _state(run / "finetune" / "checkpoints" / "last.ckpt"),
    )
    frozen = [k for k in finetune if k.startswith(("encoder.", "view_transform."))]
    assert any("running_mean" in k for k in frozen)
    for key in frozen:
        assert torch.equal(student[key], finetune[key]), key
    assert any(not torch.equal(student[k], finetune[k]) for k in finetune if k.startswith("heads."))
    # the student started from the teacher (init_from), so its checkpoint differs from a fresh model's start
    ckpt = torch.load(run / "finetune" / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert ckpt["occplug"]["labels"] == {"label_fraction": 0.5, "subset": "labelled"}


def test_a_streaming_teacher_labels_each_frame_as_a_stream_does(tmp_path):
    """A stateful teacher runs every training frame in order, so each unlabelled frame is predicted with its history."""
    from occplug.run.phases import write_teacher_labels
    from occplug.streams import set_stream_stage

    recipe = tmp_path / "stream_10pct.yaml"
    recipe.write_text(
        f"base: [{BASELINE}]\n"
        "data: {label_fraction: 0.5, sequential: true}\n"
        "model: {scene: {type: dense_voxels_history}}\n"
        "phases:\n"
        "  teacher: {trainer: {max_steps: 1}}\n"
        "  student: {pseudo_labels_from: {phase: teacher, head: occupancy, subset: unlabelled}}\n"
    )
    teacher, student = phase_specs(runner.load_config([str(recipe)], TINY))
    torch.manual_seed(0)
    dm, model = runner.build_run(teacher.config)
    (tmp_path / "run" / "teacher" / "checkpoints").mkdir(parents=True)
    torch.save({"state_dict": model.state_dict()}, tmp_path / "run" / "teacher" / "checkpoints" / "last.ckpt")
    folder = write_teacher_labels(teacher, student, student.pseudo_labels_from, tmp_path / "run")
    data = dm.dataset("train")  # every frame, in order: the stream the teacher ran
    model.eval()
    set_stream_stage(model, "predict")
    streamed, alone = {}, {}
    with torch.no_grad():
        for i in range(len(data)):
            batch = dm.collate([data[i]])
            streamed[batch.token[0]] = model.head_logits(batch, "occupancy").softmax(1).max(1)
            batch.is_sequence_start[:] = True  # the same frame with its stream cut
            alone[batch.token[0]] = model.head_logits(batch, "occupancy").softmax(1).max(1)
    unlabelled = {data[i].token for i in LabelCut(0.5).unlabelled(len(data))}
    assert {p.stem for p in folder.glob("*.npz")} == unlabelled and 0 < len(unlabelled) < len(data)
    differs = 0
    for token in unlabelled:
        saved = np.load(folder / f"{token}.npz")
        confidence, labels = streamed[token]
        assert np.array_equal(saved["labels"], labels[0].numpy().astype(np.uint8))
        np.testing.assert_allclose(saved["confidence"], confidence[0].numpy(), rtol=1e-3)
        differs += not torch.equal(confidence, alone[token][0])
    assert differs  # the history reached the pseudo labels


def test_unlabelled_voxel_labels_never_reach_a_loss(tmp_path, monkeypatch):
    """Corrupting the unlabelled training frames' voxel labels leaves a label-fraction run bit-identical."""
    overrides = [*TINY, "data.label_fraction=0.5", "trainer.max_steps=4"]
    clean = runner.fit(runner.load_config([BASELINE], overrides), tmp_path / "clean")
    original = SyntheticDataset.frame

    def corrupted(self, scene, frame_index):
        frame = original(self, scene, frame_index)
        index = scene * self.frames_per_scene + frame_index
        if self.split == "train" and index in LabelCut(0.5).unlabelled(len(self)):
            frame.voxel_labels = torch.randint_like(frame.voxel_labels, 0, 18)
        return frame

    monkeypatch.setattr(SyntheticDataset, "frame", corrupted)
    dirty = runner.fit(runner.load_config([BASELINE], overrides), tmp_path / "dirty")
    assert json.dumps(clean, sort_keys=True) == json.dumps(dirty, sort_keys=True)  # NaN for absent classes
    a, b = (
        _state(tmp_path / "clean" / "checkpoints" / "last.ckpt"),
        _state(tmp_path / "dirty" / "checkpoints" / "last.ckpt"),
    )
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_a_phased_run_killed_mid_phase_resumes_that_phase_bit_identical(tmp_path, capsys):
    """SIGKILL inside the student phase, ``fit --resume``: the finished teacher is not repeated, the student
    continues from its last checkpoint, and the run ends as an uninterrupted one (run beside it) does."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from occplug.cli import main

    killed, whole = tmp_path / "killed", tmp_path / "whole"
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    cmd = [sys.executable, "-c", "import sys; from occplug.cli import main; sys.exit(main())", "fit", "-c", SEMI]
    args = [*SMALL, "trainer.checkpoint_every_n_steps=1"]
    quiet = {"env": env, "stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    proc = subprocess.Popen([*cmd, *args, "--run-dir", str(killed)], **quiet)
    reference = subprocess.Popen([*cmd, *args, "--run-dir", str(whole)], **quiet)
    first = killed / "student" / "checkpoints" / "last.ckpt"
    try:
        deadline = time.monotonic() + 400
        while not first.exists():
            assert proc.poll() is None, "the run ended before the student's first checkpoint"
            assert time.monotonic() < deadline, "no student checkpoint after 400 s"
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait() == -signal.SIGKILL
        assert (killed / "teacher" / "DONE").is_file() and not (killed / "student" / "DONE").exists()
        assert main(["fit", "--resume", str(killed)]) == 0
        capsys.readouterr()
        assert reference.wait(timeout=600) == 0
    finally:
        for p in (proc, reference):
            if p.poll() is None:
                p.kill()
                p.wait()
    assert not (killed / "teacher" / "logs" / "version_1").exists()  # the finished phase did not run again
    assert (killed / "student" / "logs" / "version_1").is_dir()  # the student resumed beside its first log
    for phase in ("student", "finetune"):
        a = _state(killed / phase / "checkpoints" / "last.ckpt")
        b = _state(whole / phase / "checkpoints" / "last.ckpt")
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in b), phase
    assert json.loads((killed / "metrics.json").read_text()) == json.loads((whole / "metrics.json").read_text())
