"""teleop's pure part: bytes to keys, the deadman's twists by a fake clock, key by key, what the line
says of safety's decisions, and the gamepad's events to a stick."""

from __future__ import annotations

import itertools
import sys
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import NamedTuple

import msgspec
import pytest

from schemas import keys
from schemas.robot import Twist
from schemas.safety import Decision, EstopState, Rule, SafetyEvent, SafetyStatus
from tether.teleop import (
    INITIAL_HOLD,
    MAX_SCALE,
    PUBLISH_PERIOD,
    REARM_WORDS,
    REPEAT_HOLD,
    Deadman,
    Gamepad,
    Key,
    KeyDecoder,
    SafetyView,
    Speeds,
    Stick,
    TeleopError,
    stick_fraction,
)

UP, DOWN, RIGHT, LEFT = b"\x1b[A", b"\x1b[B", b"\x1b[C", b"\x1b[D"
FOCUS_OUT, FOCUS_IN = b"\x1b[O", b"\x1b[I"


# Bytes to keys


def test_arrows_wasd_and_the_other_keys_decode() -> None:
    decoder = KeyDecoder()
    data = UP + DOWN + RIGHT + LEFT + b"wsad WSAD+=-_q"
    assert decoder.feed(data, 0.0) == [
        *(Key.FORWARD, Key.BACK, Key.RIGHT, Key.LEFT),
        *(Key.FORWARD, Key.BACK, Key.LEFT, Key.RIGHT, Key.STOP),
        *(Key.FORWARD, Key.BACK, Key.LEFT, Key.RIGHT),
        *(Key.FASTER, Key.FASTER, Key.SLOWER, Key.SLOWER, Key.QUIT),
    ]


def test_application_mode_arrows_modifiers_and_focus_events_decode() -> None:
    decoder = KeyDecoder()
    assert decoder.feed(b"\x1bOA\x1bOD\x1b[1;5A", 0.0) == [Key.FORWARD, Key.LEFT, Key.FORWARD]
    # ESC[O is focus out, ESC O X an arrow in application mode: told apart by the second byte.
    assert decoder.feed(FOCUS_OUT + FOCUS_IN + b"\x1bOB", 0.0) == [Key.FOCUS_OUT, Key.FOCUS_IN, Key.BACK]


@pytest.mark.parametrize("byte", [b"\x03", b"\x04", b"\x1c", b"Q"])
def test_ctrl_c_ctrl_d_and_ctrl_backslash_quit_in_raw_mode(byte: bytes) -> None:
    assert KeyDecoder().feed(byte, 0.0) == [Key.QUIT]


def test_a_sequence_cut_between_reads_is_joined() -> None:
    decoder = KeyDecoder()
    assert decoder.feed(b"w\x1b", 0.0) == [Key.FORWARD]
    assert decoder.feed(b"[", 0.01) == []
    assert decoder.flush(0.02) == []  # still within ESC_TIMEOUT of the ESC
    assert decoder.feed(b"A", 0.03) == [Key.FORWARD]
    assert decoder.flush(1.0) == []


def test_a_lone_escape_stops_once_nothing_follows_it() -> None:
    decoder = KeyDecoder()
    assert decoder.feed(b"\x1b", 0.0) == []
    assert decoder.flush(0.01) == []
    assert decoder.flush(0.2) == [Key.STOP]
    assert decoder.flush(0.5) == []


def test_other_sequences_and_garbage_are_ignored() -> None:
    decoder = KeyDecoder()
    assert decoder.feed(b"\x1b[5~\x1b[15;2~xyz\xc3\xa9\x00\x1b[1;2I", 0.0) == []
    assert decoder.feed(b"\x1b[" + b"1;" * 40, 0.0) == []
    assert decoder.feed(b"w", 0.1) == [Key.FORWARD]


# The deadman, by a fake clock


def run(deadman: Deadman, presses: dict[float, Key], until: float, step: float = 0.01) -> list[tuple[float, Twist]]:
    """Feed `presses` at their times and tick every `step` up to `until`: what was sent, when."""
    sent: list[tuple[float, Twist]] = []
    pending = sorted(presses.items())
    ticks = round(until / step)
    for i in range(ticks + 1):
        now = round(i * step, 6)
        while pending and pending[0][0] <= now:
            at, key = pending.pop(0)
            deadman.press(key, at)
        if (twist := deadman.tick(now)) is not None:
            sent.append((now, twist))
    return sent


def held(key: Key, start: float, delay: float, interval: float, end: float) -> dict[float, Key]:
    """A key held from `start`: the press, then the terminal's repeats after `delay`, every `interval`, up to `end`."""
    times = [start]
    t = start + delay
    while t <= end + 1e-9:
        times.append(round(t, 6))
        t += interval
    return dict.fromkeys(times, key)


def last_motion(sent: list[tuple[float, Twist]]) -> float:
    moving = [t for t, twist in sent if (twist.linear_x, twist.angular_z) != (0.0, 0.0)]
    return moving[-1] if moving else -1.0


def test_a_held_key_drives_through_the_repeat_delay_and_stops_soon_after_the_last_repeat() -> None:
    deadman = Deadman(Speeds(linear=0.3, angular=0.8))
    # Pressed at 0, repeats after 0.4 s (the terminal's delay) every 0.04 s until 1.2 s, then released.
    sent = run(deadman, held(Key.FORWARD, 0.0, 0.4, 0.04, 1.2), until=3.0)
    moving = [(t, s) for t, s in sent if s.linear_x != 0.0]
    # Sent at once, then every period, without a gap through the repeat delay.
    assert moving[0][0] == 0.0
    assert all(s == Twist(linear_x=0.3) for _, s in moving)
    gaps = [b[0] - a[0] for a, b in itertools.pairwise(moving)]
    assert max(gaps) <= PUBLISH_PERIOD + 0.011
    # After the last repeat (1.2 s): motion for REPEAT_HOLD at most, then one zero, then silence.
    last_key = max(held(Key.FORWARD, 0.0, 0.4, 0.04, 1.2))
    assert last_motion(sent) <= last_key + REPEAT_HOLD + 1e-9
    stops = [t for t, s in sent if s == Twist()]
    assert len(stops) == 1 and last_key < stops[0] <= last_key + REPEAT_HOLD + 0.011
    # Braking from 0.3 m/s at the robot's 1.5 m/s^2 takes 0.2 s: at rest within 0.5 s of the last key.
    assert stops[0] - last_key <= 0.5 - 0.3 / 1.5 - 0.1
    assert sent[-1] == (stops[0], Twist())


def test_one_press_holds_its_command_until_the_repeat_delay_and_no_longer() -> None:
    deadman = Deadman()
    sent = run(deadman, {0.0: Key.LEFT}, until=2.0)
    assert sent[0] == (0.0, Twist(angular_z=0.8))
    assert INITIAL_HOLD - PUBLISH_PERIOD <= last_motion(sent) <= INITIAL_HOLD
    assert [s for _, s in sent].count(Twist()) == 1
    assert sent[-1][0] <= INITIAL_HOLD + 0.011


def test_a_slow_repeat_rate_is_held_longer_but_never_past_the_initial_hold() -> None:
    slow = Deadman()
    sent = run(slow, held(Key.FORWARD, 0.0, 0.5, 0.12, 2.0), until=4.0)
    # Repeats every 0.12 s: held 0.3 s after each, so motion never gaps between repeats.
    moving_times = [t for t, s in sent if s.linear_x > 0]
    assert max(b - a for a, b in itertools.pairwise(moving_times)) <= PUBLISH_PERIOD + 0.011
    assert slow.axes[0].direction == 0
    last_key = max(held(Key.FORWARD, 0.0, 0.5, 0.12, 2.0))
    assert last_key + REPEAT_HOLD < last_motion(sent) <= last_key + 2.5 * 0.12 + 1e-9
    # Repeats a second apart would be held at most INITIAL_HOLD, so the robot stops between them.
    sparse = run(Deadman(), held(Key.FORWARD, 0.0, 1.0, 1.0, 3.0), until=4.0)
    assert [s for _, s in sparse].count(Twist()) == 4


def test_space_focus_out_and_quit_stop_at_once() -> None:
    for stopper in (Key.STOP, Key.FOCUS_OUT, Key.QUIT):
        deadman = Deadman()
        presses = held(Key.FORWARD, 0.0, 0.3, 0.03, 1.0)
        presses[1.005] = stopper  # between two ticks: the next tick stops
        sent = run(deadman, presses, until=2.0)
        assert last_motion(sent) <= 1.0
        assert [(t, s) for t, s in sent if t > 1.0] == [(1.01, Twist())], stopper
    assert deadman.finished and deadman.tick(5.0) is None


def test_quit_while_still_sends_nothing_and_finishes() -> None:
    deadman = Deadman()
    assert run(deadman, {0.5: Key.QUIT}, until=1.0) == []
    assert deadman.finished


def test_a_key_after_a_stop_drives_again_and_a_focus_in_alone_does_not() -> None:
    deadman = Deadman()
    sent = run(deadman, {0.0: Key.FORWARD, 0.1: Key.FOCUS_OUT, 0.2: Key.FOCUS_IN, 0.3: Key.BACK}, until=1.0)
    kinds = [s.linear_x for _, s in sent]
    assert 0.3 in kinds and -0.3 in kinds
    assert all(t < 0.1 or t >= 0.3 for t, s in sent if s.linear_x != 0.0)
    assert next(t for t, s in sent if s == Twist()) == 0.1


def test_axes_combine_and_expire_separately() -> None:
    deadman = Deadman(Speeds(linear=0.5, angular=1.0))
    sent = run(deadman, {0.0: Key.FORWARD, 0.2: Key.RIGHT}, until=1.0)
    assert (0.2, Twist(linear_x=0.5, angular_z=-1.0)) in sent
    # Forward expires first (pressed first), the turn goes on alone, then one zero.
    assert (0.51, Twist(angular_z=-1.0)) in sent
    assert [s for _, s in sent].count(Twist()) == 1


def test_the_scale_steps_within_its_bounds_and_applies_at_once() -> None:
    deadman = Deadman(Speeds(linear=0.3, angular=0.8))
    presses = {0.0: Key.FORWARD, 0.02: Key.FASTER}
    sent = run(deadman, presses, until=0.03)
    assert [t for t, _ in sent] == [0.0, 0.02]
    assert [twist.linear_x for _, twist in sent] == pytest.approx([0.3, 0.33])
    for _ in range(100):
        deadman.press(Key.FASTER, 0.1)
    assert deadman.scale == MAX_SCALE
    for _ in range(100):
        deadman.press(Key.SLOWER, 0.1)
    assert deadman.scale == pytest.approx(0.1)


def test_the_gamepad_drives_while_enabled_and_the_keys_come_first() -> None:
    deadman = Deadman(Speeds(linear=0.4, angular=1.0))
    deadman.set_stick(0.5, -1.0, enabled=False)
    assert deadman.tick(0.0) is None  # the stick alone does nothing without the enable button
    deadman.set_stick(0.5, -1.0, enabled=True)
    assert deadman.tick(0.01) == Twist(linear_x=0.2, angular_z=-1.0)
    assert deadman.tick(0.02) is None
    assert deadman.tick(0.07) == Twist(linear_x=0.2, angular_z=-1.0)  # sent again every period
    deadman.press(Key.BACK, 0.08)
    assert deadman.tick(0.08) == Twist(linear_x=-0.4)
    deadman.set_stick(0.5, -1.0, enabled=False)  # released: once the key expires, one zero
    assert deadman.tick(0.08 + INITIAL_HOLD + 0.01) == Twist()
    assert deadman.tick(1.0) is None


def through_a_latch(
    deadman: Deadman, presses: dict[float, Key], latched: tuple[float, float], until: float, step: float = 0.01
) -> list[tuple[float, Twist]]:
    """`run`, with safety's e-stop latched from latched[0] to latched[1] (a `tether reset` then)."""
    sent: list[tuple[float, Twist]] = []
    pending = sorted(presses.items())
    for i in range(round(until / step) + 1):
        now = round(i * step, 6)
        while pending and pending[0][0] <= now:
            deadman.press(pending.pop(0)[1], now)
        deadman.safety(latched[0] <= now < latched[1], now)
        if (twist := deadman.tick(now)) is not None:
            sent.append((now, twist))
    return sent


def test_a_key_held_through_an_estop_and_its_reset_moves_nothing_until_let_go_and_pressed_again() -> None:
    """The robot drove off on the reset: the terminal's repeats of a key held through the e-stop kept
    coming, and the twists they made, vetoed while it was latched, were approved once it was not."""
    deadman = Deadman(Speeds(linear=0.3, angular=0.8))
    presses = held(Key.FORWARD, 0.0, 0.4, 0.04, 3.0)  # held from 0 to 3 s
    presses[4.0] = Key.FORWARD  # pressed again after letting go
    sent = through_a_latch(deadman, presses, latched=(1.0, 2.0), until=5.0)
    moving = [t for t, twist in sent if twist.linear_x != 0.0]
    assert moving and max(t for t in moving if t < 4.0) < 1.0 + 0.011, "it drove on through the latch"
    assert (1.0, Twist()) in sent, "no stop when the e-stop latched"
    assert not [t for t in moving if 1.0 <= t < 4.0], "the reset set it off on the key still held"
    assert moving[-1] >= 4.0 and (4.0, Twist(linear_x=0.3)) in sent, "a fresh press after the reset did not drive"


def test_a_gamepad_enabled_through_an_estop_and_its_reset_moves_nothing_until_the_button_comes_up_again() -> None:
    deadman = Deadman(Speeds(linear=0.4, angular=1.0))
    deadman.set_stick(0.5, 0.0, enabled=True)
    deadman.safety(False, 0.0)
    assert deadman.tick(0.0) == Twist(linear_x=0.2)
    deadman.safety(True, 0.1)
    assert deadman.tick(0.1) == Twist()
    deadman.safety(False, 0.2)  # reset, the button still held
    assert deadman.rearming and deadman.tick(0.2) is None and deadman.tick(1.0) is None
    deadman.set_stick(0.5, 0.0, enabled=False)
    deadman.safety(False, 1.1)
    deadman.set_stick(0.5, 0.0, enabled=True)
    assert not deadman.rearming and deadman.tick(1.2) == Twist(linear_x=0.2)


def test_the_line_says_to_let_go_after_a_reset_while_inputs_are_held() -> None:
    view, deadman = SafetyView(), Deadman()
    view.beat(SafetyStatus(seq=1, stamp=0.0, estop=EstopState(latched=True, source="operator", reason="x")), 0.0)
    deadman.safety(view.estop_latched(), 0.0)
    assert "E-STOP latched" in view.line(deadman, 0.0, 400) and REARM_WORDS not in view.line(deadman, 0.0, 400)
    deadman.press(Key.FORWARD, 0.1)
    view.beat(SafetyStatus(seq=2, stamp=0.0, estop=EstopState(latched=False)), 0.2)
    deadman.safety(view.estop_latched(), 0.2)
    assert REARM_WORDS in view.line(deadman, 0.2, 400)
    deadman.safety(view.estop_latched(), 0.1 + INITIAL_HOLD + 0.01)
    assert REARM_WORDS not in view.line(deadman, 0.7, 400)


def test_wake_is_due_for_the_next_resend_and_the_expiry() -> None:
    deadman = Deadman()
    deadman.press(Key.FORWARD, 0.0)
    assert deadman.tick(0.0) is not None
    assert deadman.wake(0.0) == pytest.approx(PUBLISH_PERIOD)
    assert deadman.wake(0.1) == 0.0  # overdue
    assert deadman.tick(0.47) is not None
    # The next resend (0.52) comes after the expiry (0.5): the expiry is due first.
    assert deadman.wake(0.48) == pytest.approx(INITIAL_HOLD + 1e-3 - 0.48)
    assert deadman.tick(0.502) == Twist()
    assert deadman.wake(0.502) == pytest.approx(0.1)  # nothing due: the line's redraw


def test_stick_fraction_centres_dead_zones_and_saturates() -> None:
    assert stick_fraction(128, 0, 256) == 0.0
    assert stick_fraction(140, 0, 256) == 0.0  # inside the dead zone
    assert stick_fraction(0, 0, 256) == -1.0
    assert stick_fraction(256, 0, 256) == 1.0
    assert stick_fraction(40000, -32768, 32767) == 1.0
    assert 0.0 < stick_fraction(200, 0, 256) < 1.0
    assert stick_fraction(5, 5, 5) == 0.0


# What safety did, as the line shows it


def beat(**fields: object) -> SafetyStatus:
    return SafetyStatus(seq=1, stamp=0.0, estop=EstopState(latched=False), **fields)  # type: ignore[arg-type]


def event(decision: Decision, sent: Twist | None, **fields: object) -> SafetyEvent:
    command = msgspec.Raw(msgspec.json.encode(sent))
    return SafetyEvent(stamp=0.0, key=keys.TELEOP_CMD_VEL.path, decision=decision, command=command, **fields)  # type: ignore[arg-type]


def test_the_line_reports_a_clamp_of_our_twist_and_ignores_another_teleops() -> None:
    view = SafetyView()
    deadman = Deadman(Speeds(linear=0.3), scale=3.0)
    deadman.press(Key.FORWARD, 0.0)
    ours = Twist(linear_x=0.9, stamp=123.25)
    view.sent(ours)
    view.beat(beat(), 0.0)
    assert "ready" in view.line(deadman, 0.0, 400)
    clamped = msgspec.structs.replace(ours, linear_x=0.6)
    values = {"requested_mps": 0.9, "speed_mps": 0.6, "turn_rps": 0.0}
    view.event(event(Decision.CLAMPED, clamped, rule=Rule.BASE_SPEED, values=values, reason="clamped"), 0.1)
    line = view.line(deadman, 0.1, 400)
    assert "cmd +0.90 m/s" in line and "scale x3.0" in line
    assert "CLAMPED to +0.60 m/s +0.00 rad/s (base_speed)" in line
    # Another source's twist on the same key, vetoed: not ours, not shown.
    other = Twist(linear_x=0.1, stamp=999.0)
    view.event(event(Decision.VETOED, other, rule=Rule.KEEP_OUT, reason="zone"), 0.2)
    assert "CLAMPED" in view.line(deadman, 0.2, 400)
    summary = view.summary()
    assert summary["decisions"] == {"approved": 0, "clamped": 1, "vetoed": 0}
    assert summary["clamped_by"] == {"base_speed": 1}
    assert view.line(deadman, 0.2, 40).endswith("~") and len(view.line(deadman, 0.2, 40)) == 40


def test_the_line_shows_vetoes_the_estop_a_missing_heartbeat_and_the_mode_when_there_is_one() -> None:
    view = SafetyView()
    deadman = Deadman()
    assert "NO HEARTBEAT" in view.line(deadman, 0.0, 400)
    view.beat(beat(speed_scale=0.4), 0.0)
    assert "people near: speed x0.4" in view.line(deadman, 0.0, 400)
    ours = Twist(linear_x=0.3, stamp=5.0)
    view.sent(ours)
    view.event(event(Decision.VETOED, ours, rule=Rule.KEEP_OUT, reason="the stairs ahead"), 0.1)
    assert "VETOED (keep_out): the stairs ahead" in view.line(deadman, 0.1, 400)
    # A count of repeated vetoes has no command: it counts.
    view.event(event(Decision.VETOED, None, rule=Rule.ESTOP, reason="3 more vetoed"), 0.2)
    assert view.summary()["decisions"]["vetoed"] == 2
    # Two seconds on without a heartbeat: stale, and said so.
    assert "NO HEARTBEAT" in view.line(deadman, 2.0, 400)
    view.beat(SafetyStatus(seq=2, stamp=0.0, estop=EstopState(latched=True, source="operator", reason="x")), 2.0)
    assert "E-STOP latched by operator: x" in view.line(deadman, 2.0, 400)


class PlainBeat(msgspec.Struct, frozen=True):
    """A heartbeat as the line reads it, without a mode: the line leaves the mode out."""

    seq: int = 1
    stamp: float = 0.0
    estop: EstopState = EstopState(latched=False)
    speed_scale: float = 1.0


class ModeBeat(PlainBeat, frozen=True):
    """One that names a mode, whether or not SafetyStatus has the field yet (the line reads it with getattr)."""

    mode: str = "shared"


def test_the_line_shows_the_mode_only_when_the_heartbeat_has_one() -> None:
    view = SafetyView()
    deadman = Deadman()
    view.beat(ModeBeat(), 0.0)  # type: ignore[arg-type]
    assert view.mode() == "shared" and "| mode shared |" in view.line(deadman, 0.0, 400)
    assert view.summary()["mode"] == "shared"
    view.beat(PlainBeat(), 0.0)  # type: ignore[arg-type]
    assert view.mode() is None and "mode" not in view.line(deadman, 0.0, 400)


# What anyone may publish on safety/estop (the MCP agent too): a reason that retitles the terminal,
# clears the screen and writes a false all-clear in green.
HOSTILE = "obstacle\x1b]0;PWNED\x07\x1b[2J\x1b[1;1H\x1b[32mALL CLEAR, safe to approach\x1b[0m\r\x9b2J\x7f"


def controls(text: str) -> list[str]:
    return [c for c in text if ord(c) < 0x20 or 0x7F <= ord(c) < 0xA0]


def test_the_line_escapes_control_characters_of_the_estop_a_veto_and_the_mode_at_any_width() -> None:
    view = SafetyView()
    deadman = Deadman()
    wire = msgspec.json.encode(
        {"seq": 1, "stamp": 0.0, "estop": {"latched": True, "source": HOSTILE, "reason": HOSTILE}}
    )
    view.beat(msgspec.json.decode(wire, type=SafetyStatus), 0.0)
    estop = view.line(deadman, 0.0, 1000)
    assert "E-STOP latched by obstacle\\x1b]0;PWNED\\x07" in estop and "ALL CLEAR" in estop
    ours = Twist(linear_x=0.3, stamp=5.0)
    view.sent(ours)
    view.beat(ModeBeat(mode=HOSTILE), 0.1)  # type: ignore[arg-type]
    view.event(event(Decision.VETOED, ours, rule=Rule.KEEP_OUT, reason=HOSTILE), 0.1)
    vetoed = view.line(deadman, 0.1, 1000)
    assert "VETOED (keep_out): obstacle\\x1b]0;PWNED" in vetoed and "| mode obstacle\\x1b]0;" in vetoed
    # Escaped before the cut: no width leaves a piece of a sequence at the end of the line.
    for line in (estop, vetoed):
        assert controls(line) == []
    for width in range(1, len(vetoed) + 2):
        assert controls(view.line(deadman, 0.1, width)) == []


def test_events_on_other_keys_are_not_teleops() -> None:
    view = SafetyView()
    ours = Twist(linear_x=0.3, stamp=5.0)
    view.sent(ours)
    e = SafetyEvent(
        stamp=0.0, key=keys.CMD_VEL.path, decision=Decision.VETOED, command=msgspec.Raw(msgspec.json.encode(ours))
    )
    view.event(e, 0.0)
    assert view.summary()["last"] is None


# The gamepad, with a stand-in for the evdev package (not installed here, and no device to read)


class AbsInfo(NamedTuple):
    value: int
    min: int
    max: int


class InputEvent(NamedTuple):
    type: int
    code: int
    value: int


ecodes = SimpleNamespace(
    EV_SYN=0, EV_KEY=1, EV_ABS=3, SYN_REPORT=0, SYN_DROPPED=3, ABS_X=0, ABS_Y=1, BTN_TL=310, BTN_TR=311
)


class FakeDevice:
    """evdev.InputDevice as Gamepad uses it: capabilities, a non-blocking read, the state now, then gone."""

    def __init__(self, path: str, axes: tuple[int, ...] = (0, 1)) -> None:
        if not path.startswith("/dev/input/"):
            raise FileNotFoundError(2, "No such file or directory")
        self.name = "Test Pad"
        self.axes = axes
        self.queue: list[list[InputEvent]] = []
        self.gone = False
        # What the device has now (EVIOCGKEY, EVIOCGABS), whatever was queued or lost.
        self.keys_down: set[int] = set()
        self.values = dict.fromkeys(axes, 128)

    def capabilities(self) -> dict[int, list[tuple[int, AbsInfo]]]:
        return {ecodes.EV_ABS: [(code, AbsInfo(128, 0, 255)) for code in self.axes], ecodes.EV_KEY: []}

    def active_keys(self) -> list[int]:
        return sorted(self.keys_down)

    def absinfo(self, code: int) -> AbsInfo:
        return AbsInfo(self.values[code], 0, 255)

    def fileno(self) -> int:
        return 99

    def read(self) -> Iterator[InputEvent]:
        if self.gone:
            raise OSError(19, "No such device")
        if not self.queue:
            raise BlockingIOError
        yield from self.queue.pop(0)

    def close(self) -> None:
        pass


@pytest.fixture
def evdev(monkeypatch: pytest.MonkeyPatch) -> SimpleNamespace:
    module = SimpleNamespace(ecodes=ecodes, InputDevice=FakeDevice)
    monkeypatch.setitem(sys.modules, "evdev", module)
    return module


def test_the_gamepad_drives_with_the_left_stick_while_a_shoulder_button_is_held(evdev: SimpleNamespace) -> None:
    pad = Gamepad(Path("/dev/input/event7"))
    device = pad.device
    assert pad.name == "Test Pad" and pad.fileno() == 99
    assert pad.read() == Stick(0.0, 0.0, False)  # nothing waiting: centred, not enabled
    # Stick fully up and a little right, no button: not enabled.
    device.queue.append([InputEvent(ecodes.EV_ABS, ecodes.ABS_Y, 0), InputEvent(ecodes.EV_ABS, ecodes.ABS_X, 200)])
    stick = pad.read()
    assert stick.linear == 1.0 and -1.0 < stick.angular < 0.0 and not stick.enabled
    device.queue.append([InputEvent(ecodes.EV_KEY, ecodes.BTN_TR, 1)])
    assert pad.read().enabled
    device.queue.append([InputEvent(ecodes.EV_KEY, ecodes.BTN_TR, 0), InputEvent(ecodes.EV_ABS, ecodes.ABS_Y, 128)])
    assert pad.read() == Stick(0.0, stick.angular, False)
    device.gone = True
    with pytest.raises(OSError):
        pad.read()


SYN_REPORT = InputEvent(ecodes.EV_SYN, ecodes.SYN_REPORT, 0)
SYN_DROPPED = InputEvent(ecodes.EV_SYN, ecodes.SYN_DROPPED, 0)


def test_events_the_kernel_dropped_stop_the_stick_until_the_device_is_read_anew(evdev: SimpleNamespace) -> None:
    pad = Gamepad(Path("/dev/input/event7"))
    device = pad.device
    device.queue.append(
        [InputEvent(ecodes.EV_ABS, ecodes.ABS_Y, 0), InputEvent(ecodes.EV_KEY, ecodes.BTN_TR, 1), SYN_REPORT]
    )
    assert pad.read() == Stick(1.0, 0.0, True)
    # teleop fell behind, the kernel's queue overflowed: the button's release and the stick's return
    # were lost. The device now has the button up and the stick centred.
    device.values[ecodes.ABS_Y] = 128
    device.queue.append([SYN_DROPPED, InputEvent(ecodes.EV_ABS, ecodes.ABS_Y, 5)])
    assert not pad.read().enabled, "drove on a state known to be wrong"
    device.queue.append([SYN_REPORT])
    assert pad.read() == Stick(0.0, 0.0, False)
    # A loss while the button stays held: driving again once the device is read anew.
    device.keys_down, device.values[ecodes.ABS_X] = {ecodes.BTN_TL}, 0
    device.queue.append([SYN_DROPPED, SYN_REPORT])
    stick = pad.read()
    assert stick.enabled and stick.angular == 1.0 and stick.linear == 0.0
    device.queue.append([InputEvent(ecodes.EV_KEY, ecodes.BTN_TL, 0), SYN_REPORT])
    assert not pad.read().enabled


def test_gamepad_errors_name_what_is_wrong(evdev: SimpleNamespace, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(TeleopError, match="--gamepad /nowhere: cannot open it"):
        Gamepad(Path("/nowhere"))
    monkeypatch.setattr(evdev, "InputDevice", lambda path: FakeDevice(path, axes=(0,)))
    with pytest.raises(TeleopError, match=r"'Test Pad' has no stick \(ABS_Y missing\)"):
        Gamepad(Path("/dev/input/event3"))
    monkeypatch.setitem(sys.modules, "evdev", None)  # not installed: the import fails
    with pytest.raises(TeleopError, match="needs the Python package evdev, which is not installed"):
        Gamepad(Path("/dev/input/event3"))
