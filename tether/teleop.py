"""`tether teleop`: drive the base from a terminal's keys (or a gamepad) as a deadman control, through safety.

The pure part (KeyDecoder, Deadman, SafetyView, stick_fraction) takes bytes, keys and the time as
arguments, so the unit tests feed it a fake clock; `teleop` binds it to the terminal, the gamepad
and Zenoh. What it sends goes on cmd/teleop/cmd_vel, where safety clamps it to the limits and
reports each clamp on safety/events; the line shows what safety did.
"""

from __future__ import annotations

import enum
import json
import math
import os
import select
import shutil
import signal
import sys
import termios
import threading
import time
import tty
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import IO, TYPE_CHECKING, Annotated, Any

import msgspec
import typer

from schemas import keys
from schemas.robot import Twist
from schemas.safety import Decision, SafetyEvent, SafetyStatus
from tether.output import printable

if TYPE_CHECKING:
    from services.runtime import Node

# Until the terminal starts repeating a held key (250 to 660 ms on common desktops) one key press
# holds its command this long; a key released before then moves the robot this long at most.
INITIAL_HOLD = 0.5
# Once repeats arrive (every 30 to 100 ms), a command is held this long after the last one, or
# REPEAT_FACTOR times the gap between the last two repeats if that is longer (a slow repeat rate),
# never longer than INITIAL_HOLD.
REPEAT_HOLD = 0.15
REPEAT_FACTOR = 2.5
# While a command is held it is sent again this often: the robot drops a cmd_vel after 0.5 s, and
# safety's acceleration ramp advances per message.
PUBLISH_PERIOD = 0.05
# A lone ESC byte with nothing after it for this long is the Escape key (which stops), not the start
# of an arrow key's sequence.
ESC_TIMEOUT = 0.05
REDRAW_PERIOD = 0.1
# The speed scale: +/- step it, within these bounds. Above 1 the commanded speed may pass the
# robot's limits; safety clamps it and the line says so.
SCALE_STEP = 0.1
MIN_SCALE = 0.1
MAX_SCALE = 3.0
# A safety event or heartbeat older than this is not shown as current.
STALE_EVENT = 1.0
STALE_HEARTBEAT = 1.0
# How long to wait at start for safety's heartbeat.
HEARTBEAT_WAIT = 3.0

# xterm's focus reporting (ESC[I when the terminal gains focus, ESC[O when it loses it), the cursor.
FOCUS_ON, FOCUS_OFF = "\x1b[?1004h", "\x1b[?1004l"
CURSOR_OFF, CURSOR_ON = "\x1b[?25l", "\x1b[?25h"
CLEAR_LINE = "\r\x1b[2K"

EXIT_OK = 0  # ended by the operator: q, Ctrl-C, SIGINT, SIGTERM
EXIT_INPUT_LOST = 1  # ended because its input went away: the terminal hung up or closed, the gamepad vanished
EXIT_USAGE = 2  # bad options, no terminal, no evdev for --gamepad, a device that is not a gamepad
EXIT_NO_SAFETY = 3  # no Zenoh session, or no heartbeat from safety: nothing would move

HELP_KEYS = "arrows/WASD drive, space stops, +/- speed, q quits"
REARM_WORDS = "e-stop reset: let go of the keys and the enable button, then drive"


class TeleopError(Exception):
    """A reason teleop cannot start (the message says what to fix)."""


class Key(enum.Enum):
    FORWARD = "forward"
    BACK = "back"
    LEFT = "left"
    RIGHT = "right"
    STOP = "stop"
    FASTER = "faster"
    SLOWER = "slower"
    QUIT = "quit"
    FOCUS_OUT = "focus_out"
    FOCUS_IN = "focus_in"


# What a key does to the base: (axis, direction); axis 0 is linear_x, 1 angular_z (left is positive).
MOTION = {Key.FORWARD: (0, 1), Key.BACK: (0, -1), Key.LEFT: (1, 1), Key.RIGHT: (1, -1)}

# One byte, one key. Raw mode: Ctrl-C, Ctrl-D and Ctrl-\ arrive as bytes, not signals.
BYTE_KEYS = {
    **dict.fromkeys(b"wW", Key.FORWARD),
    **dict.fromkeys(b"sS", Key.BACK),
    **dict.fromkeys(b"aA", Key.LEFT),
    **dict.fromkeys(b"dD", Key.RIGHT),
    **dict.fromkeys(b" ", Key.STOP),
    **dict.fromkeys(b"+=", Key.FASTER),
    **dict.fromkeys(b"-_", Key.SLOWER),
    **dict.fromkeys(b"qQ\x03\x04\x1c", Key.QUIT),
}
# The final byte of ESC [ ... X (CSI) or ESC O X (SS3): the arrows (with or without modifiers), focus.
SEQUENCE_KEYS = {
    ord("A"): Key.FORWARD,
    ord("B"): Key.BACK,
    ord("C"): Key.RIGHT,
    ord("D"): Key.LEFT,
    ord("I"): Key.FOCUS_IN,
    ord("O"): Key.FOCUS_OUT,
}
ESC = 0x1B
MAX_SEQUENCE = 32  # a CSI sequence longer than this is garbage: dropped


class KeyDecoder:
    """A terminal's input bytes to keys, across reads: a sequence cut between two reads is kept
    until the rest comes; `flush` ends a lone ESC (the Escape key, which stops)."""

    def __init__(self) -> None:
        self._pending = b""
        self.pending_since: float | None = None

    def feed(self, data: bytes, now: float) -> list[Key]:
        buf = self._pending + data
        found: list[Key] = []
        i = 0
        while i < len(buf):
            byte = buf[i]
            if byte != ESC:
                if (key := BYTE_KEYS.get(byte)) is not None:
                    found.append(key)
                i += 1
                continue
            if i + 1 >= len(buf):
                break  # ESC alone so far
            kind = buf[i + 1]
            if kind == ord("["):
                end = next((j for j in range(i + 2, len(buf)) if 0x40 <= buf[j] <= 0x7E), None)
                if end is None:
                    if len(buf) - i > MAX_SEQUENCE:
                        i = len(buf)  # garbage, not a sequence: dropped
                    break
                if (key := SEQUENCE_KEYS.get(buf[end])) is not None and (
                    key in MOTION or end == i + 2  # focus events carry no parameters
                ):
                    found.append(key)
                i = end + 1
            elif kind == ord("O"):
                if i + 2 >= len(buf):
                    break
                key = SEQUENCE_KEYS.get(buf[i + 2])
                if key in MOTION:
                    found.append(key)
                i += 3
            else:
                found.append(Key.STOP)  # Escape, then whatever follows it (Alt+key is ESC then the key)
                i += 1
        rest = buf[i:]
        # Still waiting for the same sequence: since it began; a new one: since now.
        same = bool(rest) and i == 0 and bool(self._pending)
        self.pending_since = (self.pending_since if same else now) if rest else None
        self._pending = rest
        return found

    def flush(self, now: float) -> list[Key]:
        """Keys from bytes that waited ESC_TIMEOUT for the rest of a sequence: a lone ESC is Escape."""
        if self.pending_since is None or now - self.pending_since < ESC_TIMEOUT:
            return []
        lone = self._pending == bytes([ESC])
        self._pending, self.pending_since = b"", None
        return [Key.STOP] if lone else []


@dataclass(frozen=True)
class Speeds:
    """The base's speeds at scale 1: metres a second forward or back, radians a second turning."""

    linear: float = 0.3
    angular: float = 0.8


@dataclass
class Axis:
    """One axis held by keys: the direction of the last key, when it came, how long it holds."""

    direction: int = 0
    last: float = -math.inf
    hold: float = 0.0
    repeats: int = 0

    def active(self, now: float) -> bool:
        return self.direction != 0 and now - self.last <= self.hold

    def until(self) -> float:
        return self.last + self.hold


@dataclass
class Stick:
    """The gamepad: stick deflections in [-1, 1] and whether the enable button is held; not `known`
    while events the kernel dropped are not read anew (neither held nor let go, then)."""

    linear: float = 0.0
    angular: float = 0.0
    enabled: bool = False
    known: bool = True


class Deadman:
    """Keys (and a gamepad's stick) in, twists to send out, by time: motion only while input keeps coming.

    A key holds its axis INITIAL_HOLD seconds, and once the terminal repeats it, REPEAT_HOLD (see
    there) after the last repeat; then the axis stops. While any axis moves, the twist is sent
    every PUBLISH_PERIOD; when everything stops (axes expired, space, focus lost, quit) one zero
    twist is sent, then nothing. The gamepad moves the base while its enable button is held and the
    stick is off centre; the keys, while they hold an axis, come first.
    """

    def __init__(
        self,
        speeds: Speeds = Speeds(),
        scale: float = 1.0,
        initial_hold: float = INITIAL_HOLD,
        repeat_hold: float = REPEAT_HOLD,
        period: float = PUBLISH_PERIOD,
    ) -> None:
        self.speeds = speeds
        self.scale = scale
        self.initial_hold = initial_hold
        self.repeat_hold = repeat_hold
        self.period = period
        self.axes = (Axis(), Axis())
        self.stick = Stick()
        self.quitting = False
        self.finished = False
        self._sent: tuple[float, float] = (0.0, 0.0)  # the last twist sent (linear, angular)
        self._sent_at = -math.inf
        self.sent_count = 0
        self.max_commanded = (0.0, 0.0)  # the largest |linear|, |angular| sent
        # Once safety's e-stop latched, what was held then moves nothing until it is let go and given
        # again: a `tether reset` must not set the robot off on a key still repeating or an enable
        # button still held (a reset does not restart motion by itself).
        self.rearming = False
        self._key_while_stopped = -math.inf  # when a motion key last came while rearming

    # Input

    def press(self, key: Key, now: float) -> None:
        if key in MOTION and self.rearming:
            self._key_while_stopped = now
        elif key in MOTION:
            index, direction = MOTION[key]
            axis = self.axes[index]
            if axis.direction == direction and axis.active(now):
                # A repeat of the key being held. The first gap is the terminal's repeat delay, not its rate.
                gap = now - axis.last
                hold = self.repeat_hold if axis.repeats == 0 else max(self.repeat_hold, REPEAT_FACTOR * gap)
                axis.hold = min(self.initial_hold, hold)
                axis.repeats += 1
            else:
                axis.direction, axis.hold, axis.repeats = direction, self.initial_hold, 0
            axis.last = now
        elif key in (Key.STOP, Key.FOCUS_OUT):
            self.release_keys()
        elif key is Key.FASTER:
            self.scale = min(MAX_SCALE, round(self.scale + SCALE_STEP, 2))
        elif key is Key.SLOWER:
            self.scale = max(MIN_SCALE, round(self.scale - SCALE_STEP, 2))
        elif key is Key.QUIT:
            self.quitting = True
        # FOCUS_IN: nothing moves until a key comes.

    def release_keys(self) -> None:
        for axis in self.axes:
            axis.direction, axis.repeats = 0, 0

    def set_stick(self, linear: float, angular: float, enabled: bool, known: bool = True) -> None:
        self.stick = Stick(linear, angular, enabled, known)

    def quit(self) -> None:
        self.quitting = True

    def safety(self, estop_latched: bool, now: float) -> None:
        """What safety's heartbeat says of the e-stop, every pass: latched, the inputs held stop
        counting; cleared, they count again once no key has come for INITIAL_HOLD (longer than a
        terminal's repeat delay: the key was let go) and the gamepad's enable button is known to be up."""
        if estop_latched:
            if not self.rearming:
                self.release_keys()
            self.rearming = True
        elif (
            self.rearming
            and now - self._key_while_stopped > self.initial_hold
            and not self.stick.enabled
            and self.stick.known
        ):
            self.rearming = False

    # Output

    def commanded(self, now: float) -> tuple[float, float]:
        """The twist wanted now (linear m/s, angular rad/s), before safety."""
        if self.quitting or self.rearming:
            return 0.0, 0.0
        linear_axis, angular_axis = self.axes
        if linear_axis.active(now) or angular_axis.active(now):
            linear = linear_axis.direction * self.speeds.linear * self.scale if linear_axis.active(now) else 0.0
            angular = angular_axis.direction * self.speeds.angular * self.scale if angular_axis.active(now) else 0.0
            return linear, angular
        if self.stick.enabled:
            return (
                self.stick.linear * self.speeds.linear * self.scale,
                self.stick.angular * self.speeds.angular * self.scale,
            )
        return 0.0, 0.0

    @property
    def moving(self) -> bool:
        """Whether the last twist sent was not a stop."""
        return self._sent != (0.0, 0.0)

    def tick(self, now: float) -> Twist | None:
        """The twist to send now, or None: the command while one is held (again every period, at
        once when it changes), one zero when motion ends, then nothing."""
        if self.finished:
            return None
        for axis in self.axes:
            if axis.direction and not axis.active(now):
                axis.direction, axis.repeats = 0, 0
        wanted = self.commanded(now)
        if self.quitting:
            self.finished = True
        if wanted == (0.0, 0.0):
            if not self.moving:
                return None
        elif wanted == self._sent and now - self._sent_at < self.period:
            return None
        self._sent, self._sent_at = wanted, now
        self.sent_count += 1
        self.max_commanded = (max(self.max_commanded[0], abs(wanted[0])), max(self.max_commanded[1], abs(wanted[1])))
        return Twist(linear_x=wanted[0], angular_z=wanted[1])

    def wake(self, now: float) -> float:
        """Seconds until `tick` has something to do (at most REDRAW_PERIOD, for the line)."""
        due = now + REDRAW_PERIOD
        if self.moving:
            due = min(due, self._sent_at + self.period)
        for axis in self.axes:
            if axis.direction:
                due = min(due, axis.until() + 1e-3)
        return max(0.0, due - now)


def stick_fraction(value: int, low: int, high: int, deadzone: float = 0.15) -> float:
    """An absolute axis reading as -1..1 (the middle of [low, high] is 0), zero inside the deadzone,
    rescaled outside it so the stick reaches full speed at its stop."""
    if high <= low:
        return 0.0
    middle, half = (low + high) / 2, (high - low) / 2
    x = max(-1.0, min(1.0, (value - middle) / half))
    if abs(x) <= deadzone:
        return 0.0
    return math.copysign((abs(x) - deadzone) / (1.0 - deadzone), x)


@dataclass
class SafetyView:
    """What safety did with this teleop's twists (safety/events on cmd/teleop/cmd_vel whose command
    carries one of our stamps) and what its heartbeat says (e-stop, speed scale, mode)."""

    heartbeat: SafetyStatus | None = None
    beat_at: float = -math.inf
    last: SafetyEvent | None = None
    last_at: float = -math.inf
    counts: dict[str, int] = field(default_factory=lambda: {d.value: 0 for d in Decision})
    clamp_rules: dict[str, int] = field(default_factory=dict)
    veto_reasons: deque[str] = field(default_factory=lambda: deque(maxlen=5))
    _ours: deque[float] = field(default_factory=lambda: deque(maxlen=512))
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def sent(self, twist: Twist) -> None:
        with self._lock:
            self._ours.append(twist.stamp)

    def beat(self, status: SafetyStatus, now: float) -> None:
        with self._lock:
            self.heartbeat, self.beat_at = status, now

    def event(self, event: SafetyEvent, now: float) -> None:
        if event.key != keys.TELEOP_CMD_VEL.path:
            return
        try:
            command = msgspec.json.decode(event.command, type=Twist | None)
        except msgspec.DecodeError:
            return
        with self._lock:
            # Another teleop's twist (a second terminal, a Foxglove panel) is not ours; a count of
            # repeated vetoes has no command and covers ours too.
            if command is not None and command.stamp not in self._ours:
                return
            self.last, self.last_at = event, now
            self.counts[event.decision.value] += 1
            if event.decision is Decision.CLAMPED and event.rule is not None:
                self.clamp_rules[event.rule.value] = self.clamp_rules.get(event.rule.value, 0) + 1
            if event.decision is Decision.VETOED:
                self.veto_reasons.append(event.reason)

    def estop_latched(self) -> bool:
        """Whether safety's latest heartbeat says its e-stop is latched."""
        with self._lock:
            return self.heartbeat is not None and self.heartbeat.estop.latched

    def mode(self) -> str | None:
        """The mode safety's heartbeat names, if it carries one."""
        with self._lock:
            mode = getattr(self.heartbeat, "mode", None)
        return None if mode is None else str(mode)

    def safety_words(self, now: float) -> str:
        """What safety did with the latest twist, in a few words."""
        with self._lock:
            last, last_at, beat, beat_at = self.last, self.last_at, self.heartbeat, self.beat_at
        if beat is None or now - beat_at > STALE_HEARTBEAT:
            return "NO HEARTBEAT from safety: the robot will not move"
        if beat.estop.latched:
            # Anyone may publish an e-stop with any reason, and safety's vetoes quote what they were
            # given: their control characters are escaped before they reach the terminal.
            estop = f"{printable(beat.estop.source)}: {printable(beat.estop.reason)}"
            return f"E-STOP latched by {estop} (`tether reset` clears it)"
        if last is None or now - last_at > STALE_EVENT:
            words = "ready"
        elif last.decision is Decision.CLAMPED:
            speed, turn = last.values.get("speed_mps", math.nan), last.values.get("turn_rps", math.nan)
            words = f"CLAMPED to {speed:+.2f} m/s {turn:+.2f} rad/s ({last.rule or 'limit'})"
        elif last.decision is Decision.VETOED:
            words = f"VETOED ({last.rule or 'rule'}): {printable(last.reason)}"
        else:
            words = "approved"
        if beat.speed_scale < 1.0:
            words += f"; people near: speed x{beat.speed_scale:.1f}"
        return words

    def line(self, deadman: Deadman, now: float, width: int) -> str:
        linear, angular = deadman.commanded(now)
        mode = self.mode()
        mode = None if mode is None else printable(mode)
        words = self.safety_words(now)
        if deadman.rearming and not self.estop_latched():
            words = f"{REARM_WORDS}; {words}"
        text = (
            f"cmd {linear:+.2f} m/s {angular:+.2f} rad/s | scale x{deadman.scale:.1f} "
            f"({deadman.speeds.linear * deadman.scale:.2f} m/s, {deadman.speeds.angular * deadman.scale:.2f} rad/s) "
            f"| safety: {words}" + (f" | mode {mode}" if mode else "") + f" | {HELP_KEYS}"
        )
        return text if len(text) <= width else text[: max(0, width - 1)] + "~"

    def summary(self) -> dict[str, Any]:
        with self._lock:
            last, beat = self.last, self.heartbeat
            counts, rules, vetoes = dict(self.counts), dict(self.clamp_rules), list(self.veto_reasons)
        return {
            "decisions": {k: v for k, v in counts.items() if k in ("approved", "clamped", "vetoed")},
            "clamped_by": rules,
            "veto_reasons": vetoes,
            "last": (
                None
                if last is None
                else {
                    "decision": last.decision.value,
                    "rule": None if last.rule is None else last.rule.value,
                    "reason": last.reason,
                    "speed_mps": last.values.get("speed_mps"),
                    "turn_rps": last.values.get("turn_rps"),
                }
            ),
            "estop_latched": None if beat is None else beat.estop.latched,
            "mode": self.mode(),
        }


# The terminal


def terminal_stream(as_json: bool) -> IO[str] | None:
    """Where the line and the terminal's modes are written: stdout, or stderr with --json (stdout
    carries the summary); the other one if that is not a terminal; None if neither is."""
    first, second = (sys.stderr, sys.stdout) if as_json else (sys.stdout, sys.stderr)
    return next((s for s in (first, second) if s.isatty()), None)


def write(stream: IO[str] | None, text: str) -> None:
    """Write to the terminal, which may be gone (SIGHUP: the window closed)."""
    if stream is None:
        return
    try:
        stream.write(text)
        stream.flush()
    except (OSError, ValueError):
        pass


@contextmanager
def raw_terminal(fd: int, stream: IO[str] | None) -> Iterator[None]:
    """Raw keys from `fd` (no echo, no line editing, Ctrl-C as a byte), focus reports on, the cursor
    hidden; all of it undone on the way out, also on an exception, and keys typed but not read are
    dropped rather than left for the shell. Keys typed before (while teleop started and waited for
    safety) are dropped too: a press from then is no command now, and was read as one."""
    saved = termios.tcgetattr(fd)
    try:
        tty.setraw(fd, termios.TCSAFLUSH)
        write(stream, FOCUS_ON + CURSOR_OFF)
        yield
    finally:
        write(stream, FOCUS_OFF + CURSOR_ON + CLEAR_LINE)
        with suppress(termios.error, OSError):  # the terminal may be gone
            termios.tcsetattr(fd, termios.TCSAFLUSH, saved)


class Gamepad:
    """A gamepad through evdev: the left stick drives (up forward, left turns left) while a shoulder
    button (BTN_TL or BTN_TR) is held."""

    def __init__(self, path: Path) -> None:
        try:
            import evdev  # optional: only --gamepad needs it, and it is not a dependency
        except ImportError:
            raise TeleopError(
                "--gamepad needs the Python package evdev, which is not installed "
                "(install it into tether's environment: pip install evdev)"
            ) from None
        self._ecodes = evdev.ecodes
        try:
            self.device = evdev.InputDevice(str(path))
        except OSError as exc:
            raise TeleopError(f"--gamepad {path}: cannot open it: {exc.strerror or exc}") from None
        absolute = dict(self.device.capabilities().get(self._ecodes.EV_ABS, []))
        missing = [n for n in ("ABS_X", "ABS_Y") if getattr(self._ecodes, n) not in absolute]
        if missing:
            self.device.close()
            raise TeleopError(f"--gamepad {path}: {self.device.name!r} has no stick ({', '.join(missing)} missing)")
        self._ranges = {code: (info.min, info.max) for code, info in absolute.items()}
        self._values = {code: (lo + hi) // 2 for code, (lo, hi) in self._ranges.items()}
        self._enable = {self._ecodes.BTN_TL, self._ecodes.BTN_TR}
        self._held: set[int] = set()
        # The kernel's queue overflowed (SYN_DROPPED): events were lost, the release of the enable
        # button maybe among them. Until the next SYN_REPORT the state is unknown, then read anew.
        self._dropped = False
        self.name = str(self.device.name)

    def fileno(self) -> int:
        return int(self.device.fileno())

    def read(self) -> Stick:
        """The stick after the events waiting now; OSError when the device is gone."""
        ecodes = self._ecodes
        try:
            for event in self.device.read():
                if event.type == ecodes.EV_SYN and event.code == ecodes.SYN_DROPPED:
                    self._dropped = True
                elif self._dropped:
                    # The rest of a packet the kernel cut short is not to be trusted (evdev's protocol).
                    if event.type == ecodes.EV_SYN and event.code == ecodes.SYN_REPORT:
                        self._resync()
                elif event.type == ecodes.EV_ABS:
                    self._values[event.code] = event.value
                elif event.type == ecodes.EV_KEY and event.code in self._enable:
                    (self._held.add if event.value else self._held.discard)(event.code)
        except BlockingIOError:
            pass
        x, y = ecodes.ABS_X, ecodes.ABS_Y
        # Stick up and left read low: forward and turning left are positive.
        return Stick(
            linear=-stick_fraction(self._values[y], *self._ranges[y]),
            angular=-stick_fraction(self._values[x], *self._ranges[x]),
            enabled=bool(self._held) and not self._dropped,
            known=not self._dropped,
        )

    def _resync(self) -> None:
        """The buttons and axes as the device has them now (after events were lost)."""
        self._held = set(self.device.active_keys()) & self._enable
        for code in self._values:
            self._values[code] = self.device.absinfo(code).value
        self._dropped = False

    def close(self) -> None:
        with suppress(OSError):
            self.device.close()


# The command


class Ending:
    """Why the loop ends, set from a signal handler or the loop; the first reason stays."""

    def __init__(self) -> None:
        self.reason: str | None = None
        self.lost_input = False

    def set(self, reason: str, lost_input: bool = False) -> None:
        if self.reason is None:
            self.reason, self.lost_input = reason, lost_input


SIGNAL_ENDINGS = {signal.SIGINT: "SIGINT", signal.SIGTERM: "SIGTERM", signal.SIGHUP: "SIGHUP (terminal closed)"}


def finite(value: float) -> float:
    """An option's number, refused unless finite: click's min and max let "nan" through (a comparison
    with NaN is false), and a NaN speed goes out as null, a twist safety cannot read."""
    if not math.isfinite(value):
        raise typer.BadParameter(f"{value} is not a number")
    return value


def usage_error(message: str, as_json: bool, code: int = EXIT_USAGE) -> typer.Exit:
    if as_json:
        print(json.dumps({"ended": "error", "error": message}))
    else:
        typer.secho("error:", fg="red", err=True, nl=False)
        typer.echo(f" {message}", err=True)
    return typer.Exit(code)


def teleop(
    ctx: typer.Context,
    linear: Annotated[
        float,
        typer.Option("--linear", min=0.01, max=10.0, callback=finite, help="Forward/back speed at scale x1.0, m/s."),
    ] = Speeds.linear,
    angular: Annotated[
        float, typer.Option("--angular", min=0.01, max=20.0, callback=finite, help="Turn rate at scale x1.0, rad/s.")
    ] = Speeds.angular,
    scale: Annotated[
        float,
        typer.Option(
            "--scale",
            min=MIN_SCALE,
            max=MAX_SCALE,
            callback=finite,
            help="The speed scale to start with (+/- step it).",
        ),
    ] = 1.0,
    gamepad: Annotated[
        Path | None,
        typer.Option(
            "--gamepad",
            help="Also drive with a gamepad, /dev/input/eventN (needs the Python package evdev): the left "
            "stick drives while a shoulder button is held. Without a terminal on stdin, the gamepad alone.",
        ),
    ] = None,
    as_json: Annotated[
        bool,
        typer.Option(
            "--json",
            help="No live line; on exit print one JSON object on stdout: `ended` (why), `duration_s`, "
            "`twists_sent`, `max_commanded` (m/s, rad/s), `scale`, `gamepad` (its name or null), and `safety` "
            "(`decisions`: approved, clamped, vetoed counts; `clamped_by`: rule -> count; `veto_reasons`; "
            "`last` decision; `estop_latched`; `mode`); or, when it cannot start, `ended` error and the `error`.",
        ),
    ] = False,
) -> None:
    """Drive the base from this terminal: arrows or WASD, space stops, + and - change the speed scale, q quits.

    A deadman control: a key holds its command 0.5 s until the terminal repeats it, then 0.15 s
    after each repeat (longer for a slow repeat rate); when keys stop, the robot is told to stop,
    and at once on space, q, Ctrl-C, SIGTERM, the terminal closing (SIGHUP) or losing focus (xterm
    focus events). Commands go on cmd/teleop/cmd_vel: safety clamps them to the robot's limits and
    the line says when it did ("CLAMPED ... (base_speed)"), with the speed scale, the e-stop and the
    mode. In a deployment run it as the operator: `tether --zenoh-config DIR/ROBOT/operator.json5
    --robot ROBOT teleop` (only the operator identity may put cmd/teleop/**).

    Exit 0 ended by the operator (q, Ctrl-C, SIGINT, SIGTERM), 1 its input went away (the terminal
    hung up or closed, the gamepad vanished), 2 bad usage (no terminal on stdin, evdev missing for
    --gamepad, a device that is no gamepad), 3 no Zenoh session or no heartbeat from safety
    (nothing would move).
    """
    keyboard = sys.stdin.isatty()
    if not keyboard and gamepad is None:
        raise usage_error("teleop reads keys from a terminal, and stdin is not one (or give --gamepad)", as_json)
    pad: Gamepad | None = None
    if gamepad is not None:
        try:
            pad = Gamepad(gamepad)
        except TeleopError as exc:
            raise usage_error(str(exc), as_json) from None
    try:
        code = drive(ctx, Deadman(Speeds(linear, angular), scale), pad, keyboard, as_json)
    finally:
        if pad is not None:
            pad.close()
    raise typer.Exit(code)


def drive(ctx: typer.Context, deadman: Deadman, pad: Gamepad | None, keyboard: bool, as_json: bool) -> int:
    # The transport only here: the pure part above loads without Zenoh.
    from services.runtime import Node
    from tether.client import next_heartbeat

    try:
        opened = Node("cli", ctx.obj)
    except Exception as exc:  # zenoh.ZError: no router, a refused login
        raise usage_error(f"cannot open a Zenoh session: {exc}", as_json, EXIT_NO_SAFETY) from None
    view = SafetyView()
    ending = Ending()
    started = time.monotonic()
    with opened as node:
        waiting = True  # for safety's first heartbeat: nothing is sent yet

        def on_signal(number: int, _frame: FrameType | None) -> None:
            ending.set(SIGNAL_ENDINGS[signal.Signals(number)], lost_input=number == signal.SIGHUP)
            if waiting:
                raise Interrupted  # out of the wait at once; once driving, the loop ends it

        # A signal also writes a byte to this pipe, which wakes the loop's select at once.
        wake_r, wake_w = os.pipe()
        os.set_blocking(wake_r, False)
        os.set_blocking(wake_w, False)
        previous = {s: signal.signal(s, on_signal) for s in SIGNAL_ENDINGS}
        previous_wakeup = signal.set_wakeup_fd(wake_w)
        try:
            try:
                try:
                    waited = next_heartbeat(node, HEARTBEAT_WAIT)
                finally:
                    waiting = False
            except Interrupted:
                pass
            except KeyboardInterrupt:  # Ctrl-C raised as Python does by default: it ends the same
                ending.set(SIGNAL_ENDINGS[signal.SIGINT])
            else:
                if waited.status is None:
                    why = f"{waited.why_not(HEARTBEAT_WAIT)}: is safety running?"
                    raise usage_error(why, as_json, EXIT_NO_SAFETY)
                view.beat(waited.status, time.monotonic())
                drive_until_ended(node, deadman, pad, keyboard, as_json, view, ending, wake_r)
        finally:
            signal.set_wakeup_fd(previous_wakeup)
            for s, handler in previous.items():
                signal.signal(s, handler)
            os.close(wake_r)
            os.close(wake_w)
    return report(ending, started, deadman, pad, view, as_json)


class Interrupted(Exception):
    """A signal while teleop waits for safety's first heartbeat: it ends there, as teleop always ends."""


def drive_until_ended(
    node: Node,
    deadman: Deadman,
    pad: Gamepad | None,
    keyboard: bool,
    as_json: bool,
    view: SafetyView,
    ending: Ending,
    wake: int,
) -> None:
    """Safety heard from: the keys and the gamepad drive until the operator, a signal or lost input ends it."""
    from tether.client import signature_shaped

    node.subscribe(keys.HEARTBEAT, lambda s: view.beat(s, time.monotonic()), verify=signature_shaped)
    node.subscribe(keys.SAFETY_EVENTS, lambda e: view.event(e, time.monotonic()))
    publisher = node.publisher(keys.TELEOP_CMD_VEL)

    def send(twist: Twist) -> None:
        stamped = msgspec.structs.replace(twist, stamp=time.time())
        view.sent(stamped)
        publisher.put(stamped)

    stream = None if not keyboard else terminal_stream(as_json)
    with raw_terminal(sys.stdin.fileno(), stream) if keyboard else _nothing():
        try:
            inputs = Inputs(sys.stdin.fileno() if keyboard else None, pad, wake)
            loop(deadman, view, send, inputs, None if as_json else stream, ending)
        finally:
            # Whatever ended it (also an exception): a moving robot is told to stop now.
            if deadman.moving:
                send(Twist())


def report(
    ending: Ending, started: float, deadman: Deadman, pad: Gamepad | None, view: SafetyView, as_json: bool
) -> int:
    """How teleop ended, on stdout as one JSON object (`--json`) or as a line on stderr; the exit code."""
    safety = view.summary()
    summary = {
        "ended": ending.reason or "error",
        "duration_s": round(time.monotonic() - started, 3),
        "twists_sent": deadman.sent_count,
        "max_commanded": {"linear_mps": deadman.max_commanded[0], "angular_rps": deadman.max_commanded[1]},
        "scale": deadman.scale,
        "gamepad": pad.name if pad is not None else None,
        "safety": safety,
    }
    if as_json:
        print(json.dumps(summary))
    else:
        decisions = safety["decisions"]
        write(
            sys.stderr,
            f"teleop ended ({summary['ended']}): {deadman.sent_count} twists sent, safety approved "
            f"{decisions['approved']}, clamped {decisions['clamped']}, vetoed {decisions['vetoed']}\n",
        )
    return EXIT_INPUT_LOST if ending.lost_input else EXIT_OK


@contextmanager
def _nothing() -> Iterator[None]:
    yield


@dataclass(frozen=True)
class Inputs:
    """What the loop waits on: the terminal's keys (None: no terminal), the gamepad, the signal pipe."""

    keyboard: int | None
    pad: Gamepad | None
    wake: int


def loop(
    deadman: Deadman,
    view: SafetyView,
    send: Callable[[Twist], None],
    inputs: Inputs,
    line_stream: IO[str] | None,
    ending: Ending,
) -> None:
    """Read keys and the gamepad, send what the deadman says, redraw the line, until told to end."""
    decoder = KeyDecoder()
    keyboard, pad = inputs.keyboard, inputs.pad
    sources = [inputs.wake] + ([keyboard] if keyboard is not None else []) + ([pad.fileno()] if pad else [])
    drawn = -math.inf
    while True:
        now = time.monotonic()
        if ending.reason is not None:
            deadman.quit()
        readable, _, _ = select.select(sources, [], [], 0.0 if deadman.quitting else deadman.wake(now))
        now = time.monotonic()
        if inputs.wake in readable:
            with suppress(BlockingIOError):
                os.read(inputs.wake, 512)
            if ending.reason is not None:
                deadman.quit()
        if keyboard is not None and keyboard in readable:
            try:
                data = os.read(keyboard, 1024)
            except OSError:
                data = b""
            if not data:
                ending.set("terminal closed", lost_input=True)
                deadman.quit()
            for key in decoder.feed(data, now):
                deadman.press(key, now)
                if key is Key.QUIT:
                    ending.set("quit")
        for key in decoder.flush(now):
            deadman.press(key, now)
        if pad is not None and pad.fileno() in readable:
            try:
                stick = pad.read()
            except OSError:
                ending.set("gamepad lost", lost_input=True)
                deadman.quit()
            else:
                deadman.set_stick(stick.linear, stick.angular, stick.enabled, stick.known)
        deadman.safety(view.estop_latched(), now)
        if (twist := deadman.tick(now)) is not None:
            send(twist)
        if deadman.finished:
            return
        if line_stream is not None and now - drawn >= REDRAW_PERIOD:
            drawn = now
            width = shutil.get_terminal_size((100, 24)).columns
            write(line_stream, CLEAR_LINE + view.line(deadman, now, width - 1))
