"""The ros2 backend on Zenoh: tether's robot keys on one session, the ROS 2 robot (rmw.py) on another."""

from __future__ import annotations

import itertools
import logging
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec
import zenoh

from schemas import keys
from schemas.actions import GoalState
from schemas.common import ErrorKind, ServiceError, preview
from schemas.robot import FollowJointTrajectoryGoal, NavigateToPoseGoal, RobotDiagnostics, RobotProblem, Twist
from schemas.safety import SafetyStatus
from schemas.world import CameraImage, Empty, World
from services.actionlib import ActionServer, GoalHandle, Outcome
from services.errors import CallError
from services.robotlink import LinkGuard, Verifier
from services.robotmodel import ArmModel
from services.robotrules import PREEMPT_TIMEOUT, HeartbeatGuard, KeepOut, check_trajectory
from services.ros2.backend import (
    BOOL,
    COMPRESSED_IMAGE,
    DETECTIONS,
    DIAGNOSTICS_WINDOW,
    ESTOP_PERIOD,
    FOLLOW_JOINT_TRAJECTORY,
    GRIPPER_COMMAND,
    IMAGE,
    JOINT_STATE,
    NAVIGATE_THROUGH_POSES,
    NAVIGATE_TO_POSE,
    ODOMETRY,
    PARALLEL_GRIPPER_COMMAND,
    REPORT_MAX_BYTES,
    SPEED_LIMIT,
    TRIGGER,
    BaseLimits,
    CmdVelHold,
    EstopSignal,
    JointMerger,
    Messages,
    Perception,
    RateLimit,
    RobotCallFailed,
    RobotGoalForgotten,
    RobotGoalUnanswered,
    RobotLinkClosed,
    RobotRefused,
    RobotReportError,
    RobotState,
    Stamps,
    camera_image,
    odometry,
)
from services.ros2.config import Ros2Config
from services.ros2.goals import Ending, GoalRun, GripperRun, NavigationRun, RunContext, TrajectoryRun
from services.ros2.rmw import (
    MAX_PAYLOAD,
    RosActionClient,
    RosCallError,
    RosClientGoal,
    RosGoalRejected,
    RosGoalUnknown,
    RosNode,
    RosNodeClosed,
)
from services.ros2.types import RosTypes
from services.ros2.wire import CancelReturn, Naming
from services.runtime import ConfigError, Node
from services.worldmodel import WorldModel

log = logging.getLogger(__name__)

# How often a complaint about the robot's reports is logged, at most (seconds).
COMPLAINT_PERIOD = 5.0
WAIT_LOG_PERIOD = 10.0
CLOSE_TIMEOUT = 3.0
PROBLEM_CHARS = 1000  # a problem's text in the diagnostics, at most
# The largest message Zenoh reassembles from the robot's network: the most any report or reply may
# weigh (above that it is dropped unread anyway). Zenoh's default, 1 GiB, let any peer there make the
# backend hold a gigabyte per message before the size check saw it.
ROBOT_MAX_MESSAGE = max(MAX_PAYLOAD, *REPORT_MAX_BYTES.values())


def robot_session_config(config: Ros2Config) -> zenoh.Config:
    """The Zenoh session on the robot's side: a peer connecting to its router (or zenoh-bridge-ros2dds),
    apart from tether's own network; or the file `zenoh_config` names."""
    if config.zenoh_config:
        path = Path(config.zenoh_config)
        if not path.is_file():
            raise ConfigError(f"[ros2] zenoh_config {path} does not exist")
        conf = zenoh.Config.from_file(str(path))
        # The file's own limit is kept when it is lower; unset (Zenoh's 1 GiB) or higher, it is ours.
        limit = "transport/link/rx/max_message_size"
        if int(msgspec.json.decode(conf.get_json(limit))) > ROBOT_MAX_MESSAGE:
            conf.insert_json5(limit, str(ROBOT_MAX_MESSAGE))
        return conf
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", msgspec.json.encode([config.endpoint]).decode())
    retry = {"period_init_ms": 200, "period_max_ms": 1000, "period_increase_factor": 2}
    conf.insert_json5("connect/retry", msgspec.json.encode(retry).decode())
    conf.insert_json5("transport/link/rx/max_message_size", str(ROBOT_MAX_MESSAGE))
    return conf


def naming(config: Ros2Config) -> Naming:
    try:
        return Naming(config.style, config.ros_domain(), config.namespace)
    except ValueError as exc:
        raise ConfigError(f"[ros2]: {exc}") from None


def check_class_map(config: Ros2Config, world: World) -> None:
    objects = {o.id for o in world.objects}
    for detected, object_id in config.class_map.items():
        if object_id not in objects:
            raise ConfigError(
                f"[ros2] class_map: {detected!r} -> {object_id!r}, which is no object of world {world.name}"
            )


def _call_failed(exc: RosCallError) -> RobotCallFailed:
    return RobotLinkClosed(str(exc)) if isinstance(exc, RosNodeClosed) else RobotCallFailed(str(exc))


class _Goal:
    """rmw's RosClientGoal, its errors as the backend's."""

    def __init__(self, goal: RosClientGoal, client: RosActionClient) -> None:
        self._goal = goal
        self._client = client
        self._canceling = False  # the server took (or may have taken) a cancel of ours: the goal may be CANCELING

    @property
    def status(self) -> int:
        return int(self._goal.status)

    def result(self, timeout: float) -> tuple[int, Any]:
        try:
            outcome = self._goal.result(timeout)
        except RosGoalUnknown as exc:
            raise RobotGoalForgotten(str(exc)) from None
        except RosCallError as exc:
            raise _call_failed(exc) from None
        self._client.forget(self._goal)
        return outcome

    def cancel(self, timeout: float) -> bool:
        """Ask the robot to cancel the goal; True when its server answers that the goal had ended already
        (before it may have taken a cancel of ours), or that it knows no such goal now (restarted, or
        forgot it): either way it runs none."""
        try:
            answer = self._goal.request_cancel(timeout)
        except RosCallError as exc:
            self._canceling = True  # the server may have taken it, and its answer been lost
            raise _call_failed(exc) from None
        if answer is CancelReturn.ERROR_NONE:
            self._canceling = True
        elif answer is CancelReturn.ERROR_GOAL_TERMINATED and self._canceling:
            # rcl_action answers so for a goal still CANCELING too (no longer cancelable): once the
            # server may have taken a cancel, only the goal's result says it ended.
            log.debug("the robot still cancels goal %s (or it ended): waiting for its result", self._goal.goal_id.hex())
            return False
        return answer in (CancelReturn.ERROR_GOAL_TERMINATED, CancelReturn.ERROR_UNKNOWN_GOAL_ID)

    def forget(self) -> None:
        self._client.forget(self._goal)


class _Action:
    """rmw's RosActionClient, its errors as the backend's."""

    def __init__(self, client: RosActionClient) -> None:
        self._client = client
        self.name = client.name

    def send_goal(self, goal: Any, *, timeout: float) -> _Goal:
        goal_id = uuid.uuid4().bytes  # known before it is sent: an unanswered goal is canceled by it
        try:
            return _Goal(self._client.send_goal(goal, timeout=timeout, goal_id=goal_id), self._client)
        except RosGoalRejected as exc:
            raise RobotRefused(str(exc)) from None
        except RosCallError as exc:
            raise RobotGoalUnanswered(str(exc), goal_id) from None

    def cancel(self, goal_id: bytes, timeout: float) -> bool:
        try:
            return self._client.cancel_goal(goal_id, timeout)
        except RosCallError as exc:
            raise RobotCallFailed(str(exc)) from None


class _Complaints:
    """Logs each kind of complaint about the robot's reports at most every COMPLAINT_PERIOD."""

    def __init__(self) -> None:
        self._last: dict[str, float] = {}

    def __call__(self, what: str, text: str) -> None:
        now = time.monotonic()
        if now - self._last.get(what, -COMPLAINT_PERIOD) >= COMPLAINT_PERIOD:
            self._last[what] = now
            log.warning("%s: %s", what, text)


class Ros2Backend:
    """Serves tether's robot protocol (docs/robot.md) by driving a ROS 2 robot.

    The tether side is services/sim/node.py's: three action servers (fail closed, one goal per
    action, preemption), cmd_vel, the heartbeat, reports and the camera. Each tether goal runs as a
    GoalRun (goals.py) against the robot's Nav2 and ros2_control actions. `run()` is the heartbeat
    watch: on a block it aborts every goal and tells the robot its own stop (emergency_stop, zero
    cmd_vel at 20 Hz) until a clear heartbeat comes.
    """

    def __init__(
        self,
        node: Node,
        session: zenoh.Session,
        ros_naming: Naming,
        config: Ros2Config,
        world: World,
        *,
        robot_key: bytes,
    ) -> None:
        self.node = node
        self.config = config
        self.world = world
        self.guard = HeartbeatGuard(
            config.heartbeat_timeout, config.first_heartbeat_wait, max_age=config.heartbeat_max_age
        )
        self.robot = RobotState(odom_topic=config.names.odom)
        # Commands and heartbeats count only with safety's MAC (services/robotlink.py): anything else
        # is dropped, logged and listed in robot/diagnostics; a forged heartbeat is no heartbeat.
        self.link = LinkGuard(Verifier(robot_key), report=self.robot.problem)
        # Its own check of the world's keep-out zones, also for a signed command (docs/robot.md).
        self.keep_out = KeepOut.of(world)
        robot_spec = world.robot
        self.limits = BaseLimits(
            config.max_linear_speed or robot_spec.max_linear_speed,
            config.max_angular_speed or robot_spec.max_angular_speed,
        )
        arm = ArmModel(robot_spec.arm_urdf)
        self.arm_limits = (arm.lower.tolist(), arm.upper.tolist())
        self.base_radius = WorldModel(world).base_radius
        self.masses = {o.id: o.mass for o in world.objects}
        self.types = RosTypes(config.distro)
        self.ros = RosNode(session, self.types, ros_naming, config.node_name, on_error=self.robot.problem)
        names, parallel = config.names, config.gripper_action == "parallel_gripper_command"
        self.messages = Messages(
            self.types,
            config.frames,
            stamped_cmd_vel=config.stamped_cmd_vel,
            parallel_gripper_joint=config.gripper_joint if parallel else "",
            gripper_position_per_gap=config.gripper_position_per_gap,
        )
        self._wake = threading.Event()
        self._estop_signal = EstopSignal()
        self._released = False  # the robot was told it may move since the last block
        # Taken to check whether the robot may move and publish to it in one step, so a cmd_vel never
        # follows the stop (emergency_stop, zero cmd_vel) that blocked it.
        self._cmd_lock = threading.RLock()
        self._cmd_hold = CmdVelHold(config.cmd_vel_timeout)
        self._cmd_stamp = 0.0  # when the held cmd_vel was sent (wall time): its stamp
        self._epoch = 0  # counts the stops the robot was told
        # Goals the robot would not end when canceled: its emergency stop is held until they end.
        self._holds: dict[int, str] = {}
        self._holds_lock = threading.Lock()
        self._hold_ids = itertools.count()
        self._stamps = Stamps()
        self._complain = _Complaints()
        self._joints = JointMerger()
        self._perception = Perception(world, config.class_map, config.person_class, config.frames)
        self._rates = {
            name: RateLimit(hz)
            for name, hz in (
                ("odom", config.odom_hz),
                ("joint_states", config.joint_states_hz),
                ("objects", config.objects_hz),
                ("humans", config.humans_hz),
            )
        }
        self._image: tuple[Any, float] | None = None

        # tether's side first: the robot's reports are relayed to it as soon as they arrive.
        self._odom_out = node.publisher(keys.ODOM)
        self._joint_states_out = node.publisher(keys.JOINT_STATES)
        self._objects_out = node.publisher(keys.OBJECTS)
        self._humans_out = node.publisher(keys.HUMANS)

        # The robot's side
        self._cmd_vel = self.ros.publisher(names.cmd_vel, self.messages.cmd_vel_type)
        self._speed_limit = self.ros.publisher(names.speed_limit, SPEED_LIMIT)
        self._estop = self.ros.publisher(names.emergency_stop, BOOL)
        self._stop = self.ros.client(names.stop, TRIGGER) if config.stop_service else None
        self._navigate = _Action(self.ros.action_client(names.navigate_to_pose, NAVIGATE_TO_POSE))
        self._navigate_through = _Action(self.ros.action_client(names.navigate_through_poses, NAVIGATE_THROUGH_POSES))
        self._trajectory = _Action(self.ros.action_client(names.follow_joint_trajectory, FOLLOW_JOINT_TRAJECTORY))
        gripper_type = PARALLEL_GRIPPER_COMMAND if parallel else GRIPPER_COMMAND
        self._gripper = _Action(self.ros.action_client(names.gripper, gripper_type))
        for topic, ros_type, callback in (
            (names.odom, ODOMETRY, self._on_odom),
            (names.joint_states, JOINT_STATE, self._on_joint_states),
            (names.detections, DETECTIONS, self._on_detections),
            (names.camera, IMAGE if config.camera_format == "raw" else COMPRESSED_IMAGE, self._on_image),
        ):
            self.ros.subscribe(topic, ros_type, callback, max_bytes=REPORT_MAX_BYTES[ros_type])

        # tether's side
        self.context = RunContext(
            safety=self.guard.now,
            robot=self.robot,
            goal_timeout=config.goal_timeout,
            cancel_timeout=config.cancel_timeout,
            halt_base=self._halt_base,
            robot_released=lambda: self._released,
            block_robot=self._block_robot,
            motion_epoch=lambda: self._epoch,
        )
        # One goal per action: a new one cancels the running one's ROS goal, waits for it to end,
        # then is accepted (docs/robot.md, Preemption), within PREEMPT_TIMEOUT.
        self.servers: list[ActionServer[Any, Any, Any]] = [
            ActionServer(
                node,
                action,
                execute,
                accept=accept,
                preempts=lambda _goal: True,
                preempt_timeout=PREEMPT_TIMEOUT,
                verify=self.link,
            )
            for action, execute, accept in (
                (keys.ROBOT_NAVIGATE, self._execute(self._navigation), self._accept_navigation),
                (keys.ROBOT_TRAJECTORY, self._execute(self._trajectory_run), self._accept_trajectory),
                (keys.ROBOT_GRIPPER, self._execute(self._gripper_run), self._accept),
            )
        ]
        node.subscribe(keys.HEARTBEAT, self._on_heartbeat, verify=self.link)
        node.subscribe(keys.ROBOT_CMD_VEL, self._on_cmd_vel, verify=self.link)
        node.serve(keys.CAMERA_IMAGE, self._on_camera_image)
        node.serve(keys.ROBOT_DIAGNOSTICS, self._on_diagnostics, inline=True)

    # Safety: fail closed

    def _on_heartbeat(self, status: SafetyStatus) -> None:
        self.guard.heard(status)
        self._wake.set()

    def _accept(self, _goal: object) -> str | None:
        return self.guard.accept() or self._held()

    def _accept_navigation(self, goal: NavigateToPoseGoal) -> str | None:
        if (reason := self._accept(goal)) is not None:
            return reason
        odom = self.robot.odometry(self.config.odom_timeout)
        reason = self.keep_out.goal(goal, None if isinstance(odom, str) else odom.pose)
        if reason is not None:
            self.robot.goal_failed(f"refused a navigate_to_pose goal: {reason}")
        return reason

    def _accept_trajectory(self, goal: FollowJointTrajectoryGoal) -> str | None:
        # ROS's goal response carries no reason: the arm's own checks here, so the reason reaches safety.
        return self.guard.accept() or self._held() or check_trajectory(goal, *self.arm_limits)

    def run(self, stop: threading.Event, keepalive: Callable[[], None] = lambda: None) -> None:
        """Watch the heartbeat until `stop`: stop the robot when it goes quiet or latches, tell it
        emergency_stop (true or false) at 20 Hz always, release it on a clear heartbeat, keep cmd_vel
        within limits and end it after its hold. A round that fails is logged and the next one runs.
        `keepalive` (systemd's watchdog) after every round that succeeded, so a watch that hangs, or
        fails round after round, is restarted."""
        while not stop.is_set():
            try:
                wake_at = self._watch()
            except Exception:
                log.exception("the heartbeat watch failed a round; it goes on")
                wake_at = time.monotonic() + ESTOP_PERIOD
            else:
                keepalive()
            self._wake.wait(max(0.0, wake_at - time.monotonic()))

    def _watch(self) -> float:
        """One round of the watch; when the next is due."""
        self._wake.clear()
        safety = self.guard.poll()
        now = time.monotonic()
        blocked = safety.blocked is not None or self._held() is not None
        flag = self._estop_signal.due(blocked, now)
        if flag is not None:
            self._signal(flag)
        if safety.stopped:
            assert safety.blocked is not None
            self._stop_robot(safety.blocked)
        if not blocked:
            self._keep_cmd_vel_within()
        wake_at = self._estop_signal.next_at
        if (ends_at := self._cmd_hold.ends_at) is not None:
            wake_at = min(wake_at, ends_at)
        stale_at = self.guard.stale_at()
        if safety.blocked is None and stale_at is not None:
            wake_at = min(wake_at, stale_at + 0.001)
        return wake_at

    def _signal(self, stopped: bool) -> None:
        """Tell the robot emergency_stop; when true, first of all, with a zero cmd_vel."""
        with self._cmd_lock:
            if stopped:
                self._released = False
                self._epoch += 1
            self._put(self._estop, self.messages.flag(stopped))
            if stopped:
                self._halt_base()
            else:
                self._released = True

    def _held(self) -> str | None:
        """Why the robot's emergency stop is held on the backend's own account, or None."""
        with self._holds_lock:
            return next(iter(self._holds.values()), None)

    def _block_robot(self, reason: str) -> Callable[[], None]:
        """Hold the robot's emergency stop until the returned function is called."""
        with self._holds_lock:
            key = next(self._hold_ids)
            self._holds[key] = reason
        log.error("the robot is held stopped: %s", reason)
        self._signal(True)
        self._wake.set()

        def release() -> None:
            with self._holds_lock:
                self._holds.pop(key, None)
            self._wake.set()

        return release

    def _stop_robot(self, reason: str) -> None:
        """Safety blocks the robot (told so already): every goal aborted, the robot's own stop service."""
        for server in self.servers:
            server.abort_all(reason)
        if self._stop is not None:
            threading.Thread(target=self._call_stop, name="ros2-stop", daemon=True).start()

    def _call_stop(self) -> None:
        assert self._stop is not None
        try:
            reply = self._stop.call(self.types.new(f"{TRIGGER}_Request"), self.config.goal_timeout)
            if not reply.success:
                log.warning("the robot's stop service said: %s", reply.message)
        except RosCallError as exc:
            log.error("the robot's stop service failed: %s", exc)

    def _halt_base(self) -> None:
        with self._cmd_lock:
            self._cmd_hold.clear()
            self._put(self._cmd_vel, self.messages.cmd_vel(0.0, 0.0, time.time()))

    def _put(self, publisher: Any, message: Any) -> None:
        try:
            publisher.put(message)
        except zenoh.ZError as exc:
            log.debug("not published on %s: %s", publisher.endpoint.name, exc)
        except Exception:
            log.exception("not published on %s", publisher.endpoint.name)

    # cmd_vel

    def _navigating(self) -> bool:
        return bool(self.servers[0].active())

    def _on_cmd_vel(self, twist: Twist) -> None:
        navigating = self._navigating()  # outside the lock: the action server's lock is taken first elsewhere
        with self._cmd_lock:
            safety = self.guard.now()
            if safety.blocked is not None or not self._released:
                log.debug("ignored cmd_vel: %s", safety.blocked or "the robot has not been released yet")
                return
            if navigating:
                self._complain("cmd_vel", "ignored while a navigate_to_pose goal runs")
                return
            linear, angular = self.limits.clamp(twist, safety)
            odom = self.robot.odometry(self.config.odom_timeout)
            here = None if isinstance(odom, str) else odom.pose
            if reason := self.keep_out.drive(here, linear, angular, self.config.cmd_vel_timeout):
                # Dropped: what the robot holds now was checked when it came, and ends before any zone.
                self.robot.problem(f"refused a cmd_vel: {reason}")
                self._complain("cmd_vel", reason)
                return
            self._cmd_hold.sent(twist, linear, angular, time.monotonic())
            # Stamped when sent, not with tether's stamp: diff_drive_controller holds a TwistStamped
            # cmd_vel_timeout from its stamp and ignores one older, so a command that took longer
            # through the pipeline would be dropped and a quicker one held for less than its hold here.
            self._cmd_stamp = time.time()
            self._put(self._cmd_vel, self.messages.cmd_vel(linear, angular, self._cmd_stamp))

    def _keep_cmd_vel_within(self) -> None:
        """A held cmd_vel above a limit that just dropped goes out again, clamped (never faster, never
        held longer); once its hold is over, one zero cmd_vel ends it."""
        navigating = self._navigating()
        with self._cmd_lock:
            if navigating:
                self._cmd_hold.clear()  # Nav2 drives the base now
                return
            safety = self.guard.now()
            command = self._cmd_hold.due(lambda twist: self.limits.clamp(twist, safety), time.monotonic())
            if command is not None:
                # A clamped re-send keeps the command's stamp, so the robot holds it no longer; the zero
                # that ends the hold is stamped now.
                stamp = self._cmd_stamp if command != (0.0, 0.0) else time.time()
                self._put(self._cmd_vel, self.messages.cmd_vel(*command, stamp))

    # Goals

    def _execute(self, make: Any) -> Any:
        def execute(handle: GoalHandle[Any, Any]) -> Outcome[Any]:
            run: GoalRun = make(handle)
            ending: Ending = run.run()
            if ending.state is GoalState.ABORTED and not handle.should_stop and self.guard.now().blocked is None:
                # Neither safety nor tether ended it: the robot did (or its reports would not let it start).
                message = ending.message if run.label in ending.message else f"{run.label}: {ending.message}"
                self.robot.goal_failed(message)
            return Outcome(ending.state, ending.result, ending.message)

        return execute

    def _navigation(self, handle: GoalHandle[Any, Any]) -> GoalRun:
        return NavigationRun(
            self.context,
            handle,
            to_pose=self._navigate,
            through_poses=self._navigate_through,
            messages=self.messages,
            limits=self.limits,
            publish_speed_limit=self._publish_speed_limit,
            base_radius=self.base_radius,
            odom_timeout=self.config.odom_timeout,
            stall_timeout=self.config.stall_timeout,
        )

    def _trajectory_run(self, handle: GoalHandle[Any, Any]) -> GoalRun:
        return TrajectoryRun(
            self.context, self._trajectory, handle, self.messages, joint_states_timeout=self.config.joint_states_timeout
        )

    def _gripper_run(self, handle: GoalHandle[Any, Any]) -> GoalRun:
        return GripperRun(self.context, self._gripper, handle, self.messages, self.masses, 1.0 / self.config.objects_hz)

    def _publish_speed_limit(self, metres_per_second: float) -> None:
        self._put(self._speed_limit, self.messages.speed_limit(metres_per_second, time.time()))

    # The robot's reports

    def _on_odom(self, message: Any) -> None:
        stamp = self._stamps.of(message.header, time.time(), self.config.names.odom)
        try:
            odom = odometry(message, self.config.frames.odom, stamp)
        except RobotReportError as exc:
            self.robot.refused_odometry(str(exc))
            self._complain(f"odometry on {self.config.names.odom}", str(exc))
            return
        self.robot.heard_odometry(odom)
        if self._rates["odom"].allow(time.monotonic()):
            self._odom_out.put(odom)

    def _on_joint_states(self, message: Any) -> None:
        try:
            stamp = self._stamps.of(message.header, time.time(), self.config.names.joint_states)
            joints = self._joints.update(message, stamp)
        except RobotReportError as exc:
            what = f"joint states on {self.config.names.joint_states}"
            self.robot.problem(f"{what}: {exc}")
            self._complain(what, str(exc))
            return
        if joints is None:
            # Also a message of none of tether's joints (a base's wheels on the same topic): nothing new.
            if missing := self._joints.missing():
                self._complain("joint states", f"waiting for joints {missing}")
            elif lagging := self._joints.lagging():
                why = f"joints {lagging} not heard for over {self._joints.max_lag:g} s while others were: not passed on"
                self.robot.problem(f"joint states on {self.config.names.joint_states}: {why}")
                self._complain("joint states", why)
            return
        self.robot.heard_joints(joints)
        if self._rates["joint_states"].allow(time.monotonic()):
            self._joint_states_out.put(joints)

    def _on_detections(self, message: Any) -> None:
        stamp = self._stamps.of(message.header, time.time(), self.config.names.detections)
        perceived = self._perception.read(message, stamp)
        for problem in perceived.problems:
            self._complain(f"detections on {self.config.names.detections}", problem)
        now = time.monotonic()
        if perceived.objects is not None:
            self.robot.heard_objects(perceived.objects)
            if self._rates["objects"].allow(now):
                self._objects_out.put(perceived.objects)
        if perceived.humans is not None and self._rates["humans"].allow(now):
            self._humans_out.put(perceived.humans)

    def _on_image(self, message: Any) -> None:
        self._image = (message, self._stamps.of(message.header, time.time(), self.config.names.camera))

    def _on_camera_image(self, _request: Empty) -> CameraImage:
        latest = self._image
        if latest is None:
            message = f"no camera image from the robot on {self.config.names.camera} yet"
            raise CallError(ServiceError(kind=ErrorKind.UNAVAILABLE, message=message))
        try:
            return camera_image(*latest)
        except RobotReportError as exc:
            raise CallError(ServiceError(kind=ErrorKind.UNAVAILABLE, message=str(exc))) from None

    def _on_diagnostics(self, _request: Empty) -> RobotDiagnostics:
        now, wall = time.monotonic(), time.time()
        problems = [
            RobotProblem(text=preview(text, PROBLEM_CHARS), last_seen=wall - (now - at))
            for text, at in self.robot.diagnostics()
        ]
        return RobotDiagnostics(stamp=wall, backend=self.node.service, window=DIAGNOSTICS_WINDOW, problems=problems)

    # Start and end

    def wait_for_robot(self, stop: threading.Event) -> bool:
        """Wait until the robot's odometry and joint states come (its side is up); False if `stop` came first."""
        logged = time.monotonic()
        while missing := self.robot.ready():
            if stop.wait(0.1):
                return False
            if time.monotonic() - logged > WAIT_LOG_PERIOD:
                logged = time.monotonic()
                problem = self.robot.recent_problem(WAIT_LOG_PERIOD)
                log.warning(
                    "still no %s from the robot at %s (domain %d)%s",
                    " or ".join(missing),
                    self.config.zenoh_config or self.config.endpoint,
                    self.ros.naming.domain_id,
                    f"; {problem}" if problem else "",
                )
        return True

    def close(self) -> None:
        """Tell the robot to stop first, abort every goal (their ROS goals canceled), leave the robot
        stopped, leave the robot's network."""
        self._signal(True)
        for server in self.servers:
            server.abort_all("the ros2 backend is shutting down")
        deadline = time.monotonic() + CLOSE_TIMEOUT
        while any(server.active() for server in self.servers) and time.monotonic() < deadline:
            time.sleep(0.02)  # goal runs canceling their ROS goals, bounded by CLOSE_TIMEOUT
        self._signal(True)
        self.ros.close()
