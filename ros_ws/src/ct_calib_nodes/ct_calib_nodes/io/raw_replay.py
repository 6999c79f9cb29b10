"""Fast replay of CT recordings: raw image messages and a zero-copy sensor_msgs/Image view.

``iter_recording_raw`` reads a recording like ``mcap_io.iter_recording`` (same order, same
ReadReport bookkeeping) but leaves the messages of ``raw_topics`` as their CDR bytes: the
generic decoder builds a Python object of a 2 MB image field by field, while
``ImageView.from_cdr`` reads the few header fields and points ``data`` at the pixel bytes
(a memoryview into the decompressed chunk, no copy). The bytes are what a worker process
gets; ``convert.array_from_image`` then checks and converts an ImageView exactly as it does
a decoded message, so the pixels, and everything computed from them, are bit for bit the
same.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from typing import Iterator

from ct_calib_nodes.io.mcap_io import ReadReport, RecordedMessage, recording_files


@dataclass(frozen=True)
class StampView:
    sec: int
    nanosec: int


@dataclass(frozen=True)
class HeaderView:
    stamp: StampView
    frame_id: str


@dataclass(frozen=True)
class ImageView:
    """The fields of a sensor_msgs/Image, ``data`` a memoryview of the serialized bytes."""

    header: HeaderView
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: memoryview

    @classmethod
    def from_cdr(cls, buf) -> "ImageView":
        """Parse a CDR-serialized sensor_msgs/Image (XCDR1, little or big endian).

        Raises ValueError naming what is wrong when the bytes are not one."""
        mv = memoryview(buf)
        if len(mv) < 4:
            raise ValueError("CDR message shorter than its encapsulation header")
        kind = mv[1]
        if mv[0] != 0 or kind not in (0, 1):
            raise ValueError(f"unsupported CDR encapsulation {bytes(mv[:2]).hex()}")
        e = "<" if kind == 1 else ">"
        body = mv[4:]
        pos = 0

        def u32():
            nonlocal pos
            pos = (pos + 3) & ~3
            if pos + 4 > len(body):
                raise ValueError("CDR Image truncated")
            (v,) = struct.unpack_from(e + "I", body, pos)
            pos += 4
            return v

        def string():
            nonlocal pos
            n = u32()
            if pos + n > len(body):
                raise ValueError("CDR Image truncated in a string")
            s = bytes(body[pos:pos + n]).rstrip(b"\0").decode("utf-8", "replace")
            pos += n
            return s

        sec = u32()
        sec = sec - (1 << 32) if sec >= (1 << 31) else sec        # int32
        nanosec = u32()
        frame_id = string()
        height, width = u32(), u32()
        encoding = string()
        if pos + 1 > len(body):
            raise ValueError("CDR Image truncated")
        is_big = body[pos]
        pos += 1
        step = u32()
        n = u32()
        if pos + n > len(body):
            raise ValueError(f"CDR Image data truncated: {len(body) - pos} of {n} bytes")
        return cls(HeaderView(StampView(sec, nanosec), frame_id), height, width, encoding, is_big, step,
                   body[pos:pos + n])


def iter_recording_raw(path, topics=None, raw_topics=(), report: ReadReport | None = None
                       ) -> Iterator[RecordedMessage]:
    """Like ``mcap_io.iter_recording``, but the messages of ``raw_topics`` come as CDR bytes
    (``RecordedMessage.msg`` is a memoryview), the others decoded."""
    from mcap.reader import StreamReader  # noqa: PLC0415
    from mcap.records import Channel, Message, Schema  # noqa: PLC0415
    from mcap_ros2.decoder import DecoderFactory  # noqa: PLC0415

    report = report if report is not None else ReadReport()
    wanted = set(topics) if topics is not None else None
    raw = set(raw_topics)
    factory = DecoderFactory()
    for file in recording_files(path):
        report.files.append(str(file))
        schemas, channels, decoders = {}, {}, {}
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
                        name = schema.name if schema else ""
                        if ch.topic in raw:
                            if ch.message_encoding != "cdr":
                                report.messages_undecodable += 1
                                continue
                            report.messages_read += 1
                            yield RecordedMessage(ch.topic, memoryview(rec.data), rec.log_time, name)
                            continue
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
                        yield RecordedMessage(ch.topic, msg, rec.log_time, name)
            except Exception as exc:  # noqa: BLE001 - truncated or corrupt file: keep what was read
                report.errors.append(f"{file.name}: stopped reading at byte {fh.tell()} of "
                                     f"{os.path.getsize(file)}: {type(exc).__name__}: {exc}")
