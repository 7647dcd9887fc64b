"""DuOcc on CUDA equals DuOcc on the CPU over a streamed sequence. Skipped without a GPU."""

import pytest
import torch

from occplug.run import runner
from occplug.streams import set_stream_stage

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]

SMALL = ["grid.range=[-8.0,-8.0,-1.0,8.0,8.0,5.4]", "model.encoder.out_channels=16", "model.encoder.width=16"]


@pytest.mark.parametrize("config", ["stream_agg", "full"])
def test_streamed_frames_on_cuda_match_cpu_and_backpropagate(config, monkeypatch):
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", False)  # TF32 convs differ from the CPU by ~1e-3
    torch.manual_seed(0)
    cfg = runner.load_config([f"duocc/{config}", "occplug/trainer/debug"], ["data.preset=tiny", *SMALL])
    dm, model = runner.build_run(cfg)
    data = dm.dataset("val")
    frames = [dm.collate([data[i]]) for i in range(2)]  # one val scene in order: the history is carried
    model.eval()

    def stream(device):
        set_stream_stage(model, "val")
        model.scene.history.clear("val")  # each device streams the scene from its start
        model.to(device)
        with torch.no_grad():
            return [model.logits_on_grid(model(f.to(device)), model.occupancy_head).cpu() for f in frames]

    cpu, gpu = stream("cpu"), stream("cuda")
    for a, b in zip(cpu, gpu, strict=True):
        torch.testing.assert_close(b, a, rtol=1e-3, atol=1e-3)
        assert float((a.argmax(1) == b.argmax(1)).float().mean()) > 0.999
    model.train()
    set_stream_stage(model, "train")
    batch = dm.collate([dm.dataset("train")[i] for i in (0, 3)]).to("cuda")
    losses = model.losses(batch, model(batch))
    total = torch.stack(list(losses.values())).sum()
    total.backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert bool(torch.isfinite(total)) and grads and all(g.is_cuda and bool(torch.isfinite(g).all()) for g in grads)
