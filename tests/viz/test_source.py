"""SampleSource: a scene's frames found from the data set's scene structure, without decoding frames."""

from pathlib import Path

import pytest

from occplug.data.sequences import SceneIndex
from occplug.run import runner
from occplug.viz.source import SampleSource

BASELINE = str(Path(__file__).resolve().parents[2] / "configs" / "baseline.yaml")


@pytest.fixture
def source(monkeypatch):
    """The tiny world's train split (2 scenes of 3 frames), counting every frame decoded."""
    src = SampleSource(runner.resolve_run_config([BASELINE], ["data.preset=tiny"]), "train")
    decoded: list[int] = []
    real = src.dataset

    class Counting:
        def __len__(self):
            return len(real)

        def __getitem__(self, index):
            decoded.append(index)
            return real[index]

    src.decoded = decoded
    src.real = real
    monkeypatch.setattr(src, "dataset", Counting())
    return src


def test_sequence_from_the_synthetic_layout_decodes_nothing(source):
    source.dataset.frames_per_scene, source.dataset.num_scenes = 3, 2  # the bare synthetic data set's layout
    assert source.sequence(4) == [3, 4, 5] and source.sequence(-6) == [0, 1, 2]
    assert source.decoded == []
    assert [source.real[i].scene for i in (3, 5)] == [source.real[4].scene] * 2


def test_sequence_from_a_scene_index_decodes_nothing(source):
    source.dataset.scenes = SceneIndex(("a", "b"), ((2, 0, 4), (1, 3, 5)))  # time order need not be index order
    assert source.sequence(0) == [2, 0, 4] and source.sequence(5) == [1, 3, 5]
    assert source.decoded == []


def test_sequence_without_scene_structure_walks_the_frames_once_and_keeps_few(source):
    assert source.scenes is None
    assert source.sequence(1) == [0, 1, 2] and source.sequence(3) == [3, 4, 5]
    # each frame of the scene once, and the first frame past either end where the walk stops
    assert sorted(source.decoded) == sorted([1, 0, 2, 3] + [3, 2, 4, 5])
    assert len(source._frames) <= 4  # decoded frames are not all kept


def test_stream_loads_each_frame_when_asked(source):
    frames = source.stream([3, 4, 5])
    assert source.decoded == []
    assert next(frames).frame_index == 0 and source.decoded == [3]
    assert [f.frame_index for f in frames] == [1, 2] and source.decoded == [3, 4, 5]
