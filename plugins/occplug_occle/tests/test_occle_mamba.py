"""OccLE's Dual Mamba pieces against their definitions: Hilbert serialisation, the selective scan, the blocks."""

import importlib
import itertools
import sys
import warnings

import pytest
import torch
import torch.nn.functional as F

from occplug_occle.blocks.mamba import DualMambaBlock, DualMambaUNet, MambaBlock, channel_exchange, exchange_mask
from occplug_occle.blocks.selective_scan import (
    SelectiveScanFn,
    _mamba_ssm_kernel,
    _scan_mamba_ssm,
    selective_scan,
    selective_scan_chunked,
    selective_scan_lean,
    selective_scan_ref,
)
from occplug_occle.blocks.serialization import deserialize, hilbert_curve, hilbert_permutation, serialize

#: the Dual Mamba stage grids the shipped recipes build (synthetic 32 x 32 x 8 and occle/semantickitti's
#: 256 x 256 x 32, anisotropic where z is short); the 2.1 M-voxel 256 x 256 x 32 itself takes ~8 s: left out
RECIPE_SHAPES = [(32, 32, 8), (16, 16, 8), (16, 16, 4), (8, 8, 4), (128, 128, 16), (64, 64, 8), (32, 32, 4)]
#: grids a 4-stage U-Net meets (Occ3D-like and SemanticKITTI-like sizes, their stages, odd and flat ones)
STAGE_SHAPES = [*RECIPE_SHAPES, (16, 16, 2), (8, 8, 1), (24, 40, 6), (25, 25, 5), (7, 9, 3), (5, 1, 3)]
EVEN_SHAPES = [*RECIPE_SHAPES, (16, 16, 2), (8, 8, 1), (24, 40, 6), (2, 2, 2), (12, 2, 8)]


def _steps(shape):
    xyz = hilbert_curve(shape)
    return (xyz[1:] - xyz[:-1]).abs().sum(1)


@pytest.mark.parametrize("shape", [*STAGE_SHAPES, (1, 1, 1)])
def test_hilbert_order_is_a_bijection(shape):
    n = shape[0] * shape[1] * shape[2]
    perm, inverse = hilbert_permutation(shape)
    assert perm.dtype == torch.long and perm.shape == (n,)
    assert torch.equal(perm.sort().values, torch.arange(n))
    assert torch.equal(perm[inverse], torch.arange(n)) and torch.equal(inverse[perm], torch.arange(n))
    xyz = hilbert_curve(shape)
    assert bool((xyz >= 0).all()) and bool((xyz < torch.tensor(shape)).all())
    assert torch.equal((xyz[:, 0] * shape[1] + xyz[:, 1]) * shape[2] + xyz[:, 2], perm)
    again = hilbert_permutation(shape)[0]
    assert torch.equal(again, perm) and again is not perm  # a fresh copy: callers cannot alter the cached order


def test_hilbert_steps_are_face_neighbours_on_even_shapes():
    shapes = [*EVEN_SHAPES, *itertools.product((2, 4, 6, 8), repeat=3)]
    for shape in shapes:
        assert bool((_steps(shape) == 1).all()), shape


@pytest.mark.parametrize(("shape", "share"), [((25, 25, 5), 0.98), ((7, 7, 7), 0.95), ((15, 15, 3), 0.96)])
def test_hilbert_odd_shapes_are_mostly_unit_steps(shape, share):
    steps = _steps(shape)
    assert float((steps == 1).float().mean()) >= share  # measured: 98.0 %, 95.3 %, 96.7 %
    assert int(steps.max()) <= 4


def test_serialize_round_trip_and_token_order():
    x = torch.randn(2, 3, 6, 10, 3)
    seq = serialize(x)
    assert seq.shape == (2, 180, 3)
    perm, _ = hilbert_permutation((6, 10, 3))
    xyz = hilbert_curve((6, 10, 3))
    for i in (0, 1, 77, 179):
        assert torch.equal(seq[:, i], x[:, :, xyz[i, 0], xyz[i, 1], xyz[i, 2]])
    assert torch.equal(deserialize(seq, (6, 10, 3)), x)
    assert torch.equal(serialize(deserialize(seq, (6, 10, 3))), seq)
    with pytest.raises(ValueError, match="deserialize"):
        deserialize(seq, (6, 10, 4))


def _scan_inputs(batch=2, length=37, dim=5, state=4, dtype=torch.float64, seed=0, delta_scale=1.0):
    g = torch.Generator().manual_seed(seed)

    def randn(*shape):
        return torch.randn(*shape, generator=g, dtype=dtype)

    u, B, C, z = (
        randn(batch, length, dim),
        randn(batch, length, state),
        randn(batch, length, state),
        randn(batch, length, dim),
    )
    delta = F.softplus(randn(batch, length, dim) - 1.0) * delta_scale
    A = -torch.exp(randn(dim, state))
    return u, delta, A, B, C, randn(dim), z


@pytest.mark.parametrize("within", ["steps", "segsum"])
@pytest.mark.parametrize("chunk", [1, 5, 16, 37, 64])
@pytest.mark.parametrize("skip_and_gate", [True, False])
def test_chunked_scan_equals_reference(within, chunk, skip_and_gate):
    u, delta, A, B, C, D, z = _scan_inputs()
    if not skip_and_gate:
        D = z = None
    y_ref, h_ref = selective_scan_ref(u, delta, A, B, C, D, z, return_last_state=True)
    y, h = selective_scan_chunked(
        u, delta, A, B, C, D, z, chunk_size=chunk, within_chunk=within, return_last_state=True
    )
    assert y.shape == (2, 37, 5) and h.shape == (2, 5, 4)
    assert float((y - y_ref).abs().max()) < 1e-10
    assert float((h - h_ref).abs().max()) < 1e-10


def test_scan_starts_from_a_zero_state():
    u, delta, A, B, C, D, _ = _scan_inputs(length=4)
    # h_1 = delta_1 B_1 u_1, so y_1 = delta_1 u_1 <B_1, C_1> + D u_1
    y0 = delta[:, 0] * u[:, 0] * (B[:, 0] * C[:, 0]).sum(-1, keepdim=True) + D * u[:, 0]
    for y in (selective_scan_ref(u, delta, A, B, C, D), selective_scan_chunked(u, delta, A, B, C, D, chunk_size=2)):
        assert float((y[:, 0] - y0).abs().max()) < 1e-12


@pytest.mark.parametrize("within", ["steps", "segsum"])
def test_chunked_scan_gradients_equal_reference(within):
    inputs = [t.requires_grad_() for t in _scan_inputs(length=19)]
    grads_ref = torch.autograd.grad(selective_scan_ref(*inputs).square().sum(), inputs)
    grads = torch.autograd.grad(
        selective_scan_chunked(*inputs, chunk_size=6, within_chunk=within).square().sum(), inputs
    )
    for g, g_ref in zip(grads, grads_ref, strict=True):
        assert float((g - g_ref).abs().max()) < 1e-10


@pytest.mark.parametrize(
    ("length", "chunk", "group_elements"),
    [(37, 5, None), (37, 37, None), (64, 16, None), (100, 7, 1), (100, 64, 300), (50, 200, None)],
)
@pytest.mark.parametrize("skip_and_gate", [True, False])
def test_lean_scan_gradients_equal_reference(length, chunk, group_elements, skip_and_gate):
    # the hand-written backward (adjoint by chunks; chunk sizes dividing L or not, one chunk, groups of one chunk
    # or several) against autograd through the step loop, for every input and the last state's gradient too
    inputs = list(_scan_inputs(length=length, seed=length + chunk))
    if not skip_and_gate:
        inputs[5] = inputs[6] = None
    inputs = [None if t is None else t.requires_grad_() for t in inputs]
    used = [t for t in inputs if t is not None]
    y_ref, h_ref = selective_scan_ref(*inputs, return_last_state=True)
    y, h = selective_scan_lean(*inputs, chunk_size=chunk, return_last_state=True, group_elements=group_elements)
    assert float((y - y_ref).detach().abs().max()) < 1e-10 and float((h - h_ref).detach().abs().max()) < 1e-10
    g = torch.Generator().manual_seed(1)
    w_y = torch.randn(y.shape, generator=g, dtype=y.dtype)
    w_h = torch.randn(h.shape, generator=g, dtype=h.dtype)
    grads_ref = torch.autograd.grad((y_ref * w_y).sum() + (h_ref * w_h).sum(), used, retain_graph=True)
    grads = torch.autograd.grad((y * w_y).sum() + (h * w_h).sum(), used)
    for grad, grad_ref in zip(grads, grads_ref, strict=True):
        assert grad.shape == grad_ref.shape and grad.dtype == grad_ref.dtype
        assert float((grad - grad_ref).abs().max()) < 1e-9
    # the output alone (the last state unused: its gradient arrives as None)
    grads = torch.autograd.grad((selective_scan_lean(*inputs, chunk_size=chunk) * w_y).sum(), used)
    grads_ref = torch.autograd.grad((y_ref * w_y).sum(), used)
    for grad, grad_ref in zip(grads, grads_ref, strict=True):
        assert float((grad - grad_ref).abs().max()) < 1e-9


def test_lean_scan_passes_gradcheck():
    inputs = [t.requires_grad_() for t in _scan_inputs(batch=2, length=6, dim=2, state=3)]
    assert torch.autograd.gradcheck(lambda *a: selective_scan_lean(*a, chunk_size=4), inputs)
    assert torch.autograd.gradcheck(lambda *a: selective_scan_lean(*a, chunk_size=4, return_last_state=True), inputs)
    assert torch.autograd.gradcheck(lambda *a: selective_scan_lean(*a[:5], chunk_size=2), inputs[:5])


def test_selective_scan_takes_the_lean_function_with_gradients():
    inputs = [t.requires_grad_() for t in _scan_inputs(length=20)]
    for mode in ("auto", "chunked"):
        y = selective_scan(*inputs, mode=mode, chunk_size=6)
        assert y.grad_fn is not None and "SelectiveScanFn" in type(y.grad_fn).__name__
    assert selective_scan(*inputs, mode="ref").grad_fn is not None
    assert "SelectiveScanFn" not in type(selective_scan(*inputs, mode="ref").grad_fn).__name__
    with torch.no_grad():
        y_ref = selective_scan_ref(*inputs)
        assert float((selective_scan(*inputs, chunk_size=6) - y_ref).abs().max()) < 1e-10
    # float32 inputs with a float32 A: gradients in the inputs' dtypes, close to the float64 reference
    inputs32 = [t.detach().float().requires_grad_() for t in inputs]
    grads32 = torch.autograd.grad(selective_scan(*inputs32, chunk_size=6).sum(), inputs32)
    grads = torch.autograd.grad(selective_scan_ref(*inputs).sum(), inputs)
    for grad32, grad in zip(grads32, grads, strict=True):
        assert grad32.dtype == torch.float32
        assert float((grad32.double() - grad).abs().max()) < 1e-4 * (1 + float(grad.abs().max()))
    assert issubclass(SelectiveScanFn, torch.autograd.Function)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_long_chunks_with_strong_decay_stay_finite(dtype):
    # |sum of log dA| over a chunk reaches ~1e4: exp(-cumsum) would overflow; segment sums never do
    u, delta, A, B, C, D, z = _scan_inputs(length=300, dtype=dtype, delta_scale=50.0)
    y_ref = selective_scan_ref(u, delta, A, B, C, D, z)
    tol = 1e-9 if dtype == torch.float64 else 1e-3
    for within, chunk in (("steps", 300), ("steps", 64), ("segsum", 300)):
        y = selective_scan_chunked(u, delta, A, B, C, D, z, chunk_size=chunk, within_chunk=within)
        assert bool(torch.isfinite(y).all())
        assert float((y - y_ref).abs().max()) < tol * float(y_ref.abs().max())


def test_selective_scan_dispatch_on_cpu():
    u, delta, A, B, C, D, z = _scan_inputs(length=9)
    had_mamba_ssm = "mamba_ssm" in sys.modules
    y_ref = selective_scan_ref(u, delta, A, B, C, D, z)
    assert torch.equal(selective_scan(u, delta, A, B, C, D, z, mode="ref"), y_ref)
    for mode in ("auto", "chunked"):
        assert float((selective_scan(u, delta, A, B, C, D, z, mode=mode) - y_ref).abs().max()) < 1e-10
    assert ("mamba_ssm" in sys.modules) == had_mamba_ssm  # never imported for CPU tensors
    with pytest.raises(ValueError, match="mode"):
        selective_scan(u, delta, A, B, C, mode="cuda")
    with pytest.raises(ValueError, match="must be"):
        selective_scan(u, delta[:, :-1], A, B, C)


def _fake_mamba_ssm(root, kernel_source):
    """A ``mamba_ssm`` package under ``root`` whose ``selective_scan_interface`` module is ``kernel_source``."""
    ops = root / "mamba_ssm" / "ops"
    ops.mkdir(parents=True)
    (root / "mamba_ssm" / "__init__.py").write_text("")
    (ops / "__init__.py").write_text("")
    (ops / "selective_scan_interface.py").write_text(kernel_source)
    importlib.invalidate_caches()  # the path finder may have listed root before these files existed


@pytest.fixture
def fresh_mamba_ssm(monkeypatch, tmp_path):
    """sys.path and sys.modules restored, the kernel lookup's cache cleared before and after."""
    for name in [m for m in sys.modules if m == "mamba_ssm" or m.startswith("mamba_ssm.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.syspath_prepend(str(tmp_path))
    _mamba_ssm_kernel.cache_clear()
    yield tmp_path
    _mamba_ssm_kernel.cache_clear()
    for name in [m for m in sys.modules if m == "mamba_ssm" or m.startswith("mamba_ssm.")]:
        del sys.modules[name]


def test_mamba_ssm_without_its_kernel_falls_back_with_one_warning(fresh_mamba_ssm):
    # what a mamba_ssm installed without its CUDA build looks like: the package imports, its kernel does not
    _fake_mamba_ssm(fresh_mamba_ssm, "import selective_scan_cuda_that_was_never_built\n")
    with pytest.warns(UserWarning, match="chunked scan"):
        assert _mamba_ssm_kernel() is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _mamba_ssm_kernel() is None  # cached: warned once


def test_mamba_ssm_layout_adapter_equals_the_reference(fresh_mamba_ssm):
    # a stand-in kernel with mamba_ssm's channels-first signature, computed by the reference: what the adapter
    # hands it and how it reads the result back must give the reference's (B, L, D) output and (B, D, N) state
    _fake_mamba_ssm(
        fresh_mamba_ssm,
        "from occplug_occle.blocks.selective_scan import selective_scan_ref\n"
        "def selective_scan_fn(u, delta, A, B, C, D=None, z=None, delta_bias=None, delta_softplus=False,\n"
        "                      return_last_state=False):\n"
        "    assert delta_bias is None and not delta_softplus and u.is_contiguous() and B.is_contiguous()\n"
        "    t = lambda x: None if x is None else x.transpose(1, 2)\n"
        "    out = selective_scan_ref(t(u), t(delta), A, t(B), t(C), D, t(z), return_last_state=True)\n"
        "    y = out[0].transpose(1, 2)\n"
        "    return (y, out[1]) if return_last_state else y\n",
    )
    kernel = _mamba_ssm_kernel()
    assert kernel is not None and kernel.__module__ == "mamba_ssm.ops.selective_scan_interface"
    u, delta, A, B, C, D, z = _scan_inputs(dtype=torch.float32)
    y_ref, last_ref = selective_scan_ref(u, delta, A, B, C, D, z, return_last_state=True)
    y, last = _scan_mamba_ssm(u, delta, A, B, C, D, z, True, kernel)
    assert y.shape == y_ref.shape and last.shape == last_ref.shape
    torch.testing.assert_close(y, y_ref)
    torch.testing.assert_close(last, last_ref)
    torch.testing.assert_close(
        _scan_mamba_ssm(u, delta, A, B, C, None, None, False, kernel), selective_scan_ref(u, delta, A, B, C)
    )


def _inner_sequence(block, tokens):
    x, _ = block.in_proj(tokens).chunk(2, dim=-1)
    return F.silu(block.conv1d(x.transpose(1, 2))[..., : tokens.shape[1]].transpose(1, 2))


def test_mamba_block_is_selective_and_causal():
    torch.manual_seed(0)
    block = MambaBlock(8, d_state=4)
    tokens = torch.randn(2, 24, 8)
    with torch.no_grad():
        x = _inner_sequence(block, tokens)
        delta, B, C = block.selective_parameters(x)
        delta2, B2, C2 = block.selective_parameters(_inner_sequence(block, torch.randn(2, 24, 8)))
        # the SSM parameters follow the input: along the sequence and between inputs
        for p, p2 in ((delta, delta2), (B, B2), (C, C2)):
            assert float(p.std(dim=1).mean()) > 1e-3
            assert float((p - p2).abs().max()) > 1e-2
        A = -torch.exp(block.A_log)
        y = selective_scan(x, delta, A, B, C)  # the state's part only (no skip D)
        # a time-invariant scan with the same parameters (their mean over the sequence) answers differently
        mean = [p.mean(dim=1, keepdim=True).expand_as(p) for p in (delta, B, C)]
        y_lti = selective_scan(x, mean[0], A, mean[1], mean[2])
        assert float((y - y_lti).abs().max()) > 0.2 * float(y.abs().max())
        out = block(tokens)
        changed = tokens.clone()
        changed[:, 10] += 1.0
        out2 = block(changed)
    assert out.shape == tokens.shape
    assert torch.allclose(out[:, :10], out2[:, :10], atol=1e-6)  # causal along the sequence
    assert float((out[:, 10:] - out2[:, 10:]).abs().max()) > 1e-4


def test_mamba_block_learns_a_delayed_copy():
    torch.manual_seed(0)
    block = MambaBlock(8, d_state=8)
    opt = torch.optim.Adam(block.parameters(), lr=5e-2)
    tokens = torch.randn(4, 32, 8)
    target = F.pad(tokens, (0, 0, 1, 0))[:, :-1]  # y_t = x_{t-1}: without memory of the past, mse stays ~1
    losses = []
    for _ in range(20):
        loss = F.mse_loss(block(tokens), target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.6 * losses[0]  # measured: 1.03 -> 0.46


def test_channel_exchange_swaps_every_other_channel_and_is_an_involution():
    a, b = torch.randn(2, 6, 3, 4, 2), torch.randn(2, 6, 3, 4, 2)
    a2, b2 = channel_exchange(a, b)
    assert torch.equal(a2[:, 1::2], b[:, 1::2]) and torch.equal(a2[:, ::2], a[:, ::2])
    assert torch.equal(b2[:, 1::2], a[:, 1::2]) and torch.equal(b2[:, ::2], b[:, ::2])
    assert not torch.equal(a2, a) and not torch.equal(b2, b)
    a3, b3 = channel_exchange(a2, b2)
    assert torch.equal(a3, a) and torch.equal(b3, b)
    mask = torch.tensor([True, False, False, False, False, True])
    a4, b4 = channel_exchange(a, b, mask)
    assert torch.equal(a4[:, [0, 5]], b[:, [0, 5]]) and torch.equal(a4[:, 1:5], a[:, 1:5])
    assert torch.equal(channel_exchange(a4, b4, mask)[0], a)
    assert int(exchange_mask(8, 0.25).sum()) == 2 and int(exchange_mask(7, 0.5).sum()) == 3
    assert not bool(exchange_mask(5, 0.0).any()) and bool(exchange_mask(5, 1.0).all())


def test_dual_mamba_block_shapes_and_both_inputs_reach_both_outputs():
    torch.manual_seed(0)
    block = DualMambaBlock(8, d_state=4)
    a = torch.randn(2, 8, 6, 5, 3, requires_grad=True)
    b = torch.randn(2, 8, 6, 5, 3, requires_grad=True)
    out_a, out_b = block(a, b)
    assert out_a.shape == a.shape and out_b.shape == b.shape
    for out in (out_a, out_b):
        grad_a, grad_b = torch.autograd.grad(out.square().sum(), (a, b), retain_graph=True)
        assert float(grad_a.abs().sum()) > 0 and float(grad_b.abs().sum()) > 0  # exchanged channels carry both


@pytest.mark.parametrize(
    ("shape", "bottom"),
    [
        ((32, 32, 4), [(16, 16, 2), (8, 8, 2), (4, 4, 2), (2, 2, 2)]),
        ((7, 9, 3), [(4, 5, 3), (2, 3, 3), (2, 3, 3), (2, 3, 3)]),
    ],
)
def test_dual_mamba_unet_runs_anisotropic_grids(shape, bottom):
    torch.manual_seed(0)
    net = DualMambaUNet((4, 6), 5, channels=(8, 8, 8, 16, 16), d_state=4)
    sizes = []
    for down in net.downs_a:
        down.register_forward_hook(lambda module, args, out: sizes.append(tuple(out.shape[2:])))
    a = torch.randn(1, 4, *shape, requires_grad=True)
    b = torch.randn(1, 6, *shape, requires_grad=True)
    out = net(a, b)
    assert out.shape == (1, 5, *shape)
    assert sizes == bottom  # four down stages; stride 1 along an axis once it is short
    out.square().mean().backward()
    assert float(a.grad.abs().sum()) > 0 and float(b.grad.abs().sum()) > 0


def test_a_grid_serialised_first_under_inference_mode_still_trains():
    """The Hilbert order is cached per shape; a first call under inference_mode (a benchmark, predict) must not
    leave an inference tensor that a later training step would save for backward."""
    shape = (3, 5, 7)  # a shape no other test serialises first
    with torch.inference_mode():
        serialize(torch.randn(1, 2, *shape))
    x = torch.randn(1, 2, *shape, requires_grad=True)
    deserialize(serialize(x) * 2, shape).sum().backward()
    assert torch.equal(x.grad, torch.full_like(x, 2.0))


def _unet_value_and_gradients(checkpoint, scan):
    """A float64 Dual Mamba U-Net (fixed weights) on fixed grids: its output and the gradients of a loss with
    respect to both inputs and every parameter."""
    torch.manual_seed(0)
    net = DualMambaUNet((3, 5), 4, channels=(6, 8), d_state=3, chunk_size=4, scan=scan, checkpoint=checkpoint)
    net = net.double()
    gen = torch.Generator().manual_seed(1)
    a = torch.randn(2, 3, 5, 4, 3, dtype=torch.float64, generator=gen, requires_grad=True)
    b = torch.randn(2, 5, 5, 4, 3, dtype=torch.float64, generator=gen, requires_grad=True)
    out = net(a, b)
    weights = torch.randn(out.shape, dtype=torch.float64, generator=gen)
    inputs = [a, b, *net.parameters()]
    grads = torch.autograd.grad((out * weights).sum(), inputs)
    return out.detach(), dict(zip(["a", "b", *(n for n, _ in net.named_parameters())], grads, strict=True))


@pytest.mark.parametrize("scan", ["chunked", "ref"])
def test_checkpointed_dual_mamba_equals_the_step_loop_in_value_and_gradient(scan):
    """``checkpoint=True`` (mixers recomputed in backward, chunked or step-loop scan) against the plain U-Net on
    the step-loop reference scan (``selective_scan_ref``), float64: the same output and the same gradient of
    both inputs and every parameter."""
    ref_out, ref_grads = _unet_value_and_gradients(checkpoint=False, scan="ref")
    out, grads = _unet_value_and_gradients(checkpoint=True, scan=scan)
    torch.testing.assert_close(out, ref_out, rtol=0, atol=1e-10)
    assert grads.keys() == ref_grads.keys()
    for name, grad in grads.items():
        torch.testing.assert_close(grad, ref_grads[name], rtol=0, atol=1e-10, msg=name)
        assert float(ref_grads[name].abs().sum()) > 0, name  # every parameter is reached


def test_checkpointed_dual_mamba_block_keeps_only_its_mixer_inputs_for_backward():
    """With ``checkpoint`` a dual block keeps for backward what its mixers take in, not what they compute: of
    the bytes autograd saves during the forward, the checkpointed block saves under a third (here the mixers'
    ``(B, L, 2 C)`` intermediates are most of the plain block's)."""
    from occplug.run.memory import SavedTensorProfile

    saved = {}
    for checkpoint in (False, True):
        torch.manual_seed(0)
        block = DualMambaBlock(8, d_state=4, checkpoint=checkpoint)
        a = torch.randn(1, 8, 8, 8, 4, requires_grad=True)
        b = torch.randn(1, 8, 8, 8, 4, requires_grad=True)
        with SavedTensorProfile(block) as profile:
            out_a, out_b = block(a, b)
        saved[checkpoint] = profile.total
        (out_a.sum() + out_b.sum()).backward()  # the recomputation runs and reaches both inputs
        assert float(a.grad.abs().sum()) > 0 and float(b.grad.abs().sum()) > 0
    assert 0 < saved[True] < saved[False] / 3, saved


def test_checkpoint_is_off_without_gradients():
    """Under ``no_grad`` (validation, prediction) a checkpointed block runs as a plain one: the same output."""
    torch.manual_seed(0)
    block = DualMambaBlock(8, d_state=4, checkpoint=True)
    a, b = torch.randn(1, 8, 4, 4, 2), torch.randn(1, 8, 4, 4, 2)
    with torch.no_grad():
        out = block(a, b)
    block.checkpoint = False
    with torch.no_grad():
        plain = block(a, b)
    assert all(torch.equal(x, y) for x, y in zip(out, plain, strict=True))
