"""The one atomic writer (ct_calib_nodes.io.atomic) behind every result file: a write interrupted
by an exception leaves the old file byte for byte and no temporary file behind; each of the four
former copies (CT results JSON, Pixel Probe calibration YAML, measurement JSON/NPZ, journal renewal)
now goes through it; `staged_outputs` moves a command's set of output files into place all or nothing."""

import json

import numpy as np
import pytest

from ct_calib_nodes.io import atomic, journal, results
from picms_nodes.core import measure


class Boom(RuntimeError):
    pass


def test_new_file_written_and_no_leftovers(tmp_path):
    p = atomic.write_text_atomic(tmp_path / "sub" / "a.json", "{\"x\": 1}")
    assert json.loads(p.read_text()) == {"x": 1}
    assert sorted(x.name for x in p.parent.iterdir()) == ["a.json"]


def test_interrupted_write_keeps_old_file(tmp_path):
    p = tmp_path / "a.json"
    p.write_text("good")

    def half(tmp):
        with open(tmp, "w") as fh:
            fh.write("partial")
            fh.flush()
            raise Boom("disk gone mid-write")
    with pytest.raises(Boom):
        atomic.replace_atomically(p, half)
    assert p.read_text() == "good"
    assert [x.name for x in tmp_path.iterdir()] == ["a.json"]


def test_ct_results_json_interrupted(tmp_path, monkeypatch):
    p = results.write_json_atomic(tmp_path / "r.json", {"a": np.float64(1.5)})
    before = p.read_bytes()
    monkeypatch.setattr(results, "_plain", lambda d: (_ for _ in ()).throw(Boom("serialise")))
    with pytest.raises(Boom):
        results.write_json_atomic(p, {"a": 2})
    assert p.read_bytes() == before and json.loads(before) == {"a": 1.5}


def test_measurement_json_and_npz_interrupted(tmp_path):
    p = measure.write_json_atomic({"a": 1}, tmp_path / "m.json")
    before = p.read_bytes()
    with pytest.raises(TypeError):      # an object json cannot encode: fails mid-dump
        measure.write_json_atomic({"a": 2, "b": object()}, p)
    assert p.read_bytes() == before
    assert [x.name for x in tmp_path.iterdir()] == ["m.json"]


def test_journal_renewal_replaces_atomically(tmp_path, monkeypatch):
    j = journal.Journal(tmp_path / "c.journal", "n", "cell").open_append()
    j.append_message(b"old record")
    j.close()
    before = (tmp_path / "c.journal").read_bytes()

    def fail(path, data):
        raise Boom("power cut")
    monkeypatch.setattr(journal, "write_bytes_atomic", fail)
    with pytest.raises(Boom):
        journal.Journal(tmp_path / "c.journal", "n", "cell").start_new()
    assert (tmp_path / "c.journal").read_bytes() == before
    monkeypatch.undo()
    j = journal.Journal(tmp_path / "c.journal", "n", "cell").start_new()
    j.close()
    assert len((tmp_path / "c.journal").read_bytes()) < len(before)
    assert [x.name for x in tmp_path.iterdir()] == ["c.journal"]


def test_staged_outputs_all_or_nothing(tmp_path):
    """A command's set of outputs (report, JSON, plots, a folder) moves into place only when all were
    written: a failure half-way leaves the previous run's files as they were and no staging folder."""
    out = tmp_path / "out"
    with atomic.staged_outputs(out) as tmp:
        (tmp / "report.md").write_text("run 1")
        (tmp / "plots").mkdir()
        (tmp / "plots" / "a.png").write_bytes(b"1")
    assert (out / "report.md").read_text() == "run 1" and (out / "plots" / "a.png").read_bytes() == b"1"
    with pytest.raises(Boom):
        with atomic.staged_outputs(out) as tmp:
            (tmp / "report.md").write_text("run 2, partial")
            raise Boom("plotting failed")
    assert (out / "report.md").read_text() == "run 1"
    with atomic.staged_outputs(out) as tmp:      # a complete second run replaces files and folders
        (tmp / "report.md").write_text("run 3")
        (tmp / "plots").mkdir()
        (tmp / "plots" / "b.png").write_bytes(b"3")
    assert (out / "report.md").read_text() == "run 3"
    assert sorted(p.name for p in (out / "plots").iterdir()) == ["b.png"]
    assert sorted(p.name for p in out.iterdir()) == ["plots", "report.md"]
