"""The public code's occupancy CE class weights (5 / ln f, free halved) and occplug_duocc.tools.fit_class_weights."""

import pytest
import torch
import yaml

from occplug.data import class_counts, inverse_log_weights
from occplug.run import runner
from occplug_duocc.tools import fit_class_weights
from occplug_duocc.tools.class_weights import duocc_class_weights

# fmt: off
#: Occ3D-nuScenes voxels per class (others .. vegetation, free): the ``nusc_class_frequencies`` of the
#: Occ3D-based code bases DuOcc's config reads.
NUSC_COUNTS = [944004, 1897170, 152386, 2391677, 16957802, 724139, 189027, 2074468, 413451, 2384460, 5916653,
               175883646, 4275424, 51393615, 61411620, 105975596, 116424404, 1892500630]
#: the weights the code notes (§4) list for those counts, in the same order.
CODE_WEIGHTS = [0.363, 0.346, 0.419, 0.340, 0.300, 0.371, 0.412, 0.344, 0.387, 0.340, 0.321, 0.263, 0.327, 0.282,
                0.279, 0.271, 0.269, 0.117]
# fmt: on


def test_the_nuscenes_counts_give_the_code_notes_weights():
    w = duocc_class_weights(NUSC_COUNTS)
    assert torch.allclose(w, torch.tensor(CODE_WEIGHTS), atol=5e-4)


def test_free_is_halved_and_an_absent_class_takes_the_largest_weight():
    w = duocc_class_weights([0, 100, 10_000, 1_000_000], free_index=-1)
    assert w[1] == pytest.approx(5 / torch.log(torch.tensor(100.0, dtype=torch.float64)).item(), rel=1e-6)
    assert w[0] == w[1] == w.max()  # absent: at least as rare as the rarest seen
    assert w[3] == pytest.approx(0.5 * 5 / 13.815510557964274, rel=1e-6)  # ln(1e6), halved
    first = duocc_class_weights([1_000_000, 100, 10_000], free_index=0)  # free elsewhere than last
    assert first[0] == pytest.approx(w[3].item()) and first[1] == pytest.approx(w[1].item())
    with pytest.raises(ValueError, match="no class is counted"):
        duocc_class_weights([0, 1, 0])


def test_inverse_log_weights_refuses_normalised_frequencies():
    assert torch.allclose(inverse_log_weights([10.0, 100.0], scale=2.0), torch.tensor([2 / 2.302585, 2 / 4.605170]))
    with pytest.raises(ValueError, match="raw class counts"):
        inverse_log_weights([0.7, 0.3])


def test_fit_class_weights_writes_the_weights_of_the_training_split(tmp_path, capsys):
    out = tmp_path / "weights.yaml"
    assert fit_class_weights.main(["-c", "duocc/stream_agg", "data.preset=tiny", "--out", str(out)]) == 0
    written = yaml.safe_load(out.read_text())["model"]["supervision"]["occupancy"]["class_weights"]
    cfg = runner.load_config(["duocc/stream_agg", str(out)], ["data.preset=tiny"])
    dm = runner.build_datamodule(cfg)
    counts = class_counts(dm.dataset("train"), len(dm.class_names))
    expected = duocc_class_weights(counts.counts, free_index=list(dm.class_names).index("free"))
    assert torch.allclose(torch.tensor(written), expected, atol=5e-4)
    assert cfg["model"]["supervision"]["occupancy"]["class_weights"] == written
    # a user mistake is one line and exit code 2, nothing written
    bad = tmp_path / "bad.yaml"
    assert (
        fit_class_weights.main(["-c", "duocc/stream_agg", "data.preset=tiny", "--source", "depth", "--out", str(bad)])
        == 2
    )
    assert "expected a voxel_ce source" in capsys.readouterr().err and not bad.exists()


def test_fit_class_weights_unrounded_writes_the_code_s_rule_to_float32_precision(tmp_path):
    from occplug_duocc.tools.class_weights import CODE_EPS

    out = tmp_path / "exact.yaml"
    args = ["-c", "duocc/stream_agg", "data.preset=tiny", "--unrounded", "--eps", "0.001", "--out", str(out)]
    assert fit_class_weights.main(args) == 0
    text = out.read_text()
    assert "plus 0.001" in text and "--eps 0.001 --unrounded" in text  # the header says how it was made
    written = yaml.safe_load(text)["model"]["supervision"]["occupancy"]["class_weights"]
    dm = runner.build_datamodule(runner.load_config(["duocc/stream_agg"], ["data.preset=tiny"]))
    counts = class_counts(dm.dataset("train"), len(dm.class_names))
    free = list(dm.class_names).index("free")
    expected = duocc_class_weights(counts.counts, free_index=free, eps=CODE_EPS)
    assert torch.equal(torch.tensor(written, dtype=torch.float32), expected)
    assert not torch.equal(expected, duocc_class_weights(counts.counts, free_index=free))  # + 0.001 shows here
    bad = tmp_path / "bad.yaml"
    assert fit_class_weights.main(["-c", "duocc/stream_agg", "--eps", "-1", "--out", str(bad)]) == 2
    assert not bad.exists()
