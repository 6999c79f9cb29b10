"""MCAP recordings in the layout rosbag2's MCAP storage writes, and their replay.

Writing (``Rosbag2McapWriter``):
- profile ``ros2``, schema encoding ``ros2msg`` with the full message
  definition text (the type's .msg text first, then every dependency preceded
  by a line of 80 ``=`` and ``MSG: pkg/msg/Type``, as rosbag2 does), message
  encoding ``cdr``, channel metadata ``offered_qos_profiles`` and
  ``topic_type_hash`` (RIHS01, from the installed type description);
- every message is stored with its exact CDR length. Bytes from a raw
  subscription are exact; ``serialize_message`` can append a few junk bytes
  (see ROS_WHEELS.md), so ``write`` trims to ``cdr_size(msg)``;
- either a bare ``.mcap`` file or a rosbag2 directory (``metadata.yaml`` plus
  ``<name>_0.mcap``).

Reading (``iter_recording``): a generator of ``RecordedMessage`` from a file
or a rosbag2 directory, decoded from the schema stored in the file itself
(mcap-ros2-support), so recordings made by other software replay without the
project's message packages. A truncated or corrupt file yields everything
readable and then reports what was not in ``ReadReport``.

This module needs no rclpy, except ``write(msg)`` and the definition lookup,
which use the installed message packages.
"""

from __future__ import annotations

import importlib
import io
import json
import os
import pathlib
import re
from dataclasses import dataclass, field
from typing import Iterator

import yaml

SEPARATOR = "=" * 80
PRIMITIVES = {
    "bool": 1, "boolean": 1, "byte": 1, "char": 1, "octet": 1, "uint8": 1, "int8": 1,
    "int16": 2, "uint16": 2, "int32": 4, "uint32": 4, "float": 4, "float32": 4,
    "int64": 8, "uint64": 8, "double": 8, "float64": 8,
}


def _ament_prefixes() -> list[str]:
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    venv = os.environ.get("VIRTUAL_ENV")
    if venv and venv not in prefixes:
        prefixes.append(venv)
    return prefixes


def _find_share_file(pkg: str, kind: str, name: str, ext: str) -> pathlib.Path:
    for prefix in _ament_prefixes():
        path = pathlib.Path(prefix) / "share" / pkg / kind / f"{name}.{ext}"
        if path.is_file():
            return path
    raise FileNotFoundError(
        f"no {pkg}/{kind}/{name}.{ext} under AMENT_PREFIX_PATH ({os.pathsep.join(_ament_prefixes()) or 'unset'}); "
        "source scripts/env.sh first")


def normalise_type(type_name: str) -> str:
    """'sensor_msgs/Image' or 'sensor_msgs/msg/Image' -> 'sensor_msgs/msg/Image'."""
    parts = type_name.strip().split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    if len(parts) == 3:
        return type_name.strip()
    raise ValueError(f"not a ROS 2 message type name: {type_name!r}")


_FIELD = re.compile(r"^\s*([A-Za-z_][\w/]*)(\[[^\]]*\])?(<=\d+)?\s+[A-Za-z_]\w*")


def _dependencies(pkg: str, text: str) -> list[str]:
    deps = []
    for line in text.splitlines():
        line = line.split("#", 1)[0]
        m = _FIELD.match(line)
        if not m:
            continue
        base = m.group(1)
        if base in PRIMITIVES or base in ("string", "wstring"):
            continue
        if "/" in base:
            dep = normalise_type(base)
        else:
            dep = f"{pkg}/msg/{base}"
        if dep not in deps:
            deps.append(dep)
    return deps


def message_definition(type_name: str) -> str:
    """Full ``ros2msg`` definition text of a message type, as rosbag2 stores it.

    Parameters
    ----------
    type_name : str
        'pkg/msg/Type' (or 'pkg/Type').

    Returns
    -------
    str
        The type's .msg text, then each dependency (depth first, once) after
        a line of 80 '=' and a line 'MSG: pkg/msg/Type'.
    """
    root = normalise_type(type_name)
    seen: list[str] = []
    texts: dict[str, str] = {}

    def visit(t: str):
        if t in texts:
            return
        pkg, _, name = t.split("/")
        text = _find_share_file(pkg, "msg", name, "msg").read_text(encoding="utf-8")
        texts[t] = text
        seen.append(t)
        for dep in _dependencies(pkg, text):
            visit(dep)

    visit(root)
    out = texts[root].rstrip("\n")
    for t in seen[1:]:
        out += f"\n{SEPARATOR}\nMSG: {t}\n" + texts[t].rstrip("\n")
    return out + "\n"


def import_message_type(type_name: str):
    """The Python class of an installed message type, e.g. 'sensor_msgs/msg/Image'."""
    pkg, kind, name = normalise_type(type_name).split("/")
    try:
        return getattr(importlib.import_module(f"{pkg}.{kind}"), name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"message type {type_name} is not installed: {exc}") from None


def type_hash(type_name: str) -> str:
    """RIHS01 type hash of an installed message type ('' if not available)."""
    pkg, _, name = normalise_type(type_name).split("/")
    try:
        data = json.loads(_find_share_file(pkg, "msg", name, "json").read_text())
    except FileNotFoundError:
        return ""
    for entry in data.get("type_hashes", []):
        if entry.get("type_name") == f"{pkg}/msg/{name}":
            return entry.get("hash_string", "")
    return ""


# --- exact CDR size --------------------------------------------------------------------------------

def _align(offset: int, n: int) -> int:
    return (offset + n - 1) // n * n


_SEQ = re.compile(r"^sequence<(.+?)(?:,\s*\d+)?>$")
_ARR = re.compile(r"^(.+)\[(\d+)\]$")


def _size_of(value, type_str: str, offset: int) -> int:
    m = _SEQ.match(type_str)
    if m:
        elem = m.group(1)
        offset = _align(offset, 4) + 4
        return _size_seq(value, elem, offset)
    m = _ARR.match(type_str)
    if m:
        return _size_seq(value, m.group(1), offset)
    if type_str.startswith("string"):
        data = value.encode("utf-8") if isinstance(value, str) else bytes(value)
        return _align(offset, 4) + 4 + len(data) + 1
    if type_str.startswith("wstring"):
        raise ValueError("wstring fields are not supported by cdr_size")
    if type_str in PRIMITIVES:
        n = PRIMITIVES[type_str]
        return _align(offset, n) + n
    return _size_msg(value, offset)


def _size_seq(value, elem: str, offset: int) -> int:
    n = len(value)
    if elem in PRIMITIVES:
        size = PRIMITIVES[elem]
        return (_align(offset, size) + size * n) if n else offset
    for item in value:
        offset = _size_of(item, elem, offset)
    return offset


def _size_msg(msg, offset: int) -> int:
    for name, type_str in msg.get_fields_and_field_types().items():
        offset = _size_of(getattr(msg, name), type_str, offset)
    return offset


def cdr_size(msg) -> int:
    """Exact length of the CDR serialisation of a ROS 2 message, with its 4-byte header."""
    return 4 + _size_msg(msg, 0)


def serialize_exact(msg) -> bytes:
    """``rclpy.serialization.serialize_message`` trimmed to the exact CDR length."""
    from rclpy.serialization import serialize_message  # noqa: PLC0415 (io layer may use rclpy)

    data = serialize_message(msg)
    n = cdr_size(msg)
    if n > len(data):
        raise RuntimeError(f"cdr_size {n} exceeds serialized length {len(data)} for {type(msg).__name__}")
    return data[:n]


# --- writer ---------------------------------------------------------------------------------------

QOS_RELIABLE_LATCHED = [dict(history="keep_last", depth=1, reliability="reliable",
                             durability="transient_local", deadline=dict(sec=0, nsec=0),
                             lifespan=dict(sec=0, nsec=0), liveliness="automatic",
                             liveliness_lease_duration=dict(sec=0, nsec=0),
                             avoid_ros_namespace_conventions=False)]
QOS_RELIABLE_VOLATILE = [dict(QOS_RELIABLE_LATCHED[0], depth=10, durability="volatile")]


@dataclass
class _Topic:
    channel_id: int
    type_name: str
    qos: list
    hash: str
    count: int = 0


class Rosbag2McapWriter:
    """Write a recording as rosbag2's MCAP storage plugin does.

    Parameters
    ----------
    path : str or Path
        A ``.mcap`` file, or a directory (created; must not exist or be
        empty) that becomes a rosbag2 bag with ``metadata.yaml``.
    compression : {"zstd", "lz4", ""}
        MCAP chunk compression (rosbag2's default MCAP profile uses zstd).
    chunk_size : int
        Uncompressed bytes after which a chunk is closed (a damaged chunk costs its own messages
        only; a crashed writer loses the chunk in progress).
    """

    def __init__(self, path, compression: str = "zstd", chunk_size: int = 1024 * 1024):
        from mcap.writer import CompressionType, Writer  # noqa: PLC0415

        path = pathlib.Path(path)
        if path.suffix == ".mcap":
            self.directory = None
            self.file_path = path
            path.parent.mkdir(parents=True, exist_ok=True)
        else:
            if path.exists() and any(path.iterdir()):
                raise FileExistsError(f"bag directory {path} exists and is not empty")
            path.mkdir(parents=True, exist_ok=True)
            self.directory = path
            self.file_path = path / f"{path.name}_0.mcap"
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "": CompressionType.NONE}[compression]
        self._fh = open(self.file_path, "wb")
        self._writer = Writer(self._fh, compression=comp, chunk_size=int(chunk_size))
        self._writer.start(profile="ros2", library="metro ct_calib_nodes mcap_io")
        self._topics: dict[str, _Topic] = {}
        self._schemas: dict[str, int] = {}
        self._t0 = None
        self._t1 = None
        self._closed = False
        self._compression = compression

    def add_topic(self, topic: str, type_name: str, qos=None) -> None:
        """Register a topic (idempotent). ``qos``: list of rosbag2 QoS dicts."""
        type_name = normalise_type(type_name)
        if topic in self._topics:
            if self._topics[topic].type_name != type_name:
                raise ValueError(f"topic {topic} already registered as {self._topics[topic].type_name}")
            return
        if type_name not in self._schemas:
            self._schemas[type_name] = self._writer.register_schema(
                name=type_name, encoding="ros2msg", data=message_definition(type_name).encode("utf-8"))
        qos = list(qos) if qos is not None else QOS_RELIABLE_VOLATILE
        h = type_hash(type_name)
        meta = {"offered_qos_profiles": yaml.safe_dump(qos, sort_keys=False)}
        if h:
            meta["topic_type_hash"] = h
        cid = self._writer.register_channel(topic=topic, message_encoding="cdr",
                                            schema_id=self._schemas[type_name], metadata=meta)
        self._topics[topic] = _Topic(cid, type_name, qos, h)

    def write_raw(self, topic: str, data: bytes, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        """Store exact CDR bytes (e.g. from a raw subscription) on a registered topic."""
        t = self._topics.get(topic)
        if t is None:
            raise KeyError(f"topic {topic} not registered; call add_topic first")
        log_time_ns = int(log_time_ns)
        self._writer.add_message(channel_id=t.channel_id, log_time=log_time_ns, data=bytes(data),
                                 publish_time=int(publish_time_ns if publish_time_ns is not None else log_time_ns),
                                 sequence=t.count)
        t.count += 1
        self._t0 = log_time_ns if self._t0 is None else min(self._t0, log_time_ns)
        self._t1 = log_time_ns if self._t1 is None else max(self._t1, log_time_ns)

    def write(self, topic: str, msg, log_time_ns: int, type_name: str | None = None) -> None:
        """Serialize an rclpy message (exact length) and store it."""
        if topic not in self._topics:
            if type_name is None:
                mod = type(msg).__module__.split(".")
                type_name = f"{mod[0]}/msg/{type(msg).__name__}"
            self.add_topic(topic, type_name)
        self.write_raw(topic, serialize_exact(msg), log_time_ns)

    def flush(self) -> None:
        """Close the chunk in progress and hand everything written so far to the operating system:
        a writer killed afterwards leaves a file readable up to here."""
        if not self._closed:
            self._writer.flush()
            self._fh.flush()

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self._topics.values())

    def close(self) -> pathlib.Path:
        """Finish the file (and metadata.yaml); returns the path of the recording."""
        if self._closed:
            return self.directory or self.file_path
        self._writer.finish()
        self._fh.close()
        self._closed = True
        if self.directory is not None:
            self._write_metadata()
            return self.directory
        return self.file_path

    def _write_metadata(self) -> None:
        t0 = self._t0 or 0
        dur = (self._t1 - self._t0) if self._t0 is not None else 0
        info = {
            "version": 9,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": dur},
            "starting_time": {"nanoseconds_since_epoch": t0},
            "message_count": self.message_count,
            "topics_with_message_count": [
                {"topic_metadata": {"name": name, "type": t.type_name, "serialization_format": "cdr",
                                    "offered_qos_profiles": t.qos, "type_description_hash": t.hash},
                 "message_count": t.count}
                for name, t in self._topics.items()
            ],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [self.file_path.name],
            "files": [{"path": self.file_path.name, "starting_time": {"nanoseconds_since_epoch": t0},
                       "duration": {"nanoseconds": dur}, "message_count": self.message_count}],
            "custom_data": {},
            "ros_distro": "jazzy",
        }
        with open(self.directory / "metadata.yaml", "w", encoding="utf-8") as f:
            yaml.safe_dump({"rosbag2_bagfile_information": info}, f, sort_keys=False)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# --- reader ---------------------------------------------------------------------------------------
#
# The MCAP records are parsed here rather than with mcap.reader.StreamReader, which stops at the
# first damaged record: one flipped bit in an early chunk then costs the rest of the file. This
# parser checks every chunk on its own (header consistent with the record length, size within
# bounds, decompression, CRC of the uncompressed records) and skips only a chunk that fails,
# then reads on. After a record whose length cannot be trusted it resynchronises on the next
# record that has the exact layout of a chunk (opcode, length, compression name and records
# length all consistent: a chance match is practically impossible), using the summary's chunk
# index when the file has an intact one. What was skipped is reported: bytes, the messages the
# file's own indexes say were there (per topic), and their log-time range.
#
# Allocation is bounded by the input: the file is memory-mapped, never read whole; a chunk is
# decompressed by a streaming decompressor that stops at the size its header states, and that
# size must not exceed ``MAX_CHUNK_BYTES``; message decoding reads slices of the chunk.

MAGIC = b"\x89MCAP0\r\n"
MAX_CHUNK_BYTES = 1 << 30          # largest uncompressed chunk accepted (a 4096^2 float frame is 64 MiB)
_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 1, 2, 3, 4, 5, 6
_OP_MESSAGE_INDEX, _OP_CHUNK_INDEX, _OP_STATISTICS, _OP_DATA_END = 7, 8, 11, 15
_COMPRESSIONS = ("", "zstd", "lz4")


@dataclass(frozen=True)
class RecordedMessage:
    """One message of a recording: topic, decoded message, log time, type name."""

    topic: str
    msg: object
    log_time_ns: int
    type_name: str


@dataclass
class LostSpan:
    """A part of a file that could not be read.

    ``messages`` is what the file's own indexes say was there (None: unknown, e.g. a truncated
    file has no index); ``by_topic`` splits it per topic when known; ``t0_ns``/``t1_ns`` the log
    time range of what was lost (None: unknown).
    """

    file: str
    offset: int
    nbytes: int
    reason: str
    messages: int | None = None
    by_topic: dict = field(default_factory=dict)
    t0_ns: int | None = None
    t1_ns: int | None = None

    def describe(self) -> str:
        what = "an unknown number of messages" if self.messages is None else f"{self.messages} message(s)"
        if self.by_topic:
            what += " (" + ", ".join(f"{t}: {n}" for t, n in sorted(self.by_topic.items())) + ")"
        when = ""
        if self.t0_ns is not None:
            when = f", log time {self.t0_ns} to {self.t1_ns if self.t1_ns is not None else 'end'} ns"
        return (f"{self.file}: lost {self.nbytes} bytes at byte {self.offset}: {self.reason}; "
                f"{what}{when}")


@dataclass
class ReadReport:
    """What a replay could and could not read."""

    files: list = field(default_factory=list)
    messages_read: int = 0
    messages_undecodable: int = 0
    errors: list = field(default_factory=list)   # human-readable problems (truncation, CRC, decode)
    lost: list = field(default_factory=list)     # LostSpan per unreadable part of a file
    undecodable_by_topic: dict = field(default_factory=dict)
    chunks_read: int = 0
    wrong_type: int = 0                           # messages whose topic carried an unexpected type

    @property
    def complete(self) -> bool:
        return not self.errors and self.messages_undecodable == 0 and not self.lost

    @property
    def bytes_lost(self) -> int:
        return sum(s.nbytes for s in self.lost)

    @property
    def messages_lost(self) -> int | None:
        """Messages the files' indexes say were in the unreadable parts (None if any part is unknown)."""
        if any(s.messages is None for s in self.lost):
            return None
        return sum(s.messages for s in self.lost)

    def summary(self) -> str:
        """One line: what was read and what was lost."""
        text = f"{self.messages_read} message(s) read from {len(self.files)} file(s)"
        if self.lost:
            n = self.messages_lost
            text += (f"; {len(self.lost)} unreadable part(s), {self.bytes_lost} bytes, "
                     f"{'an unknown number of' if n is None else n} message(s) lost")
        if self.messages_undecodable:
            text += f"; {self.messages_undecodable} undecodable message(s)"
        return text


class RecordingError(ValueError):
    """A recording that cannot be read at all (missing, empty folder, not MCAP)."""


def recording_files(path) -> list[pathlib.Path]:
    """The .mcap files of a recording: the file itself, or those of a rosbag2 directory in order.

    Raises RecordingError (a FileNotFoundError too) naming what is missing.
    """
    path = pathlib.Path(path)
    if path.is_file():
        return [path]
    if path.is_dir():
        meta = path / "metadata.yaml"
        if meta.is_file():
            try:
                info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
                files = [path / pathlib.PurePath(p).name for p in info.get("relative_file_paths", [])]
                if files and all(f.is_file() for f in files):
                    return files
            except Exception:  # noqa: BLE001 - fall back to the directory listing
                pass
        files = sorted(path.glob("*.mcap"))
        if files:
            return files
        raise _NoRecording(f"{path} is a folder that holds no .mcap file (expected a .mcap file or a rosbag2 "
                           "directory with one)")
    raise _NoRecording(f"no recording at {path}")


class _NoRecording(RecordingError, FileNotFoundError):
    pass


class _Bad(Exception):
    """A record that fails its checks."""


def _u16(b, o):
    return int.from_bytes(b[o:o + 2], "little")


def _u32(b, o):
    return int.from_bytes(b[o:o + 4], "little")


def _u64(b, o):
    return int.from_bytes(b[o:o + 8], "little")


def _need(b, o, n):
    if o + n > len(b):
        raise _Bad(f"record ends {o + n - len(b)} byte(s) early")


def _str(b, o):
    _need(b, o, 4)
    n = _u32(b, o)
    _need(b, o + 4, n)
    try:
        return bytes(b[o + 4:o + 4 + n]).decode("utf-8"), o + 4 + n
    except UnicodeDecodeError as exc:
        raise _Bad(f"string is not UTF-8: {exc}") from None


def _parse_schema(c):
    from mcap.records import Schema  # noqa: PLC0415

    _need(c, 0, 2)
    sid = _u16(c, 0)
    name, o = _str(c, 2)
    enc, o = _str(c, o)
    _need(c, o, 4)
    n = _u32(c, o)
    _need(c, o + 4, n)
    return Schema(id=sid, name=name, encoding=enc, data=bytes(c[o + 4:o + 4 + n]))


def _parse_channel(c):
    _need(c, 0, 4)
    cid, sid = _u16(c, 0), _u16(c, 2)
    topic, o = _str(c, 4)
    enc, o = _str(c, o)
    return cid, sid, topic, enc


def _parse_chunk_header(c, total=None):
    """(start, end, uncompressed size, crc, compression, records offset, records length) or _Bad.

    ``c`` is the chunk record's content, or its first bytes with ``total`` the content length."""
    total = len(c) if total is None else total
    _need(c, 0, 28)
    t0, t1, usize, crc = _u64(c, 0), _u64(c, 8), _u64(c, 16), _u32(c, 24)
    _need(c, 28, 4)
    n = _u32(c, 28)
    if n > 8:
        raise _Bad(f"compression name of {n} bytes")
    comp = bytes(c[32:32 + n]).decode("ascii", "replace")
    if comp not in _COMPRESSIONS:
        raise _Bad(f"unknown chunk compression {comp!r}")
    o = 32 + n
    _need(c, o, 8)
    rlen = _u64(c, o)
    if o + 8 + rlen != total:
        raise _Bad(f"chunk records length {rlen} does not match the record length {total}")
    if usize > MAX_CHUNK_BYTES:
        raise _Bad(f"chunk claims {usize} uncompressed bytes (more than the {MAX_CHUNK_BYTES} accepted)")
    if comp == "" and usize != rlen:
        raise _Bad(f"uncompressed chunk of {rlen} bytes claims {usize}")
    return t0, t1, usize, crc, comp, o + 8, rlen


def _decompress(comp: str, data, size: int) -> bytes:
    """Decompress at most ``size`` bytes (the chunk header's size), streaming: allocation is bounded
    by the declared size and by what the data really expands to, never by a size field inside the
    compressed stream."""
    if comp == "":
        return bytes(data)
    if comp == "zstd":
        import zstandard  # noqa: PLC0415

        try:
            declared = zstandard.frame_content_size(data)
        except zstandard.ZstdError as exc:
            raise _Bad(f"zstd frame header unreadable: {exc}") from None
        if declared == size:     # the frame states the same size as the chunk: one call, one allocation
            out = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
            if len(out) != size:
                raise _Bad(f"chunk decompresses to {len(out)} bytes, its header says {size}")
            return out
        reader = zstandard.ZstdDecompressor().stream_reader(bytes(data), read_across_frames=True)
    else:
        import lz4.frame  # noqa: PLC0415

        reader = lz4.frame.LZ4FrameFile(io.BytesIO(bytes(data)), mode="rb")
    parts, got = [], 0
    with reader:
        while got <= size:
            block = reader.read(min(1 << 20, size + 1 - got))
            if not block:
                break
            parts.append(block)
            got += len(block)
    if got != size:
        raise _Bad(f"chunk decompresses to {'more than ' if got > size else ''}{min(got, size + 1) if got <= size else size} "
                   f"bytes, its header says {size}")
    return b"".join(parts)


class _FileReader:
    """Record-level reader of one MCAP file that survives damage (see the section comment)."""

    def __init__(self, file: pathlib.Path, buf, report: ReadReport):
        self.file, self.buf, self.report = file, buf, report
        self.size = len(buf)
        self.schemas: dict = {}
        self.channels: dict = {}      # id -> (topic, schema id, message encoding)
        self.chunk_index: list = []   # (offset, length, t0, t1, message-index offsets) from the summary
        self.stats_count = None
        self.seen = 0                 # messages met in the data section, every topic
        self._read_summary()

    # summary: schemas and channels (so a damaged first chunk does not orphan every later one),
    # the chunk index (resynchronisation points, lost-message counts), the statistics
    def _read_summary(self):
        b, n = self.buf, self.size
        if n < 8 + 9 + 20 + 8 or bytes(b[n - 8:]) != MAGIC:
            return
        f = n - 8 - 29
        if b[f] != _OP_FOOTER or _u64(b, f + 1) != 20:
            return
        start, crc = _u64(b, f + 9), _u32(b, f + 25)
        if not 8 <= start < f:
            return
        if crc:
            import zlib  # noqa: PLC0415

            if zlib.crc32(b[start:f + 25]) != crc:
                self.report.errors.append(f"{self.file.name}: summary section fails its CRC: not used")
                return
        o = start
        try:
            while o + 9 <= f:
                op, ln = b[o], _u64(b, o + 1)
                c = b[o + 9:o + 9 + ln]
                if o + 9 + ln > f:
                    break
                if op == _OP_SCHEMA:
                    s = _parse_schema(c)
                    self.schemas[s.id] = s
                elif op == _OP_CHANNEL:
                    cid, sid, topic, enc = _parse_channel(c)
                    self.channels[cid] = (topic, sid, enc)
                elif op == _OP_CHUNK_INDEX:
                    _need(c, 0, 36)
                    t0, t1, off, length = _u64(c, 0), _u64(c, 8), _u64(c, 16), _u64(c, 24)
                    m = _u32(c, 32)
                    _need(c, 36, m)
                    idx = {_u16(c, 36 + 10 * i): _u64(c, 38 + 10 * i) for i in range(m // 10)}
                    self.chunk_index.append((off, length, t0, t1, idx))
                elif op == _OP_STATISTICS:
                    _need(c, 8, 0)
                    self.stats_count = _u64(c, 0)
                o += 9 + ln
        except _Bad:
            pass
        self.chunk_index.sort()

    def _is_chunk_at(self, o: int) -> bool:
        b = self.buf
        if o + 9 > self.size or b[o] != _OP_CHUNK:
            return False
        ln = _u64(b, o + 1)
        if o + 9 + ln > self.size:
            return False
        try:
            _parse_chunk_header(b[o + 9:o + 9 + min(ln, 64)], ln)
        except _Bad:
            return False
        return True

    def _is_end_at(self, o: int) -> bool:
        b = self.buf
        return (o + 13 <= self.size and b[o] == _OP_DATA_END and _u64(b, o + 1) == 4) or \
               (o + 29 <= self.size and b[o] == _OP_FOOTER and _u64(b, o + 1) == 20)

    def _resync(self, start: int):
        """Offset of the next intact-looking chunk (or of the data end) at or after ``start``."""
        for off, *_ in self.chunk_index:
            if off >= start and self._is_chunk_at(off):
                best = off
                break
        else:
            best = None
        b = self.buf
        o = start
        limit = best if best is not None else self.size
        while o < limit:
            o6 = b.find(bytes([_OP_CHUNK]), o, limit)
            o15 = b.find(bytes([_OP_DATA_END]), o, limit)
            cands = [x for x in (o6, o15) if x >= 0]
            if not cands:
                break
            o = min(cands)
            if self._is_chunk_at(o) or self._is_end_at(o):
                return o
            o += 1
        return best

    def _index_counts(self, after: int, chunk_off: int):
        """Messages per channel listed by the message-index records that follow a chunk (or by the
        summary's chunk index): {channel id: (count, t0, t1)}, or None when unknown."""
        b = self.buf
        out = {}
        o = after
        while o + 9 <= self.size and b[o] == _OP_MESSAGE_INDEX:
            ln = _u64(b, o + 1)
            if o + 9 + ln > self.size or ln < 6:
                break
            c = b[o + 9:o + 9 + ln]
            cid, m = _u16(c, 0), _u32(c, 2)
            if 6 + m > ln or m % 16:
                break
            times = [_u64(c, 6 + 16 * i) for i in range(m // 16)]
            out[cid] = (len(times), min(times, default=None), max(times, default=None))
            o += 9 + ln
        if out:
            return out
        for off, _length, _t0, _t1, idx in self.chunk_index:
            if off == chunk_off and idx:
                return {cid: (self._index_len(io), None, None) for cid, io in idx.items()}
        return None

    def _index_len(self, o):
        b = self.buf
        if o + 15 > self.size or b[o] != _OP_MESSAGE_INDEX:
            return 0
        return _u32(b, o + 11) // 16

    def _lost(self, offset, nbytes, reason, counts=None, t0=None, t1=None):
        span = LostSpan(self.file.name, int(offset), int(nbytes), reason)
        if counts is not None:
            span.messages = sum(n for n, _a, _b in counts.values())
            for cid, (n, a, z) in counts.items():
                topic = self.channels.get(cid, (f"channel {cid}",))[0]
                span.by_topic[topic] = span.by_topic.get(topic, 0) + n
                if a is not None:
                    t0 = a if t0 is None else min(t0, a)
                    t1 = z if t1 is None else max(t1, z)
        elif self.chunk_index:   # a gap: the summary knows which chunks lay in it
            inside = [c for c in self.chunk_index if offset <= c[0] < offset + nbytes]
            if inside:
                span.messages = 0
                for off, _ln, a, z, idx in inside:
                    for cid, io in idx.items():
                        k = self._index_len(io)
                        span.messages += k
                        topic = self.channels.get(cid, (f"channel {cid}",))[0]
                        span.by_topic[topic] = span.by_topic.get(topic, 0) + k
                    t0 = a if t0 is None else min(t0, a)
                    t1 = z if t1 is None else max(t1, z)
            elif nbytes and offset + nbytes >= self.size:
                span.messages = None
        span.t0_ns, span.t1_ns = t0, t1
        self.report.lost.append(span)
        self.report.errors.append(span.describe())

    def records(self):
        """Yield (opcode, content) of the data section's readable records, chunks opened."""
        b, n = self.buf, self.size
        if n < 8 or bytes(b[:8]) != MAGIC:
            if n == 0:
                raise RecordingError(f"{self.file} is empty")
            o = self._resync(0)
            if o is None:
                raise RecordingError(f"{self.file} is not an MCAP file (no MCAP magic, no readable chunk)")
            self._lost(0, o, "no MCAP magic at the start")
        else:
            o = 8
        t_last = None
        while o < n:
            if o + 9 > n:
                self._lost(o, n - o, "file ends inside a record header (truncated: recording not closed?)",
                           t0=t_last)
                return
            op, ln = b[o], _u64(b, o + 1)
            end = o + 9 + ln
            if op == _OP_FOOTER or op == _OP_DATA_END and ln == 4:
                return
            if not 1 <= op <= 15 or end > n:
                nxt = self._resync(o + 1)
                if nxt is None:
                    why = ("file ends inside a record (truncated: recording not closed?)" if 1 <= op <= 15
                           else f"unreadable bytes (record opcode {op}) to the end of the file")
                    self._lost(o, n - o, why, t0=t_last)
                    return
                self._lost(o, nxt - o, f"unreadable record (opcode {op}, length {ln}); read on at byte {nxt}")
                o = nxt
                continue
            c = b[o + 9:end]
            if op == _OP_CHUNK:
                try:
                    t0, t1, usize, crc, comp, ro, rl = _parse_chunk_header(c)
                    try:
                        data = _decompress(comp, memoryview(c)[ro:ro + rl], usize)
                    except _Bad:
                        raise
                    except Exception as exc:  # noqa: BLE001 - any codec error is a damaged chunk
                        raise _Bad(f"{comp} decompression failed: {exc}") from None
                    if crc:
                        import zlib  # noqa: PLC0415

                        got = zlib.crc32(data)
                        if got != crc:
                            raise _Bad(f"CRC mismatch (stored {crc:08x}, computed {got:08x})")
                    inner = list(self._inner(data))
                except _Bad as exc:
                    hdr = None
                    try:
                        hdr = _parse_chunk_header(c[:64], len(c))
                    except _Bad:
                        pass
                    if hdr is None:     # the length itself may be wrong: find the next chunk
                        nxt = self._resync(o + 1)
                        nxt = n if nxt is None else nxt
                        self._lost(o, nxt - o, f"damaged chunk: {exc}; read on at byte {nxt}")
                        o = nxt
                        continue
                    self._lost(o, end - o, f"damaged chunk: {exc}", self._index_counts(end, o), hdr[0], hdr[1])
                    o = end
                    continue
                self.report.chunks_read += 1
                for rec in inner:
                    if rec[0] == _OP_MESSAGE:
                        t_last = rec[3]
                    yield rec
            elif op in (_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE):
                try:
                    rec = self._one(op, c)
                except _Bad as exc:
                    self._lost(o, end - o, f"bad record (opcode {op}): {exc}")
                    rec = None
                if rec is not None:
                    if rec[0] == _OP_MESSAGE:
                        t_last = rec[3]
                    yield rec
            o = end
        self._lost(n, 0, "file ends at a record boundary without its data-end record and summary "
                         "(truncated, or the writer was stopped before closing it)", t0=t_last)

    def _inner(self, data):
        o, n = 0, len(data)
        while o < n:
            if o + 9 > n:
                raise _Bad("chunk records end inside a record header")
            op, ln = data[o], _u64(data, o + 1)
            if o + 9 + ln > n:
                raise _Bad(f"record of {ln} bytes overruns its chunk")
            rec = self._one(op, memoryview(data)[o + 9:o + 9 + ln])
            if rec is not None:
                yield rec
            o += 9 + ln

    def _one(self, op, c):
        if op == _OP_SCHEMA:
            s = _parse_schema(c)
            self.schemas[s.id] = s
            return None
        if op == _OP_CHANNEL:
            cid, sid, topic, enc = _parse_channel(c)
            self.channels[cid] = (topic, sid, enc)
            return None
        if op == _OP_MESSAGE:
            _need(c, 0, 22)
            self.seen += 1
            return (_OP_MESSAGE, _u16(c, 0), _u64(c, 6), _u64(c, 14), c[22:])
        return None


def _schema_lacks(schema, type_name: str) -> list:
    """Fields of the installed ``type_name`` that the schema text's own message does not define
    (empty when it defines them all, or when the type is not installed here)."""
    try:
        fields = import_message_type(type_name).get_fields_and_field_types()
    except ValueError:
        return []
    text = bytes(schema.data).decode("utf-8", "replace").split(SEPARATOR, 1)[0]
    names = set()
    for line in text.splitlines():
        m = _FIELD.match(line.split("#", 1)[0])
        if m:
            names.add(m.group(0).split()[-1])
    return [f for f in fields if f not in names]


def iter_recording(path, topics=None, report: ReadReport | None = None,
                   types: dict | None = None, raw_topics=()) -> Iterator[RecordedMessage]:
    """Replay a recording as a generator, in file order (log-time order for rosbag2 writers).

    Parameters
    ----------
    path : str or Path
        A ``.mcap`` file or a rosbag2 directory.
    topics : iterable of str, optional
        Only these topics.
    report : ReadReport, optional
        Filled with counts and the problems met: damaged chunks (skipped, reading goes on after
        them), truncation, unreadable stretches, undecodable messages, each with what was lost.
    types : dict, optional
        ``{topic: 'pkg/msg/Type'}``: messages on these topics whose schema names another type,
        or whose schema text lacks fields of the installed type, are counted as undecodable
        (``report.wrong_type``) instead of yielded. A key may also be a compiled ``re.Pattern``
        (topics it matches, e.g. every ``/picms/camera_N/image_raw``); exact names come first.
    raw_topics : iterable of str, optional
        Messages on these topics come undecoded: ``RecordedMessage.msg`` is a memoryview of
        their CDR bytes (one copy out of the decompressed chunk), for readers that parse only a
        few fields and hand the bytes on (io/raw_replay.py). Their encoding must be ``cdr``.

    Raises
    ------
    RecordingError
        Nothing to read at all: no recording at ``path``, a folder without .mcap, an empty file
        or one that holds no MCAP data. Damage inside a file never raises.
    """
    import mmap  # noqa: PLC0415

    from mcap_ros2.decoder import DecoderFactory  # noqa: PLC0415

    report = report if report is not None else ReadReport()
    wanted = set(topics) if topics is not None else None
    expect = {t: normalise_type(v) for t, v in (types or {}).items() if isinstance(t, str)}
    expect_re = [(t, normalise_type(v)) for t, v in (types or {}).items() if not isinstance(t, str)]

    def expected(topic):
        if topic not in expect:
            expect[topic] = next((v for pat, v in expect_re if pat.match(topic)), None)
        return expect[topic]
    raw = set(raw_topics)
    factory = DecoderFactory()

    def bad(topic, text):
        report.messages_undecodable += 1
        report.undecodable_by_topic[topic] = report.undecodable_by_topic.get(topic, 0) + 1
        if report.undecodable_by_topic[topic] <= 3:
            report.errors.append(text)

    def one_file(file):
        with open(file, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size == 0:
                raise RecordingError(f"{file} is empty")
            mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)   # slices of it are copies
            try:
                fr = _FileReader(file, mm, report)
                decoders: dict = {}
                for _op, cid, log_time, _pub, data in fr.records():
                    ch = fr.channels.get(cid)
                    if ch is None:
                        bad(f"channel {cid}", f"{file.name}: message on unknown channel {cid} at {log_time} ns "
                                              "(its channel record was lost)")
                        continue
                    topic, sid, enc = ch
                    if wanted is not None and topic not in wanted:
                        continue
                    schema = fr.schemas.get(sid)
                    tname = normalise_type(schema.name) if schema is not None and schema.name.count("/") in (1, 2) \
                        else (schema.name if schema is not None else "")
                    want = expected(topic)
                    if want is not None and tname != want:
                        report.wrong_type += 1
                        bad(topic, f"{file.name}: {topic} carries {tname or 'no schema'}, expected {want}")
                        continue
                    if topic in raw:
                        if enc != "cdr":
                            bad(topic, f"{file.name}: {topic} has message encoding {enc!r}, not cdr")
                            continue
                        report.messages_read += 1
                        yield RecordedMessage(topic, memoryview(bytes(data)), log_time, tname)
                        continue
                    key = (cid, sid)
                    dec = decoders.get(key)
                    if dec is None:
                        try:
                            if schema is None:
                                raise ValueError(f"schema {sid} is missing")
                            lacks = _schema_lacks(schema, want) if want is not None else []
                            if lacks:
                                raise ValueError(f"its schema text lacks the fields {lacks} of {want}")
                            dec = factory.decoder_for(enc, schema)
                            if dec is None:
                                raise ValueError(f"no decoder for message encoding {enc!r} "
                                                 f"and schema encoding {schema.encoding!r}")
                        except Exception as exc:  # noqa: BLE001 - a bad schema text is bad input
                            report.errors.append(f"{file.name}: cannot decode {topic}: {exc}")
                            dec = False
                        decoders[key] = dec
                    if not dec:
                        bad(topic, f"{file.name}: undecodable message on {topic} at {log_time} ns")
                        continue
                    try:
                        msg = dec(bytes(data))
                    except Exception as exc:  # noqa: BLE001
                        bad(topic, f"{file.name}: undecodable message on {topic} at {log_time} ns: "
                                   f"{type(exc).__name__}: {exc}")
                        continue
                    report.messages_read += 1
                    yield RecordedMessage(topic, msg, log_time, tname)
                if fr.stats_count is not None and fr.seen < fr.stats_count and not fr.report.lost:
                    report.errors.append(f"{file.name}: the summary lists {fr.stats_count} messages, "
                                         f"{fr.seen} were found")
            finally:
                fr = None
                mm.close()

    files = recording_files(path)
    failed = []
    for file in files:
        report.files.append(str(file))
        try:
            yield from one_file(file)
        except RecordingError as exc:      # one unreadable file of several: say so, read the others
            if len(files) == 1:
                raise
            failed.append(exc)
            span = LostSpan(file.name, 0, file.stat().st_size, f"unreadable file: {exc}")
            report.lost.append(span)
            report.errors.append(span.describe())
    if failed and len(failed) == len(files):
        raise failed[0]
    if report.lost:
        report.errors.append(f"read with losses: {report.summary()}")
