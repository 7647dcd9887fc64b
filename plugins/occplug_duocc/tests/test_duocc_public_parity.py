"""occplug's DuOcc modules against the public code's, from committed figures (``fixtures/public_parity/``).

Each fixture holds seeded random inputs, the public module's seeded random weights (norm statistics included) and
its outputs, written once by ``python -m occplug_duocc.tools.public_parity MIRROR`` from a local copy of the public
code; no public code is needed here. Each case maps the weights (:mod:`occplug_duocc.tools.public_weights`), runs
occplug's module under the ``duocc/code_recipe`` switches and compares (:mod:`occplug_duocc.tools.public_parity_cases`).
"""

import pytest
import torch

from occplug_duocc.tools.public_parity_cases import CASES, FIXTURE_DIR, FIXTURE_OF

TOLERANCE = 1e-5


def _fixture(case):
    return torch.load(FIXTURE_DIR / f"{FIXTURE_OF[case]}.pt", weights_only=True)


@pytest.mark.parametrize("case", sorted(CASES))
def test_occplug_matches_the_public_module(case):
    fixture = _fixture(case)
    assert set(fixture) == {"inputs", "public_state_dict", "public_outputs"}
    diffs = CASES[case](fixture)
    print(case, {k: f"{v:.2e}" for k, v in diffs.items()})
    assert diffs and all(v <= TOLERANCE for v in diffs.values()), diffs


def test_the_fixtures_are_small_tensors_only_and_not_degenerate():
    total = 0
    for name in sorted(set(FIXTURE_OF.values())):
        path = FIXTURE_DIR / f"{name}.pt"
        total += path.stat().st_size
        fixture = torch.load(path, weights_only=True)
        for part in fixture.values():
            assert all(isinstance(v, torch.Tensor) for v in part.values())
        for out in fixture["public_outputs"].values():  # something to compare: finite, not constant
            assert torch.isfinite(out).all() and float(out.double().std()) > 1e-3
    assert total < 2 * 1024 * 1024


def test_a_broken_mapping_or_a_dropped_switch_fails():
    """The comparison can fail: a transposed kernel, a permuted weight row, a switch left at its default."""
    import occplug_duocc.tools.public_parity_cases as cases
    import occplug_duocc.tools.public_weights as weights

    fixture = _fixture("refinenet")
    swapped = dict(fixture["public_state_dict"])
    w = swapped["conv2.weight"]
    swapped["conv2.weight"] = w.transpose(2, 4)  # the kernel read as (x, y, z) instead of (z, y, x)
    assert cases.refinenet({**fixture, "public_state_dict": swapped})["refined"] > 1e-3
    fixture = _fixture("v2q")
    real = weights.map_v2q

    def head_major(sd, heads, points):  # the point-major weight rows left unpermuted
        out = real(sd, heads, points)
        out["attn.weight"], out["attn.bias"] = sd["voxel_weights_fc.weight"], sd["voxel_weights_fc.bias"]
        return out

    cases.map_v2q = head_major
    try:
        assert cases.v2q(fixture)["queries"] > 1e-3
    finally:
        cases.map_v2q = real
    fixture = _fixture("dqa")
    original = cases.DynamicQueryAggregation
    cases.DynamicQueryAggregation = lambda *a, **kw: original(*a, **{**kw, "outside_boxes": "skip"})
    try:
        assert cases.dqa(fixture)["volume"] > 1e-3  # a box off the grid writes its face slab in the code
    finally:
        cases.DynamicQueryAggregation = original
