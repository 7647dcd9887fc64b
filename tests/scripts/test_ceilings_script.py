"""scripts/ceilings.py: one table of floor and ceilings, a JSON report, and one error line for bad input."""

from __future__ import annotations

import json

import pytest


def test_prints_the_table_and_writes_the_report(script, tmp_path, capsys):
    out = tmp_path / "r.json"
    args = ["--preset", "tiny", "--train-scenes", "1", "--eval-scenes", "1", "--depth-stride", "0"]
    assert (
        script("ceilings").main([*args, "--readouts", "center,any2", "--masks", "camera,none", "--json", str(out)]) == 0
    )
    printed = capsys.readouterr().out
    assert "ideal field: any2" in printed and "floor: per-voxel training prior" in printed
    assert "front_all_voxels" in printed
    report = json.loads(out.read_text())
    assert set(report["ideal"]) == {"camera", "none"} and set(report["ideal"]["camera"]) == {"center", "any2"}
    assert report["world"]["grid"] == {"range": [-16.0, -16.0, -1.0, 16.0, 16.0, 5.4], "voxel_size": [0.8, 0.8, 0.8]}


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--preset", "huge"], "unknown synthetic world preset 'huge'"),
        (["--preset", "tiny", "--set", "lidar_dropout=2"], "lidar_dropout must be in [0, 1)"),
        (["--preset", "tiny", "--set", "colour=1"], "--set"),
        (["--preset", "tiny", "--readouts", "centre"], "readout 'centre'"),
        (["--preset", "tiny", "--masks", "cam"], "unknown mask 'cam'"),
    ],
)
def test_bad_input_is_one_error_line(script, capsys, args, message):
    assert script("ceilings").main([*args, "--train-scenes", "1", "--eval-scenes", "1", "--depth-stride", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: ") and message in err[-1]
