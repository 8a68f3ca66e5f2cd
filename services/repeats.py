"""Coalescing a message that repeats: the first logged at once, the rest as a count every few seconds. Pure."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

log = logging.getLogger(__name__)

# A stream of the same complaint is one line per this many seconds, with its count.
SUMMARY_PERIOD = 5.0
# Problems keeps this many kinds of problem, the latest.
PROBLEM_KINDS = 32
# A RepeatLog keeps this many keys, the first-seen forgotten first: its keys may be a peer's (garbage
# on a thousand made-up keys under a wildcard must not grow it without end). A key forgotten and
# seen again is logged again at once.
MAX_KEYS = 1024


class RepeatLog:
    """Per key (a key expression), what to log of a complaint that may come a thousand times a second:
    `note` returns the line for the first one at once, then nothing until `period` seconds have
    passed, then one line with the count since (ending that window), or None. A stream that stops
    within a window has its last count in the next line for that key. `total` counts them all."""

    def __init__(self, what: str, period: float = SUMMARY_PERIOD, clock: Callable[[], float] = time.monotonic) -> None:
        self.what = what
        self.period = period
        self._clock = clock
        self._lock = threading.Lock()
        self._windows: dict[str, tuple[float, int]] = {}  # key -> (window start, count since its line)
        self._covered: dict[str, int] = {}  # key -> how many its last line told of
        self.total = 0

    def note(self, key: str, detail: object) -> str | None:
        now = self._clock()
        with self._lock:
            self.total += 1
            seen = self._windows.get(key)
            if seen is None:
                if len(self._windows) >= MAX_KEYS:
                    oldest = next(iter(self._windows))
                    del self._windows[oldest]
                    self._covered.pop(oldest, None)
                self._windows[key] = (now, 0)
                self._covered[key] = 1
                return f"{self.what} on {key}: {detail}"
            start, count = seen
            if now - start < self.period:
                self._windows[key] = (start, count + 1)
                return None
            self._windows[key] = (now, 0)
            self._covered[key] = count + 1
        return f"{count + 1} more {self.what} on {key} in the last {now - start:.1f} s; the latest: {detail}"

    def covered(self, key: str) -> int:
        """How many the last line for `key` told of (1 for the first, then each summary's count)."""
        with self._lock:
            return self._covered.get(key, 0)

    def count(self, key: str) -> int:
        """How many on `key` since its last line."""
        with self._lock:
            seen = self._windows.get(key)
        return 0 if seen is None else seen[1]


class Problems:
    """What a robot backend refused, for robot/diagnostics and its log: each kind of problem (its text)
    with when it was last seen (wall clock) and how often; the first of a kind logged at once, the rest
    counted into a line every few seconds (`repeats`, to `logger`)."""

    def __init__(
        self,
        wall_clock: Callable[[], float] = time.time,
        repeats: RepeatLog | None = None,
        logger: logging.Logger = log,
    ) -> None:
        self._wall_clock = wall_clock
        self._lock = threading.Lock()
        self._seen: dict[str, tuple[float, int]] = {}
        self.log = repeats or RepeatLog("refused")
        self._logger = logger

    def note(self, text: str, about: str = "", detail: object = None) -> None:
        """One problem; `about` groups its log lines (a key), default the text itself; `detail` is
        what the log line says of it, default the text."""
        with self._lock:
            _, count = self._seen.pop(text, (0.0, 0))
            self._seen[text] = (self._wall_clock(), count + 1)
            if len(self._seen) > PROBLEM_KINDS:
                del self._seen[next(iter(self._seen))]
        if (line := self.log.note(about or text, text if detail is None else detail)) is not None:
            self._logger.warning("%s", line)

    def recent(self, within: float) -> list[tuple[str, float]]:
        """Each problem seen in the last `within` seconds, with its count, and when last seen: the latest first."""
        since = self._wall_clock() - within
        with self._lock:
            seen = list(self._seen.items())
        return [(f"{text} ({count} so far)", at) for text, (at, count) in reversed(seen) if at >= since]
