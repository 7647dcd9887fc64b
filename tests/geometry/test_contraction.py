"""Contracted grids: the contraction itself, GridSpec indexing/normalising/centres, sample_volume, configs."""

from __future__ import annotations

import pytest
import torch

from occplug.geometry import Contraction, GridSpec, contract, sample_volume, uncontract

# Half-range R = 80 m, near = 40 m, kappa = 0.5: near = kappa * R, so the near field is metric (0.8 m voxels).
CGRID = GridSpec(
    range=(-80, -80, -1, 80, 80, 5.4), voxel_size=(0.8, 0.8, 0.4), contraction={"near": 40.0, "kappa": 0.5}
)
METRIC = GridSpec(range=(-80, -80, -1, 80, 80, 5.4), voxel_size=(0.8, 0.8, 0.4))


def test_contract_known_values() -> None:
    x = torch.tensor([0.0, 20.0, 40.0, 80.0, -160.0, 1000.0], dtype=torch.float64)
    # near 40, kappa 0.5: linear 0.5 x / 40 inside, 1 - 0.5 / (|x| / 40) outside
    expected = torch.tensor([0.0, 0.25, 0.5, 0.75, -0.875, 1 - 0.5 / 25], dtype=torch.float64)
    torch.testing.assert_close(contract(x, 40.0, 0.5), expected, atol=0, rtol=1e-15)


@pytest.mark.parametrize("kappa", [0.2, 0.5, 0.9])
def test_contract_is_continuous_monotone_bounded_and_inverts_exactly(kappa: float) -> None:
    x = torch.linspace(-5000.0, 5000.0, 200001, dtype=torch.float64)
    y = contract(x, 30.0, kappa)
    assert (y.diff() > 0).all(), "strictly increasing"
    assert y.abs().max() < 1.0
    # continuity at the near-field edge: both pieces meet at kappa
    eps = torch.tensor([30.0 - 1e-9, 30.0 + 1e-9], dtype=torch.float64)
    assert (contract(eps, 30.0, kappa) - kappa).abs().max() < 1e-9
    torch.testing.assert_close(uncontract(y, 30.0, kappa), x, atol=1e-9, rtol=1e-12)


def test_grid_contraction_known_values() -> None:
    # Centre 0, R = 80: contracted x' = 80 * contract(x, 40, 0.5); cell = floor((x' + 80) / 0.8).
    pts = torch.tensor(
        [[0.1, 0.1, 0.0], [39.9, 0.1, 0.0], [80.0, 0.1, 0.0], [1000.0, -1000.0, 0.0]], dtype=torch.float64
    )
    idx = CGRID.coord_to_index(pts)
    # x = 39.9 -> x' = 39.9 (metric near field) -> cell 149; x = 80 -> x' = 60 -> cell 175;
    # x = 1000 -> x' = 80 * 0.98 = 78.4 -> cell 198; y = -1000 -> y' = -78.4 -> cell 1
    assert idx.tolist() == [[100, 100, 2], [149, 100, 2], [175, 100, 2], [198, 1, 2]]
    # voxel centres: near-field cells are metric, far cells spread out
    c = CGRID.index_to_coord(torch.tensor([[100, 100, 0], [174, 0, 0]]))
    torch.testing.assert_close(c[0], torch.tensor([0.4, 0.4, -0.8]))
    # cell 174 centre x' = 59.6 -> phi = 1 / (1 - 59.6 / 80) ... x = 40 * 0.5 / (1 - 0.745) = 78.4313...
    assert abs(float(c[1, 0]) - 40 * 0.5 / (1 - 59.6 / 80)) < 1e-4
    assert abs(float(c[1, 1]) + 40 * 0.5 / (1 - 79.6 / 80)) < 1e-2  # y cell 0: x' = -79.6 -> -5000 m
    torch.testing.assert_close(CGRID.normalize(pts)[:, 0], contract(pts[:, 0], 40.0, 0.5))


def test_far_points_land_in_border_cells_never_out_of_bounds() -> None:
    far = torch.tensor([[1e3, 0.0, 1.0], [1e6, 1e6, 1.0], [-1e9, 5.0, 1.0], [1e30, -1e30, 1.0]], dtype=torch.float64)
    idx = CGRID.coord_to_index(far)
    assert CGRID.index_in_bounds(idx).all() and CGRID.contains(far).all()
    assert idx[1:, 0].tolist() == [199, 0, 199] and idx[3, 1] == 0
    # z stays linear: a point above the range is outside
    assert not CGRID.contains(torch.tensor([1e3, 0.0, 9.0])) and not CGRID.index_in_bounds(
        CGRID.coord_to_index(torch.tensor([1e3, 0.0, 9.0]))
    )


def test_contracted_index_centre_round_trip_and_centers_agree() -> None:
    idx = torch.stack(
        torch.meshgrid(torch.arange(200), torch.tensor([0, 7, 100, 199]), torch.tensor([0, 15]), indexing="ij"), -1
    )
    assert torch.equal(CGRID.coord_to_index(CGRID.index_to_coord(idx)), idx)
    centers = CGRID.centers()
    assert centers.shape == (200, 200, 16, 3)
    torch.testing.assert_close(centers[idx[..., 0], idx[..., 1], idx[..., 2]], CGRID.index_to_coord(idx))
    # float64 round trip of the coordinate warp
    pts = torch.rand(1000, 3, dtype=torch.float64) * 2000 - 1000
    torch.testing.assert_close(CGRID.uncontract_coords(CGRID.contract_coords(pts)), pts, atol=1e-9, rtol=1e-12)
    # centres are symmetric and increasing along x
    xs = centers[:, 0, 0, 0].double()
    assert (xs.diff() > 0).all() and torch.allclose(xs, -xs.flip(0), atol=1e-3)


def test_uncontracted_grid_is_unchanged_and_config_round_trips() -> None:
    assert METRIC.contraction is None and not METRIC.is_contracted
    assert repr(METRIC) == "GridSpec(range=(-80.0, -80.0, -1.0, 80.0, 80.0, 5.4), voxel_size=(0.8, 0.8, 0.4))"
    assert METRIC.to_dict() == {"range": [-80.0, -80.0, -1.0, 80.0, 80.0, 5.4], "voxel_size": [0.8, 0.8, 0.4]}
    pts = torch.randn(500, 3) * 50
    lower, size = torch.tensor(METRIC.lower, dtype=torch.float64), torch.tensor(METRIC.voxel_size, dtype=torch.float64)
    assert torch.equal(METRIC.coord_to_index(pts), torch.floor((pts.double() - lower) / size).long())
    assert torch.equal(
        METRIC.normalize(pts), (pts - lower.float()) / (torch.tensor(METRIC.upper) - lower.float()) * 2 - 1
    )
    assert GridSpec.from_config(METRIC.to_dict()) == METRIC
    cfg = CGRID.to_dict()
    assert cfg["contraction"] == {"near": [40.0, 40.0], "kappa": 0.5}
    back = GridSpec.from_config(cfg)
    assert back == CGRID and back != METRIC and hash(back) == hash(CGRID) and "contraction" in repr(back)


def test_contraction_config_errors_are_one_line() -> None:
    with pytest.raises(ValueError, match="kappa must lie in"):
        GridSpec(range=(-1, -1, -1, 1, 1, 1), voxel_size=0.5, contraction={"near": 1.0, "kappa": 1.0})
    with pytest.raises(ValueError, match="near must be a positive"):
        Contraction(near=[1.0, -2.0])
    with pytest.raises(ValueError, match="mapping"):
        GridSpec.from_config(
            {"range": [-1, -1, -1, 1, 1, 1], "voxel_size": 0.5, "contraction": {"near": 1, "kapa": 0.5}}
        )


def test_sample_volume_on_a_contracted_grid_reads_the_metric_grid() -> None:
    # A volume whose value is the contracted x coordinate' of each cell centre is linear in contracted space, so
    # sampling it at any metric point returns that point's contracted x' exactly (inside the outer half-cells).
    grid = GridSpec(
        range=(-8, -8, 0, 8, 8, 2), voxel_size=(1.0, 1.0, 1.0), contraction={"near": (4.0, 2.0), "kappa": 0.5}
    )
    centers = grid.centers().double()
    xc = grid.contract_coords(centers)[..., 0].float()
    volume = xc[None, None]  # (1, 1, X, Y, Z)
    metric = GridSpec(range=(-20, -20, 0, 20, 20, 2), voxel_size=0.4)
    pts = metric.centers().reshape(1, -1, 3)
    pts[..., 2] = 1.0  # between the two z centres (0.5, 1.5): no blending with the zero padding in z
    read = sample_volume(volume, grid, pts)[0, :, 0]
    warped = grid.contract_coords(pts[0].double())
    want = warped[:, 0]
    inner = (warped[:, :2].abs() < 7.5).all(-1)  # beyond the outermost cell centres grid_sample blends with zeros
    assert inner.float().mean() > 0.5
    torch.testing.assert_close(read[inner].double(), want[inner], atol=1e-5, rtol=0)
    # BEV: the same along x on a (B, C, X, Y) map, whatever the height
    bev = volume[..., 0]
    read_bev = sample_volume(bev, grid, pts + torch.tensor([0.0, 0.0, 100.0]))[0, :, 0]
    torch.testing.assert_close(read_bev[inner].double(), want[inner], atol=1e-5, rtol=0)
