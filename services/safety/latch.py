"""The e-stop latch: anyone may set it; only a valid operator token clears it; it survives restarts."""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path

import msgspec

from schemas.safety import EstopState
from services.datafile import read_bytes
from services.safety.errors import Unauthorized
from services.safety.operator import token_matches

log = logging.getLogger(__name__)


def write_durably(path: Path, data: bytes) -> None:
    """Replace `path` with `data`, renamed into place before it is synced: a crash of this process
    at any point after the rename leaves the new file (the page cache outlives the process), so the
    window in which a written state can be lost that way is the write into the page cache, not the
    sync. A power cut before the syncs finish leaves the old file, the new one or (on a file system
    that does not order a renamed file's data first; ext4 and btrfs do) an unreadable one, which the
    readers take the fail-closed way (the latch latched, the mode supervised). On return the file,
    then the directory holding its name (the rename is durable only once it is), are on disk."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    with tmp.open("wb") as out:
        out.write(data)
        out.flush()
        os.replace(tmp, path)
        os.fsync(out.fileno())
    directory = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


class EstopLatch:
    """With a `state_file`, a latched e-stop is written down as soon as the robot has been told, and
    read back at start: restarting safety (by hand, systemd or `tether up`) does not clear it."""

    def __init__(self, operator_token: str, state_file: Path | None = None) -> None:
        self._token = operator_token
        self._file = state_file
        self._lock = threading.Lock()
        self._file_lock = threading.Lock()
        self._state = self._load()

    def _load(self) -> EstopState:
        if self._file is None:
            return EstopState(latched=False)
        if not self._file.exists():
            # Fail closed: the first start of an install writes it (operator.ensure_token); missing
            # now, it may have held a latch (deleted, a volume not mounted).
            log.error("e-stop state file %s is missing: starting latched; an operator must reset it", self._file)
            return EstopState(latched=True, source="safety", reason=f"e-stop state file {self._file} is missing")
        try:
            # Bounded and not blocking: a FIFO or a device in its place hung safety's start.
            state = msgspec.json.decode(read_bytes(self._file, "e-stop state", OSError), type=EstopState)
        except (OSError, msgspec.DecodeError) as exc:
            # Fail closed: a state we cannot read might have been a latched one.
            log.error("e-stop state file %s is unreadable (%s): starting latched", self._file, exc)
            return EstopState(latched=True, source="safety", reason=f"unreadable e-stop state file {self._file}")
        if state.latched:
            log.warning("e-stop still latched from before the restart (by %s: %s)", state.source, state.reason)
        return state

    def save(self) -> None:
        """Write the current state down (the latest wins when several write at once)."""
        if self._file is None:
            return
        with self._file_lock:
            write_durably(self._file, msgspec.json.encode(self.state))

    @property
    def state(self) -> EstopState:
        with self._lock:
            return self._state

    def trigger(self, source: str, reason: str, stamp: float) -> bool:
        """Latch in memory at `stamp` (wall-clock seconds); returns True if this call latched it
        (False if it already was).

        The caller tells the robot first and then calls save() (as after a reset): a slow disk must
        not delay a stop. save() renames the file into place before syncing it, so a crash of safety
        between the two still leaves it latched on restart.
        """
        return self.request(source, reason, stamp)[0]

    def request(self, source: str, reason: str, stamp: float) -> tuple[bool, EstopState]:
        """As trigger, and the state in force after it: when already latched, the one that latched it
        (read in the same step, so a reset in between cannot make it say the wrong holder)."""
        with self._lock:
            if self._state.latched:
                return False, self._state
            self._state = EstopState(latched=True, source=source, reason=reason, stamp=stamp)
            return True, self._state

    def accepts(self, token: str) -> bool:
        """Whether `token` is the operator's (compared in constant time)."""
        return token_matches(self._token, token)

    def reset(self, operator: str, token: str, stamp: float) -> EstopState:
        """Clear it at `stamp` (wall-clock seconds), with the operator's token."""
        with self._lock:
            if not token_matches(self._token, token):
                raise Unauthorized(f"reset refused for '{operator}': not the operator's token")
            self._state = EstopState(latched=False, source=operator, reason="reset by operator", stamp=stamp)
            return self._state
