"""The robot link over real processes: what safety did not sign never moves the robot, and is reported.

An attacker on the same machine (a plain Zenoh session, no key) puts robot/cmd_vel and sends a goal
straight to the sim; forges and replays heartbeats with the e-stop unlatched while safety's says
latched. The sim drops each, names it in robot/diagnostics, and the base stays where it is (ground
truth). A session holding the stack's key (as only safety does) is the control: its command moves it.
The recording of it all, through `tether inspect` and `tether recheck`, flags each as not safety's.
"""

from __future__ import annotations

import json
import math
import secrets
import stat
import threading
import time
from collections.abc import Callable, Iterator

import pytest
import zenoh

from schemas import keys
from schemas.actions import SendGoal
from schemas.common import ErrorKind, Pose2D
from schemas.robot import NavigateToPoseGoal, Twist
from schemas.safety import EstopSource, EstopState, SafetyStatus
from schemas.trace import RecorderStatus
from schemas.world import Empty, GroundTruth
from services.errors import CallError
from services.robotlink import BAD_MAC, NOT_SIGNED, REPLAYED, Signer
from services.runtime import Node, encode
from tests.integration.conftest import Stack, start_stack, stop_stack, tether_cli
from tests.procs import wait_until
from tests.watch import Watch
from tether.client import reset_estop, trigger_estop

# The base counts as not moved within this (m, rad); a 0.5 m/s command for a second would be far past it.
STILL = 0.01


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    tmp = tmp_path_factory.mktemp("robot_link")
    s = start_stack(tmp, realtime_factor=2.0, services=("sim", "safety", "recorder"))
    try:
        yield s
    finally:
        stop_stack(s)


def truth(stack: Stack) -> GroundTruth:
    return stack.node.call(keys.GROUND_TRUTH, Empty(), timeout=5.0)


def moved(before: GroundTruth, after: GroundTruth) -> float:
    return math.dist((before.robot.x, before.robot.y), (after.robot.x, after.robot.y)) + abs(
        after.robot.yaw - before.robot.yaw
    )


def problems(stack: Stack) -> str:
    return " | ".join(p.text for p in stack.node.call(keys.ROBOT_DIAGNOSTICS, Empty(), timeout=5.0).problems)


def wait_reported(stack: Stack, *texts: str, timeout: float = 10.0) -> str:
    deadline = time.monotonic() + timeout
    while not all(t in (found := problems(stack)) for t in texts):
        assert time.monotonic() < deadline, f"not reported: {texts}; robot/diagnostics: {found}"
        time.sleep(0.05)  # polling the diagnostics with a deadline
    return found


def flood(node: Node, seconds: float, send: Callable[[Node], None]) -> None:
    """`send` at 20 Hz for `seconds` (as a teleop stream would)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        send(node)
        time.sleep(0.05)  # pacing the stream at 20 Hz


def test_the_key_is_the_stacks_own_and_only_its_owner_reads_it(stack: Stack) -> None:
    path = stack.supervisor.robot_key_file
    # Beside the operator token, never in the log directory (which goes into incident reports).
    assert path.parent == stack.tmp and stat.S_IMODE(path.stat().st_mode) == 0o600
    assert not list((stack.tmp / "logs").glob("*.key"))
    assert len(bytes.fromhex(path.read_text().strip())) == 32


def test_an_attackers_cmd_vel_and_goal_never_move_the_robot_and_are_reported(stack: Stack) -> None:
    odom = Watch(stack.node, keys.ODOM)
    before = truth(stack)
    cmd_vel = keys.ROBOT_CMD_VEL.key(stack.settings.robot)
    with Node("attacker", stack.settings) as attacker:
        goal = SendGoal(goal_id="attack1", goal=NavigateToPoseGoal(pose=Pose2D(x=before.robot.x - 2.0, y=1.2)))
        with pytest.raises(CallError, match="not signed by safety") as refused:
            attacker.call(keys.ROBOT_NAVIGATE.send_goal, goal, timeout=5.0)
        assert refused.value.error.kind is ErrorKind.UNAUTHORIZED
        # Signed with a key of its own making, and bare: both dropped.
        forger = Signer(secrets.token_bytes(32))
        payload = encode(Twist(linear_x=0.5))

        def send(node: Node) -> None:
            node.session.put(cmd_vel, payload)
            node.session.put(cmd_vel, payload, attachment=forger.sign(cmd_vel, payload))

        flood(attacker, 1.0, send)
    n = len(odom)
    assert odom.wait_for(lambda _o: True, timeout=2.0, after=n), "no odometry"
    assert max(abs(o.linear_x) for o in odom.messages) < STILL, "the base moved"
    assert moved(before, truth(stack)) < STILL
    found = wait_reported(
        stack, f"robot/cmd_vel: {NOT_SIGNED}", f"robot/cmd_vel: {BAD_MAC}", "robot/navigate_to_pose/_action/send_goal"
    )
    assert "so far" in found

    # The control: the same command signed with the stack's key moves it (so the test could fail).
    with Node("key-holder", stack.settings) as holder:
        holder.signer = Signer(stack.supervisor.robot_key())
        flood(holder, 0.5, lambda node: node.publish(keys.ROBOT_CMD_VEL, Twist(angular_z=0.3)))
    assert odom.wait_for(lambda o: abs(o.angular_z) > 0.1, timeout=5.0, after=n), "a signed command did not move it"


def test_forged_and_replayed_heartbeats_do_not_unlatch_the_robot(stack: Stack) -> None:
    heartbeat = keys.HEARTBEAT.key(stack.settings.robot)
    captured: list[tuple[bytes, bytes]] = []
    got = threading.Event()

    def capture(sample: zenoh.Sample) -> None:
        # Safety's own heartbeats, unlatched, with their MACs: what a replay sends again.
        if sample.attachment is not None and b'"latched":false' in sample.payload.to_bytes():
            captured.append((sample.payload.to_bytes(), sample.attachment.to_bytes()))
            if len(captured) >= 20:
                got.set()

    with Node("attacker", stack.settings) as attacker:
        tap = attacker.session.declare_subscriber(heartbeat, capture)
        assert got.wait(5.0), "no heartbeats from safety"
        tap.undeclare()
        assert trigger_estop(stack.node, EstopSource.OPERATOR, "robot link test") is not None
        odom = Watch(stack.node, keys.ODOM)
        before = truth(stack)
        unlatched = encode(SafetyStatus(seq=10**6, stamp=time.time(), estop=EstopState(latched=False), speed_scale=1.0))
        replays = iter(captured)

        def send(node: Node) -> None:
            node.session.put(heartbeat, unlatched)  # forged, no MAC
            if (replay := next(replays, None)) is not None:
                node.session.put(heartbeat, replay[0], attachment=replay[1])  # replayed, safety's own MAC

        # A key holder's signed command goes with them: it would move the robot, were it released.
        with Node("key-holder", stack.settings) as holder:
            holder.signer = Signer(stack.supervisor.robot_key())

            def both(node: Node) -> None:
                send(node)
                holder.publish(keys.ROBOT_CMD_VEL, Twist(linear_x=0.5))

            flood(attacker, 1.5, both)
        assert max(abs(o.linear_x) for o in odom.messages) < STILL, "the base moved on a forged heartbeat"
        assert moved(before, truth(stack)) < STILL
        wait_reported(stack, f"safety/heartbeat: {NOT_SIGNED}", f"safety/heartbeat: {REPLAYED}")
    reply = reset_estop(stack.node, str(stack.token_file))
    assert reply.ok, reply.message


def test_the_robot_refuses_a_signed_goal_into_a_keep_out_zone_on_its_own(stack: Stack) -> None:
    """Past safety with the key (as a compromised safety would send it): the sim checks the zone itself."""
    odom = Watch(stack.node, keys.ODOM)
    before = truth(stack)
    stairs = SendGoal(goal_id="into-stairs", goal=NavigateToPoseGoal(pose=Pose2D(x=11.2, y=8.0, yaw=1.5708)))
    with Node("key-holder", stack.settings) as holder:
        holder.signer = Signer(stack.supervisor.robot_key())
        reply = holder.call(keys.ROBOT_NAVIGATE.send_goal, stairs, timeout=10.0)
    assert not reply.accepted and "keep-out zone 'stairs'" in reply.reason, reply
    n = len(odom)
    assert odom.wait_for(lambda _o: True, timeout=2.0, after=n), "no odometry"
    assert max(abs(o.linear_x) for o in odom.messages[n:]) < STILL and moved(before, truth(stack)) < 0.05
    wait_reported(stack, "refused a navigate_to_pose goal", "'stairs'")


def recorded(stack: Stack) -> int:
    """How many messages the recorder has taken so far (each status query adds one, its trace)."""
    status: RecorderStatus = stack.node.call(keys.RECORDER_STATUS, Empty(), timeout=5.0)
    return status.messages


def test_inspect_and_recheck_flag_what_was_not_safetys(stack: Stack) -> None:
    # One command through safety, so recheck has a decision to check beside the flags.
    sent = Watch(stack.node, keys.ROBOT_CMD_VEL)
    decided = Watch(stack.node, keys.SAFETY_EVENTS)
    deadline = time.monotonic() + 10.0
    while sent.latest(0.1) is None:
        assert time.monotonic() < deadline, "safety passed no cmd_vel on"
        stack.node.publish(keys.CMD_VEL, Twist(angular_z=0.2))
    # Safety publishes its decision just after the twist it passed on. Heard here, it may still be on
    # its way to the recorder, or in its queue (a make test run stopped the recorder that soon and
    # lost it): the recorder is stopped only once it has taken another 200 messages after that, over
    # a second of the stack's own traffic (odometry, joint states, heartbeats at 50 Hz each).
    assert decided.wait_for(lambda e: e.key == keys.CMD_VEL.path, timeout=10.0) is not None, "no decision heard"
    heard = recorded(stack)
    taken = wait_until(lambda: recorded(stack) >= heard + 200, 20.0)
    assert taken, f"the recorder took {recorded(stack) - heard} messages in 20 s"
    assert stack.supervisor.stop("recorder") == 0
    [file] = stack.recordings.glob("*.mcap")
    inspected = tether_cli(stack, "inspect", "--json", str(file))
    assert inspected.returncode == 0, inspected.stderr
    rows = json.loads(inspected.stdout)["rows"]
    suspects = [(r["key"], r["summary"]) for r in rows if r["kind"] == "suspect"]
    assert all(summary.startswith("NOT SAFETY'S") for _, summary in suspects), suspects
    said = {(key, summary.split(": ", 2)[2]) for key, summary in suspects}
    for expected in (
        ("robot/cmd_vel", "not signed by safety"),  # the attacker's bare twists
        ("robot/cmd_vel", "signed by another sender"),  # the forger's and the key holder's
        ("safety/heartbeat", "not signed by safety"),
        ("safety/heartbeat", "replayed or reordered"),
        ("robot/navigate_to_pose/_action/send_goal", "refused by the robot"),
    ):
        assert any(key == expected[0] and why.startswith(expected[1]) for key, why in said), (expected, said)
    rechecked = tether_cli(stack, "recheck", str(file))
    assert rechecked.returncode == 1, rechecked.stdout + rechecked.stderr
    output = " ".join((rechecked.stdout + rechecked.stderr).split())
    assert "not safety's" in output and "safety/heartbeat: replayed or reordered" in output, output
