"""Where a trained QueryOcc model predicts occupied space that is free, and whether any training query reached it.

Reads a run's checkpoint and the validation split (no training)::

    python -m occplug_queryocc.tools.diagnose runs/queryocc_ablate/base-seed0            # the run's last.ckpt
    python -m occplug_queryocc.tools.diagnose CKPT --batches 12 --draws 4 --json out.json

Scored voxels are those of the camera mask (the evaluation's). A **false-occupied** voxel is scored, free in
the voxel labels and predicted occupied (any class). Each is tallied

* by **height above the ground** of its column: its centre's ``z`` minus the top of the highest ground-class
  voxel (``driveable_surface``, ``other_flat``, ``sidewalk``, ``terrain``) in the column of the labels, or
  of the sample's median ground top where the column has none;
* by **distance** from the ego origin in ``x, y``;
* by the class of the **first hit along the camera ray** through it: the first occupied voxel of the labels
  on the ray from the camera that sees it (the one whose optical axis is nearest its direction) through its
  centre, ``nothing in the grid`` when that ray leaves the grid without one (it sees the sky, or something
  beyond the grid);
* by the **camera that sees it** (the same rule), also as a share of the scored free voxels that camera sees (the
  back camera's 110° field of view against the others' 70°);
* by **how many voxels lie between it and that first hit** (Chebyshev distance of the voxel indices; 1: the
  hit is its neighbour, so the field runs one voxel in front of a surface), or ``hit before it`` when that ray
  meets something before the voxel's centre (another camera sees it);
* by **query coverage**: whether a query of the run's own ``queryocc_query_points`` came within one voxel of it
  (its 3 x 3 x 3 neighbourhood held one), split into negatives (free queries) and positives. The queries are
  drawn on the diagnosed (validation) frames themselves, ``draws`` times each (the default 4: what 4 epochs of
  training draw from a frame); training draws the same way from its own frames, which are not scored.

and, the other side of the occupancy IoU, the share of each class's scored occupied voxels that it predicts free
(**false free**). It prints the shares and, with ``--json``, writes them.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from occplug import UserError
from occplug.geometry import GridSpec, first_hit

__all__ = [
    "DISTANCE_EDGES",
    "GROUND_CLASSES",
    "HEIGHT_EDGES",
    "Tally",
    "covered",
    "first_hit_classes",
    "first_hits_from_camera",
    "height_above_ground",
    "main",
    "seeing_camera",
]

#: Occ3D ground classes: driveable_surface, other_flat, sidewalk, terrain.
GROUND_CLASSES = (11, 12, 13, 14)
#: Bin edges (metres) of the height above the ground and of the distance from the ego origin.
HEIGHT_EDGES = (0.0, 1.0, 2.0, 4.0)
DISTANCE_EDGES = (0.0, 8.0, 16.0, 24.0)
#: Bin edges (voxels) of the gap from a false-occupied voxel to the first hit behind it: 1, 2, 3-4, >= 5.
GAP_EDGES = (1, 2, 3, 5)
#: The first-hit key of a ray that leaves the grid without hitting anything (it sees the sky or what lies beyond).
NO_HIT = "nothing in the grid"


def height_above_ground(labels: Tensor, grid: GridSpec, ground: Sequence[int] = GROUND_CLASSES) -> Tensor:
    """``(X, Y, Z)`` metres from the top of each column's highest ground voxel to each voxel's centre.

    Args:
        labels: ``(X, Y, Z)`` class ids on ``grid`` (ego frame).
        ground: the ground class ids. A column without any takes the median ground top of the columns that
            have one (the grid's floor ``z_min`` when none has).
    """
    z_size = grid.voxel_size[2]
    is_ground = torch.isin(labels.long(), torch.tensor(ground, device=labels.device))
    k = torch.arange(labels.shape[2], device=labels.device)
    top_k = torch.where(is_ground, k, torch.full_like(k, -1)).amax(dim=2)  # (X, Y) highest ground index, -1: none
    top = grid.lower[2] + (top_k + 1).double() * z_size  # (X, Y) metres
    has = top_k >= 0
    fill = top[has].median() if bool(has.any()) else torch.tensor(grid.lower[2], dtype=torch.float64)
    top = torch.where(has, top, fill)
    centres = grid.lower[2] + (k.double() + 0.5) * z_size
    return (centres[None, None, :] - top[..., None]).float()


def covered(points: Tensor, grid: GridSpec, reach: int = 1) -> Tensor:
    """``(X, Y, Z)`` bool: voxels within ``reach`` voxels (Chebyshev, per axis) of a voxel holding one of the
    ``(P, 3)`` points (ego frame, metres). Points outside the grid reach nothing."""
    shape = grid.shape
    lower = torch.tensor(grid.lower, dtype=torch.float64, device=points.device)
    size = torch.tensor(grid.voxel_size, dtype=torch.float64, device=points.device)
    index = torch.floor((points.double() - lower) / size).long()
    inside = ((index >= 0) & (index < torch.tensor(shape, device=points.device))).all(-1)
    index = index[inside]
    hit = torch.zeros(shape, dtype=torch.float32, device=points.device)
    hit[index[:, 0], index[:, 1], index[:, 2]] = 1.0
    if reach > 0:
        hit = F.max_pool3d(hit[None, None], 2 * reach + 1, stride=1, padding=reach)[0, 0]
    return hit > 0


def first_hit_classes(
    labels: Tensor, grid: GridSpec, free_label: int, cam_to_ego: Tensor, voxels: Tensor
) -> list[str | int]:
    """The class of the first occupied voxel on the ray from the camera that sees each voxel through its centre.

    Args:
        labels: ``(X, Y, Z)`` class ids (``free_label`` free; 255 unknown counts as occupied, as it is not free).
        cam_to_ego: ``(N, 4, 4)`` camera poses; a voxel is seen by the camera whose optical axis (camera ``+z``)
            makes the smallest angle with the direction from that camera to the voxel centre.
        voxels: ``(V, 3)`` int64 voxel indices.

    Returns:
        per voxel, the class id hit, or :data:`NO_HIT` when the ray leaves the grid without a hit (the sky, or
        something beyond the grid).
    """
    return first_hits_from_camera(labels, grid, free_label, cam_to_ego, voxels)[0]


def first_hits_from_camera(
    labels: Tensor, grid: GridSpec, free_label: int, cam_to_ego: Tensor, voxels: Tensor
) -> tuple[list[str | int], list[int | None]]:
    """:func:`first_hit_classes` and, per voxel, how many voxels lie between it and that first hit.

    Returns:
        ``classes`` as :func:`first_hit_classes`; ``gaps``: per voxel the Chebyshev distance in voxel indices
        from it to the voxel hit (1: the hit is its neighbour), ``0`` when the ray hits before reaching the
        voxel's centre (another camera sees it), ``None`` without a hit.
    """
    if len(voxels) == 0:
        return [], []
    centres = _centres(grid, voxels)
    cam = seeing_camera(grid, cam_to_ego, voxels)
    o = cam_to_ego[:, :3, 3].double()[cam]
    d = F.normalize(centres - o, dim=-1)
    occupied = labels != free_label
    index, distance = first_hit(occupied, grid, o, d, float("inf"))
    reach = (centres - o).norm(dim=-1)
    steps = (index - voxels).abs().amax(dim=-1)
    classes: list[str | int] = []
    gaps: list[int | None] = []
    for (i, j, k), gap, before in zip(
        index.tolist(), steps.tolist(), (distance.double() < reach).tolist(), strict=True
    ):
        classes.append(NO_HIT if i < 0 else int(labels[i, j, k]))
        gaps.append(None if i < 0 else (0 if before else int(gap)))
    return classes, gaps


def _centres(grid: GridSpec, voxels: Tensor) -> Tensor:
    """``(V, 3)`` float64 ego-frame centres of ``(V, 3)`` voxel indices."""
    lower = torch.tensor(grid.lower, dtype=torch.float64)
    size = torch.tensor(grid.voxel_size, dtype=torch.float64)
    return lower + (voxels.double() + 0.5) * size


def seeing_camera(grid: GridSpec, cam_to_ego: Tensor, voxels: Tensor) -> Tensor:
    """``(V,)`` int64 index of the camera that sees each of ``voxels`` ``(V, 3)`` (voxel indices of ``grid``): the one
    whose optical axis (camera ``+z`` of ``cam_to_ego`` ``(N, 4, 4)``) makes the smallest angle with the direction
    from that camera to the voxel's centre."""
    if len(voxels) == 0:
        return torch.zeros(0, dtype=torch.int64)
    origins = cam_to_ego[:, :3, 3].double()  # (N, 3)
    axes = cam_to_ego[:, :3, 2].double()  # (N, 3) optical axes in the ego frame
    to_voxel = F.normalize(_centres(grid, voxels)[:, None] - origins[None], dim=-1)  # (V, N, 3)
    return (to_voxel * axes[None]).sum(-1).argmax(1)


class Tally:
    """Counts of false-occupied voxels by bin, and of the scored free voxels they come from."""

    def __init__(self) -> None:
        self.scored_free = 0
        self.false_occupied = 0
        self.height = [0] * len(HEIGHT_EDGES)
        self.distance = [0] * len(DISTANCE_EDGES)
        self.first_hit: dict[str, int] = {}
        self.gap = [0] * (len(GAP_EDGES) + 2)  # GAP_EDGES bins, then the hit before it, then no hit
        self.uncovered = 0
        self.no_negative = 0
        self.no_positive = 0
        self.occupied: dict[str, int] = {}
        self.missed: dict[str, int] = {}
        # per camera (the one that sees the voxel, :func:`seeing_camera`): scored free voxels, false-occupied ones
        self.camera_free: dict[str, int] = {}
        self.camera_false: dict[str, int] = {}

    def add(
        self,
        pred: Tensor,
        labels: Tensor,
        mask: Tensor,
        grid: GridSpec,
        free_label: int,
        cam_to_ego: Tensor,
        negatives: Tensor,
        positives: Tensor,
        class_names: Sequence[str],
        camera_names: Sequence[str] = (),
    ) -> None:
        """One sample: ``pred``, ``labels`` ``(X, Y, Z)`` class ids, ``mask`` ``(X, Y, Z)`` bool (scored voxels),
        ``negatives`` / ``positives`` ``(P, 3)`` the training queries drawn for it (ego frame, metres),
        ``camera_names`` those of ``cam_to_ego``'s cameras (default ``cam<i>``)."""
        free = mask & (labels == free_label)
        wrong = free & (pred != free_label)
        self.scored_free += int(free.sum())
        self.false_occupied += int(wrong.sum())
        free_voxels = torch.nonzero(free)
        cams = seeing_camera(grid, cam_to_ego, free_voxels)
        is_wrong = wrong[free_voxels[:, 0], free_voxels[:, 1], free_voxels[:, 2]]
        for c in range(len(cam_to_ego)):
            name = camera_names[c] if c < len(camera_names) else f"cam{c}"
            self.camera_free[name] = self.camera_free.get(name, 0) + int((cams == c).sum())
            self.camera_false[name] = self.camera_false.get(name, 0) + int(((cams == c) & is_wrong).sum())
        occupied = mask & (labels != free_label) & (labels != 255)
        for c in labels[occupied].unique().tolist():
            name = class_names[c] if c < len(class_names) else str(c)
            here = occupied & (labels == c)
            self.occupied[name] = self.occupied.get(name, 0) + int(here.sum())
            self.missed[name] = self.missed.get(name, 0) + int((here & (pred == free_label)).sum())
        voxels = torch.nonzero(wrong)
        if len(voxels) == 0:
            return
        height = height_above_ground(labels, grid)[wrong]
        for b in torch.bucketize(height, torch.tensor(HEIGHT_EDGES[1:]), right=True).tolist():
            self.height[b] += 1
        lower = torch.tensor(grid.lower[:2])
        size = torch.tensor(grid.voxel_size[:2])
        xy = lower + (voxels[:, :2].double() + 0.5) * size
        dist = xy.norm(dim=-1)
        for b in torch.bucketize(dist, torch.tensor(DISTANCE_EDGES[1:], dtype=torch.float64), right=True).tolist():
            self.distance[b] += 1
        hits, gaps = first_hits_from_camera(labels, grid, free_label, cam_to_ego, voxels)
        for hit, gap in zip(hits, gaps, strict=True):
            key = hit if isinstance(hit, str) else (class_names[hit] if hit < len(class_names) else str(hit))
            self.first_hit[key] = self.first_hit.get(key, 0) + 1
            if gap is None:
                self.gap[-1] += 1
            elif gap == 0:
                self.gap[-2] += 1
            else:
                self.gap[sum(gap >= e for e in GAP_EDGES[1:])] += 1
        near_neg = covered(negatives, grid)[wrong]
        near_pos = covered(positives, grid)[wrong]
        self.uncovered += int((~near_neg & ~near_pos).sum())
        self.no_negative += int((~near_neg).sum())
        self.no_positive += int((~near_pos).sum())

    def shares(self) -> dict:
        """Every count as a percentage of the false-occupied voxels (their own share: of the scored free ones)."""
        n = max(self.false_occupied, 1)

        def pct(c: int) -> float:
            return round(100.0 * c / n, 2)

        def labels(edges: Sequence[float]) -> list[str]:
            inner = [f"{a:g}-{b:g} m" for a, b in zip(edges[1:], edges[2:], strict=False)]
            return [f"< {edges[1]:g} m", *inner, f">= {edges[-1]:g} m"]

        return {
            "scored_free_voxels": self.scored_free,
            "false_occupied_voxels": self.false_occupied,
            "false_occupied_pct_of_scored_free": round(100.0 * self.false_occupied / max(self.scored_free, 1), 2),
            "by_height_above_ground_pct": dict(zip(labels(HEIGHT_EDGES), map(pct, self.height), strict=True)),
            "by_distance_pct": dict(zip(labels(DISTANCE_EDGES), map(pct, self.distance), strict=True)),
            "by_first_hit_pct": {k: pct(v) for k, v in sorted(self.first_hit.items(), key=lambda kv: -kv[1])},
            "by_voxels_to_first_hit_pct": dict(
                zip(["1", "2", "3-4", ">= 5", "hit before it", NO_HIT], map(pct, self.gap), strict=True)
            ),
            "no_query_within_one_voxel_pct": pct(self.uncovered),
            "no_negative_within_one_voxel_pct": pct(self.no_negative),
            "no_positive_within_one_voxel_pct": pct(self.no_positive),
            "by_camera_pct": {k: pct(v) for k, v in self.camera_false.items()},
            "false_occupied_pct_of_scored_free_by_camera": {
                k: round(100.0 * self.camera_false[k] / n_k, 2) for k, n_k in self.camera_free.items() if n_k
            },
            "scored_occupied_voxels": sum(self.occupied.values()),
            "false_free_voxels": sum(self.missed.values()),
            "false_free_pct_by_class": {
                k: round(100.0 * self.missed[k] / n_k, 2) for k, n_k in sorted(self.occupied.items()) if n_k
            },
        }


def _checkpoint(path: Path) -> Path:
    """A run directory's ``checkpoints/last.ckpt``, or ``path`` itself (a checkpoint file)."""
    return path / "checkpoints" / "last.ckpt" if path.is_dir() else path


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m occplug_queryocc.tools.diagnose",
        description=__doc__,
        formatter_class=argparse.RawTextHelpFormatter,
    )
    parser.add_argument("run", type=Path, help="a run directory (its checkpoints/last.ckpt) or a checkpoint file")
    parser.add_argument("--batches", type=_positive, default=8, help="validation samples to diagnose (default 8)")
    parser.add_argument("--draws", type=_positive, default=4, help="query draws per sample (the epochs; default 4)")
    parser.add_argument("--supervision", default="queries", help="the query supervision's name (default queries)")
    parser.add_argument("--json", type=Path, default=None, help="also write the shares here")
    args = parser.parse_args(argv)

    from occplug.run.runner import RunError, config_from_checkpoint, data_errors, load_checkpoint, restore_run

    path = _checkpoint(args.run)
    try:
        ckpt = load_checkpoint(path)
        cfg = config_from_checkpoint(ckpt, path)
        dm, model = restore_run(cfg, ckpt, path)
        with data_errors():
            shares = _diagnose(cfg, dm, model, args)
    except (RunError, UserError, LookupError) as exc:  # LookupError: a component no installed plugin registers
        print(f"error: {path}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}", file=sys.stderr)
        return 2
    shares.update(checkpoint=str(path), samples=shares.pop("_samples"), draws=args.draws)
    print(json.dumps(shares, indent=2))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(shares, indent=2) + "\n")
    return 0


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return value


def _diagnose(cfg: dict, dm, model, args: argparse.Namespace) -> dict:
    """The tally's shares over the first ``args.batches`` validation samples (plus ``_samples``, their count)."""
    source = model.supervision[args.supervision] if args.supervision in model.supervision else None
    if source is None or not hasattr(source, "queries"):
        raise UserError(f"model.supervision has no query source '{args.supervision}' (--supervision)")
    torch.manual_seed(0)
    grid = model.grid  # the run's, parsed once by the runner
    free_label, names = model.free_label, dm.class_names
    dataset = dm.dataset("val")
    tally = Tally()
    model.eval()
    for index in range(min(args.batches, len(dataset))):
        batch = dm.collate([dataset[index]])
        with torch.inference_mode():
            pred = model.predict_occupancy(batch)[0]
        negatives, positives = [], []
        for _ in range(args.draws):
            q = source.queries(batch)
            keep = q.valid[0]
            negatives.append(q.points[0][keep & ~q.occupied[0]])
            positives.append(q.points[0][keep & q.occupied[0]])
        tally.add(
            pred,
            batch.voxel_labels[0].long(),
            batch.mask_camera[0].bool(),
            grid,
            free_label,
            batch.cam_to_ego[0].float(),
            torch.cat(negatives),
            torch.cat(positives),
            names,
            tuple(batch.camera_names),
        )
    return {**tally.shares(), "_samples": min(args.batches, len(dataset))}


if __name__ == "__main__":
    raise SystemExit(main())
