"""Safety over real processes: unsafe plans never move the robot, people slow and pause it, teleop is
clamped while programs are refused, the monitors and the watchdog latch the e-stop, the arm stops on
an e-stop, a bad policy file keeps safety from starting, and every event names the policy."""

from __future__ import annotations

import hashlib
import json
import math
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from schemas import keys
from schemas.actions import GoalState
from schemas.common import Pose2D
from schemas.executor import ExecutePlanGoal, PlanStatus
from schemas.robot import ARM_JOINTS, FollowJointTrajectoryGoal, NavigateToPoseGoal, Odometry, TrajectoryPoint, Twist
from schemas.safety import Decision, EstopSource, Rule
from schemas.world import Empty, GroundTruth, MoveEntity
from services.actionlib import ActionClient
from services.safety.policyfile import DEFAULT_POLICY
from tests.integration.conftest import Stack, start_stack, stop_stack
from tests.watch import Watch
from tether.client import PlanSender, reset_estop, trigger_estop

POLICY_HASH = "sha256:" + hashlib.sha256(DEFAULT_POLICY.read_bytes()).hexdigest()


def truth(stack: Stack) -> GroundTruth:
    return stack.node.call(keys.GROUND_TRUTH, Empty(), timeout=5.0)


def move(stack: Stack, entity: str, x: float, y: float) -> None:
    stack.node.call(keys.SIM_MOVE, MoveEntity(id=entity, x=x, y=y), timeout=10.0)


@pytest.fixture
def robot_stack(tmp_path: Path) -> Iterator[Stack]:
    """The robot and its safety only, the sim at real time: commands sent as the executor would."""
    s = start_stack(tmp_path, realtime_factor=1.0, services=("sim", "safety"), strict_timing=True)
    try:
        yield s
    finally:
        stop_stack(s)


@pytest.fixture
def safety_alone(tmp_path: Path) -> Iterator[Stack]:
    """Safety with no robot: the test plays the robot's state, to make it fail in ways the sim cannot."""
    s = start_stack(tmp_path, realtime_factor=1.0, services=("safety",), strict_timing=True)
    try:
        yield s
    finally:
        stop_stack(s)


UNSAFE_PLANS = {
    "payload": ({"plan": [{"action": "pick", "target": "cast-iron pan"}]}, "payload"),
    "speed": (
        {"plan": [{"action": "navigate_to", "target": "kitchen table", "parameters": {"speed": 0.9}}]},
        "0.6 m/s",
    ),
    "last step": (
        {"plan": [{"action": "navigate_to", "target": "kitchen"}, {"action": "navigate_to", "target": "stairs"}]},
        "stairs",
    ),
}


def test_unsafe_plans_never_move_the_robot(stack: Stack) -> None:
    odom = Watch(stack.node, keys.ODOM)
    joints = Watch(stack.node, keys.JOINT_STATES)
    events = Watch(stack.node, keys.SAFETY_EVENTS)
    before = truth(stack)
    assert joints.wait_for(lambda _: True, timeout=5.0)
    arm_before = joints.messages[-1].position[: len(ARM_JOINTS)]
    for name, (plan, why) in UNSAFE_PLANS.items():
        run = PlanSender(stack.node).run(ExecutePlanGoal(text=json.dumps(plan)), 60.0)
        assert run.result is not None
        assert (run.result.status, run.result.stage) == (PlanStatus.REJECTED, "safety"), (name, run.result.reason)
        assert why in run.result.reason, (name, run.result.reason)
    after = truth(stack)
    assert after.sim_time > before.sim_time
    assert math.hypot(after.robot.x - before.robot.x, after.robot.y - before.robot.y) < 0.005
    assert abs(after.robot.yaw - before.robot.yaw) < 0.005
    assert all(abs(o.linear_x) < 0.01 and abs(o.angular_z) < 0.01 for o in odom.messages)
    arm_after = joints.messages[-1].position[: len(ARM_JOINTS)]
    assert max(abs(a - b) for a, b in zip(arm_before, arm_after, strict=True)) < 0.005
    # Each veto's event, which comes on its own key and may follow the plan's result (a run here found
    # the last plan's not yet heard when the result was in).
    for rule in (Rule.PAYLOAD, Rule.BASE_SPEED, Rule.KEEP_OUT):
        vetoed = events.wait_for(lambda e, rule=rule: e.decision is Decision.VETOED and e.rule is rule, timeout=10.0)
        assert vetoed is not None, f"no {rule.value} veto among the events: {events.messages}"
    assert all(e.policy_hash == POLICY_HASH for e in events.messages)


@pytest.mark.realtime
def test_an_estop_during_arm_motion_stops_the_arm(robot_stack: Stack) -> None:
    stack = robot_stack
    joints = Watch(stack.node, keys.JOINT_STATES)
    first = joints.wait_for(lambda _: True, timeout=10.0)
    assert first is not None
    start = first.position[: len(ARM_JOINTS)]
    target = [start[0] + 1.0, *start[1:]]
    goal = FollowJointTrajectoryGoal(
        joint_names=list(ARM_JOINTS),
        points=[
            TrajectoryPoint(positions=start, time_from_start=0.0),
            TrajectoryPoint(positions=target, time_from_start=2.0),
        ],
    )
    handle = ActionClient(stack.node, keys.CMD_TRAJECTORY).send(goal)
    assert joints.wait_for(lambda j: abs(j.velocity[0]) > 0.3, timeout=10.0), "the arm never started moving"

    n = len(joints)
    pressed = time.time()
    assert trigger_estop(stack.node, EstopSource.EXECUTOR, "stop during arm motion") is not None
    still = joints.wait_for(
        lambda j: j.stamp > pressed and all(abs(v) < 0.01 for v in j.velocity[: len(ARM_JOINTS)]), timeout=2.0, after=n
    )
    assert still is not None, "the arm kept moving after the e-stop"
    result = handle.result(timeout=10.0)
    assert result.state is GoalState.ABORTED and "e-stop" in result.message
    assert still.position[0] < target[0] - 0.1, "the trajectory ran to its end"


@pytest.mark.realtime
def test_a_person_near_slows_the_base_and_a_person_close_pauses_it(robot_stack: Stack) -> None:
    stack = robot_stack
    beats = Watch(stack.node, keys.HEARTBEAT)
    events = Watch(stack.node, keys.SAFETY_EVENTS)
    odom = Watch(stack.node, keys.ODOM)
    # The operator steps away: full speed.
    move(stack, "operator", 2.0, 5.5)
    assert beats.wait_for(lambda b: b.speed_scale == 1.0, timeout=10.0), "never at full speed"
    statuses = Watch(stack.node, keys.CMD_NAVIGATE.status)
    handle = ActionClient(stack.node, keys.CMD_NAVIGATE).send(NavigateToPoseGoal(pose=Pose2D(x=9.5, y=1.2)))
    assert odom.wait_for(lambda o: o.linear_x > 0.5, timeout=20.0), "the base never reached full speed"

    # Beside the way ahead, within D (1.5 m) of the base: reduced to 0.4 of 0.6 m/s.
    here = odom.messages[-1].pose
    move(stack, "operator", here.x + 1.2, 2.0)
    slow = beats.wait_for(lambda b: 0.0 < b.speed_scale < 1.0, timeout=5.0, after=len(beats))
    assert slow is not None and "operator" in slow.speed_reason
    assert odom.wait_for(lambda o: o.linear_x < 0.26, timeout=3.0, after=len(odom)), "the base did not slow down"
    settled = len(odom)
    assert odom.wait_for(lambda o: True, timeout=2.0, after=settled + 20)
    assert max(o.linear_x for o in odom.messages[settled:]) <= 0.24 * 1.1 + 0.01

    # Then in its way: the base closes in slowly and pauses within d (0.3 m), the goal still running.
    here = odom.messages[-1].pose
    move(stack, "operator", here.x + 1.0, here.y)
    assert beats.wait_for(lambda b: b.speed_scale == 0.0, timeout=10.0, after=len(beats)), "never paused"
    paused = odom.wait_for(lambda o: abs(o.linear_x) < 0.005, timeout=5.0, after=len(odom))
    assert paused is not None, "the base did not pause"
    assert paused.pose.x < here.x + 1.0 - 0.3 - 0.2, "the base came closer than d to the person"
    assert not [s for s in statuses.messages if s.goal_id == handle.goal_id and s.state.terminal]

    # The person steps back: the goal finishes.
    move(stack, "operator", 2.0, 5.5)
    assert handle.result(timeout=60.0).state is GoalState.SUCCEEDED
    limited = [e for e in events.messages if e.decision is Decision.LIMITED]
    scales = [e.values["scale"] for e in limited]
    assert is_subsequence([0.4, 0.0, 1.0], scales), scales
    assert all(e.rule is Rule.HUMAN_SEPARATION and e.policy_hash == POLICY_HASH for e in limited)


def is_subsequence(wanted: list[float], seen: list[float]) -> bool:
    it = iter(seen)
    return all(any(x == w for x in it) for w in wanted)


@pytest.mark.realtime
def test_teleop_is_clamped_and_reported_while_a_program_over_the_limit_is_refused(robot_stack: Stack) -> None:
    stack = robot_stack
    events = Watch(stack.node, keys.SAFETY_EVENTS)
    sent = Watch(stack.node, keys.ROBOT_CMD_VEL)
    odom = Watch(stack.node, keys.ODOM)
    move(stack, "operator", 2.0, 5.5)
    assert Watch(stack.node, keys.HEARTBEAT).wait_for(lambda b: b.speed_scale == 1.0, timeout=10.0)

    stop = threading.Event()

    def stream(topic: keys.Topic[Twist], twist: Twist) -> None:
        while not stop.wait(0.05):
            stack.node.publish(topic, twist)

    # A person pushes the stick too far (turning in place, which is safe anywhere): clamped, reported.
    pusher = threading.Thread(target=stream, args=(keys.TELEOP_CMD_VEL, Twist(angular_z=3.0)), daemon=True)
    pusher.start()
    try:
        assert odom.wait_for(lambda o: o.angular_z > 1.0, timeout=5.0), "teleop never turned the base"
        clamped = events.wait_for(lambda e: e.decision is Decision.CLAMPED and e.values.get("turn_rps") == 1.2, 5.0)
        assert clamped is not None and clamped.rule is Rule.BASE_SPEED and "clamped" in clamped.reason
        assert all(abs(t.angular_z) <= 1.2 for t in sent.messages)
    finally:
        stop.set()
        pusher.join()
    assert odom.wait_for(lambda o: abs(o.angular_z) < 0.01, timeout=5.0, after=len(odom))

    # A program asks for the same: refused, the base stopped, nothing over the limit sent.
    n_sent, n_odom = len(sent), len(odom)
    stack.node.publish(keys.CMD_VEL, Twist(angular_z=3.0))
    vetoed = events.wait_for(lambda e: e.decision is Decision.VETOED and e.key == keys.CMD_VEL.path, timeout=5.0)
    assert vetoed is not None and vetoed.rule is Rule.BASE_SPEED and "exceeds the limit" in vetoed.reason
    assert sent.wait_for(lambda t: t == Twist(), timeout=2.0, after=n_sent)
    assert all(t.angular_z == 0.0 for t in sent.messages[n_sent:])
    assert odom.wait_for(lambda _: True, timeout=2.0, after=n_odom + 25)
    assert all(abs(o.angular_z) < 0.01 for o in odom.messages[n_odom:])
    assert all(e.policy_hash == POLICY_HASH for e in events.messages)


def publish_odom(stack: Stack, linear: float, samples: int, x: float = 6.0) -> None:
    for _ in range(samples):
        now = time.time()
        stack.node.publish(
            keys.ODOM, Odometry(stamp=now, sim_time=now, pose=Pose2D(x=x, y=1.2), linear_x=linear, angular_z=0.0)
        )
        time.sleep(0.02)  # paces the played robot's 50 Hz odometry; nothing waits on it


@pytest.mark.realtime
def test_a_runaway_robot_trips_the_monitor_and_a_silent_one_the_watchdog(safety_alone: Stack) -> None:
    stack = safety_alone
    beats = Watch(stack.node, keys.HEARTBEAT)
    events = Watch(stack.node, keys.SAFETY_EVENTS)
    assert beats.wait_for(lambda b: not b.estop.latched, timeout=10.0)

    # The robot says it drives at 1 m/s although nothing allowed more than 0.6.
    publish_odom(stack, 1.0, 10)
    tripped = beats.wait_for(lambda b: b.estop.latched, timeout=5.0)
    assert tripped is not None and tripped.estop.source == EstopSource.MONITOR
    latch = events.wait_for(lambda e: e.decision is Decision.LATCHED, timeout=5.0)
    assert latch is not None and latch.rule is Rule.MONITOR_SPEED and latch.values["speed_mps"] == 1.0

    # Stopped, so the runaway sample is not the last word when the latch is reset.
    publish_odom(stack, 0.0, 5)
    assert reset_estop(stack.node, str(stack.token_file)).ok
    assert beats.wait_for(lambda b: not b.estop.latched, timeout=5.0, after=len(beats))

    # Within the limits, then silence while moving: the watchdog latches.
    n = len(events)
    publish_odom(stack, 0.2, 10)
    silent = beats.wait_for(lambda b: b.estop.latched, timeout=5.0, after=len(beats))
    assert silent is not None and silent.estop.source == EstopSource.WATCHDOG
    assert "no odometry" in silent.estop.reason
    latch = events.wait_for(lambda e: e.decision is Decision.LATCHED, timeout=5.0, after=n)
    assert latch is not None and latch.rule is Rule.WATCHDOG and latch.values["speed_mps"] == 0.2

    # An e-stop nobody can read still stops the robot.
    assert reset_estop(stack.node, str(stack.token_file)).ok
    assert beats.wait_for(lambda b: not b.estop.latched, timeout=5.0, after=len(beats))
    stack.node.session.put(keys.ESTOP.key(stack.settings.robot), b'{"source": "big red button"')
    garbled = beats.wait_for(lambda b: b.estop.latched, timeout=5.0, after=len(beats))
    assert garbled is not None and garbled.estop.source == "unknown"
    assert "could not be read" in garbled.estop.reason

    # A stream refused over and over is one event, then one count of the rest.
    n = len(events)
    for _ in range(50):
        stack.node.publish(keys.CMD_VEL, Twist(angular_z=0.1))
    counted = events.wait_for(lambda e: e.values.get("count", 0) > 0, timeout=5.0, after=n)
    assert counted is not None and counted.rule is Rule.ESTOP and counted.values["count"] == 49
    refusals = [e for e in events.messages[n:] if e.key == keys.CMD_VEL.path]
    assert len(refusals) == 2 and "an operator must reset it" in refusals[0].reason


@pytest.mark.realtime
def test_a_policy_zone_where_the_robot_stands_trips_the_monitor_at_once(tmp_path: Path) -> None:
    policy = tmp_path / "policy.toml"
    policy.write_text(
        DEFAULT_POLICY.read_text()
        + '\n[[keep_out]]\nid = "wet_floor"\nname = "wet floor"\nreason = "just mopped"\n'
        + "polygon = [[5.5, 0.7], [6.5, 0.7], [6.5, 1.7], [5.5, 1.7]]\n"
    )
    stack = start_stack(tmp_path, realtime_factor=1.0, services=("sim", "safety"), policy=policy, strict_timing=True)
    try:
        beat = Watch(stack.node, keys.HEARTBEAT).wait_for(lambda b: b.estop.latched, timeout=10.0)
        assert beat is not None and beat.estop.source == EstopSource.MONITOR
        assert "wet floor" in beat.estop.reason
        assert beat.policy_hash == "sha256:" + hashlib.sha256(policy.read_bytes()).hexdigest() != POLICY_HASH
    finally:
        stop_stack(stack)


def test_a_policy_looser_than_the_robot_keeps_safety_from_starting(tmp_path: Path) -> None:
    policy = tmp_path / "policy.toml"
    policy.write_text(DEFAULT_POLICY.read_text().replace("max_linear_speed = 0.6", "max_linear_speed = 2.0"))
    config = tmp_path / "tether.toml"
    config.write_text(f'[safety]\npolicy = "{policy}"\noperator_token_file = "{tmp_path / "token"}"\n')
    ran = subprocess.run(
        [sys.executable, "-m", "tether", "run", "safety", "--config", str(config)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert ran.returncode == 2, ran.stderr
    assert "base.max_linear_speed" in ran.stdout + ran.stderr
    assert "above the robot's own 0.6 m/s" in ran.stdout + ran.stderr
