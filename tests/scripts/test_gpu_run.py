"""scripts/gpu_run.py's dry run on a CPU: every stage once at tiny sizes, the install planned, one JSON."""

from __future__ import annotations

import json
import math


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def test_the_dry_run_writes_every_stage_into_one_json(script, tmp_path):
    gpu_run = script("gpu_run")
    wheels = tmp_path / "wheels"
    wheels.mkdir()
    (wheels / "mamba_ssm-2.2.4-cp311-cp311-linux_x86_64.whl").write_bytes(b"")  # planned, never installed
    out = tmp_path / "out"
    assert gpu_run.main(["--dry-run", "--wheels", str(wheels), "--out", str(out), "--repeats", "1"]) == 0
    result = json.loads((out / "gpu_run.json").read_text())
    assert result["schema"] == gpu_run.SCHEMA_VERSION and result["dry_run"] is True
    assert tuple(result["stages"]) == gpu_run.STAGES
    assert all(_number(stage["seconds"]) for stage in result["stages"].values())
    assert _number(result["seconds"]) and result["within_budget"] is True

    install = result["stages"]["install"]
    assert install["status"] == "dry-run"
    assert [c.split(" -m pip install --no-index --find-links ")[1] for c in install["commands"]] == [
        f"{wheels} -e {gpu_run.ROOT}[timm,duocc]",
        f"{wheels} mamba-ssm",
    ]
    env = result["stages"]["environment"]
    assert env["status"] == "ok" and env["device"] == "cpu" and env["torch"].startswith("2.")

    fast = result["stages"]["fast_paths"]
    assert fast["status"] == "ok"
    splat, scan = fast["splat"], fast["selective_scan"]
    assert all(_number(splat[k]) for k in ("fast_ms", "reference_ms", "speedup", "scale"))
    assert splat["scale"] > 0 and splat["max_abs_diff"] <= 1e-5 * splat["scale"]
    assert splat["max_abs_grad_diff"] <= 1e-4
    assert _number(scan["ref_ms"]) and _number(scan["chunked_ms"])
    assert scan["chunked_max_abs_diff"] <= 1e-4 * max(1.0, scan["scale"])
    assert "auto_ms" not in scan  # mamba-ssm's kernel is CUDA only

    (row,) = result["stages"]["precision"]["recipes"].values()
    assert 0.9 <= row["class_agreement"] <= 1.0 and 0 <= row["max_rel_logit_diff"] < 0.1
    assert _number(row["fp32_ms"]) and _number(row["bf16_ms"]) and row["voxels"] > 0

    real = result["stages"]["real_size"]
    assert real["status"] == "ok"
    assert set(real["composed"]) == {
        "baseline/occ3d_nuscenes",
        "queryocc/occ3d_nuscenes",
        "duocc/occ3d_nuscenes",
        "duocc/occ3d_nuscenes_rayiou",
        "occle/semantickitti",
    }
    (step,) = real["rows"]
    assert step["recipe"] == "baseline/synthetic-tiny" and step["batch"] == 1
    assert _number(step["step_s"]) and _number(step["val_s"]) and step["peak_bytes"] > 2**20
    assert real["papers"]["duocc/occ3d_nuscenes"] == {"latency_ms": 83.3, "memory_mb": 2788, "image_size": [256, 704]}
