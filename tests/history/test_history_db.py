"""Calibration history database: records, crash safety (SIGKILL mid-transaction), concurrent writers."""
import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from ct_calib_nodes.io.history import (History, Input, Quantity, SolveRecord, compare_quantities, content_hash,
                                       normalise_status)

SRC = os.path.join(os.path.dirname(__file__), "..", "..", "ros_ws", "src", "ct_calib_nodes")


def _env():
    env = os.environ.copy()
    env["PYTHONPATH"] = os.path.abspath(SRC) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _rec(i, cell="/cell_a", status="success", n_q=3):
    return SolveRecord(cell=cell, kind="ct_geometry", status=status, result={"i": i, "x": [float(i)] * 4},
                       campaign_id=f"c{i}", inputs=[Input(role="recording", path=f"/r/{i}", sha256="ab" * 32)],
                       quantities=[Quantity(name=f"p{j}", value=i + 0.1 * j, u=0.01, unit="m") for j in range(n_q)])


def test_record_roundtrip_and_latest_valid(tmp_path):
    db = tmp_path / "h.sqlite"
    with History(db) as h:
        a = h.record(_rec(1))
        h.record(_rec(2, status="poor_fit"))            # a failed solve never hides the valid one
        h.record(_rec(3, cell="/cell_b"))
        assert h.latest_valid("/cell_a", "ct_geometry").uid == a.uid
        assert h.latest_valid("cell_a/", "ct_geometry").uid == a.uid   # namespace spellings
        assert h.latest_valid("/", "ct_geometry") is None
        got = h.get(a.uid)
        assert got.result == {"i": 1, "x": [1.0] * 4}
        assert got.inputs[0].sha256 == "ab" * 32 and got.status_code == 0
        assert [(q.name, q.value, q.u) for q in got.quantities] == [("p0", 1.0, 0.01), ("p1", 1.1, 0.01),
                                                                    ("p2", 1.2, 0.01)]
        assert [r.status for r in h.list(cell="/cell_a")] == ["success", "poor_fit"]
        assert [t[2] for t in h.trend("p1", cell="/cell_a")] == [1.1]
        assert h.integrity_ok()
    with pytest.raises(ValueError):
        normalise_status("ok")
    assert normalise_status(5) == "poor_fit"


def test_compare_flags_only_changes_beyond_uncertainty():
    a, b = _rec(1), _rec(1)
    b.quantities[0].value += 0.015     # 1.06 u_diff: not flagged at k = 2
    b.quantities[1].value += 0.05      # 3.5 u_diff: flagged
    rows = {r[0]: r for r in compare_quantities(a, b)}
    assert not rows["p0"][7] and rows["p1"][7] and not rows["p2"][7]
    assert rows["p1"][6] == pytest.approx(0.01 * 2 ** 0.5)


def test_content_hash_of_directory_is_location_independent(tmp_path):
    for d in ("a", "b"):
        (tmp_path / d).mkdir()
        (tmp_path / d / "x.mcap").write_bytes(b"123")
        (tmp_path / d / "metadata.yaml").write_text("m")
    assert content_hash(tmp_path / "a") == content_hash(tmp_path / "b")
    (tmp_path / "b" / "x.mcap").write_bytes(b"124")
    assert content_hash(tmp_path / "a") != content_hash(tmp_path / "b")


WRITER = textwrap.dedent("""
    import sys, time
    from ct_calib_nodes.io.history import History, Input, Quantity, SolveRecord
    path, tag, n, big = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    h = History(path)
    for i in range(n):
        r = SolveRecord(cell="/" + tag, kind="ct_error_map", status="success", result={"i": i, "pad": "x" * big},
                        campaign_id=f"{tag}-{i}",
                        quantities=[Quantity(name="positioning_m", value=i, u=1e-6, position=k) for k in range(big // 50)])
        h.record(r)
        print(f"{tag} {i} {r.uid}", flush=True)
    if sys.argv[5:] == ["hang"]:
        con = h._con
        con.execute("BEGIN IMMEDIATE")
        sid = con.execute("INSERT INTO solves (uid, created_utc, created_ns, cell, kind, source, status, status_code, software,"
                    " result_json) VALUES ('UNCOMMITTED', 'x', 0, '/x', 'k', 'live', 'success', 0, 's', '{}')").lastrowid
        con.executemany("INSERT INTO quantities (solve_id, name, value) VALUES (?, ?, ?)",
                        [(sid, 'q', float(j)) for j in range(20000)])
        print(f'SID {sid}', flush=True)
        print("IN-TRANSACTION", flush=True)
        time.sleep(120)
""")


def _read_lines_until(proc, marker, timeout):
    lines, t_end = [], time.monotonic() + timeout
    while time.monotonic() < t_end:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line.strip())
        if line.strip() == marker:
            return lines
    raise AssertionError(f"writer never printed {marker!r}: {lines[-3:]}, stderr {proc.stderr.read()[-2000:]}")


def test_sigkill_mid_transaction_keeps_committed_and_drops_partial(tmp_path):
    db = str(tmp_path / "h.sqlite")
    p = subprocess.Popen([sys.executable, "-c", WRITER, db, "w", "25", "2000", "hang"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=_env())
    try:
        lines = _read_lines_until(p, "IN-TRANSACTION", 60)
        # the writer holds the write lock with 20001 uncommitted rows in the WAL / cache
        os.kill(p.pid, signal.SIGKILL)
        p.wait(10)
    finally:
        if p.poll() is None:
            p.kill()
    committed = [ln.split()[2] for ln in lines if ln.startswith("w ")]
    assert len(committed) == 25
    with History(db, timeout_s=5) as h:
        assert h.integrity_ok()
        assert h.count() == 25
        assert [r.uid for r in h.list()] == committed
        assert h.get("UNCOMMITTED") is None
        sid = int([ln for ln in lines if ln.startswith("SID")][0].split()[1])
        assert h._con.execute("SELECT COUNT(*) FROM quantities WHERE solve_id = ?", (sid,)).fetchone()[0] == 0
        # and the database takes new writes after the crash (the dead writer's lock is gone)
        h.record(_rec(99))
        assert h.count() == 26


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sigkill_at_random_moment_while_writing(tmp_path, seed):
    """Kill a writer at an arbitrary moment inside its loop of record() calls: every record it reported
    committed is there and whole (all its quantities), and at most one more (committed, not yet printed)."""
    db = str(tmp_path / "h.sqlite")
    p = subprocess.Popen([sys.executable, "-c", WRITER, db, "w", "100000", "20000"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=_env())
    try:
        first = p.stdout.readline()
        assert first.startswith("w 0 "), p.stderr.read()
        time.sleep(0.1 + 0.17 * seed)
        os.kill(p.pid, signal.SIGKILL)
        p.wait(10)
        rest = p.stdout.read().splitlines()
    finally:
        if p.poll() is None:
            p.kill()
    reported = [first.split()[2]] + [ln.split()[2] for ln in rest if ln.startswith("w ")]
    with History(db, timeout_s=5) as h:
        assert h.integrity_ok()
        stored = [r.uid for r in h.list()]
        assert stored[:len(reported)] == reported
        assert len(stored) - len(reported) in (0, 1)
        n_q = h._con.execute("SELECT solve_id, COUNT(*) FROM quantities GROUP BY solve_id").fetchall()
        assert {c for _s, c in n_q} == {400} and len(n_q) == len(stored)


def test_concurrent_writers_and_reader(tmp_path):
    db = str(tmp_path / "h.sqlite")
    History(db).close()          # schema first, so the writers race on records only
    n = 40
    procs = [subprocess.Popen([sys.executable, "-c", WRITER, db, f"cell{j}", str(n), "500"], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, env=_env()) for j in range(3)]
    seen = []
    with History(db) as reader:       # reads while the writers write (WAL: never blocked)
        while any(p.poll() is None for p in procs):
            seen.append(reader.count())
            time.sleep(0.02)
    outs = [p.communicate(timeout=60) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err[-2000:]
    with History(db) as h:
        assert h.integrity_ok()
        assert h.count() == 3 * n
        for j in range(3):
            recs = h.list(cell=f"/cell{j}")
            assert [r.result["i"] for r in recs] == list(range(n))
            assert [r.uid for r in recs] == [ln.split()[2] for ln in outs[j][0].splitlines()]
    assert seen == sorted(seen)
    assert json.loads(json.dumps(seen))  # the reader saw the count grow monotonically
