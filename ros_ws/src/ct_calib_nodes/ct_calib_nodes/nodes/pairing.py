"""Pairing of two streams by identical header stamp, with bounded buffers.

A node that pairs frames with readings must not grow without limit when one stream stops (a
stage controller that went silent while the detector streams at full rate). ``StampPairer``
holds each side's unpaired messages by stamp and drops the oldest (by arrival) when a side
exceeds ``max_count`` messages or ``max_bytes`` bytes, and anything older than ``timeout_s``.
Every drop is counted (``dropped``: side -> count, by reason) so the node can report it.
Plain Python, no rclpy.
"""

from __future__ import annotations

import time
from collections import OrderedDict


class StampPairer:
    """Two bounded buffers keyed by stamp; ``add(side, stamp, msg, nbytes)`` returns the pair
    ``(msg_a, msg_b)`` when the other side holds the same stamp, else None."""

    def __init__(self, max_count: int = 100, max_bytes: int = 256 << 20, timeout_s: float = 120.0,
                 sides=("image", "stage"), clock=time.monotonic):
        if max_count < 1 or max_bytes < 1:
            raise ValueError(f"pairing bounds must be positive (max_count {max_count}, max_bytes {max_bytes})")
        self.max_count, self.max_bytes, self.timeout_s = int(max_count), int(max_bytes), float(timeout_s)
        self.sides = tuple(sides)
        self.clock = clock
        self.buf = {s: OrderedDict() for s in self.sides}     # stamp -> (msg, nbytes, arrival)
        self.nbytes = {s: 0 for s in self.sides}
        self.dropped = {s: {"count_bound": 0, "byte_bound": 0, "timeout": 0, "replaced": 0, "overtaken": 0} for s in self.sides}
        self.peak = {s: {"count": 0, "bytes": 0} for s in self.sides}

    def pending(self, side: str) -> int:
        return len(self.buf[side])

    def add(self, side: str, stamp: int, msg, nbytes: int = 0):
        other = self.sides[1] if side == self.sides[0] else self.sides[0]
        if stamp in self.buf[other]:
            m, n, _t = self.buf[other].pop(stamp)
            self.nbytes[other] -= n
            return (msg, m) if side == self.sides[0] else (m, msg)
        b = self.buf[side]
        if stamp in b:                       # a duplicate stamp: the newer message replaces the older
            _m, n, _t = b.pop(stamp)
            self.nbytes[side] -= n
            self.dropped[side]["replaced"] += 1
        b[stamp] = (msg, int(nbytes), self.clock())
        self.nbytes[side] += int(nbytes)
        while len(b) > self.max_count:
            self._drop_oldest(side, "count_bound")
        while self.nbytes[side] > self.max_bytes and len(b) > 1:
            self._drop_oldest(side, "byte_bound")
        pk = self.peak[side]
        pk["count"], pk["bytes"] = max(pk["count"], len(b)), max(pk["bytes"], self.nbytes[side])
        return None

    def _drop_oldest(self, side, reason):
        _stamp, (_m, n, _t) = self.buf[side].popitem(last=False)
        self.nbytes[side] -= n
        self.dropped[side][reason] += 1

    def drop_older(self, side: str, stamp: int, reason: str = "overtaken") -> int:
        """Drop ``side``'s messages stamped before ``stamp``; returns how many. For a partner stream
        that arrives in stamp order (one publisher), a message of ``side`` older than the partner's
        newest stamp will never be paired: its partner was lost on the way."""
        b, k = self.buf[side], 0
        for old in [s for s in b if s < stamp]:
            _m, n, _t = b.pop(old)
            self.nbytes[side] -= n
            self.dropped[side][reason] += 1
            k += 1
        return k

    def expire(self) -> int:
        """Drop what waited longer than ``timeout_s``; returns how many were dropped."""
        now, k = self.clock(), 0
        for side in self.sides:
            b = self.buf[side]
            while b:
                stamp, (_m, n, t) = next(iter(b.items()))
                if now - t <= self.timeout_s:
                    break
                b.popitem(last=False)
                self.nbytes[side] -= n
                self.dropped[side]["timeout"] += 1
                k += 1
        return k

    def total_dropped(self) -> int:
        return sum(sum(d.values()) for d in self.dropped.values())
