"""The simulated household and robot in pybullet: world building, controllers, perception and ground truth.

Pure logic: no Zenoh."""

from __future__ import annotations

import logging
import math
import tempfile
import threading
from pathlib import Path
from typing import Any, Generic, TypeVar

import numpy as np
import pybullet
import pybullet_data
from pybullet_utils import bullet_client
from shapely.geometry import Point

from schemas.actions import GoalState
from schemas.common import ErrorKind, Pose2D, ServiceError, Vec3
from schemas.robot import (
    ARM_JOINTS,
    FINGER_JOINTS,
    GRIPPER_MAX_GAP,
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
    Twist,
)
from schemas.world import (
    Furniture,
    GroundTruth,
    Moved,
    MoveEntity,
    PerceivedHuman,
    PerceivedHumans,
    PerceivedObject,
    PerceivedObjects,
    Wall,
    World,
    WorldObject,
)
from services.footprint import TRACKING_TOLERANCE, route_legs
from services.sim.camera import Camera
from services.sim.config import CameraConfig
from services.sim.detection import Target
from services.sim.robot_urdf import BASE_LINK, BASE_X_JOINT, BASE_Y_JOINT, BASE_YAW_JOINT, mobile_manipulator_urdf
from services.worldmodel import WorldModel, drive_route

log = logging.getLogger(__name__)

F = TypeVar("F")
R = TypeVar("R")
M = TypeVar("M", bound="Motion[Any, Any]")

HAND_LINK = "panda_hand"
FINGER_LINKS: tuple[str, str] = ("panda_leftfinger", "panda_rightfinger")
GRIPPER_OPEN = GRIPPER_MAX_GAP
GRAVITY = -9.81

# The base: wheels are abstracted as velocity motors on planar joints. The force is large so a
# stop takes a few milliseconds, yet finite so furniture still blocks the base.
BASE_FORCE = 4000.0
BASE_TORQUE = 2000.0
# Arm joint torques: the URDF's effort limits, raised so the arm stays stiff while the base brakes.
ARM_FORCES = (300.0, 300.0, 300.0, 300.0, 100.0, 100.0, 100.0)
ARM_POSITION_GAIN = 0.3
FINGER_SPEED = 0.1  # m/s per finger

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

WALL_RGBA = [0.92, 0.9, 0.86, 1.0]
HUMAN_RADIUS = 0.2
HUMAN_HEIGHT = 1.7

# sim/move: an object is let go this far above where it is to rest, so it never starts inside
# anything, and counts as settled once slower than SETTLED_OBJECT_SPEED for SETTLED_OBJECT_TIME.
DROP_HEIGHT = 0.002
SETTLED_OBJECT_SPEED = 0.01
SETTLED_OBJECT_TIME = 0.1
SETTLE_TIMEOUT = 3.0


def _target(obj: WorldObject) -> Target:
    """What the camera looks for: the object's height, and for a box with unequal sides, its sides."""
    footprint = (obj.size.x, obj.size.y) if obj.shape == "box" and abs(obj.size.x - obj.size.y) > 1e-3 else None
    return Target(obj.id, obj.size.z, footprint)


def wrap_angle(angle: float) -> float:
    return math.atan2(math.sin(angle), math.cos(angle))


def _clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))


class Motion(Generic[F, R]):
    """A goal being carried out. The sim thread ticks it; other threads read `feedback` and wait on `done`."""

    kind = "motion"

    def __init__(self, sim: Simulation) -> None:
        self.started = sim.sim_time
        self.feedback: F | None = None
        self.state = GoalState.EXECUTING
        self.result: R | None = None
        self.message = ""
        self.done = threading.Event()

    @property
    def running(self) -> bool:
        return not self.done.is_set()

    def tick(self, sim: Simulation) -> None:
        raise NotImplementedError

    def result_now(self, sim: Simulation) -> R:
        """The result as things stand, for when the motion ends early."""
        raise NotImplementedError

    def finish(self, state: GoalState, result: R, message: str = "") -> None:
        if self.done.is_set():
            return
        self.state, self.result, self.message = state, result, message
        log.info("%s %s: %s", self.kind, state.value, message or "done")
        self.done.set()

    def end(self, sim: Simulation, state: GoalState, message: str) -> None:
        """End early (cancel, abort, stop) with the result as things stand."""
        self.finish(state, self.result_now(sim), message)


class Navigation(Motion[NavigateToPoseFeedback, NavigateToPoseResult]):
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

    def __init__(self, sim: Simulation, goal: NavigateToPoseGoal) -> None:
        super().__init__(sim)
        robot = sim.world.robot
        self.goal = goal
        start = goal.start or sim.base_pose()
        # The same legs safety checked: the path, maybe a pre-goal point, the goal.
        self.legs = route_legs(start, drive_route(start, goal.path, goal.pose))
        self.index = 0
        self.turning = True  # turning at the current leg's start (or, past the last leg, at the goal)
        self.base_radius = sim.model.base_radius
        self.max_speed = min(goal.max_speed or robot.max_linear_speed, robot.max_linear_speed)
        self.max_turn = min(goal.max_turn_rate or robot.max_angular_speed, robot.max_angular_speed)
        self.accel, self.turn_accel = robot.max_linear_acceleration, robot.max_angular_acceleration
        length = sum(leg.length for leg in self.legs)
        turns = len(self.legs) + 1
        self.clock = 0.0
        self.deadline = 2.0 * length / self.max_speed + turns * 2.0 * math.pi / self.max_turn + 10.0
        self.best_progress = math.inf
        self.last_progress = self.clock

    def result_now(self, sim: Simulation) -> NavigateToPoseResult:
        return NavigateToPoseResult(pose=sim.base_pose())

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

    def tick(self, sim: Simulation) -> None:
        self.clock += sim.dt * sim.speed_scale
        pose = sim.base_pose()
        remaining = self._remaining(pose)
        self.feedback = NavigateToPoseFeedback(pose=pose, distance_remaining=remaining)
        stray = self._stray(pose)
        if stray > TRACKING_TOLERANCE:
            self._fail(
                sim,
                pose,
                f"{stray * 100:.1f} cm off its route (tolerance {TRACKING_TOLERANCE * 100:g} cm): pushed or blocked?",
            )
            return
        linear, angular = sim.base_velocity()
        settled = abs(linear) < SETTLED_SPEED and abs(angular) < SETTLED_SPEED
        if self.index >= len(self.legs):
            error = wrap_angle(self.goal.pose.yaw - pose.yaw)
            if abs(error) < GOAL_YAW_TOLERANCE and settled:
                sim.command_base(0.0, 0.0)
                self.finish(GoalState.SUCCEEDED, NavigateToPoseResult(pose=pose, message="reached the goal pose"))
                return
            sim.command_base(0.0, self._turn_rate(error))
            progress = abs(error)
        elif self.turning:
            error = wrap_angle(self.legs[self.index].heading - pose.yaw)
            if abs(error) < ALIGNED and settled:
                self.turning = False
            sim.command_base(0.0, self._turn_rate(error) if self.turning else 0.0)
            progress = remaining + 0.3 * abs(error)
        else:
            leg = self.legs[self.index]
            s, e = self._along(pose)
            left = leg.length - s  # negative once past the end: it comes back
            if abs(left) < WAYPOINT_TOLERANCE and settled:
                self.index += 1
                self.turning = True
                sim.command_base(0.0, 0.0)
            else:
                speed = min(
                    self.max_speed, math.sqrt(2.0 * self.accel * 0.8 * abs(left)), SETTLE_GAIN * abs(left) + 0.01
                )
                direction = (-1.0 if leg.backwards else 1.0) * math.copysign(1.0, left)
                # Back onto the line: aim at a point LOOKAHEAD further along it.
                error = wrap_angle(leg.heading - math.atan2(e, LOOKAHEAD) - pose.yaw)
                sim.command_base(direction * speed, self._turn_rate(error))
            progress = remaining
        if progress < self.best_progress - 0.01:
            self.best_progress, self.last_progress = progress, self.clock
        elif self.clock - self.last_progress > STALL_TIME:
            self._fail(sim, pose, f"stalled for {STALL_TIME:g} s with {remaining:.2f} m to go; is the way blocked?")
        elif self.clock > self.deadline:
            self._fail(sim, pose, f"timed out after {sim.sim_time - self.started:.1f} s with {remaining:.2f} m to go")

    def _turn_rate(self, error: float) -> float:
        magnitude = min(self.max_turn, math.sqrt(2.0 * self.turn_accel * 0.8 * abs(error)), SETTLE_GAIN * abs(error))
        return math.copysign(magnitude, error)

    def _fail(self, sim: Simulation, pose: Pose2D, why: str) -> None:
        sim.command_base(0.0, 0.0)
        goal = self.goal.pose
        message = f"navigation to ({goal.x:.2f}, {goal.y:.2f}) aborted at ({pose.x:.2f}, {pose.y:.2f}): {why}"
        self.finish(GoalState.ABORTED, NavigateToPoseResult(pose=pose, message=message), message)


class TrajectoryFollow(Motion[FollowJointTrajectoryFeedback, FollowJointTrajectoryResult]):
    """Linear interpolation of the points under position control, then a short settle.

    The trajectory runs on its own clock, which each tick advances by dt times the speed scale: at
    half speed the arm takes the same path in twice the time; at 0 it holds the current desired
    point. The settle after the last point counts on the same clock.
    """

    kind = "follow_joint_trajectory"

    def __init__(self, sim: Simulation, goal: FollowJointTrajectoryGoal) -> None:
        super().__init__(sim)
        self.goal = goal
        self.indices = [ARM_JOINTS.index(name) for name in goal.joint_names]
        times = [p.time_from_start for p in goal.points]
        positions = [p.positions for p in goal.points]
        if times[0] > 0.0:
            current = sim.arm_positions()
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

    def _actual(self, sim: Simulation) -> np.ndarray:
        arm = sim.arm_positions()
        return np.array([arm[i] for i in self.indices])

    def result_now(self, sim: Simulation) -> FollowJointTrajectoryResult:
        error = float(np.max(np.abs(self._actual(sim) - self.final)))
        return FollowJointTrajectoryResult(error=error)

    def tick(self, sim: Simulation) -> None:
        t = self.clock
        actual = self._actual(sim)
        # Where the last tick commanded the joints: this tick's position control has moved them there.
        lag = np.abs(actual - self.commanded) if self.commanded is not None else np.zeros_like(actual)
        if float(np.max(lag)) > self.goal.path_tolerance:
            worst = int(np.argmax(lag))
            sim.hold_arm()
            message = (
                f"{self.goal.joint_names[worst]} was {lag[worst]:.3f} rad from the trajectory at {t:.2f} s "
                f"(path tolerance {self.goal.path_tolerance:g} rad): blocked or pushed"
            )
            result = FollowJointTrajectoryResult(error=float(np.max(np.abs(actual - self.final))), message=message)
            self.finish(GoalState.ABORTED, result, message)
            return
        self.clock += sim.dt * sim.speed_scale
        desired, velocity = self._desired(t)
        sim.command_arm(self.indices, desired, velocity * sim.speed_scale)
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


class GripperMotion(Motion[GripperCommandFeedback, GripperCommandResult]):
    """Move both fingers; a closing gripper that stops on an object takes hold of it."""

    kind = "gripper_command"

    def __init__(self, sim: Simulation, goal: GripperCommandGoal) -> None:
        super().__init__(sim)
        self.goal = goal
        self.closing = goal.position < sim.gripper_gap() - 1e-4
        if not self.closing and sim.holding is not None:
            sim.release()
        sim.command_fingers(goal.position, goal.max_effort)
        # The gripper's own clock stands still while paused (speed scale 0: a person is too close
        # for fingers to close); any other scale moves the fingers at their normal speed.
        self.clock = 0.0
        self.paused = False
        self.still_since = 0.0

    def result_now(self, sim: Simulation) -> GripperCommandResult:
        gap = sim.gripper_gap()
        return GripperCommandResult(
            position=gap,
            stalled=False,
            reached_goal=abs(gap - self.goal.position) < GRIPPER_REACHED,
            holding=sim.holding,
        )

    def tick(self, sim: Simulation) -> None:
        gap = sim.gripper_gap()
        self.feedback = GripperCommandFeedback(position=gap)
        if sim.speed_scale <= 0.0:
            if not self.paused:
                self.paused = True
                sim.command_fingers(gap, self.goal.max_effort)
            return
        if self.paused:
            self.paused = False
            sim.command_fingers(self.goal.position, self.goal.max_effort)
        self.clock += sim.dt
        elapsed = self.clock
        reached = abs(gap - self.goal.position) < GRIPPER_REACHED
        if sim.finger_speed() > 1e-3:
            self.still_since = self.clock
        still = self.clock - self.still_since > GRIPPER_STILL_TIME and elapsed > GRIPPER_STILL_TIME
        if not (reached or still or elapsed > GRIPPER_TIMEOUT):
            return
        message = f"gripper at {gap * 1000:.0f} mm"
        stalled = False
        if self.closing:
            grasped = sim.object_between_fingers()
            if grasped is not None:
                stalled = True
                why_not = sim.grasp(grasped, self.goal.payload_limit)
                message = why_not or f"holding {grasped}"
        result = GripperCommandResult(position=gap, stalled=stalled, reached_goal=reached, holding=sim.holding)
        self.finish(GoalState.SUCCEEDED, result, message)


class Drop(Motion[None, Moved]):
    """An object teleported by sim/move and let go: done once it lies still (or has rolled for too long)."""

    kind = "move"

    def __init__(self, sim: Simulation, object_id: str) -> None:
        super().__init__(sim)
        self.object_id = object_id
        self.still_since = sim.sim_time

    def result_now(self, sim: Simulation) -> Moved:
        return Moved(id=self.object_id, position=sim.object_position(self.object_id))

    def tick(self, sim: Simulation) -> None:
        if sim.object_speed(self.object_id) > SETTLED_OBJECT_SPEED:
            self.still_since = sim.sim_time
        if sim.sim_time - self.still_since >= SETTLED_OBJECT_TIME:
            self.finish(GoalState.SUCCEEDED, self.result_now(sim), f"{self.object_id} at rest")
        elif sim.sim_time - self.started > SETTLE_TIMEOUT:
            self.finish(GoalState.SUCCEEDED, self.result_now(sim), f"{self.object_id} still moving")


class Simulation:
    """One household world and one mobile manipulator, stepped by whoever owns this object (one thread)."""

    def __init__(self, world: World, *, physics_hz: float = 240.0, camera: CameraConfig | None = None) -> None:
        self.world = world
        self.model = WorldModel(world)
        self.dt = 1.0 / physics_hz
        self.sim_time = 0.0
        self.holding: str | None = None
        self._grasp_constraint: int | None = None
        self._base_command = (0.0, 0.0)  # what the controllers ask: linear_x, angular_z
        self._base_actual = (0.0, 0.0)  # after the speed scale and the acceleration limits
        # Speed-and-separation: the fraction of normal speed the base and arm may use (0 pauses).
        self.speed_scale = 1.0
        self.base_limits = (self.world.robot.max_linear_speed, self.world.robot.max_angular_speed)
        self._cmd_vel: Twist | None = None
        self._cmd_vel_until = 0.0
        self.motions: dict[str, Motion[Any, Any]] = {}
        self._drops: list[Drop] = []
        self.bullet: Any = bullet_client.BulletClient(connection_mode=pybullet.DIRECT)
        self.bullet.setAdditionalSearchPath(pybullet_data.getDataPath())
        self.bullet.setGravity(0.0, 0.0, GRAVITY)
        self.bullet.setTimeStep(self.dt)
        self.bullet.loadURDF("plane.urdf")
        self.wall_bodies = {w.id: self._add_wall(w) for w in world.walls}
        self.furniture_bodies = {f.id: self._add_furniture(f.center, f.size, f.rgba) for f in world.furniture}
        self.object_bodies = {o.id: self._add_object(o) for o in world.objects}
        self.human_bodies = {h.id: self._add_human(h.pose) for h in world.humans}
        # Where people stand now: they move (sim/move), the world file only says where they start.
        self.human_poses = {h.id: h.pose for h in world.humans}
        self.robot = self._add_robot()
        self.camera = Camera(self.bullet, camera or CameraConfig())
        self._camera_targets = {self.object_bodies[o.id]: _target(o) for o in world.objects}
        log.info("world %s loaded: %d furniture, %d objects", world.name, len(world.furniture), len(world.objects))

    # Building the world

    def _add_furniture(self, center: list[float], size: Any, rgba: list[float]) -> int:
        half = [size.x / 2, size.y / 2, size.z / 2]
        shape = self.bullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=half)
        visual = self.bullet.createVisualShape(pybullet.GEOM_BOX, halfExtents=half, rgbaColor=rgba)
        body: int = self.bullet.createMultiBody(0.0, shape, visual, [center[0], center[1], size.z / 2])
        self.bullet.changeDynamics(body, -1, lateralFriction=1.0)
        return body

    def _add_wall(self, wall: Wall) -> int:
        (x0, y0), (x1, y1) = wall.start, wall.end
        half = [math.dist((x0, y0), (x1, y1)) / 2, wall.thickness / 2, wall.height / 2]
        shape = self.bullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=half)
        visual = self.bullet.createVisualShape(pybullet.GEOM_BOX, halfExtents=half, rgbaColor=WALL_RGBA)
        orientation = self.bullet.getQuaternionFromEuler([0.0, 0.0, math.atan2(y1 - y0, x1 - x0)])
        centre = [(x0 + x1) / 2, (y0 + y1) / 2, wall.height / 2]
        body: int = self.bullet.createMultiBody(0.0, shape, visual, centre, orientation)
        return body

    def _add_object(self, obj: WorldObject) -> int:
        size = obj.size
        if obj.shape == "cylinder":
            shape = self.bullet.createCollisionShape(pybullet.GEOM_CYLINDER, radius=size.x / 2, height=size.z)
            visual = self.bullet.createVisualShape(
                pybullet.GEOM_CYLINDER, radius=size.x / 2, length=size.z, rgbaColor=obj.rgba
            )
        elif obj.shape == "sphere":
            shape = self.bullet.createCollisionShape(pybullet.GEOM_SPHERE, radius=size.x / 2)
            visual = self.bullet.createVisualShape(pybullet.GEOM_SPHERE, radius=size.x / 2, rgbaColor=obj.rgba)
        else:
            half = [size.x / 2, size.y / 2, size.z / 2]
            shape = self.bullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=half)
            visual = self.bullet.createVisualShape(pybullet.GEOM_BOX, halfExtents=half, rgbaColor=obj.rgba)
        where = self.model.initial_position(obj)
        body: int = self.bullet.createMultiBody(obj.mass, shape, visual, [where.x, where.y, where.z])
        self.bullet.changeDynamics(body, -1, lateralFriction=1.0, spinningFriction=0.01, rollingFriction=0.001)
        return body

    def _add_human(self, pose: Pose2D) -> int:
        visual = self.bullet.createVisualShape(
            pybullet.GEOM_CYLINDER, radius=HUMAN_RADIUS, length=HUMAN_HEIGHT, rgbaColor=[0.9, 0.7, 0.5, 1.0]
        )
        body: int = self.bullet.createMultiBody(0.0, -1, visual, [pose.x, pose.y, HUMAN_HEIGHT / 2])
        return body

    def _add_robot(self) -> int:
        spec = self.world.robot
        with tempfile.TemporaryDirectory(prefix="tether-sim-") as tmp:
            path = Path(tmp) / "mobile_panda.urdf"
            path.write_text(mobile_manipulator_urdf(spec))
            robot: int = self.bullet.loadURDF(str(path), useFixedBase=True)
        self.joint_index: dict[str, int] = {}
        self.link_index: dict[str, int] = {}
        for i in range(self.bullet.getNumJoints(robot)):
            info = self.bullet.getJointInfo(robot, i)
            self.joint_index[info[1].decode()] = i
            self.link_index[info[12].decode()] = i
        self._base_joints = [self.joint_index[n] for n in (BASE_X_JOINT, BASE_Y_JOINT, BASE_YAW_JOINT)]
        self._arm_joints = [self.joint_index[n] for n in ARM_JOINTS]
        self._finger_joints = [self.joint_index[n] for n in FINGER_JOINTS]
        self._hand = self.link_index[HAND_LINK]
        self._fingers = [self.link_index[n] for n in FINGER_LINKS]
        self._base_link = self.link_index[BASE_LINK]
        infos = [self.bullet.getJointInfo(robot, j) for j in self._arm_joints]
        # Kept as plain lists so check_trajectory can run on any thread without touching pybullet.
        self._arm_limits = ([float(i[8]) for i in infos], [float(i[9]) for i in infos])
        start = spec.start
        for joint, value in zip(self._base_joints, (start.x, start.y, start.yaw), strict=True):
            self.bullet.resetJointState(robot, joint, value)
        for joint, value in zip(self._arm_joints, spec.home_joints, strict=True):
            self.bullet.resetJointState(robot, joint, value)
        for joint in self._finger_joints:
            self.bullet.resetJointState(robot, joint, GRIPPER_OPEN / 2)
            self.bullet.changeDynamics(robot, joint, lateralFriction=1.0)
        self._arm_targets = np.array(spec.home_joints, dtype=float)
        self._arm_velocities = np.zeros(7)
        self._finger_target, self._finger_force = GRIPPER_OPEN / 2, 40.0
        self.robot = robot
        self._apply_arm()
        self._apply_fingers()
        self._apply_base()
        return robot

    def close(self) -> None:
        self.bullet.disconnect()

    # Stepping

    def step(self, steps: int = 1) -> None:
        """Advance physics by `steps` ticks, running every controller before each."""
        for _ in range(steps):
            if self._cmd_vel is not None and self.sim_time >= self._cmd_vel_until:
                self._cmd_vel = None
                self._base_command = (0.0, 0.0)
            for kind, motion in list(self.motions.items()):
                if motion.running:
                    motion.tick(self)
                if not motion.running:
                    del self.motions[kind]
            for drop in self._drops:
                drop.tick(self)
            self._drops = [d for d in self._drops if d.running]
            if self._cmd_vel is not None and "navigate_to_pose" not in self.motions:
                self._base_command = (self._cmd_vel.linear_x, self._cmd_vel.angular_z)
            self._apply_base()
            self.bullet.stepSimulation()
            self.sim_time += self.dt

    def run(self, motion: Motion[F, R], timeout: float) -> Motion[F, R]:
        """Step until `motion` ends, or abort it after `timeout` sim seconds. For tests and scripts."""
        deadline = self.sim_time + timeout
        while motion.running and self.sim_time < deadline:
            self.step()
        if motion.running:
            self.cancel(motion, GoalState.ABORTED, f"{motion.kind} did not finish within {timeout:g} s")
        return motion

    def settle(self, seconds: float) -> None:
        self.step(max(1, round(seconds / self.dt)))

    # Goals

    def _start(self, motion: M) -> M:
        previous = self.motions.get(motion.kind)
        if previous is not None and previous.running:
            previous.end(self, GoalState.ABORTED, f"preempted by a new {motion.kind} goal")
        self.motions[motion.kind] = motion
        return motion

    def navigate(self, goal: NavigateToPoseGoal) -> Motion[Any, Any]:
        """Drive the goal's route; refused (ended at once) when the base does not stand where the
        route was checked from: it would drive other legs than those safety approved."""
        self._cmd_vel = None
        if goal.start is not None and (reason := self._away_from(goal.start)):
            motion = Motion[NavigateToPoseFeedback, NavigateToPoseResult](self)
            motion.finish(GoalState.ABORTED, NavigateToPoseResult(pose=self.base_pose(), message=reason), reason)
            return motion
        return self._start(Navigation(self, goal))

    def _away_from(self, start: Pose2D) -> str | None:
        here = self.base_pose()
        off = math.dist((here.x, here.y), (start.x, start.y)) + self.model.base_radius * abs(
            wrap_angle(here.yaw - start.yaw)
        )
        if off <= TRACKING_TOLERANCE:
            return None
        return (
            f"the route was checked from ({start.x:.2f}, {start.y:.2f}, {start.yaw:.2f} rad) but the base stands at "
            f"({here.x:.2f}, {here.y:.2f}, {here.yaw:.2f} rad)"
        )

    def check_trajectory(self, goal: FollowJointTrajectoryGoal) -> str | None:
        """Why a trajectory goal cannot run, or None when it can. Safe from any thread."""
        unknown = [n for n in goal.joint_names if n not in ARM_JOINTS]
        if unknown:
            return f"unknown joints {unknown}; this arm has {list(ARM_JOINTS)}"
        if len(set(goal.joint_names)) != len(goal.joint_names):
            return f"joint names repeat: {goal.joint_names}"
        lower, upper = self.arm_limits()
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

    def follow_trajectory(self, goal: FollowJointTrajectoryGoal) -> Motion[Any, Any]:
        reason = self.check_trajectory(goal)
        if reason is not None:
            motion = Motion[FollowJointTrajectoryFeedback, FollowJointTrajectoryResult](self)
            motion.finish(GoalState.ABORTED, FollowJointTrajectoryResult(error=0.0, message=reason), reason)
            return motion
        return self._start(TrajectoryFollow(self, goal))

    def gripper(self, goal: GripperCommandGoal) -> GripperMotion:
        return self._start(GripperMotion(self, goal))

    def cancel(
        self, motion: Motion[Any, Any], state: GoalState = GoalState.CANCELED, message: str = "canceled"
    ) -> None:
        """End one motion early; the base stops and the arm holds where it is."""
        if not motion.running:
            return
        if isinstance(motion, Navigation):
            self.command_base(0.0, 0.0)
        if isinstance(motion, TrajectoryFollow):
            self.hold_arm()
        motion.end(self, state, message)

    def set_cmd_vel(self, twist: Twist, hold_for: float) -> bool:
        """Drive the base at `twist` for `hold_for` sim seconds; refused while navigating."""
        if "navigate_to_pose" in self.motions:
            return False
        self._cmd_vel = twist
        self._cmd_vel_until = self.sim_time + hold_for
        return True

    def set_speed_scale(self, scale: float, linear: float | None = None, angular: float | None = None) -> None:
        """Let the base and arm use `scale` (0..1) of their normal speed from the next step on; the
        base at most `linear` m/s and `angular` rad/s when given (else its own maximum times the scale).

        The base ramps down to the new limit at its normal deceleration; trajectories slow down in
        time along the same path; navigation's stall and deadline clocks slow down alike; goals keep
        running, even at 0. The gripper is not slowed but pauses at 0.
        """
        self.speed_scale = min(1.0, scale) if scale >= 0.0 else 0.0  # NaN counts as 0
        robot = self.world.robot
        limits = []
        for given, own in ((linear, robot.max_linear_speed), (angular, robot.max_angular_speed)):
            limit = own * self.speed_scale if given is None else min(own, given) if given >= 0.0 else 0.0
            limits.append(limit)
        self.base_limits = (limits[0], limits[1])

    def stop(self, reason: str) -> None:
        """Base velocity to zero at once, arm held where it is, every running goal aborted."""
        self._cmd_vel = None
        self._base_command = self._base_actual = (0.0, 0.0)
        self._apply_base()
        self.hold_arm()
        for motion in list(self.motions.values()):
            motion.end(self, GoalState.ABORTED, reason)
        self.motions.clear()

    # Actuators

    def command_base(self, linear_x: float, angular_z: float) -> None:
        robot = self.world.robot
        self._base_command = (
            _clamp(linear_x, robot.max_linear_speed),
            _clamp(angular_z, robot.max_angular_speed),
        )

    def _apply_base(self) -> None:
        robot = self.world.robot
        want_v = _clamp(self._base_command[0], self.base_limits[0])
        want_w = _clamp(self._base_command[1], self.base_limits[1])
        have_v, have_w = self._base_actual
        dv, dw = robot.max_linear_acceleration * self.dt, robot.max_angular_acceleration * self.dt
        v = have_v + max(-dv, min(dv, want_v - have_v))
        w = have_w + max(-dw, min(dw, want_w - have_w))
        self._base_actual = (v, w)
        yaw = self.base_pose().yaw
        self.bullet.setJointMotorControlArray(
            self.robot,
            self._base_joints,
            pybullet.VELOCITY_CONTROL,
            targetVelocities=[v * math.cos(yaw), v * math.sin(yaw), w],
            forces=[BASE_FORCE, BASE_FORCE, BASE_TORQUE],
        )

    def command_arm(self, indices: list[int], positions: np.ndarray, velocities: np.ndarray) -> None:
        self._arm_targets[indices] = positions
        self._arm_velocities[:] = 0.0
        self._arm_velocities[indices] = velocities
        self._apply_arm()

    def hold_arm(self) -> None:
        self._arm_targets = np.array(self.arm_positions())
        self._arm_velocities = np.zeros(7)
        self._apply_arm()

    def _apply_arm(self) -> None:
        self.bullet.setJointMotorControlArray(
            self.robot,
            self._arm_joints,
            pybullet.POSITION_CONTROL,
            targetPositions=self._arm_targets.tolist(),
            targetVelocities=self._arm_velocities.tolist(),
            forces=list(ARM_FORCES),
            positionGains=[ARM_POSITION_GAIN] * 7,
        )

    def command_fingers(self, gap: float, max_effort: float) -> None:
        self._finger_target = min(max(gap, 0.0), GRIPPER_OPEN) / 2
        self._finger_force = max_effort
        self._apply_fingers()

    def _apply_fingers(self) -> None:
        for joint in self._finger_joints:
            self.bullet.setJointMotorControl2(
                self.robot,
                joint,
                pybullet.POSITION_CONTROL,
                targetPosition=self._finger_target,
                force=self._finger_force,
                maxVelocity=FINGER_SPEED,
            )

    # Grasping

    def object_between_fingers(self) -> str | None:
        """The object both fingers touch: only that one is held."""
        for object_id, body in self.object_bodies.items():
            if all(self.bullet.getContactPoints(self.robot, body, link, -1) for link in self._fingers):
                return object_id
        return None

    def grasp(self, object_id: str, payload_limit: float | None = None) -> str | None:
        """Fix the object to the hand; the reason when it cannot be held (too heavy), else None."""
        obj = self.model.objects[object_id]
        payload = min(self.world.robot.payload, payload_limit or self.world.robot.payload)
        if obj.mass > payload:
            return f"{object_id} weighs {obj.mass:g} kg, over the {payload:g} kg payload; it slips out"
        body = self.object_bodies[object_id]
        hand_com = self.bullet.getLinkState(self.robot, self._hand)[0:2]
        object_pose = self.bullet.getBasePositionAndOrientation(body)
        inverse = self.bullet.invertTransform(*hand_com)
        relative = self.bullet.multiplyTransforms(inverse[0], inverse[1], *object_pose)
        # A real friction grasp in pybullet is flaky; a fixed constraint stands in for the grip.
        self._grasp_constraint = self.bullet.createConstraint(
            self.robot,
            self._hand,
            body,
            -1,
            pybullet.JOINT_FIXED,
            [0, 0, 0],
            relative[0],
            [0, 0, 0],
            relative[1],
            [0, 0, 0, 1],
        )
        self.bullet.changeConstraint(self._grasp_constraint, maxForce=200.0)
        self.holding = object_id
        return None

    def release(self) -> None:
        if self._grasp_constraint is not None:
            self.bullet.removeConstraint(self._grasp_constraint)
        self._grasp_constraint = None
        self.holding = None

    # Sensing

    def base_pose(self) -> Pose2D:
        x, y, yaw = (s[0] for s in self.bullet.getJointStates(self.robot, self._base_joints))
        return Pose2D(x=x, y=y, yaw=wrap_angle(yaw))

    def base_velocity(self) -> tuple[float, float]:
        """Measured linear_x and angular_z in the base frame."""
        states = self.bullet.getJointStates(self.robot, self._base_joints)
        yaw = states[2][0]
        vx, vy, w = (s[1] for s in states)
        return vx * math.cos(yaw) + vy * math.sin(yaw), w

    def base_speed(self) -> float:
        vx, vy = (s[1] for s in self.bullet.getJointStates(self.robot, self._base_joints[:2]))
        return math.hypot(vx, vy)

    def arm_positions(self) -> list[float]:
        return [s[0] for s in self.bullet.getJointStates(self.robot, self._arm_joints)]

    def arm_limits(self) -> tuple[list[float], list[float]]:
        """Lower and upper limits of the seven arm joints, from the URDF."""
        return self._arm_limits

    def gripper_gap(self) -> float:
        return float(sum(s[0] for s in self.bullet.getJointStates(self.robot, self._finger_joints)))

    def finger_speed(self) -> float:
        return float(max(abs(s[1]) for s in self.bullet.getJointStates(self.robot, self._finger_joints)))

    def joint_state(self, stamp: float) -> JointState:
        joints = [*self._arm_joints, *self._finger_joints]
        states = self.bullet.getJointStates(self.robot, joints)
        return JointState(
            stamp=stamp,
            name=[*ARM_JOINTS, *FINGER_JOINTS],
            position=[s[0] for s in states],
            velocity=[s[1] for s in states],
        )

    def odometry(self, stamp: float) -> Odometry:
        linear, angular = self.base_velocity()
        return Odometry(stamp=stamp, sim_time=self.sim_time, pose=self.base_pose(), linear_x=linear, angular_z=angular)

    def object_position(self, object_id: str) -> Vec3:
        (x, y, z), _ = self.bullet.getBasePositionAndOrientation(self.object_bodies[object_id])
        return Vec3(x=x, y=y, z=z)

    def object_speed(self, object_id: str) -> float:
        linear, _ = self.bullet.getBaseVelocity(self.object_bodies[object_id])
        return float(np.linalg.norm(linear))

    def _report(
        self, obj: WorldObject, position: Vec3, on: str | None, stamp: float, yaw: float | None = None
    ) -> PerceivedObject:
        room = self.model.room_of(position.x, position.y)
        return PerceivedObject(
            id=obj.id,
            name=obj.name,
            cls=obj.cls,
            color=obj.color,
            position=position,
            room=room,
            on=on,
            stamp=stamp,
            yaw=yaw,
        )

    def _exact(self, obj: WorldObject, stamp: float) -> PerceivedObject:
        position = self.object_position(obj.id)
        on = "gripper" if obj.id == self.holding else self.model.support_under(position, obj.size.z / 2)
        yaw = None
        if self._camera_targets[self.object_bodies[obj.id]].footprint is not None:
            _, orientation = self.bullet.getBasePositionAndOrientation(self.object_bodies[obj.id])
            heading = self.bullet.getEulerFromQuaternion(orientation)[2]
            yaw = math.atan(math.tan(heading)) if abs(math.cos(heading)) > 1e-9 else math.pi / 2
        return self._report(obj, position, on, stamp, yaw)

    def perceived_objects(self, stamp: float) -> PerceivedObjects:
        """What the camera sees from where the base stands, and what the gripper holds: the robot
        knows what it grasped without looking, so that one is exact and `on` the gripper."""
        targets = {body: t for body, t in self._camera_targets.items() if t.name != self.holding}
        seen = self.camera.look(self.base_pose(), targets)
        objects = []
        for obj in self.world.objects:
            if obj.id == self.holding:
                objects.append(self._exact(obj, stamp))
            elif obj.id in seen:
                x, y, z = (float(v) for v in seen[obj.id].centre)
                position = Vec3(x=x, y=y, z=z)
                on = self.model.support_under(position, obj.size.z / 2)
                objects.append(self._report(obj, position, on, stamp, seen[obj.id].yaw))
        return PerceivedObjects(stamp=stamp, objects=objects)

    def camera_picture(self) -> np.ndarray:
        """What the robot's camera sees now, in colour (see Camera.picture)."""
        return self.camera.picture(self.base_pose())

    def perceived_humans(self, stamp: float) -> PerceivedHumans:
        """Every person where they stand: a people tracker, not the camera."""
        humans = []
        for human in self.world.humans:
            pose = self.human_poses[human.id]
            room = self.model.room_of(pose.x, pose.y)
            humans.append(PerceivedHuman(id=human.id, name=human.name, pose=pose, room=room))
        return PerceivedHumans(stamp=stamp, humans=humans)

    def ground_truth(self) -> GroundTruth:
        """The simulator's own state: every object exactly where it is, seen or not."""
        return GroundTruth(
            sim_time=self.sim_time,
            robot=self.base_pose(),
            linear_speed=self.base_speed(),
            holding=self.holding,
            objects=[self._exact(o, self.sim_time) for o in self.world.objects],
        )

    # The world changing under the robot's feet (sim/move)

    def move(self, request: MoveEntity) -> Drop | Moved | ServiceError:
        """Teleport a person (done at once) or an object (let go to settle: wait for the Drop), or say
        why not."""
        refusal = self._move_refusal(request)
        if refusal is not None:
            return refusal
        if request.id in self.human_bodies:
            return self._move_human(request)
        return self._drop_object(request)

    def _move_refusal(self, request: MoveEntity) -> ServiceError | None:
        entities = [*self.object_bodies, *self.human_bodies]
        if request.id not in entities:
            message = f"no object or person {request.id!r} in the world {self.world.name!r}"
            return ServiceError(kind=ErrorKind.INVALID_REQUEST, message=message, candidates=sorted(entities))
        if self.model.room_of(request.x, request.y) is None:
            message = f"({request.x:g}, {request.y:g}) is outside every room of the world {self.world.name!r}"
            return ServiceError(kind=ErrorKind.INVALID_REQUEST, message=message)
        if request.id == self.holding:
            message = f"{request.id} is in the robot's gripper; the robot has to put it down first"
            return ServiceError(kind=ErrorKind.PRECONDITION, message=message)
        if self._under_the_robot(request.x, request.y):
            message = f"({request.x:g}, {request.y:g}) is where the robot stands"
            return ServiceError(kind=ErrorKind.INVALID_REQUEST, message=message)
        furniture = self._furniture_at(request.x, request.y)
        if furniture is not None and request.z is not None and request.z < furniture.size.z:
            message = f"z = {request.z:g} m is inside the {furniture.name}, whose top is at {furniture.size.z:g} m"
            return ServiceError(kind=ErrorKind.INVALID_REQUEST, message=message)
        return None

    def _under_the_robot(self, x: float, y: float) -> bool:
        base, size = self.base_pose(), self.world.robot.base_size
        dx, dy = x - base.x, y - base.y
        ahead = dx * math.cos(base.yaw) + dy * math.sin(base.yaw)
        left = -dx * math.sin(base.yaw) + dy * math.cos(base.yaw)
        return abs(ahead) <= size.x / 2 and abs(left) <= size.y / 2

    def _furniture_at(self, x: float, y: float) -> Furniture | None:
        point = Point(x, y)
        return next((f for f in self.world.furniture if self.model.footprint(f).covers(point)), None)

    def _move_human(self, request: MoveEntity) -> Moved:
        current = self.human_poses[request.id]
        yaw = current.yaw if request.yaw is None else request.yaw
        self.human_poses[request.id] = Pose2D(x=request.x, y=request.y, yaw=yaw)
        orientation = self.bullet.getQuaternionFromEuler([0.0, 0.0, yaw])
        self.bullet.resetBasePositionAndOrientation(
            self.human_bodies[request.id], [request.x, request.y, HUMAN_HEIGHT / 2], orientation
        )
        log.info("moved %s to (%.2f, %.2f)", request.id, request.x, request.y)
        return Moved(id=request.id, position=Vec3(x=request.x, y=request.y, z=0.0))

    def _drop_object(self, request: MoveEntity) -> Drop:
        """Upright at (x, y) with its bottom at z, or on whatever furniture is there, else the floor."""
        obj = self.model.objects[request.id]
        body = self.object_bodies[request.id]
        if request.z is not None:
            bottom = request.z
        else:
            furniture = self._furniture_at(request.x, request.y)
            bottom = furniture.size.z if furniture is not None else 0.0
        _, orientation = self.bullet.getBasePositionAndOrientation(body)
        yaw = self.bullet.getEulerFromQuaternion(orientation)[2] if request.yaw is None else request.yaw
        centre = [request.x, request.y, bottom + obj.size.z / 2 + DROP_HEIGHT]
        self.bullet.resetBasePositionAndOrientation(body, centre, self.bullet.getQuaternionFromEuler([0.0, 0.0, yaw]))
        self.bullet.resetBaseVelocity(body, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
        log.info("moved %s to (%.2f, %.2f, %.2f); letting it settle", request.id, *centre)
        drop = Drop(self, request.id)
        self._drops.append(drop)
        return drop
