"""occplug.ceilings: readouts, the perfect-depth lift and the history headroom on hand-made cases with known answers."""

import pytest
import torch

from occplug.ceilings import (
    Scorer,
    depth_lift,
    history_headroom,
    parse_readout,
    read_voxels,
    training_prior,
)
from occplug.data import OCC3D_CLASSES
from occplug.geometry import GridSpec

FREE, CAR, ROAD = 17, 4, 11
K = len(OCC3D_CLASSES)


def test_parse_readout_names_and_errors():
    assert parse_readout("center").k == 1 and parse_readout("center").name == "center"
    r = parse_readout("vote3")
    assert (r.k, r.rule, r.name) == (3, "vote", "vote3")
    assert parse_readout("any2").name == "any2"
    for bad in ("any", "mean2", "any0", "centre"):
        with pytest.raises(ValueError, match="expected 'center'"):
            parse_readout(bad)


def test_read_voxels_any_and_vote():
    samples = torch.full((3, 1, 1, 2, 2, 2), FREE, dtype=torch.uint8)
    samples[0, 0, 0, 0, 0, 0] = CAR  # one car sample of eight
    samples[1, 0, 0, :, :, 0] = ROAD  # four road samples, four free: a tie
    samples[2, 0, 0, 0] = CAR  # four car ...
    samples[2, 0, 0, 1, 0] = ROAD  # ... two road, two free
    anyr = read_voxels(samples, "any", FREE, K)
    vote = read_voxels(samples, "vote", FREE, K)
    assert anyr[:, 0, 0].tolist() == [CAR, ROAD, CAR]
    assert vote[:, 0, 0].tolist() == [FREE, ROAD, CAR]  # the tie goes to the lower id (road 11 < free 17)
    centre = read_voxels(samples[..., :1, :1, :1], "any", FREE, K)
    assert centre[:, 0, 0].tolist() == [CAR, ROAD, CAR]


def test_scorer_matches_hand_counted_iou():
    target = torch.tensor([CAR, CAR, FREE, ROAD, FREE]).view(5, 1, 1)
    pred = torch.tensor([CAR, FREE, CAR, ROAD, FREE]).view(5, 1, 1)
    s = Scorer(OCC3D_CLASSES, FREE)
    s.update(pred, target, None)
    out = s.compute()
    # occupied: tp = 2 (car, road), fp = 1, fn = 1 -> 2 / 4
    assert out["IoU"] == pytest.approx(50.0)
    masked = Scorer(OCC3D_CLASSES, FREE)
    masked.update(pred, target, torch.tensor([True, False, False, True, True]).view(5, 1, 1))
    assert masked.compute()["IoU"] == pytest.approx(100.0)


def test_training_prior_is_the_per_voxel_mode():
    a = torch.tensor([CAR, ROAD, FREE]).view(3, 1, 1)
    b = torch.tensor([CAR, FREE, FREE]).view(3, 1, 1)
    c = torch.tensor([ROAD, ROAD, CAR]).view(3, 1, 1)
    prior, most = training_prior([a, b, c], K, FREE)
    assert prior[:, 0, 0].tolist() == [CAR, ROAD, FREE]
    assert most == CAR  # car 3, road 3: the tie goes to the lower id
    assert training_prior([c, c], K, FREE)[1] == ROAD


def _shift(x: float) -> torch.Tensor:
    pose = torch.eye(4, dtype=torch.float64)
    pose[0, 3] = x
    return pose


def test_history_headroom_on_a_hand_made_drive():
    """A 4 x 1 x 1 row of 1 m voxels; the ego moves 1 m along +x between the frames. Frame 0 observes its
    voxels 1, 2 (world 1-3 m), frame 1 its voxel 0 (world 1-2 m). Scored: every voxel.

    Frame 1: voxel 1 (world 2-3 m) is not seen now, but frame 0 saw it -> 1 earlier-only, 1 adjacent-only.
    Frame 0: nothing earlier; frame 1 sees world 1-2 m, which frame 0 sees itself -> 0 adjacent-only."""
    grid = GridSpec((0.0, 0.0, 0.0, 4.0, 1.0, 1.0), 1.0)
    observed = torch.zeros(2, 4, 1, 1, dtype=torch.bool)
    observed[0, 1:3] = True
    observed[1, 0] = True
    scored = torch.ones_like(observed)
    h = history_headroom(observed, scored, torch.stack([_shift(0.0), _shift(1.0)]), grid)
    assert (h.scored, h.observed_now, h.earlier_only, h.adjacent_only) == (8, 3, 1, 1)
    assert h.shares()["earlier_only"] == pytest.approx(12.5)
    # scoring only what is observed now leaves no room by construction (six cameras + camera mask)
    own = history_headroom(observed, observed, torch.stack([_shift(0.0), _shift(1.0)]), grid)
    assert (own.earlier_only, own.adjacent_only) == (0, 0)


def test_history_headroom_sees_through_a_rotation():
    """A quarter turn about z: frame 1's voxel at (+x) is frame 0's voxel at (+y)."""
    grid = GridSpec((-2.0, -2.0, 0.0, 2.0, 2.0, 1.0), 1.0)
    turn = torch.eye(4, dtype=torch.float64)
    turn[:2, :2] = torch.tensor([[0.0, -1.0], [1.0, 0.0]], dtype=torch.float64)
    observed = torch.zeros(2, 4, 4, 1, dtype=torch.bool)
    observed[0, 2, 3] = True  # frame 0: centre (0.5, 1.5)
    scored = torch.zeros_like(observed)
    scored[1, 3, 1] = True  # frame 1: centre (1.5, -0.5) -> world (0.5, 1.5)
    h = history_headroom(observed, scored, torch.stack([torch.eye(4, dtype=torch.float64), turn]), grid)
    assert (h.scored, h.earlier_only, h.adjacent_only) == (1, 1, 1)


def test_depth_lift_puts_a_wall_in_its_voxel_layer():
    """One camera at the origin looking along +x at a wall 5.5 m away: every lifted point lies in x in [5, 6)."""
    grid = GridSpec((0.0, -8.0, -8.0, 10.0, 8.0, 8.0), 1.0)
    h = w = 16
    intr = torch.tensor([[[8.0, 0.0, 7.5], [0.0, 8.0, 7.5], [0.0, 0.0, 1.0]]])
    cam = torch.eye(4)[None].clone()
    cam[0, :3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # OpenCV axes
    depth = torch.full((1, h, w), 5.5)
    sem = torch.full((1, h, w), CAR)
    sem[0, :, :8] = 255  # left half: sky-like, no class
    out = depth_lift(depth, sem, intr, cam, grid, 2, FREE, K)
    occupied = out != FREE
    assert int(occupied[5].sum()) >= 16  # 8 x 4 cells land in 1 m voxels of the wall
    assert not occupied[:5].any() and not occupied[6:].any()
    assert (out[occupied] == CAR).all()
    # the skipped half: points at y > 0 (image left) never appear
    ys = grid.centers()[occupied][:, 1]
    assert (ys < 0.5).all()
