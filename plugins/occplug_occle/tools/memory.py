#!/usr/bin/env python
"""How OccLE's training memory follows the grid: one training step (of Phase III, or ``--phase``) at several grid
sizes, with and without activation checkpointing.

Settings (``--settings``, default ``plain checkpoint``): ``plain`` keeps every activation; ``checkpoint`` sets
``model.scene.mamba_checkpoint`` (the Dual Mamba's mixers recomputed in backward); ``both`` also sets
``model.scene.semantic_checkpoint`` (the semantic branch's dense LiDAR UNet and mix recomputed too), as
``occle/semantickitti`` does.

For each grid ``X x Y x Z`` and setting, a child process builds the final phase (``fusion``, Phase III; another with
``--phase``) of
``occle/three_phase_10pct`` on the synthetic world with the grid replaced (voxel edge ``6.4 m / Z``, ``X`` voxels
forward from the ego, ``Y`` centred, from 1 m below the ego: 32 x 32 x 8 is the recipe's own grid, 256 x 256 x 32
SemanticKITTI's 51.2 m x 51.2 m x 6.4 m at 0.2 m), freezes what the phase freezes, and runs one training step
(forward, losses, backward, AdamW step) on one batch of random-weight model. It reports:

* tokens at level 1: the length of the first Dual Mamba level's scans, ``X * Y * Z`` per grid;
* peak MiB: the child's peak resident set during the step (Linux ``VmHWM``, reset just before it through
  ``/proc/self/clear_refs``), which includes the model, the data and the interpreter (``base MiB``: the resident set
  just before the step);
* saved MiB: what autograd kept for backward during the forward (``occplug.run.memory.SavedTensorProfile``); a
  checkpointed mixer's kept input is held by the checkpoint, not saved, so it is not in this column;
* below the table, per grid and setting, the saved bytes by module (``--depth`` parts of the name), largest first.

A child whose resident set passes ``--max-rss-gib`` is stopped and its row says so (the parent polls it every
0.2 s, so the bound can be overshot by what 0.2 s allocates). The last table row extrapolates, where asked
(``--extrapolate X Y Z``), each setting's peak linearly in the voxels from its two largest measured grids; it is an
estimate, not a measurement, and says so.

Usage::

    python -m occplug_occle.tools.memory [--grids 32x32x8 64x64x16 ...] [--settings plain checkpoint] [--batch 1]
                                   [--phase fusion] [--set key=value ...] [--depth 3] [--max-rss-gib 10]
                                   [--extrapolate 256 256 32] [--json FILE]
    python -m occplug_occle.tools.memory --from-json FILE [--settings ...] [--extrapolate X Y Z]   # the tables again

Pure PyTorch on the CPU (``mamba_ssm`` is CUDA only; on a CPU the Mamba mixers run the chunked scan with its
memory-lean backward, ``occplug_occle.blocks.selective_scan.SelectiveScanFn``). Run it alone, with
``OMP_NUM_THREADS=1``: the peaks are per process, and the children run one after another.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent  # inside the checkout: git finds the commit from here
RECIPE = "occle/three_phase_10pct"
#: the phase measured by default (``--phase``): Phase III, the largest model that trains
PHASE = "fusion"
#: setting -> (model.scene.mamba_checkpoint, model.scene.semantic_checkpoint); ``occle/semantickitti`` runs "both"
SETTINGS = {"plain": (False, False), "checkpoint": (True, False), "both": (True, True)}


def grid_overrides(shape: tuple[int, int, int]) -> list[str]:
    """Overrides putting ``shape`` voxels on the recipe's layout (forward of the ego, y centred, 6.4 m tall)."""
    x, y, z = shape
    edge = 6.4 / z
    extent = [0.0, -y * edge / 2, -1.0, x * edge, y * edge / 2, -1.0 + z * edge]
    return [f"grid.range=[{','.join(f'{v:.6g}' for v in extent)}]", f"grid.voxel_size={edge:.6g}"]


def _status(key: str) -> float:
    """A ``/proc/self/status`` entry in MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key):
            return int(line.split()[1]) / 1024
    raise KeyError(key)


def worker(job: dict[str, Any]) -> dict[str, Any]:
    """One training step of the recipe's phase ``job["phase"]`` at ``job``'s grid; the numbers of its row."""
    import torch

    from occplug.config import phase_specs
    from occplug.run import runner
    from occplug.run.memory import SavedTensorProfile, peak_rss, reset_peak_rss
    from occplug.run.phases import freeze

    torch.manual_seed(0)
    overrides = [
        *grid_overrides(tuple(job["grid"])),
        f"data.batch_size={job['batch']}",
        f"model.scene.mamba_checkpoint={str(SETTINGS[job['setting']][0]).lower()}",
        f"model.scene.semantic_checkpoint={str(SETTINGS[job['setting']][1]).lower()}",
        "model.point_encoders.lidar.sampling=first",
        *job.get("set", []),
    ]
    cfg = runner.load_config([job.get("recipe", RECIPE)], overrides)
    phase = job.get("phase", PHASE)
    spec = next(s for s in phase_specs(cfg) if s.name == phase)
    dm = runner.build_datamodule(spec.config)
    model = runner.build_model(spec.config, dm)
    frozen = freeze(model, spec.freeze, f"phases.{phase}.freeze")
    dataset = dm.dataset("train")
    frames = min(int(job["batch"]), len(dataset))  # a phase on the labelled subset of a small world has fewer
    batch = dm.collate([dataset[i] for i in range(frames)])
    model.train()
    modules = dict(model.named_modules())
    for name in frozen:  # as the phase trains them (FrozenModulesEval)
        modules[name].eval()
    optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-4)
    base = _status("VmRSS:")
    reset_peak_rss()
    start = time.perf_counter()
    with SavedTensorProfile(model) as profile:
        losses = model.losses(batch, model(batch))
        loss = torch.stack(list(losses.values())).sum()
    loss.backward()
    optimizer.step()
    step = time.perf_counter() - start
    times, cpu = [], []
    for _ in range(int(job.get("steps", 1)) - 1):  # further steps on the same batch: the step time once warm
        optimizer.zero_grad(set_to_none=True)
        start, start_cpu = time.perf_counter(), time.process_time()
        losses = model.losses(batch, model(batch))
        torch.stack(list(losses.values())).sum().backward()
        optimizer.step()
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)  # CPU seconds: what a loaded machine's wall time hides
    extra = {}
    if times:
        step = statistics.median(times)
        extra["step_cpu_s"] = statistics.median(cpu)
    return {
        "base_mib": base,
        "peak_mib": peak_rss() / 2**20,
        "saved_mib": profile.total / 2**20,
        "saved_by_module": {k: v / 2**20 for k, v in list(profile.by_prefix(job["depth"]).items())[:12]},
        "step_s": step,
        "loss": float(loss.detach()),
        "grid_shape": list(model.scene.grid.shape),
        "batch_frames": frames,
        **extra,
    }


def run(job: dict[str, Any], max_rss_gib: float, timeout: float) -> dict[str, Any]:
    """``job`` in a child process, stopped when its resident set passes ``max_rss_gib``."""
    import psutil

    proc = subprocess.Popen(
        [sys.executable, "-u", __file__, "--worker", json.dumps(job)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    child, start, limit, high = psutil.Process(proc.pid), time.monotonic(), max_rss_gib * 2**30, 0
    while proc.poll() is None:
        try:
            high = max(high, child.memory_info().rss)
        except psutil.NoSuchProcess:
            break
        if high > limit or time.monotonic() - start > timeout:
            proc.kill()
            proc.wait()
            why = f"over {max_rss_gib:g} GiB" if high > limit else f"over {timeout:g} s"
            return {**job, "error": f"stopped: {why} (resident {high / 2**20:,.0f} MiB when stopped)"}
        time.sleep(0.2)
    out, err = proc.communicate()
    lines = [line for line in out.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        last = (err.strip().splitlines() or ["(no output)"])[-1]
        return {**job, "error": f"exit {proc.returncode}: {last[:160]}"}
    return {**job, **json.loads(lines[-1])}


def _voxels(grid: list[int]) -> int:
    return grid[0] * grid[1] * grid[2]


def table(rows: list[dict[str, Any]], settings: list[str], extrapolate: list[int] | None) -> str:
    """One line per grid: tokens, peaks per setting, their ratio, and the peak and voxel ratios to the first grid."""
    grids: list[tuple[int, ...]] = list(dict.fromkeys(tuple(r["grid"]) for r in rows))
    by = {(tuple(r["grid"]), r["setting"]): r for r in rows}
    head = ["grid", "tokens at level 1", "voxels / first", "base MiB"]
    for s in settings:
        head += [f"peak MiB, {s}", f"saved MiB, {s}", f"step s, {s}", f"peak / first, {s}"]
    if len(settings) == 2:
        head.append(f"peak {settings[1]} / {settings[0]}")
    lines = ["| " + " | ".join(head) + " |", "|---|" + "--:|" * (len(head) - 1)]
    first = grids[0]

    def peak(grid: tuple[int, ...], s: str) -> float | None:
        row = by.get((grid, s))
        return None if row is None or "error" in row else row["peak_mib"]

    for grid in grids:
        bases = [by[(grid, s)]["base_mib"] for s in settings if "base_mib" in by.get((grid, s), {})]
        cells = [
            "x".join(map(str, grid)),
            f"{_voxels(list(grid)):,}",
            f"{_voxels(list(grid)) / _voxels(list(first)):g}",
            f"{max(bases):,.0f}" if bases else "",
        ]
        for s in settings:
            row = by.get((grid, s), {})
            if "error" in row or not row:
                cells += [row.get("error", "not run"), "", "", ""]
                continue
            ref = peak(first, s)
            cells += [
                f"{row['peak_mib']:,.0f}",
                f"{row['saved_mib']:,.0f}",
                f"{row['step_s']:.1f}",
                f"{row['peak_mib'] / ref:.2f}" if ref else "",
            ]
        if len(settings) == 2:
            a, b = peak(grid, settings[0]), peak(grid, settings[1])
            cells.append(f"{b / a:.2f}" if a and b else "")
        lines.append("| " + " | ".join(cells) + " |")
    if extrapolate:
        target = list(extrapolate)
        ratio = f"{_voxels(target) / _voxels(list(first)):g}"
        cells = ["x".join(map(str, target)) + " (extrapolated)", f"{_voxels(target):,}", ratio, ""]
        for s in settings:
            measured = [(g, peak(g, s)) for g in grids if peak(g, s)]
            if len(measured) < 2:
                cells += ["", "", "", ""]
                continue
            (g1, p1), (g2, p2) = sorted(measured, key=lambda gp: _voxels(list(gp[0])))[-2:]
            slope = (p2 - p1) / (_voxels(list(g2)) - _voxels(list(g1)))
            estimate = p2 + slope * (_voxels(target) - _voxels(list(g2)))
            cells += [f"~{estimate:,.0f} (est.)", "", "", ""]
        if len(settings) == 2:
            cells.append("")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m occplug_occle.tools.memory", description=__doc__.split("\n\n")[0])
    parser.add_argument("--grids", nargs="+", default=["32x32x8", "64x64x16", "128x128x16"])
    parser.add_argument("--settings", nargs="+", choices=list(SETTINGS), default=["plain", "checkpoint"])
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--depth", type=int, default=3)
    parser.add_argument("--max-rss-gib", type=float, default=10.0)
    parser.add_argument("--timeout", type=float, default=1800.0)
    parser.add_argument("--extrapolate", type=int, nargs=3, metavar=("X", "Y", "Z"))
    parser.add_argument("--json", help="write every row here")
    parser.add_argument("--from-json", help="print the tables of rows an earlier --json wrote (runs nothing)")
    parser.add_argument("--phase", default=PHASE, help=f"the phase of {RECIPE} to measure (default {PHASE})")
    parser.add_argument("--set", nargs="*", default=[], help="further config overrides (key=value) for every row")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(json.loads(args.worker))), flush=True)
        return 0
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    commit = commit.stdout.strip() or "?"
    rows = json.loads(Path(args.from_json).read_text()) if args.from_json else []
    phase = args.phase
    if rows:
        commit, phase = rows[0].get("commit", "?"), rows[0].get("phase", PHASE)
    for text in [] if args.from_json else args.grids:
        grid = [int(v) for v in text.lower().split("x")]
        for setting in args.settings:
            job = {"grid": grid, "setting": setting, "batch": args.batch, "depth": args.depth}
            job |= {"phase": args.phase, "set": list(args.set)}
            row = {**run(job, args.max_rss_gib, args.timeout), "commit": commit}
            rows.append(row)
            summary = row.get("error") or f"peak {row['peak_mib']:,.0f} MiB, step {row['step_s']:.1f} s"
            print(f"{text} {setting}: {summary}", file=sys.stderr, flush=True)
    print(f"OccLE `{RECIPE}` phase `{phase}`, one training step, batch {args.batch}, CPU, commit "
          f"{commit}\n")  # fmt: skip
    print(table(rows, args.settings, args.extrapolate))
    for row in rows:
        if "saved_by_module" in row:
            print(f"\nsaved for backward, {'x'.join(map(str, row['grid']))}, {row['setting']} (MiB):")
            print("| module | MiB |\n|---|--:|")
            for name, mib in row["saved_by_module"].items():
                print(f"| {name} | {mib:,.0f} |")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
