"""A hostile ROS 2 robot against the real ros2 backend: silence, another type hash, undecodable CDR,
refused and aborted goals, odometry in another frame. Each ends the goal with a clear error, shows in
the robot's diagnostics (`tether status`), and leaves the robot told to stop."""

from __future__ import annotations

import dataclasses
import itertools
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest
import zenoh

from schemas import keys
from schemas.actions import GoalState, ResultResponse
from schemas.common import Pose2D
from schemas.executor import ExecutePlanGoal, PlanStatus
from schemas.robot import ARM_JOINTS, FINGER_JOINTS, NavigateToPoseGoal, NavigateToPoseResult, Twist
from schemas.safety import EstopState, SafetyStatus
from schemas.world import Empty
from services.actionlib import ActionClient
from services.errors import CallError
from services.robotlink import NOT_SIGNED
from services.ros2.config import Ros2Config
from services.ros2.rmw import RosCallError, RosNode, RosServerGoal
from services.ros2.types import RosTypes
from services.ros2.wire import Attachment, Naming, Style
from services.runtime import Node
from services.worldmodel import load_world
from tests.integration.conftest import LOADED_MACHINE_HEARTBEAT, start_stack, stop_stack, tether_cli
from tests.robot_contract.conftest import CONTRACT_SIM, RunningBackend, ros2_backend, running
from tests.sessions import free_port
from tether.cli import status_dict
from tether.client import PlanSender

ODOMETRY = "nav_msgs/msg/Odometry"
JOINT_STATE = "sensor_msgs/msg/JointState"
DETECTIONS = "vision_msgs/msg/Detection3DArray"
TWIST = "geometry_msgs/msg/Twist"
NAVIGATE_TO_POSE = "nav2_msgs/action/NavigateToPose"
NAVIGATE_THROUGH_POSES = "nav2_msgs/action/NavigateThroughPoses"
WRONG_HASH = "RIHS01_" + "ab" * 32
UNDECODABLE = b"\x00\x01\x00\x00not an odometry"
ABORT_REASON = "controller_server: collision ahead, giving up"
# The whole stack but the sim (the hostile robot stands in for it), the recorder and the planner.
STACK = ("ros2", "safety", "parser", "resolver", "executor")

REPORT_PERIOD = 0.05  # the robot's odometry and joint states, 20 Hz
DETECTIONS_EVERY = 4  # report periods: its camera sees nothing, at 5 Hz
DEADLINE = 10.0  # every wait ends as soon as its condition holds; generous for a shared machine
# [ros2] goal_timeout: how long the backend waits for the robot to answer a goal. The robot played here
# answers from this test's process, which a loaded CI machine has kept from answering for 1.7 s.
GOAL_TIMEOUT = 3.0
# [ros2] odom_timeout: how long the backend goes without odometry before a navigation fails. The robot
# played here publishes it from this test's process too: twice the default (the tests of bad odometry
# wait it out).
ODOM_TIMEOUT = 1.0
BACKEND_TOML = f"""
[ros2]
endpoint = "{{endpoint}}"
goal_timeout = {GOAL_TIMEOUT}
cancel_timeout = 1.0
odom_timeout = {ODOM_TIMEOUT}
first_heartbeat_wait = 1.0
{LOADED_MACHINE_HEARTBEAT}"""

WORLD = load_world("household")
START = WORLD.robot.start
# Where the hostile odometry puts the base: never to be reported on tether's side.
ELSEWHERE = Pose2D(x=START.x + 2.0, y=START.y, yaw=START.yaw)


class Odom(StrEnum):
    """What the robot publishes as odometry."""

    GOOD = "good"
    WRONG_HASH = "wrong hash"  # on a key with another RIHS01
    UNDECODABLE = "undecodable"  # bytes that are no CDR Odometry, on the right key
    MAP_FRAME = "map frame"  # header.frame_id "map" where "odom" is configured


class Nav(StrEnum):
    """How the robot's navigation servers treat a goal."""

    RUN = "run"  # accept, drive until canceled
    SILENT = "silent"  # never answer send_goal
    LATE = "late"  # answer send_goal, accepted, `late_answer` seconds after it came
    REJECT = "reject"
    ABORT = "abort"  # accept, then abort with ABORT_REASON


@dataclass
class Heard:
    """What the robot was told, with the monotonic time it arrived."""

    items: list[tuple[float, Any]] = field(default_factory=list)
    changed: threading.Condition = field(default_factory=threading.Condition)

    def __call__(self, item: Any) -> None:
        with self.changed:
            self.items.append((time.monotonic(), item))
            self.changed.notify_all()

    def since(self, mark: float, predicate: Callable[[Any], bool], timeout: float = DEADLINE) -> Any | None:
        """The first item heard after `mark` that satisfies `predicate`, waiting up to `timeout`."""
        found: list[Any] = []

        def check() -> bool:
            found[:] = [item for at, item in self.items if at >= mark and predicate(item)][:1]
            return bool(found)

        with self.changed:
            self.changed.wait_for(check, timeout)
        return found[0] if found else None


def robot_session(endpoint: str, *, listen: bool = True) -> zenoh.Session:
    """The robot's network: a peer listening where the backend connects, as rmw_zenoh's router does
    (or, not `listen`ing, one more connecting there)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", msgspec.json.encode([endpoint] if listen else []).decode())
    conf.insert_json5("connect/endpoints", msgspec.json.encode([] if listen else [endpoint]).decode())
    return zenoh.open(conf)


class HostileRobot:
    """The robot's side, played by the test: one ROS 2 node publishing odometry (as `odom` says),
    joint states and empty detections, serving navigate_to_pose and navigate_through_poses (as `nav`
    says), and hearing cmd_vel. Every goal it ran is kept, and when its cancel came."""

    def __init__(self, endpoint: str) -> None:
        self.odom = Odom.GOOD
        self.nav = Nav.RUN
        self.cmd_vel = Heard()
        self.goals = Heard()  # RosServerGoal, once executing
        self.canceled = Heard()  # RosServerGoal, once its cancel came
        self.types = RosTypes()
        self.naming = Naming(Style.RMW_ZENOH, Ros2Config().ros_domain())
        self.late_answer = GOAL_TIMEOUT + 0.5  # seconds: after the backend gave up waiting
        self._answer = threading.Event()  # lets a SILENT or LATE server answer
        self._stop = threading.Event()
        self.endpoint = endpoint
        self.session = robot_session(endpoint)
        try:
            self.ros = RosNode(self.session, self.types, self.naming, "hostile_robot")
            self._odom = self.ros.publisher("odom", ODOMETRY)
            self._joints = self.ros.publisher("joint_states", JOINT_STATE)
            self._detections = self.ros.publisher("detections", DETECTIONS)
            # The same topic on a key with another type hash, as a robot built from other definitions sends it.
            self._odom_other_hash = self.session.declare_publisher(self.naming.topic("odom", ODOMETRY, WRONG_HASH))
            self.ros.subscribe("cmd_vel", TWIST, self.cmd_vel)
            for name, action in (
                ("navigate_to_pose", NAVIGATE_TO_POSE),
                ("navigate_through_poses", NAVIGATE_THROUGH_POSES),
            ):
                self.ros.action_server(name, action, accept=self._accept, execute=self._executor(action))
            self._reports = threading.Thread(target=self._report, name="hostile-reports", daemon=True)
            self._reports.start()
        except BaseException:
            self.session.close()
            raise

    # Reports

    def odometry(self, frame: str, pose: Pose2D) -> Any:
        new = self.types.new
        return new(
            ODOMETRY,
            header=new("std_msgs/msg/Header", stamp=self.stamp(), frame_id=frame),
            child_frame_id="base_link",
            pose=new(
                "geometry_msgs/msg/PoseWithCovariance",
                pose=new(
                    "geometry_msgs/msg/Pose",
                    position=new("geometry_msgs/msg/Point", x=pose.x, y=pose.y),
                    orientation=new("geometry_msgs/msg/Quaternion", z=math.sin(pose.yaw / 2), w=math.cos(pose.yaw / 2)),
                ),
            ),
        )

    def stamp(self) -> Any:
        now = time.time_ns()
        return self.types.new("builtin_interfaces/msg/Time", sec=now // 10**9, nanosec=now % 10**9)

    def _report(self) -> None:
        names = [*ARM_JOINTS, *FINGER_JOINTS]
        positions = np.array([*WORLD.robot.home_joints, 0.04, 0.04])
        sequence = 0
        for tick in itertools.count():
            if self._stop.wait(REPORT_PERIOD):
                return
            if tick % DETECTIONS_EVERY == 0:
                header = self.types.new("std_msgs/msg/Header", stamp=self.stamp(), frame_id="odom")
                self._detections.put(self.types.new(DETECTIONS, header=header))
            self._joints.put(
                self.types.new(
                    JOINT_STATE,
                    header=self.types.new("std_msgs/msg/Header", stamp=self.stamp()),
                    name=names,
                    position=positions,
                    velocity=np.zeros(len(names)),
                )
            )
            match self.odom:
                case Odom.GOOD:
                    self._odom.put(self.odometry("odom", START))
                case Odom.WRONG_HASH:
                    sequence += 1
                    attachment = Attachment(sequence, time.time_ns(), bytes(16)).encode()
                    data = self.types.encode(ODOMETRY, self.odometry("odom", ELSEWHERE))
                    self._odom_other_hash.put(data, attachment=attachment)
                case Odom.UNDECODABLE:
                    self._odom.put_raw(UNDECODABLE)
                case Odom.MAP_FRAME:
                    self._odom.put(self.odometry("map", ELSEWHERE))

    # Navigation

    def _accept(self, _goal: Any) -> bool:
        match self.nav:
            case Nav.SILENT:
                self._answer.wait(60.0)
                return False
            case Nav.LATE:
                self._answer.wait(self.late_answer)
                return True
            case Nav.REJECT:
                return False
        return True

    def _executor(self, action: str) -> Callable[[RosServerGoal], None]:
        def execute(goal: RosServerGoal) -> None:
            self.goals(goal)
            result = self.types.new(f"{action}_Result")
            if self.nav is Nav.ABORT:
                goal.abort(dataclasses.replace(result, error_code=9000, error_msg=ABORT_REASON))
                return
            if goal.cancel_requested.wait(60.0):
                self.canceled(goal)
                goal.canceled(result)

        return execute

    def close(self) -> None:
        self._stop.set()
        self._answer.set()
        self._reports.join(5.0)
        self.ros.close()
        self.session.close()


@dataclass
class Rig:
    robot: HostileRobot
    backend: RunningBackend
    navigate: ActionClient[NavigateToPoseGoal, Any, NavigateToPoseResult]


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    """The ros2 backend as a real process, once for the module, driving the hostile robot; the test
    in safety's place, its heartbeat clear (as tests/robot_contract does)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    robot = HostileRobot(endpoint)
    try:
        backend = dataclasses.replace(ros2_backend(CONTRACT_SIM), config=backend_toml(endpoint), robot_service=None)
        with running(backend, tmp_path_factory.mktemp("hostile"), beating=True) as started:
            yield Rig(robot, started, ActionClient(started.node, keys.ROBOT_NAVIGATE))
    finally:
        robot.close()


@pytest.fixture
def hostile(rig: Rig) -> Iterator[Rig]:
    """The robot behaving until the test says otherwise, and the backend hearing its odometry."""
    rig.robot.odom, rig.robot.nav, rig.robot.late_answer = Odom.GOOD, Nav.RUN, GOAL_TIMEOUT + 0.5
    assert rig.backend.odom.wait_for(lambda _: True, DEADLINE, after=len(rig.backend.odom)), "no odometry"
    yield rig
    rig.robot.odom, rig.robot.nav = Odom.GOOD, Nav.RUN
    rig.backend.cancel_everything()


def backend_toml(endpoint: str) -> str:
    return BACKEND_TOML.replace("{endpoint}", endpoint)


def ahead() -> NavigateToPoseGoal:
    return NavigateToPoseGoal(pose=Pose2D(x=START.x + 1.0, y=START.y, yaw=START.yaw))


def navigate(rig: Rig) -> ResultResponse[NavigateToPoseResult]:
    return rig.navigate.send(ahead(), timeout=DEADLINE).result(DEADLINE)


def aborted_saying(result: ResultResponse[NavigateToPoseResult], *words: str) -> str:
    """The goal ended aborted, its message (also the result's) naming every one of `words`."""
    assert result.state is GoalState.ABORTED, result
    assert result.result is not None and result.result.message == result.message, result
    assert all(word in result.message for word in words), result.message
    return result.message


def halted_since(robot: HostileRobot, mark: float) -> None:
    """The backend told the robot to stop after `mark`: a zero Twist on cmd_vel."""
    zero = robot.cmd_vel.since(mark, lambda t: t.linear.x == 0.0 and t.angular.z == 0.0)
    assert zero is not None, "no zero Twist on cmd_vel"


def diagnosed(rig: Rig, since: float, *words: str) -> str:
    """The problem the robot's diagnostics (robot/diagnostics, as `tether status` shows them) saw
    after `since` (wall time) that names every one of `words`; asked again at each heartbeat until
    it shows, as some come from the robot's side after the goal ended."""
    deadline = time.monotonic() + DEADLINE
    while True:
        diagnostics = rig.backend.node.call(keys.ROBOT_DIAGNOSTICS, Empty(), timeout=5.0)
        assert diagnostics.backend == "ros2"
        for problem in diagnostics.problems:
            if problem.last_seen >= since and all(word in problem.text for word in words):
                return problem.text
        assert time.monotonic() < deadline, f"no problem naming {words}: {diagnostics.problems}"
        assert rig.backend.safety.beats(1), "the played safety's heartbeat stopped"


def test_a_goal_the_robot_never_answers_ends_aborted_and_the_base_halted(hostile: Rig) -> None:
    hostile.robot.nav = Nav.SILENT
    since, mark = time.time(), time.monotonic()
    message = aborted_saying(
        navigate(hostile), "the robot did not take the navigate_to_pose goal", f"no answer within {GOAL_TIMEOUT:g} s"
    )
    halted_since(hostile.robot, mark)
    assert diagnosed(hostile, since, "did not take the navigate_to_pose goal") == message


def test_a_goal_the_robot_takes_only_after_the_backend_gave_up_is_canceled(hostile: Rig) -> None:
    hostile.robot.nav = Nav.LATE
    since, mark = time.time(), time.monotonic()
    message = aborted_saying(navigate(hostile), "the robot did not take the navigate_to_pose goal", "no answer within")
    halted_since(hostile.robot, mark)
    # The robot took the goal after all: it is canceled, not left to drive.
    late = hostile.robot.goals.since(mark, lambda _: True)
    assert late is not None, "the robot never ran the goal it took late"
    assert hostile.robot.canceled.since(mark, lambda goal: goal is late) is not None, "the late goal was not canceled"
    assert diagnosed(hostile, since, "did not take the navigate_to_pose goal") == message


def test_a_goal_taken_long_after_its_send_goal_went_unanswered_is_canceled_once_its_status_shows(
    hostile: Rig,
) -> None:
    """However late the robot takes it, past any retried cancel: the wire layer's action client
    cancels a goal it gave up on as soon as the action's status lists it, and says so."""
    robot = hostile.robot
    robot.nav, robot.late_answer = Nav.LATE, 0.6
    errors = Heard()
    with (
        robot_session(robot.endpoint, listen=False) as session,
        RosNode(session, robot.types, robot.naming, "impatient", on_error=errors) as node,
    ):
        client = node.action_client("navigate_to_pose", NAVIGATE_TO_POSE)
        assert client.wait_for_server(DEADLINE)
        mark = time.monotonic()
        with pytest.raises(RosCallError, match="no answer within"):
            client.send_goal(node.types.new(f"{NAVIGATE_TO_POSE}_Goal"), timeout=0.2)
        late = robot.goals.since(mark, lambda _: True)
        assert late is not None, "the robot never ran the goal it took late"
        assert robot.canceled.since(mark, lambda goal: goal is late) is not None, "the late goal was not canceled"
        said = errors.since(mark, lambda text: late.goal_id.hex() in text)
        assert said is not None and "after its send_goal went unanswered; canceled it" in said, errors.items


def test_a_goal_the_robot_rejects_ends_aborted_with_its_refusal(hostile: Rig) -> None:
    hostile.robot.nav = Nav.REJECT
    since, mark = time.time(), time.monotonic()
    message = aborted_saying(
        navigate(hostile), "the robot refused the navigate_to_pose goal", "goal rejected by the server"
    )
    assert hostile.robot.goals.since(mark, lambda _: True, timeout=0.0) is None, "a rejected goal ran"
    assert diagnosed(hostile, since, "refused") == message


def test_a_goal_the_robot_aborts_ends_aborted_with_its_reason_and_the_base_halted(hostile: Rig) -> None:
    hostile.robot.nav = Nav.ABORT
    since, mark = time.time(), time.monotonic()
    message = aborted_saying(navigate(hostile), "the robot aborted the navigate_to_pose goal", ABORT_REASON)
    halted_since(hostile.robot, mark)
    assert diagnosed(hostile, since, ABORT_REASON) == message


# What each kind of bad odometry is called: in the goal's message and in the diagnostics.
BAD_ODOMETRY = {
    Odom.WRONG_HASH: ("sample on /odom has type hash", WRONG_HASH, "expected RIHS01_"),
    Odom.UNDECODABLE: ("undecodable sample on /odom", "nav_msgs/msg/Odometry"),
    Odom.MAP_FRAME: ("odometry in frame 'map', expected 'odom'",),
}


@pytest.mark.parametrize("odom", list(BAD_ODOMETRY), ids=lambda odom: str(odom).replace(" ", "_"))
def test_odometry_going_bad_under_a_navigation_aborts_it_stops_the_robot_and_is_never_reported(
    hostile: Rig, odom: Odom
) -> None:
    sent = time.monotonic()
    handle = hostile.navigate.send(ahead(), timeout=DEADLINE)
    driving = hostile.robot.goals.since(sent, lambda goal: goal.active)
    assert driving is not None, "the robot never got the goal"
    since, mark = time.time(), time.monotonic()
    hostile.robot.odom = odom
    words = BAD_ODOMETRY[odom]
    aborted_saying(handle.result(DEADLINE), "no odometry from the robot for", *words)
    assert hostile.robot.canceled.since(mark, lambda goal: goal is driving) is not None, "the goal was not canceled"
    halted_since(hostile.robot, mark)
    diagnosed(hostile, since, *words)
    reported = [o for o in hostile.backend.odom.messages if math.isclose(o.pose.x, ELSEWHERE.x, abs_tol=0.01)]
    assert not reported, f"the bad odometry reached tether: {reported[0]}"


# The whole stack: the robot's error in the plan's result and in `tether status`.

NAVIGATE_PLAN = '{"plan": [{"action": "navigate_to", "target": "kitchen"}]}'


def test_a_plan_whose_goal_the_robot_aborts_fails_naming_the_robots_reason_also_in_status(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    robot = HostileRobot(endpoint)
    robot.nav = Nav.ABORT
    try:
        # One attempt: the robot's reason, not the executor's retries, is what is checked here.
        extra = f"{backend_toml(endpoint)}\n[executor.retries]\nnavigate_to = 0\n"
        stack = start_stack(tmp_path, realtime_factor=1.0, services=STACK, extra_config=extra)
        try:
            mark = time.monotonic()
            run = PlanSender(stack.node).run(ExecutePlanGoal(text=NAVIGATE_PLAN), 60.0)
            assert run.result is not None
            assert run.result.status is PlanStatus.FAILED, run.result
            assert "the robot aborted the navigate_to_pose goal" in run.result.reason, run.result.reason
            assert ABORT_REASON in run.result.reason, run.result.reason
            assert robot.goals.since(mark, lambda _: True) is not None, "the robot never got a goal"
            halted_since(robot, mark)

            state = status_dict(stack.node)  # what `tether status --json` prints
            assert state["robot"]["pose"]["x"] == pytest.approx(START.x)
            assert any(ABORT_REASON in p["text"] for p in state["robot"]["problems"]), state["robot"]
            shown = tether_cli(stack, "status")
            assert shown.returncode == 0, shown.stderr
            printed = " ".join((shown.stdout + shown.stderr).split())
            assert "robot problems" in printed and ABORT_REASON in printed, printed
        finally:
            stop_stack(stack)
    finally:
        robot.close()


def test_commands_and_heartbeats_safety_did_not_sign_never_reach_the_robot(hostile: Rig) -> None:
    """An attacker's session (no robot key) puts cmd_vel, sends a goal, and forges an unlatched
    heartbeat while safety's (here the test's, signed) says latched: the ROS 2 robot hears none of it."""
    robot, backend = hostile.robot, hostile.backend
    since, mark = time.time(), time.monotonic()
    goals_before = len(robot.goals.items)
    unlatched = SafetyStatus(seq=1, stamp=time.time(), estop=EstopState(latched=False), speed_scale=1.0)
    backend.safety.set(latched=True)
    assert backend.safety.beats(3)
    try:
        with Node("attacker", backend.settings) as attacker:
            with pytest.raises(CallError, match="not signed by safety"):
                ActionClient(attacker, keys.ROBOT_NAVIGATE).send(ahead(), timeout=DEADLINE)
            for _ in range(20):
                attacker.publish(keys.HEARTBEAT, unlatched)
                attacker.publish(keys.ROBOT_CMD_VEL, Twist(linear_x=0.4))
                # Signed (the test holds the key, as safety): it would drive, were the forged beat believed.
                backend.node.publish(keys.ROBOT_CMD_VEL, Twist(linear_x=0.3))
                assert backend.safety.beats(1), "the played safety's heartbeat stopped"
        diagnosed(hostile, since, "refused safety/heartbeat", NOT_SIGNED)
        diagnosed(hostile, since, "refused robot/cmd_vel", NOT_SIGNED)
        diagnosed(hostile, since, "refused robot/navigate_to_pose/_action/send_goal", NOT_SIGNED)
        assert robot.cmd_vel.since(mark, lambda t: t.linear.x != 0.0, timeout=0.0) is None, "the robot was driven"
        assert len(robot.goals.items) == goals_before, "a goal reached the robot"
    finally:
        backend.safety.set(latched=False)
        assert backend.safety.beats(2)
