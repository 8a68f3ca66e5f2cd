"""Safety's authenticated link to the robot: a MAC on each robot command and heartbeat, checked by the robot. Pure."""

from __future__ import annotations

import contextlib
import hmac
import logging
import math
import os
import secrets
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from schemas import keys
from services.datafile import read_bounded
from services.repeats import Problems, RepeatLog

log = logging.getLogger(__name__)

# Names the key file for every service a supervisor starts (a stack's own key); a service's config
# (`robot_key_file` in [safety], [sim], [ros2]) takes precedence.
KEY_ENV = "TETHER_ROBOT_KEY_FILE"
KEY_BYTES = 32
# Its hex and a newline, with room for stray whitespace; a longer file is not a robot key.
MAX_KEY_FILE_BYTES = 1024
# A signed message stamped further than this from the robot's wall clock (either way) is refused:
# safety and the robot backend run on one computer (or on hosts kept in time by NTP).
MAX_SKEW = 2.0
# Sender sessions remembered at most (each safety start is one); the oldest is forgotten first.
MAX_SESSIONS = 64
SESSION_BYTES = 16
MAGIC = b"T1"
# The attachment: magic, sender session, counter, sender's wall-clock stamp, HMAC-SHA256.
_ATTACHMENT = struct.Struct("!2s16sQd32s")
ATTACHMENT_BYTES = _ATTACHMENT.size
_DOMAIN = b"tether robot link v1\0"

# What only safety sends to the robot, under tether/<robot>/: the robot acts on these only when signed.
SIGNED_PATHS = frozenset(
    {
        keys.HEARTBEAT.path,
        keys.ROBOT_CMD_VEL.path,
        *(a.send_goal.path for a in (keys.ROBOT_NAVIGATE, keys.ROBOT_TRAJECTORY, keys.ROBOT_GRIPPER)),
        *(a.cancel_goal.path for a in (keys.ROBOT_NAVIGATE, keys.ROBOT_TRAJECTORY, keys.ROBOT_GRIPPER)),
    }
)


def path_of(key_expr: str) -> str:
    """`tether/<robot>/<path>` -> `<path>`."""
    parts = key_expr.split("/", 2)
    return parts[2] if len(parts) == 3 and parts[0] == keys.ROOT else key_expr


def signed(key_expr: str) -> bool:
    """Whether messages on `key_expr` carry (and need) safety's MAC."""
    return path_of(key_expr) in SIGNED_PATHS


# The key file


class KeyFileError(Exception):
    """The robot key file is missing, unreadable, open to others or not a 32-byte hex key (the message says)."""


def key_path(configured: str | None, default_dir: Path, robot: str) -> Path:
    """The key file: the config's, else $TETHER_ROBOT_KEY_FILE, else robot-<robot>.key in `default_dir`
    (beside the operator token)."""
    if configured:
        return Path(configured).expanduser()
    if env := os.environ.get(KEY_ENV):
        return Path(env).expanduser()
    return default_dir / f"robot-{robot}.key"


def ensure_key(path: Path) -> bytes:
    """The key in `path`, made (mode 0600) if there is none. Safety and the robot backend may both
    start at once and both make one: each writes a complete file under another name and links it
    into place, which fails for all but the first, so both read the same whole key."""
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            with os.fdopen(fd, "w") as f:
                f.write(secrets.token_hex(KEY_BYTES) + "\n")
                f.flush()
                os.fsync(f.fileno())
            with contextlib.suppress(FileExistsError):
                os.link(tmp, path)  # atomic, and never replaces: the first one made wins
        finally:
            tmp.unlink(missing_ok=True)
    return read_key(path)


def robot_key(configured: str | None, default_dir: Path, robot: str) -> tuple[bytes, Path]:
    """The robot key, made on first start, and the file it is in (see key_path)."""
    path = key_path(configured, default_dir, robot)
    return ensure_key(path), path


def read_key(path: Path) -> bytes:
    # A FIFO or device configured as the key would hang start-up or be read without end (read_bounded).
    mode, data = read_bounded(path, MAX_KEY_FILE_BYTES, "robot key", KeyFileError)
    if mode & 0o077:
        raise KeyFileError(f"robot key file {path} is readable by others (mode {mode & 0o777:o}); chmod 600 it")
    try:
        key = bytes.fromhex(data.decode("ascii").strip())
    except ValueError:  # also bytes that are not ASCII
        raise KeyFileError(f"robot key file {path} is not hex") from None
    if len(key) != KEY_BYTES:
        raise KeyFileError(f"robot key file {path} holds {len(key)} bytes; a robot key is {KEY_BYTES}")
    return key


# Signing and checking


def _keyed(key: bytes) -> hmac.HMAC:
    """HMAC-SHA256 set up with `key`, copied for each message (_mac)."""
    return hmac.new(key, digestmod="sha256")


def _mac(keyed: hmac.HMAC, key_expr: str, payload: bytes, session: bytes, counter: int, stamp: float) -> bytes:
    expr = key_expr.encode()
    message = b"".join(
        (_DOMAIN, struct.pack("!I", len(expr)), expr, session, struct.pack("!Qd", counter, stamp), payload)
    )
    # A copy of OpenSSL's context keyed once, rather than hmac.digest, which finds the digest and sets
    # the key up again on every call: the same bytes, in 1.4 us against 1.9 back to back, and 30 against
    # 63 after 40 ms asleep (the pace of goals: code run then takes many times its warm time on a VM).
    # Safety signs, and the robot checks, every heartbeat and goal with it.
    mac = keyed.copy()
    mac.update(message)
    return mac.digest()


class Signer:
    """Safety's side: signs what it sends to the robot. One random session per start, a counter over
    all it signs. The sender holds `lock` from signing a message to handing it to Zenoh, so the
    counters on each key go out in order."""

    def __init__(self, key: bytes, clock: Callable[[], float] = time.time, session: bytes | None = None) -> None:
        if len(key) != KEY_BYTES:
            raise ValueError(f"a robot key is {KEY_BYTES} bytes, not {len(key)}")
        self._keyed = _keyed(key)
        self._clock = clock
        self.session = session or secrets.token_bytes(SESSION_BYTES)
        self._counter = 0
        self.lock = threading.RLock()

    def sign(self, key_expr: str, payload: bytes) -> bytes:
        """The attachment for `payload` on `key_expr`."""
        with self.lock:
            self._counter += 1
            counter = self._counter
        stamp = self._clock()
        mac = _mac(self._keyed, key_expr, payload, self.session, counter, stamp)
        return _ATTACHMENT.pack(MAGIC, self.session, counter, stamp, mac)


@dataclass(frozen=True)
class Signature:
    """An attachment taken apart (not yet checked)."""

    session: bytes
    counter: int
    stamp: float
    mac: bytes


def unpack(attachment: bytes | None) -> Signature | None:
    """The signature in an attachment; None when there is none or it is not one."""
    if attachment is None or len(attachment) != ATTACHMENT_BYTES:
        return None
    magic, session, counter, stamp, mac = _ATTACHMENT.unpack(attachment)
    if magic != MAGIC:
        return None
    return Signature(session, counter, stamp, mac)


def mac_matches(key: bytes, key_expr: str, payload: bytes, signature: Signature) -> bool:
    """Whether `signature` was made with `key` over `payload` on `key_expr` (for checking a recording)."""
    return _matches(_keyed(key), key_expr, payload, signature)


def _matches(keyed: hmac.HMAC, key_expr: str, payload: bytes, signature: Signature) -> bool:
    expected = _mac(keyed, key_expr, payload, signature.session, signature.counter, signature.stamp)
    return hmac.compare_digest(expected, signature.mac)


@dataclass(frozen=True)
class Refusal:
    """Why a message was not taken as safety's: `why` stays the same for one kind of refusal (for
    counting and diagnostics); `detail` has the numbers."""

    why: str
    detail: str = ""

    def __str__(self) -> str:
        return f"{self.why} ({self.detail})" if self.detail else self.why


NOT_SIGNED = "not signed by safety (no robot-link MAC attached)"
MALFORMED = "robot-link attachment malformed"
BAD_MAC = "robot-link MAC does not match: not signed with this robot's key, or altered"
STALE = "robot-link stamp out of the time window"
BEFORE_START = "robot-link stamp from before this robot backend started (a replay?)"
REPLAYED = "robot-link counter not increasing: replayed or reordered"
SUPERSEDED = "robot-link sender superseded: another safety session beats the heartbeat now"


class Verifier:
    """The robot's side: a message counts as safety's when its MAC matches under the robot key, its
    stamp is within MAX_SKEW of `clock` and not from before this verifier was made (a restarted robot
    takes nothing recorded before), and its counter is above the last taken from its sender session
    on that key (replayed or reordered messages are refused). A restarted safety is a new session: once
    its heartbeat is taken, the session that beat it before is superseded and nothing more of it is
    taken (what the old safety signed and was held back on the way would run under a safety that never
    approved it). A session not heard within 2 x MAX_SKEW is forgotten: anything of it sent before
    that is too old anyway, and should the robot's clock step back, what is stamped no later than the
    newest of a forgotten session is still refused. A superseded session is not forgotten: a safety
    frozen meanwhile (a suspended host, a stopped process) would speak again with fresh stamps and take
    the robot back from the live one.
    The last MAX_SESSIONS superseded are remembered (each is a start of safety, which needs the key)."""

    def __init__(self, key: bytes, clock: Callable[[], float] = time.time, max_skew: float = MAX_SKEW) -> None:
        if len(key) != KEY_BYTES:
            raise ValueError(f"a robot key is {KEY_BYTES} bytes, not {len(key)}")
        self._keyed = _keyed(key)
        self._clock = clock
        self.max_skew = max_skew
        self.started = clock()
        self._lock = threading.Lock()
        self._last: dict[tuple[bytes, str], int] = {}  # (session, key expr) -> counter last taken
        self._newest: dict[bytes, float] = {}  # session -> its newest stamp taken
        # The newest stamp of the sessions forgotten as silent: a robot clock stepped back (NTP) puts
        # what they sent inside the window again, with their counters gone.
        self._forgotten = -math.inf
        # The session whose heartbeat was taken last, kept when it falls silent and is forgotten: a
        # safety that starts while the last one is frozen supersedes it.
        self._beating: bytes | None = None
        self._superseded: dict[bytes, None] = {}  # oldest first, at most MAX_SESSIONS

    def check(self, key_expr: str, payload: bytes, attachment: bytes | None) -> Refusal | None:
        """None when the message is safety's, and it is taken (its counter remembered); else why not."""
        # Every goal and heartbeat pays this, mostly after the robot has slept between them, when each
        # Python call costs many times its warm time: the attachment is taken apart here (not by
        # `unpack`, which builds a Signature), and what is done for every message is done inline.
        if attachment is None:
            return Refusal(NOT_SIGNED)
        if len(attachment) != ATTACHMENT_BYTES:
            return Refusal(MALFORMED, f"{len(attachment)} bytes")
        magic, session, counter, stamp, mac = _ATTACHMENT.unpack(attachment)
        if magic != MAGIC:
            return Refusal(MALFORMED, f"{len(attachment)} bytes")
        if not hmac.compare_digest(_mac(self._keyed, key_expr, payload, session, counter, stamp), mac):
            return Refusal(BAD_MAC)
        now = self._clock()
        age = now - stamp
        if not abs(age) <= self.max_skew:  # also NaN
            return Refusal(STALE, f"stamped {age:+.3f} s from now; at most {self.max_skew:g} s either way")
        if stamp < self.started:
            return Refusal(BEFORE_START, f"{self.started - stamp:.3f} s before")
        newest = self._newest
        with self._lock:
            for heard, at in list(newest.items()):  # forget the sessions not heard lately
                if now - at > 2 * self.max_skew:
                    self._forgotten = max(self._forgotten, at)
                    self._drop(heard)
            if stamp <= self._forgotten:
                detail = "stamped no later than a sender forgotten as silent (the robot's clock stepped back?)"
                return Refusal(REPLAYED, detail)
            last = self._last.get((session, key_expr), 0)
            if counter <= last:
                return Refusal(REPLAYED, f"counter {counter} after {last} on {path_of(key_expr)}")
            if session in self._superseded:
                return Refusal(SUPERSEDED)
            self._last[(session, key_expr)] = counter
            if session != self._beating and path_of(key_expr) == keys.HEARTBEAT.path:
                if self._beating is not None:
                    self._superseded[self._beating] = None
                    while len(self._superseded) > MAX_SESSIONS:
                        del self._superseded[next(iter(self._superseded))]
                self._beating = session
            # The latest heard last (the oldest is dropped first).
            newest[session] = max(newest.pop(session, stamp), stamp)
            if len(newest) > MAX_SESSIONS:
                self._drop(next(iter(newest)))
        return None

    def _drop(self, session: bytes) -> None:
        self._newest.pop(session, None)
        for k in [k for k in self._last if k[0] == session]:
            del self._last[k]


# What a refusal names instead of a key expression with wildcards (only safety's concrete keys are signed).
WILDCARD = "a wildcard key expression"


class LinkGuard:
    """A robot backend's door: each message on a signed key is checked before anything reads it; what
    is refused is dropped, logged (the first at once, then a count every few seconds) and kept as a
    problem for robot/diagnostics, and `report` (if given) hears it too."""

    def __init__(
        self,
        verifier: Verifier,
        report: Callable[[str], None] | None = None,
        wall_clock: Callable[[], float] = time.time,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.verifier = verifier
        self._report = report
        self._problems = Problems(wall_clock, RepeatLog("messages refused as not from safety", clock=clock), log)

    def __call__(self, key_expr: str, payload: bytes, attachment: bytes | None) -> Refusal | None:
        refusal = self.verifier.check(key_expr, payload, attachment)
        if refusal is None:
            return None
        path = path_of(key_expr)
        detail: object = refusal
        if path not in SIGNED_PATHS:
            # A put or query on a wildcard expression reaches the robot's keys too; a peer can make up
            # endless ones ("tether/r1/s$*/h$*t"): counted as one kind, never one log line each.
            path, detail = WILDCARD, f"{refusal}; sent to {key_expr[:200]!r}"
        text = f"refused {path}: {refusal.why}"
        self._problems.note(text, path, detail)
        if self._report is not None:
            self._report(text)
        return refusal

    def problems(self, within: float) -> list[tuple[str, float]]:
        """Each kind of refusal seen in the last `within` seconds, with its count, and when last seen
        (wall clock): the latest first."""
        return self._problems.recent(within)
