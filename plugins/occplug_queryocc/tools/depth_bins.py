"""Where a world's depth is, against where QueryOcc's lift spends its depth bins.

Reads the true depth maps (camera z, metres) of the first ``--frames`` training frames of a synthetic world and
prints, per camera and over the rig: the share of pixels with a surface, its quantiles, and the share beyond each
``--beyond`` distance; then for each ``--bins D:near:far`` setting (Eq. 2, ``linear_mix`` 0) the bin width at a few
depths and the share of bins whose centre lies beyond the rig's 99th depth percentile (bins spent where almost
nothing is)::

    python -m occplug_queryocc.tools.depth_bins --preset aligned --bins 32:1:80 32:1:50 24:1:50
    python -m occplug_queryocc.tools.depth_bins --preset aligned --json results/queryocc/calibrated/depth_bins.json

Bad input (an unknown preset, a malformed ``--bins``) is one ``error:`` line and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from occplug_queryocc.view_transform import log_linear_depths

QUANTILES = (0.5, 0.9, 0.95, 0.99)
AT = (5.0, 10.0, 20.0, 40.0)


def parse_bins(spec: str) -> tuple[int, float, float]:
    """``"D:near:far"`` -> ``(D, near, far)``; ``ValueError`` naming the spec otherwise."""
    parts = spec.split(":")
    try:
        d, near, far = int(parts[0]), float(parts[1]), float(parts[2])
    except (IndexError, ValueError):
        raise ValueError(f"--bins {spec!r}: expected D:near:far (e.g. 32:1:80)") from None
    if len(parts) != 3 or d < 2 or not 0 < near < far:
        raise ValueError(f"--bins {spec!r}: expected D >= 2 and 0 < near < far")
    return d, near, far


def depth_report(depths: torch.Tensor, names: list[str], beyond: list[float]) -> dict:
    """``depths`` ``(F, N, H, W)`` camera z (0: no surface) -> per camera and ``rig``: ``with_surface`` (share of
    pixels, %), ``quantiles`` (metres, of the pixels with a surface) and ``beyond`` (% of those beyond each distance)."""
    out = {}
    for cam, name in [*enumerate(names), (None, "rig")]:
        z = depths if cam is None else depths[:, cam]
        hit = z[z > 0].double()
        out[name] = {
            "with_surface": 100.0 * hit.numel() / z.numel(),
            "quantiles": {
                f"p{round(q * 100)}": float(torch.quantile(hit[:: max(1, hit.numel() // 2_000_000)], q))
                for q in QUANTILES
            },
            "beyond": {f"{b:g}": 100.0 * float((hit > b).double().mean()) for b in beyond},
        }
    return out


def bins_report(settings: list[tuple[int, float, float]], p99: float) -> dict:
    """Per ``(D, near, far)``: the bin gap (metres) at each depth of :data:`AT` and the share of bins beyond ``p99``."""
    out = {}
    for d, near, far in settings:
        c = log_linear_depths(d, near, far).double()
        gaps = c[1:] - c[:-1]
        width = {f"{a:g}": float(gaps[min(int(torch.searchsorted(c, a)), len(gaps) - 1)]) for a in AT}
        out[f"{d}:{near:g}:{far:g}"] = {"gap_at": width, "bins_beyond_p99": 100.0 * float((c > p99).double().mean())}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m occplug_queryocc.tools.depth_bins", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--preset", default="aligned")
    parser.add_argument("--frames", type=int, default=24, help="training frames read (default 24: two scenes)")
    parser.add_argument("--beyond", type=float, nargs="+", default=[20.0, 30.0, 40.0, 50.0, 60.0])
    parser.add_argument("--bins", nargs="+", default=["32:1:80", "32:1:50", "24:1:50"])
    parser.add_argument("--json", help="also write the report here")
    args = parser.parse_args(argv)
    from occplug.data.synthetic import SyntheticDataset, default_cache_dir, preset

    try:
        settings = [parse_bins(b) for b in args.bins]
        config = preset(args.preset)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    ds = SyntheticDataset(config, "train", cache_dir=default_cache_dir(), with_adjacent=False)
    frames = [ds[i] for i in range(min(args.frames, len(ds)))]
    depths = torch.stack([f.depth for f in frames])  # (F, N, H, W)
    names = list(frames[0].camera_names) or [f"cam{i}" for i in range(depths.shape[1])]
    report = {"preset": args.preset, "frames": len(frames), "depth": depth_report(depths, names, args.beyond)}
    report["bins"] = bins_report(settings, report["depth"]["rig"]["quantiles"]["p99"])
    print(
        f"{'camera':<22} {'surface %':>9} "
        + " ".join(f"{q:>6}" for q in report["depth"]["rig"]["quantiles"])
        + " "
        + " ".join(f">{b:g}m %".rjust(8) for b in args.beyond)
    )
    for name, r in report["depth"].items():
        print(
            f"{name:<22} {r['with_surface']:9.1f} "
            + " ".join(f"{v:6.1f}" for v in r["quantiles"].values())
            + " "
            + " ".join(f"{v:8.2f}" for v in r["beyond"].values())
        )
    print()
    print(f"{'bins D:near:far':<16} " + " ".join(f"gap@{a:g}m".rjust(9) for a in AT) + "  bins beyond p99 %")
    for name, r in report["bins"].items():
        print(f"{name:<16} " + " ".join(f"{v:9.2f}" for v in r["gap_at"].values()) + f"  {r['bins_beyond_p99']:17.1f}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
