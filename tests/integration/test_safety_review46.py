"""Review 46 of safety over real processes: a program's cmd_vel and an arm trajectory never move the
robot at once (rule one_motion), whichever comes first."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from schemas import keys
from schemas.actions import GoalState
from schemas.robot import ARM_JOINTS, FollowJointTrajectoryGoal, TrajectoryPoint, Twist
from schemas.safety import Decision, Rule
from services.actionlib import ActionClient
from services.errors import GoalRejected
from tests.integration.conftest import Stack, start_stack, stop_stack
from tests.watch import Watch

# A turn in place: safe anywhere, so only one_motion can refuse it.
TURN = Twist(angular_z=0.5)


@pytest.fixture
def robot_stack(tmp_path: Path) -> Iterator[Stack]:
    s = start_stack(tmp_path, realtime_factor=1.0, services=("sim", "safety"))
    try:
        yield s
    finally:
        stop_stack(s)


def swing(start: list[float], seconds: float) -> FollowJointTrajectoryGoal:
    target = [start[0] + 0.6, *start[1:]]
    return FollowJointTrajectoryGoal(
        joint_names=list(ARM_JOINTS), points=[TrajectoryPoint(positions=target, time_from_start=seconds)]
    )


def test_a_programs_cmd_vel_and_an_arm_trajectory_never_move_the_robot_at_once(robot_stack: Stack) -> None:
    stack = robot_stack
    events = Watch(stack.node, keys.SAFETY_EVENTS)
    joints = Watch(stack.node, keys.JOINT_STATES)
    odom = Watch(stack.node, keys.ODOM)
    first = joints.wait_for(lambda _: True, timeout=10.0)
    assert first is not None and odom.wait_for(lambda _: True, timeout=10.0)
    arm = ActionClient(stack.node, keys.CMD_TRAJECTORY)

    # The arm moves: a program's turn is refused, and the base stays still.
    handle = arm.send(swing(first.position[: len(ARM_JOINTS)], 3.0))
    assert joints.wait_for(lambda j: abs(j.velocity[0]) > 0.1, timeout=10.0), "the arm never started moving"
    n_odom = len(odom)
    stack.node.publish(keys.CMD_VEL, TURN)
    vetoed = events.wait_for(lambda e: e.key == keys.CMD_VEL.path and e.decision is Decision.VETOED, timeout=5.0)
    assert vetoed is not None and vetoed.rule is Rule.ONE_MOTION, vetoed
    assert f"an arm trajectory (goal {handle.goal_id}) may still be under way" in vetoed.reason
    assert odom.wait_for(lambda _: True, timeout=2.0, after=n_odom + 25)
    assert all(abs(o.angular_z) < 0.01 for o in odom.messages[n_odom:]), "the base turned while the arm moved"
    assert handle.result(timeout=10.0).state is GoalState.SUCCEEDED

    # Its result in, the turn goes; a trajectory sent while the base is told to turn is refused.
    stop = threading.Event()

    def stream() -> None:
        while not stop.wait(0.05):
            stack.node.publish(keys.CMD_VEL, TURN)

    turner = threading.Thread(target=stream, daemon=True)
    turner.start()
    try:
        assert odom.wait_for(lambda o: o.angular_z > 0.2, timeout=5.0), "the turn never went"
        now = joints.wait_for(lambda _: True, timeout=2.0, after=len(joints))
        assert now is not None
        with pytest.raises(GoalRejected) as refused:
            arm.send(swing(now.position[: len(ARM_JOINTS)], 3.0))
        assert "may still be moving (the robot holds one" in refused.value.reason, refused.value.reason
    finally:
        stop.set()
        turner.join()
