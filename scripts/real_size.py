#!/usr/bin/env python
"""Every real-data recipe for one training step and one validation batch at its paper's size, with random weights.

A new user with real data meets these recipes first at their full size; the test suite only composes them. This
script writes minimal real-size trees with the synthetic world (a nuScenes / Occ3D-shaped tree at 256 x 704 images
and 200 x 200 x 16 voxels of 0.4 m, with pseudo labels; a SemanticKITTI-shaped tree on the 256 x 256 x 32 SSC
grid), prepares and checks them, then runs each recipe as shipped (``weights: null``, the data root pointed at the
tree) in its own process for one training step and one validation batch, and prints a table:

    recipe | phase | device | precision | batch | step (s) | val batch (s) | peak MiB | peak KiB / voxel | error

* step: forward, backward and optimizer step of one training batch (a timer around Lightning's batch hooks; data
  loading excluded); val batch: one validation batch with its metrics.
* peak: the process's peak resident set (Linux ``VmHWM``, reset before each phase through ``/proc/self/clear_refs``)
  on a CPU, CUDA's peak allocation on a GPU; per voxel: that peak over the label grid's voxels, so a regression in
  how memory follows the grid shows.
* est. GPU MiB: an estimate, not a measurement: the activations the step saved for backward per sample times the
  recipe's batch, plus 16 bytes per parameter (float32 weights, gradients and AdamW's two moments); a GPU's
  workspace, fragmentation and the inputs come on top.
* precision: what the trainer ran at. A bf16-autocast recipe on a machine without a GPU trains at 32-true (the
  ``notice:`` line of ``occplug fit``).
* Below the table, per row: the bytes autograd saved for the backward pass during the training step's forward,
  by module (``occplug.run.memory.SavedTensorProfile``; ``--depth`` parts of the module name), the largest first:
  which tensors hold the peak.
* A recipe of phases (OccLE's Algorithm 1) runs every phase for one step, one row per phase, as ``occplug fit``
  would (each phase starting from the previous one's weights, teacher labels written between them).
* On CUDA (``--device cuda``) each row also times inference at batch 1 (``latency ms``, median of 5 after 2
  warm-up rounds) beside the papers' numbers.

Usage::

    python scripts/real_size.py [--out runs/real_size] [--recipes NAME ...] [--device auto|cpu|cuda]
                                [--batch 1|recipe] [--timeout 3600] [--json FILE]

The trees are written once under ``<out>/trees`` (about 2 minutes each on 2 CPU cores) and reused. The QueryOcc and
DuOcc recipes use timm encoders: install ``torch==2.14.1 torchvision==0.29.1`` and ``occplug[timm,duocc]`` first
(docs/data.md, "From your files to the first step, at the real size"); a recipe that cannot start prints its first
error line in the table and the script goes on.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

#: Occ3D-nuScenes-shaped tree: one scene per split, three key frames each (the middle one has both neighbours).
OCC3D_TREE = ["--preset", "occ3d", "--format", "occ3d", "--pseudo", "default", "train_scenes=1", "val_scenes=1",
              "test_scenes=1", "frames_per_scene=3"]  # fmt: skip
#: SemanticKITTI-shaped tree: the SSC grid (256 x 256 x 32 at 0.2 m), KITTI's image size, the front camera.
KITTI_TREE = ["--preset", "default", "--format", "semantickitti", "--pseudo", "default", "--splits", "train", "val",
              "train_scenes=1",
              "val_scenes=1", "test_scenes=1", "frames_per_scene=3", "image_size=[376,1241]"]  # fmt: skip

#: The papers' inference numbers at batch 1 on a GPU, printed beside a CUDA run's latency.
PAPER_LATENCY = {
    "queryocc/occ3d_nuscenes": "86 ms (paper)",
    "duocc/occ3d_nuscenes": "83.3 ms, 2,788 MB (paper; StreamAgg alone 49 ms)",
    "duocc/occ3d_nuscenes_rayiou": "83.3 ms, 2,788 MB (paper)",
}


def recipes(trees: Path) -> dict[str, tuple[list[str], list[str]]]:
    """Recipe name -> (config references, overrides pointing it at the trees)."""
    occ3d, kitti = trees / "occ3d", trees / "semantickitti"
    nuscenes = [f"data.root={occ3d}", f"data.index={occ3d / 'index'}"]
    pseudo = occ3d / "pseudo"
    queryocc_pseudo = {
        "depth": str(pseudo / "depth"),
        "semantics": [
            {"dir": str(pseudo / "semantics"), "mapping": str(pseudo / "semantics_mapping.yaml")},
            {"dir": str(pseudo / "semantics_aux"), "mapping": str(pseudo / "semantics_aux_mapping.yaml")},
        ],
    }
    kp = kitti / "pseudo"
    occle_pseudo = {
        "semantics": [
            {"dir": str(kp / "semantics"), "mapping": str(kp / "semantics_mapping.yaml")},
            {"dir": str(kp / "semantics_aux"), "mapping": str(kp / "semantics_aux_mapping.yaml")},
        ]
    }
    return {
        "baseline/occ3d_nuscenes": ([str(ROOT / "configs" / "baseline.yaml"), "occplug/data/occ3d_nuscenes"], nuscenes),
        "queryocc/occ3d_nuscenes": (
            ["queryocc/occ3d_nuscenes"],
            [*nuscenes, "data.pseudo_labels=" + json.dumps(queryocc_pseudo)],
        ),
        "duocc/occ3d_nuscenes": (["duocc/occ3d_nuscenes"], nuscenes),
        "duocc/occ3d_nuscenes_rayiou": (["duocc/occ3d_nuscenes_rayiou"], nuscenes),
        "occle/semantickitti": (
            ["occle/semantickitti"],
            [f"data.root={kitti}", "data.pseudo_labels=" + json.dumps(occle_pseudo)],
        ),
    }


# ---------------------------------------------------------------------- the trees
def occplug(*args: str) -> None:
    """Run the ``occplug`` CLI in a child process; a failure stops the script with its last line."""
    result = subprocess.run([sys.executable, "-m", "occplug.cli", *args], capture_output=True, text=True)
    if result.returncode != 0:
        last = (result.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise SystemExit(f"error: occplug {' '.join(args[:3])} ... failed: {last}")


def write_trees(trees: Path) -> None:
    """The two minimal real-size trees (written once; a finished tree has a ``.done`` marker)."""
    occ3d, kitti = trees / "occ3d", trees / "semantickitti"
    trees.mkdir(parents=True, exist_ok=True)
    if not (occ3d / ".done").is_file():
        print(f"writing {occ3d} (Occ3D-nuScenes shape, 256 x 704 images, 200 x 200 x 16 voxels)", flush=True)
        shutil.rmtree(occ3d, ignore_errors=True)  # an unfinished tree from an interrupted run
        occplug("data", "synth", "--out", str(occ3d), *OCC3D_TREE)
        occplug("data", "prepare", "nuscenes", "--root", str(occ3d), "--version", "v1.0-trainval", "--occ", str(occ3d),
                "--out", str(occ3d / "index"), "--splits", str(occ3d / "splits.json"), "--sweeps", "2")  # fmt: skip
        occplug(
            "data",
            "check",
            "index",
            "--index",
            str(occ3d / "index"),
            "--splits",
            str(occ3d / "splits.json"),
            "--no-progress",
        )
        (occ3d / ".done").write_text("written, prepared and checked\n")
    if not (kitti / ".done").is_file():
        print(f"writing {kitti} (SemanticKITTI shape, 256 x 256 x 32 voxels)", flush=True)
        shutil.rmtree(kitti, ignore_errors=True)
        occplug("data", "synth", "--out", str(kitti), *KITTI_TREE)
        occplug(
            "data",
            "check",
            "semantickitti",
            "--root",
            str(kitti),
            "--splits",
            str(kitti / "splits.json"),
            "--no-progress",
        )
        (kitti / ".done").write_text("written and checked\n")


# ---------------------------------------------------------------------- one recipe, in its own process
def worker(job: dict[str, Any]) -> list[dict[str, Any]]:
    """Fit ``job``'s recipe for one step and one validation batch per phase; one row per phase."""
    import torch
    from lightning.pytorch.callbacks import Callback

    from occplug.run import runner
    from occplug.run.memory import SavedTensorProfile, peak_rss, reset_peak_rss
    from occplug.run.phases import fit_phases

    cuda = job["device"] == "cuda"
    overrides = [
        *job["overrides"],
        f"trainer.accelerator={'gpu' if cuda else 'auto'}",
        "trainer.devices=1",
        "trainer.max_steps=1",
        "trainer.max_epochs=1",
        "trainer.limit_train_batches=1",
        "trainer.limit_val_batches=1",
        "trainer.num_sanity_val_steps=0",
        "trainer.enable_progress_bar=false",
        "data.num_workers=0",  # every byte in this process's peak
    ]
    job["recipe_batch"] = int(runner.load_config(job["refs"], job["overrides"])["data"].get("batch_size", 1))
    if job["batch"] is not None:
        overrides.append(f"data.batch_size={job['batch']}")
    cfg = runner.load_config(job["refs"], overrides)
    for node in [cfg, *(cfg.get("phases") or {}).values()]:  # random weights: no pretrained file is read
        encoder = ((node or {}).get("model") or {}).get("encoder") or {}
        if "weights" in encoder:
            encoder["weights"] = None
    grid = cfg.get("grid") or {}
    rows: list[dict[str, Any]] = []

    def sync() -> None:
        if cuda:
            torch.cuda.synchronize()

    class Probe(Callback):
        """Times the training batch and the validation batch, and the phase's peak memory."""

        def on_fit_start(self, trainer, pl_module) -> None:  # type: ignore[override]
            reset_peak_rss()
            if cuda:
                torch.cuda.reset_peak_memory_stats()
            phase = Path(trainer.default_root_dir).name if cfg.get("phases") else "-"
            precision = str(trainer.precision)
            batch = int(cfg["data"].get("batch_size", 1))
            params = sum(p.numel() for p in pl_module.parameters())
            recipe_batch = int(job["recipe_batch"])
            rows.append({"phase": phase, "precision": precision, "batch": batch, "recipe_batch": recipe_batch,
                         "voxels": voxels(pl_module), "params": params})  # fmt: skip

        def on_train_batch_start(self, trainer, pl_module, *args) -> None:  # type: ignore[override]
            self.profile = SavedTensorProfile(pl_module).__enter__()  # left in on_before_backward
            sync()
            self.start = time.perf_counter()

        def on_before_backward(self, trainer, pl_module, loss) -> None:  # type: ignore[override]
            self.profile.__exit__(None, None, None)
            rows[-1]["saved_bytes"] = self.profile.total
            # a GPU estimate at the recipe's batch: the activations saved per sample times the batch, plus the
            # weights, their gradients and AdamW's two moments (float32); workspace and fragmentation not included
            row = rows[-1]
            row["gpu_estimate_bytes"] = self.profile.total / row["batch"] * row["recipe_batch"] + 16 * row["params"]
            rows[-1]["saved_by_module"] = dict(list(self.profile.by_prefix(job["depth"]).items())[:12])

        def on_train_batch_end(self, *args) -> None:  # type: ignore[override]
            sync()
            rows[-1]["step_s"] = time.perf_counter() - self.start

        def on_validation_batch_start(self, *args) -> None:  # type: ignore[override]
            sync()
            self.val_start = time.perf_counter()

        def on_validation_batch_end(self, *args) -> None:  # type: ignore[override]
            sync()
            rows[-1]["val_s"] = time.perf_counter() - self.val_start

        def on_fit_end(self, trainer, pl_module) -> None:  # type: ignore[override]
            rows[-1]["peak_bytes"] = torch.cuda.max_memory_allocated() if cuda else peak_rss()
            if cuda:
                rows[-1]["latency_ms"] = latency(trainer, pl_module)

    def voxels(model: Any) -> int:
        """Voxels of the label grid (the top-level ``grid:``)."""
        from occplug import parse_grid

        count = 1
        for n in parse_grid(grid).shape:
            count *= int(n)
        return count

    def latency(trainer: Any, model: Any) -> float:
        dm = trainer.datamodule
        dataset = dm.dataset("val")
        batch = dm.collate([dataset[0]]).to(model.device)
        model.eval()
        times = []
        for i in range(7):
            sync()
            start = time.perf_counter()
            with torch.inference_mode():
                model.predict_occupancy(batch)
            sync()
            if i >= 2:
                times.append((time.perf_counter() - start) * 1000.0)
        return sorted(times)[len(times) // 2]

    with tempfile.TemporaryDirectory(prefix="occplug-real-size-") as tmp:
        run_dir = Path(tmp) / "run"
        if cfg.get("phases") is not None:
            fit_phases(cfg, run_dir, callbacks=[Probe()])
        else:
            runner.fit(cfg, run_dir, callbacks=[Probe()])
    return rows


def run_recipe(name: str, refs: list[str], overrides: list[str], args: argparse.Namespace) -> list[dict[str, Any]]:
    """One recipe in a child process (a process's peak only grows; a crash or a kill stays in its row)."""
    job = {"refs": refs, "overrides": overrides, "device": args.device, "batch": args.batch, "depth": args.depth}
    log = Path(args.out) / "logs" / (name.replace("/", "_") + ".log")
    log.parent.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with log.open("w") as fh:
        try:
            env = dict(os.environ)
            if args.device == "cpu":  # auto-accelerator on a machine with a GPU must still not pick it
                env["CUDA_VISIBLE_DEVICES"] = ""
            result = subprocess.run(
                [sys.executable, "-u", __file__, "--worker", json.dumps(job)],
                env=env,
                stdout=subprocess.PIPE,
                stderr=fh,
                text=True,
                timeout=args.timeout,
            )
        except subprocess.TimeoutExpired:
            return [{"recipe": name, "error": f"no result within --timeout {args.timeout} s (log: {log})"}]
    wall = time.perf_counter() - start
    lines = [line for line in result.stdout.splitlines() if line.startswith("{")]
    if result.returncode == 0 and lines:
        return [{"recipe": name, **row, "wall_s": wall} for row in json.loads(lines[-1])["rows"]]
    if result.returncode < 0:
        error = f"killed by signal {-result.returncode}" + (" (out of memory?)" if result.returncode == -9 else "")
    else:
        text = log.read_text().strip().splitlines()
        errors = [t for t in text if t.startswith(("error", "Error")) or "Error: " in t]
        error = errors[0] if errors else (text[-1] if text else "failed")
    return [{"recipe": name, "error": error[:200], "wall_s": wall}]


def table(rows: list[dict[str, Any]], device: str) -> str:
    head = (
        "| recipe | phase | device | precision | batch | step (s) | val batch (s) | peak MiB | peak KiB / voxel "
        "| est. GPU MiB at the recipe's batch |"
    )
    if device == "cuda":
        head += " latency ms (batch 1) | paper |"
    head += " error |"
    out = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        peak = r.get("peak_bytes")
        cells = [
            r["recipe"],
            r.get("phase", "-"),
            device,
            r.get("precision", "-"),
            str(r.get("batch", "-")),
            f"{r['step_s']:.1f}" if "step_s" in r else "-",
            f"{r['val_s']:.1f}" if "val_s" in r else "-",
            f"{peak / 2**20:,.0f}" if peak else "-",
            f"{peak / 1024 / r['voxels']:.2f}" if peak and r.get("voxels") else "-",
            f"{r['gpu_estimate_bytes'] / 2**20:,.0f} (batch {r['recipe_batch']})" if "gpu_estimate_bytes" in r else "-",
        ]
        if device == "cuda":
            cells += [f"{r['latency_ms']:.1f}" if "latency_ms" in r else "-", PAPER_LATENCY.get(r["recipe"], "-")]
        cells.append(r.get("error", ""))
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="runs/real_size", help="trees and logs (default runs/real_size)")
    parser.add_argument("--recipes", nargs="+", default=None, help="recipe names (default: all)")
    parser.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    parser.add_argument(
        "--batch", default=None, help="1 (default on a CPU) or 'recipe' (the recipe's batch; default on CUDA)"
    )
    parser.add_argument("--timeout", type=float, default=3600.0, help="seconds per recipe (default 3600)")
    parser.add_argument("--json", help="also write the rows here")
    parser.add_argument("--depth", type=int, default=3, help="module-name depth of the saved-activation profile")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        result = os.fdopen(os.dup(1), "w")  # the result line goes to the real stdout ...
        os.dup2(2, 1)  # ... everything else printed (Lightning, plugins) to the log
        sys.stdout = sys.stderr
        rows = worker(json.loads(args.worker))
        result.write(json.dumps({"rows": rows}) + "\n")
        result.close()
        return 0
    if args.device == "auto":
        import torch

        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    if args.batch is None:
        args.batch = "1" if args.device == "cpu" else "recipe"
    if args.batch not in ("1", "recipe"):
        parser.error(f"--batch: expected 1 or recipe, got {args.batch!r}")
    args.batch = None if args.batch == "recipe" else 1
    trees = Path(args.out) / "trees"
    known = recipes(trees.resolve())
    names = args.recipes or list(known)
    unknown = [n for n in names if n not in known]
    if unknown:
        parser.error(f"--recipes: unknown {', '.join(unknown)} (known: {', '.join(known)})")
    write_trees(trees)
    rows: list[dict[str, Any]] = []
    for name in names:
        print(f"{name}: one step and one validation batch ({args.device})", flush=True)
        refs, overrides = known[name]
        rows.extend(run_recipe(name, refs, overrides, args))
        print(table(rows[-1:], args.device).splitlines()[-1], flush=True)
    print()
    print(table(rows, args.device))
    for r in rows:
        if r.get("saved_by_module"):
            where = r["recipe"] + ("" if r.get("phase", "-") == "-" else f" (phase {r['phase']})")
            print(f"\n{where}: {r['saved_bytes'] / 2**20:,.0f} MiB saved for backward in the training step; largest:")
            for name, nbytes in r["saved_by_module"].items():
                print(f"  {nbytes / 2**20:10,.0f} MiB  {name}")
    if args.json:
        from occplug.run.bench import code_commit

        commit = code_commit(ROOT)  # the code the rows measured (None outside a git checkout)
        Path(args.json).write_text(json.dumps([{**r, "commit": commit} for r in rows], indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
