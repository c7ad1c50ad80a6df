"""The reader process yields exactly what the sequence yields, with its warnings."""

from __future__ import annotations

import multiprocessing as mp
from pathlib import Path

import numpy as np
import pytest

from datasets.mcap_io import McapSequence, write_sequence_mcap
from datasets.mcap_scan import scan_mcap
from datasets.memory import random_sequence
from slam.core.messages import StereoFrame
from slam.runtime.reader import prefetched_messages


@pytest.fixture(scope="module")
def path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    seq = random_sequence(num_frames=30, width=96, height=72, seed=5)
    out = tmp_path_factory.mktemp("prefetch") / "seq.mcap"
    write_sequence_mcap(seq, out, progress=False, chunk_size_bytes=48 * 1024)
    return out


def _same(a: list, b: list) -> None:  # type: ignore[type-arg]
    assert [type(m) for m in a] == [type(m) for m in b]
    assert [m.t_ns for m in a] == [m.t_ns for m in b]
    for x, y in zip(a, b, strict=True):
        if isinstance(x, StereoFrame):
            assert np.array_equal(x.left, y.left) and np.array_equal(x.right, y.right)
            assert x.index == y.index
        else:
            assert np.array_equal(x.gyro_rad_s, y.gyro_rad_s)
            assert np.array_equal(x.accel_m_s2, y.accel_m_s2)


@pytest.mark.parametrize("slots", ["shared memory", "inline"])
def test_same_messages_in_the_same_order(
    path: Path, slots: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    import slam.runtime.reader

    if slots == "inline":  # slots too small for any frame: every image travels in the queue
        monkeypatch.setattr(slam.runtime.reader, "_slot_bytes", lambda seq: 16)
    direct = list(McapSequence(path).messages())
    assert sum(isinstance(m, StereoFrame) for m in direct) == 30
    _same(list(prefetched_messages(McapSequence(path), frames_ahead=3)), direct)


def test_warnings_found_while_reading_reach_the_sequence(path: Path, tmp_path: Path) -> None:
    """A damaged image chunk is found only when read (in the reader process)."""
    data = bytearray(path.read_bytes())
    images = [c for c in scan_mcap(path).chunks if not c.validated]
    mid = images[len(images) // 2].data_offset + images[len(images) // 2].data_length // 2
    data[mid : mid + 64] = bytes(64)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    direct_seq = McapSequence(bad)
    direct = list(direct_seq.messages())
    seq = McapSequence(bad)
    before = list(seq.warnings)
    fetched = list(prefetched_messages(seq))
    _same(fetched, direct)
    assert len(seq.warnings) > len(before)
    assert seq.warnings == direct_seq.warnings


def test_closing_early_stops_the_reader(path: Path) -> None:
    gen = prefetched_messages(McapSequence(path), frames_ahead=2)
    first = [next(gen) for _ in range(5)]
    assert len(first) == 5
    gen.close()
    assert not [p for p in mp.active_children() if p.name == "slam-reader"]
