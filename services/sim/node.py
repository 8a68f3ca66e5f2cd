"""The simulator on Zenoh: one thread owns pybullet; actions, cmd_vel and the heartbeat feed it."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from schemas import keys
from schemas.common import Pose2D
from schemas.robot import (
    MAX_PROBLEMS,
    FollowJointTrajectoryGoal,
    NavigateToPoseGoal,
    RobotDiagnostics,
    RobotProblem,
    Twist,
)
from schemas.safety import SafetyStatus
from schemas.world import CameraImage, Empty
from services.actionlib import ActionServer, GoalHandle, Outcome
from services.repeats import Problems
from services.robotlink import LinkGuard, Verifier
from services.robotrules import PREEMPT_TIMEOUT, HeartbeatGuard, KeepOut
from services.runtime import Node
from services.sim.config import SimConfig
from services.sim.controllers import Controllers
from services.sim.loop import ANSWER_TIMEOUT, Command, Report, SimLoop
from services.sim.renderer import Renderer
from services.sim.simulation import Simulation
from services.sim.world import Motion

log = logging.getLogger(__name__)

# robot/camera/image waits this long for the renderer (a 320 x 240 picture takes 0.1 to 0.5 s on a
# busy machine), within the MCP camera tool's 5 s.
PICTURE_TIMEOUT = 4.0
# robot/diagnostics lists the refusals seen in this many seconds.
DIAGNOSTICS_WINDOW = 60.0

Execute = Callable[[GoalHandle[Any, Any]], Outcome[Any]]


def _always(_goal: object) -> bool:
    return True


def _never(_goal: object) -> bool:
    return False


def _unplaced(goal: NavigateToPoseGoal) -> bool:
    return goal.start is None


class SimNode:
    """Binds a Simulation's controllers, sensors and world to the robot keys.

    Call run() on the thread that should own pybullet.
    """

    def __init__(self, node: Node, sim: Simulation, config: SimConfig, *, robot_key: bytes) -> None:
        self.node = node
        self.sim = sim
        self.config = config
        self.guard = HeartbeatGuard(
            config.heartbeat_timeout, config.first_heartbeat_wait, max_age=config.heartbeat_max_age
        )
        # Commands and heartbeats count only with safety's MAC (services/robotlink.py): anything else
        # is dropped and reported on robot/diagnostics; a forged heartbeat is no heartbeat.
        self.link = LinkGuard(Verifier(robot_key))
        # Its own check of the world's keep-out zones, also for a signed command (docs/robot.md).
        self.keep_out = KeepOut.of(sim.world)
        self.problems = Problems()
        sim.controllers.route_check = self._route_refusal
        self._cmd_vel_lock = threading.Lock()
        self._cmd_vel: tuple[Twist, float] | None = None  # the latest, until the sim thread applies it
        self._blocked_reason: str | None = "no safety heartbeat received yet"  # as of the sim thread's last look
        self._joint_states = node.publisher(keys.JOINT_STATES)
        self._odom = node.publisher(keys.ODOM)
        self._objects = node.publisher(keys.OBJECTS)
        self._humans = node.publisher(keys.HUMANS)
        # What only the sim feels (a collision, an object dropped), reported to safety's incident memory.
        incidents = node.publisher(keys.INCIDENT_REPORT)
        sim.faults.report = incidents.put
        # The camera renders and detects in a process of its own, never on the sim thread.
        self.renderer = Renderer(sim.world, config.camera)
        reports = (
            Report("joint_states", config.joint_states_hz, self._publish_joint_states, while_catching_up=True),
            Report("odom", config.odom_hz, self._publish_odom, while_catching_up=True),
            Report("objects", config.objects_hz, self._publish_objects),
            Report("humans", config.humans_hz, self._publish_humans),
        )
        self.loop = SimLoop(sim, config.realtime_factor, self._obey, reports)
        # A new goal preempts the running one of its action: the old goal ends (canceled, "preempted
        # by goal <id>") before the new one is accepted, so two never drive at once. A ROS 2 backend
        # does the same by canceling the old goal and waiting for its result before sending the new.
        self.servers: list[ActionServer[Any, Any, Any]] = [
            ActionServer(
                node,
                action,
                self._run_goal(start),
                accept=accept,
                preempts=_always,
                preempt_timeout=PREEMPT_TIMEOUT,
                verify=self.link,
                accept_waits=waits,
            )
            # Only a navigation goal safety did not fill `start` in for waits: for the sim thread's pose.
            for action, start, accept, waits in (
                (keys.ROBOT_NAVIGATE, Controllers.navigate, self._accept_navigation, _unplaced),
                (keys.ROBOT_TRAJECTORY, Controllers.follow_trajectory, self._accept_trajectory, _never),
                (keys.ROBOT_GRIPPER, Controllers.gripper, self._accept, _never),
            )
        ]
        node.subscribe(keys.HEARTBEAT, self._on_heartbeat, verify=self.link)
        node.subscribe(keys.ROBOT_CMD_VEL, self._on_cmd_vel, verify=self.link)
        node.serve(keys.ROBOT_DIAGNOSTICS, self._on_diagnostics, inline=True)
        node.serve(keys.GROUND_TRUTH, self.loop.ground_truth)
        node.serve(keys.SIM_MOVE, self.loop.move)
        node.serve(keys.SIM_FAULT, self.loop.fault)
        node.serve(keys.CAMERA_IMAGE, self._on_camera_image)

    # Safety: fail closed (services/robotrules.py)

    def _on_heartbeat(self, status: SafetyStatus) -> None:
        self.guard.heard(status)

    def safety_block(self) -> str | None:
        """Why the robot must stay still right now, or None when safety says it may move."""
        return self.guard.block()

    def _accept(self, _goal: object) -> str | None:
        return self.guard.accept()

    def _accept_navigation(self, goal: NavigateToPoseGoal) -> str | None:
        if (reason := self._accept(goal)) is not None:
            return reason
        # From where safety checked it (the sim refuses it if the base stands elsewhere), else from here.
        here = None
        if goal.start is None:
            here = self.loop.ask(lambda sim: sim.scene.robot.base_pose(), ANSWER_TIMEOUT, changes=False)
        return self._route_refusal(goal, here)

    def _route_refusal(self, goal: NavigateToPoseGoal, here: Pose2D | None) -> str | None:
        """Why the route of `goal` from `here` (its `start` when given) would enter a keep-out zone, noted for
        robot/diagnostics, or None. Also for a route the sim thread plans once the base came to rest."""
        if (reason := self.keep_out.goal(goal, here)) is not None:
            self.problems.note(f"refused a navigate_to_pose goal: {reason}", keys.ROBOT_NAVIGATE.path)
        return reason

    def _accept_trajectory(self, goal: FollowJointTrajectoryGoal) -> str | None:
        return self._accept(goal) or self.sim.controllers.arm.check_trajectory(goal)

    def _obey(self) -> str | None:
        """On the sim thread: stop everything when safety goes quiet or latches; otherwise move at
        the speed scale the heartbeat allows (0 pauses goals without ending them). Why the robot
        must stay still, or None."""
        now = self.guard.poll()
        self._blocked_reason = now.blocked
        if now.blocked is None and now.status is not None:
            self.sim.controllers.set_speed_scale(
                now.status.speed_scale, now.status.max_linear_speed, now.status.max_angular_speed
            )
        else:
            # While blocked the scale is 0 too, so nothing moves until a heartbeat says how fast it may.
            self.sim.controllers.set_speed_scale(0.0)
        if now.stopped:
            assert now.blocked is not None
            self.sim.controllers.stop(now.blocked)
            for server in self.servers:
                server.abort_all(now.blocked)
        return now.blocked

    # Inputs

    def _on_cmd_vel(self, twist: Twist) -> None:
        reason = self.safety_block()
        if reason is not None:
            log.debug("ignored cmd_vel: %s", reason)
            return
        hold_for = self.config.cmd_vel_timeout * self.config.realtime_factor
        # Only the latest twist waits for the sim thread: one that a newer replaces before that thread
        # gets to it would never have driven the base (the newer overrides it before the next step),
        # so a fast stream (1 kHz) cannot pile up keep-out checks ahead of physics and odometry.
        with self._cmd_vel_lock:
            waiting, self._cmd_vel = self._cmd_vel is not None, (twist, hold_for)
        if not waiting:
            self.submit(self._apply_latest_cmd_vel)

    def _apply_latest_cmd_vel(self, sim: Simulation) -> None:
        with self._cmd_vel_lock:
            latest, self._cmd_vel = self._cmd_vel, None
        if latest is not None:
            self._apply_cmd_vel(sim, *latest)

    def _apply_cmd_vel(self, sim: Simulation, twist: Twist, hold_for: float) -> None:
        if self._blocked_reason is not None:
            return
        if reason := self.keep_out.drive(sim.scene.robot.base_pose(), twist.linear_x, twist.angular_z, hold_for):
            # Dropped: what the base holds now was checked when it came, and ends before any zone.
            self.problems.note(f"refused a cmd_vel: {reason}", keys.ROBOT_CMD_VEL.path)
            return
        if not sim.controllers.set_cmd_vel(twist, hold_for):
            log.info("ignored cmd_vel while a navigate_to_pose goal runs")

    def submit(self, command: Command) -> None:
        """Run `command` on the sim thread."""
        self.loop.submit(command)

    def _on_diagnostics(self, _request: Empty) -> RobotDiagnostics:
        seen = self.link.problems(DIAGNOSTICS_WINDOW) + self.problems.recent(DIAGNOSTICS_WINDOW)
        seen = sorted(seen, key=lambda problem: -problem[1])[:MAX_PROBLEMS]
        problems = [RobotProblem(text=text, last_seen=at) for text, at in seen]
        return RobotDiagnostics(
            stamp=time.time(), backend=self.node.service, window=DIAGNOSTICS_WINDOW, problems=problems
        )

    def _on_camera_image(self, _request: Empty) -> CameraImage:
        # Where things stand read on the sim thread; rendered and encoded by the renderer process.
        poses = self.loop.answer(lambda sim: sim.scene.poses(time.time()), changes=False)
        return self.renderer.camera_image(poses, scale=2, timeout=PICTURE_TIMEOUT)

    # Goals

    def _run_goal(self, start: Callable[[Controllers, Any], Motion[Any, Any]]) -> Execute:
        """An ActionServer execute callback: the goal's motion carried out on the sim thread (SimLoop.relay)."""

        def execute(handle: GoalHandle[Any, Any]) -> Outcome[Any]:
            return self.loop.relay(lambda controllers: start(controllers, handle.goal), handle)

        return execute

    # The sim thread

    def run(self, stop: threading.Event, keepalive: Callable[[], None] = lambda: None) -> None:
        """Step physics paced to wall time x realtime_factor, publish, and obey safety, until `stop`."""
        self.loop.run(stop, keepalive)

    def _publish_joint_states(self, stamp: float) -> None:
        self._joint_states.put(self.sim.sensors.joint_state(stamp))

    def _publish_odom(self, stamp: float) -> None:
        self._odom.put(self.sim.sensors.odometry(stamp))

    def _publish_objects(self, stamp: float) -> None:
        # Published from the renderer's thread once detected; a frame it is still busy with is not queued.
        self.renderer.detect(self.sim.scene.poses(stamp), self._objects.put)

    def _publish_humans(self, stamp: float) -> None:
        self._humans.put(self.sim.sensors.perceived_humans(stamp))

    def close(self) -> None:
        for server in self.servers:
            server.abort_all("the simulator is shutting down")
        self.renderer.close()
