#!/usr/bin/env python
"""What the paper's pieces cost here: a training step's time and peak memory per phase, each option beside OccLE at
10 % labels (``occle/three_phase_10pct``), as ratios.

Options (``--options``, default all):

* ``paper_protocol`` (``occle/paper_protocol``): SSC evaluation without the camera mask and class-frequency weighted
  cross-entropy (training pays only for the weights);
* ``geometry_own_encoders`` (``occle/geometry_own_encoders``): the geometric branch's own image encoder, lift and
  LiDAR encoder, trained in Phase II;
* ``mamba_4_stages`` (``occle/mamba_4_stages``): the paper's 4-stage Dual Mamba (the recipes': 2).

For each recipe and phase a child process (:func:`occplug_occle.tools.memory.run`) builds the phase on the synthetic
world (``--preset``, default ``tiny``; the recipes' 32 x 32 x 8 grid, batch ``--batch``), freezes what the phase
freezes and runs ``--steps`` training steps on one batch: the step time is the median CPU time (``process_time``:
with one thread, what the step computes, which a shared machine's wall time does not show) of the steps after the
first (wall times are in ``--json``), the peak the child's resident set over them. The children run one after
another, each option right after the baseline of the same phase; ``--rounds R`` repeats the sweep (every other
round in reverse order) and reports each cell's median step time and largest peak. Run it alone with ``OMP_NUM_THREADS=1``::

    python -m occplug_occle.tools.options [--options ...] [--phases semantic teacher student fusion] [--steps 6]
                                          [--preset tiny] [--batch 2] [--rounds 1] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

from occplug_occle.tools.memory import ROOT, run

BASELINE = "three_phase_10pct"
OPTIONS = ("paper_protocol", "geometry_own_encoders", "mamba_4_stages")
PHASES = ("semantic", "teacher", "student", "fusion")


def combined(rows: list[dict]) -> list[dict]:
    """One row per (option, phase): the median step time and the largest peak over its rounds (an error if any)."""
    out: dict[tuple[str, str], list[dict]] = {}
    for row in rows:
        out.setdefault((row["option"], row["phase"]), []).append(row)
    merged = []
    for group in out.values():
        failed = [r for r in group if "error" in r]
        if failed:
            merged.append(failed[0])
            continue
        step = statistics.median(r["step_s"] for r in group)
        cpu = statistics.median(r.get("step_cpu_s", r["step_s"]) for r in group)
        peak = max(r["peak_mib"] for r in group)
        merged.append({**group[0], "step_s": step, "step_cpu_s": cpu, "peak_mib": peak})
    return merged


def table(rows: list[dict], options: list[str], phases: list[str]) -> str:
    """Per phase: the baseline's step time and peak, then each option's and its ratio to the baseline."""
    by = {(r["option"], r["phase"]): r for r in rows}
    head = ["phase", f"{BASELINE} step CPU s", f"{BASELINE} peak MiB"]
    for option in options:
        head += [f"{option} step CPU s (x)", f"{option} peak MiB (x)"]
    lines = ["| " + " | ".join(head) + " |", "|---|" + "--:|" * (len(head) - 1)]
    for phase in phases:
        base = by.get((BASELINE, phase), {})
        if "error" in base or not base:
            lines.append(f"| {phase} | {base.get('error', 'not run')} |" + " |" * (len(head) - 2))
            continue
        cells = [phase, f"{base['step_cpu_s']:.3f}", f"{base['peak_mib']:,.0f}"]
        for option in options:
            row = by.get((option, phase), {})
            if "error" in row or not row:
                cells += [row.get("error", "not run"), ""]
                continue
            cells += [
                f"{row['step_cpu_s']:.3f} ({row['step_cpu_s'] / base['step_cpu_s']:.2f})",
                f"{row['peak_mib']:,.0f} ({row['peak_mib'] / base['peak_mib']:.2f})",
            ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m occplug_occle.tools.options", description=__doc__.split("\n\n")[0])
    parser.add_argument("--options", nargs="+", choices=OPTIONS, default=list(OPTIONS))
    parser.add_argument("--phases", nargs="+", choices=PHASES, default=list(PHASES))
    parser.add_argument("--steps", type=int, default=6, help="training steps per child (the first is not timed)")
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--batch", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=1800.0)
    parser.add_argument("--max-rss-gib", type=float, default=10.0)
    parser.add_argument("--rounds", type=int, default=1, help="sweeps; each cell's median step time, largest peak")
    parser.add_argument("--json", help="write every row here")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.rounds < 1:
        print(f"error: --steps and --rounds must be at least 1, got {args.steps} and {args.rounds}", file=sys.stderr)
        return 2
    import subprocess

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    commit = commit.stdout.strip() or "?"
    rows = []
    cells = [(phase, option) for phase in args.phases for option in [BASELINE, *args.options]]
    for r in range(args.rounds):
        for phase, option in cells if r % 2 == 0 else cells[::-1]:
            job = {"grid": [32, 32, 8], "setting": "plain", "batch": args.batch, "depth": 2, "phase": phase}
            job |= {"recipe": f"occle/{option}", "steps": args.steps, "set": [f"data.preset={args.preset}"]}
            row = {**run(job, args.max_rss_gib, args.timeout), "option": option, "commit": commit, "round": r}
            rows.append(row)
            summary = row.get("error") or (
                f"step {row['step_s']:.3f} s ({row.get('step_cpu_s', float('nan')):.3f} CPU s), "
                f"peak {row['peak_mib']:,.0f} MiB"
            )
            print(f"round {r} {phase} {option}: {summary}", file=sys.stderr, flush=True)
    print(
        f"OccLE options, training step per phase (median of {args.steps - 1 or 1} after the first), world "
        f"'{args.preset}', batch {args.batch}, 32 x 32 x 8, CPU, {args.rounds} round(s), commit {commit}; "
        f"(x) = ratio to {BASELINE}\n"
    )
    print(table(combined(rows), list(args.options), list(args.phases)))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
