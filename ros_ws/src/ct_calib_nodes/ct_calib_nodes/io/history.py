"""Calibration history: every solve of the cell, in an embedded SQLite database.

No ROS, no numpy: the standard library only, so every node, offline tool and
the Pixel Probe cell (``picms_nodes``) can write and read the same file.

One row per solve (``solves``): when (UTC), which cell (the node namespace,
``/`` for the root), what kind (``ct_geometry``, ``ct_error_map``,
``picms_calibration``, ``picms_measurement``, ``discrepancy_verdict``, ...),
where from (``live``, ``offline``, ``archive``), the campaign it belongs to
and whether it is final, the status in the one outcome vocabulary
(:data:`STATUS_WORDS`, the words of ``io/results.py`` OUTCOME_CODES and the
codes of metro_msgs/SolveStatus), the software version, and the full result
as JSON. Beside it:

- ``inputs``: what the solve was made from: a recording (path + content hash),
  the YAML files (path + sha256), upstream results (``upstream`` role, the
  upstream solve's uid in ``ref_uid``), topics with stamp ranges;
- ``quantities``: the scalar results with their standard uncertainties (name,
  optional position index, unit, value, u), which is what trends, comparisons
  and change flags read without parsing JSON.

Concurrency and crashes: WAL journal, ``synchronous=FULL``, every record is
one ``BEGIN IMMEDIATE`` transaction with a busy timeout, so several writer
processes (two nodes and an offline run) serialise on the file lock and a
writer killed mid-transaction leaves nothing of its record and everything
committed before (tests/history/test_history_db.py kills one with SIGKILL).

The database path: an explicit argument, else ``$METRO_HISTORY_DB``, else
``~/.local/share/metro_cell/history.sqlite``. ``none`` disables recording.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
import pathlib
import sqlite3
import subprocess
import threading
import time
import uuid
from dataclasses import dataclass, field

SCHEMA_VERSION = 1

#: outcome word -> metro_msgs/SolveStatus code (identical to io/results.py OUTCOME_CODES)
STATUS_WORDS = {"success": 0, "not_converged": 1, "degenerate": 2, "insufficient_data": 3, "failed": 4,
                "poor_fit": 5}
STATUS_BY_CODE = {v: k for k, v in STATUS_WORDS.items()}

ENV_DB = "METRO_HISTORY_DB"
DISABLED = ("none", "off", "false", "0")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS solves (
    id            INTEGER PRIMARY KEY AUTOINCREMENT,
    uid           TEXT NOT NULL UNIQUE,
    created_utc   TEXT NOT NULL,          -- ISO 8601, UTC, when the record was written
    created_ns    INTEGER NOT NULL,       -- the same, ns since the Unix epoch
    cell          TEXT NOT NULL,          -- node namespace of the cell ('/' = root), or a plant name
    kind          TEXT NOT NULL,          -- ct_geometry, ct_error_map, picms_calibration, ...
    source        TEXT NOT NULL,          -- live, offline, archive
    campaign_id   TEXT,
    final         INTEGER NOT NULL DEFAULT 1,
    status        TEXT NOT NULL,          -- outcome word (STATUS_WORDS)
    status_code   INTEGER NOT NULL,       -- metro_msgs/SolveStatus code
    message       TEXT NOT NULL DEFAULT '',
    data_start_ns INTEGER,                -- stamps of the data the solve used
    data_end_ns   INTEGER,
    software      TEXT NOT NULL,
    host          TEXT NOT NULL DEFAULT '',
    result_json   TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS solves_cell_kind ON solves(cell, kind, status, id);
CREATE TABLE IF NOT EXISTS inputs (
    solve_id  INTEGER NOT NULL REFERENCES solves(id) ON DELETE CASCADE,
    role      TEXT NOT NULL,              -- recording, instrument_yaml, reference_object_yaml, upstream, topic
    path      TEXT,
    sha256    TEXT,
    ref_uid   TEXT,                       -- upstream solve uid
    detail    TEXT                        -- JSON: stamps, sizes, ...
);
CREATE INDEX IF NOT EXISTS inputs_solve ON inputs(solve_id);
CREATE TABLE IF NOT EXISTS quantities (
    solve_id  INTEGER NOT NULL REFERENCES solves(id) ON DELETE CASCADE,
    name      TEXT NOT NULL,
    position  INTEGER,                    -- index along a map (error-map position), NULL for scalars
    unit      TEXT NOT NULL DEFAULT '',
    value     REAL,                       -- NULL when not finite
    u         REAL                        -- standard uncertainty (k = 1), NULL when unknown
);
CREATE INDEX IF NOT EXISTS quantities_solve ON quantities(solve_id);
CREATE INDEX IF NOT EXISTS quantities_name ON quantities(name, position);
"""


class HistoryError(RuntimeError):
    """The history database cannot be opened or written (path, permissions, not a database)."""


# ------------------------------------------------------------------------------------------------
# hashing and provenance
def sha256_file(path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(chunk), b""):
            h.update(block)
    return h.hexdigest()


def content_hash(path) -> str:
    """sha256 of a file; of a directory (rosbag2 layout): of its files' relative names and hashes,
    sorted, so a copy of a recording elsewhere has the same hash."""
    p = pathlib.Path(path)
    if p.is_file():
        return sha256_file(p)
    if not p.is_dir():
        raise FileNotFoundError(f"no file or directory at {p}")
    h = hashlib.sha256()
    for f in sorted(q for q in p.rglob("*") if q.is_file()):
        h.update(f"{f.relative_to(p).as_posix()}\0{sha256_file(f)}\n".encode())
    return h.hexdigest()


_VERSION = None


def software_version() -> str:
    """``ct_calib_nodes <version>`` plus the git commit of the source tree when it is one."""
    global _VERSION
    if _VERSION is None:
        try:
            from importlib.metadata import version  # noqa: PLC0415
            v = f"ct_calib_nodes {version('ct_calib_nodes')}"
        except Exception:  # noqa: BLE001 - not installed as a distribution
            v = "ct_calib_nodes (unversioned)"
        try:
            here = pathlib.Path(__file__).resolve().parent
            r = subprocess.run(["git", "-C", str(here), "describe", "--always", "--dirty", "--abbrev=12"],
                               capture_output=True, text=True, timeout=5)
            if r.returncode == 0 and r.stdout.strip():
                v += f" git {r.stdout.strip()}"
        except (OSError, subprocess.SubprocessError):
            pass
        _VERSION = v
    return _VERSION


def default_path() -> str:
    env = os.environ.get(ENV_DB, "").strip()
    if env:
        return env
    return str(pathlib.Path.home() / ".local" / "share" / "metro_cell" / "history.sqlite")


def plain(v):
    """JSON-able copy: numpy arrays and scalars via tolist/item, non-finite floats as strings."""
    if isinstance(v, dict):
        return {str(k): plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [plain(x) for x in v]
    if hasattr(v, "tolist"):
        return plain(v.tolist())
    if isinstance(v, bool) or v is None or isinstance(v, (int, str)):
        return v
    if isinstance(v, float):
        return v if math.isfinite(v) else str(v)
    return str(v)


def _num(x):
    try:
        x = float(x)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


# ------------------------------------------------------------------------------------------------
@dataclass
class Input:
    role: str
    path: str | None = None
    sha256: str | None = None
    ref_uid: str | None = None
    detail: dict | None = None

    @classmethod
    def file(cls, role: str, path) -> "Input":
        """A file or recording directory with its content hash (None when it cannot be read)."""
        p = pathlib.Path(path)
        try:
            h = content_hash(p)
        except OSError:
            h = None
        return cls(role=role, path=str(p.resolve()), sha256=h)


@dataclass
class Quantity:
    name: str
    value: float
    u: float | None = None
    unit: str = ""
    position: int | None = None


@dataclass
class SolveRecord:
    """One solve as stored (``id``/``uid``/``created_*`` are filled by :meth:`History.record`)."""

    cell: str
    kind: str
    status: str
    result: dict
    source: str = "live"
    message: str = ""
    campaign_id: str | None = None
    final: bool = True
    data_start_ns: int | None = None
    data_end_ns: int | None = None
    inputs: list = field(default_factory=list)       # [Input]
    quantities: list = field(default_factory=list)   # [Quantity]
    software: str = ""
    host: str = ""
    id: int | None = None
    uid: str = ""
    created_utc: str = ""
    created_ns: int = 0

    @property
    def status_code(self) -> int:
        return STATUS_WORDS[self.status]

    @property
    def valid(self) -> bool:
        return self.status == "success"


def normalise_status(status) -> str:
    """An outcome word or a SolveStatus code -> the outcome word (ValueError if neither)."""
    if isinstance(status, bool):
        return "success" if status else "failed"
    if isinstance(status, int):
        if status not in STATUS_BY_CODE:
            raise ValueError(f"unknown SolveStatus code {status}; known {sorted(STATUS_BY_CODE)}")
        return STATUS_BY_CODE[status]
    s = str(status).strip().lower()
    if s not in STATUS_WORDS:
        raise ValueError(f"unknown status {status!r}; known {sorted(STATUS_WORDS)}")
    return s


def cell_name(namespace: str) -> str:
    """A node namespace as a cell name: '' and '/' are the root cell '/'; no trailing slash."""
    ns = "/" + str(namespace or "").strip("/")
    return ns


class History:
    """One connection to the history database (thread-safe; open one per process or node)."""

    def __init__(self, path=None, timeout_s: float = 30.0):
        self.path = str(path if path is not None else default_path())
        if self.path.lower() in DISABLED:
            raise HistoryError("history disabled")
        p = pathlib.Path(self.path)
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
            self._con = sqlite3.connect(self.path, timeout=timeout_s, isolation_level=None,
                                        check_same_thread=False)
            self._con.row_factory = sqlite3.Row
            self._con.execute(f"PRAGMA busy_timeout = {int(timeout_s * 1000)}")
            mode = self._con.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                raise HistoryError(f"{self.path}: WAL journal not available (got {mode})")
            self._con.execute("PRAGMA synchronous = FULL")
            self._con.execute("PRAGMA foreign_keys = ON")
            self._migrate()
        except sqlite3.DatabaseError as exc:
            raise HistoryError(f"history database {self.path}: {exc}") from exc
        except OSError as exc:
            raise HistoryError(f"history database {self.path}: {exc}") from exc
        self._lock = threading.Lock()

    def _migrate(self):
        v = self._con.execute("PRAGMA user_version").fetchone()[0]
        if v > SCHEMA_VERSION:
            raise HistoryError(f"{self.path} has schema {v}, newer than this software's {SCHEMA_VERSION}")
        if v < SCHEMA_VERSION:
            self._con.execute("BEGIN IMMEDIATE")
            try:
                for stmt in _SCHEMA.split(";"):
                    if stmt.strip():
                        self._con.execute(stmt)
                self._con.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
                self._con.execute("COMMIT")
            except BaseException:
                self._con.execute("ROLLBACK")
                raise

    def close(self):
        try:
            self._con.close()
        except sqlite3.Error:
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -------------------------------------------------------------------------------- writing
    def record(self, rec: SolveRecord) -> SolveRecord:
        """Store one solve atomically; returns it with id, uid and time filled in."""
        rec.status = normalise_status(rec.status)
        now_ns = time.time_ns()
        rec.uid = rec.uid or uuid.uuid4().hex
        rec.created_ns = now_ns
        rec.created_utc = _dt.datetime.fromtimestamp(now_ns / 1e9, _dt.timezone.utc).isoformat(timespec="microseconds")
        rec.software = rec.software or software_version()
        rec.host = rec.host or os.uname().nodename
        rec.cell = cell_name(rec.cell)
        payload = json.dumps(plain(rec.result), allow_nan=False)
        with self._lock:
            con = self._con
            con.execute("BEGIN IMMEDIATE")
            try:
                cur = con.execute(
                    "INSERT INTO solves (uid, created_utc, created_ns, cell, kind, source, campaign_id, final, status,"
                    " status_code, message, data_start_ns, data_end_ns, software, host, result_json)"
                    " VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                    (rec.uid, rec.created_utc, now_ns, rec.cell, rec.kind, rec.source, rec.campaign_id,
                     int(bool(rec.final)), rec.status, rec.status_code, rec.message, rec.data_start_ns,
                     rec.data_end_ns, rec.software, rec.host, payload))
                sid = cur.lastrowid
                con.executemany("INSERT INTO inputs (solve_id, role, path, sha256, ref_uid, detail) VALUES (?,?,?,?,?,?)",
                                [(sid, i.role, i.path, i.sha256, i.ref_uid,
                                  None if i.detail is None else json.dumps(plain(i.detail))) for i in rec.inputs])
                con.executemany("INSERT INTO quantities (solve_id, name, position, unit, value, u) VALUES (?,?,?,?,?,?)",
                                [(sid, q.name, q.position, q.unit, _num(q.value), _num(q.u)) for q in rec.quantities])
                con.execute("COMMIT")
            except BaseException:
                con.execute("ROLLBACK")
                raise
        rec.id = sid
        return rec

    # -------------------------------------------------------------------------------- reading
    def _row_to_record(self, row, with_details: bool = True) -> SolveRecord:
        rec = SolveRecord(cell=row["cell"], kind=row["kind"], status=row["status"], result=json.loads(row["result_json"]),
                          source=row["source"], message=row["message"], campaign_id=row["campaign_id"],
                          final=bool(row["final"]), data_start_ns=row["data_start_ns"], data_end_ns=row["data_end_ns"],
                          software=row["software"], host=row["host"], id=row["id"], uid=row["uid"],
                          created_utc=row["created_utc"], created_ns=row["created_ns"])
        if with_details:
            rec.inputs = [Input(role=r["role"], path=r["path"], sha256=r["sha256"], ref_uid=r["ref_uid"],
                                detail=None if r["detail"] is None else json.loads(r["detail"]))
                          for r in self._con.execute("SELECT * FROM inputs WHERE solve_id = ? ORDER BY rowid",
                                                     (row["id"],))]
            rec.quantities = self.quantities(row["id"])
        return rec

    def quantities(self, solve_id: int) -> list:
        return [Quantity(name=r["name"], value=math.nan if r["value"] is None else r["value"], u=r["u"],
                         unit=r["unit"], position=r["position"])
                for r in self._con.execute("SELECT * FROM quantities WHERE solve_id = ? ORDER BY rowid", (solve_id,))]

    def get(self, key) -> SolveRecord | None:
        """A solve by id (int) or uid (str)."""
        q = "SELECT * FROM solves WHERE id = ?" if isinstance(key, int) else "SELECT * FROM solves WHERE uid = ?"
        row = self._con.execute(q, (key,)).fetchone()
        return None if row is None else self._row_to_record(row)

    def list(self, cell=None, kind=None, status=None, source=None, campaign_id=None, since_ns=None, limit=None,
             newest_first: bool = False, with_details: bool = False) -> list:
        where, args = [], []
        for col, v in (("cell", None if cell is None else cell_name(cell)), ("kind", kind), ("source", source),
                       ("campaign_id", campaign_id)):
            if v is not None:
                where.append(f"{col} = ?")
                args.append(v)
        if status is not None:
            where.append("status = ?")
            args.append(normalise_status(status))
        if since_ns is not None:
            where.append("created_ns >= ?")
            args.append(int(since_ns))
        q = "SELECT * FROM solves" + (" WHERE " + " AND ".join(where) if where else "")
        q += " ORDER BY id " + ("DESC" if newest_first else "ASC")
        if limit is not None:
            q += f" LIMIT {int(limit)}"
        return [self._row_to_record(r, with_details) for r in self._con.execute(q, args).fetchall()]

    def latest_valid(self, cell, kind, final_only: bool = False) -> SolveRecord | None:
        """The newest SUCCESS solve of a cell and kind (a failed solve never hides it) that no later
        record supersedes (:meth:`supersede`: e.g. a geometry later found inadequate)."""
        q = ("SELECT * FROM solves WHERE cell = ? AND kind = ? AND status = 'success' AND uid NOT IN "
             "(SELECT ref_uid FROM inputs WHERE role = 'supersedes' AND ref_uid IS NOT NULL)")
        if final_only:
            q += " AND final = 1"
        row = self._con.execute(q + " ORDER BY id DESC LIMIT 1", (cell_name(cell), kind)).fetchone()
        return None if row is None else self._row_to_record(row)

    def supersede(self, original: SolveRecord, status, message: str, extra: dict | None = None) -> SolveRecord:
        """Append a record that supersedes ``original`` with a new status (a verdict that came after
        the solve, e.g. ``poor_fit`` from the discrepancy engine). The original row is never changed:
        the new one copies its quantities, stamps and inputs, names it (input role ``supersedes``,
        ``ref_uid``) and carries ``result['supersedes']`` plus ``extra`` (e.g. the re-published message)."""
        if not original.uid:
            raise ValueError("supersede: the original record has no uid (was it stored?)")
        result = dict(original.result)
        result.pop("ros_msg", None)
        result["supersedes"] = {"uid": original.uid, "id": original.id, "status": original.status,
                                "message": original.message}
        result.update(extra or {})
        rec = SolveRecord(cell=original.cell, kind=original.kind, status=status, result=result,
                          source=original.source, message=message, campaign_id=original.campaign_id,
                          final=original.final, data_start_ns=original.data_start_ns,
                          data_end_ns=original.data_end_ns,
                          inputs=[Input(role="supersedes", ref_uid=original.uid)]
                          + [i for i in original.inputs if i.role != "supersedes"],
                          quantities=list(original.quantities))
        return self.record(rec)

    def superseded(self, uid: str) -> bool:
        """Whether a later record supersedes the solve ``uid``."""
        row = self._con.execute("SELECT 1 FROM inputs WHERE role = 'supersedes' AND ref_uid = ? LIMIT 1",
                                (uid,)).fetchone()
        return row is not None

    def trend(self, name: str, cell=None, kind=None, position=None, valid_only: bool = True) -> list:
        """[(solve id, created_ns, value, u, unit, campaign_id)] of one quantity over time."""
        q = ("SELECT s.id, s.created_ns, q.value, q.u, q.unit, s.campaign_id, s.data_end_ns FROM quantities q "
             "JOIN solves s ON s.id = q.solve_id WHERE q.name = ?")
        args = [name]
        if position is None:
            q += " AND q.position IS NULL"
        else:
            q += " AND q.position = ?"
            args.append(int(position))
        if cell is not None:
            q += " AND s.cell = ?"
            args.append(cell_name(cell))
        if kind is not None:
            q += " AND s.kind = ?"
            args.append(kind)
        if valid_only:
            q += " AND s.status = 'success'"
        return [tuple(r) for r in self._con.execute(q + " ORDER BY s.id", args)]

    def kinds(self, cell=None, status: str | None = "success") -> list:
        """The kinds of solves stored (of a cell; with a status), sorted."""
        q, args = "SELECT DISTINCT kind FROM solves WHERE 1 = 1", []
        if cell is not None:
            q += " AND cell = ?"
            args.append(cell_name(cell))
        if status is not None:
            q += " AND status = ?"
            args.append(normalise_status(status))
        return sorted(r[0] for r in self._con.execute(q, args))

    def count(self) -> int:
        return int(self._con.execute("SELECT COUNT(*) FROM solves").fetchone()[0])

    def integrity_ok(self) -> bool:
        return self._con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"


def open_history(path=None, logger=None):
    """A History, or None when disabled (``none``) or when it cannot be opened (the reason is logged:
    a calibration cell keeps working without its history)."""
    path = path if path not in (None, "") else default_path()
    if str(path).lower() in DISABLED:
        return None
    try:
        return History(path)
    except HistoryError as exc:
        if logger is not None:
            logger(f"calibration history not recorded: {exc}")
        return None


def compare_quantities(a: SolveRecord, b: SolveRecord, k: float = 2.0) -> list:
    """Quantities present in both records: [(name, position, unit, value_a, value_b, diff, u_diff, flagged)].

    ``u_diff`` = sqrt(u_a^2 + u_b^2) (the two solves taken as independent); ``flagged`` when
    |diff| > k u_diff (k = 2 by default: a change beyond its expanded uncertainty). Without both
    uncertainties nothing is flagged (u_diff None)."""
    qa = {(q.name, q.position): q for q in a.quantities}
    out = []
    for q in b.quantities:
        p = qa.get((q.name, q.position))
        if p is None:
            continue
        va, vb = _num(p.value), _num(q.value)
        if va is None or vb is None:
            continue
        d = vb - va
        ud = math.hypot(p.u, q.u) if (_num(p.u) is not None and _num(q.u) is not None) else None
        out.append((q.name, q.position, q.unit, va, vb, d, ud, ud is not None and abs(d) > k * ud))
    return out


__all__ = ["History", "HistoryError", "SolveRecord", "Input", "Quantity", "open_history", "content_hash",
           "sha256_file", "software_version", "default_path", "STATUS_WORDS", "STATUS_BY_CODE", "normalise_status",
           "cell_name", "compare_quantities", "plain"]
