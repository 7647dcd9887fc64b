"""``occplug viz sample | run`` and the ``bev_panel_logger`` callback, end to end on the tiny world."""

import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

pytest.importorskip("matplotlib")

from occplug.cli import main  # noqa: E402
from occplug.data.classes import OCC3D_CLASSES  # noqa: E402
from occplug.geometry import GridSpec  # noqa: E402
from occplug.testing import run_config  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
TINY = ["data.preset=tiny", "trainer.accelerator=cpu"]
SMALL = ["--dpi", "40", "--view-size", "160x100"]  # small pictures: the tests check files, not looks


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A short tiny-world fit with the BEV callback switched on (the runner's CSVLogger)."""
    root = tmp_path_factory.mktemp("viz") / "run"
    run_config(BASELINE, run_dir=root, overrides=[*TINY, "callbacks={bev: {type: bev_panel_logger, samples: [0, 1]}}"])
    return root


def _one_line_error(capsys):
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.strip().count("\n") == 0 and "Traceback" not in err
    return err


def test_callback_writes_bev_pngs_into_the_csv_log_dir(run_dir):
    pngs = sorted((run_dir / "logs" / "version_0" / "bev").glob("epoch_*_sample_*.png"))
    assert [p.name.split("_sample_")[1] for p in pngs] == ["0.png", "1.png"]
    assert all(p.stat().st_size > 5_000 for p in pngs)


def test_callback_uses_a_logger_image_api(tmp_path):
    from occplug.viz.callback import BevPanelLogger
    from occplug.viz.panels import bev_figure, figure_to_rgb
    from occplug.viz.style import Palette

    calls = []
    tensorboard = SimpleNamespace(experiment=SimpleNamespace(add_image=lambda *a, **k: calls.append((a, k))))
    trainer = SimpleNamespace(loggers=[tensorboard], global_step=7, default_root_dir=str(tmp_path))
    grid = GridSpec((-2, -2, -1, 2, 2, 1), 0.5)
    labels = torch.full(grid.shape, 17)
    fig = bev_figure(labels, labels, Palette.for_classes(OCC3D_CLASSES, 17), grid)
    cb = BevPanelLogger(samples=[3])
    cb._log(trainer, fig, figure_to_rgb, epoch=2, index=3)
    ((args, kwargs),) = calls
    assert args[0] == "bev/sample_3" and args[1].ndim == 3 and args[1].shape[2] == 3
    assert kwargs == {"global_step": 7, "dataformats": "HWC"}
    assert not cb.written  # nothing on disk when the logger takes images


def test_viz_sample_ground_truth_on_the_synthetic_world(tmp_path, capsys):
    out = tmp_path / "pngs"
    args = ["viz", "sample", "-c", BASELINE, *TINY, "--index", "0", "1", "--out", str(out), *SMALL]
    assert main(args) == 0
    assert sorted(p.name for p in out.iterdir()) == ["val_00000.png", "val_00001.png"]
    assert "wrote" in capsys.readouterr().out


def test_viz_sample_with_checkpoint_config_and_rerun(run_dir, tmp_path, capsys):
    pytest.importorskip("rerun")
    from viz_helpers import read_rrd

    ckpt = run_dir / "checkpoints" / "last.ckpt"
    rrd = tmp_path / "seq.rrd"
    args = ["viz", "sample", "--ckpt", str(ckpt), "--index", "1", "--out", str(tmp_path), "--rerun", str(rrd), *SMALL]
    assert main(args) == 0
    assert (tmp_path / "val_00001.png").is_file()
    data = read_rrd(rrd)
    assert data["/world/ego/occupancy/pred"]["frames"] == {0, 1}  # the tiny val scene has 2 frames
    assert "scene synth-val-0000, 2 frames" in capsys.readouterr().out


def test_viz_sample_rerun_max_frames_records_a_window_of_the_scene(tmp_path, capsys):
    pytest.importorskip("rerun")
    from viz_helpers import read_rrd

    rrd = tmp_path / "seq.rrd"
    args = ["viz", "sample", "-c", BASELINE, *TINY, "--split", "train", "--index", "4", "--out", str(tmp_path)]
    assert main([*args, "--rerun", str(rrd), "--max-frames", "2", *SMALL]) == 0
    assert read_rrd(rrd)["/world/ego/lidar"]["frames"] == {1, 2}  # train item 4: frame 1 of a 3-frame scene
    assert "scene synth-train-0001, 2 frames" in capsys.readouterr().out


def test_max_frames_window():
    from occplug.cli.viz_cmd import _window

    scene = [10, 11, 12, 13, 14]
    assert _window(scene, 12, None) == scene and _window(scene, 12, 9) == scene
    assert _window(scene, 11, 2) == [11, 12]  # from the --index frame on
    assert _window(scene, 14, 3) == [12, 13, 14]  # near the end: the scene's last frames


def test_viz_run_writes_curves_and_class_iou(run_dir, tmp_path):
    assert main(["viz", "run", str(run_dir), "--out", str(tmp_path)]) == 0
    assert (tmp_path / "curves.png").is_file() and (tmp_path / "class_iou.png").is_file()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["viz", "sample", "--out", "x"], "needs -c CONFIG"),
        (["viz", "sample", "-c", BASELINE, *TINY, "--index", "99", "--out", "x"], "out of range: the val split has 2"),
        (["viz", "sample", "-c", BASELINE, *TINY, "--split", "nope", "--out", "x"], "--split nope"),
        (["viz", "sample", "-c", BASELINE, *TINY, "--out", "x", "--rerun", "x.txt"], "must end in .rrd"),
        (["viz", "sample", "-c", BASELINE, *TINY, "--out", "x", "--rerun", "x.rrd", "--max-frames", "0"], "positive"),
        (["viz", "sample", "-c", BASELINE, *TINY, "--out", "x", "--max-frames", "3"], "with --rerun"),
        (["viz", "sample", "--ckpt", "missing.ckpt", "--out", "x"], "does not exist"),
        (["viz", "sample", "-c", BASELINE, "--out", "x", "--view-size", "big"], "expected WIDTHxHEIGHT"),
        (["viz", "run", "no/such/run"], "no such run directory"),
    ],
)
def test_user_mistakes_exit_2_with_one_line(args, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(args) == 2
    assert message in _one_line_error(capsys)


def test_missing_matplotlib_names_the_extra(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    from occplug.viz.callback import BevPanelLogger
    from occplug.viz.deps import MissingExtraError

    with pytest.raises(MissingExtraError, match=r"pip install 'occplug\[viz\]'") as info:
        BevPanelLogger()
    assert isinstance(info.value, ValueError) and isinstance(info.value, ImportError)
    (tmp_path / "logs").mkdir()
    assert main(["viz", "run", str(tmp_path)]) == 2
    assert "occplug[viz]" in _one_line_error(capsys)
    args = ["fit", "-c", BASELINE, *TINY, "callbacks={bev: {type: bev_panel_logger}}", "--run-dir", str(tmp_path / "r")]
    assert main(args) == 2
    assert "bev_panel_logger callback needs matplotlib" in _one_line_error(capsys)
    assert not (tmp_path / "r").exists()
