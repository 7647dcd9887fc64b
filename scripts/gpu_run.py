#!/usr/bin/env python
"""The prepared GPU run: everything this project measures on one GPU, in one command, into one JSON.

On a machine with one CUDA GPU and no internet (budget: 8 minutes)::

    python scripts/gpu_run.py --wheels DIR [--out runs/gpu_run] [--json FILE] [--budget 480]

Stages, in order, each a key of the JSON's ``stages`` with its ``status`` (``ok``, ``error``, ``skipped`` or
``dry-run``), ``seconds`` and its numbers; the JSON is rewritten after every stage, so a run cut short keeps what
it measured:

1. ``install``: ``pip install --no-index --find-links DIR -e ".[timm,duocc]"`` (the wheels the run is handed:
   torch, torchvision, timm, Lightning and the rest of the dependencies, setuptools and wheel for the editable
   build) and, where DIR holds a ``mamba_ssm-*.whl`` (mamba-ssm ships no wheel on PyPI: build one once with
   ``pip wheel --no-build-isolation mamba-ssm`` on a CUDA machine), ``mamba-ssm`` too; then the script starts
   again in a fresh interpreter that sees what was installed. Without ``--wheels`` it uses what is installed.
2. ``environment``: torch, CUDA, the GPU, timm and mamba-ssm versions, the code's commit.
3. ``fast_paths``: the CUDA fast paths against their pure-PyTorch references on the same inputs: the splat
   (:class:`occplug.ops.FrustumSplatter` ``mode="fast"`` against ``mode="reference"``, six nuScenes-like
   cameras at 256 x 704 / 16, 64 depth bins, 64 channels, the 200 x 200 x 16 Occ3D grid; values and gradients)
   and OccLE's selective scan (``selective_scan_ref`` against the chunked scan and, where its kernel loads,
   ``mamba-ssm``'s; ``B = 2, L = 4096, D = 64, N = 16``; output, last state, gradient of ``u``). Each row: the
   largest absolute difference to the reference and the milliseconds of each (median of 5 after a warm-up).
4. ``trees``: real_size.py's minimal real-size trees from the synthetic world (Occ3D-nuScenes and SemanticKITTI
   shapes), written once under ``<out>/trees`` and reused.
5. ``precision``: bf16 autocast against float32 on one batch (``queryocc/occ3d_nuscenes`` and
   ``duocc/occ3d_nuscenes``, random weights, the real-size tree's first validation sample): the largest difference of the occupancy logits
   relative to their largest magnitude, the share of voxels whose class agrees, and the milliseconds of each.
6. ``real_size``: ``scripts/real_size.py --device cuda`` for every recipe: one training step (s), one
   validation batch (s), peak CUDA memory, inference latency at batch 1 (ms, median of 5), beside the papers'
   figures (QueryOcc: 11.6 FPS at 224 x 704; DuOcc: 83.3 ms and 2,788 MB at 256 x 704).

``--dry-run`` (CPU, tiny sizes; what CI runs) plans the install without running it, writes no tree, and runs
every other stage once, small: the splat on a 20 x 20 x 4 grid, the scan at ``L = 64``, bf16 against float32 on
the baseline recipe's tiny synthetic world, and real_size's worker for one step of that recipe; the real-size
recipes are only composed and validated.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType, SimpleNamespace
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
SCHEMA_VERSION = 1
STAGES = ("install", "environment", "fast_paths", "trees", "precision", "real_size")
#: The papers' figures the GPU table compares with (QueryOcc 11.6 FPS = 86 ms per frame).
PAPERS = {
    "queryocc/occ3d_nuscenes": {"fps": 11.6, "latency_ms": 1000.0 / 11.6, "image_size": [224, 704]},
    "duocc/occ3d_nuscenes": {"latency_ms": 83.3, "memory_mb": 2788, "image_size": [256, 704]},
}
PRECISION_RECIPES = ("queryocc/occ3d_nuscenes", "duocc/occ3d_nuscenes")


def load_script(name: str) -> ModuleType:
    """``scripts/<name>.py`` as a module (the scripts are not a package)."""
    spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name(f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    return module


def error_line(exc: BaseException) -> str:
    """``Type: first line of the message`` (at most 300 characters), for a row that failed."""
    return f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"[:300]


def timed(fn: Callable[[], Any], repeats: int, cuda: bool, warmup: bool = True) -> tuple[float, Any]:
    """Median milliseconds of ``repeats`` calls of ``fn`` after one warm-up (CUDA synchronised), its last result."""
    import torch

    out = fn() if warmup else None
    times = []
    for _ in range(repeats):
        if cuda:
            torch.cuda.synchronize()
        start = time.perf_counter()
        out = fn()
        if cuda:
            torch.cuda.synchronize()
        times.append((time.perf_counter() - start) * 1000.0)
    return statistics.median(times), out


# ---------------------------------------------------------------------- 1. install
def install_commands(wheels: Path) -> list[list[str]]:
    """The pip commands that install the project from ``wheels`` alone (no index)."""
    pip = [sys.executable, "-m", "pip", "install", "--no-index", "--find-links", str(wheels)]
    commands = [[*pip, "-e", f"{ROOT}[timm,duocc]"]]
    if any(wheels.glob("mamba_ssm-*.whl")):
        commands.append([*pip, "mamba-ssm"])
    return commands


def stage_install(args: argparse.Namespace) -> dict[str, Any]:
    if args.wheels is None:
        return {"status": "skipped", "reason": "no --wheels: the packages installed here are used"}
    wheels = Path(args.wheels)
    if not wheels.is_dir():
        raise SystemExit(f"error: --wheels: {wheels} is not a folder")
    commands = install_commands(wheels)
    shown = [" ".join(c) for c in commands]
    if args.dry_run:
        return {"status": "dry-run", "commands": shown}
    for command in commands:
        result = subprocess.run(command, capture_output=True, text=True)
        if result.returncode != 0:
            last = (result.stderr.strip().splitlines() or ["(no output)"])[-1]
            return {"status": "error", "commands": shown, "error": last[:300]}
    return {"status": "ok", "commands": shown, "mamba_ssm": len(commands) > 1}


# ---------------------------------------------------------------------- 2. environment
def stage_environment(args: argparse.Namespace) -> dict[str, Any]:
    import torch

    from occplug.run.bench import code_commit

    info: dict[str, Any] = {
        "status": "ok",
        "device": args.device,
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "cuda_available": torch.cuda.is_available(),
        "commit": code_commit(ROOT),
    }
    if torch.cuda.is_available():
        props = torch.cuda.get_device_properties(0)
        info.update(gpu=props.name, gpu_memory_mib=props.total_memory // 2**20, capability=[props.major, props.minor])
    for package in ("timm", "torchvision", "mamba_ssm"):
        try:
            info[package] = importlib.import_module(package).__version__
        except Exception as exc:  # absent, or present but not loading beside this torch
            info[package] = f"not available ({type(exc).__name__})"
    return info


# ---------------------------------------------------------------------- 3. fast paths
def ring_cameras(n: int, height: int, width: int, batch: int) -> SimpleNamespace:
    """``n`` pinhole cameras in a ring around the ego (nuScenes-like: 1.5 m up, yaw ``360 / n`` degrees apart)."""
    import math

    import torch

    f = 0.8 * width
    k = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    poses = []
    for i in range(n):
        yaw = 2 * math.pi * i / n
        forward = torch.tensor([math.cos(yaw), math.sin(yaw), 0.0])
        right = torch.tensor([math.sin(yaw), -math.cos(yaw), 0.0])
        down = torch.tensor([0.0, 0.0, -1.0])
        pose = torch.eye(4)
        pose[:3, :3] = torch.stack([right, down, forward], dim=1)  # camera axes (x right, y down, z fwd) in ego
        pose[:3, 3] = torch.tensor([0.0, 0.0, 1.5])
        poses.append(pose)
    return SimpleNamespace(
        intrinsics=k.expand(batch, n, 3, 3).clone(),
        cam_to_ego=torch.stack(poses).expand(batch, n, 4, 4).clone(),
        img_aug=torch.eye(3).expand(batch, n, 3, 3).clone(),
    )


def splat_row(args: argparse.Namespace) -> dict[str, Any]:
    import torch

    from occplug import parse_grid
    from occplug.ops import FrustumSplatter

    cuda = args.device == "cuda"
    if args.dry_run:
        size, stride, bins, channels, n = (64, 176), 16, 8, 8, 2
        grid = parse_grid({"range": [-16.0, -16.0, -1.0, 16.0, 16.0, 5.4], "voxel_size": [1.6, 1.6, 1.6]})
    else:
        size, stride, bins, channels, n = (256, 704), 16, 64, 64, 6
        grid = parse_grid({"range": [-40.0, -40.0, -1.0, 40.0, 40.0, 5.4], "voxel_size": 0.4})
    device = torch.device(args.device)
    cams = ring_cameras(n, *size, batch=1)
    cams = SimpleNamespace(**{k: v.to(device) for k, v in vars(cams).items()})
    h, w = size[0] // stride, size[1] // stride
    gen = torch.Generator().manual_seed(0)
    depth = torch.rand(1, n, bins, h, w, generator=gen).softmax(2).to(device).requires_grad_()
    context = torch.randn(1, n, channels, h, w, generator=gen).to(device).requires_grad_()
    depths = torch.linspace(1.0, 60.0, bins, device=device)
    row: dict[str, Any] = {"shape": {"cameras": n, "bins": bins, "channels": channels, "feature": [h, w],
                                     "grid": list(grid.shape)}}  # fmt: skip
    outputs = {}
    weights = torch.randn(1, channels, *grid.shape, generator=gen).to(device)  # one cotangent for both modes
    for mode in ("fast", "reference"):
        splatter = FrustumSplatter(grid, stride, mode=mode)

        def run(splatter: FrustumSplatter = splatter) -> Any:
            return splatter.splat_outer(depth, context, cams, depths)

        row[f"{mode}_ms"], volume = timed(run, args.repeats, cuda)
        grads = torch.autograd.grad((volume * weights).sum(), (depth, context))
        outputs[mode] = (volume.detach(), grads)
    fast, ref = outputs["fast"], outputs["reference"]
    row["max_abs_diff"] = float((fast[0] - ref[0]).abs().max())
    row["max_abs_grad_diff"] = max(float((a - b).abs().max()) for a, b in zip(fast[1], ref[1], strict=True))
    row["scale"] = float(ref[0].abs().max())
    row["speedup"] = row["reference_ms"] / row["fast_ms"]
    return row


def scan_row(args: argparse.Namespace) -> dict[str, Any]:
    import torch
    import torch.nn.functional as F

    from occplug_occle.blocks.selective_scan import selective_scan, selective_scan_chunked, selective_scan_ref

    cuda = args.device == "cuda"
    b, length, d, n = (2, 64, 8, 4) if args.dry_run else (2, 4096, 64, 16)
    device = torch.device(args.device)
    gen = torch.Generator().manual_seed(0)

    def rand(*shape: int) -> Any:
        return torch.randn(*shape, generator=gen).to(device)

    u, z = rand(b, length, d), rand(b, length, d)
    delta = F.softplus(rand(b, length, d) - 1.0)
    A, B, C, D = -torch.exp(rand(d, n)), rand(b, length, n), rand(b, length, n), rand(d)
    row: dict[str, Any] = {"shape": {"B": b, "L": length, "D": d, "N": n}}
    with torch.no_grad():
        row["ref_ms"], (y_ref, last_ref) = timed(
            lambda: selective_scan_ref(u, delta, A, B, C, D, z, return_last_state=True), max(1, args.repeats // 2), cuda
        )
        row["chunked_ms"], (y, last) = timed(
            lambda: selective_scan_chunked(u, delta, A, B, C, D, z, return_last_state=True), args.repeats, cuda
        )
    row["chunked_max_abs_diff"] = float(max((y - y_ref).abs().max(), (last - last_ref).abs().max()))
    mamba = importlib.util.find_spec("mamba_ssm") is not None
    row["mamba_ssm"] = "installed" if mamba else "not installed"
    if cuda and mamba:
        with torch.no_grad():
            row["auto_ms"], (y, last) = timed(
                lambda: selective_scan(u, delta, A, B, C, D, z, mode="auto", return_last_state=True), args.repeats, True
            )
        row["auto_max_abs_diff"] = float(max((y - y_ref).abs().max(), (last - last_ref).abs().max()))
        grads = []
        for mode in ("auto", "ref"):
            x = u.clone().requires_grad_()
            (g,) = torch.autograd.grad(selective_scan(x, delta, A, B, C, D, z, mode=mode).square().sum(), x)
            grads.append(g)
        row["auto_max_abs_grad_diff"] = float((grads[0] - grads[1]).abs().max())
    row["scale"] = float(y_ref.abs().max())
    return row


def stage_fast_paths(args: argparse.Namespace) -> dict[str, Any]:
    rows: dict[str, Any] = {}
    for name, fn in (("splat", splat_row), ("selective_scan", scan_row)):
        try:
            rows[name] = fn(args)
        except Exception as exc:
            rows[name] = {"error": error_line(exc)}
    errors = [name for name, row in rows.items() if "error" in row]
    return {"status": "error" if errors else "ok", **rows}


# ---------------------------------------------------------------------- 4. the real-size trees
def stage_trees(args: argparse.Namespace, real_size: ModuleType, trees: Path) -> dict[str, Any]:
    """real_size.py's two minimal real-size trees (written once under ``<out>/trees``, then reused)."""
    if args.dry_run:
        return {"status": "skipped", "reason": "dry run: the tiny synthetic world instead"}
    real_size.write_trees(trees)
    return {"status": "ok", "trees": str(trees)}


# ---------------------------------------------------------------------- 5. precision
def precision_row(refs: list[str], overrides: list[str], device: str, repeats: int) -> dict[str, Any]:
    """bf16 autocast against float32: one forward of one validation sample, random weights."""
    import torch

    from occplug.run import runner

    cfg = runner.load_config(refs, [*overrides, "data.num_workers=0", "data.batch_size=1"])
    encoder = cfg["model"].get("encoder") or {}
    if "weights" in encoder:
        encoder["weights"] = None
    torch.manual_seed(0)
    dm, model = runner.build_run(cfg)
    batch = dm.collate([dm.dataset("val")[0]]).to(device)
    model = model.to(device).eval()

    def logits(bf16: bool) -> Any:
        with torch.inference_mode(), torch.autocast(device, dtype=torch.bfloat16, enabled=bf16):
            return model.logits_on_grid(model(batch), model.occupancy_head).float()

    cuda = device == "cuda"  # bf16 autocast on a CPU takes seconds per forward: the dry run skips the warm-up
    fp32_ms, a = timed(lambda: logits(False), repeats, cuda, warmup=cuda)
    bf16_ms, b = timed(lambda: logits(True), repeats, cuda, warmup=cuda)
    return {
        "fp32_ms": fp32_ms,
        "bf16_ms": bf16_ms,
        "speedup": fp32_ms / bf16_ms,
        "class_agreement": float((a.argmax(1) == b.argmax(1)).float().mean()),
        "max_rel_logit_diff": float((a - b).abs().max() / a.abs().max().clamp_min(1e-12)),
        "voxels": a[:, 0].numel(),
    }


def stage_precision(args: argparse.Namespace, jobs: dict[str, tuple[list[str], list[str]]]) -> dict[str, Any]:
    rows: dict[str, Any] = {}
    for name, (refs, overrides) in jobs.items():
        try:
            rows[name] = precision_row(refs, overrides, args.device, args.repeats)
        except Exception as exc:
            rows[name] = {"error": error_line(exc)}
    errors = [name for name, row in rows.items() if "error" in row]
    return {"status": "error" if errors else "ok", "recipes": rows}


# ---------------------------------------------------------------------- 6. real size
def stage_real_size(args: argparse.Namespace, real_size: ModuleType, deadline: float) -> dict[str, Any]:
    trees = Path(args.out) / "trees"
    known = real_size.recipes(trees.resolve())
    names = args.recipes or list(known)
    rows: list[dict[str, Any]] = []
    if args.dry_run:
        from occplug.run import runner

        composed = {}
        for name in names:  # the real-size recipes as real_size.py runs them: they compose and validate
            refs, overrides = known[name]
            try:
                runner.load_config(refs, overrides)
                composed[name] = "ok"
            except Exception as exc:
                composed[name] = error_line(exc)
        refs, overrides = DRY_JOB  # real_size's worker in this process (the subprocess around it: its own tests)
        job = {"refs": refs, "overrides": overrides, "device": "cpu", "batch": 1, "depth": 1}
        try:
            rows = [{"recipe": "baseline/synthetic-tiny", **row} for row in real_size.worker(job)]
        except Exception as exc:
            rows = [{"recipe": "baseline/synthetic-tiny", "error": error_line(exc)}]
        status = "ok" if all(v == "ok" for v in composed.values()) and "error" not in rows[0] else "error"
        return {"status": status, "composed": composed, "rows": rows, "papers": PAPERS}
    for name in names:
        left = deadline - time.monotonic()
        if left < 20:
            rows.append({"recipe": name, "error": "not run: the run's --budget was spent"})
            continue
        job = SimpleNamespace(device=args.device, batch=None, depth=3, timeout=left, out=str(Path(args.out)))
        rows.extend(real_size.run_recipe(name, *known[name], job))
    status = "error" if any("error" in r for r in rows) else "ok"
    return {"status": status, "rows": rows, "papers": PAPERS}


#: The dry run's one real_size job: the baseline recipe for one step on the tiny synthetic world.
DRY_JOB = ([str(ROOT / "configs" / "baseline.yaml")], ["data.preset=tiny", "data.batch_size=1"])


# ---------------------------------------------------------------------- the run
def write(path: Path, result: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(result, indent=2, default=str) + "\n")
    os.replace(tmp, path)


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--wheels", help="install from the wheels in this folder (pip --no-index) first")
    parser.add_argument("--out", default="runs/gpu_run", help="trees, logs and the JSON (default runs/gpu_run)")
    parser.add_argument("--json", help="the result (default <out>/gpu_run.json)")
    parser.add_argument("--budget", type=float, default=480.0, help="seconds for the whole run (default 480)")
    parser.add_argument("--recipes", nargs="+", help="real_size.py's recipe names (default: all)")
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats per measurement (default 5)")
    parser.add_argument("--dry-run", action="store_true", help="CPU, tiny sizes, a step each, the install planned")
    parser.add_argument("--installed", help=argparse.SUPPRESS)  # the JSON so far, after the install stage
    args = parser.parse_args(argv)
    args.json = args.json or str(Path(args.out) / "gpu_run.json")
    return args


def main(argv: list[str] | None = None) -> int:
    start = time.monotonic()
    args = parse(argv)
    path = Path(args.json)
    if args.installed:
        result = json.loads(Path(args.installed).read_text())
        start -= result["seconds"]
    else:
        result = {"schema": SCHEMA_VERSION, "dry_run": args.dry_run, "budget_s": args.budget, "stages": {}}
        t0 = time.monotonic()
        result["stages"]["install"] = {**stage_install(args), "seconds": time.monotonic() - t0}
        result["seconds"] = time.monotonic() - start
        write(path, result)
        if result["stages"]["install"]["status"] == "ok":  # a fresh interpreter sees the new packages
            rest = [a for a in (argv if argv is not None else sys.argv[1:])]
            os.execv(sys.executable, [sys.executable, __file__, *rest, "--installed", str(path)])
    deadline = start + args.budget
    import torch

    if args.dry_run:
        args.device = "cpu"
    elif not torch.cuda.is_available():
        raise SystemExit("error: no CUDA device: scripts/gpu_run.py measures a GPU (--dry-run runs on a CPU)")
    else:
        args.device = "cuda"
    real_size = load_script("real_size")
    trees = Path(args.out) / "trees"
    known = real_size.recipes(trees.resolve())
    unknown = [n for n in args.recipes or [] if n not in known]
    if unknown:
        raise SystemExit(f"error: --recipes: unknown {', '.join(unknown)} (known: {', '.join(known)})")
    precision_jobs = {"baseline/synthetic-tiny": DRY_JOB} if args.dry_run else {n: known[n] for n in PRECISION_RECIPES}
    stages: dict[str, Callable[[], dict[str, Any]]] = {
        "environment": lambda: stage_environment(args),
        "fast_paths": lambda: stage_fast_paths(args),
        "trees": lambda: stage_trees(args, real_size, trees),
        "precision": lambda: stage_precision(args, precision_jobs),
        "real_size": lambda: stage_real_size(args, real_size, deadline),
    }
    for name, stage in stages.items():
        print(f"gpu_run: {name} ...", flush=True)
        t0 = time.monotonic()
        try:
            outcome = stage()
        except Exception as exc:
            outcome = {"status": "error", "error": error_line(exc)}
        result["stages"][name] = {**outcome, "seconds": time.monotonic() - t0}
        result["seconds"] = time.monotonic() - start
        write(path, result)
        print(f"gpu_run: {name}: {outcome['status']} ({time.monotonic() - t0:.1f} s)", flush=True)
    result["within_budget"] = result["seconds"] <= args.budget
    write(path, result)
    print(f"gpu_run: wrote {path} ({result['seconds']:.0f} s of a {args.budget:.0f} s budget)")
    failed = [name for name, stage in result["stages"].items() if stage["status"] == "error"]
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
