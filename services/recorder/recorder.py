"""A run of recording: the current MCAP file and its ROS 2 twin, rotated by size and age, with totals over all files."""

from __future__ import annotations

import datetime as dt
import logging
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

from schemas.trace import RecorderStatus, Ros2RecorderStatus
from services.recorder.config import RecorderConfig
from services.recorder.mcapfile import Provenance, Recording, version
from services.recorder.ros2file import Ros2Recording, Ros2Source, WarnOnce, ros2_path

log = logging.getLogger(__name__)


# Names tried when files of the same name keep appearing between the look and the open.
NAME_TRIES = 100
# Files named in the status (and `files`), the latest: a run rotating for months must not grow
# either without bound. The totals count every file.
FILES_LISTED = 100


def unused_path(path: Path, twin: Callable[[Path], Path] | None = None) -> Path:
    """`path`, or `name_1.mcap`, `name_2.mcap`... when a file of that name (or its `twin`) exists (two
    rotations in one second)."""
    candidate, n = path, 0
    while candidate.exists() or (twin is not None and twin(candidate).exists()):
        n += 1
        candidate = path.with_name(f"{path.stem}_{n}{path.suffix}")
    return candidate


class Recorder:
    """Writes every message to the current file; `tick()` flushes it and starts a new one when it is
    full or old enough. Thread-safe: Zenoh delivers from several threads.

    With `ros2`, each file has a twin `<stem>.ros2.mcap` for the robot's ROS 2 samples (`record_ros2`),
    opened, flushed and rotated with it. Nothing on that side stops tether's file: a twin that cannot be
    opened is logged and shown in the status, and tether's recording goes on.

    `clock` gives the receive times written (the wall clock); `monotonic` measures a file's age and the
    run's elapsed time written in each part, which a step of the wall clock (NTP correcting it) must
    not move.
    """

    def __init__(
        self,
        config: RecorderConfig,
        provenance: Provenance,
        *,
        clock: Callable[[], int] = time.time_ns,
        monotonic: Callable[[], int] = time.monotonic_ns,
        first_path: Path | None = None,
        ros2: Ros2Source | None = None,
    ) -> None:
        self.config = config
        self.provenance = provenance
        self._clock = clock
        self._monotonic = monotonic
        # A name chosen by the user for the first file; later files take it with _1, _2...
        self._first_path = first_path
        self._lock = threading.Lock()
        self.files: list[Path] = []  # the latest FILES_LISTED
        self.parts = 0  # files started over the run
        self._messages_before = 0  # in the files already closed
        self._dropped_before = 0
        self.started_ns = clock()
        self._run_started = self._monotonic()
        self._part_started = self._run_started
        self.run = uuid.uuid4().hex  # in every part's metadata
        self._ros2 = ros2
        self._ros2_warn = WarnOnce()  # once per kind over the whole run, not per file
        self.ros2_files: list[Path] = []  # the latest FILES_LISTED
        self._ros2_messages_before = 0
        self._ros2_skipped_before = 0
        self._ros2_file_error = ""
        self._ros2_link_error = ""
        self._rotation_error = ""  # why the next file could not be started, "" once one was
        self._current = self._open()
        self._ros2_current = self._open_ros2(Path(self._current.path))

    def _open(self) -> Recording:
        now, started = self._clock(), self._monotonic()
        named = self._first_path or self.config.path_for(
            self.provenance.robot, dt.datetime.fromtimestamp(now / 1e9, dt.UTC)
        )
        named.parent.mkdir(parents=True, exist_ok=True)
        for _ in range(NAME_TRIES):
            path = unused_path(named, ros2_path if self._ros2 is not None else None)
            try:
                recording = Recording(
                    path,
                    self.provenance.robot,
                    compression=self.config.compression,
                    chunk_size=self.config.chunk_size,
                    clock=self._clock,
                    provenance=self.provenance,
                    part=self.parts,
                    run=self.run,
                    elapsed_ns=started - self._run_started,
                )
                break
            except FileExistsError:
                # Another recorder made that name between the look and the open (the same robot and
                # output_dir, the same second): the next free name, never over its file.
                continue
        else:
            raise FileExistsError(f"no free file name like {named} after {NAME_TRIES} tries")
        self.parts += 1
        self._part_started = started
        _append_latest(self.files, path)
        log.info("recording to %s", path)
        return recording

    def _open_ros2(self, tether_path: Path) -> Ros2Recording | None:
        """The twin of the tether file at `tether_path`; None (logged, in the status) if it cannot be opened."""
        if self._ros2 is None:
            return None
        path = ros2_path(tether_path)
        metadata = {
            "robot": self.provenance.robot,
            "run": self.run,
            "part": str(self.parts - 1),
            "tether_file": tether_path.name,
            "version": version(),
            **self._ros2.metadata(),
        }
        try:
            recording = Ros2Recording(
                path,
                self._ros2.keys,
                compression=self.config.compression,
                chunk_size=self.config.chunk_size,
                clock=self._clock,
                metadata=metadata,
                warn=self._ros2_warn,
            )
        except OSError as exc:
            self._ros2_file_error = f"cannot write the ROS 2 recording {path}: {exc.strerror or exc}"
            log.error("%s; tether's recording goes on without it", self._ros2_file_error)
            return None
        self._ros2_file_error = ""
        _append_latest(self.ros2_files, path)
        log.info("recording ROS 2 traffic (%s) to %s", ", ".join(self._ros2.keys.key_exprs()), path)
        return recording

    def record(self, key: str, payload: bytes, attachment: bytes | None = None) -> bool:
        with self._lock:
            return self._current.record(key, payload, attachment=attachment)

    def record_ros2(self, key: str, payload: bytes, attachment: bytes | None = None) -> bool:
        """Write one sample of the robot's ROS 2 traffic to the twin; False if there is none or it was skipped."""
        with self._lock:
            current = self._ros2_current
            return current.record(key, payload, attachment) if current is not None else False

    def ros2_link_failed(self, error: str) -> None:
        """Why the robot's ROS 2 network is not reached now ("" once it is): shown in the status."""
        with self._lock:
            self._ros2_link_error = error

    def tick(self) -> None:
        """Flush, then rotate if the file reached max_file_bytes or max_file_seconds. Call about once a second."""
        with self._lock:
            current, twin = self._current, self._ros2_current
            current.flush()
            if twin is not None:
                self._on_twin(twin, twin.flush)
            why = self._rotation_due(current, twin)
            if why is None:
                return
            log.info("rotating %s: %s", current.path, why)
            try:
                following = self._open()
            except OSError as exc:  # the disk full, the directory gone: the current file goes on
                error = f"cannot start the next file in {self.config.output_dir}: {exc.strerror or exc}"
                if error != self._rotation_error:
                    log.error("%s; %s goes on", error, current.path)
                self._rotation_error = error
                return
            self._rotation_error = ""
            self._messages_before += current.messages
            self._dropped_before += current.dropped
            self._current = following
            if twin is not None:
                self._ros2_messages_before += twin.messages
                self._ros2_skipped_before += twin.skipped
            self._ros2_current = self._open_ros2(Path(following.path))
        # The summaries of the full files are written outside the lock; nothing writes to them any more.
        current.finish()
        if twin is not None:
            self._on_twin(twin, twin.finish)

    def _on_twin(self, twin: Ros2Recording, write: Callable[[], None]) -> None:
        """Flush or finish the twin; a failure (its disk full) is logged once and shown, never raised."""
        try:
            write()
        except OSError as exc:
            error = f"cannot write the ROS 2 recording {twin.path}: {exc.strerror or exc}"
            if error != self._ros2_file_error:
                log.error("%s; tether's recording goes on", error)
            self._ros2_file_error = error

    def _rotation_due(self, current: Recording, twin: Ros2Recording | None) -> str | None:
        if current.error:  # tried each tick: recording goes on in a new file once one can be written
            return current.error
        if twin is not None and twin.error:  # its name goes with tether's file's: a new pair
            return twin.error
        if current.removed():
            log.error("%s was removed while it was written: what it held since its last rotation is lost", current.path)
            return "its file was removed"
        limit_bytes, limit_seconds = self.config.max_file_bytes, self.config.max_file_seconds
        if limit_bytes is not None and (size := current.size) >= limit_bytes:
            return f"{size} bytes, the limit is {limit_bytes}"
        if limit_bytes is not None and twin is not None and (size := twin.size) >= limit_bytes:
            return f"its ROS 2 twin holds {size} bytes, the limit is {limit_bytes}"
        age = (self._monotonic() - self._part_started) / 1e9
        if limit_seconds is not None and age >= limit_seconds:
            return f"{age:.0f} s old, the limit is {limit_seconds:g} s"
        return None

    def finish(self) -> None:
        with self._lock:
            self._current.finish()
            if self._ros2_current is not None:
                self._on_twin(self._ros2_current, self._ros2_current.finish)

    def files_said(self) -> str:
        """The files of the run, in words: the latest FILES_LISTED named, and how many came before them."""
        named = ", ".join(map(str, self.files))
        earlier = self.parts - len(self.files)
        return f"{named} (after {earlier} earlier file{'s' if earlier > 1 else ''})" if earlier else named

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
                ros2=self._ros2_status(),
                error="; ".join(e for e in (current.error, self._rotation_error) if e),
            )

    def _ros2_status(self) -> Ros2RecorderStatus | None:
        if self._ros2 is None:
            return None
        twin = self._ros2_current
        return Ros2RecorderStatus(
            path=twin.path if twin is not None else "",
            messages=self._ros2_messages_before + (twin.messages if twin is not None else 0),
            skipped=self._ros2_skipped_before + (twin.skipped if twin is not None else 0),
            files=[str(p) for p in self.ros2_files],
            error="; ".join(
                e for e in (self._ros2_link_error, self._ros2_file_error, twin.error if twin is not None else "") if e
            ),
        )


def _append_latest(files: list[Path], path: Path) -> None:
    files.append(path)
    del files[:-FILES_LISTED]
