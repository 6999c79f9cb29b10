"""picms_measure_offline on damaged measurement.json files (issue 10): every hostile value in every
top-level field, and damaged JSON, must end in a documented exit status (1: nothing usable, 2: the
file or program unreadable) with a message, never a traceback. In-process, a few seconds."""

import json

import pytest

from picms_nodes import measure_offline
from picms_programs import chrome_targets_program

PROGRAM = chrome_targets_program("{id: c7, type: circle, center: [0.009, -0.008], diameter: 0.007, points: 6}")
HOSTILE = [None, 0, -1, 1e308, float("nan"), "", "x", [], [1, 2], {}, {"a": 1}, [[float("nan")] * 3] * 3, True]
FIELDS = ["mode", "program_yaml", "program", "points", "probe", "part_finding", "band_width_m"]


def _base():
    return {"mode": "stage", "program_yaml": PROGRAM, "points": [],
            "probe": {"calibration": {"stage": {"R_tracker_stage": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}}},
            "part_finding": {"R_stage_part": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}}


def _cases():
    for f in FIELDS:
        for k, v in enumerate(HOSTILE):
            yield f"{f}-{k}", {**_base(), f: v}
    for k, v in enumerate(HOSTILE):
        yield f"R_tracker_stage-{k}", {**_base(), "probe": {"calibration": {"stage": {"R_tracker_stage": v}}}}
        yield f"R_stage_part-{k}", {**_base(), "part_finding": {"R_stage_part": v}}
        yield f"point-{k}", {**_base(), "points": [v, {"feature": "c7", "index": 0}]}
    for k, v in enumerate(HOSTILE):
        yield f"document-{k}", v


@pytest.mark.parametrize("relocate", [False, True])
def test_measure_offline_hostile_fields(tmp_path, capsys, relocate):
    failures, outcomes = [], {}
    for name, doc in _cases():
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps(doc))
        args = [str(path), "--out", str(tmp_path / f"{name}.out.json"), "--history", "none"]
        try:
            rc = measure_offline.main(args + (["--relocate"] if relocate else []))
        except Exception as exc:  # noqa: BLE001 - the point of the test
            failures.append(f"{name}: {type(exc).__name__}: {exc}")
            continue
        err = capsys.readouterr().err
        outcomes[rc] = outcomes.get(rc, 0) + 1
        if rc not in (1, 2) or not err.strip():
            failures.append(f"{name}: exit {rc}, stderr {err[-200:]!r}")
    for k, text in enumerate([b"", b"{", b"\xff\xfe\x00", b'{"points": [' * 5000]):
        path = tmp_path / f"raw{k}.json"
        path.write_bytes(text)
        rc = measure_offline.main([str(path), "--out", str(tmp_path / "raw.out.json"), "--history", "none"])
        assert rc == 2 and "cannot read" in capsys.readouterr().err
    assert not failures, "\n".join(failures)
    assert sum(outcomes.values()) == len(FIELDS) * len(HOSTILE) + 4 * len(HOSTILE)
