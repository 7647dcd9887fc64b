"""How V_fin's magnitude evolves along a stream: DuOcc's StreamAgg diagnostics on a trained run.

For each run directory, the validation split is read in order (the stream state carried as in evaluation) and the
module prints, per position in the scene (frame 0 = the reset frame), the mean L2 norm of ``V_curr`` (this frame's
lifted volume) and of ``V_S.A`` (after the stream fusion, what the next frame's history is in B). With the paper's
Eq. 5 (``V_S.A = RefineNet(warp(V_fin)) + V_curr``, RefineNet residual) the fused volume is a running sum over the
stream; with the public code's concat + GroupNorm fusion it stays bounded::

    python investigations/duocc/history_norm.py runs/duocc_ablate/stream_agg-seed0 runs/duocc_ablate/stream_agg_concat-seed0
"""

from __future__ import annotations

import argparse
import collections
from pathlib import Path

import torch

from occplug.run import runner
from occplug.streams import find_streams, set_stream_stage


def norms_along_stream(run: Path, max_batches: int) -> dict[int, tuple[float, float]]:
    """``{position in scene: (mean |V_curr|, mean |V_S.A|)}`` over the first ``max_batches`` validation batches."""
    ckpt = run / "checkpoints" / "last.ckpt"
    dm, model = runner.build_run(runner.resolve_run_config([], [], ckpt))
    model.load_state_dict(runner.load_checkpoint(ckpt)["state_dict"])
    model.eval()
    agg = model.scene.agg
    if agg is None:
        raise SystemExit(f"{run}: the scene has no StreamAgg (a single-frame model)")
    set_stream_stage(model, "val")
    for _, state in find_streams(model):
        state.clear("val")
    position: list[int] = []
    sums: dict[int, list[float]] = collections.defaultdict(lambda: [0.0, 0.0, 0.0])
    forward = agg.forward

    def recording(v_curr, v_hist=None, prev_to_current=None, reset=None):
        out = forward(v_curr, v_hist, prev_to_current, reset)
        for b in range(v_curr.shape[0]):
            if len(position) <= b:
                position.append(0)
            position[b] = 0 if reset is None or bool(reset[b]) else position[b] + 1
            cell = sums[position[b]]
            cell[0] += float(v_curr[b].norm())
            cell[1] += float(out.fused[b].norm())
            cell[2] += 1
        return out

    agg.forward = recording
    dm.prepare_data()
    dm.setup("validate")
    with torch.no_grad():
        for i, batch in enumerate(dm.val_dataloader()):
            if i >= max_batches:
                break
            model(batch)
    return {k: (v[0] / v[2], v[1] / v[2]) for k, v in sorted(sums.items())}


def main() -> None:
    parser = argparse.ArgumentParser(
        prog="python investigations/duocc/history_norm.py",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("runs", nargs="+", type=Path, help="run directories of duocc_stream models")
    parser.add_argument("--batches", type=int, default=12, help="validation batches read (in order)")
    args = parser.parse_args()
    for run in args.runs:
        print(f"{run}:")
        print("| frame in scene | mean |V_curr| | mean |V_S.A| | ratio |")
        print("|--:|--:|--:|--:|")
        for k, (curr, fused) in norms_along_stream(run, args.batches).items():
            print(f"| {k} | {curr:.1f} | {fused:.1f} | {fused / curr:.2f} |")


if __name__ == "__main__":
    main()
