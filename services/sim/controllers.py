"""The robot's controllers: base, arm and gripper, carrying out goals the way Nav2 and ros2_control do."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np

from schemas.actions import GoalState
from schemas.common import Pose2D
from schemas.robot import (
    ARM_JOINTS,
    FollowJointTrajectoryFeedback,
    FollowJointTrajectoryGoal,
    FollowJointTrajectoryResult,
    GripperCommandFeedback,
    GripperCommandGoal,
    GripperCommandResult,
    NavigateToPoseFeedback,
    NavigateToPoseGoal,
    NavigateToPoseResult,
    Twist,
)
from services.footprint import TRACKING_TOLERANCE, Leg, route_legs
from services.robotrules import away_from, check_trajectory
from services.sim.world import GRIPPER_OPEN, Motion, SimWorld, wrap_angle
from services.worldmodel import drive_route

F = TypeVar("F")
R = TypeVar("R")
M = TypeVar("M", bound="GoalMotion[Any, Any]")

# navigate_to_pose
# The base stops on every point of its route within this before it turns for the next leg.
WAYPOINT_TOLERANCE = 0.01
GOAL_YAW_TOLERANCE = 0.02
# Turning to a leg's heading, the base sets off once within this of it (its corners then within
# half a centimetre of where the leg's sweep has them).
ALIGNED = 0.01
# Driving a leg, the base steers back onto its line at this distance ahead (metres): a lateral
# error of 1 cm turns it 0.02 rad towards the line.
LOOKAHEAD = 0.5
# Close to a stop or a heading, speed is this many times the distance (per second) still to go: the
# last centimetres take a fraction of a second, well within the braking the acceleration allows.
SETTLE_GAIN = 4.0
# Navigation's stall and deadline clocks run on scaled time (sim seconds times the speed scale),
# so a pause or slowdown for people nearby never counts as being stuck.
STALL_TIME = 4.0  # scaled sim seconds without progress
SETTLED_SPEED = 0.05

# follow_joint_trajectory
TRAJECTORY_SETTLE_TIME = 1.0

# gripper_command
GRIPPER_TIMEOUT = 2.0
GRIPPER_STILL_TIME = 0.1
GRIPPER_REACHED = 0.002


def _clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))


class BaseController:
    """Velocity control of the base: what navigation or cmd_vel asks, within the limits the
    heartbeat allows, reached at the robot's accelerations (like ros2_control's diff drive
    controller with its limiter)."""

    def __init__(self, world: SimWorld) -> None:
        self.world = world
        self.spec = world.spec.robot
        self.wanted = (0.0, 0.0)  # what the controllers ask: linear_x, angular_z
        self.actual = (0.0, 0.0)  # after the speed limits and the acceleration limits
        self.limits = (self.spec.max_linear_speed, self.spec.max_angular_speed)
        self._stopped = False  # the motors were last told to stand still
        self.apply()

    def command(self, linear_x: float, angular_z: float) -> None:
        self.wanted = (_clamp(linear_x, self.spec.max_linear_speed), _clamp(angular_z, self.spec.max_angular_speed))

    def halt(self) -> None:
        """Velocity to zero at once: the e-stop path, the only one that skips the acceleration limits."""
        self.wanted = self.actual = (0.0, 0.0)
        self.apply()

    def apply(self) -> None:
        want_v = _clamp(self.wanted[0], self.limits[0])
        want_w = _clamp(self.wanted[1], self.limits[1])
        have_v, have_w = self.actual
        dt = self.world.dt
        dv, dw = self.spec.max_linear_acceleration * dt, self.spec.max_angular_acceleration * dt
        v = have_v + max(-dv, min(dv, want_v - have_v))
        w = have_w + max(-dw, min(dw, want_w - have_w))
        self.actual = (v, w)
        # Standing still needs telling once: the motors hold zero velocity until told otherwise
        # (only this controller drives the base), whatever the heading.
        stopped = v == 0.0 and w == 0.0
        if not (stopped and self._stopped):
            self.world.robot.drive_base(v, w)
        self._stopped = stopped


class ArmController:
    """Position control of the seven arm joints with velocity feed-forward (ros2_control's
    joint_trajectory_controller does the interpolation; see TrajectoryFollow)."""

    def __init__(self, world: SimWorld) -> None:
        self.body = world.robot
        self.targets = np.array(world.spec.robot.home_joints, dtype=float)
        self.velocities = np.zeros(7)
        self.apply()

    def command(self, indices: list[int], positions: np.ndarray, velocities: np.ndarray) -> None:
        self.targets[indices] = positions
        self.velocities[:] = 0.0
        self.velocities[indices] = velocities
        self.apply()

    def hold(self) -> None:
        self.targets = np.array(self.body.arm_positions())
        self.velocities = np.zeros(7)
        self.apply()

    def apply(self) -> None:
        self.body.drive_arm(self.targets, self.velocities)

    def check_trajectory(self, goal: FollowJointTrajectoryGoal) -> str | None:
        """Why a trajectory goal cannot run, or None when it can. Safe from any thread."""
        return check_trajectory(goal, *self.body.arm_limits)


class GripperController:
    """Both fingers to one gap, pushing with at most the goal's effort (control_msgs' GripperCommand)."""

    def __init__(self, world: SimWorld) -> None:
        self.body = world.robot
        self.target, self.force = GRIPPER_OPEN / 2, 40.0
        self.apply()

    def command(self, gap: float, max_effort: float) -> None:
        self.target = min(max(gap, 0.0), GRIPPER_OPEN) / 2
        self.force = max_effort
        self.apply()

    def hold(self) -> None:
        self.target = self.body.gripper_gap() / 2
        self.apply()

    def apply(self) -> None:
        self.body.drive_fingers(self.target, self.force)


class GoalMotion(Motion[F, R]):
    """A goal being carried out: the controllers tick it every physics step."""

    def __init__(self, ctl: Controllers) -> None:
        super().__init__(ctl.world.sim_time)

    def tick(self, ctl: Controllers) -> None:
        raise NotImplementedError

    def result_now(self, ctl: Controllers) -> R:
        """The result as things stand, for when the goal ends early."""
        raise NotImplementedError

    def end(self, ctl: Controllers, state: GoalState, message: str) -> None:
        """End early (cancel, abort, stop) with the result as things stand."""
        self.finish(state, self.result_now(ctl), message)


class Navigation(GoalMotion[NavigateToPoseFeedback, NavigateToPoseResult]):
    """Drive the route as services/footprint.py describes it, from the start safety checked it from
    (`goal.start`): for each leg turn in place to its heading, drive along its line holding that
    heading (backwards for a short leg behind), stop at its end; at the last point turn to the
    goal's yaw.

    The footprint may stray at most TRACKING_TOLERANCE from what the legs sweep, measured as the
    centre's distance from the leg (or from the point it turns at) plus how far the corners are
    turned off the leg's heading; further (pushed, or blocked and sliding) aborts the goal. The
    stall detector and the deadline count scaled time (`clock`: each tick adds dt times the speed
    scale), so they stand still while the sim is paused and run slower while it is slowed.
    """

    kind = "navigate_to_pose"

    def __init__(self, ctl: Controllers, goal: NavigateToPoseGoal) -> None:
        super().__init__(ctl)
        robot = ctl.world.spec.robot
        self.goal = goal
        body = ctl.world.robot
        # A goal that preempted another may find the base still rolling: it brakes to rest first and
        # plans its legs from there (unless safety checked them from a given start).
        linear, angular = body.base_velocity()
        self.braking = goal.start is None and max(abs(linear), abs(angular)) >= SETTLED_SPEED
        self.legs = self._legs(goal.start or body.base_pose())
        self.index = 0
        self.turning = True  # turning at the current leg's start (or, past the last leg, at the goal)
        self.base_radius = ctl.world.model.base_radius
        self.max_speed = min(goal.max_speed or robot.max_linear_speed, robot.max_linear_speed)
        self.max_turn = min(goal.max_turn_rate or robot.max_angular_speed, robot.max_angular_speed)
        self.accel, self.turn_accel = robot.max_linear_acceleration, robot.max_angular_acceleration
        self.clock = 0.0
        self.deadline = self._deadline()
        self.best_progress = math.inf
        self.last_progress = self.clock

    def _legs(self, start: Pose2D) -> list[Leg]:
        # The same legs safety checked: the path, maybe a pre-goal point, the goal.
        return route_legs(start, drive_route(start, self.goal.path, self.goal.pose))

    def _deadline(self) -> float:
        length = sum(leg.length for leg in self.legs)
        turns = len(self.legs) + 1
        return self.clock + 2.0 * length / self.max_speed + turns * 2.0 * math.pi / self.max_turn + 10.0

    def result_now(self, ctl: Controllers) -> NavigateToPoseResult:
        return NavigateToPoseResult(pose=ctl.world.robot.base_pose())

    def _turn_point(self) -> tuple[float, float]:
        if self.index < len(self.legs):
            return self.legs[self.index].start
        return self.legs[-1].end if self.legs else (self.goal.pose.x, self.goal.pose.y)

    def _along(self, pose: Pose2D) -> tuple[float, float]:
        """How far along the current leg the centre is, and how far left of its line."""
        leg = self.legs[self.index]
        (ax, ay), (bx, by) = leg.start, leg.end
        tx, ty = (bx - ax) / leg.length, (by - ay) / leg.length
        dx, dy = pose.x - ax, pose.y - ay
        return dx * tx + dy * ty, dx * -ty + dy * tx

    def _stray(self, pose: Pose2D) -> float:
        """How far the footprint is from where the route's sweeps have it (an upper bound)."""
        if self.turning:
            return math.dist((pose.x, pose.y), self._turn_point())
        leg = self.legs[self.index]
        s, e = self._along(pose)
        beyond = max(0.0, -s, s - leg.length)
        return math.hypot(e, beyond) + self.base_radius * abs(wrap_angle(pose.yaw - leg.heading))

    def _remaining(self, pose: Pose2D) -> float:
        if self.index >= len(self.legs):
            return 0.0
        along = 0.0 if self.turning else self._along(pose)[0]
        return self.legs[self.index].length - along + sum(leg.length for leg in self.legs[self.index + 1 :])

    def tick(self, ctl: Controllers) -> None:
        base, body = ctl.base, ctl.world.robot
        self.clock += ctl.world.dt * ctl.speed_scale
        pose = body.base_pose()
        if self.braking:
            self._brake(ctl, pose)
            return
        remaining = self._remaining(pose)
        self.feedback = NavigateToPoseFeedback(pose=pose, distance_remaining=remaining)
        stray = self._stray(pose)
        if stray > TRACKING_TOLERANCE:
            self._fail(
                ctl,
                pose,
                f"{stray * 100:.1f} cm off its route (tolerance {TRACKING_TOLERANCE * 100:g} cm): pushed or blocked?",
            )
            return
        linear, angular = body.base_velocity()
        settled = abs(linear) < SETTLED_SPEED and abs(angular) < SETTLED_SPEED
        if self.index >= len(self.legs):
            error = wrap_angle(self.goal.pose.yaw - pose.yaw)
            if abs(error) < GOAL_YAW_TOLERANCE and settled:
                base.command(0.0, 0.0)
                self.finish(GoalState.SUCCEEDED, NavigateToPoseResult(pose=pose, message="reached the goal pose"))
                return
            base.command(0.0, self._turn_rate(error))
            progress = abs(error)
        elif self.turning:
            error = wrap_angle(self.legs[self.index].heading - pose.yaw)
            if abs(error) < ALIGNED and settled:
                self.turning = False
            base.command(0.0, self._turn_rate(error) if self.turning else 0.0)
            progress = remaining + 0.3 * abs(error)
        else:
            leg = self.legs[self.index]
            s, e = self._along(pose)
            left = leg.length - s  # negative once past the end: it comes back
            if abs(left) < WAYPOINT_TOLERANCE and settled:
                self.index += 1
                self.turning = True
                base.command(0.0, 0.0)
            else:
                speed = min(
                    self.max_speed, math.sqrt(2.0 * self.accel * 0.8 * abs(left)), SETTLE_GAIN * abs(left) + 0.01
                )
                direction = (-1.0 if leg.backwards else 1.0) * math.copysign(1.0, left)
                # Back onto the line: aim at a point LOOKAHEAD further along it.
                error = wrap_angle(leg.heading - math.atan2(e, LOOKAHEAD) - pose.yaw)
                base.command(direction * speed, self._turn_rate(error))
            progress = remaining
        if progress < self.best_progress - 0.01:
            self.best_progress, self.last_progress = progress, self.clock
        elif self.clock - self.last_progress > STALL_TIME:
            self._fail(ctl, pose, f"stalled for {STALL_TIME:g} s with {remaining:.2f} m to go; is the way blocked?")
        elif self.clock > self.deadline:
            elapsed = ctl.world.sim_time - self.started
            self._fail(ctl, pose, f"timed out after {elapsed:.1f} s with {remaining:.2f} m to go")

    def _brake(self, ctl: Controllers, pose: Pose2D) -> None:
        ctl.base.command(0.0, 0.0)
        linear, angular = ctl.world.robot.base_velocity()
        if abs(linear) < SETTLED_SPEED and abs(angular) < SETTLED_SPEED:
            self.braking = False
            self.legs = self._legs(pose)
            self.deadline = self._deadline()
            self.last_progress = self.clock
            # Checked against the keep-out zones as the goal came, from where the base then was.
            if (reason := ctl.route_check(self.goal, pose)) is not None:
                self._fail(ctl, pose, reason)
                return
        remaining = sum(leg.length for leg in self.legs)
        self.feedback = NavigateToPoseFeedback(pose=pose, distance_remaining=remaining)

    def _turn_rate(self, error: float) -> float:
        magnitude = min(self.max_turn, math.sqrt(2.0 * self.turn_accel * 0.8 * abs(error)), SETTLE_GAIN * abs(error))
        return math.copysign(magnitude, error)

    def _fail(self, ctl: Controllers, pose: Pose2D, why: str) -> None:
        ctl.base.command(0.0, 0.0)
        goal = self.goal.pose
        message = f"navigation to ({goal.x:.2f}, {goal.y:.2f}) aborted at ({pose.x:.2f}, {pose.y:.2f}): {why}"
        self.finish(GoalState.ABORTED, NavigateToPoseResult(pose=pose, message=message), message)


class TrajectoryFollow(GoalMotion[FollowJointTrajectoryFeedback, FollowJointTrajectoryResult]):
    """Linear interpolation of the points under position control, then a short settle.

    The trajectory runs on its own clock, which each tick advances by dt times the speed scale: at
    half speed the arm takes the same path in twice the time; at 0 it holds the current desired
    point. The settle after the last point counts on the same clock.
    """

    kind = "follow_joint_trajectory"

    def __init__(self, ctl: Controllers, goal: FollowJointTrajectoryGoal) -> None:
        super().__init__(ctl)
        self.goal = goal
        self.indices = [ARM_JOINTS.index(name) for name in goal.joint_names]
        times = [p.time_from_start for p in goal.points]
        positions = [p.positions for p in goal.points]
        if times[0] > 0.0:
            current = ctl.world.robot.arm_positions()
            times.insert(0, 0.0)
            positions.insert(0, [current[i] for i in self.indices])
        self.times = np.array(times)
        self.positions = np.array(positions)
        self.final = self.positions[-1]
        self.clock = 0.0  # trajectory time: sim seconds times the speed scale
        self.commanded: np.ndarray | None = None

    def _desired(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        if t >= self.times[-1]:
            return self.final, np.zeros_like(self.final)
        k = int(np.searchsorted(self.times, t, side="right")) - 1
        span = self.times[k + 1] - self.times[k]
        if span <= 0.0:
            return self.positions[k + 1], np.zeros_like(self.final)
        blend = (t - self.times[k]) / span
        desired = self.positions[k] + blend * (self.positions[k + 1] - self.positions[k])
        return desired, (self.positions[k + 1] - self.positions[k]) / span

    def _actual(self, ctl: Controllers) -> np.ndarray:
        arm = ctl.world.robot.arm_positions()
        return np.array([arm[i] for i in self.indices])

    def result_now(self, ctl: Controllers) -> FollowJointTrajectoryResult:
        error = float(np.max(np.abs(self._actual(ctl) - self.final)))
        return FollowJointTrajectoryResult(error=error)

    def tick(self, ctl: Controllers) -> None:
        t = self.clock
        actual = self._actual(ctl)
        # Where the last tick commanded the joints: this tick's position control has moved them there.
        lag = np.abs(actual - self.commanded) if self.commanded is not None else np.zeros_like(actual)
        if float(np.max(lag)) > self.goal.path_tolerance:
            worst = int(np.argmax(lag))
            ctl.arm.hold()
            message = (
                f"{self.goal.joint_names[worst]} was {lag[worst]:.3f} rad from the trajectory at {t:.2f} s "
                f"(path tolerance {self.goal.path_tolerance:g} rad): blocked or pushed"
            )
            result = FollowJointTrajectoryResult(error=float(np.max(np.abs(actual - self.final))), message=message)
            self.finish(GoalState.ABORTED, result, message)
            return
        self.clock += ctl.world.dt * ctl.speed_scale
        desired, velocity = self._desired(t)
        ctl.arm.command(self.indices, desired, velocity * ctl.speed_scale)
        self.commanded = desired
        self.feedback = FollowJointTrajectoryFeedback(
            desired=desired.tolist(), actual=actual.tolist(), time_from_start=t
        )
        if t < self.times[-1]:
            return
        error = float(np.max(np.abs(actual - self.final)))
        if error < self.goal.goal_tolerance:
            self.finish(GoalState.SUCCEEDED, FollowJointTrajectoryResult(error=error, message="reached the last point"))
        elif t > self.times[-1] + TRAJECTORY_SETTLE_TIME:
            message = f"final joint error {error:.3f} rad exceeds the tolerance {self.goal.goal_tolerance:g} rad"
            self.finish(GoalState.ABORTED, FollowJointTrajectoryResult(error=error, message=message), message)


class GripperMotion(GoalMotion[GripperCommandFeedback, GripperCommandResult]):
    """Move both fingers; a closing gripper that stops on an object takes hold of it."""

    kind = "gripper_command"

    def __init__(self, ctl: Controllers, goal: GripperCommandGoal) -> None:
        super().__init__(ctl)
        world = ctl.world
        self.goal = goal
        self.closing = goal.position < world.robot.gripper_gap() - 1e-4
        # The gripper's own clock stands still while paused (speed scale 0: a person is too close
        # for fingers to close); any other scale moves the fingers at their normal speed. The fingers
        # set off at the first tick that may move them: an opening goal that came while paused must
        # not let go of what the hand holds while the goal waits.
        self.clock = 0.0
        self.paused = False
        self.set_off = False
        self.still_since = 0.0

    def _go(self, ctl: Controllers) -> None:
        """The fingers towards the goal's gap; opening lets go of what the hand holds."""
        self.set_off = True
        world = ctl.world
        if self.closing:
            world.fingers_touch_all()
        elif world.holding is not None:
            world.release()
        ctl.fingers.command(self.goal.position, self.goal.max_effort)

    def result_now(self, ctl: Controllers) -> GripperCommandResult:
        gap = ctl.world.robot.gripper_gap()
        return GripperCommandResult(
            position=gap,
            stalled=False,
            reached_goal=abs(gap - self.goal.position) < GRIPPER_REACHED,
            holding=ctl.world.holding,
        )

    def tick(self, ctl: Controllers) -> None:
        world, fingers = ctl.world, ctl.fingers
        gap = world.robot.gripper_gap()
        self.feedback = GripperCommandFeedback(position=gap)
        if ctl.speed_scale <= 0.0:
            if not self.paused:
                self.paused = True
                fingers.command(gap, self.goal.max_effort)
            return
        if self.paused or not self.set_off:
            self.paused = False
            self._go(ctl)
        self.clock += world.dt
        elapsed = self.clock
        reached = abs(gap - self.goal.position) < GRIPPER_REACHED
        if world.robot.finger_speed() > 1e-3:
            self.still_since = self.clock
        still = self.clock - self.still_since > GRIPPER_STILL_TIME and elapsed > GRIPPER_STILL_TIME
        if not (reached or still or elapsed > GRIPPER_TIMEOUT):
            return
        message = f"gripper at {gap * 1000:.0f} mm"
        stalled = False
        if self.closing:
            grasped = world.object_between_fingers()
            if grasped is not None:
                stalled = True
                why_not = world.grasp(grasped, self.goal.payload_limit)
                message = why_not or f"holding {grasped}"
        result = GripperCommandResult(position=gap, stalled=stalled, reached_goal=reached, holding=world.holding)
        self.finish(GoalState.SUCCEEDED, result, message)


class Controllers:
    """The base, arm and gripper controllers and the goals they carry out, one goal per kind: a new
    goal preempts the running one, which ends canceled ("preempted by ...") through the same path as
    a cancel (the base brakes, the arm and fingers hold), as the sim's action servers end it."""

    def __init__(self, world: SimWorld) -> None:
        self.world = world
        self.arm = ArmController(world)
        self.fingers = GripperController(world)
        self.base = BaseController(world)
        # Speed-and-separation: the fraction of normal speed the base and arm may use (0 pauses).
        self.speed_scale = 1.0
        self._cmd_vel: Twist | None = None
        self._cmd_vel_until = 0.0
        self.motions: dict[str, GoalMotion[Any, Any]] = {}
        # The robot's keep-out check of a route it plans itself (a goal without `start`, from where the
        # base comes to rest): why not, or None. The sim node sets it to KeepOut.goal.
        self.route_check: Callable[[NavigateToPoseGoal, Pose2D], str | None] = lambda _goal, _here: None

    @property
    def idle(self) -> bool:
        """No goal running, no cmd_vel in force, the base neither asked to move nor moving as commanded."""
        base = self.base
        return not self.motions and self._cmd_vel is None and base.wanted == base.actual == (0.0, 0.0)

    def tick(self) -> None:
        """Before each physics step: expire cmd_vel, run every goal, set the base's motors."""
        if self._cmd_vel is not None and self.world.sim_time >= self._cmd_vel_until:
            self._cmd_vel = None
            self.base.wanted = (0.0, 0.0)
        for kind, motion in list(self.motions.items()):
            if motion.running:
                motion.tick(self)
            if not motion.running:
                del self.motions[kind]
        if self._cmd_vel is not None and Navigation.kind not in self.motions:
            self.base.wanted = (self._cmd_vel.linear_x, self._cmd_vel.angular_z)
        self.base.apply()

    # Goals

    def _start(self, kind: str, make: Callable[[], M]) -> M:
        # The old goal is canceled (its controller holds) before the new one is made, which may
        # command its controller at once.
        previous = self.motions.get(kind)
        if previous is not None and previous.running:
            self.cancel(previous, GoalState.CANCELED, f"preempted by a new {kind} goal")
        motion = self.motions[kind] = make()
        return motion

    def navigate(self, goal: NavigateToPoseGoal) -> Motion[Any, Any]:
        """Drive the goal's route; refused (ended at once) when the base does not stand where the
        route was checked from: it would drive other legs than those safety approved. A refused goal
        leaves cmd_vel as it was, expiring at its time; a started one ends it."""
        if goal.start is not None and (reason := self._away_from(goal.start)):
            motion = Motion[NavigateToPoseFeedback, NavigateToPoseResult](self.world.sim_time)
            pose = self.world.robot.base_pose()
            motion.finish(GoalState.ABORTED, NavigateToPoseResult(pose=pose, message=reason), reason)
            return motion
        self._cmd_vel = None
        return self._start(Navigation.kind, lambda: Navigation(self, goal))

    def _away_from(self, start: Pose2D) -> str | None:
        here, radius = self.world.robot.base_pose(), self.world.model.base_radius
        if (reason := away_from(here, start, radius)) is not None:
            return reason
        # A base still braking (the goal this one preempted was just canceled) is within reach of
        # `start` now but comes to rest past it, off the legs checked from there.
        (linear, angular), robot = self.base.actual, self.world.spec.robot
        ahead = linear * abs(linear) / (2.0 * robot.max_linear_acceleration)
        turned = angular * abs(angular) / (2.0 * robot.max_angular_acceleration)
        yaw = here.yaw + turned
        rest = Pose2D(x=here.x + ahead * math.cos(here.yaw), y=here.y + ahead * math.sin(here.yaw), yaw=yaw)
        if away_from(rest, start, radius) is None:
            return None
        return (
            f"the route was checked from ({start.x:.2f}, {start.y:.2f}, {start.yaw:.2f} rad) but the base is still "
            f"moving ({linear:.2f} m/s, {angular:.2f} rad/s) and comes to rest at ({rest.x:.2f}, {rest.y:.2f}, "
            f"{wrap_angle(yaw):.2f} rad)"
        )

    def follow_trajectory(self, goal: FollowJointTrajectoryGoal) -> Motion[Any, Any]:
        reason = self.arm.check_trajectory(goal)
        if reason is not None:
            motion = Motion[FollowJointTrajectoryFeedback, FollowJointTrajectoryResult](self.world.sim_time)
            motion.finish(GoalState.ABORTED, FollowJointTrajectoryResult(error=0.0, message=reason), reason)
            return motion
        return self._start(TrajectoryFollow.kind, lambda: TrajectoryFollow(self, goal))

    def gripper(self, goal: GripperCommandGoal) -> GripperMotion:
        return self._start(GripperMotion.kind, lambda: GripperMotion(self, goal))

    def cancel(
        self, motion: Motion[Any, Any], state: GoalState = GoalState.CANCELED, message: str = "canceled"
    ) -> None:
        """End one goal early; the base brakes to rest, the arm holds where it is, and the fingers hold
        where they are (as ros2_control's gripper controller does on a cancel)."""
        if not isinstance(motion, GoalMotion) or not motion.running:
            return
        if isinstance(motion, Navigation):
            self.base.command(0.0, 0.0)
        if isinstance(motion, TrajectoryFollow):
            self.arm.hold()
        if isinstance(motion, GripperMotion):
            self.fingers.hold()
        motion.end(self, state, message)

    # Streams and limits

    def set_cmd_vel(self, twist: Twist, hold_for: float) -> bool:
        """Drive the base at `twist` for `hold_for` sim seconds; refused while navigating."""
        if Navigation.kind in self.motions:
            return False
        self._cmd_vel = twist
        self._cmd_vel_until = self.world.sim_time + hold_for
        return True

    def set_speed_scale(self, scale: float, linear: float | None = None, angular: float | None = None) -> None:
        """Let the base and arm use `scale` (0..1) of their normal speed from the next step on; the
        base at most its own maximum times the scale, and at most `linear` m/s and `angular` rad/s
        when given (a limit given above the scaled one does not raise it).

        The base ramps down to the new limit at its normal deceleration; trajectories slow down in
        time along the same path; navigation's stall and deadline clocks slow down alike; goals keep
        running, even at 0. The gripper is not slowed but pauses at 0.
        """
        self.speed_scale = min(1.0, scale) if scale >= 0.0 else 0.0  # NaN counts as 0
        robot = self.world.spec.robot
        limits = []
        for given, own in ((linear, robot.max_linear_speed), (angular, robot.max_angular_speed)):
            scaled = own * self.speed_scale
            limits.append(scaled if given is None else min(scaled, given) if given >= 0.0 else 0.0)
        self.base.limits = (limits[0], limits[1])

    def stop(self, reason: str) -> None:
        """Base velocity to zero at once, arm and fingers held where they are, every running goal aborted."""
        self._cmd_vel = None
        self.base.halt()
        self.arm.hold()
        self.fingers.hold()
        for motion in list(self.motions.values()):
            motion.end(self, GoalState.ABORTED, reason)
        self.motions.clear()
