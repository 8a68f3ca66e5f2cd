"""Collision-free arm motions: the arm, its base and the scene in pinocchio and coal, OMPL between them.

Frames: poses and positions are in panda_link0, the arm's base frame (x ahead of the robot, z up),
for one base pose; scene input (obstacles, objects) is in the map frame and placed by
`arm_from_map`. Joint vectors are the seven arm joints in ARM_JOINTS order. The fingers are modelled
open (0.04 m each), as they are while the arm moves; holding something they are closer, never wider.

Collisions: the arm's links (convex hulls of the URDF's collision meshes) against each other, and
against the robot's base box, the floor, the walls and furniture within reach and the objects; a
held object moves with the hand and is checked against all of these but the hand and fingers
holding it. Scene obstacles are kept `padding` away (a security margin); links need only not touch.
Link pairs on one rigid body or adjacent in the URDF (their meshes overlap at the joint), and pairs
touching in nearly every configuration, are never checked; every other pair is, the hand against
link0 and the base included.

Contacts a motion needs are allowed per call, by name: `("red_cup", GRIPPER)` while the fingers
close on the cup, `("red_cup", "kitchen_counter")` while a held cup leaves the counter. A start or
goal inside the padding of something but not touching it (the hand just above a released object)
is accepted: those pairs are checked without padding within `endpoint_radius` of it, so a motion
can leave. A start that really touches something is refused, naming the contact, unless that
contact is allowed: move away first with `cartesian(..., allowed=...)`.
"""

from __future__ import annotations

import itertools
import math
import random
import threading
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import coal
import numpy as np
import pinocchio as pin
from ompl import base as ob
from ompl import geometric as og
from shapely.geometry import Point

from schemas.common import Pose2D, Vec3
from schemas.robot import ARM_JOINTS, FINGER_JOINTS, GRIPPER_MAX_GAP, MAX_TRAJECTORY_POINTS, TrajectoryPoint
from schemas.world import WorldObject
from services.executor.errors import Canceled, IKFailed, PlanningFailed
from services.executor.grasps import Grasp, Placement
from services.executor.kinematics import ArmKinematics, arm_from_map, rotation_z
from services.executor.omplsetup import Guard, solving
from services.robotmodel import GRASP_FRAME, arm_urdf_path
from services.worldmodel import WorldModel

# Names for several geometries at once, in allowed contacts.
GRIPPER = "gripper"  # the hand and both fingers
ARM = "arm"  # every link of the arm
GRIPPER_LINKS = ("panda_hand", "panda_leftfinger", "panda_rightfinger")
BASE = "robot_base"
FLOOR = "floor"
# A pair touching in at least this share of random configurations is a modelling artefact (meshes
# overlapping at a joint), not a collision to avoid. Sampled once per model, deterministically.
ALWAYS_IN_CONTACT = 0.95
EXCLUSION_SAMPLES = 300
EXCLUSION_SEED = 11
FLOOR_HALF_SIZE = 2.0
FLOOR_THICKNESS = 0.1
# A waypoint where some joint's share of the direction changes by more than this is a corner to
# stop at; gentler bends (a straight line of the hand, in joint space) are passed through.
SHARP_TURN = 0.5
# Largest turn of the hand between two IK points of a straight move (rad).
CARTESIAN_TURN_STEP = 0.05
# How far the wrist (joint 7) gets from the shoulder (joint 2): sampled once, plus a margin, beyond
# which a pose is out of reach without asking IK; past COMFORTABLE_REACH of that, candidates are
# tried last (IK there mostly fails, slowly).
REACH_SAMPLES = 4000
REACH_MARGIN = 0.03
COMFORTABLE_REACH = 0.93
# A search that finds no path says what blocks: the contacts of a sample of this many of the
# configurations it rejected (a uniform, seeded sample), the commonest this many of them.
REJECTED_SAMPLE = 100
BLOCKERS_SHOWN = 3
# Rounds of slowing corners down before timing a path gives up.
TIMING_ROUNDS = 100

Contact = tuple[str, str]


@dataclass(frozen=True)
class ArmPlannerConfig:
    """The arm planner's tunables. Lengths in metres, angles in radians, times in seconds."""

    planning_time: float = 1.0  # RRTConnect's budget for one path
    resolution: float = 0.02  # largest joint step between two collision checks along a motion
    padding: float = 0.01  # kept between the robot (and what it holds) and the scene
    limit_margin: float = 0.02  # planned joints stay this far inside the URDF limits (safety wants 0.01)
    reach: float = 1.2  # scene obstacles farther than this from panda_link0 (horizontally) are left out
    endpoint_radius: float = 0.2  # how far (largest joint difference) a padding contact at an end is forgiven
    cartesian_step: float = 0.01  # between IK points along a straight move of the grasp frame
    max_joint_jump: float = 0.25  # between two IK points of a straight move: more is a flip, not a line
    ik_random_seeds: int = 16  # IK restarts beyond the caller's seed and the hints
    sample_period: float = 0.04  # between trajectory samples, at most
    seed: int = 1  # OMPL's random seed, set for each plan: the same request gives the same path

    def __post_init__(self) -> None:
        for name in (
            "planning_time",
            "resolution",
            "reach",
            "cartesian_step",
            "max_joint_jump",
            "sample_period",
        ):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"ArmPlannerConfig.{name} must be a positive number, got {value!r}")
        for name in ("padding", "limit_margin", "endpoint_radius"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"ArmPlannerConfig.{name} must be zero or positive, got {value!r}")
        if self.resolution > 0.2:
            raise ValueError(f"ArmPlannerConfig.resolution {self.resolution} rad is too coarse to check collisions")
        if self.ik_random_seeds < 0:
            raise ValueError(f"ArmPlannerConfig.ik_random_seeds must be >= 0, got {self.ik_random_seeds}")
        if self.seed <= 0:
            raise ValueError(f"ArmPlannerConfig.seed must be positive (OMPL takes 0 as 'random'), got {self.seed}")


@dataclass(frozen=True)
class SceneObject:
    """A movable object where perception sees it: its centre (map frame) and heading."""

    obj: WorldObject
    position: Vec3
    yaw: float = 0.0


@dataclass(frozen=True)
class HeldObject:
    """An object in the hand: `in_grasp` is its pose in the grasp frame (Grasp.object_in_grasp)."""

    obj: WorldObject
    in_grasp: pin.SE3


@dataclass(frozen=True)
class PickPlan:
    """The joint paths of one pick, in order: through free space to the pre-grasp; straight in to
    the grasp (fingers open); after closing, straight up with the object; to the stowed pose."""

    grasp: Grasp
    to_pregrasp: list[np.ndarray]
    approach: list[np.ndarray]
    lift: list[np.ndarray]
    to_stow: list[np.ndarray] | None = None


@dataclass(frozen=True)
class PlacePlan:
    """The joint paths of one place, in order: through free space to above the spot; straight down
    (object held); after opening, straight back along the approach; to the stowed pose."""

    placement: Placement
    to_preplace: list[np.ndarray]
    lower: list[np.ndarray]
    retreat: list[np.ndarray]
    to_stow: list[np.ndarray] | None = None


def shape_of(obj: WorldObject) -> coal.ShapeBase:
    """The object's collision shape about its centre, upright, as the sim builds it."""
    size = obj.size
    if obj.shape == "cylinder":
        return coal.Cylinder(size.x / 2, size.z)
    if obj.shape == "sphere":
        return coal.Sphere(size.x / 2)
    return coal.Box(size.x, size.y, size.z)


class RobotGeometry:
    """The arm's kinematic and collision model, built once: links as convex hulls, fingers open."""

    def __init__(self, arm_urdf: str | Path) -> None:
        path = arm_urdf_path(arm_urdf)
        full = pin.buildModelFromUrdf(str(path))
        geometry = pin.buildGeomFromUrdf(full, str(path), pin.GeometryType.COLLISION, package_dirs=[str(path.parent)])
        fingers = [full.getJointId(name) for name in FINGER_JOINTS if full.existJointName(name)]
        q_locked = pin.neutral(full)
        for joint in fingers:
            q_locked[full.idx_qs[joint]] = GRIPPER_MAX_GAP / 2
        self.model, (self.geometry,) = pin.buildReducedModel(full, [geometry], fingers, q_locked)
        for item in self.geometry.geometryObjects:
            if isinstance(item.geometry, coal.BVHModelBase):
                # Convex hulls check in microseconds, and err on the side of a collision.
                item.geometry.buildConvexRepresentation(False)
                item.geometry = item.geometry.convex
            # buildGeomFromUrdf names a link's collision elements link_0, link_1, ...
            stem, _, number = item.name.rpartition("_")
            item.name = stem if number.isdigit() else item.name
        self.names: tuple[str, ...] = tuple(item.name for item in self.geometry.geometryObjects)
        self.grasp_frame = self.model.getFrameId(GRASP_FRAME)
        self.grasp_joint = self.model.frames[self.grasp_frame].parentJoint
        self.gripper = tuple(i for i, name in enumerate(self.names) if name in GRIPPER_LINKS)
        self.excluded = self._excluded_pairs()
        self.shoulder, self.wrist_in_grasp, self.reach = self._reach()

    def _reach(self) -> tuple[np.ndarray, pin.SE3, float]:
        """The shoulder (joint 2) in panda_link0, the wrist (the grasp frame's joint) seen from the
        grasp frame, and how far the wrist gets from the shoulder."""
        data = self.model.createData()
        pin.forwardKinematics(self.model, data, pin.neutral(self.model))
        shoulder = np.array(data.oMi[min(2, self.model.njoints - 1)].translation)
        wrist_in_grasp = self.model.frames[self.grasp_frame].placement.inverse()
        farthest = 0.0
        for q in self._samples(REACH_SAMPLES):
            pin.forwardKinematics(self.model, data, q)
            farthest = max(farthest, float(np.linalg.norm(data.oMi[self.grasp_joint].translation - shoulder)))
        return shoulder, wrist_in_grasp, farthest + REACH_MARGIN

    def _samples(self, count: int) -> np.ndarray:
        """`count` configurations drawn uniformly within the joint limits, the same at every start (seeded),
        in one draw: the same rows as `count` draws of one each, without numpy's checks of the limits on
        each draw (they were half of the 0.43 s of CPU this model took to build; 0.22 s now)."""
        rng = np.random.default_rng(EXCLUSION_SEED)
        return rng.uniform(self.model.lowerPositionLimit, self.model.upperPositionLimit, (count, self.model.nq))

    def stretch(self, pose: pin.SE3) -> float:
        """How far the wrist is from the shoulder with the grasp frame at `pose`: beyond `reach`, out of reach."""
        return float(np.linalg.norm((pose * self.wrist_in_grasp).translation - self.shoulder))

    def moving(self, index: int) -> bool:
        return self.geometry.geometryObjects[index].parentJoint != 0

    def _parent_link(self, frame: int) -> int | None:
        """The nearest link above `frame` in the URDF tree that has collision geometry."""
        with_geometry = {item.parentFrame for item in self.geometry.geometryObjects}
        seen = {frame}
        while True:
            parent = self.model.frames[frame].parentFrame
            if parent in seen:  # the universe, or a locked joint's frame pointing at itself
                return None
            seen.add(parent)
            if self.model.frames[parent].type == pin.FrameType.BODY and parent in with_geometry:
                return parent
            frame = parent

    def _adjacent(self, a: int, b: int) -> bool:
        first, second = self.geometry.geometryObjects[a], self.geometry.geometryObjects[b]
        if first.parentJoint == second.parentJoint:
            return True  # one rigid body: they never move relative to each other
        return self._parent_link(first.parentFrame) == second.parentFrame or (
            self._parent_link(second.parentFrame) == first.parentFrame
        )

    def _excluded_pairs(self) -> frozenset[tuple[int, int]]:
        """Pairs never checked: one rigid body or adjacent links, or touching in nearly every configuration."""
        pairs = [
            (a, b) for a, b in itertools.combinations(range(len(self.names)), 2) if self.moving(a) or self.moving(b)
        ]
        excluded = {(a, b) for a, b in pairs if self._adjacent(a, b)}
        candidates = [pair for pair in pairs if pair not in excluded]
        geometry = pin.GeometryModel()
        for item in self.geometry.geometryObjects:
            geometry.addGeometryObject(item)
        for a, b in candidates:
            geometry.addCollisionPair(pin.CollisionPair(a, b))
        data, geometry_data = self.model.createData(), geometry.createData()
        hits = np.zeros(len(candidates))
        for q in self._samples(EXCLUSION_SAMPLES):
            pin.computeCollisions(self.model, data, geometry, geometry_data, q, False)
            hits += [result.isCollision() for result in geometry_data.collisionResults]
        always = {pair for pair, n in zip(candidates, hits, strict=True) if n >= ALWAYS_IN_CONTACT * EXCLUSION_SAMPLES}
        return frozenset(excluded | always)

    def excluded_names(self) -> list[Contact]:
        return sorted((self.names[a], self.names[b]) for a, b in self.excluded)


class ArmPlanner:
    """The robot's collision model, built once (about 0.2 s of CPU); `scene()` gives a planning scene."""

    def __init__(
        self, world: WorldModel, config: ArmPlannerConfig | None = None, kinematics: ArmKinematics | None = None
    ) -> None:
        self.world = world
        self.config = config or ArmPlannerConfig()
        self.robot = RobotGeometry(world.world.robot.arm_urdf)
        self.kin = kinematics or ArmKinematics(world.world.robot.arm_urdf)
        self.mount = world.world.robot.arm_mount
        self.home = np.array(world.world.robot.home_joints, dtype=float)

    def scene(self, base: Pose2D, objects: Iterable[SceneObject] = (), held: HeldObject | None = None) -> ArmScene:
        """The scene with the base at `base` (map frame): walls and furniture within reach,
        `objects` where they are (the held one left out), and `held` in the hand."""
        return ArmScene(self, base, tuple(objects), held)


class _PairChecker:
    """The pair checks with some pairs off and some without their padding, with scratch space."""

    def __init__(self, scene: ArmScene, off: frozenset[int], unpadded: frozenset[int]) -> None:
        self.data = scene.geometry.createData()
        for k, request in enumerate(self.data.collisionRequests):
            request.security_margin = 0.0 if k in unpadded else float(scene.margins[k])
        for k in off:
            self.data.deactivateCollisionPair(k)
        self.kinematics = scene.model.createData()


class ArmScene:
    """One base pose's collision world and the motions planned in it. One thread at a time."""

    def __init__(
        self, planner: ArmPlanner, base: Pose2D, objects: tuple[SceneObject, ...], held: HeldObject | None
    ) -> None:
        self.planner = planner
        self.config = planner.config
        self.kin = planner.kin
        self.robot = planner.robot
        self.model = planner.robot.model
        self.base = base
        self.objects = objects
        self.held = held
        self.to_arm = arm_from_map(base, planner.mount)
        self.lower = planner.kin.lower + self.config.limit_margin
        self.upper = planner.kin.upper - self.config.limit_margin
        self.geometry = pin.GeometryModel()
        for item in self.robot.geometry.geometryObjects:
            self.geometry.addGeometryObject(item)
        self.names: list[str] = list(self.robot.names)
        self._add_scene()
        self.held_index: int | None = None
        if held is not None:
            placement = self.model.frames[self.robot.grasp_frame].placement * held.in_grasp
            item = pin.GeometryObject(held.obj.id, self.robot.grasp_joint, placement, shape_of(held.obj))
            self.held_index = self._add(held.obj.id, item)
        self.pairs, self.margins = self._pairs()
        self._checkers: dict[tuple[frozenset[int], frozenset[int]], _PairChecker] = {}

    def holding(self, held: HeldObject) -> ArmScene:
        """This scene with `held` in the hand instead of where it stood."""
        return ArmScene(self.planner, self.base, self.objects, held)

    def placed(self, obj: WorldObject, position: Vec3, yaw: float) -> ArmScene:
        """This scene with the hand empty and `obj` standing at `position` (map frame)."""
        others = tuple(item for item in self.objects if item.obj.id != obj.id)
        return ArmScene(self.planner, self.base, (*others, SceneObject(obj, position, yaw)), None)

    # Building

    def _add(self, name: str, item: pin.GeometryObject) -> int:
        self.geometry.addGeometryObject(item)
        self.names.append(name)
        return len(self.names) - 1

    def _add_fixed(self, name: str, shape: coal.ShapeBase, pose: pin.SE3) -> None:
        self._add(name, pin.GeometryObject(name, 0, pose, shape))

    def _add_scene(self) -> None:
        robot = self.planner.world.world.robot
        mount, size = self.planner.mount, robot.base_size
        self._add_fixed(
            BASE,
            coal.Box(size.x, size.y, size.z),
            pin.SE3(np.eye(3), np.array([-mount.x, -mount.y, size.z / 2 - mount.z])),
        )
        self._add_fixed(
            FLOOR,
            coal.Box(2 * FLOOR_HALF_SIZE, 2 * FLOOR_HALF_SIZE, FLOOR_THICKNESS),
            pin.SE3(np.eye(3), np.array([0.0, 0.0, -mount.z - FLOOR_THICKNESS / 2])),
        )
        link0 = self.to_arm.inverse().translation
        here = Point(float(link0[0]), float(link0[1]))
        reach = self.config.reach + self._held_radius()
        for obstacle in self.planner.world.obstacles:
            if obstacle.shape.distance(here) > reach:
                continue
            # Walls and furniture are rectangles; anything else is covered by its enclosing one.
            corners = np.array(obstacle.shape.minimum_rotated_rectangle.exterior.coords)[:4]
            along, across = corners[1] - corners[0], corners[2] - corners[1]
            centre = corners.mean(axis=0)
            heading = math.atan2(float(along[1]), float(along[0]))
            pose = pin.SE3(rotation_z(heading), np.array([centre[0], centre[1], obstacle.height / 2]))
            box = coal.Box(float(np.linalg.norm(along)), float(np.linalg.norm(across)), obstacle.height)
            self._add_fixed(obstacle.id, box, self.to_arm * pose)
        for item in self.objects:
            if self.held is not None and item.obj.id == self.held.obj.id:
                continue
            if here.distance(Point(item.position.x, item.position.y)) > reach + max(item.obj.size.x, item.obj.size.y):
                continue
            position = item.position
            pose = pin.SE3(rotation_z(item.yaw), np.array([position.x, position.y, position.z]))
            self._add_fixed(item.obj.id, shape_of(item.obj), self.to_arm * pose)

    def _held_radius(self) -> float:
        if self.held is None:
            return 0.0
        size = self.held.obj.size
        return float(np.linalg.norm(self.held.in_grasp.translation)) + math.hypot(size.x, size.y, size.z) / 2

    def _pairs(self) -> tuple[list[tuple[int, int]], np.ndarray]:
        """Every pair to check, and its security margin: padding against the scene, 0 within the robot."""
        robot = range(len(self.robot.names))
        scene = [i for i in range(len(self.robot.names), len(self.names)) if i != self.held_index]
        wanted: list[tuple[int, int, float]] = [
            (a, b, 0.0) for a, b in itertools.combinations(robot, 2) if (a, b) not in self.robot.excluded
        ]
        wanted += [(a, b, self.config.padding) for a in robot if self.robot.moving(a) for b in scene]
        if self.held_index is not None:
            wanted += [(a, self.held_index, 0.0) for a in robot if a not in self.robot.gripper]
            wanted += [(b, self.held_index, self.config.padding) for b in scene]
        margins = {}
        for a, b, margin in wanted:
            self.geometry.addCollisionPair(pin.CollisionPair(a, b))
            margins[(a, b)] = margin
        pairs = [(pair.first, pair.second) for pair in self.geometry.collisionPairs]
        return pairs, np.array([margins[pair] for pair in pairs])

    # Collision checks

    def _indices(self, name: str) -> set[int]:
        if name == GRIPPER:
            return set(self.robot.gripper)
        if name == ARM:
            return set(range(len(self.robot.names)))
        return {i for i, n in enumerate(self.names) if n == name}

    def _allowed(self, allowed: Iterable[Contact]) -> frozenset[int]:
        off: set[int] = set()
        for a, b in allowed:
            first, second = self._indices(a), self._indices(b)
            off.update(
                k for k, (i, j) in enumerate(self.pairs) if (i in first and j in second) or (i in second and j in first)
            )
        return frozenset(off)

    def _checker(self, off: frozenset[int], unpadded: frozenset[int] = frozenset()) -> _PairChecker:
        checker = self._checkers.get((off, unpadded))
        if checker is None:
            checker = self._checkers[(off, unpadded)] = _PairChecker(self, off, unpadded)
        return checker

    def _hits(self, checker: _PairChecker, q: np.ndarray) -> list[int]:
        pin.computeCollisions(self.model, checker.kinematics, self.geometry, checker.data, q, False)
        return [k for k, result in enumerate(checker.data.collisionResults) if result.isCollision()]

    def _free(self, checker: _PairChecker, q: np.ndarray) -> bool:
        return not pin.computeCollisions(self.model, checker.kinematics, self.geometry, checker.data, q, True)

    def _contact(self, pair: int) -> str:
        first, second = self.pairs[pair]
        return f"{self.names[first]} touches {self.names[second]}"

    def _describe(self, pairs: Iterable[int]) -> str:
        return ", ".join(sorted({self._contact(k) for k in pairs}))

    def collisions(self, q: Sequence[float] | np.ndarray, allowed: Iterable[Contact] = ()) -> list[Contact]:
        """Every pair in collision at q (scene pairs within the padding), by name."""
        hits = self._hits(self._checker(self._allowed(allowed)), np.asarray(q, dtype=float))
        return sorted((self.names[self.pairs[k][0]], self.names[self.pairs[k][1]]) for k in hits)

    def is_free(self, q: Sequence[float] | np.ndarray, allowed: Iterable[Contact] = ()) -> bool:
        return self._free(self._checker(self._allowed(allowed)), np.asarray(q, dtype=float))

    def path_free(
        self, path: Sequence[Sequence[float] | np.ndarray], allowed: Iterable[Contact] = (), step: float | None = None
    ) -> bool:
        """Every point of the joint path, interpolated linearly with no joint moving more than `step`
        (default: the configured resolution) between checks, is free."""
        checker = self._checker(self._allowed(allowed))
        return all(self._free(checker, q) for q in interpolate(path, step or self.config.resolution))

    # Motions

    def ik(
        self,
        pose: pin.SE3,
        q_seed: Sequence[float] | np.ndarray,
        allowed: Iterable[Contact] = (),
        *,
        what: str = "the target",
    ) -> np.ndarray:
        """Joints putting the grasp frame at `pose` (panda_link0) with no collision but the allowed
        ones. Deterministic: the seed first, then it and the stowed pose turned towards the target,
        then a fixed spread. Raises IKFailed naming the pose."""
        checker = self._checker(self._allowed(allowed))
        seed = np.asarray(q_seed, dtype=float)
        heading = math.atan2(float(pose.translation[1]), float(pose.translation[0]))
        hints = [seed.copy(), self.planner.home.copy()]
        for hint in hints:
            hint[0] = heading
        try:
            return self.kin.solve(
                pose,
                seed,
                accept=lambda q: self._free(checker, q),
                explain=lambda q: self._describe(self._hits(checker, q)),
                seeds=hints,
                random_seeds=self.config.ik_random_seeds,
                margin=self.config.limit_margin,
            )
        except IKFailed as exc:
            x, y, z = (float(v) for v in pose.translation)
            raise IKFailed(f"no IK for {what} at ({x:.3f}, {y:.3f}, {z:.3f}) m in panda_link0: {exc}") from None

    def cartesian(
        self,
        q_start: Sequence[float] | np.ndarray,
        target: Sequence[float] | np.ndarray,
        orientation: np.ndarray | None = None,
        allowed: Iterable[Contact] = (),
        *,
        what: str = "the straight move",
    ) -> list[np.ndarray]:
        """Joint waypoints moving the grasp frame in a straight line to `target` (panda_link0),
        turning evenly to `orientation` (default: as it is), free of collisions but `allowed`.

        Raises IKFailed when a point is out of reach or the arm would flip on the way, PlanningFailed
        when the line collides.
        """
        q0 = np.asarray(q_start, dtype=float)
        start = self.kin.forward(q0)
        goal = np.asarray(target, dtype=float)
        rotation = start.rotation if orientation is None else np.asarray(orientation, dtype=float)
        turn = pin.log3(start.rotation.T @ rotation)
        count = max(
            1,
            math.ceil(float(np.linalg.norm(goal - start.translation)) / self.config.cartesian_step),
            math.ceil(float(np.linalg.norm(turn)) / CARTESIAN_TURN_STEP),
        )
        path = [q0]
        for k in range(1, count + 1):
            s = k / count
            pose = pin.SE3(start.rotation @ pin.exp3(turn * s), start.translation + (goal - start.translation) * s)
            try:
                q = self.kin.solve(pose, path[-1], random_seeds=0, margin=self.config.limit_margin, max_iterations=100)
            except IKFailed as exc:
                raise IKFailed(f"{what}: point {k} of {count} is out of reach ({exc})") from None
            jump = float(np.max(np.abs(q - path[-1])))
            if jump > self.config.max_joint_jump:
                raise IKFailed(f"{what}: a joint would jump {jump:.2f} rad at point {k} of {count}")
            path.append(q)
        valid = self._validity(path[0], path[-1], self._allowed(allowed), what)
        for q in interpolate(path, self.config.resolution):
            if not valid(q):
                raise PlanningFailed(f"{what} collides: {self._describe(valid.hits(q))}")
        return path

    def plan(
        self,
        q_start: Sequence[float] | np.ndarray,
        q_goal: Sequence[float] | np.ndarray,
        allowed: Iterable[Contact] = (),
        *,
        what: str = "moving the arm",
    ) -> list[np.ndarray]:
        """A collision-free joint path from q_start to q_goal: the straight line when it is free,
        else RRTConnect within the joint limits (less limit_margin), shortcut. Raises PlanningFailed
        naming what blocks."""
        q0 = np.asarray(q_start, dtype=float)
        q1 = np.asarray(q_goal, dtype=float)
        for name, q in (("start", q0), ("goal", q1)):
            if not self.kin.within_limits(q):
                raise PlanningFailed(f"{what}: the {name} {np.round(q, 3).tolist()} is outside the joint limits")
        valid = self._validity(q0, q1, self._allowed(allowed), what)
        blocked = next((q for q in interpolate([q0, q1], self.config.resolution) if not valid(q)), None)
        if blocked is None:
            return [q0, q1]
        rejected = _Sample(REJECTED_SAMPLE)
        path = self._rrt(q0, q1, valid, rejected)
        if path is None:
            raise PlanningFailed(
                f"{what}: no collision-free path found in {self.config.planning_time:g} s: the direct motion "
                f"is blocked where {self._describe(valid.hits(blocked))}{self._blockers(valid, rejected)}"
            )
        bad = next((q for q in interpolate(path, self.config.resolution) if not valid(q)), None)
        if bad is not None:
            contacts = self._describe(valid.hits(bad))
            raise PlanningFailed(f"{what}: the path found collides when checked finely: {contacts}")
        return path

    def _blockers(self, valid: _Validity, rejected: _Sample) -> str:
        """What the configurations a search rejected ran into most often, as the end of a message."""
        counts = Counter(contact for q in rejected.kept for contact in {self._contact(k) for k in valid.hits(q)})
        if not counts:
            return ""
        kept = len(rejected.kept)
        tried = f"{kept} of the {rejected.seen}" if rejected.seen > kept else f"the {kept}"
        commonest = sorted(counts.items(), key=lambda item: (-item[1], item[0]))[:BLOCKERS_SHOWN]
        shown = ", ".join(f"{contact} ({round(100 * n / kept)}%)" for contact, n in commonest)
        return f"; in {tried} configurations it tried and rejected, the commonest contacts were {shown}"

    def _validity(self, q0: np.ndarray, q1: np.ndarray, off: frozenset[int], what: str) -> _Validity:
        """The state check of a motion from q0 to q1: pairs within the padding at an end are checked
        without it near that end; a real contact at either end is refused."""
        plain = self._checker(off)
        near: list[tuple[np.ndarray, _PairChecker]] = []
        for name, q in (("start", q0), ("goal", q1)):
            padded = frozenset(self._hits(plain, q))
            if not padded:
                continue
            relaxed = self._checker(off, padded)
            touching = self._hits(relaxed, q)
            if touching:
                raise PlanningFailed(f"{what}: the {name} configuration collides: {self._describe(touching)}")
            near.append((q, relaxed))
        return _Validity(self, plain, near, self.config.endpoint_radius)

    def _rrt(self, q0: np.ndarray, q1: np.ndarray, valid: _Validity, rejected: _Sample) -> list[np.ndarray] | None:
        """RRTConnect, then shortcuts; None when it finds nothing in time. The configurations it
        finds in collision go to `rejected`."""
        guard = Guard()
        with solving(self.config.seed):
            path = self._rrt_connect(q0, q1, valid, rejected, guard)
        guard.raise_failure("a collision check of the arm planner")
        return path

    def _rrt_connect(
        self, q0: np.ndarray, q1: np.ndarray, valid: _Validity, rejected: _Sample, guard: Guard
    ) -> list[np.ndarray] | None:
        """_rrt inside the solve. Every OMPL object is local and freed on return, never held by a
        traceback: OMPL's nanobind bindings report objects still alive at interpreter exit as leaks."""
        dimension = len(q0)
        space = ob.RealVectorStateSpace(dimension)
        bounds = ob.RealVectorBounds(dimension)
        # The ends may sit in the margin (the arm stopped there): the bounds take them in.
        lower, upper = np.minimum(self.lower, np.minimum(q0, q1)), np.maximum(self.upper, np.maximum(q0, q1))
        for i in range(dimension):
            bounds.setLow(i, float(lower[i]))
            bounds.setHigh(i, float(upper[i]))
        space.setBounds(bounds)

        def free(state: ob.State) -> bool:
            q = np.fromiter((state[i] for i in range(dimension)), float, dimension)
            if valid(q):
                return True
            rejected.add(q)
            return False

        setup = og.SimpleSetup(space)
        setup.setStateValidityChecker(lambda state: guard.check(free, state))
        start, goal = space.allocState(), space.allocState()
        for i in range(dimension):
            start[i], goal[i] = float(q0[i]), float(q1[i])
        setup.setStartAndGoalStates(start, goal)
        information = setup.getSpaceInformation()
        # OMPL's resolution is a fraction of the space's extent, along the Euclidean distance: a
        # Euclidean step of `resolution` moves no joint more than that.
        information.setStateValidityCheckingResolution(self.config.resolution / space.getMaximumExtent())
        setup.setPlanner(og.RRTConnect(information))
        setup.solve(self.config.planning_time)
        if not setup.haveExactSolutionPath():
            return None
        found = setup.getSolutionPath()
        # Shortcuts between points along the path, then dropping waypoints the straight line between
        # their neighbours makes needless: a few milliseconds, against tens for simplifySolution.
        simplifier = og.PathSimplifier(information)
        simplifier.ropeShortcutPath(found)
        simplifier.reduceVertices(found)
        return [np.array([found.getState(k)[i] for i in range(dimension)]) for k in range(found.getStateCount())]


class _Validity:
    """The state check of one motion (ArmScene._validity): near an end whose padding it starts or
    ends in, that end's check without that padding; elsewhere the plain one."""

    def __init__(
        self, scene: ArmScene, plain: _PairChecker, near: list[tuple[np.ndarray, _PairChecker]], radius: float
    ) -> None:
        self.scene = scene
        self.plain = plain
        self.near = near
        self.radius = radius

    def _checker(self, q: np.ndarray) -> _PairChecker:
        for end, checker in self.near:
            if float(np.max(np.abs(q - end))) <= self.radius:
                return checker
        return self.plain

    def __call__(self, q: np.ndarray) -> bool:
        return self.scene._free(self._checker(q), q)

    def hits(self, q: np.ndarray) -> list[int]:
        """The pairs in collision at q, as this check sees them."""
        return self.scene._hits(self._checker(q), q)


class _Sample:
    """A uniform sample of at most `size` of the configurations added (reservoir sampling, seeded)."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.seen = 0
        self.kept: list[np.ndarray] = []
        self.rng = random.Random(size)

    def add(self, q: np.ndarray) -> None:
        self.seen += 1
        if len(self.kept) < self.size:
            self.kept.append(q)
        elif (k := self.rng.randrange(self.seen)) < self.size:
            self.kept[k] = q


def interpolate(path: Sequence[Sequence[float] | np.ndarray], step: float) -> Iterator[np.ndarray]:
    """Every waypoint and points between them, no joint moving more than `step` from one to the next."""
    yield np.asarray(path[0], dtype=float)
    for a, b in itertools.pairwise(path):
        start, end = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
        count = max(1, math.ceil(float(np.max(np.abs(end - start), initial=0.0)) / step))
        for k in range(1, count + 1):
            yield start + (end - start) * (k / count)


# Pick and place


def plan_pick(
    scene: ArmScene,
    q_start: Sequence[float] | np.ndarray,
    candidates: Sequence[Grasp],
    target: WorldObject,
    support: str | None,
    *,
    q_stow: Sequence[float] | np.ndarray | None = None,
    cancel: threading.Event | None = None,
) -> PickPlan:
    """The first grasp of `candidates` (in order) that the arm can carry out from q_start: pre-grasp
    by collision-free IK, a straight approach (fingers may touch the target), a straight lift with
    the target held (it may touch its `support`), then a path to the pre-grasp (tried last: the
    costliest) and, given q_stow, from the lift to it with the object. `scene` holds `target` as an
    object. Raises PlanningFailed with each grasp's reason; Canceled once `cancel` is set (looked at
    before each grasp: each may take seconds of search, and there may be dozens)."""
    if not candidates:
        raise PlanningFailed(f"no grasp for {target.name}: nothing about it fits between the fingers")
    reasons: list[str] = []
    reachable, unreachable = _within_reach(scene, candidates, lambda g: (g.pregrasp, g.pose, g.lift))
    for grasp in reachable:
        _may_go_on(cancel, f"planning the pick of {target.name}")
        try:
            q_pre = scene.ik(grasp.pregrasp, q_start, what=f"above {target.name}")
            approach = scene.cartesian(
                q_pre,
                grasp.pose.translation,
                grasp.pose.rotation,
                [(target.id, GRIPPER)],
                what=f"reaching {target.name}",
            )
            holding = scene.holding(HeldObject(target, grasp.object_in_grasp))
            lift = holding.cartesian(
                approach[-1],
                grasp.lift.translation,
                allowed=[(target.id, support)] if support else [],
                what=f"lifting {target.name}",
            )
            to_pregrasp = scene.plan(q_start, q_pre, what=f"moving above {target.name}")
            to_stow = None if q_stow is None else holding.plan(lift[-1], q_stow, what=f"stowing {target.name}")
            return PickPlan(grasp, to_pregrasp, approach, lift, to_stow)
        except PlanningFailed as exc:
            reasons.append(f"{grasp.description}: {exc}")
    raise PlanningFailed(_summary(f"no grasp of {target.name} works", reasons + unreachable))


def plan_place(
    scene: ArmScene,
    q_start: Sequence[float] | np.ndarray,
    candidates: Sequence[Placement],
    surface: str,
    *,
    q_stow: Sequence[float] | np.ndarray | None = None,
    cancel: threading.Event | None = None,
) -> PlacePlan:
    """The first placement of `candidates` the arm can carry out from q_start, holding scene.held:
    above the spot by collision-free IK, straight down, and after letting go straight back along
    the approach (the fingers may touch the object). Raises PlanningFailed with each one's reason;
    Canceled once `cancel` is set (looked at before each placement, as plan_pick does)."""
    held = scene.held
    if held is None:
        raise PlanningFailed("placing needs a scene with an object in the hand")
    name = held.obj.name
    reasons: list[str] = []
    reachable, unreachable = _within_reach(scene, candidates, lambda p: (p.preplace, p.pose, p.retreat))
    for placement in reachable:
        _may_go_on(cancel, f"planning how to put {name} on {surface}")
        try:
            q_pre = scene.ik(placement.preplace, q_start, what=f"{name} above {surface}")
            lower = scene.cartesian(
                q_pre, placement.pose.translation, placement.pose.rotation, what=f"lowering {name} onto {surface}"
            )
            centre = scene.to_arm.inverse() * placement.object_pose
            where = Vec3(x=float(centre.translation[0]), y=float(centre.translation[1]), z=float(centre.translation[2]))
            heading = math.atan2(float(centre.rotation[1, 0]), float(centre.rotation[0, 0]))
            after = scene.placed(held.obj, where, heading)
            retreat = after.cartesian(
                lower[-1], placement.retreat.translation, allowed=[(held.obj.id, GRIPPER)], what=f"leaving {name}"
            )
            to_preplace = scene.plan(q_start, q_pre, what=f"moving {name} above {surface}")
            to_stow = None if q_stow is None else after.plan(retreat[-1], q_stow, what="stowing the arm")
            return PlacePlan(placement, to_preplace, lower, retreat, to_stow)
        except PlanningFailed as exc:
            reasons.append(f"{placement.description}: {exc}")
    raise PlanningFailed(_summary(f"no way to put {name} on {surface}", reasons + unreachable))


C = TypeVar("C", Grasp, Placement)


def _may_go_on(cancel: threading.Event | None, what: str) -> None:
    if cancel is not None and cancel.is_set():
        raise Canceled(f"{what} canceled")


def _within_reach(
    scene: ArmScene, candidates: Sequence[C], poses: Callable[[C], tuple[pin.SE3, ...]]
) -> tuple[list[C], list[str]]:
    """The candidates whose poses the wrist can reach, those well inside its reach first (else in
    the given order), and why each of the others is out of reach, found without asking IK."""
    robot = scene.robot
    ranked = []
    unreachable = []
    for index, candidate in enumerate(candidates):
        stretch = max(robot.stretch(pose) for pose in poses(candidate))
        if stretch > robot.reach:
            unreachable.append(
                f"{candidate.description}: out of reach, the wrist {stretch:.2f} m from the shoulder "
                f"(it reaches {robot.reach:.2f} m)"
            )
        else:
            ranked.append((stretch > COMFORTABLE_REACH * robot.reach, index, candidate))
    ranked.sort(key=lambda r: r[:2])
    return [r[2] for r in ranked], unreachable


def _summary(what: str, reasons: list[str], shown: int = 3) -> str:
    more = f"; and {len(reasons) - shown} more" if len(reasons) > shown else ""
    return f"{what} ({len(reasons)} tried): " + "; ".join(reasons[:shown]) + more


# Timing


@dataclass(frozen=True)
class _Segment:
    start: np.ndarray
    direction: np.ndarray  # unit (Euclidean) direction in joint space
    length: float
    max_speed: float  # path speed that keeps every joint within its velocity limit
    max_acceleration: float  # path acceleration that keeps every joint within its acceleration limit


def time_parameterize(
    path: Sequence[Sequence[float] | np.ndarray],
    max_velocity: float | Sequence[float] | np.ndarray,
    max_acceleration: float | Sequence[float] | np.ndarray,
    *,
    sample_period: float = 0.04,
) -> list[TrajectoryPoint]:
    """Time a joint path so every joint stays within its velocity and acceleration limits, sampled
    at most `sample_period` apart with every waypoint a sample.

    The samples lie on the path's straight segments, so following them by linear interpolation (as
    the robot does) traces exactly the path that was collision-checked. Along each segment the speed
    follows a trapezoid (accelerate, cruise, brake) within the segment's limits; through a waypoint
    it carries the speed the corner allows, found like a CNC look-ahead planner (forward and
    backward passes). Velocities and accelerations are those of the samples: the speed of each
    interval, and the change between two intervals over their mean duration, which for a corner is
    what the robot's controller sees. Corners whose samples come out over a limit are taken slower
    until none does (a full stop at a corner always complies).
    """
    points = [np.asarray(q, dtype=float) for q in path]
    if not points:
        raise ValueError("time_parameterize needs at least one point")
    dimension = len(points[0])
    v = np.broadcast_to(np.asarray(max_velocity, dtype=float), (dimension,)).copy()
    a = np.broadcast_to(np.asarray(max_acceleration, dtype=float), (dimension,)).copy()
    if not (np.all(v > 0) and np.all(a > 0) and np.all(np.isfinite(v)) and np.all(np.isfinite(a))):
        raise ValueError(f"velocity and acceleration limits must be positive, got {v.tolist()} and {a.tolist()}")
    # Planned a hair inside the limits, checked against them: rounding never tips a sample over.
    limits = (v.copy(), a.copy())
    v, a = v * (1 - 1e-9), a * (1 - 1e-9)
    segments = _segments(points, v, a)
    if not segments:
        return [
            TrajectoryPoint(positions=points[0].tolist(), time_from_start=0.0),
            TrajectoryPoint(positions=points[0].tolist(), time_from_start=sample_period),
        ]
    caps = _corner_caps(segments, a, sample_period)
    period = sample_period
    problem = ""
    for _ in range(TIMING_ROUNDS):
        speeds = _junction_speeds(segments, caps)
        times, samples, owner = _sample(segments, speeds, period)
        if len(samples) > MAX_TRAJECTORY_POINTS:
            problem = f"it takes more than the {MAX_TRAJECTORY_POINTS} points a trajectory may have"
            period *= 1.5
            caps = _corner_caps(segments, a, period)
            continue
        ratio = _limit_ratio(times, samples, *limits)
        over = np.nonzero(ratio > 1)[0]
        if len(over) == 0:
            return [
                TrajectoryPoint(positions=q.tolist(), time_from_start=float(t))
                for t, q in zip(times, samples, strict=True)
            ]
        problem = _over_limit(times, samples, *limits)
        corners = [i for i in over if owner[i] > 0]
        if len(corners) < len(over):
            # Inside segments the samples follow a profile within the limits: only rounding gets here.
            v, a = v * (1 - 1e-6), a * (1 - 1e-6)
            segments = _segments(points, v, a)
        for i in corners:
            k = owner[i]
            slower = speeds[k] * min(0.8, 1 / float(ratio[i]))
            caps[k] = 0.0 if slower < 1e-3 else slower
    raise PlanningFailed(f"could not time a path of {len(points)} waypoints within the joint limits: {problem}")


def _segments(points: list[np.ndarray], v: np.ndarray, a: np.ndarray) -> list[_Segment]:
    segments = []
    for p, q in itertools.pairwise(points):
        delta = q - p
        length = float(np.linalg.norm(delta))
        if length < 1e-9:
            continue
        direction = delta / length
        moving = np.abs(direction) > 1e-12
        segments.append(
            _Segment(
                start=p,
                direction=direction,
                length=length,
                max_speed=float(np.min(v[moving] / np.abs(direction[moving]))),
                max_acceleration=float(np.min(a[moving] / np.abs(direction[moving]))),
            )
        )
    return segments


def _corner_caps(segments: list[_Segment], a: np.ndarray, period: float) -> list[float]:
    """A first guess of the speed each waypoint can be passed at (index k: between segments k-1 and k):
    half the acceleration budget for turning the velocity, spread over the samples around the corner."""
    caps = [0.0]
    for before, after in itertools.pairwise(segments):
        turn = np.abs(after.direction - before.direction)
        turning = turn > 1e-12
        if not np.any(turning):
            caps.append(math.inf)
            continue
        if float(np.max(turn)) > SHARP_TURN:
            caps.append(0.0)  # it would be crawling round it anyway: stop there
            continue
        budget = 0.5 * a[turning] / turn[turning]
        spread = (before.length + after.length) / 2
        caps.append(float(min(np.min(budget) * period, np.min(np.sqrt(budget * spread)))))
    caps.append(0.0)
    return caps


def _junction_speeds(segments: list[_Segment], caps: list[float]) -> list[float]:
    """Path speed at each waypoint: within the corner cap and both segments' speed limits, and
    reachable from the neighbours with the segments' accelerations (backward, then forward pass)."""
    n = len(segments)
    speeds = [0.0] * (n + 1)
    for k in range(1, n):
        speeds[k] = min(caps[k], segments[k - 1].max_speed, segments[k].max_speed)
    for k in range(n - 1, -1, -1):
        s = segments[k]
        speeds[k] = min(speeds[k], math.sqrt(speeds[k + 1] ** 2 + 2 * s.max_acceleration * s.length))
    for k in range(n):
        s = segments[k]
        speeds[k + 1] = min(speeds[k + 1], math.sqrt(speeds[k] ** 2 + 2 * s.max_acceleration * s.length))
    return speeds


def _trapezoid(segment: _Segment, entry: float, exit_: float) -> tuple[float, float, float, float]:
    """Peak speed and the durations of speeding up, cruising and braking along one segment."""
    acceleration = segment.max_acceleration
    peak = min(segment.max_speed, math.sqrt(acceleration * segment.length + (entry**2 + exit_**2) / 2))
    peak = max(peak, entry, exit_)
    up = (peak - entry) / acceleration
    down = (peak - exit_) / acceleration
    cruise_distance = (
        segment.length - (peak**2 - entry**2) / (2 * acceleration) - (peak**2 - exit_**2) / (2 * acceleration)
    )
    cruise = max(0.0, cruise_distance) / peak if peak > 0 else 0.0
    return peak, up, cruise, down


def _distance(t: float, entry: float, peak: float, acceleration: float, up: float, cruise: float) -> float:
    """Distance along a segment t seconds after entering it (t within its duration)."""
    if t <= up:
        return entry * t + acceleration * t * t / 2
    covered = entry * up + acceleration * up * up / 2
    if t <= up + cruise:
        return covered + peak * (t - up)
    covered += peak * cruise
    t -= up + cruise
    return covered + peak * t - acceleration * t * t / 2


def _sample(
    segments: list[_Segment], speeds: list[float], period: float
) -> tuple[np.ndarray, list[np.ndarray], list[int]]:
    """Sample times and positions; owner[i] is the waypoint index a sample sits on (0 inside a segment)."""
    times = [0.0]
    samples = [segments[0].start]
    owner = [0]
    clock = 0.0
    for k, segment in enumerate(segments):
        entry, exit_ = speeds[k], speeds[k + 1]
        peak, up, cruise, down = _trapezoid(segment, entry, exit_)
        duration = up + cruise + down
        count = max(1, math.ceil(duration / period - 1e-9))
        for i in range(1, count + 1):
            t = duration * i / count
            distance = segment.length if i == count else _distance(t, entry, peak, segment.max_acceleration, up, cruise)
            times.append(clock + t)
            samples.append(segment.start + segment.direction * min(distance, segment.length))
            owner.append(k + 1 if i == count and k + 1 < len(segments) else 0)
        clock += duration
    return np.array(times), samples, owner


def _rates(times: np.ndarray, samples: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The joint velocities of the intervals between samples, and the accelerations at each sample
    (at rest before the first and after the last, where the change takes half an interval)."""
    positions = np.array(samples)
    dt = np.diff(times)
    velocity = np.diff(positions, axis=0) / dt[:, None]
    padded = np.vstack([np.zeros(positions.shape[1]), velocity, np.zeros(positions.shape[1])])
    spans = np.concatenate([[dt[0]], dt, [dt[-1]]])
    mean = (spans[:-1] + spans[1:]) / 2
    mean[0], mean[-1] = dt[0] / 2, dt[-1] / 2
    return velocity, np.diff(padded, axis=0) / mean[:, None]


def _limit_ratio(times: np.ndarray, samples: list[np.ndarray], v: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Per sample, the largest ratio of a sampled joint velocity (of the interval that follows) or
    acceleration to its limit: above 1 is over."""
    velocity, acceleration = _rates(times, samples)
    ratio = np.max(np.abs(acceleration) / a, axis=1)
    ratio[:-1] = np.maximum(ratio[:-1], np.max(np.abs(velocity) / v, axis=1))
    return ratio


def _over_limit(times: np.ndarray, samples: list[np.ndarray], v: np.ndarray, a: np.ndarray) -> str:
    """The sampled joint rate furthest over its limit, in words: which joint, how fast and when,
    and the limit."""
    velocity, acceleration = _rates(times, samples)
    kinds = [
        (np.abs(velocity) / v, velocity, v, "velocity", "rad/s"),
        (np.abs(acceleration) / a, acceleration, a, "acceleration", "rad/s²"),
    ]
    ratio, rates, limits, what, unit = max(kinds, key=lambda kind: float(kind[0].max()))
    sample, joint = (int(k) for k in np.unravel_index(np.argmax(ratio), ratio.shape))
    name = ARM_JOINTS[joint] if len(limits) == len(ARM_JOINTS) else f"joint {joint + 1}"
    return (
        f"{name} would still reach {abs(float(rates[sample, joint])):.2f} {unit} at {float(times[sample]):.2f} s, "
        f"over its {what} limit of {float(limits[joint]):.2f} {unit}"
    )
