"""Campaign journal: the accepted input messages of a node's campaign, so a restarted node resumes it.

A node killed mid-campaign (SIGKILL, power cut of the host, OOM) loses its in-memory state: the
observations of the positions it had collected. The journal is an append-only file per (cell,
node) holding the serialized messages the node ACCEPTED into its campaign, in arrival order, and
the events that end the campaign. At start the node replays a journal that is not final through
the same code path as live messages: its state (accumulator, campaign guard, solves) is rebuilt
exactly, so the campaign then completes with a bit-identical result when the frames sent while
the node was down are re-sent (the node says which: the stamps after the journal's last one).

File format (little-endian), one record after another::

    b"MJ1" kind(1 byte) length(u32) crc32(u32) payload(length bytes)

kind ``H`` header (JSON: node, cell, version), ``M`` one serialized message (CDR bytes, as
``rclpy.serialization.serialize_message`` gives them), ``E`` an event (JSON: ``{"event": "final"|
"solved", "n_messages": messages accepted before it, ...}``; final: the campaign's final result was
published, nothing to resume unless messages follow). Each record is written with one ``write`` and flushed to
the operating system at once (``fsync`` too with ``fsync=True``): a process killed at any point
leaves at most one torn record at the end, which the reader detects (length past the end of the
file, bad magic or CRC), reports, and cuts off before appending. A journal is never read beyond
its first damaged record: what follows a damaged record cannot be trusted to be in order.

This module is plain Python (no rclpy): the node passes bytes in and gets bytes out.
"""

from __future__ import annotations

import json
import os
import pathlib
import re
import struct
import zlib

from ct_calib_nodes.io.atomic import write_bytes_atomic

MAGIC = b"MJ1"
_HEAD = struct.Struct("<3scII")
VERSION = 1
ENV_DIR = "METRO_JOURNAL_DIR"
DISABLED = ("none", "off", "false", "0")
MAX_RECORD_BYTES = 64 * 1024 * 1024       # an observation message is KiB: a larger length is damage


def default_dir(history_db: str = "") -> str:
    """``$METRO_JOURNAL_DIR``, else ``journal/`` beside the history database (its default location
    when ``history_db`` is empty or disabled)."""
    env = os.environ.get(ENV_DIR, "").strip()
    if env:
        return env
    from ct_calib_nodes.io.history import DISABLED as HIST_OFF, default_path  # noqa: PLC0415

    db = str(history_db or "").strip()
    if not db or db.lower() in HIST_OFF:
        db = default_path()
    return str(pathlib.Path(db).expanduser().resolve().parent / "journal")


def journal_path(directory: str, cell: str, node: str) -> pathlib.Path:
    """``<directory>/<cell>__<node>.journal``, the cell's slashes as ``+`` (``/`` -> ``root``)."""
    c = cell.strip("/").replace("/", "+") or "root"
    safe = re.sub(r"[^A-Za-z0-9_+.-]", "_", f"{c}__{node}")
    return pathlib.Path(directory) / f"{safe}.journal"


class JournalError(ValueError):
    pass


class Journal:
    """The state of one journal file after reading it, and appends to it.

    Attributes after :meth:`open`: ``messages`` (list of bytes, accepted messages in order),
    ``events`` (list of dicts), ``final`` (the campaign ended: nothing to resume), ``damaged``
    (None or a sentence: a torn or corrupt record cut off at byte ``valid_bytes``)."""

    def __init__(self, path, node: str, cell: str, fsync: bool = False):
        self.path = pathlib.Path(path)
        self.node, self.cell, self.fsync = node, cell, bool(fsync)
        self.messages: list = []
        self.events: list = []
        self.damaged = None
        self.valid_bytes = 0
        self._fh = None

    # --- reading ---------------------------------------------------------------------------------
    @property
    def final(self) -> bool:
        """The campaign ended: a ``final`` event after which no message was accepted."""
        return any(e.get("event") == "final" and e.get("n_messages") == len(self.messages) for e in self.events)

    def read(self) -> "Journal":
        """Read the file (absent = empty journal). A foreign header (another node or cell) is an error."""
        self.messages, self.events, self.damaged, self.valid_bytes = [], [], None, 0
        if not self.path.exists():
            return self
        data = self.path.read_bytes()
        off, header = 0, None
        while off < len(data):
            why = None
            if len(data) - off < _HEAD.size:
                why = f"a torn record header ({len(data) - off} B)"
            else:
                magic, kind, n, crc = _HEAD.unpack_from(data, off)
                if magic != MAGIC:
                    why = "no record magic"
                elif n > MAX_RECORD_BYTES or off + _HEAD.size + n > len(data):
                    why = f"a record of {n} B past the end of the file (torn write)"
                else:
                    payload = data[off + _HEAD.size: off + _HEAD.size + n]
                    if zlib.crc32(payload) != crc:
                        why = "a record whose CRC does not match"
            if why is not None:
                self.damaged = (f"journal {self.path}: {why} at byte {off} of {len(data)}; "
                                f"the {len(data) - off} B from there are dropped")
                break
            if kind == b"H":
                header = json.loads(payload.decode())
                if header.get("node") != self.node or header.get("cell") != self.cell:
                    raise JournalError(f"journal {self.path} belongs to node {header.get('node')!r} of cell "
                                       f"{header.get('cell')!r}, not {self.node!r} of {self.cell!r}")
            elif header is None:
                self.damaged = f"journal {self.path}: no header record; ignored"
                break
            elif kind == b"M":
                self.messages.append(bytes(payload))
            elif kind == b"E":
                self.events.append(json.loads(payload.decode()))
            off += _HEAD.size + n
            self.valid_bytes = off
        return self

    # --- writing ---------------------------------------------------------------------------------
    def _write(self, kind: bytes, payload: bytes):
        if self._fh is None:
            raise JournalError("journal not open for appending")
        self._fh.write(_HEAD.pack(MAGIC, kind, len(payload), zlib.crc32(payload)) + payload)
        self._fh.flush()
        if self.fsync:
            os.fsync(self._fh.fileno())

    def open_append(self):
        """Append after the last valid record (a torn tail is cut off first)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists() and self.valid_bytes < self.path.stat().st_size:
            with open(self.path, "r+b") as fh:
                fh.truncate(self.valid_bytes)
        self._fh = open(self.path, "ab")      # noqa: SIM115 - held open for the campaign
        if self.valid_bytes == 0:
            self._write(b"H", json.dumps({"node": self.node, "cell": self.cell, "version": VERSION}).encode())
            self.valid_bytes = self._fh.tell()
        return self

    def start_new(self):
        """Begin a new campaign: the old file is replaced (atomically: a new file renamed over it)."""
        self.close()
        payload = json.dumps({"node": self.node, "cell": self.cell, "version": VERSION}).encode()
        write_bytes_atomic(self.path, _HEAD.pack(MAGIC, b"H", len(payload), zlib.crc32(payload)) + payload)
        self.messages, self.events, self.damaged = [], [], None
        self.valid_bytes = self.path.stat().st_size
        self._fh = open(self.path, "ab")      # noqa: SIM115
        return self

    def append_message(self, data: bytes):
        self._write(b"M", bytes(data))
        self.messages.append(bytes(data))

    def append_event(self, event: str, **info):
        rec = {"event": event, **info}
        self._write(b"E", json.dumps(rec, sort_keys=True).encode())
        self.events.append(rec)

    def close(self):
        if self._fh is not None:
            try:
                self._fh.close()
            finally:
                self._fh = None
