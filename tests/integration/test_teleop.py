"""`tether teleop` in a real terminal (tmux) against the sim and safety: it drives while keys repeat,
the robot is at rest within 0.5 s of the last key (on the sim's odometry stamps), a lost focus and a
closed terminal stop it at once, and q quits with the terminal restored."""

from __future__ import annotations

import json
import shlex
import shutil
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from schemas import keys
from schemas.robot import Odometry
from schemas.safety import SafetyStatus
from schemas.world import Empty, GroundTruth, MoveEntity
from services.worldmodel import load_world
from tests.integration.conftest import Stack, start_stack, stop_stack
from tests.watch import Watch
from tether.teleop import FOCUS_OFF, FOCUS_ON, INITIAL_HOLD

TMUX = shutil.which("tmux")
pytestmark = [
    pytest.mark.realtime,
    pytest.mark.skipif(TMUX is None, reason="tmux is not installed (Debian: apt-get install -y tmux)"),
]

ROOT = Path(__file__).resolve().parents[2]
# How often the test repeats a held key (terminals: every 30 to 50 ms).
REPEAT = 0.04
# The bound under test, and what the measurement adds: the odometry's period (50 Hz) and the
# moment send-keys returns being a little before the key is read.
STOP_BOUND = 0.5
SLACK = 0.1
AT_REST = 0.01  # m/s and rad/s
# The base's braking limit (the sim's, as for acceleration): m/s².
BRAKING = load_world().robot.max_linear_acceleration


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    """The sim at real time and safety: all teleop needs."""
    s = start_stack(
        tmp_path_factory.mktemp("teleop"), realtime_factor=1.0, services=("sim", "safety"), strict_timing=True
    )
    try:
        # The operator away from the base's way: full speed, no separation limit.
        s.node.call(keys.SIM_MOVE, MoveEntity(id="operator", x=3.0, y=7.0), timeout=10.0)
        yield s
    finally:
        stop_stack(s)


def wait_until(predicate: Callable[[], bool], timeout: float) -> bool:
    """Poll `predicate` until it holds or `timeout` passes; whether it held."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        threading.Event().wait(0.05)
    return True


class Tmux:
    """A tmux server of the test's own (its own socket, no user config), killed at the end."""

    def __init__(self, env: dict[str, str]) -> None:
        assert TMUX is not None
        self.base = [TMUX, "-L", f"tether-teleop-{uuid.uuid4().hex[:8]}", "-f", "/dev/null"]
        self.env = env

    def __call__(self, *args: str) -> str:
        done = subprocess.run([*self.base, *args], env=self.env, capture_output=True, text=True, timeout=10)
        assert done.returncode == 0, f"tmux {' '.join(args)}: {done.stderr}"
        return done.stdout

    def screen(self, session: str) -> str:
        return self("capture-pane", "-p", "-t", session)

    def wait_screen(self, session: str, predicate: Callable[[str], bool], timeout: float) -> str:
        """The screen once `predicate` holds for it, or as it is at the deadline."""
        wait_until(lambda: predicate(self.screen(session)), timeout)
        return self.screen(session)

    def close(self) -> None:
        subprocess.run([*self.base, "kill-server"], env=self.env, capture_output=True, timeout=10)


@pytest.fixture
def tmux(robot: Stack) -> Iterator[Tmux]:
    t = Tmux(robot.supervisor.env())
    try:
        yield t
    finally:
        t.close()


TELEOP = f"{shlex.quote(sys.executable)} -m tether teleop"


def start_teleop(tmux: Tmux, session: str, command: str, output: Path) -> None:
    """`command` in a new 160x10 terminal whose every output byte goes to `output`; returns once
    teleop has heard safety's heartbeat and taken the terminal (it turned focus reports on)."""
    tmux("new-session", "-d", "-s", session, "-x", "160", "-y", "10", "-c", str(ROOT), "bash --norc --noprofile")
    tmux("pipe-pane", "-t", session, "-o", f"cat >> {shlex.quote(str(output))}")
    tmux("send-keys", "-t", session, "-l", command)
    tmux("send-keys", "-t", session, "Enter")

    def started(_: str) -> bool:
        return output.exists() and FOCUS_ON in output.read_text(errors="replace")

    screen = tmux.wait_screen(session, started, timeout=60.0)
    assert started(screen), f"teleop did not start:\n{screen}"


def hold_key(tmux: Tmux, session: str, key: str, seconds: float) -> float:
    """Press `key` and repeat it every REPEAT for `seconds`, as a terminal does for a held key; the
    wall time just after the last one was sent."""
    end = time.monotonic() + seconds
    while True:
        tmux("send-keys", "-t", session, key)
        sent = time.time()
        if time.monotonic() >= end:
            return sent
        threading.Event().wait(REPEAT)  # the key repeat's pace, not a wait for a condition


def at_rest(odom: Watch[Odometry], since: float, after: int) -> Odometry | None:
    """The first odometry stamped after `since` with the base still, that stays still for 0.3 s."""
    first = odom.wait_for(
        lambda o: o.stamp > since and abs(o.linear_x) < AT_REST and abs(o.angular_z) < AT_REST, 3.0, after
    )
    if first is None:
        return None
    index = odom.messages.index(first)
    assert odom.wait_for(lambda o: o.stamp > first.stamp + 0.3, 2.0, after=index)
    still = [o for o in odom.messages[index:] if o.stamp <= first.stamp + 0.3]
    return first if all(abs(o.linear_x) < AT_REST for o in still) else None


def held_rest(pressed: float, moving: Odometry) -> float:
    """The soonest a base whose one key press held its twist for INITIAL_HOLD could be at rest: driving on
    at no less than `moving`'s speed until `pressed + INITIAL_HOLD` (the held twist only speeds it up),
    then braking at BRAKING down to AT_REST. A base stopped at once rests sooner, by however much of the
    hold was left when the stop was sent (on a loaded machine seeing it move took 0.31 s of the 0.5)."""
    return pressed + INITIAL_HOLD + (abs(moving.linear_x) - AT_REST) / BRAKING


def truth(stack: Stack) -> GroundTruth:
    return stack.node.call(keys.GROUND_TRUTH, Empty(), timeout=5.0)


def test_teleop_drives_while_keys_repeat_stops_within_half_a_second_and_q_restores_the_terminal(
    robot: Stack, tmux: Tmux
) -> None:
    tmp = robot.tmp
    output, rc, stty = tmp / "pane.out", tmp / "teleop.rc", tmp / "stty.txt"
    odom = Watch(robot.node, keys.ODOM)
    before = truth(robot)
    start_teleop(tmux, "drive", f"{TELEOP}; echo $? > {rc}; stty -a > {stty}", output)

    # Up held for a second: the base drives forward (it faces +x at the start).
    last_key = hold_key(tmux, "drive", "Up", 1.0)
    screen = tmux.screen("drive")
    n = len(odom)
    rest = at_rest(odom, last_key, after=0)
    assert rest is not None, "the base never came to rest after the keys stopped"
    assert rest.stamp - last_key <= STOP_BOUND + SLACK, f"at rest {rest.stamp - last_key:.3f} s after the last key"
    after = truth(robot)
    assert after.robot.x - before.robot.x > 0.15, (before.robot, after.robot)
    assert abs(after.robot.y - before.robot.y) < 0.05 and abs(after.robot.yaw - before.robot.yaw) < 0.05
    assert max(o.linear_x for o in odom.messages[:n]) > 0.25, "never near the commanded 0.3 m/s"
    assert "cmd +0.30 m/s" in screen and "scale x1.0" in screen, screen
    if "mode" in SafetyStatus.__struct_fields__:  # safety's heartbeat names the mode: the line shows it
        assert "| mode autonomous |" in screen, screen

    # Faster than the robot may go (x3.0: 2.4 rad/s, the limit 1.2), turning in place: safety clamps
    # it and the line says so.
    tmux("send-keys", "-t", "drive", "-l", "+" * 25)
    tmux.wait_screen("drive", lambda s: "scale x3.0" in s, timeout=5.0)
    hold_key(tmux, "drive", "Left", 0.8)
    screen = tmux.screen("drive")
    assert "cmd +0.00 m/s +2.40 rad/s" in screen, screen
    assert "safety: CLAMPED to +0.00 m/s +1.20 rad/s (base_speed)" in screen, screen
    turning = [o.angular_z for o in odom.messages[n:]]
    assert 1.0 < max(turning) <= 1.2 * 1.1 + 0.05, max(turning)
    assert at_rest(odom, time.time(), after=len(odom)) is not None
    tmux("send-keys", "-t", "drive", "-l", "_" * 20)  # _ is - with shift
    tmux.wait_screen("drive", lambda s: "scale x1.0" in s, timeout=5.0)

    # One key, then the terminal loses focus: stopped at once, not held for the repeat delay.
    tmux("send-keys", "-t", "drive", "Up")
    pressed = time.time()
    moving = odom.wait_for(lambda o: o.stamp > pressed and o.linear_x > 0.1, 3.0, after=len(odom))
    assert moving is not None
    tmux("send-keys", "-t", "drive", "-H", "1b", "5b", "4f")  # ESC [ O: xterm's focus out
    lost = time.time()
    rest = at_rest(odom, lost, after=len(odom))
    assert rest is not None
    # Held, it would have moved until `pressed + INITIAL_HOLD`, then braked.
    late = rest.stamp - held_rest(pressed, moving)
    assert late < 0, f"at rest {rest.stamp - lost:.3f} s after the focus left, {late:.3f} s late"

    # q: teleop ends (exit 0), and the shell's terminal is as it was: line editing and echo back on,
    # focus reports off again.
    tmux("send-keys", "-t", "drive", "q")
    tmux.wait_screen("drive", lambda _: stty.exists() and stty.stat().st_size > 0, timeout=20.0)
    assert rc.read_text().strip() == "0", output.read_text(errors="replace")
    modes = stty.read_text().split()
    assert {"icanon", "echo", "isig", "opost"} <= set(modes), modes
    written = output.read_text(errors="replace")
    assert FOCUS_ON in written and FOCUS_OFF in written.split(FOCUS_ON)[-1]
    assert "teleop ended (quit)" in written
    summary = next(line for line in written.splitlines() if "teleop ended" in line)
    assert "clamped 0," not in summary, summary


def test_closing_the_terminal_while_driving_stops_the_robot_at_once(robot: Stack, tmux: Tmux) -> None:
    odom = Watch(robot.node, keys.ODOM)
    summary = robot.tmp / "summary.json"
    start_teleop(tmux, "close", f"exec {TELEOP} --json > {summary}", robot.tmp / "close.out")
    # Backwards this time (the first test drove forward), one key: held INITIAL_HOLD if nothing else happens.
    tmux("send-keys", "-t", "close", "Down")
    pressed = time.time()
    moving = odom.wait_for(lambda o: o.stamp > pressed and o.linear_x < -0.1, 3.0, after=len(odom))
    assert moving is not None
    tmux("kill-session", "-t", "close")  # the window closes: SIGHUP
    closed = time.time()
    rest = at_rest(odom, closed, after=len(odom))
    assert rest is not None
    # Left to the robot, the last twist would hold for the sim's 0.5 s cmd_vel timeout after the hold.
    late = rest.stamp - held_rest(pressed, moving)
    assert late < 0, f"at rest {rest.stamp - closed:.3f} s after the terminal closed, {late:.3f} s late"
    # --json: one object on stdout (a file here), saying why it ended and what safety did.
    assert wait_until(lambda: summary.stat().st_size > 0, timeout=10.0), "no summary"
    ended = json.loads(summary.read_text())
    assert ended["ended"] in ("SIGHUP (terminal closed)", "terminal closed"), ended
    assert ended["twists_sent"] >= 2 and ended["max_commanded"]["linear_mps"] == 0.3
    assert ended["safety"]["decisions"]["approved"] + ended["safety"]["decisions"]["clamped"] >= 1
