"""Tether goals carried out as ROS 2 goals: sent, paused, re-timed, resumed, canceled, checked. No Zenoh here.

A GoalRun drives one tether goal (actionlib's GoalHandle, as TetherGoal) through one or more goals
on the robot's action servers (rmw's action clients as RosAction, adapted by node.py): sent once
safety allows motion, paused at speed scale 0 by canceling (the robot holds), resumed by sending the
rest, re-timed when the scale changes (trajectories), and checked against what the robot reports
(the route safety checked, odometry, deadlines).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from schemas.actions import GoalState
from schemas.common import Pose2D
from schemas.robot import (
    FollowJointTrajectoryFeedback,
    FollowJointTrajectoryGoal,
    FollowJointTrajectoryResult,
    GripperCommandFeedback,
    GripperCommandGoal,
    GripperCommandResult,
    JointState,
    NavigateToPoseFeedback,
    NavigateToPoseGoal,
    NavigateToPoseResult,
    Odometry,
)
from services.footprint import TRACKING_TOLERANCE, Leg, route_legs, turn_angle
from services.robotrules import FEEDBACK_PERIOD, SafetyNow, away_from
from services.ros2.backend import (
    NAV2_NO_REASON,
    TRAJECTORY_SETTLE,
    BaseLimits,
    Messages,
    RobotCallFailed,
    RobotGoalForgotten,
    RobotGoalUnanswered,
    RobotLinkClosed,
    RobotRefused,
    RobotState,
    UnsendableGoal,
    gripper_error,
    gripper_gap,
    navigation_error,
    ros_failure,
    trajectory_error,
)
from services.ros2.wire import GoalStatus
from services.worldmodel import drive_route

log = logging.getLogger(__name__)

# Goal runs look at the robot this often (wall seconds).
POLL = 0.02
# get_result is a long query, asked again when it times out.
RESULT_POLL = 10.0
# A trajectory re-timed for a lower speed scale at once; for a higher one at most this often.
RETIME_PERIOD = 1.0
# A trajectory point sent after the trajectory's end (a pause in its settle) is reached over this long.
MIN_SEGMENT = 0.1
# The arm controller gets the goal's time plus its settle plus this (trajectory seconds) to finish.
TRAJECTORY_GRACE = 5.0
GRIPPER_DEADLINE = 5.0  # seconds unpaused
SETTLED_SPEED = 0.05  # m/s, rad/s: the base counts as at rest
REST_TIMEOUT = 3.0  # a navigation without `start` waits this long for a rolling base to come to rest
PROGRESS_STEP = 0.01  # metres (or radians, weighted) of progress that count
# A tracked phase within this of the best-matching one is kept, so the tracker moves on only once
# the base is clearly doing the next thing.
PHASE_HYSTERESIS = 0.005
FRESH_REPORT_WAIT = 0.2  # a result waits this long for a report from after it
# A navigation ends this close to its goal pose (metres, radians; docs/robot.md): Nav2 saying it
# arrived farther off (a goal checker looser than this, or a robot that is wrong) ends it aborted.
ARRIVAL_DISTANCE = 0.05
ARRIVAL_YAW = 0.05
# A cancel the robot did not confirm is asked again this often (wall seconds) until the goal ends.
CANCEL_RETRY = 0.5
# A goal whose send_goal went unanswered is canceled by its id for the goal timeout plus this.
UNANSWERED_MARGIN = 2.0
TERMINAL = (GoalStatus.SUCCEEDED, GoalStatus.CANCELED, GoalStatus.ABORTED)


# Ports: what the goal runs need of rmw.py (node.py adapts it) and of the tether action server.


class RosGoal(Protocol):
    """A goal the robot accepted (rmw.RosClientGoal, its errors as RobotCallFailed)."""

    @property
    def status(self) -> int: ...

    def result(self, timeout: float) -> tuple[int, Any]: ...

    def cancel(self, timeout: float) -> bool:
        """Ask the robot to cancel the goal; True when its action server answers that the goal had
        ended already, or that it knows no such goal (a goal it is canceling is not over yet)."""
        ...

    def forget(self) -> None:
        """Stop following the goal (its status and feedback): it is over, or no longer ours to follow."""


class RosAction(Protocol):
    """One of the robot's action servers (rmw.RosActionClient, its errors as RobotCallFailed; a
    send_goal that got no usable answer raises RobotGoalUnanswered, naming the goal's id)."""

    name: str

    def send_goal(self, goal: Any, *, timeout: float) -> RosGoal: ...

    def cancel(self, goal_id: bytes, timeout: float) -> bool:
        """Cancel the goal of this id; True when the robot is canceling it or it had ended."""
        ...


class TetherGoal(Protocol):
    """The tether goal being carried out (actionlib.GoalHandle)."""

    @property
    def goal(self) -> Any: ...

    @property
    def should_stop(self) -> bool: ...

    @property
    def abort_reason(self) -> str: ...

    def feedback(self, message: Any) -> None: ...


# Following a route from odometry


class RouteTracker:
    """Where the base is along the legs safety checked (services/footprint.route_legs), from
    odometry alone, and how far its footprint strays from their sweeps (as the sim measures it:
    turning, the centre's distance from the point it turns at; driving, the centre's distance from
    the leg plus the corners turned off the leg's heading).

    The route is a sequence of phases: turn at each leg's start, drive the leg, and at the end turn
    to the goal's yaw. The tracker moves on to a later phase (up to two ahead) once that one
    explains the pose clearly better, and never goes back.
    """

    def __init__(self, legs: Sequence[Leg], start: Pose2D, goal: Pose2D, base_radius: float) -> None:
        self.legs = list(legs)
        self.start = start
        self.goal = goal
        self.base_radius = base_radius
        self.phases: list[tuple[str, int]] = [p for i in range(len(self.legs)) for p in (("turn", i), ("drive", i))]
        self.phases.append(("final", len(self.legs)))
        self.phase = 0

    def _point(self, index: int) -> tuple[float, float]:
        if index < len(self.legs):
            return self.legs[index].start
        return self.legs[-1].end if self.legs else (self.start.x, self.start.y)

    def _along(self, leg: Leg, pose: Pose2D) -> tuple[float, float]:
        (ax, ay), (bx, by) = leg.start, leg.end
        tx, ty = (bx - ax) / leg.length, (by - ay) / leg.length
        dx, dy = pose.x - ax, pose.y - ay
        return dx * tx + dy * ty, dx * -ty + dy * tx

    def _stray(self, phase: tuple[str, int], pose: Pose2D) -> float:
        kind, index = phase
        if kind != "drive":
            return math.dist((pose.x, pose.y), self._point(index))
        leg = self.legs[index]
        s, e = self._along(leg, pose)
        beyond = max(0.0, -s, s - leg.length)
        return math.hypot(e, beyond) + self.base_radius * abs(turn_angle(pose.yaw, leg.heading))

    def update(self, pose: Pose2D) -> float:
        """Follow the base to `pose`; how far its footprint strays from the route there."""
        window = range(self.phase, min(self.phase + 3, len(self.phases)))
        strays = {k: self._stray(self.phases[k], pose) for k in window}
        best = min(strays.values())
        self.phase = next(k for k in window if strays[k] <= best + PHASE_HYSTERESIS)
        return strays[self.phase]

    def remaining(self, pose: Pose2D) -> float:
        """How far the base still has to drive (metres)."""
        kind, index = self.phases[self.phase]
        if kind == "final":
            return 0.0
        along = self._along(self.legs[index], pose)[0] if kind == "drive" else 0.0
        return max(0.0, self.legs[index].length - along) + sum(leg.length for leg in self.legs[index + 1 :])

    def progress(self, pose: Pose2D) -> float:
        """What is left to do: distance plus the turn to the goal's yaw at the end (weighted)."""
        kind, _ = self.phases[self.phase]
        turn = abs(turn_angle(pose.yaw, self.goal.yaw)) if kind == "final" else 0.0
        return self.remaining(pose) + 0.3 * turn

    def rest(self) -> list[Pose2D]:
        """The poses still to drive through, the goal last: what to send again after a pause. The
        same legs from where the base stopped on the current one."""
        _, index = self.phases[self.phase]
        points = [Pose2D(x=leg.end[0], y=leg.end[1], yaw=leg.heading) for leg in self.legs[index:-1]]
        return [*points, self.goal]


# Re-timing trajectories


class TrajectoryPlan:
    """A trajectory goal on its own clock (trajectory seconds): where the joints should be at each
    time, and the rest of it re-timed for a speed scale (its clock advancing at the scale), so the
    arm keeps the path, slower."""

    def __init__(self, goal: FollowJointTrajectoryGoal, current: Sequence[float]) -> None:
        """`current`: the goal's joints where they are now, the point at time 0 when the first is later."""
        self.goal = goal
        times = [p.time_from_start for p in goal.points]
        positions = [list(p.positions) for p in goal.points]
        if times[0] > 0.0:
            times.insert(0, 0.0)
            positions.insert(0, list(current))
        self.times = np.array(times)
        self.positions = np.array(positions)
        self.final = self.positions[-1]

    @property
    def end(self) -> float:
        return float(self.times[-1])

    def desired(self, t: float) -> list[float]:
        if t >= self.end:
            return self.final.tolist()
        k = int(np.searchsorted(self.times, t, side="right")) - 1
        span = self.times[k + 1] - self.times[k]
        if span <= 0.0:
            return self.positions[k + 1].tolist()
        blend = (t - self.times[k]) / span
        return (self.positions[k] + blend * (self.positions[k + 1] - self.positions[k])).tolist()

    def first(self, scale: float) -> list[tuple[list[float], float]]:
        """The goal's own points, re-timed for `scale`."""
        return [(list(p.positions), p.time_from_start / scale) for p in self.goal.points]

    def rest(self, t: float, scale: float) -> list[tuple[list[float], float]]:
        """The points after trajectory time `t`, re-timed for `scale`, from where the arm holds now;
        past the end, the last point (the arm settles onto it)."""
        later = [k for k in range(len(self.times)) if self.times[k] > t]
        if not later:
            return [(self.final.tolist(), MIN_SEGMENT)]
        return [(self.positions[k].tolist(), float(self.times[k] - t) / scale) for k in later]


# Goal runs


@dataclass(frozen=True)
class Ending:
    """How a tether goal ended: the state, its result, a message for people."""

    state: GoalState
    result: Any = None
    message: str = ""


@dataclass
class RunContext:
    """What every goal run needs: safety's word, the robot's reports, timeouts, and a way to stop the base."""

    safety: Callable[[], SafetyNow]
    robot: RobotState
    goal_timeout: float
    cancel_timeout: float
    halt_base: Callable[[], None]
    # Whether the robot has been told it may move (emergency_stop false went out after the last
    # block): a goal sent before would find the robot's own stop still set and be rejected.
    robot_released: Callable[[], bool] = lambda: True
    # Holds the robot's own stop (emergency_stop true, never released) for a reason people see,
    # until the function it returns is called: a goal the robot would not end when canceled.
    block_robot: Callable[[str], Callable[[], None]] = lambda _reason: lambda: None
    # Counts safety's stops: a goal sent while it changed is canceled at once.
    motion_epoch: Callable[[], int] = lambda: 0
    clock: Callable[[], float] = time.monotonic
    sleep: Callable[[float], None] = time.sleep


class _Flight:
    """A ROS goal the robot accepted, its result fetched on a thread of its own.

    `ended` says the fetch is over (a result, or a status saying the goal ended whose result could
    not be read); `settled` that the robot's action server itself said the goal ended: its result,
    or its answer to a cancel. Only `settled` lets the backend take the goal for over: anyone on
    the robot's network can publish its status topic, and a forged or stale one would leave it running.
    """

    def __init__(self, goal: RosGoal, label: str) -> None:
        self.goal = goal
        self.label = label
        self.ended = threading.Event()
        self.settled = threading.Event()
        # The backend left the robot's network: nothing more can be asked of the goal, so no thread waits on it.
        self.closed = threading.Event()
        self.outcome: tuple[int, Any, str] = (0, None, "")
        threading.Thread(target=self._fetch, name=f"result:{label}", daemon=True).start()

    def _fetch(self) -> None:
        try:
            self._fetch_result()
        except Exception as exc:
            # The goal may still run: the outcome says so (status UNKNOWN), and the run cancels it.
            log.exception("reading the result of the %s goal failed", self.label)
            self.outcome = (int(GoalStatus.UNKNOWN), None, f"reading its result failed: {exc!r}")
            self.ended.set()
            return
        self.goal.forget()

    def _fetch_result(self) -> None:
        while not self.settled.is_set():
            try:
                status, result = self.goal.result(RESULT_POLL)
            except RobotLinkClosed as exc:
                if not self.ended.is_set():
                    self.outcome = (int(GoalStatus.UNKNOWN), None, f"its result could not be read: {exc}")
                self.closed.set()
                self.ended.set()
                return
            except RobotGoalForgotten as exc:
                # Its own server says it has no such goal (it restarted): over, nothing there to cancel
                # or wait for. Asked on, it would answer so forever, and the emergency stop held for it never lift.
                if not self.ended.is_set():
                    self.outcome = (int(GoalStatus.UNKNOWN), None, str(exc))
                self.settled.set()
                self.ended.set()
                return
            except RobotCallFailed as exc:
                status = int(self.goal.status)
                if status in TERMINAL and not self.ended.is_set():
                    # It ended, the status topic says, but its result cannot be read: the run ends and
                    # cancels it; the result is asked for on, as only the robot's own word settles it.
                    self.outcome = (status, None, f"its result could not be read: {exc}")
                    self.ended.set()
                log.debug("no result yet for the %s goal: %s", self.label, exc)
                time.sleep(POLL * 10)
                continue
            if not self.ended.is_set():
                self.outcome = (int(status), result, "")
            if int(status) in TERMINAL:
                self.settled.set()
            self.ended.set()
            return

    def cancel(self, timeout: float) -> None:
        """Ask the robot to cancel the goal; its answer that the goal had ended already settles it."""
        try:
            if self.goal.cancel(timeout):
                self.settled.set()
        except RobotLinkClosed:
            self.closed.set()
        except RobotCallFailed as exc:
            log.warning("cancel of the %s goal failed: %s", self.label, exc)

    @property
    def result_read(self) -> bool:
        """Whether the goal's own result says it ended. Its status alone does not settle it: anyone
        on the robot's network can publish one, and a lost or forged one would leave the goal running."""
        return self.ended.is_set() and self.outcome[0] in TERMINAL and not self.outcome[2]


class GoalRun:
    """One tether goal carried out as one or more ROS goals.

    Sent once safety allows motion; relayed as feedback; paused at speed scale 0 by canceling the ROS
    goal (the robot then holds) and resumed by sending the rest; re-sent for a new scale when
    `wants_resend` says so; canceled (the ROS goal canceled and its end awaited) when the tether
    goal is canceled, preempted or aborted. A robot that rejects, aborts or never answers ends the
    goal aborted with what it said, and is left still (the ROS goal canceled, the base halted).
    Subclasses say what to send and what the robot's answer means.
    """

    label = "goal"

    def __init__(self, ctx: RunContext, action: RosAction, handle: TetherGoal) -> None:
        self.ctx = ctx
        self.action = action
        self.handle = handle
        self.sends = 0
        self.flight: _Flight | None = None  # the ROS goal the robot runs now

    # What a kind of goal provides

    def prepare(self) -> str | None:
        """Why the goal cannot start (it ends aborted, having never moved), or None."""
        return None

    def next_goal(self, scale: float) -> tuple[RosAction, Any]:
        raise NotImplementedError

    def sent(self, scale: float, now: float) -> None:
        """Just after the robot accepted a goal sent for `scale` at `now`."""

    def held(self, now: float) -> None:
        """The ROS goal was canceled at `now` to pause or re-time: the robot holds there."""

    def wants_resend(self, scale: float, now: float) -> bool:
        """Whether to cancel and send the rest again for a new speed scale (besides a pause at 0)."""
        return False

    def check(self, now: float, moving: bool, scale: float) -> str | None:
        """Why the goal must end now (aborted), or None."""
        return None

    def feedback(self, now: float) -> Any | None:
        return None

    def result_now(self) -> Any:
        raise NotImplementedError

    def succeeded(self, result: Any) -> Ending:
        return Ending(GoalState.SUCCEEDED, self.result_now(), "")

    def failure(self, status: int, result: Any, error: str) -> str:
        return ros_failure(self.label, status, error)

    def make_safe(self) -> None:
        """After a ROS goal ended badly or could not be canceled."""

    # The loop

    def run(self) -> Ending:
        """Carry the goal out; whatever goes wrong here, the ROS goal is canceled and the robot left safe."""
        try:
            return self._run()
        except Exception as exc:
            log.exception("the %s goal run failed", self.label)
            message = f"the ros2 backend failed carrying out the {self.label} goal: {exc!r}"
            try:
                if self.flight is not None and not self.flight.result_read:
                    self._cancel(self.flight)
            finally:
                self.make_safe()
            try:
                result = self.result_now()
            except Exception:
                result = None
            return Ending(GoalState.ABORTED, result, message)

    def _run(self) -> Ending:
        handle, ctx = self.handle, self.ctx
        if handle.should_stop:
            return self._stopped(None)
        problem = self.prepare()
        if handle.should_stop:
            return self._stopped(None)
        if problem:
            log.warning("%s goal refused: %s", self.label, problem)
            return Ending(GoalState.ABORTED, self.result_now(), problem)
        fed = -math.inf
        while True:
            now = ctx.clock()
            flight = self.flight
            if handle.should_stop:
                return self._stopped(flight)
            safety = ctx.safety()
            scale = safety.speed_scale
            if flight is not None and flight.ended.is_set():
                return self._ended(flight)
            if flight is None and scale > 0.0 and ctx.robot_released():
                sent = self._send(scale)
                if isinstance(sent, Ending):
                    return sent
                if sent is not None and (handle.should_stop or ctx.safety().blocked is not None):
                    # Safety stopped the robot while the goal was on its way: cancel it at once.
                    self.flight = sent
                    if handle.should_stop:
                        return self._stopped(sent)
                    if (ended := self._hold(sent, "safety stop during its send")) is not None:
                        return ended
                    sent = None
                self.flight = flight = sent
            elif flight is not None and (scale <= 0.0 or self.wants_resend(scale, now)):
                ended = self._hold(flight, "pause" if scale <= 0.0 else "re-timing")
                if ended is not None:
                    return ended
                self.flight = flight = None
            problem = self.check(now, flight is not None, scale)
            if problem:
                return self._abort(flight, problem)
            if now - fed >= FEEDBACK_PERIOD:
                fed = now
                if (message := self.feedback(now)) is not None:
                    handle.feedback(message)
            ctx.sleep(POLL)

    def _send(self, scale: float) -> _Flight | Ending | None:
        """Send the next ROS goal; None when safety stopped the robot just before (nothing sent)."""
        try:
            action, goal = self.next_goal(scale)
        except UnsendableGoal as exc:
            message = f"the {self.label} goal cannot be sent at speed scale {scale:.3g}: {exc}"
            log.warning("%s", message)
            self.make_safe()
            return Ending(GoalState.ABORTED, self.result_now(), message)
        epoch = self.ctx.motion_epoch()
        if self.handle.should_stop or self.ctx.safety().blocked is not None or not self.ctx.robot_released():
            return None
        try:
            ros_goal = action.send_goal(goal, timeout=self.ctx.goal_timeout)
        except RobotRefused as exc:
            log.warning("the robot refused the %s goal: %s", self.label, exc)
            return Ending(GoalState.ABORTED, self.result_now(), f"the robot refused the {self.label} goal ({exc})")
        except RobotCallFailed as exc:
            # It may take the goal all the same: cancel that goal (by its id, not every goal on the
            # server, which may be other clients'), and halt the base.
            log.error("the robot did not take the %s goal: %s", self.label, exc)
            if isinstance(exc, RobotGoalUnanswered):
                threading.Thread(
                    target=self._cancel_unanswered, args=(action, exc.goal_id), name="cancel-unanswered", daemon=True
                ).start()
            self.make_safe()
            message = f"the robot did not take the {self.label} goal: {exc}"
            return Ending(GoalState.ABORTED, self.result_now(), message)
        self.sends += 1
        self.sent(scale, self.ctx.clock())
        flight = _Flight(ros_goal, self.label)
        if self.ctx.motion_epoch() != epoch and not self.handle.should_stop:
            # Safety stopped (and maybe released) the robot while this goal was on its way.
            self.flight = flight
            if (ended := self._hold(flight, "safety stop during its send")) is not None:
                return ended
            self.flight = None
            return None
        return flight

    def _cancel_unanswered(self, action: RosAction, goal_id: bytes) -> None:
        """Cancel the goal whose send_goal went unanswered, for as long as the robot may yet take it."""
        deadline = time.monotonic() + self.ctx.goal_timeout + UNANSWERED_MARGIN
        while True:
            try:
                if action.cancel(goal_id, self.ctx.cancel_timeout):
                    log.info("the unanswered %s goal %s is canceled on %s", self.label, goal_id.hex(), action.name)
                    return
            except RobotCallFailed as exc:
                log.warning("could not cancel the unanswered %s goal %s: %s", self.label, goal_id.hex(), exc)
            if time.monotonic() >= deadline:
                log.info("the %s goal %s never showed on %s", self.label, goal_id.hex(), action.name)
                return
            time.sleep(CANCEL_RETRY)

    def _cancel(self, flight: _Flight) -> bool:
        """Cancel the ROS goal and wait for the robot to say it ended; whether it did in time. When it
        did not, the robot is held stopped (its emergency_stop) until it does, and the cancel asked again."""
        deadline = time.monotonic() + self.ctx.cancel_timeout
        while True:
            flight.cancel(self.ctx.cancel_timeout)
            # Its result says when it ends, or the robot's answer to a cancel asked again (no result coming).
            remaining = deadline - time.monotonic()
            if flight.settled.wait(max(0.0, min(remaining, CANCEL_RETRY))):
                # Settled by a cancel's answer, its result (the outcome: how it ended) is on its way.
                flight.ended.wait(max(0.0, deadline - time.monotonic()))
                return True
            if time.monotonic() >= deadline:
                break
        log.error("the robot did not end the %s goal within %g s of its cancel", self.label, self.ctx.cancel_timeout)
        self._escalate(flight)
        return False

    def _escalate(self, flight: _Flight) -> None:
        self.make_safe()
        reason = (
            f"the robot did not end its {self.label} goal when canceled: its emergency stop is held until the goal ends"
        )
        self.ctx.robot.goal_failed(reason)
        release = self.ctx.block_robot(reason)
        threading.Thread(
            target=self._keep_canceling, args=(flight, release), name=f"cancel:{self.label}", daemon=True
        ).start()

    def _keep_canceling(self, flight: _Flight, release: Callable[[], None]) -> None:
        """Ask the robot to cancel the goal until its result (or its answer to a cancel) says it ended,
        then release it: never on its status topic alone, which anyone on its network can publish."""
        while not flight.settled.wait(CANCEL_RETRY):
            if flight.closed.is_set():
                log.warning("the backend left the robot's network with its %s goal not known to have ended", self.label)
                return  # the robot's emergency stop stays as it was last told: true, by the backend's close
            try:
                flight.cancel(self.ctx.cancel_timeout)
            except Exception:
                log.exception("cancel of the %s goal failed again", self.label)
        log.info("the robot ended the %s goal after all: its emergency stop is no longer held for it", self.label)
        release()

    def _hold(self, flight: _Flight, why: str) -> Ending | None:
        """Cancel the ROS goal to pause or re-time; an Ending when the goal is over instead."""
        now = self.ctx.clock()
        if not self._cancel(flight):
            message = (
                f"the robot did not stop the {self.label} goal within {self.ctx.cancel_timeout:g} s ({why}); "
                "its emergency stop is held until it does"
            )
            return Ending(GoalState.ABORTED, self.result_now(), message)
        status = flight.outcome[0]
        if status in (GoalStatus.SUCCEEDED, GoalStatus.ABORTED):
            return self._ended(flight)
        self.held(now)
        log.info("%s goal held for a %s; the rest is sent again once it may move", self.label, why)
        return None

    def _stopped(self, flight: _Flight | None) -> Ending:
        """The tether goal was canceled, preempted or aborted: end the ROS goal and say how."""
        reason = self.handle.abort_reason
        if flight is not None:
            if not self._cancel(flight):
                message = (
                    f"{reason or 'canceled'}; the robot did not confirm it within {self.ctx.cancel_timeout:g} s: "
                    "its emergency stop is held until it does"
                )
                return Ending(GoalState.ABORTED if reason else GoalState.CANCELED, self.result_now(), message)
            if flight.outcome[0] == GoalStatus.SUCCEEDED:
                return self._ended(flight)
        elif self.sends == 0:
            if reason:
                return Ending(GoalState.ABORTED, self.result_now(), reason)
            return Ending(GoalState.CANCELED, self.result_now(), "canceled before it started")
        if reason:
            return Ending(GoalState.ABORTED, self.result_now(), reason)
        return Ending(GoalState.CANCELED, self.result_now(), "canceled")

    def _abort(self, flight: _Flight | None, problem: str) -> Ending:
        log.warning("aborting the %s goal: %s", self.label, problem)
        if flight is not None:
            self._cancel(flight)
        self.make_safe()
        return Ending(GoalState.ABORTED, self.result_now(), problem)

    def _ended(self, flight: _Flight) -> Ending:
        status, result, unreadable = flight.outcome
        if status == GoalStatus.SUCCEEDED and not unreadable:
            return self.succeeded(result)
        # Its result could not be fetched: it may run still, whatever its status says.
        running = not flight.result_read and not self._cancel(flight)
        self.make_safe()
        blocked = self.ctx.safety().blocked
        if blocked is not None:
            message = blocked  # the robot stopped because safety stopped it
        elif status == GoalStatus.SUCCEEDED:
            message = f"the robot reports the {self.label} goal succeeded, but {unreadable}"
        else:
            message = self.failure(status, result, unreadable)
        if running:
            message += (
                f"; the robot did not end it within {self.ctx.cancel_timeout:g} s of its cancel: its emergency "
                "stop is held until it does"
            )
        log.warning("%s goal ended: %s", self.label, message)
        return Ending(GoalState.ABORTED, self.result_now(), message)


class NavigationRun(GoalRun):
    """A navigate_to_pose goal as Nav2's NavigateToPose (no path) or NavigateThroughPoses (the path,
    then the pose), checked against odometry: refused when `start` is not where the base stands,
    aborted when the base strays from the legs safety checked, stalls or odometry stops. The speed
    limit goes to Nav2 as it changes; a pause cancels the Nav2 goal, a resume sends the rest."""

    label = "navigate_to_pose"

    def __init__(
        self,
        ctx: RunContext,
        handle: TetherGoal,
        *,
        to_pose: RosAction,
        through_poses: RosAction,
        messages: Messages,
        limits: BaseLimits,
        publish_speed_limit: Callable[[float], None],
        base_radius: float,
        odom_timeout: float,
        stall_timeout: float,
    ) -> None:
        super().__init__(ctx, to_pose, handle)
        self.goal: NavigateToPoseGoal = handle.goal
        self.to_pose, self.through_poses = to_pose, through_poses
        self.messages = messages
        self.limits = limits
        self.publish_speed_limit = publish_speed_limit
        self.base_radius = base_radius
        self.odom_timeout = odom_timeout
        self.stall_timeout = stall_timeout
        self.tracker: RouteTracker | None = None
        self.speed_limit: float | None = None
        self.clock = 0.0  # scaled seconds while a Nav2 goal runs: stall detection
        self.best = math.inf
        self.progressed = 0.0
        self.ticked = ctx.clock()

    def prepare(self) -> str | None:
        odom = self.ctx.robot.odometry(self.odom_timeout)
        if isinstance(odom, str):
            return odom
        # A base still rolling (this goal preempted another, or cmd_vel holds) brakes to rest first:
        # its legs begin where it stops, which is where `start` must be.
        rest = self._at_rest(odom)
        if isinstance(rest, str):
            return rest
        start = self.goal.start or rest.pose
        if reason := away_from(rest.pose, start, self.base_radius):
            return reason
        legs = route_legs(start, drive_route(start, self.goal.path, self.goal.pose))
        self.tracker = RouteTracker(legs, start, self.goal.pose, self.base_radius)
        return None

    def _at_rest(self, odom: Odometry) -> Odometry | str:
        """The base at rest: at once when it stands still, else braked (zero cmd_vel) and waited for."""
        if abs(odom.linear_x) < SETTLED_SPEED and abs(odom.angular_z) < SETTLED_SPEED:
            return odom
        self.ctx.halt_base()
        deadline = self.ctx.clock() + REST_TIMEOUT
        while abs(odom.linear_x) >= SETTLED_SPEED or abs(odom.angular_z) >= SETTLED_SPEED:
            if self.ctx.clock() > deadline:
                return f"the base did not come to rest within {REST_TIMEOUT:g} s to set off"
            if self.handle.should_stop:
                return "stopped before it started"
            self.ctx.sleep(POLL)
            latest = self.ctx.robot.odometry(self.odom_timeout)
            if isinstance(latest, str):
                return latest
            odom = latest
        return odom

    def next_goal(self, scale: float) -> tuple[RosAction, Any]:
        assert self.tracker is not None
        self._limit_speed(force=True)
        poses = [*self.goal.path, self.goal.pose] if self.sends == 0 else self.tracker.rest()
        through, goal = self.messages.navigate(poses, time.time())
        return (self.through_poses if through else self.to_pose), goal

    def _limit_speed(self, force: bool = False) -> None:
        limit = self.limits.navigation_limit(self.ctx.safety(), self.goal.max_speed, self.goal.max_turn_rate)
        if limit <= 0.0:
            return  # paused: the goal is canceled instead (0 is Nav2's "no limit")
        if force or self.speed_limit is None or abs(limit - self.speed_limit) > 0.01 * self.speed_limit:
            self.speed_limit = limit
            self.publish_speed_limit(limit)

    def check(self, now: float, moving: bool, scale: float) -> str | None:
        assert self.tracker is not None
        dt, self.ticked = now - self.ticked, now
        odom = self.ctx.robot.odometry(self.odom_timeout)
        if isinstance(odom, str):
            return odom
        pose = odom.pose
        stray = self.tracker.update(pose)
        if stray > TRACKING_TOLERANCE:
            return (
                f"navigation to ({self.goal.pose.x:.2f}, {self.goal.pose.y:.2f}) aborted at ({pose.x:.2f}, "
                f"{pose.y:.2f}): {stray * 100:.1f} cm off its route (tolerance {TRACKING_TOLERANCE * 100:g} cm): "
                "the robot drives other legs than safety checked, or it was pushed or blocked"
            )
        if not moving:
            return None
        self._limit_speed()
        self.clock += dt * scale
        progress = self.tracker.progress(pose)
        if progress < self.best - PROGRESS_STEP:
            self.best, self.progressed = progress, self.clock
        elif self.clock - self.progressed > self.stall_timeout:
            return (
                f"the base made no progress for {self.stall_timeout:g} s with {self.tracker.remaining(pose):.2f} m "
                "to go; is the way blocked?"
            )
        return None

    def held(self, now: float) -> None:
        self.progressed = self.clock  # a pause is no stall

    def feedback(self, now: float) -> NavigateToPoseFeedback | None:
        odom = self.ctx.robot.latest_odometry
        if odom is None or self.tracker is None:
            return None
        return NavigateToPoseFeedback(pose=odom.pose, distance_remaining=self.tracker.remaining(odom.pose))

    def result_now(self) -> NavigateToPoseResult | None:
        odom = self.ctx.robot.latest_odometry
        return None if odom is None else NavigateToPoseResult(pose=odom.pose)

    def succeeded(self, result: Any) -> Ending:
        odom = self.ctx.robot.fresh_odometry(self.ctx.robot.clock(), FRESH_REPORT_WAIT)
        pose = odom.pose if odom is not None else self.goal.pose
        goal = self.goal.pose
        off, turned = math.hypot(pose.x - goal.x, pose.y - goal.y), abs(math.remainder(pose.yaw - goal.yaw, math.tau))
        if off > ARRIVAL_DISTANCE or turned > ARRIVAL_YAW:
            message = (
                f"the robot says it reached the goal pose, but odometry has the base at ({pose.x:.2f}, {pose.y:.2f}, "
                f"yaw {pose.yaw:.2f}), {off:.2f} m and {turned:.2f} rad from it (tether's navigations end within "
                f"{ARRIVAL_DISTANCE * 100:g} cm and {ARRIVAL_YAW:g} rad: set Nav2's goal checker within these)"
            )
            log.warning("%s goal ended: %s", self.label, message)
            self.make_safe()
            return Ending(GoalState.ABORTED, NavigateToPoseResult(pose=pose, message=message), message)
        message = "reached the goal pose"
        return Ending(GoalState.SUCCEEDED, NavigateToPoseResult(pose=pose, message=message), message)

    def failure(self, status: int, result: Any, error: str) -> str:
        if not (error := navigation_error(result) or error) and status == GoalStatus.ABORTED and result is not None:
            error = NAV2_NO_REASON
        return ros_failure(self.label, status, error)

    def result_with(self, message: str) -> NavigateToPoseResult | None:
        odom = self.ctx.robot.latest_odometry
        return None if odom is None else NavigateToPoseResult(pose=odom.pose, message=message)

    def make_safe(self) -> None:
        self.ctx.halt_base()

    def run(self) -> Ending:
        ending = super().run()
        if self.speed_limit is not None and self.speed_limit < self.limits.max_linear:
            # The limit was this goal's: lifted (to the robot's own top speed), as a robot may apply it
            # to cmd_vel too. cmd_vel keeps to the heartbeat's limits on the backend's side.
            self.publish_speed_limit(self.limits.max_linear)
        if ending.state is not GoalState.SUCCEEDED and ending.message:
            return Ending(ending.state, self.result_with(ending.message), ending.message)
        return ending


class TrajectoryRun(GoalRun):
    """A follow_joint_trajectory goal as control_msgs FollowJointTrajectory, re-timed for the speed
    scale: its clock advances at the scale, a change cancels the ROS goal (the arm holds) and sends
    the rest re-timed; at 0 the arm holds until it may move."""

    label = "follow_joint_trajectory"

    def __init__(
        self,
        ctx: RunContext,
        action: RosAction,
        handle: TetherGoal,
        messages: Messages,
        *,
        joint_states_timeout: float,
    ) -> None:
        super().__init__(ctx, action, handle)
        self.goal: FollowJointTrajectoryGoal = handle.goal
        self.messages = messages
        # As NavigationRun's odom_timeout: joint states older than this end the goal (node.py passes
        # `[ros2] joint_states_timeout`).
        self.joint_states_timeout = joint_states_timeout
        self.plan: TrajectoryPlan | None = None
        self.t = 0.0  # trajectory time reached when last sent or held
        self.sent_at: float | None = None  # clock time of the last send while the goal runs
        self.scale = 1.0

    def _actual(self) -> list[float] | None:
        joints = self.ctx.robot.joints
        if joints is None or not all(n in joints.name for n in self.goal.joint_names):
            return None
        return [joints.position[joints.name.index(n)] for n in self.goal.joint_names]

    def prepare(self) -> str | None:
        if isinstance(joints := self.ctx.robot.joint_states(self.joint_states_timeout), str):
            return joints  # the trajectory would start from where the arm was, not where it is
        actual = self._actual()
        if actual is None:
            return "no joint states from the robot for the trajectory's joints"
        self.plan = TrajectoryPlan(self.goal, actual)
        return None

    def clock_at(self, now: float) -> float:
        if self.sent_at is None:
            return self.t
        return self.t + (now - self.sent_at) * self.scale

    def next_goal(self, scale: float) -> tuple[RosAction, Any]:
        assert self.plan is not None
        points = self.plan.first(scale) if self.sends == 0 else self.plan.rest(self.t, scale)
        goal = self.messages.trajectory(
            self.goal.joint_names,
            points,
            path_tolerance=self.goal.path_tolerance,
            goal_tolerance=self.goal.goal_tolerance,
        )
        return self.action, goal

    def sent(self, scale: float, now: float) -> None:
        self.sent_at, self.scale = now, scale

    def held(self, now: float) -> None:
        self.t, self.sent_at = self.clock_at(now), None

    def wants_resend(self, scale: float, now: float) -> bool:
        if scale < 0.95 * self.scale:
            return True  # slower at once: safety asked for it
        return scale > 1.1 * self.scale and self.sent_at is not None and now - self.sent_at > RETIME_PERIOD

    def check(self, now: float, moving: bool, scale: float) -> str | None:
        assert self.plan is not None
        if isinstance(joints := self.ctx.robot.joint_states(self.joint_states_timeout), str):
            return joints
        limit = self.plan.end + TRAJECTORY_SETTLE + TRAJECTORY_GRACE
        if moving and self.clock_at(now) > limit:
            return f"the arm controller did not finish the trajectory within {limit:g} s of trajectory time"
        return None

    def feedback(self, now: float) -> FollowJointTrajectoryFeedback | None:
        actual = self._actual()
        if actual is None or self.plan is None:
            return None
        t = self.clock_at(now)
        return FollowJointTrajectoryFeedback(desired=self.plan.desired(t), actual=actual, time_from_start=t)

    def _error(self, joints: JointState | None) -> float:
        if joints is None or self.plan is None or not all(n in joints.name for n in self.goal.joint_names):
            return 0.0
        actual = [joints.position[joints.name.index(n)] for n in self.goal.joint_names]
        return float(max(abs(a - b) for a, b in zip(actual, self.plan.final, strict=True)))

    def result_now(self) -> FollowJointTrajectoryResult:
        return FollowJointTrajectoryResult(error=self._error(self.ctx.robot.joints))

    def succeeded(self, result: Any) -> Ending:
        if problem := trajectory_error(result):
            message = ros_failure(self.label, GoalStatus.ABORTED, problem)
            return Ending(
                GoalState.ABORTED, FollowJointTrajectoryResult(error=self.result_now().error, message=message), message
            )
        # The error as of a joint state from after the robot said it arrived.
        error = self._error(self.ctx.robot.fresh_joints(self.ctx.robot.clock(), FRESH_REPORT_WAIT))
        message = "reached the last point"
        return Ending(GoalState.SUCCEEDED, FollowJointTrajectoryResult(error=error, message=message), message)

    def failure(self, status: int, result: Any, error: str) -> str:
        return ros_failure(self.label, status, trajectory_error(result) or error)


class GripperRun(GoalRun):
    """A gripper_command goal as control_msgs GripperCommand (or ParallelGripperCommand): not slowed,
    but paused at speed scale 0 (the goal canceled, the fingers hold) and sent again on resume. What
    it holds comes from the detections: the object seen in the gripper frame."""

    label = "gripper_command"

    def __init__(
        self,
        ctx: RunContext,
        action: RosAction,
        handle: TetherGoal,
        messages: Messages,
        masses: dict[str, float],
        objects_period: float,
    ) -> None:
        super().__init__(ctx, action, handle)
        self.goal: GripperCommandGoal = handle.goal
        self.messages = messages
        self.masses = masses
        self.objects_period = objects_period
        self.closing = False
        self.busy = 0.0  # seconds a ROS goal ran
        self.sent_at: float | None = None

    def prepare(self) -> str | None:
        gap = gripper_gap(self.ctx.robot.joints)
        self.closing = gap is None or self.goal.position < gap - 1e-4
        return None

    def next_goal(self, scale: float) -> tuple[RosAction, Any]:
        return self.action, self.messages.gripper(self.goal.position, self.goal.max_effort)

    def sent(self, scale: float, now: float) -> None:
        self.sent_at = now

    def held(self, now: float) -> None:
        if self.sent_at is not None:
            self.busy += now - self.sent_at
        self.sent_at = None

    def check(self, now: float, moving: bool, scale: float) -> str | None:
        busy = self.busy + (now - self.sent_at if self.sent_at is not None else 0.0)
        if moving and busy > GRIPPER_DEADLINE:
            return f"the gripper did not finish within {GRIPPER_DEADLINE:g} s"
        return None

    def feedback(self, now: float) -> GripperCommandFeedback | None:
        gap = gripper_gap(self.ctx.robot.joints)
        return None if gap is None else GripperCommandFeedback(position=gap)

    def result_now(self) -> GripperCommandResult:
        gap = gripper_gap(self.ctx.robot.joints) or 0.0
        return GripperCommandResult(position=gap, stalled=False, reached_goal=abs(gap - self.goal.position) < 0.002)

    def succeeded(self, result: Any) -> Ending:
        if hasattr(result, "state"):  # ParallelGripperCommand
            position = float(result.state.position[0]) * 2 if len(result.state.position) else 0.0
        else:
            position = float(result.position) / self.messages.gripper_position_per_gap
        if not math.isfinite(position):
            # Passed on, no one could decode the result (JSON has no NaN): the goal ends aborted instead.
            message = (
                f"the robot reports the {self.label} goal succeeded, but with the gripper at {position}: not a gap"
            )
            log.warning("%s goal ended: %s", self.label, message)
            return Ending(GoalState.ABORTED, self.result_now(), message)
        stalled, reached = bool(result.stalled), bool(result.reached_goal)
        holding = self._holding() if self.closing and stalled else None
        message = f"gripper at {position * 1000:.0f} mm"
        if holding is not None:
            message = f"holding {holding}"
            limit, mass = self.goal.payload_limit, self.masses.get(holding, 0.0)
            if limit is not None and mass > limit:
                message += f" ({mass:g} kg, over the payload limit of {limit:g} kg)"
        result_value = GripperCommandResult(position=position, stalled=stalled, reached_goal=reached, holding=holding)
        return Ending(GoalState.SUCCEEDED, result_value, message)

    def failure(self, status: int, result: Any, error: str) -> str:
        return ros_failure(self.label, status, gripper_error(result, self.messages.gripper_position_per_gap) or error)

    def _holding(self) -> str | None:
        """The object the detections put in the gripper, from a report after the grasp."""
        seen = self.ctx.robot.fresh_objects(self.ctx.robot.clock(), max(FRESH_REPORT_WAIT, 2.5 * self.objects_period))
        if seen is None:
            return None
        held = [o.id for o in seen.objects if o.on == "gripper"]
        return held[0] if held else None
