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
import json
import os
import pathlib
import re
from dataclasses import dataclass, field
from typing import Iterator

import yaml

SEPARATOR = "=" * 80
PRIMITIVES = {
    "bool": 1, "byte": 1, "char": 1, "octet": 1, "uint8": 1, "int8": 1,
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
    """

    def __init__(self, path, compression: str = "zstd"):
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
        self._writer = Writer(self._fh, compression=comp)
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

@dataclass(frozen=True)
class RecordedMessage:
    """One message of a recording: topic, decoded message, log time, type name."""

    topic: str
    msg: object
    log_time_ns: int
    type_name: str


@dataclass
class ReadReport:
    """What a replay could and could not read."""

    files: list = field(default_factory=list)
    messages_read: int = 0
    messages_undecodable: int = 0
    errors: list = field(default_factory=list)   # human-readable problems (truncation, CRC, decode)

    @property
    def complete(self) -> bool:
        return not self.errors and self.messages_undecodable == 0


def recording_files(path) -> list[pathlib.Path]:
    """The .mcap files of a recording: the file itself, or those of a rosbag2 directory in order."""
    path = pathlib.Path(path)
    if path.is_file():
        return [path]
    if path.is_dir():
        meta = path / "metadata.yaml"
        if meta.is_file():
            try:
                info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
                files = [path / p for p in info.get("relative_file_paths", [])]
                if files and all(f.is_file() for f in files):
                    return files
            except Exception:  # noqa: BLE001 - fall back to the directory listing
                pass
        files = sorted(path.glob("*.mcap"))
        if files:
            return files
        raise FileNotFoundError(f"{path} holds no .mcap file")
    raise FileNotFoundError(f"no recording at {path}")


def iter_recording(path, topics=None, report: ReadReport | None = None) -> Iterator[RecordedMessage]:
    """Replay a recording as a generator, in file order (log-time order for rosbag2 writers).

    Parameters
    ----------
    path : str or Path
        A ``.mcap`` file or a rosbag2 directory.
    topics : iterable of str, optional
        Only these topics.
    report : ReadReport, optional
        Filled with counts and the problems met (truncation, corrupt chunks,
        undecodable messages); reading goes on past every problem it can.
    """
    from mcap.reader import StreamReader  # noqa: PLC0415
    from mcap.records import Channel, Chunk, Message, Schema  # noqa: PLC0415
    from mcap_ros2.decoder import DecoderFactory  # noqa: PLC0415

    report = report if report is not None else ReadReport()
    wanted = set(topics) if topics is not None else None
    factory = DecoderFactory()
    for file in recording_files(path):
        report.files.append(str(file))
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        decoders: dict[int, object] = {}
        with open(file, "rb") as fh:
            reader = StreamReader(fh, skip_magic=False, emit_chunks=False, validate_crcs=True)
            try:
                for rec in reader.records:
                    if isinstance(rec, Schema):
                        schemas[rec.id] = rec
                    elif isinstance(rec, Channel):
                        channels[rec.id] = rec
                    elif isinstance(rec, Message):
                        ch = channels.get(rec.channel_id)
                        if ch is None:
                            report.messages_undecodable += 1
                            continue
                        if wanted is not None and ch.topic not in wanted:
                            continue
                        schema = schemas.get(ch.schema_id)
                        dec = decoders.get(ch.id)
                        if dec is None:
                            try:
                                dec = factory.decoder_for(ch.message_encoding, schema)
                            except Exception as exc:  # noqa: BLE001
                                dec = None
                                report.errors.append(f"{file.name}: no decoder for {ch.topic}: {exc}")
                            decoders[ch.id] = dec or False
                        if not dec:
                            report.messages_undecodable += 1
                            continue
                        try:
                            msg = dec(rec.data)
                        except Exception as exc:  # noqa: BLE001
                            report.messages_undecodable += 1
                            if report.messages_undecodable <= 5:
                                report.errors.append(f"{file.name}: undecodable message on {ch.topic} "
                                                     f"at {rec.log_time} ns: {exc}")
                            continue
                        report.messages_read += 1
                        yield RecordedMessage(ch.topic, msg, rec.log_time, schema.name if schema else "")
                    elif isinstance(rec, Chunk):
                        pass
            except Exception as exc:  # noqa: BLE001 - truncated or corrupt file: keep what was read
                report.errors.append(f"{file.name}: stopped reading at byte {fh.tell()} of "
                                     f"{os.path.getsize(file)}: {type(exc).__name__}: {exc}")
