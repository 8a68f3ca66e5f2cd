"""What every robot backend does alike (docs/robot.md): fail closed on the heartbeat, check goals. Pure logic."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from schemas.common import Pose2D
from schemas.robot import ARM_JOINTS, FollowJointTrajectoryGoal
from schemas.safety import SafetyStatus
from services.footprint import TRACKING_TOLERANCE, turn_angle

log = logging.getLogger(__name__)

# Action feedback while a goal runs (wall seconds).
FEEDBACK_PERIOD = 0.1
# A goal arriving while the e-stop shows latched waits this long for a newer heartbeat (a reset).
RESET_GRACE = 0.1
# A preempting goal waits this long for the running one to end. With the waits in accepting it
# (RESET_GRACE, twice: before and after), send_goal answers well within safety's forward_timeout
# (5 s), so safety never reports a forward failed that the robot then runs. docs/robot.md, Timing.
PREEMPT_TIMEOUT = 2.0
NO_HEARTBEAT_YET = "no safety heartbeat received yet"


@dataclass(frozen=True)
class SafetyNow:
    """What safety's heartbeat allows at one moment."""

    blocked: str | None  # why the robot must stay still; None when it may move
    status: SafetyStatus | None  # the latest heartbeat
    stopped: bool = False  # it has just become blocked: stop everything, abort every goal
    released: bool = False  # it has just become clear: it may move again

    @property
    def speed_scale(self) -> float:
        """The fraction of its speed the robot may use: 0 while blocked or paused."""
        if self.blocked is not None or self.status is None:
            return 0.0
        return self.status.speed_scale


class HeartbeatGuard:
    """The fail-closed rules on safety's heartbeat (docs/robot.md, Fail closed), for any backend.

    `heard` takes each heartbeat; `block` says why the robot must stay still now; `accept` is an
    action server's accept check (waiting, bounded, for the first heartbeat and for a reset);
    `poll`, from the one loop that enforces it, also says when the robot has just become blocked or
    clear. Times come from `clock` (monotonic seconds), so tests can step it.
    """

    def __init__(
        self, heartbeat_timeout: float, first_heartbeat_wait: float, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.heartbeat_timeout = heartbeat_timeout
        self.first_heartbeat_wait = first_heartbeat_wait
        self._clock = clock
        self._beat = threading.Condition()
        self._status: SafetyStatus | None = None
        self._heard_at = 0.0
        self._first = threading.Event()
        self._blocked: str | None = NO_HEARTBEAT_YET  # as of the last poll
        self._scale = 1.0  # as of the last poll

    def heard(self, status: SafetyStatus) -> None:
        with self._beat:
            self._status, self._heard_at = status, self._clock()
            self._beat.notify_all()
        self._first.set()

    @property
    def status(self) -> SafetyStatus | None:
        with self._beat:
            return self._status

    def stale_at(self) -> float | None:
        """When the latest heartbeat stops counting (clock seconds); None before the first."""
        with self._beat:
            return None if self._status is None else self._heard_at + self.heartbeat_timeout

    def block(self) -> str | None:
        """Why the robot must stay still right now, or None when safety says it may move."""
        with self._beat:
            status, at = self._status, self._heard_at
        if status is None:
            return NO_HEARTBEAT_YET
        age = self._clock() - at
        if age > self.heartbeat_timeout:
            return f"no safety heartbeat for {age * 1000:.0f} ms"
        if status.estop.latched:
            return f"e-stop latched by {status.estop.source or 'unknown'}: {status.estop.reason or 'no reason given'}"
        return None

    def now(self) -> SafetyNow:
        """What the heartbeat allows now (no transitions: those are `poll`'s)."""
        return SafetyNow(self.block(), self.status)

    def next_heartbeat(self, timeout: float) -> None:
        """Wait (bounded) until a heartbeat newer than the latest arrives."""
        with self._beat:
            latest = self._status
            self._beat.wait_for(lambda: self._status is not latest, timeout)

    def accept(self) -> str | None:
        """None when a goal may be accepted now, else why not. Never moves without a heartbeat: this
        only waits (bounded) for the first one to arrive, and for one more when the e-stop shows latched."""
        self._first.wait(self.first_heartbeat_wait)
        reason = self.block()
        status = self.status
        if status is not None and status.estop.latched:
            # Safety announces a reset with a heartbeat before it approves anything, but a goal it
            # approved right after can overtake that heartbeat on the way here: hear one more.
            self.next_heartbeat(RESET_GRACE)
            reason = self.block()
        return reason

    def poll(self) -> SafetyNow:
        """What the heartbeat allows now, and whether that just changed. Call from one loop only."""
        now = self.now()
        was_blocked = self._blocked is not None
        self._blocked = now.blocked
        if now.blocked is not None:
            self._scale = 0.0  # while blocked nothing moves until a heartbeat says how fast it may
            if not was_blocked:
                log.warning("stopping the robot: %s", now.blocked)
                return SafetyNow(now.blocked, now.status, stopped=True)
            return now
        assert now.status is not None
        scale = now.status.speed_scale
        if was_blocked:
            log.info("safety heartbeat present and e-stop clear: the robot may move at %.2f of full speed", scale)
        else:
            _log_speed_change(self._scale, scale, now.status.speed_reason or "no reason given")
        self._scale = scale
        return SafetyNow(None, now.status, released=was_blocked)


def _log_speed_change(previous: float, scale: float, why: str) -> None:
    if scale == previous:
        return
    if scale == 0.0:
        log.info("pausing motion, goals kept: speed scale 0 (%s)", why)
    elif previous == 0.0:
        log.info("resuming at speed scale %.2f (%s)", scale, why)
    else:
        log.debug("speed scale %.2f (%s)", scale, why)


def check_trajectory(goal: FollowJointTrajectoryGoal, lower: Sequence[float], upper: Sequence[float]) -> str | None:
    """Why the arm cannot follow a trajectory goal, or None when it can; `lower` and `upper` are the
    limits of ARM_JOINTS, in order."""
    unknown = [n for n in goal.joint_names if n not in ARM_JOINTS]
    if unknown:
        return f"unknown joints {unknown}; this arm has {list(ARM_JOINTS)}"
    if len(set(goal.joint_names)) != len(goal.joint_names):
        return f"joint names repeat: {goal.joint_names}"
    previous = -1.0
    for k, point in enumerate(goal.points):
        if len(point.positions) != len(goal.joint_names):
            return f"point {k} has {len(point.positions)} positions for {len(goal.joint_names)} joints"
        if point.time_from_start < previous:
            return f"point {k} goes back in time ({point.time_from_start:g} s after {previous:g} s)"
        previous = point.time_from_start
        for name, value in zip(goal.joint_names, point.positions, strict=True):
            i = ARM_JOINTS.index(name)
            if not lower[i] <= value <= upper[i]:
                return f"point {k}: {name} = {value:.3f} rad is outside [{lower[i]:.3f}, {upper[i]:.3f}]"
    return None


def away_from(here: Pose2D, start: Pose2D, base_radius: float) -> str | None:
    """Why a navigation checked from `start` may not set off with the base at `here` (it would drive
    other legs than those safety checked), or None when the base stands there within TRACKING_TOLERANCE."""
    off = math.dist((here.x, here.y), (start.x, start.y)) + base_radius * abs(turn_angle(here.yaw, start.yaw))
    if off <= TRACKING_TOLERANCE:
        return None
    return (
        f"the route was checked from ({start.x:.2f}, {start.y:.2f}, {start.yaw:.2f} rad) but the base stands at "
        f"({here.x:.2f}, {here.y:.2f}, {here.yaw:.2f} rad)"
    )
