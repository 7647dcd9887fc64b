"""Behaviour fingerprint of the main configs: fixed-seed tiny-world fits, their metrics and checkpoint hashes.

A refactoring that must not change behaviour records a fingerprint before its first commit and compares after
its last one::

    python scripts/fingerprint.py --out runs/fingerprint_before.json          # before
    python scripts/fingerprint.py --check runs/fingerprint_before.json        # after: exit 1 on any difference

Each entry fits one config on the tiny synthetic world with ``occplug/trainer/debug`` (two training steps, one
validation batch; a phased config runs every phase), on one CPU thread with deterministic algorithms, and records
the validation metrics and a SHA-256 over every tensor of every phase's last checkpoint (``state_dict`` in key
order, bytes as stored). Two runs of the same code on the same machine and torch build give the same hashes.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
from pathlib import Path

import torch

#: name -> config refs (composed in this order, then ``occplug/trainer/debug``)
CONFIGS: dict[str, list[str]] = {
    "baseline": ["configs/baseline.yaml"],
    "queryocc_base": ["queryocc/base"],
    "occle_three_phase": ["occle/three_phase_10pct"],
    "duocc_b": ["duocc/stream_agg_concat"],
    "duocc_d": ["duocc/full"],
}


def checkpoint_hash(path: Path) -> str:
    """SHA-256 over the checkpoint's ``state_dict``: each key, dtype, shape and the tensor's bytes, in key order."""
    state = torch.load(path, map_location="cpu", weights_only=True)["state_dict"]
    digest = hashlib.sha256()
    for key in sorted(state):
        tensor = state[key].detach().contiguous().cpu().reshape(-1)
        digest.update(f"{key}|{tensor.dtype}|{tuple(tensor.shape)}|".encode())
        digest.update(tensor.view(torch.uint8).numpy().tobytes() if tensor.numel() else b"")
    return digest.hexdigest()


def fingerprint(name: str, refs: list[str], work: Path) -> dict:
    """Fit ``refs`` into ``work/name``; the metrics and the hash of each last checkpoint (one per phase)."""
    from occplug.testing import run_config

    run_dir = work / name
    metrics = run_config(*refs, run_dir=run_dir, overrides=["trainer.deterministic=true"])
    hashes = {
        str(ckpt.parent.parent.relative_to(run_dir)) or ".": checkpoint_hash(ckpt)
        for ckpt in sorted(run_dir.rglob("checkpoints/last.ckpt"))
    }
    return {"metrics": {k: float(v) for k, v in sorted(metrics.items())}, "checkpoints": hashes}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, help="write the fingerprint JSON here")
    parser.add_argument("--check", type=Path, help="compare with this fingerprint JSON; exit 1 on any difference")
    parser.add_argument("--only", nargs="*", choices=sorted(CONFIGS), help="fingerprint only these entries")
    args = parser.parse_args(argv)
    if args.check is not None and not args.check.is_file():
        parser.exit(2, f"error: --check {args.check}: no such file\n")
    torch.set_num_threads(1)
    torch.use_deterministic_algorithms(True)
    names = args.only or list(CONFIGS)
    result: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            result[name] = fingerprint(name, CONFIGS[name], Path(tmp))
            print(f"{name}: {json.dumps(result[name]['checkpoints'])}", flush=True)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2) + "\n")
    if args.check is not None:
        reference = json.loads(args.check.read_text())
        same = [json.dumps(reference.get(n), sort_keys=True) == json.dumps(result[n], sort_keys=True) for n in names]
        differ = [n for n, equal in zip(names, same, strict=True) if not equal]  # compared as JSON text: NaN equals NaN
        for n in differ:
            print(f"DIFFERS {n}:\n  before {json.dumps(reference.get(n))}\n  now    {json.dumps(result[n])}")
        print("identical" if not differ else f"{len(differ)} of {len(names)} differ")
        return 1 if differ else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
