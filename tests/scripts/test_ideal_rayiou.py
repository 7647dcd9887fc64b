"""scripts/ideal_rayiou.py scores the ideal field as scripts/ceilings.py does, and adds RayIoU."""

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _script():
    spec = importlib.util.spec_from_file_location("ideal_rayiou", ROOT / "scripts" / "ideal_rayiou.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_ideal_fields_iou_equals_the_ceilings_and_rayiou_is_scored(tmp_path):
    from occplug.data.synthetic import default_cache_dir, preset
    from occplug.data.synthetic.testbed import measure

    out = tmp_path / "ideal.json"
    args = ["--preset", "tiny", "--readouts", "center", "any2", "--json", str(out)]
    assert _script().main([*args, "--results", str(tmp_path / "res"), "--seeds", "0", "1"]) == 0
    report = json.loads(out.read_text())["readouts"]
    measured = measure(
        preset("tiny"), readouts=["center", "any2"], masks=["camera"], depth_stride=None, cache_dir=default_cache_dir()
    )
    ceilings = measured["ideal"]["camera"]
    for name in ("center", "any2"):
        assert report[name]["IoU"] == pytest.approx(ceilings[name]["IoU"], abs=1e-3)
        assert 0.0 <= report[name]["RayIoU_geometry"] <= 100.0
    assert report["any2"]["RayIoU_geometry"] > report["center"]["RayIoU_geometry"]  # sub-samples see thin surfaces
    floor = measured["floor"]["camera"]["per-voxel training prior"]
    assert report["prior"]["IoU"] == pytest.approx(floor["IoU"], abs=1e-3)  # the same floor as ceilings.py's
    files = sorted(p.name for p in (tmp_path / "res").glob("*.json"))
    assert files == [f"{r}-seed{k}.json" for r in ("ideal_any2", "ideal_center", "prior_floor") for k in (0, 1)]
    record = json.loads((tmp_path / "res" / "ideal_any2-seed1.json").read_text())
    assert record["values"]["Occ.RayIoU"] == pytest.approx(report["any2"]["RayIoU_geometry"])


def test_a_bad_readout_is_one_error_line(capsys):
    assert _script().main(["--preset", "tiny", "--readouts", "all9"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and err.count("\n") == 1
