"""What the sim's send_goal path must still do after it was cut down for speed: the robot link's check
(services/robotlink.py), the heartbeat guard's and the arm's goal checks (services/robotrules.py), and
each goal's own handle (services/actionlib.py)."""

from __future__ import annotations

import threading
import time
import uuid
from concurrent.futures import ThreadPoolExecutor

from schemas import keys
from schemas.actions import GoalState
from schemas.common import Pose2D
from schemas.robot import (
    ARM_JOINTS,
    FollowJointTrajectoryGoal,
    NavigateToPoseFeedback,
    NavigateToPoseGoal,
    NavigateToPoseResult,
    TrajectoryPoint,
)
from schemas.safety import EstopState, SafetyStatus
from services.actionlib import ActionClient, ActionServer, GoalHandle, Outcome
from services.robotlink import ATTACHMENT_BYTES, MALFORMED, REPLAYED, Signer, Verifier
from services.robotrules import NO_HEARTBEAT_YET, HeartbeatGuard, check_trajectory
from services.runtime import Node, NodeSettings
from tests.procs import wait_until
from tests.sessions import free_port

WAIT = 5.0
KEY = bytes(range(32))
SEND_GOAL = keys.ROBOT_TRAJECTORY.send_goal.key("robot1")
# The arm's limits in ARM_JOINTS order: every joint's are different, so a joint checked against
# another's shows.
LOWER = [-1.0, -2.0, -3.0, -4.0, -5.0, -6.0, -7.0]
UPPER = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]


class Clock:
    def __init__(self, now: float = 1000.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


def trajectory(names: list[str], *points: list[float]) -> FollowJointTrajectoryGoal:
    steps = [TrajectoryPoint(positions=p, time_from_start=0.5 * (k + 1)) for k, p in enumerate(points)]
    return FollowJointTrajectoryGoal(joint_names=names, points=steps)


# The arm's goal check


def test_joints_named_in_another_order_are_each_held_to_their_own_limits() -> None:
    names = ["panda_joint7", "panda_joint1", "panda_joint4"]
    assert check_trajectory(trajectory(names, [6.5, 0.5, -3.5]), LOWER, UPPER) is None
    assert check_trajectory(trajectory(names, [6.5, 0.5, -3.5], [0.0, 1.5, 0.0]), LOWER, UPPER) == (
        "point 1: panda_joint1 = 1.500 rad is outside [-1.000, 1.000]"
    )
    assert check_trajectory(trajectory(names, [7.5, 0.0, 0.0]), LOWER, UPPER) == (
        "point 0: panda_joint7 = 7.500 rad is outside [-7.000, 7.000]"
    )


def test_the_arms_joints_in_order_are_held_to_their_limits_at_every_point() -> None:
    inside = [0.5 * hi for hi in UPPER]
    assert check_trajectory(trajectory(list(ARM_JOINTS), inside, inside), LOWER, UPPER) is None
    beyond = [*inside[:5], -6.25, inside[6]]
    assert check_trajectory(trajectory(list(ARM_JOINTS), inside, beyond), LOWER, UPPER) == (
        "point 1: panda_joint6 = -6.250 rad is outside [-6.000, 6.000]"
    )


def test_unknown_repeated_or_missing_joints_are_refused_saying_which() -> None:
    arm = list(ARM_JOINTS)
    assert check_trajectory(trajectory(["panda_joint1", "elbow", "wrist"], [0.0, 0.0, 0.0]), LOWER, UPPER) == (
        f"unknown joints ['elbow', 'wrist']; this arm has {arm}"
    )
    assert check_trajectory(trajectory(["panda_joint2", "panda_joint2"], [0.0, 0.0]), LOWER, UPPER) == (
        "joint names repeat: ['panda_joint2', 'panda_joint2']"
    )
    assert check_trajectory(trajectory(arm, [0.0] * 6), LOWER, UPPER) == "point 0 has 6 positions for 7 joints"
    back = FollowJointTrajectoryGoal(
        joint_names=arm,
        points=[TrajectoryPoint(positions=[0.0] * 7, time_from_start=t) for t in (1.0, 0.5)],
    )
    assert check_trajectory(back, LOWER, UPPER) == "point 1 goes back in time (0.5 s after 1 s)"
    # Two points at one time: taken, the sim stepped the arm from one to the other at once.
    jump = FollowJointTrajectoryGoal(
        joint_names=arm,
        points=[TrajectoryPoint(positions=[q] * 7, time_from_start=1.0) for q in (0.0, 0.5)],
    )
    assert check_trajectory(jump, LOWER, UPPER) == "point 1 comes at the same time as point 0 (1 s): the arm would jump"


# The robot link's check


def test_an_attachment_of_the_right_size_without_the_magic_is_malformed() -> None:
    clock = Clock()
    signer, verifier = Signer(KEY, clock), Verifier(KEY, clock)
    attachment = signer.sign(SEND_GOAL, b"{}")
    forged = b"X1" + attachment[2:]
    assert len(forged) == ATTACHMENT_BYTES
    refusal = verifier.check(SEND_GOAL, b"{}", forged)
    assert refusal is not None and refusal.why == MALFORMED and refusal.detail == f"{ATTACHMENT_BYTES} bytes"
    assert verifier.check(SEND_GOAL, b"{}", attachment) is None, "the malformed one took nothing"


def test_a_session_silent_past_twice_the_skew_is_forgotten_and_its_counters_with_it() -> None:
    clock = Clock()
    signer, verifier = Signer(KEY, clock), Verifier(KEY, clock)
    assert verifier.check(SEND_GOAL, b"{}", signer.sign(SEND_GOAL, b"{}")) is None
    assert verifier.check(SEND_GOAL, b"{}", signer.sign(SEND_GOAL, b"{}")) is None
    # The same session counting from 1 again: its counters are remembered while it is heard...
    again = Signer(KEY, clock, session=signer.session)
    refusal = verifier.check(SEND_GOAL, b"{}", again.sign(SEND_GOAL, b"{}"))
    assert refusal is not None and refusal.why == REPLAYED and refusal.detail.startswith("counter 1 after 2")
    # ...and forgotten once it was silent too long (anything it sent before is out of the window anyway).
    clock.now += 2 * verifier.max_skew + 1.0
    assert verifier.check(SEND_GOAL, b"{}", again.sign(SEND_GOAL, b"{}")) is None


# The heartbeat guard


def status(latched: bool = False) -> SafetyStatus:
    return SafetyStatus(seq=1, stamp=time.time(), estop=EstopState(latched=latched, source="operator", reason="t"))


def test_a_goal_before_the_first_heartbeat_waits_for_it_and_is_then_accepted() -> None:
    guard = HeartbeatGuard(1.0, WAIT)
    answer: list[str | None] = []
    asking = threading.Thread(target=lambda: answer.append(guard.accept()))
    asking.start()
    guard.heard(status())
    asking.join(WAIT)
    assert answer == [None]


def test_a_goal_with_no_heartbeat_at_all_is_refused_after_the_bounded_wait() -> None:
    assert HeartbeatGuard(1.0, 0.05).accept() == NO_HEARTBEAT_YET


def test_a_latched_heartbeat_refuses_goals_and_a_reset_one_accepts_them() -> None:
    guard = HeartbeatGuard(1.0, WAIT)
    guard.heard(status(latched=True))
    assert (guard.accept() or "").startswith("e-stop latched by operator")
    guard.heard(status())
    assert guard.accept() is None


# Each goal's own handle


def test_each_accepted_goal_has_its_own_cancel_and_done_never_a_previous_goals() -> None:
    """The handle's Events are made ahead of the goal (off the reply's path): a goal canceled and
    ended must leave nothing set in the next one's."""
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    handles: list[GoalHandle[NavigateToPoseGoal, NavigateToPoseFeedback]] = []

    def execute(
        handle: GoalHandle[NavigateToPoseGoal, NavigateToPoseFeedback],
    ) -> Outcome[NavigateToPoseResult]:
        handles.append(handle)
        handle.cancel_requested.wait(WAIT)
        return Outcome(GoalState.CANCELED, None, "stopped")

    here = Pose2D(x=1.0, y=2.0)
    with Node("sim", settings) as server_node, Node("test", settings) as client_node:
        ActionServer(server_node, keys.ROBOT_NAVIGATE, execute, preempts=lambda _goal: True)
        server_node.declare_alive()
        assert not client_node.wait_alive({"sim"}, WAIT)
        client = ActionClient(client_node, keys.ROBOT_NAVIGATE)
        first = client.send(NavigateToPoseGoal(pose=here))
        assert wait_until(lambda: len(handles) == 1, WAIT)
        assert first.cancel().accepted
        assert first.result(WAIT).state is GoalState.CANCELED
        second = client.send(NavigateToPoseGoal(pose=here))
        assert wait_until(lambda: len(handles) == 2, WAIT)
        old, new = handles
        assert old.cancel_requested.is_set() and old.done.is_set()
        assert not new.cancel_requested.is_set() and not new.done.is_set()
        assert {id(old.cancel_requested), id(old.done)}.isdisjoint({id(new.cancel_requested), id(new.done)})
        assert new.cancel_requested is not new.done
        # The third preempts the second: only the second is told to stop.
        third = client.send(NavigateToPoseGoal(pose=here))
        assert second.result(WAIT).state is GoalState.CANCELED
        assert wait_until(lambda: len(handles) == 3, WAIT)
        assert not handles[2].cancel_requested.is_set()
        third.cancel()
        assert third.result(WAIT).state is GoalState.CANCELED


def test_goals_sent_at_once_each_get_their_own_handle() -> None:
    """Several send_goals decided at once on concurrent goals (they keep nothing out) each take their
    own Events, whether a spare pair was waiting or not."""
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    handles: list[GoalHandle[NavigateToPoseGoal, NavigateToPoseFeedback]] = []
    lock = threading.Lock()
    release = threading.Event()
    goals = 8

    def execute(
        handle: GoalHandle[NavigateToPoseGoal, NavigateToPoseFeedback],
    ) -> Outcome[NavigateToPoseResult]:
        with lock:
            handles.append(handle)
        release.wait(WAIT)
        return Outcome(GoalState.SUCCEEDED, None, "done")

    with Node("sim", settings) as server_node, Node("test", settings) as client_node:
        ActionServer(server_node, keys.ROBOT_NAVIGATE, execute, concurrent=lambda _goal: True)
        server_node.declare_alive()
        assert not client_node.wait_alive({"sim"}, WAIT)
        client = ActionClient(client_node, keys.ROBOT_NAVIGATE)
        goal = NavigateToPoseGoal(pose=Pose2D(x=1.0, y=2.0))
        with ThreadPoolExecutor(goals) as senders:
            sent = list(senders.map(lambda _: client.send(goal), range(goals)))
        try:
            assert wait_until(lambda: len(handles) == goals, WAIT)
            events = [id(e) for h in handles for e in (h.cancel_requested, h.done)]
            assert len(set(events)) == 2 * goals
            assert not any(h.cancel_requested.is_set() or h.done.is_set() for h in handles)
        finally:
            release.set()
        for goal in sent:
            assert goal.result(WAIT).state is GoalState.SUCCEEDED
