"""OccLE on CUDA equals OccLE on the CPU (the pure-PyTorch reference). Skipped without a GPU."""

import pytest
import torch

from occplug.run import runner
from occplug_occle.blocks.selective_scan import _mamba_ssm_kernel, selective_scan, selective_scan_ref

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]

SMALL = ["grid.range=[0.0,-6.4,-1.0,12.8,6.4,5.4]", "model.scene.mamba_channels=[16,24]"]


def test_chunked_scan_on_cuda_equals_the_cpu_reference_in_float64():
    g = torch.Generator().manual_seed(0)
    u, B, C, z = (torch.randn(2, 300, s, generator=g, dtype=torch.float64) for s in (6, 4, 4, 6))
    delta = torch.nn.functional.softplus(torch.randn(2, 300, 6, generator=g, dtype=torch.float64) - 1)
    A, D = -torch.exp(torch.randn(6, 4, generator=g, dtype=torch.float64)), torch.randn(6, dtype=torch.float64)
    y_ref = selective_scan_ref(u, delta, A, B, C, D, z)
    moved = [t.cuda() for t in (u, delta, A, B, C, D, z)]
    for mode in ("ref", "chunked"):
        y = selective_scan(*moved, mode=mode).cpu()
        assert float((y - y_ref).abs().max()) < 1e-10, mode


def test_mamba_ssm_kernel_equals_the_reference_forward_and_backward(monkeypatch):
    """``auto`` on CUDA float32 dispatches to ``mamba_ssm``'s kernel: its output, last state and input gradients
    equal the step-loop reference in float64 (the kernel computes in float32)."""
    if _mamba_ssm_kernel() is None:
        pytest.skip("mamba_ssm's scan kernel does not load here")

    def not_this(*args, **kwargs):
        raise AssertionError("auto fell back to the pure-PyTorch scan")

    g = torch.Generator().manual_seed(0)
    u, B, C, z = (torch.randn(2, 300, s, generator=g, dtype=torch.float64) for s in (6, 4, 4, 6))
    delta = torch.nn.functional.softplus(torch.randn(2, 300, 6, generator=g, dtype=torch.float64) - 1)
    A, D = -torch.exp(torch.randn(6, 4, generator=g, dtype=torch.float64)), torch.randn(6, dtype=torch.float64)
    ref_in = [t.clone().requires_grad_() for t in (u, delta, A, B, C, D, z)]
    y_ref, last_ref = selective_scan_ref(*ref_in, return_last_state=True)
    kernel_in = [t.float().cuda().requires_grad_() for t in (u, delta, A, B, C, D, z)]
    for name in ("selective_scan_lean", "selective_scan_chunked", "selective_scan_ref"):
        monkeypatch.setattr(f"occplug_occle.blocks.selective_scan.{name}", not_this)
    y, last = selective_scan(*kernel_in, mode="auto", return_last_state=True)
    monkeypatch.undo()
    scale = float(y_ref.abs().max())
    assert float((y.double().cpu() - y_ref).abs().max()) < 1e-4 * scale
    assert float((last.double().cpu() - last_ref).abs().max()) < 1e-4 * float(last_ref.abs().max())
    w = torch.randn(y_ref.shape, generator=g, dtype=torch.float64)
    (y_ref * w).sum().backward()
    (y * w.float().cuda()).sum().backward()
    for name, a, b in zip("u delta A B C D z".split(), ref_in, kernel_in, strict=True):
        err = float((b.grad.double().cpu() - a.grad).abs().max())
        assert err < 1e-3 * float(a.grad.abs().max()), name


def test_model_on_cuda_matches_cpu_and_backpropagates(monkeypatch):
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", False)  # TF32 convs differ from the CPU by ~1e-3
    torch.manual_seed(0)
    cfg = runner.load_config(["occle/base", "occplug/trainer/debug"], ["data.preset=tiny", *SMALL])
    dm, model = runner.build_run(cfg)
    data = dm.dataset("val")
    batch = dm.collate([data[i] for i in range(2)])
    model.eval()
    with torch.no_grad():
        cpu = model.logits_on_grid(model(batch), model.occupancy_head)
        model.cuda()
        gpu = model.logits_on_grid(model(batch.to("cuda")), model.occupancy_head).cpu()
    torch.testing.assert_close(gpu, cpu, rtol=1e-3, atol=1e-4)
    assert float((gpu.argmax(1) == cpu.argmax(1)).float().mean()) > 0.999
    model.train()
    losses = model.losses(batch.to("cuda"), model(batch.to("cuda")))
    total = torch.stack(list(losses.values())).sum()
    total.backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert bool(torch.isfinite(total)) and grads and all(g.is_cuda and bool(torch.isfinite(g).all()) for g in grads)
