"""`tether teleop`'s deadman where two things change at once: the e-stop's reset and the gamepad's state."""

from __future__ import annotations

import dataclasses
import json
import os
import pty
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import cast

import pytest
import zenoh

from schemas import keys
from schemas.robot import Twist
from services.runtime import ALL_SERVICES, Node, NodeSettings
from tests.sessions import free_ports
from tests.unit.test_teleop import SYN_DROPPED, SYN_REPORT, FakeDevice, InputEvent, ecodes
from tether.teleop import EXIT_INPUT_LOST, EXIT_OK, SIGNAL_ENDINGS, Deadman, Gamepad, Speeds


@pytest.fixture
def pad(monkeypatch: pytest.MonkeyPatch) -> Gamepad:
    monkeypatch.setitem(sys.modules, "evdev", SimpleNamespace(ecodes=ecodes, InputDevice=FakeDevice))
    return Gamepad(Path("/dev/input/event7"))


def read_into(pad: Gamepad, deadman: Deadman) -> None:
    """What teleop's loop does when the gamepad is readable."""
    deadman.set_stick(**dataclasses.asdict(pad.read()))


def test_events_lost_after_a_reset_do_not_count_as_the_enable_button_let_go(pad: Gamepad) -> None:
    """While the kernel's lost events are not read anew, the stick is not trusted: it does not drive,
    and it is not known to be let go either. Taken as let go, it re-armed the deadman after a reset,
    and the device read anew, the button still held, set the robot off."""
    device: FakeDevice = pad.device
    deadman = Deadman(Speeds(linear=0.4, angular=1.0))
    device.keys_down, device.values[ecodes.ABS_Y] = {ecodes.BTN_TR}, 0
    device.queue.append(
        [InputEvent(ecodes.EV_ABS, ecodes.ABS_Y, 0), InputEvent(ecodes.EV_KEY, ecodes.BTN_TR, 1), SYN_REPORT]
    )
    read_into(pad, deadman)
    deadman.safety(False, 0.0)
    assert deadman.tick(0.0) == Twist(linear_x=0.4)
    deadman.safety(True, 0.1)  # the e-stop latched
    assert deadman.tick(0.1) == Twist()
    deadman.safety(False, 0.2)  # reset, the button held all along
    assert deadman.rearming
    # teleop fell behind as the stick jittered: the kernel's queue overflowed, nothing up or down lost.
    device.queue.append([SYN_DROPPED, InputEvent(ecodes.EV_ABS, ecodes.ABS_Y, 3)])
    read_into(pad, deadman)
    deadman.safety(False, 1.0)
    assert deadman.tick(1.0) is None
    device.queue.append([SYN_REPORT])  # read anew: the button is still held
    read_into(pad, deadman)
    deadman.safety(False, 1.1)
    assert deadman.rearming and deadman.tick(1.1) is None, "the reset set it off on the button still held"
    # Let go, then held again: it drives.
    device.queue.append([InputEvent(ecodes.EV_KEY, ecodes.BTN_TR, 0), SYN_REPORT])
    read_into(pad, deadman)
    deadman.safety(False, 1.2)
    device.queue.append([InputEvent(ecodes.EV_KEY, ecodes.BTN_TR, 1), SYN_REPORT])
    read_into(pad, deadman)
    deadman.safety(False, 1.3)
    assert deadman.tick(1.3) == Twist(linear_x=0.4)


# A signal while teleop waits for safety's first heartbeat


def wait_until(condition: Callable[[], bool], what: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"not within {timeout} s: {what}"
        time.sleep(0.005)


def matching(publisher: zenoh.Publisher) -> bool:
    return cast(zenoh.MatchingStatus, publisher.matching_status).matching  # the stub says bool


@pytest.mark.parametrize("number", [signal.SIGTERM, signal.SIGHUP])
def test_a_signal_while_waiting_for_safetys_heartbeat_ends_teleop_with_its_summary(number: int) -> None:
    """Ctrl-C there ended it with its summary (exit 0, one JSON object with --json); SIGTERM and SIGHUP
    killed it: no summary, exit -15, as if teleop had crashed."""
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_ports(len(ALL_SERVICES)))
    pty_main, pty_side = pty.openpty()  # teleop reads keys from a terminal
    with Node("safety", settings) as safety:  # where safety would be, and no heartbeat
        beats = safety.session.declare_publisher(keys.HEARTBEAT.key(settings.robot))
        base = ["--robot", settings.robot, "--base-port", str(settings.base_port)]
        teleop = subprocess.Popen(
            [sys.executable, "-m", "tether", *base, "teleop", "--json"],
            stdin=pty_side,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        try:
            # teleop subscribed to the heartbeat: it waits (HEARTBEAT_WAIT) for safety's first.
            wait_until(lambda: matching(beats), "teleop waiting for the heartbeat", 60.0)
            teleop.send_signal(number)
            out, err = teleop.communicate(timeout=30.0)
        finally:
            if teleop.poll() is None:
                teleop.kill()
                teleop.communicate()
            os.close(pty_main)
            os.close(pty_side)
            beats.undeclare()
    lost_input = number == signal.SIGHUP
    assert teleop.returncode == (EXIT_INPUT_LOST if lost_input else EXIT_OK), (teleop.returncode, out, err)
    summary = json.loads(out)
    assert summary["ended"] == SIGNAL_ENDINGS[signal.Signals(number)] and summary["twists_sent"] == 0, summary
    assert "Traceback" not in err, err
