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

import struct
from dataclasses import dataclass
from typing import Iterator

from ct_calib_nodes.io.mcap_io import ReadReport, RecordedMessage, iter_recording


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


def iter_recording_raw(path, topics=None, raw_topics=(), report: ReadReport | None = None,
                       types: dict | None = None) -> Iterator[RecordedMessage]:
    """Like ``mcap_io.iter_recording`` (same reader: damaged chunks skipped and reported), but
    the messages of ``raw_topics`` come as CDR bytes (``RecordedMessage.msg`` is a memoryview)."""
    return iter_recording(path, topics=topics, report=report, types=types, raw_topics=raw_topics)
