"""A run of recording: the current MCAP file, rotated by size and by age, with totals over all files."""

from __future__ import annotations

import datetime as dt
import logging
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

from schemas.trace import RecorderStatus
from services.recorder.config import RecorderConfig
from services.recorder.mcapfile import Provenance, Recording

log = logging.getLogger(__name__)


def unused_path(path: Path) -> Path:
    """`path`, or `name_1.mcap`, `name_2.mcap`... when a file of that name exists (two rotations in one second)."""
    candidate, n = path, 0
    while candidate.exists():
        n += 1
        candidate = path.with_name(f"{path.stem}_{n}{path.suffix}")
    return candidate


class Recorder:
    """Writes every message to the current file; `tick()` flushes it and starts a new one when it is
    full or old enough. Thread-safe: Zenoh delivers from several threads."""

    def __init__(
        self,
        config: RecorderConfig,
        provenance: Provenance,
        *,
        clock: Callable[[], int] = time.time_ns,
        first_path: Path | None = None,
    ) -> None:
        self.config = config
        self.provenance = provenance
        self._clock = clock
        # A name chosen by the user for the first file; later files take it with _1, _2...
        self._first_path = first_path
        self._lock = threading.Lock()
        self.files: list[Path] = []
        self._messages_before = 0  # in the files already closed
        self._dropped_before = 0
        self.started_ns = clock()
        self.run = uuid.uuid4().hex  # in every part's metadata
        self._current = self._open()

    def _open(self) -> Recording:
        now = self._clock()
        named = self._first_path or self.config.path_for(
            self.provenance.robot, dt.datetime.fromtimestamp(now / 1e9, dt.UTC)
        )
        path = unused_path(named)
        path.parent.mkdir(parents=True, exist_ok=True)
        recording = Recording(
            path,
            self.provenance.robot,
            compression=self.config.compression,
            chunk_size=self.config.chunk_size,
            clock=self._clock,
            provenance=self.provenance,
            part=len(self.files),
            run=self.run,
        )
        self.files.append(path)
        log.info("recording to %s", path)
        return recording

    def record(self, key: str, payload: bytes) -> bool:
        with self._lock:
            return self._current.record(key, payload)

    def tick(self) -> None:
        """Flush, then rotate if the file reached max_file_bytes or max_file_seconds. Call about once a second."""
        with self._lock:
            current = self._current
            current.flush()
            why = self._rotation_due(current)
            if why is None:
                return
            log.info("rotating %s: %s", current.path, why)
            following = self._open()  # if this fails (disk full), the current file goes on
            self._messages_before += current.messages
            self._dropped_before += current.dropped
            self._current = following
        # The summary of the full file is written outside the lock; nothing writes to it any more.
        current.finish()

    def _rotation_due(self, current: Recording) -> str | None:
        limit_bytes, limit_seconds = self.config.max_file_bytes, self.config.max_file_seconds
        if limit_bytes is not None and (size := current.size) >= limit_bytes:
            return f"{size} bytes, the limit is {limit_bytes}"
        age = (self._clock() - current.started_ns) / 1e9
        if limit_seconds is not None and age >= limit_seconds:
            return f"{age:.0f} s old, the limit is {limit_seconds:g} s"
        return None

    def finish(self) -> None:
        with self._lock:
            self._current.finish()

    @property
    def messages(self) -> int:
        with self._lock:
            return self._messages_before + self._current.messages

    @property
    def dropped(self) -> int:
        with self._lock:
            return self._dropped_before + self._current.dropped

    def status(self) -> RecorderStatus:
        with self._lock:
            current = self._current
            return RecorderStatus(
                path=current.path,
                messages=self._messages_before + current.messages,
                started=self.started_ns / 1e9,
                dropped=self._dropped_before + current.dropped,
                files=[str(p) for p in self.files],
            )
