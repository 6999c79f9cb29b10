"""Bad input in nodes: count it by topic and kind, log it rate-limited, never let it end the node.

One helper for every node (plain Python, no rclpy import: the Pixel Probe nodes can use it too):

    self.bad_input = BadInputCounter(self.get_logger())
    self.create_subscription(Image, topic, self.bad_input.guard(topic, self._on_image), qos)
    ...
    except MessageError as exc:
        self.bad_input.report(topic, exc)        # counted, logged rate-limited, message skipped

``guard`` wraps a subscription callback: any exception a message provokes (a MessageError
naming what is wrong, or anything unexpected) is counted and the message is skipped; the
node keeps serving the next one. The kind of a problem is its text with the numbers and
quoted values taken out, so "image is 64x64 px ..." and "image is 32x32 px ..." count as one
kind. The first message of each (topic, kind) is logged at once; afterwards one summary line
per ``period_s`` says how many more of each kind came. ``counts`` holds the totals.
"""

from __future__ import annotations

import re
import threading
import time
import traceback

_NUM = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?|nan|inf", re.IGNORECASE)
_QUOTED = re.compile(r"'[^']*'|\"[^\"]*\"|\[[^\]]*\]")


def kind_of(exc_or_text) -> str:
    """A short key for a problem: its text without numbers and quoted values (at most 80 chars)."""
    if isinstance(exc_or_text, BaseException):
        text = str(exc_or_text) or type(exc_or_text).__name__
        if type(exc_or_text).__name__ not in ("MessageError", "ValueError", "FrameError"):
            text = f"{type(exc_or_text).__name__}: {text}"
    else:
        text = str(exc_or_text)
    text = _QUOTED.sub("<v>", text)
    text = _NUM.sub("#", text)
    return re.sub(r"\s+", " ", text).strip()[:80]


class BadInputCounter:
    """Counts bad input per (topic, kind) and logs it rate-limited (see the module docstring)."""

    def __init__(self, logger, period_s: float = 10.0, clock=time.monotonic):
        self.logger = logger
        self.period_s = float(period_s)
        self.clock = clock
        self.counts: dict = {}          # (topic, kind) -> total
        self._since: dict = {}          # (topic, kind) -> count since the last summary
        self._last_summary = clock()
        self._lock = threading.Lock()

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def by_topic(self) -> dict:
        out: dict = {}
        for (topic, _k), n in self.counts.items():
            out[topic] = out.get(topic, 0) + n
        return out

    def report(self, topic: str, problem, unexpected: bool = False) -> None:
        """Count one bad message on ``topic``; ``problem`` is the exception or a text."""
        key = (topic, kind_of(problem))
        with self._lock:
            first = key not in self.counts
            self.counts[key] = self.counts.get(key, 0) + 1
            if not first:
                self._since[key] = self._since.get(key, 0) + 1
        if first:
            text = f"bad input on {topic}, skipped: {problem}"
            if unexpected and isinstance(problem, BaseException):
                tb = "".join(traceback.format_exception(problem)[-3:]).strip()
                self.logger.error(f"{text} (unexpected {type(problem).__name__}; further ones of this kind are "
                                  f"counted, summary every {self.period_s:g} s)\n{tb}")
            else:
                self.logger.warning(f"{text} (further ones of this kind are counted, summary every "
                                    f"{self.period_s:g} s)")
        self.maybe_summarise()

    def maybe_summarise(self, force: bool = False) -> None:
        now = self.clock()
        with self._lock:
            if not self._since or (not force and now - self._last_summary < self.period_s):
                return
            since, self._since = self._since, {}
            self._last_summary = now
        parts = "; ".join(f"{topic} [{kind}]: {n}" for (topic, kind), n in sorted(since.items()))
        self.logger.warning(f"bad input in the last {self.period_s:g} s (skipped): {parts}; "
                            f"totals {self.total}")

    def log_totals(self) -> None:
        """Pending summary, then one line of totals per topic (called when the node ends)."""
        self.maybe_summarise(force=True)
        self.logger.info(f"bad input totals: {self.total} message(s) skipped {self.by_topic()}")

    def guard(self, topic: str, callback):
        """``callback`` wrapped so that no message can end the node (see the module docstring)."""
        def wrapped(msg):
            try:
                return callback(msg)
            except (ValueError, TypeError, AttributeError, IndexError, KeyError, OverflowError,
                    ArithmeticError, MemoryError, AssertionError, RuntimeError) as exc:
                expected = type(exc).__name__ in ("MessageError", "FrameError")
                self.report(topic, exc, unexpected=not expected)
                return None
        wrapped.__name__ = getattr(callback, "__name__", "callback")
        return wrapped
