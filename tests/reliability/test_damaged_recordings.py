"""Damaged recordings: a flipped bit costs its own chunk only, a truncated file is read up to its
last complete chunk, a folder without .mcap is a clear error; what was lost is reported."""

import numpy as np
import pytest

from ct_calib_nodes import offline
from ct_calib_nodes.io.mcap_io import ReadReport, RecordingError, iter_recording
from reliab_recordings import IMAGE, STAGE, T0_NS, record_offsets, synthetic_recording

N = 30


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    path = synthetic_recording(tmp_path_factory.mktemp("dmg") / "rec.mcap", n_frames=N)
    chunks = [(o, ln) for o, op, ln in record_offsets(path) if op == 6]
    assert len(chunks) >= 8      # 8 KiB frames in 16 KiB chunks
    return path, path.read_bytes(), chunks


def _read(data, tmp_path, name="m.mcap"):
    p = tmp_path / name
    p.write_bytes(bytes(data))
    rep = ReadReport()
    frames = [int(np.frombuffer(bytes(m.msg.data), np.uint16)[0]) for m in iter_recording(p, report=rep)
              if m.topic == IMAGE]
    return frames, rep


def _chunk_frames(data, off):
    """Frame numbers whose image the chunk at ``off`` holds (images are logged at T0 + i * 0.1 s)."""
    t0 = int.from_bytes(data[off + 9:off + 17], "little")
    t1 = int.from_bytes(data[off + 17:off + 25], "little")
    return set(range(-((T0_NS - t0) // 100_000_000), (t1 - T0_NS) // 100_000_000 + 1)), t0, t1


@pytest.mark.parametrize("where", ["payload", "crc_field", "compression_name", "length_field"])
def test_flipped_bit_costs_one_chunk(rec, tmp_path, where):
    path, data, chunks = rec
    rng = np.random.default_rng(["payload", "crc_field", "compression_name", "length_field"].index(where))
    for trial in range(3):
        ci = int(rng.integers(1, len(chunks) - 1))
        off, ln = chunks[ci]
        pos = {"payload": off + 9 + 45 + int(rng.integers(0, ln - 45)), "crc_field": off + 9 + 24,
               "compression_name": off + 9 + 33, "length_field": off + 1 + 2}[where]
        d = bytearray(data)
        d[pos] ^= 1 << int(rng.integers(0, 8))
        frames, rep = _read(d, tmp_path)
        lost_frames, t0, t1 = _chunk_frames(data, off)
        expected = [i for i in range(N) if i not in lost_frames]
        assert frames == expected, (where, ci, rep.errors)
        assert len(rep.lost) == 1 and not rep.complete
        span = rep.lost[0]
        assert span.offset == off
        # the file's own indexes tell how many messages the skipped chunk held, and when
        n_img = len(lost_frames)
        assert span.by_topic.get(IMAGE) == n_img and span.messages >= n_img
        assert span.t0_ns <= t0 + 1 and span.t1_ns >= t1 - 1
        assert "lost" in rep.errors[0] and "message(s)" in rep.errors[0]


def test_flip_without_summary_uses_message_index(rec, tmp_path):
    """A recording cut short (no summary) with a damaged chunk in the middle: the chunk is skipped,
    its message count comes from the message-index records behind it, the tail is reported."""
    path, data, chunks = rec
    off, ln = chunks[3]
    cut = chunks[-2][0] + 100                                # inside the last-but-one chunk
    d = bytearray(data[:cut])
    d[off + 200] ^= 0x40
    frames, rep = _read(d, tmp_path)
    lost3, _, _ = _chunk_frames(data, off)
    tail, _, _ = _chunk_frames(data, chunks[-2][0])
    last = max(_chunk_frames(data, chunks[-3][0])[0])
    assert frames == [i for i in range(last + 1) if i not in lost3]
    assert len(rep.lost) == 2
    assert rep.lost[0].by_topic[IMAGE] == len(lost3)
    assert rep.lost[1].messages is None and "truncated" in rep.lost[1].reason
    assert rep.lost[1].offset + rep.lost[1].nbytes == cut
    assert min(tail) > last


def test_truncated_at_every_record_boundary_and_mid_chunk(rec, tmp_path):
    path, data, chunks = rec
    recs = record_offsets(path)
    data_end = [o for o, op, _ in recs if op == 15][0]
    for o, op, ln in recs[:: max(1, len(recs) // 25)]:
        for cut in (o, o + 9 + ln // 2):
            frames, rep = _read(data[:cut], tmp_path)
            done = [c for c in chunks if c[0] + 9 + c[1] <= cut]
            expect = sorted(set().union(*[_chunk_frames(data, c[0])[0] for c in done])) if done else []
            assert frames == expect, cut
            if cut <= data_end:          # past the data-end record only the index is missing
                assert not rep.complete and "truncated" in rep.errors[0]


def test_empty_folder_and_non_mcap_give_clear_errors(tmp_path, capsys):
    empty = tmp_path / "empty_bag"
    empty.mkdir()
    (empty / "notes.txt").write_text("no recording here")
    with pytest.raises(RecordingError, match="holds no .mcap"):
        list(iter_recording(empty))
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an MCAP file at all" * 10)
    with pytest.raises(RecordingError, match="not an MCAP file"):
        list(iter_recording(junk))
    (tmp_path / "zero.mcap").write_bytes(b"")
    for target, text in ((empty, "holds no .mcap"), (junk, "not an MCAP file"), (tmp_path / "zero.mcap", "empty")):
        assert offline.main([str(target), "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert text in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_offline_tool_reports_the_loss(rec, tmp_path, capsys):
    """The offline tool says what was lost (messages, topics, time range) and exits as documented
    (1: these random frames hold no spheres, so nothing is solvable)."""
    path, data, chunks = rec
    off, ln = chunks[2]
    d = bytearray(data)
    d[off + 500] ^= 0x01
    p = tmp_path / "flip.mcap"
    p.write_bytes(bytes(d))
    assert offline.main([str(p), "--out", str(tmp_path / "out")]) == 1
    out = capsys.readouterr().out
    assert "damaged chunk" in out and f"{IMAGE}:" in out and "log time" in out and f"{STAGE}:" in out


@pytest.mark.parametrize("compression", ["lz4", ""])
def test_other_compressions(tmp_path, compression):
    path = synthetic_recording(tmp_path / "c.mcap", n_frames=12, compression=compression)
    data = path.read_bytes()
    chunks = [(o, ln) for o, op, ln in record_offsets(path) if op == 6]
    off, ln = chunks[2]
    d = bytearray(data)
    d[off + 9 + ln // 2] ^= 0x08
    frames, rep = _read(d, tmp_path)
    lost, _, _ = _chunk_frames(data, off)
    assert frames == [i for i in range(12) if i not in lost] and len(rep.lost) == 1
    assert rep.lost[0].by_topic[IMAGE] == len(lost)


def test_bag_directory_with_one_unreadable_file(rec, tmp_path):
    """A rosbag2 folder of two files, the second not MCAP at all: the first is read, the second
    reported; a folder of only unreadable files is a RecordingError."""
    path, data, chunks = rec
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "bag_0.mcap").write_bytes(data)
    (bag / "bag_1.mcap").write_bytes(b"\x00" * 5000)
    rep = ReadReport()
    n = sum(1 for m in iter_recording(bag, report=rep) if m.topic == IMAGE)
    assert n == N and len(rep.lost) == 1 and rep.lost[0].file == "bag_1.mcap" and "not an MCAP" in rep.lost[0].reason
    (bag / "bag_0.mcap").write_bytes(b"junk" * 100)
    with pytest.raises(RecordingError):
        list(iter_recording(bag))
