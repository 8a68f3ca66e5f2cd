"""The stand-in robot's transport: the sim behind a ROS 2 face (Nav2, ros2_control, vision_msgs)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgspec
import zenoh

from schemas import keys
from schemas.actions import GoalState
from schemas.robot import Twist
from schemas.world import PerceivedObjects
from services.actionlib import Outcome
from services.ros2.config import Names
from services.ros2.rmw import RosNode, RosPublisher, RosServerGoal
from services.ros2sim import messages
from services.ros2sim.config import Ros2SimConfig
from services.ros2sim.estop import STOP_REASON, EstopLock
from services.ros2sim.messages import BadMessage
from services.runtime import Node
from services.sim.config import SimConfig
from services.sim.controllers import Controllers, Navigation
from services.sim.loop import Report, SimLoop
from services.sim.renderer import Picture, Renderer
from services.sim.simulation import Simulation
from services.sim.world import Motion

log = logging.getLogger(__name__)

NODE_NAME = "tether_standin"
# The ROS names it serves: the defaults of the backend's [ros2.names].
NAMES = Names()

# A stream of bad messages (cmd_vel at 20 Hz) is reported at most this often per topic (seconds).
REFUSAL_LOG_INTERVAL = 1.0
# A goal finding the robot held waits this long for one more emergency_stop message (at 20 Hz from the backend).
RELEASE_GRACE = 0.1
# How long closing waits for running goals to report how they ended.
CLOSE_TIMEOUT = 1.0


def ros_session(config: Ros2SimConfig) -> zenoh.Session:
    """The robot's own zenoh network: a peer listening where rmw_zenoh's router would, reachable by nothing else."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", msgspec.json.encode([config.listen]).decode())
    conf.insert_json5("connect/endpoints", "[]")
    return zenoh.open(conf)


@dataclass(frozen=True)
class ActionFace:
    """One ROS action the robot serves, and how its messages map onto the sim's goals."""

    name: str
    ros_type: str
    goal: Callable[[Any], Any]  # the ROS goal -> the sim's goal; BadMessage when unusable
    start: Callable[[Controllers, Any], Motion[Any, Any]]
    feedback: Callable[[Any, Any, float], Any]  # (the sim's feedback, its goal, seconds since accepted) -> ROS
    result: Callable[[Outcome[Any], Any], Any]  # (how it ended, the sim's goal or None) -> the ROS result
    # How a goal that a new one preempted ends, as the real server ends it: its status and result.
    preempted: Callable[[], tuple[GoalState, Any]]
    check: Callable[[Any], str | None] = lambda _goal: None  # the robot's own checks of the sim's goal
    navigator: bool = False  # one of Nav2's navigators, which take goals one navigator at a time
    # Takes every goal, aborting one it cannot carry out, as Nav2's servers and ros2_control's gripper
    # controller do; else rejects it, as joint_trajectory_controller does.
    takes_every_goal: bool = False


class RosGoal:
    """A goal on a ROS action server as SimLoop.relay sees it: stops once canceled (a stop ends
    its motion as aborted on the sim thread); its feedback converted to ROS on the way out."""

    abort_reason = ""

    def __init__(self, goal: RosServerGoal, convert: Callable[[Any, float], Any]) -> None:
        self._goal = goal
        self._convert = convert
        self._accepted = time.monotonic()

    @property
    def should_stop(self) -> bool:
        return self._goal.cancel_requested.is_set()

    def feedback(self, message: Any) -> None:
        try:
            self._goal.publish_feedback(self._convert(message, time.monotonic() - self._accepted))
        except Exception:
            # Feedback is best effort: never let it end the relay, which would orphan the motion.
            log.exception("feedback of goal %s not published", self._goal.goal_id.hex())


class StandIn:
    """The sim as a plain ROS 2 robot: no tether heartbeat, its own emergency_stop (a dead-man signal
    too: silence for stop_timeout stops it), Nav2's speed_limit.

    Serves tether's network only sim/ground_truth and sim/move. Call run() on the thread that
    should own pybullet.
    """

    def __init__(self, ros: RosNode, node: Node, sim: Simulation, sim_config: SimConfig, config: Ros2SimConfig) -> None:
        self.ros = ros
        self.sim = sim
        self.config = config
        self.types = ros.types
        self._realtime_factor = sim_config.realtime_factor
        self._lock = threading.Lock()
        self._signal = threading.Condition(self._lock)  # notified on every emergency_stop message
        self._signals = 0
        self._estop = EstopLock(config.stop_timeout)  # emergency_stop, its silence, the stop service
        self._limits: tuple[float | None, float | None] = (None, None)
        self._refused_at: dict[str, float] = {}
        self._navigating: dict[str, int] = {}  # navigation goals executing, per action (Nav2's navigator muxer)
        # The sim thread's own: what it last applied.
        self._stops_applied = 0
        self._stopped: str | None = None

        self._odom = ros.publisher(NAMES.odom, "nav_msgs/msg/Odometry")
        self._joint_states = ros.publisher(NAMES.joint_states, "sensor_msgs/msg/JointState")
        self._detections = ros.publisher(NAMES.detections, "vision_msgs/msg/Detection3DArray")
        self._camera = ros.publisher(NAMES.camera, "sensor_msgs/msg/CompressedImage")
        # The camera renders, detects and encodes in a process of its own, never on the sim thread.
        self.renderer = Renderer(sim.world, sim_config.camera)
        self.loop = SimLoop(sim, sim_config.realtime_factor, self._obey, self._reports(sim_config))

        cmd_vel_type = "geometry_msgs/msg/TwistStamped" if config.stamped_cmd_vel else "geometry_msgs/msg/Twist"
        ros.subscribe(NAMES.cmd_vel, cmd_vel_type, self._on_cmd_vel)
        ros.subscribe(NAMES.speed_limit, "nav2_msgs/msg/SpeedLimit", self._on_speed_limit)
        ros.subscribe(NAMES.emergency_stop, "std_msgs/msg/Bool", self._on_emergency_stop)
        ros.serve(NAMES.stop, "std_srvs/srv/Trigger", self._on_stop)
        self.servers = [
            ros.action_server(face.name, face.ros_type, accept=self._acceptor(face), execute=self._executor(face))
            for face in self._faces()
        ]
        node.serve(keys.GROUND_TRUTH, self.loop.ground_truth)
        node.serve(keys.SIM_MOVE, self.loop.move)

    def _reports(self, sim_config: SimConfig) -> tuple[Report, ...]:
        """What the robot publishes on its own, each at its rate: odometry and joint states also while
        the sim catches up with the wall clock."""
        types, sensors, scene = self.types, self.sim.sensors, self.sim.scene
        sizes = {o.id: o.size for o in self.sim.world.objects}

        def publish_objects(objects: PerceivedObjects) -> None:
            self._detections.put(messages.object_detections(types, objects, sizes))

        return (
            Report(
                "joint_states",
                sim_config.joint_states_hz,
                self._report(self._joint_states, lambda t: messages.joint_state(types, sensors.joint_state(t))),
                while_catching_up=True,
            ),
            Report(
                "odom",
                sim_config.odom_hz,
                self._report(self._odom, lambda t: messages.odometry(types, sensors.odometry(t))),
                while_catching_up=True,
            ),
            # Published from the renderer's thread once detected; a frame it is busy with is not queued.
            Report("objects", sim_config.objects_hz, lambda t: self.renderer.detect(scene.poses(t), publish_objects)),
            Report(
                "humans",
                sim_config.humans_hz,
                self._report(
                    self._detections, lambda t: messages.people_detections(types, sensors.perceived_humans(t))
                ),
            ),
            Report("camera", self.config.camera_hz, self._picture),
        )

    def _faces(self) -> tuple[ActionFace, ...]:
        """The four actions: Nav2's two navigations (one base), ros2_control's arm and gripper."""
        types = self.types
        now = time.time

        def navigation(name: str, action_type: str, to_goal: Callable[[Any], Any]) -> ActionFace:
            return ActionFace(
                name,
                action_type,
                to_goal,
                Controllers.navigate,
                lambda fb, _goal, elapsed: messages.navigation_feedback(types, action_type, fb, now(), elapsed),
                lambda outcome, _goal: messages.navigation_result(types, action_type, outcome),
                # Nav2's SimpleActionServer aborts it with an empty result (accept_pending_goal).
                lambda: (GoalState.ABORTED, types.new(f"{action_type}_Result")),
                navigator=True,
                takes_every_goal=True,
            )

        return (
            navigation(NAMES.navigate_to_pose, messages.NAVIGATE_TO_POSE, messages.navigate_to_pose_goal),
            navigation(
                NAMES.navigate_through_poses, messages.NAVIGATE_THROUGH_POSES, messages.navigate_through_poses_goal
            ),
            ActionFace(
                NAMES.follow_joint_trajectory,
                messages.FOLLOW_JOINT_TRAJECTORY,
                messages.trajectory_goal,
                Controllers.follow_trajectory,
                lambda fb, goal, _elapsed: messages.trajectory_feedback(types, fb, goal.joint_names, now()),
                lambda outcome, _goal: messages.trajectory_result(types, outcome),
                lambda: (GoalState.CANCELED, messages.trajectory_preempted(types)),
                check=self.sim.controllers.arm.check_trajectory,
            ),
            ActionFace(
                NAMES.gripper,
                messages.GRIPPER_COMMAND,
                messages.gripper_goal,
                Controllers.gripper,
                lambda fb, _goal, _elapsed: messages.gripper_feedback(types, fb),
                lambda outcome, goal: messages.gripper_result(types, outcome, goal),
                # gripper_action_controller cancels it with an empty result (preempt_active_goal).
                lambda: (GoalState.CANCELED, types.new(f"{messages.GRIPPER_COMMAND}_Result")),
                takes_every_goal=True,
            ),
        )

    # The robot's own stop and speed limit

    def _held(self) -> str | None:
        """Why the robot must stay still now (emergency_stop, or its silence), or None."""
        with self._lock:
            return self._estop.poll(time.monotonic()).held

    def _on_emergency_stop(self, message: Any) -> None:
        with self._lock:
            now = time.monotonic()
            before = self._estop.poll(now).held
            self._estop.heard(bool(message.data), now)
            after = self._estop.poll(now).held
            self._signals += 1
            self._signal.notify_all()
        if after != before:
            log.warning("emergency_stop: %s", f"halting: {after}" if after else "released")

    def _on_stop(self, _request: Any) -> Any:
        """std_srvs Trigger: stop now (base halted, arm and fingers held, goals aborted), not latched."""
        with self._lock:
            self._estop.stop_service()
        return self.types.new("std_srvs/srv/Trigger_Response", success=True, message=STOP_REASON)

    def _on_speed_limit(self, message: Any) -> None:
        try:
            limits = messages.speed_limits(message, self.sim.world.robot)
        except BadMessage as exc:
            self._refuse(NAMES.speed_limit, str(exc))
            return
        with self._lock:
            changed, self._limits = limits != self._limits, limits
        if changed:
            linear, angular = limits
            if linear is None or angular is None:
                log.info("speed limit lifted")
            else:
                log.info("speed limit %.2f m/s, %.2f rad/s", linear, angular)

    def _obey(self) -> str | None:
        """On the sim thread, before every step and goal: stop at once on a new stop; hold still while
        emergency_stop is set or silent; else move at full speed, navigations within the speed limit."""
        with self._lock:
            state, limits = self._estop.poll(time.monotonic()), self._limits
        controllers = self.sim.controllers
        if state.stops != self._stops_applied:  # counted, so a stop set and released within one step still stops
            self._stops_applied = state.stops
            log.warning("stopping the robot: %s", state.stop_reason)
            controllers.stop(state.stop_reason)
        if state.held is not None:
            self._stopped = state.held
            controllers.set_speed_scale(0.0)
            return state.held
        self._stopped = None
        # speed_limit is Nav2's controller_server's: it limits navigation, never cmd_vel, which goes
        # to the base controller past Nav2 (the backend clamps its own). SimLoop obeys again after
        # running commands, so a navigation just started is limited from its first step.
        navigating = Navigation.kind in controllers.motions
        controllers.set_speed_scale(1.0, *(limits if navigating else (None, None)))
        return None

    # cmd_vel

    def _on_cmd_vel(self, message: Any) -> None:
        try:
            command = messages.twist(message, self.config.stamped_cmd_vel)
        except BadMessage as exc:
            self._refuse(NAMES.cmd_vel, str(exc))
            return
        held = self._held()
        if held is not None:
            log.debug("ignored cmd_vel: %s", held)
            return
        # As diff_drive_controller: a stamped command holds cmd_vel_timeout from its stamp (0: from
        # now), and one older than that is ignored. A stamp ahead of this clock counts as now, never
        # holding it longer.
        timeout = self.config.cmd_vel_timeout
        age = max(0.0, time.time() - command.stamp) if command.stamp else 0.0
        if age >= timeout:
            self._refuse(NAMES.cmd_vel, f"stamped {age:.2f} s ago, older than cmd_vel_timeout ({timeout:g} s)")
            return
        hold = (timeout - age) * self._realtime_factor  # sim seconds
        self.loop.submit(lambda sim: self._apply_cmd_vel(sim, command, hold))

    def _apply_cmd_vel(self, sim: Simulation, command: Twist, hold: float) -> None:
        if self._stopped is None and not sim.controllers.set_cmd_vel(command, hold):
            log.debug("ignored cmd_vel while a navigation goal runs")

    def _refuse(self, where: str, reason: str) -> None:
        now = time.monotonic()
        if now - self._refused_at.get(where, -REFUSAL_LOG_INTERVAL) >= REFUSAL_LOG_INTERVAL:
            self._refused_at[where] = now
            log.warning("ignored a message on %s: %s", where, reason)

    # Goals

    def _held_after_next_signal(self) -> str | None:
        """Why the robot must stay still, asked again after one more emergency_stop message when it is
        held: a goal sent right after a release can overtake the release on the way (the two are not
        ordered in ROS 2), as the sim's goals may overtake a reset heartbeat (docs/robot.md)."""
        with self._signal:
            if self._estop.poll(time.monotonic()).held is None:
                return None
            heard = self._signals
            self._signal.wait_for(lambda: self._signals != heard, RELEASE_GRACE)
            return self._estop.poll(time.monotonic()).held

    def _refusal(self, face: ActionFace, ros_goal: Any) -> str | None:
        """Why the robot will not carry out a goal now, or None."""
        reason = self._held_after_next_signal()
        if reason is None:
            try:
                reason = face.check(face.goal(ros_goal))
            except BadMessage as exc:
                reason = str(exc)
        return reason

    def _acceptor(self, face: ActionFace) -> Callable[[Any], bool]:
        def accept(ros_goal: Any) -> bool:
            if face.takes_every_goal:
                return True  # refused once it executes (_carry_out)
            reason = self._refusal(face, ros_goal)
            if reason is not None:
                log.warning("rejected a goal on %s: %s", face.name, reason)
                return False
            return True

        return accept

    def _executor(self, face: ActionFace) -> Callable[[RosServerGoal], None]:
        def execute(server_goal: RosServerGoal) -> None:
            if not face.navigator:
                self._carry_out(face, server_goal)
                return
            with self._lock:
                busy = next((name for name, n in self._navigating.items() if n and name != face.name), None)
                if busy is None:
                    self._navigating[face.name] = self._navigating.get(face.name, 0) + 1
            if busy is not None:
                # Nav2's bt_navigator takes the goal, then aborts it at once: the running one goes on.
                server_goal.abort(face.preempted()[1])
                log.warning("%s goal aborted: %s is navigating", face.name, busy)
                return
            try:
                self._carry_out(face, server_goal)
            finally:
                with self._lock:
                    self._navigating[face.name] -= 1

        return execute

    def _carry_out(self, face: ActionFace, server_goal: RosServerGoal) -> None:
        """Relay one accepted goal to the sim and end it as the real action server would."""
        if face.takes_every_goal and (reason := self._refusal(face, server_goal.goal)) is not None:
            log.warning("aborted a goal on %s: %s", face.name, reason)
            server_goal.abort(face.result(Outcome(GoalState.ABORTED, None, reason), None))
            return
        goal = face.goal(server_goal.goal)  # accepted or refused above, so it converts
        port = RosGoal(server_goal, lambda feedback, elapsed: face.feedback(feedback, goal, elapsed))
        outcome = self.loop.relay(lambda controllers: face.start(controllers, goal), port)
        result = face.result(outcome, goal)
        if outcome.state is GoalState.CANCELED and not server_goal.cancel_requested.is_set():
            # No client asked: the sim's controllers ended it for a new goal of its kind.
            state, result = face.preempted()
            outcome = Outcome(state, outcome.result, outcome.message)
        match outcome.state:
            case GoalState.SUCCEEDED:
                server_goal.succeed(result)
            case GoalState.CANCELED:
                server_goal.canceled(result)
            case _:
                server_goal.abort(result)
        log.info(
            "%s goal %s %s: %s",
            face.name,
            server_goal.goal_id.hex()[:8],
            outcome.state.value,
            outcome.message or "done",
        )

    # Reports, on the sim thread

    def _picture(self, stamp: float) -> None:
        """The camera's picture at the detector's resolution: where things stand read here, on the sim
        thread; rendered and encoded by the renderer process and published from its thread. One still
        waiting to be drawn is replaced by this one rather than queued."""

        def publish(picture: Picture | None) -> None:
            if picture is None:
                return  # the renderer is gone: it said so when it went
            try:
                self._camera.put(messages.compressed_image(self.types, picture.png, stamp))
            except Exception:
                log.exception("no camera picture published")

        self.renderer.picture(self.sim.scene.poses(stamp), 1, publish)

    @staticmethod
    def _report(publisher: RosPublisher, make: Callable[[float], Any]) -> Callable[[float], None]:
        """A report for the sim thread: the message made for a wall-clock stamp and published; a
        failure (a session closing) is the loop's to log (SimLoop._publish), never stopping the
        thread, and holds back systemd's watchdog while it lasts."""

        def publish(stamp: float) -> None:
            publisher.put(make(stamp))

        return publish

    # The sim thread

    def run(self, stop: threading.Event, keepalive: Callable[[], None] = lambda: None) -> None:
        """Step physics paced to wall time x realtime_factor, publish, obey the stops, until `stop`."""
        self.loop.run(stop, keepalive)

    def close(self) -> None:
        """After run(): wait (bounded) for the goals the shutdown aborted to report it; stop the renderer."""
        deadline = time.monotonic() + CLOSE_TIMEOUT
        while any(goal.active for server in self.servers for goal in server.goals) and time.monotonic() < deadline:
            time.sleep(0.02)  # polling goal threads finishing, bounded by CLOSE_TIMEOUT
        self.renderer.close()
