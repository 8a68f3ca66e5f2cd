"""The simulator on Zenoh: one thread owns pybullet; actions, cmd_vel and the heartbeat feed it."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

from schemas import keys
from schemas.actions import GoalState
from schemas.common import ErrorKind, ServiceError
from schemas.robot import FollowJointTrajectoryGoal, Twist
from schemas.safety import SafetyStatus
from schemas.world import CameraImage, Empty, GroundTruth, MoveEntity, MoveReply
from services.actionlib import ActionServer, GoalHandle, Outcome
from services.errors import CallError
from services.runtime import Node
from services.sim.camera import png_base64
from services.sim.config import SimConfig
from services.sim.controllers import Controllers
from services.sim.simulation import Simulation
from services.sim.world import SETTLE_TIMEOUT, Drop, Motion

log = logging.getLogger(__name__)

T = TypeVar("T")
Command = Callable[[Simulation], None]
Execute = Callable[[GoalHandle[Any, Any]], Outcome[Any]]

FEEDBACK_PERIOD = 0.1  # wall seconds
START_TIMEOUT = 5.0
ANSWER_TIMEOUT = 2.0
# A goal arriving while the e-stop shows latched waits this long for a newer heartbeat (a reset).
RESET_GRACE = 0.1
# A preempting goal waits this long for the running one to end. With the waits in accepting it
# (RESET_GRACE, twice: before and after), send_goal answers well within safety's forward_timeout
# (5 s), so safety never reports a forward failed that the sim then runs. docs/robot.md, Timing.
PREEMPT_TIMEOUT = 2.0
# If the sim falls this far behind the wall clock (sim seconds), it stops trying to catch up.
MAX_LAG = 0.5


def _always(_goal: object) -> bool:
    return True


class SimNode:
    """Binds a Simulation's controllers, sensors and world to the robot keys.

    Call run() on the thread that should own pybullet.
    """

    def __init__(self, node: Node, sim: Simulation, config: SimConfig) -> None:
        self.node = node
        self.sim = sim
        self.config = config
        self._commands: queue.SimpleQueue[Command] = queue.SimpleQueue()
        self._wake = threading.Event()
        self._lock = threading.Lock()
        self._beat = threading.Condition(self._lock)
        self._heartbeat: SafetyStatus | None = None
        self._heartbeat_at = 0.0
        self._first_heartbeat = threading.Event()
        self._blocked_reason: str | None = "no safety heartbeat received yet"
        self._joint_states = node.publisher(keys.JOINT_STATES)
        self._odom = node.publisher(keys.ODOM)
        self._objects = node.publisher(keys.OBJECTS)
        self._humans = node.publisher(keys.HUMANS)
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
            )
            for action, start, accept in (
                (keys.ROBOT_NAVIGATE, Controllers.navigate, self._accept),
                (keys.ROBOT_TRAJECTORY, Controllers.follow_trajectory, self._accept_trajectory),
                (keys.ROBOT_GRIPPER, Controllers.gripper, self._accept),
            )
        ]
        node.subscribe(keys.HEARTBEAT, self._on_heartbeat)
        node.subscribe(keys.ROBOT_CMD_VEL, self._on_cmd_vel)
        node.serve(keys.GROUND_TRUTH, self._on_ground_truth)
        node.serve(keys.SIM_MOVE, self._on_move)
        node.serve(keys.CAMERA_IMAGE, self._on_camera_image)

    # Safety: fail closed

    def _on_heartbeat(self, status: SafetyStatus) -> None:
        with self._beat:
            self._heartbeat, self._heartbeat_at = status, time.monotonic()
            self._beat.notify_all()
        self._first_heartbeat.set()

    def _next_heartbeat(self, timeout: float) -> None:
        """Wait (bounded) until a heartbeat newer than the latest arrives."""
        with self._beat:
            latest = self._heartbeat
            self._beat.wait_for(lambda: self._heartbeat is not latest, timeout)

    def safety_block(self) -> str | None:
        """Why the robot must stay still right now, or None when safety says it may move."""
        with self._lock:
            status, at = self._heartbeat, self._heartbeat_at
        if status is None:
            return "no safety heartbeat received yet"
        age = time.monotonic() - at
        if age > self.config.heartbeat_timeout:
            return f"no safety heartbeat for {age * 1000:.0f} ms"
        if status.estop.latched:
            return f"e-stop latched by {status.estop.source or 'unknown'}: {status.estop.reason or 'no reason given'}"
        return None

    def _accept(self, _goal: object) -> str | None:
        # Never moves without a heartbeat: this only waits (bounded) for the first one to arrive.
        self._first_heartbeat.wait(self.config.first_heartbeat_wait)
        reason = self.safety_block()
        with self._lock:
            latched = self._heartbeat is not None and self._heartbeat.estop.latched
        if latched:
            # Safety announces a reset with a heartbeat before it approves anything, but a goal it
            # approved right after can overtake that heartbeat on the way here: hear one more.
            self._next_heartbeat(RESET_GRACE)
            reason = self.safety_block()
        return reason

    def _accept_trajectory(self, goal: FollowJointTrajectoryGoal) -> str | None:
        return self._accept(goal) or self.sim.controllers.arm.check_trajectory(goal)

    def _enforce_safety(self) -> None:
        """On the sim thread: stop everything when safety goes quiet or latches; otherwise move at
        the speed scale the heartbeat allows (0 pauses goals without ending them)."""
        reason = self.safety_block()
        was_blocked = self._blocked_reason is not None
        self._blocked_reason = reason
        with self._lock:
            status = self._heartbeat
        if reason is None and status is not None:
            scale = status.speed_scale
            if not was_blocked:
                self._log_speed_change(
                    self.sim.controllers.speed_scale, scale, status.speed_reason or "no reason given"
                )
            self.sim.controllers.set_speed_scale(scale, status.max_linear_speed, status.max_angular_speed)
        else:
            # While blocked the scale is 0 too, so nothing moves until a heartbeat says how fast it may.
            scale = 0.0
            self.sim.controllers.set_speed_scale(scale)
        if reason is not None and not was_blocked:
            log.warning("stopping the robot: %s", reason)
            self.sim.controllers.stop(reason)
            for server in self.servers:
                server.abort_all(reason)
        elif reason is None and was_blocked:
            log.info("safety heartbeat present and e-stop clear: the robot may move at %.2f of full speed", scale)

    @staticmethod
    def _log_speed_change(previous: float, scale: float, why: str) -> None:
        if scale == previous:
            return
        if scale == 0.0:
            log.info("pausing motion, goals kept: speed scale 0 (%s)", why)
        elif previous == 0.0:
            log.info("resuming at speed scale %.2f (%s)", scale, why)
        else:
            log.debug("speed scale %.2f (%s)", scale, why)

    # Inputs

    def _on_cmd_vel(self, twist: Twist) -> None:
        reason = self.safety_block()
        if reason is not None:
            log.debug("ignored cmd_vel: %s", reason)
            return
        hold_for = self.config.cmd_vel_timeout * self.config.realtime_factor
        self.submit(lambda sim: self._apply_cmd_vel(sim, twist, hold_for))

    def _apply_cmd_vel(self, sim: Simulation, twist: Twist, hold_for: float) -> None:
        if self._blocked_reason is None and not sim.controllers.set_cmd_vel(twist, hold_for):
            log.info("ignored cmd_vel while a navigate_to_pose goal runs")

    def submit(self, command: Command) -> None:
        """Run `command` on the sim thread."""
        self._commands.put(command)
        self._wake.set()

    def _ask(self, query: Callable[[Simulation], T], timeout: float) -> T | None:
        """Run `query` on the sim thread and wait for its value; None if the thread does not answer."""
        box: list[T] = []
        answered = threading.Event()

        def run(sim: Simulation) -> None:
            try:
                box.append(query(sim))
            finally:
                answered.set()

        self.submit(run)
        answered.wait(timeout)
        return box[0] if box else None

    def _answer(self, query: Callable[[Simulation], T]) -> T:
        """`query`'s value from the sim thread, for a queryable: an unavailable error if it does not answer."""
        value = self._ask(query, ANSWER_TIMEOUT)
        if value is None:
            message = f"the simulator did not answer within {ANSWER_TIMEOUT:g} s"
            raise CallError(ServiceError(kind=ErrorKind.UNAVAILABLE, message=message))
        return value

    def _on_ground_truth(self, _request: Empty) -> GroundTruth:
        return self._answer(lambda sim: sim.scene.ground_truth())

    def _on_camera_image(self, _request: Empty) -> CameraImage:
        # Rendered on the sim thread (pybullet is not thread-safe); encoded here, off it.
        pixels = self._answer(lambda sim: sim.sensors.camera_picture())
        return CameraImage(stamp=time.time(), width=pixels.shape[1], height=pixels.shape[0], data=png_base64(pixels))

    def _on_move(self, request: MoveEntity) -> MoveReply:
        moved = self._answer(lambda sim: sim.scene.move(request))
        if not isinstance(moved, Drop):
            return moved
        # The object falls and comes to rest while the sim thread keeps stepping (and obeying safety).
        if not moved.done.wait(SETTLE_TIMEOUT / self.config.realtime_factor + ANSWER_TIMEOUT):
            message = f"{request.id} was moved but the simulator did not report it at rest"
            raise CallError(ServiceError(kind=ErrorKind.TIMEOUT, message=message))
        assert moved.result is not None
        return moved.result

    # Goals

    def _run_goal(self, start: Callable[[Controllers, Any], Motion[Any, Any]]) -> Execute:
        """An ActionServer execute callback: start the motion on the sim thread, relay feedback, wait."""

        def execute(handle: GoalHandle[Any, Any]) -> Outcome[Any]:
            lock = threading.Lock()
            abandoned = False  # set under `lock` when the wait for `begin` gives up
            # What begin did: the motion it started, why it refused, or None when it did not start
            # one because the goal was to stop first.
            started: list[Motion[Any, Any] | str | None] = []
            answered = threading.Event()

            def begin(sim: Simulation) -> None:
                try:
                    with lock:
                        if abandoned:
                            return  # its waiter gave up: started now, no cancel could reach it
                        self._enforce_safety()  # as of the latest heartbeat, not the last step's
                        if handle.should_stop:
                            started.append(None)
                        else:
                            started.append(self._blocked_reason or start(sim.controllers, handle.goal))
                finally:
                    answered.set()

            if handle.should_stop:
                return self._ended_before_start(handle)
            self.submit(begin)
            answered.wait(START_TIMEOUT)
            with lock:
                if not started:
                    abandoned = True
                    return Outcome(GoalState.ABORTED, None, "the simulator did not start the goal")
            motion = started[0]
            if motion is None:
                return self._ended_before_start(handle)
            if isinstance(motion, str):
                return Outcome(GoalState.ABORTED, None, motion)
            cancel_sent = False
            while True:
                if handle.should_stop and not cancel_sent:
                    cancel_sent = True
                    self.submit(self._canceller(motion, handle.abort_reason))
                if motion.done.wait(FEEDBACK_PERIOD):
                    break
                if motion.feedback is not None:
                    handle.feedback(motion.feedback)
            return Outcome(motion.state, motion.result, motion.message)

        return execute

    @staticmethod
    def _ended_before_start(handle: GoalHandle[Any, Any]) -> Outcome[Any]:
        """A goal canceled (or aborted) before it started: it never moved."""
        if handle.abort_reason:
            return Outcome(GoalState.ABORTED, None, handle.abort_reason)
        return Outcome(GoalState.CANCELED, None, "canceled before it started")

    @staticmethod
    def _canceller(motion: Motion[Any, Any], abort_reason: str) -> Command:
        """Ends `motion` as aborted (safety, shutdown) when there is a reason, else as canceled."""
        if abort_reason:
            return lambda sim: sim.controllers.cancel(motion, GoalState.ABORTED, abort_reason)
        return lambda sim: sim.controllers.cancel(motion, GoalState.CANCELED, "canceled")

    # The sim thread

    def run(self, stop: threading.Event) -> None:
        """Step physics paced to wall time x realtime_factor, publish, and obey safety, until `stop`."""
        sim, config = self.sim, self.config
        factor = config.realtime_factor
        wall_start, sim_start = time.monotonic(), sim.sim_time
        due = {"joint_states": 0.0, "odom": 0.0, "objects": 0.0, "humans": 0.0}
        periods = {
            "joint_states": 1.0 / config.joint_states_hz,
            "odom": 1.0 / config.odom_hz,
            "objects": 1.0 / config.objects_hz,
            "humans": 1.0 / config.humans_hz,
        }
        try:
            while not stop.is_set():
                self._drain()
                self._enforce_safety()
                now = time.monotonic()
                target = sim_start + (now - wall_start) * factor
                if target - sim.sim_time > MAX_LAG:
                    log.warning(
                        "simulation is %.2f s behind the wall clock; dropping the backlog", target - sim.sim_time
                    )
                    wall_start, sim_start = now, sim.sim_time
                    target = sim.sim_time
                while sim.sim_time + sim.dt <= target and not stop.is_set():
                    sim.step()
                    self._drain()
                    self._enforce_safety()
                    # Also while catching up: on a busy machine physics runs behind, but odometry
                    # and joint states must keep coming, or safety's watchdog sees a silent robot.
                    # Not objects: each renders a camera frame (about 20 ms), slowing the catch-up.
                    self._publish(due, periods, only=("odom", "joint_states"))
                self._publish(due, periods)
                next_step = wall_start + (sim.sim_time + sim.dt - sim_start) / factor
                self._wake.wait(max(0.0, min(next_step - time.monotonic(), 0.05)))
                self._wake.clear()
        finally:
            sim.controllers.stop("the simulator is shutting down")
            self._drain()

    def _drain(self) -> None:
        while True:
            try:
                command = self._commands.get_nowait()
            except queue.Empty:
                return
            try:
                command(self.sim)
            except Exception:
                log.exception("sim command failed")

    def _publish(self, due: dict[str, float], periods: dict[str, float], only: tuple[str, ...] = ()) -> None:
        """Publish what is due; only the reports named in `only`, when given."""
        now = time.monotonic()
        stamp = time.time()
        for name, period in periods.items():
            if now < due[name] or (only and name not in only):
                continue
            # On the schedule, so a late wake-up does not stretch every later period; after a
            # stall longer than a period it starts afresh rather than publishing the backlog.
            scheduled = due[name] + period
            due[name] = scheduled if scheduled > now else now + period
            if name == "joint_states":
                self._joint_states.put(self.sim.sensors.joint_state(stamp))
            elif name == "odom":
                self._odom.put(self.sim.sensors.odometry(stamp))
            elif name == "objects":
                self._objects.put(self.sim.sensors.perceived_objects(stamp))
            else:
                self._humans.put(self.sim.sensors.perceived_humans(stamp))

    def close(self) -> None:
        for server in self.servers:
            server.abort_all("the simulator is shutting down")
