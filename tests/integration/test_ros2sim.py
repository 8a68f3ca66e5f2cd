"""The stand-in robot as a real process, driven as a ROS 2 robot over rmw_zenoh keys on its own Zenoh.

A check of the stand-in itself (tests/robot_contract checks the ros2 backend driving it), and of the
robot's half of "safety down = robot still": it stops on its own when the backend dies.
"""

from __future__ import annotations

import dataclasses
import math
import os
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Generic, TypeVar

import msgspec
import numpy as np
import pytest
import zenoh

from schemas import keys
from schemas.common import Pose2D
from schemas.robot import ARM_JOINTS, FINGER_JOINTS, NavigateToPoseGoal
from schemas.world import Empty
from services.actionlib import ActionClient
from services.errors import GoalRejected
from services.ros2.rmw import GoalStatus, RosGoalRejected, RosNode
from services.ros2.types import RosTypes
from services.ros2.wire import Naming, Style
from services.ros2sim import messages
from services.ros2sim import node as standin
from services.ros2sim.config import Ros2SimConfig, domain_id
from services.runtime import ALL_SERVICES, Node, NodeSettings
from tests.robot_contract.conftest import CONTRACT_SIM, ros2_backend, running
from tests.sessions import free_port, free_ports
from tether.supervisor import Supervisor

# Bounds in wall-clock time, and a dead-man signal sent from this process at 20 Hz: `make test`
# runs these alone on the machine (tests/suite.py).
pytestmark = [pytest.mark.realtime, pytest.mark.alone]

T = TypeVar("T")

DOMAIN = 7  # not the default, so a side that ignored ROS_DOMAIN_ID would hear nothing
CMD_VEL_TIMEOUT = 0.5
STOP_TIMEOUT = 0.5  # the stand-in's default dead-man on emergency_stop
ESTOP_PERIOD = 0.05  # as the backend sends it: 20 Hz, true or false
STARTUP_TIMEOUT = 90.0
GOAL_TIMEOUT = 5.0  # for send_goal, cancel and results that are due at once
LANE_END = 9.5  # the household corridor from the start pose (6.0, 1.2) east, clear to x = 10


class RosWatch(Generic[T]):
    """Collects one ROS topic's messages and waits on conditions over them, with deadlines."""

    def __init__(self, ros: RosNode, topic: str, ros_type: str) -> None:
        self.messages: list[T] = []
        self._changed = threading.Condition()
        ros.subscribe(topic, ros_type, self._on_message)

    def _on_message(self, message: T) -> None:
        with self._changed:
            self.messages.append(message)
            self._changed.notify_all()

    def wait_for(self, predicate: Callable[[T], bool], timeout: float, after: int = 0) -> T | None:
        found: list[T] = []

        def check() -> bool:
            found.extend(m for m in self.messages[after:] if predicate(m))
            return bool(found)

        with self._changed:
            self._changed.wait_for(check, timeout)
        return found[0] if found else None

    def __len__(self) -> int:
        return len(self.messages)


class Robot:
    """The test in the ros2 backend's place: the stand-in's ROS face, and tether's sim keys."""

    def __init__(self, tether: Node, ros: RosNode) -> None:
        self.tether = tether
        self.ros = ros
        self.types = ros.types
        self.odom: RosWatch[Any] = RosWatch(ros, standin.NAMES.odom, "nav_msgs/msg/Odometry")
        self.joint_states: RosWatch[Any] = RosWatch(ros, standin.NAMES.joint_states, "sensor_msgs/msg/JointState")
        self.detections: RosWatch[Any] = RosWatch(ros, standin.NAMES.detections, "vision_msgs/msg/Detection3DArray")
        self.camera: RosWatch[Any] = RosWatch(ros, standin.NAMES.camera, "sensor_msgs/msg/CompressedImage")
        self.cmd_vel = ros.publisher(standin.NAMES.cmd_vel, "geometry_msgs/msg/Twist")
        self._estop = ros.publisher(standin.NAMES.emergency_stop, "std_msgs/msg/Bool")
        # The backend's dead-man signal: emergency_stop at 20 Hz while `_sending`, the latest value.
        self._estop_value = False
        self._estop_lock = threading.Lock()  # one value at a time: a stale repeat never follows a new one
        self._sending = threading.Event()
        self._sending.set()
        self._closed = threading.Event()
        self._signal = threading.Thread(target=self._send_estop, name="estop-signal", daemon=True)
        self._signal.start()
        self._navigate = ros.action_client(standin.NAMES.navigate_to_pose, messages.NAVIGATE_TO_POSE)
        self._trajectory = ros.action_client(standin.NAMES.follow_joint_trajectory, messages.FOLLOW_JOINT_TRAJECTORY)
        self.gripper = ros.action_client(standin.NAMES.gripper, messages.GRIPPER_COMMAND)

    def pose(self) -> tuple[float, float]:
        x, y, _ = self.odom_pose()
        return x, y

    def odom_pose(self) -> tuple[float, float, float]:
        """Where the base stands and which way it faces (x, y, yaw), from the latest odometry."""
        latest = self.odom.wait_for(lambda _m: True, 5.0, after=max(0, len(self.odom) - 1))
        assert latest is not None, "no odometry"
        p = latest.pose.pose.position
        return float(p.x), float(p.y), messages.yaw_of(latest.pose.pose.orientation)

    def _send_estop(self) -> None:
        while not self._closed.wait(ESTOP_PERIOD):
            with self._estop_lock:
                if self._sending.is_set():
                    self._estop.put(self.types.new("std_msgs/msg/Bool", data=self._estop_value))

    def estop(self, on: bool) -> None:
        """emergency_stop `on` at once and from then on at 20 Hz."""
        with self._estop_lock:
            self._estop_value = on
            self._estop.put(self.types.new("std_msgs/msg/Bool", data=on))
            self._sending.set()

    def silence(self) -> None:
        """No more emergency_stop, as from a backend that died."""
        with self._estop_lock:
            self._sending.clear()

    def wait_free(self, timeout: float = 10.0) -> None:
        """Until the stand-in takes goals: a navigation to where the base stands, facing the way it
        faces (a turn back to yaw 0 took some 3 s), is accepted and succeeds."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                goal = self.navigate(*self.odom_pose())
            except RosGoalRejected:
                assert time.monotonic() < deadline, "the stand-in still rejects goals"
                self._closed.wait(ESTOP_PERIOD)  # a poll between two replies, bounded by the deadline
                continue
            status, result = goal.result(timeout=GOAL_TIMEOUT)
            # Nav2 takes every goal: one the stand-in's stop holds ends aborted saying so. Taken on
            # the first signal after a silence, a goal may also still end on the dead-man if the
            # signal (from this loaded test process) stalls again: free means a goal that succeeds.
            if status != GoalStatus.SUCCEEDED and "emergency_stop" in result.error_msg:
                assert time.monotonic() < deadline, f"the stand-in still stops goals: {result.error_msg}"
                self._closed.wait(ESTOP_PERIOD)  # a poll between two goals, bounded by the deadline
                continue
            assert status == GoalStatus.SUCCEEDED, result.error_msg
            return

    def close(self) -> None:
        self._closed.set()
        self._signal.join(5.0)

    def navigate(self, x: float, y: float, yaw: float = 0.0, frame: str = "odom") -> Any:
        types = self.types
        stamped = types.new(
            "geometry_msgs/msg/PoseStamped",
            header=messages.header(types, 0.0, frame),
            pose=messages.pose(types, x, y, yaw=yaw),
        )
        goal = types.new(f"{messages.NAVIGATE_TO_POSE}_Goal", pose=stamped)
        return self._navigate.send_goal(goal, timeout=GOAL_TIMEOUT)

    def trajectory(self, names: list[str], positions: list[float], at: float = 1.0) -> Any:
        types = self.types
        point = types.new(
            "trajectory_msgs/msg/JointTrajectoryPoint",
            positions=np.array(positions, dtype=np.float64),
            time_from_start=messages.duration(types, at),
        )
        trajectory = types.new("trajectory_msgs/msg/JointTrajectory", joint_names=names, points=[point])
        goal = types.new(f"{messages.FOLLOW_JOINT_TRAJECTORY}_Goal", trajectory=trajectory)
        return self._trajectory.send_goal(goal, timeout=GOAL_TIMEOUT)


def ros_client_session(endpoint: str) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", msgspec.json.encode([endpoint]).decode())
    return zenoh.open(conf)


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Robot]:
    with running_standin(tmp_path_factory.mktemp("ros2sim")) as robot:
        yield robot


@contextmanager
def running_standin(tmp: Path, ros2sim: str = "") -> Iterator[Robot]:
    """The stand-in as a process, free to move; `ros2sim`: more lines of its [ros2sim] table."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = tmp / "tether.toml"
    # At real time: on two loaded cores a faster sim falls behind the wall clock.
    config.write_text(
        f'[sim]\nrealtime_factor = 1.0\n\n[ros2sim]\nlisten = "{endpoint}"\ncmd_vel_timeout = {CMD_VEL_TIMEOUT}\n'
        + ros2sim
    )
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_ports(len(ALL_SERVICES)))
    supervisor = Supervisor(settings, tmp / "logs", config, extra_env={"ROS_DOMAIN_ID": str(DOMAIN)})
    tether: Node | None = None
    session: zenoh.Session | None = None
    ros: RosNode | None = None
    robot: Robot | None = None
    try:
        supervisor.start("ros2sim")
        tether = Node("cli", settings)
        assert not tether.wait_alive(["ros2sim"], STARTUP_TIMEOUT), "ros2sim not up"
        session = ros_client_session(endpoint)
        ros = RosNode(session, RosTypes(), Naming(Style.RMW_ZENOH, DOMAIN), "test_backend")
        robot = Robot(tether, ros)
        # Reports flowing means this session reaches the robot's: goals and publications will too.
        assert robot.odom.wait_for(lambda _m: True, 10.0), "no odometry from the stand-in"
        robot.wait_free()  # held until it hears emergency_stop: the dead-man signal has reached it
        yield robot
    finally:
        if robot is not None:
            robot.close()
        if ros is not None:
            ros.close()
        if session is not None:
            session.close()
        if tether is not None:
            tether.close()
        supervisor.stop_all()
        print(f"----- ros2sim log -----\n{supervisor.log_tail('ros2sim', 80)}")  # shown when a test failed


def ahead(robot: Robot, distance: float) -> tuple[float, float]:
    """A point `distance` along the corridor from where the base stands, back west near its end."""
    x, y = robot.pose()
    return (x + distance if x + distance <= LANE_END else x - distance), y


def speed(odom: Any) -> float:
    return abs(float(odom.twist.twist.linear.x))


def stamp(message: Any) -> float:
    return float(message.header.stamp.sec) + float(message.header.stamp.nanosec) * 1e-9


def position(odom: Any) -> tuple[float, float]:
    p = odom.pose.pose.position
    return float(p.x), float(p.y)


def test_reports_arrive_in_the_robot_frames(robot: Robot) -> None:
    odom = robot.odom.wait_for(lambda _m: True, 5.0)
    assert odom is not None and (odom.header.frame_id, odom.child_frame_id) == ("odom", "base_link")
    assert robot.pose() == pytest.approx((6.0, 1.2), abs=0.05)
    joints = robot.joint_states.wait_for(lambda _m: True, 5.0)
    assert joints is not None and joints.name == [*ARM_JOINTS, *FINGER_JOINTS] and len(joints.position) == 9
    people = robot.detections.wait_for(lambda m: any(d.id == "operator" for d in m.detections), 5.0)
    assert people is not None, "no detection of the operator"
    person = next(d for d in people.detections if d.id == "operator")
    assert person.results[0].hypothesis.class_id == "person"
    # From the start pose the camera sees the coffee table and the book on it.
    objects = robot.detections.wait_for(lambda m: any(d.id == "blue_book" for d in m.detections), 5.0)
    assert objects is not None, "no detection of the blue book"
    book = next(d for d in objects.detections if d.id == "blue_book")
    assert (book.header.frame_id, book.results[0].hypothesis.class_id) == ("odom", "book")
    assert float(book.bbox.size.x) > 0.0
    picture = robot.camera.wait_for(lambda _m: True, 5.0)
    assert picture is not None and picture.format == "png" and bytes(picture.data[:4]) == b"\x89PNG"
    truth = robot.tether.call(keys.GROUND_TRUTH, Empty(), timeout=5.0)
    assert (truth.robot.x, truth.robot.y) == pytest.approx(robot.pose(), abs=0.05)


def test_navigate_to_pose_drives_the_base_there(robot: Robot) -> None:
    x, y = ahead(robot, 0.8)
    goal = robot.navigate(x, y)
    status, result = goal.result(timeout=30.0)
    assert status == GoalStatus.SUCCEEDED, result.error_msg
    assert result.error_code == messages.NAV_NONE
    assert robot.pose() == pytest.approx((x, y), abs=0.05)


def test_a_goal_it_cannot_carry_out_is_rejected_or_as_nav2_aborted(robot: Robot) -> None:
    here = robot.pose()
    for x, frame, reason in ((math.nan, "odom", "not finite"), (7.0, "base_link", "frame 'base_link'")):
        status, result = robot.navigate(x, 1.2, frame=frame).result(timeout=GOAL_TIMEOUT)
        assert (status, result.error_code) == (GoalStatus.ABORTED, messages.NAV_UNKNOWN)
        assert reason in result.error_msg
    assert robot.pose() == pytest.approx(here, abs=0.01)
    with pytest.raises(RosGoalRejected):
        robot.trajectory(["panda_joint1", "elbow"], [0.0, 0.0])
    with pytest.raises(RosGoalRejected):
        robot.trajectory(["panda_joint4"], [1.0])  # outside the joint's limits [-3.07, -0.07]


def test_trajectory_and_gripper_goals_succeed(robot: Robot) -> None:
    joints = robot.joint_states.wait_for(lambda _m: True, 5.0)
    assert joints is not None
    home = float(joints.position[0])
    goal = robot.trajectory(["panda_joint1"], [home + 0.2])
    status, result = goal.result(timeout=20.0)
    assert (status, result.error_code) == (GoalStatus.SUCCEEDED, messages.TRAJECTORY_SUCCESSFUL), result.error_string
    command = robot.types.new("control_msgs/msg/GripperCommand", position=0.04, max_effort=20.0)
    goal = robot.types.new(f"{messages.GRIPPER_COMMAND}_Goal", command=command)
    gripper = robot.gripper.send_goal(goal, timeout=GOAL_TIMEOUT)
    status, result = gripper.result(timeout=20.0)
    assert status == GoalStatus.SUCCEEDED and result.reached_goal and not result.stalled
    assert float(result.position) == pytest.approx(0.04, abs=0.003)


def test_emergency_stop_halts_aborts_and_refuses_until_released(robot: Robot) -> None:
    x, y = ahead(robot, 1.5)
    goal = robot.navigate(x, y)
    assert robot.odom.wait_for(lambda m: speed(m) > 0.2, 10.0, after=len(robot.odom)), "the base never got going"
    robot.estop(True)
    status, result = goal.result(timeout=GOAL_TIMEOUT)
    assert status == GoalStatus.ABORTED and "emergency stop" in result.error_msg
    assert robot.odom.wait_for(lambda m: speed(m) < 0.01, 2.0, after=len(robot.odom)), "the base did not stop"
    status, result = robot.navigate(x, y).result(timeout=GOAL_TIMEOUT)
    assert status == GoalStatus.ABORTED and "emergency stop" in result.error_msg
    with pytest.raises(RosGoalRejected):
        robot.trajectory(["panda_joint1"], [0.0])
    robot.estop(False)
    goal = robot.navigate(x, y)
    status, result = goal.result(timeout=30.0)
    assert status == GoalStatus.SUCCEEDED, result.error_msg


def test_cmd_vel_drives_then_holds_only_its_timeout(robot: Robot) -> None:
    twist = robot.types.new("geometry_msgs/msg/Twist", linear=robot.types.new("geometry_msgs/msg/Vector3", x=0.3))
    start = len(robot.odom)
    robot.cmd_vel.put(twist)
    moving = robot.odom.wait_for(lambda m: speed(m) > 0.25, 5.0, after=start)
    assert moving is not None, "cmd_vel did not move the base"
    rest = robot.odom.wait_for(lambda m: speed(m) < 0.01, 5.0, after=robot.odom.messages.index(moving))
    assert rest is not None, "the base did not stop after cmd_vel's timeout"
    stamps = [
        m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in robot.odom.messages[start:] if speed(m) > 0.05
    ]
    # Held its timeout from the command, plus the ramps up and down at the robot's accelerations.
    assert CMD_VEL_TIMEOUT - 0.1 < stamps[-1] - stamps[0] < CMD_VEL_TIMEOUT + 0.5


def test_the_stop_service_halts_once_without_latching(robot: Robot) -> None:
    start = len(robot.odom)
    forward = robot.types.new("geometry_msgs/msg/Vector3", x=0.3)
    robot.cmd_vel.put(robot.types.new("geometry_msgs/msg/Twist", linear=forward))
    assert robot.odom.wait_for(lambda m: speed(m) > 0.2, 5.0, after=start), "cmd_vel did not move the base"
    stop = robot.ros.client(standin.NAMES.stop, "std_srvs/srv/Trigger")
    assert stop.call(robot.types.new("std_srvs/srv/Trigger_Request"), timeout=GOAL_TIMEOUT).success
    stopped = robot.odom.wait_for(lambda m: speed(m) < 0.01, 2.0, after=len(robot.odom))
    assert stopped is not None, "the base did not stop"
    again = len(robot.odom)
    robot.cmd_vel.put(robot.types.new("geometry_msgs/msg/Twist", linear=forward))
    assert robot.odom.wait_for(lambda m: speed(m) > 0.2, 5.0, after=again), "the stop latched"


def test_silence_on_emergency_stop_halts_aborts_and_refuses_until_it_resumes(robot: Robot) -> None:
    x, y = ahead(robot, 1.5)
    goal = robot.navigate(x, y)
    assert robot.odom.wait_for(lambda m: speed(m) > 0.2, 10.0, after=len(robot.odom)), "the base never got going"
    try:
        robot.silence()
        status, result = goal.result(timeout=STOP_TIMEOUT + GOAL_TIMEOUT)
        assert status == GoalStatus.ABORTED, result.error_msg
        assert "no emergency_stop signal for" in result.error_msg
        assert robot.odom.wait_for(lambda m: speed(m) < 0.01, 2.0, after=len(robot.odom)), "the base did not stop"
        status, result = robot.navigate(x, y).result(timeout=GOAL_TIMEOUT)
        assert status == GoalStatus.ABORTED and "no emergency_stop signal for" in result.error_msg
    finally:
        robot.estop(False)  # the signal back, so the module's other tests find the robot free
    robot.wait_free()


# The stand-in stops within its stop_timeout of the backend's last emergency_stop, plus a sim step,
# the next odometry report (50 Hz) and the report crossing Zenoh: generous for two shared cores.
STOP_SLACK = 0.5
STILL = 0.01  # m/s: at rest
HELD = 1.0  # seconds the base must then stay where it stopped
HELD_TOLERANCE = 0.005  # metres


def test_the_robot_stops_on_its_own_when_the_backend_dies_mid_motion(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    contract = ros2_backend(CONTRACT_SIM)
    toml = contract.config.replace("{endpoint}", endpoint)
    backend = dataclasses.replace(
        contract, config=toml.replace("[ros2sim]\n", f"[ros2sim]\nstop_timeout = {STOP_TIMEOUT}\n")
    )
    naming = Naming(Style.RMW_ZENOH, domain_id(Ros2SimConfig(), os.environ))
    with (
        running(backend, tmp_path, beating=True) as tether,
        ros_client_session(endpoint) as session,
        RosNode(session, RosTypes(), naming, "test_watcher") as ros,
    ):
        # The robot's own odometry: tether's comes through the backend, which is about to die.
        odom: RosWatch[Any] = RosWatch(ros, standin.NAMES.odom, "nav_msgs/msg/Odometry")
        assert odom.wait_for(lambda _m: True, 10.0), "no odometry on the robot's network"
        assert tether.safety.beats(3), "the played safety's heartbeat thread stopped"
        lane = backend.lane
        x, y = lane.point(lane.length - 0.3)
        navigate = ActionClient(tether.node, keys.ROBOT_NAVIGATE)
        goal = NavigateToPoseGoal(pose=Pose2D(x=x, y=y, yaw=lane.heading))
        # The played safety's heartbeat comes from this test process: a beat held up here makes the
        # backend (rightly) stop the robot before the kill, which is not what is tested. Then the
        # goal is sent again, at most twice more, and the kill waits for the base moving right then.
        for _ in range(3):
            deadline = time.monotonic() + 10.0
            while True:  # sent again after each heartbeat while the backend has yet to release the robot
                try:
                    navigate.send(goal, timeout=15.0)
                    break
                except GoalRejected:
                    assert time.monotonic() < deadline, "the backend still refuses the goal"
                    tether.safety.beats(1)
            moving = odom.wait_for(lambda m: speed(m) > 0.2, 15.0, after=len(odom))
            assert moving is not None, "the base never got going"
            if speed(odom.messages[-1]) > 0.2:
                break
            tether.safety.beats(3)
        assert speed(odom.messages[-1]) > 0.2, "the base stopped before the kill three times"

        killed_at = time.time()  # the stand-in stamps odometry with wall time
        tether.supervisor.kill("ros2")
        at_rest = odom.wait_for(
            lambda m: stamp(m) > killed_at and speed(m) < STILL, STOP_TIMEOUT + STOP_SLACK + 5.0, after=len(odom) - 1
        )
        assert at_rest is not None, "the robot kept moving after the backend died"
        stopped_after = stamp(at_rest) - killed_at
        print(f"base at rest {stopped_after:.3f} s after the backend was killed (stop_timeout {STOP_TIMEOUT} s)")
        assert stopped_after < STOP_TIMEOUT + STOP_SLACK
        # It stopped for the silence, not for anything before it: the last signal went out at most
        # one period before the kill.
        assert stopped_after > STOP_TIMEOUT - 2 * ESTOP_PERIOD

        rest_index = odom.messages.index(at_rest)
        held = odom.wait_for(lambda m: stamp(m) > stamp(at_rest) + HELD, HELD + 5.0, after=rest_index)
        assert held is not None, "the robot stopped reporting odometry"
        since = odom.messages[rest_index : odom.messages.index(held) + 1]
        assert max(speed(m) for m in since) < STILL
        x0, y0 = position(at_rest)
        assert all(math.dist(position(m), (x0, y0)) < HELD_TOLERANCE for m in since), "the base moved after stopping"
