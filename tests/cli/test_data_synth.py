import json

import torch

from occplug.cli import main
from occplug.data.synthetic import SyntheticDataModule, read_frame


def test_data_synth_writes_frames_equal_to_generated(tmp_path, capsys):
    out = tmp_path / "synth"
    assert main(["data", "synth", "--preset", "tiny", "--splits", "val", "--out", str(out)]) == 0
    assert "wrote 2 frames" in capsys.readouterr().out
    files = sorted(out.rglob("*.pt"))
    assert len(files) == 2 and json.loads((out / "meta.json").read_text())
    written = read_frame(files[0])
    generated = SyntheticDataModule(preset="tiny", cache=False).dataset("val")[0]
    assert written.token == generated.token
    for name in ("images", "voxel_labels", "mask_camera", "points", "boxes", "intrinsics", "cam_to_ego"):
        assert torch.equal(getattr(written, name), getattr(generated, name)), name


def test_data_synth_refuses_bad_input(tmp_path, capsys):
    assert main(["data", "synth", "--preset", "tinyy", "--out", str(tmp_path / "a")]) == 2
    assert "unknown synthetic world preset 'tinyy'" in capsys.readouterr().err
    assert main(["data", "synth", "--preset", "tiny", "--out", str(tmp_path / "b"), "num_camras=3"]) == 2
    assert "did you mean 'num_cameras'?" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
