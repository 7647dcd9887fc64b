"""QueryOcc's lift with other depth nets (true depth in its own bins, the calibration encoding) and the temporal
window at a scene's ends (no clamped frame counted as t +- 1)."""

import csv
import dataclasses
import math
from pathlib import Path

import pytest
import torch

from occplug.components import CameraAwareDepthNet, OracleDepthNet
from occplug.data.synthetic import preset
from occplug.geometry import GridSpec
from occplug.testing import make_tiny_batch, run_config, tiny_context
from occplug_queryocc import LiftContractSplat, log_linear_depths, supervision_points
from occplug_queryocc.supervision import QuerySupervision, sky_rays
from occplug_queryocc.supervision.render_points import sample_rays

FREE = 17


def window_batch():
    """Frames 0 and 1 of the tiny world's first scene with the frames at -1 and +1: frame 0's -1 is clamped to
    frame 0 itself (the data's rule at a scene's start), frame 1's is frame 0."""
    return make_tiny_batch(2, adjacent_offsets=[-1, 1], pseudo_labels={"preset": "default", "sky_as_free": True})


def test_the_clamped_frame_at_a_scene_start_is_left_out_of_the_window():
    batch = window_batch()
    assert batch.adjacent[-1].token[0] == batch.token[0]  # clamped: the data hands in the current frame again
    assert batch.adjacent[-1].token[1] != batch.token[1]
    (first, _), (second, second_t) = supervision_points(batch, "pseudo", [-1], 255, pixel_stride=2)
    assert len(first) == 0  # no repeated frame passed off as t - 1
    assert len(second) > 0 and bool((second_t < 0).all())
    window = supervision_points(batch, "pseudo", [-1, 0, 1], 255, pixel_stride=2)
    alone = supervision_points(batch, "pseudo", [0, 1], 255, pixel_stride=2)
    # sample 0 at the scene's start: its window is exactly the current and the next frame
    assert torch.equal(window[0][0].points, alone[0][0].points) and torch.equal(window[0][1], alone[0][1])
    assert len(window[1][0]) > len(alone[1][0])  # sample 1 has a real previous frame
    (sky_first, _), (sky_second, _) = sky_rays(batch, [-1], FREE, pixel_stride=2)
    assert len(sky_first) == 0 and len(sky_second) > 0


def test_the_rendering_rival_draws_no_ray_from_a_clamped_frame():
    batch = window_batch()
    rays = sample_rays(batch, [-1], 32, 4, 1.0, 40.0, 255, pixel_stride=2, sky_rays=8, free_label=FREE)
    assert not bool(rays.valid[0].any())  # sample 0 has no previous frame: placeholders only, in no loss
    assert bool(rays.valid[1].all()) and bool((rays.times[1] < 0).all())


def test_query_supervision_at_a_scene_start_gives_only_real_times():
    batch = window_batch()
    source = QuerySupervision(frame_offsets=[-1, 0, 1], points_per_sample=256, pixel_stride=2)
    torch.manual_seed(0)
    q = source.queries(batch)
    dt = float(batch.adjacent[1].timestamp[0] - batch.timestamp[0])
    assert dt > 0
    times = q.times[0].unique()
    assert set(times.tolist()) <= {0.0, dt}  # no query at t - 1 for the scene's first frame
    assert bool((q.times[1] < 0).any())  # the second frame's previous frame is real


def test_oracle_depth_lifts_onto_the_true_depth_in_the_log_linear_bins():
    batch = make_tiny_batch(1)
    grid = GridSpec.from_config({"range": [-20.0, -20.0, -1.0, 20.0, 20.0, 5.4], "voxel_size": [1.0, 1.0, 6.4]})
    vt = LiftContractSplat(
        8,
        4,
        grid,
        out_channels=4,
        num_bins=16,
        depth_net={"type": "oracle_depth", "hidden": 0},
        context=tiny_context(grid),
    )
    assert isinstance(vt.depth_net, OracleDepthNet)
    centers = log_linear_depths(16, 1.0, 60.0)
    assert torch.equal(vt.depth_net.centers, centers)  # the lift handed in its own bins, not 1 m bins
    h, w = batch.images.shape[-2] // 4, batch.images.shape[-1] // 4
    out = vt(torch.randn(1, batch.images.shape[1], 8, h, w), batch)
    z = batch.depth[..., 2::4, 2::4]
    gaps = centers[1:] - centers[:-1]
    valid = (z >= centers[0] - gaps[0] / 2) & (z < centers[-1] + gaps[-1] / 2)
    assert valid.any()
    nearest = (z[valid][:, None] - centers[None]).abs().argmin(-1)
    assert torch.equal(out.depth_probs.argmax(2)[valid], nearest)
    assert (out.depth_probs.amax(2)[valid] == 1.0).all()  # one-hot: every feature on its surface


def test_camera_aware_reads_the_calibration_and_plain_does_not():
    batch = make_tiny_batch(1)
    grid = preset("tiny").grid
    features = torch.randn(1, batch.images.shape[1], 8, batch.images.shape[-2] // 4, batch.images.shape[-1] // 4)
    wide = dataclasses.replace(batch, intrinsics=batch.intrinsics.clone())
    wide.intrinsics[..., 0, 0] *= 0.5  # a wider field of view: half the focal length
    for kind, reads in (("camera_aware", True), ("plain", False)):
        torch.manual_seed(0)
        vt = LiftContractSplat(
            8, 4, grid, out_channels=4, num_bins=8, depth_net={"type": kind}, context=tiny_context(grid)
        ).eval()
        assert isinstance(vt.depth_net, CameraAwareDepthNet) == reads
        a = vt.depth_net(features, batch)
        b = vt.depth_net(features, wide)
        assert (not torch.allclose(a.depth_logits, b.depth_logits)) == reads, kind


@pytest.mark.parametrize("config", ["queryocc/perfect_depth", "queryocc/camera_aware"])
def test_the_lift_variants_train_one_step_on_tiny(config: str, tmp_path: Path):
    metrics = run_config(
        config,
        run_dir=tmp_path,
        overrides=[
            "trainer.max_steps=1",
            "trainer.log_every_n_steps=1",
            "data.batch_size=1",
            "model.supervision.queries.points_per_sample=64",
        ],
    )
    assert 0.0 <= metrics["IoU"] <= 100.0
    rows = list(csv.DictReader((tmp_path / "logs" / "version_0" / "metrics.csv").open()))
    losses = [float(r["train/loss"]) for r in rows if r.get("train/loss")]
    assert losses and all(math.isfinite(v) and v > 0 for v in losses)
    resolved = (tmp_path / "config.yaml").read_text()
    assert ("oracle_depth" if "perfect" in config else "camera_aware") in resolved


def test_depth_bins_report_measures_shares_and_gaps():
    from occplug_queryocc.tools import depth_bins

    z = torch.zeros(1, 2, 2, 5)
    z[0, 0, 0] = torch.tensor([5.0, 15.0, 25.0, 45.0, 0.0])  # camera 0: four surfaces, one sky pixel
    z[0, 1, 0] = torch.tensor([2.0, 3.0, 4.0, 6.0, 8.0])
    report = depth_bins.depth_report(z, ["a", "b"], [20.0, 40.0])
    assert report["a"]["with_surface"] == pytest.approx(40.0)  # 4 of 10 pixels
    assert report["a"]["beyond"] == {"20": pytest.approx(50.0), "40": pytest.approx(25.0)}
    assert report["rig"]["beyond"]["20"] == pytest.approx(100.0 * 2 / 9)
    bins = depth_bins.bins_report([(32, 1.0, 80.0)], p99=40.0)["32:1:80"]
    c = log_linear_depths(32, 1.0, 80.0).double()
    assert bins["bins_beyond_p99"] == pytest.approx(100.0 * float((c > 40.0).double().mean()))
    i = int(torch.searchsorted(c, 20.0))
    assert bins["gap_at"]["20"] == pytest.approx(float(c[i + 1] - c[i]))
    with pytest.raises(ValueError, match="D:near:far"):
        depth_bins.parse_bins("32:1")
    assert depth_bins.main(["--bins", "32:80:1"]) == 2  # near >= far: one error line, nothing read


def test_the_depth_bins_tool_is_a_well_behaved_tool(tmp_path):
    from occplug.testing import check_tool_help, check_tool_main_guard, check_tools_import_quietly

    module = "occplug_queryocc.tools.depth_bins"
    check_tool_help(module, tmp_path)
    check_tools_import_quietly([module], tmp_path)
    check_tool_main_guard(module)
