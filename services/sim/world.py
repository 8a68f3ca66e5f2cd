"""The simulated world in pybullet: the bodies, the robot's joints, time, ground truth, and things moved for tests."""

from __future__ import annotations

import copy
import functools
import logging
import math
import tempfile
import threading
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

import numpy as np
import pybullet
import pybullet_data
from pybullet_utils import bullet_client
from shapely.geometry import Point

from schemas.actions import GoalState
from schemas.common import ErrorKind, Pose2D, ServiceError, Vec3
from schemas.robot import ARM_JOINTS, FINGER_JOINTS, GRIPPER_MAX_GAP
from schemas.world import Furniture, GroundTruth, Moved, MoveEntity, PerceivedObject, Wall, World, WorldObject
from services.sim.robot_urdf import BASE_LINK, BASE_X_JOINT, BASE_Y_JOINT, BASE_YAW_JOINT, mobile_manipulator_urdf
from services.worldmodel import WorldModel

log = logging.getLogger(__name__)

F = TypeVar("F")
R = TypeVar("R")

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
# The fingers pass through an object the hand let go of until they are this far from it (SimWorld.release).
LET_GO_CLEARANCE = 0.005

WALL_RGBA = [0.92, 0.9, 0.86, 1.0]
BLOCK_RGBA = [0.95, 0.55, 0.1, 1.0]  # a temporary obstacle (sim/fault block): orange, to be seen
HUMAN_RADIUS = 0.2
HUMAN_HEIGHT = 1.7

# sim/move: an object is let go this far above where it is to rest, so it never starts inside
# anything, and counts as settled once slower than SETTLED_OBJECT_SPEED for SETTLED_OBJECT_TIME.
DROP_HEIGHT = 0.002
SETTLED_OBJECT_SPEED = 0.01
SETTLED_OBJECT_TIME = 0.1
SETTLE_TIMEOUT = 3.0
# sim/move's `z` is where an object is set down, not thrown from: below the floor Bullet shot it
# metres up, from far above it was still falling when the reply said where it was.
MOVE_MAX_Z = 2.0
# A fault puts nothing nearer than this to the robot: its base, its arm, or what the hand holds.
ROBOT_CLEARANCE = 0.01


def wrap_angle(angle: float) -> float:
    return math.atan2(math.sin(angle), math.cos(angle))


def has_heading(obj: WorldObject) -> bool:
    """Whether the object's yaw can be told: a box with unequal sides (the book)."""
    return obj.shape == "box" and abs(obj.size.x - obj.size.y) > 1e-3


class _Client(bullet_client.BulletClient):  # type: ignore[misc]
    """pybullet_utils' client with each pybullet function looked up once. Its own lookup makes a
    functools.partial on every call: 3 us a call, and the sim makes several calls a tick."""

    def __getattr__(self, name: str) -> Any:
        attribute = super().__getattr__(name)
        if name != "disconnect" and isinstance(attribute, functools.partial):
            self.__dict__[name] = attribute
        return attribute


class Motion(Generic[F, R]):
    """Something carried out over time: the sim thread ticks it; other threads read `feedback` and wait on `done`."""

    kind = "motion"

    def __init__(self, started: float) -> None:
        self.started = started
        self.feedback: F | None = None
        self.state = GoalState.EXECUTING
        self.result: R | None = None
        self.message = ""
        self.done = threading.Event()

    @property
    def running(self) -> bool:
        return not self.done.is_set()

    def finish(self, state: GoalState, result: R, message: str = "") -> None:
        if self.done.is_set():
            return
        self.state, self.result, self.message = state, result, message
        log.info("%s %s: %s", self.kind, state.value, message or "done")
        self.done.set()


Position = tuple[float, float, float]
Orientation = tuple[float, float, float, float]  # a quaternion (x, y, z, w), as pybullet gives it


@dataclass(frozen=True)
class BlockShape:
    """A temporary obstacle (sim/fault block): a static box `half` its sides (x, y, z) around
    `centre`, turned `yaw` about the vertical; `name` for people ("a box in the kitchen doorway")."""

    id: str
    name: str
    centre: Position
    half: Position
    yaw: float = 0.0


# How far a body may be from where it was drawn and still count as standing there (metres, radians,
# quaternion components). A base at rest creeps (its yaw about 2e-5 rad a sim second under the arm's
# motors), so exact equality would always draw again. A millimetre or a milliradian moves what the
# camera sees by a tenth of one of its pixels (87 degrees over 160) at a metre: less than the
# detector's own noise (3 mm by default).
STILL = 1e-3
# A joint, or an object's base, slower than this (m/s, rad/s) counts as at rest (Simulation.step).
REST_SPEED = 1e-3


@dataclass(frozen=True)
class Poses:
    """Where everything that moves stood at one moment (`stamp`, wall clock): what another pybullet
    client with the same world loaded needs to draw the same scene (services/sim/renderer.py)."""

    stamp: float
    joints: tuple[float, ...]  # the robot's movable joints (RobotBody.movable), in that order
    objects: dict[str, tuple[Position, Orientation]]
    humans: dict[str, tuple[Position, Orientation]]
    holding: str | None
    # The temporary obstacles standing now: the renderer adds and removes its copies to match.
    blocks: tuple[BlockShape, ...] = ()

    def stands_as(self, other: Poses, tolerance: float = STILL) -> bool:
        """Whether everything stands where it stood in `other`: every joint, position and quaternion
        component within `tolerance`, the same obstacles. A camera there sees the same picture."""
        if self.blocks != other.blocks or self.objects.keys() != other.objects.keys():
            return False
        if self.humans.keys() != other.humans.keys() or len(self.joints) != len(other.joints):
            return False
        here = [*self.joints, *_flat(self.objects), *_flat(self.humans)]
        there = [*other.joints, *_flat(other.objects), *_flat(other.humans)]
        return all(abs(a - b) <= tolerance for a, b in zip(here, there, strict=True))


def _flat(bodies: dict[str, tuple[Position, Orientation]]) -> list[float]:
    return [v for name in sorted(bodies) for part in bodies[name] for v in part]


def without_visuals(urdf: str) -> str:
    """The URDF without its <visual> elements: the same physics, nothing to draw. The Panda's visual
    meshes take some 70 MB; a sim whose camera renders in another process has no use for them."""
    root = ET.fromstring(urdf)
    for link in root.iter("link"):
        for visual in link.findall("visual"):
            link.remove(visual)
    return ET.tostring(root, encoding="unicode")


# The arm as the camera draws it by default: its collision hulls (about 3,400 triangles) in the
# Panda's white. Its visual meshes have about 100,000, and pybullet's CPU renderer pays per
# triangle: 20 to 30 ms a frame with them, about 3 without (160 x 120, the floor not drawn).
HULL_RGBA = "0.9 0.9 0.9 1"


def hulls_as_visuals(urdf: str) -> str:
    """The URDF with each link's visual meshes replaced by its collision shapes, in HULL_RGBA: what
    hides what from the camera stays (the hulls wrap the meshes closely), at a thirtieth of the
    triangles. The boxes and primitives drawn as such are kept as they are."""
    root = ET.fromstring(urdf)
    for link in root.iter("link"):
        visuals = link.findall("visual")
        if not any(visual.find("geometry/mesh") is not None for visual in visuals):
            continue
        for visual in visuals:
            link.remove(visual)
        for collision in link.findall("collision"):
            drawn = ET.SubElement(link, "visual")
            drawn.extend(copy.deepcopy(child) for child in collision if child.tag in ("origin", "geometry"))
            material = ET.SubElement(drawn, "material", name="hull")
            ET.SubElement(material, "color", rgba=HULL_RGBA)
    return ET.tostring(root, encoding="unicode")


# The Panda's visual meshes share one 1024 x 1024 colour palette (colors.png), which pybullet decodes
# again for every mesh: some 33 MB in the camera's process. A copy at this size keeps the colours
# (each is a patch of the palette) for 1/64 of that.
TEXTURE_SIZE = 128


def with_small_textures(urdf: str, into: Path) -> str:
    """The URDF with its visual OBJ meshes copied into `into`, their textures scaled down to
    TEXTURE_SIZE (nearest pixel, so no colour is blended): the same robot, drawn the same, in less memory."""
    from PIL import Image  # only the camera's process draws, and only it needs Pillow

    root = ET.fromstring(urdf)
    copied: dict[Path, Path] = {}
    for visual in root.iter("visual"):
        for mesh in visual.iter("mesh"):
            source = Path(mesh.get("filename", ""))
            if source.suffix != ".obj" or not source.is_file():
                continue
            if source.parent not in copied:
                target = into / f"meshes{len(copied)}"
                target.mkdir()
                for item in source.parent.iterdir():
                    if item.suffix in (".obj", ".mtl"):
                        (target / item.name).write_bytes(item.read_bytes())
                    elif item.suffix == ".png":
                        with Image.open(item) as image:
                            image.resize((TEXTURE_SIZE, TEXTURE_SIZE), Image.Resampling.NEAREST).save(
                                target / item.name
                            )
                copied[source.parent] = target
            mesh.set("filename", str(copied[source.parent] / source.name))
    return ET.tostring(root, encoding="unicode")


class RobotBody:
    """The robot's joints in pybullet: its motors take targets, its encoders are read here."""

    def __init__(self, bullet: Any, world: World, *, visuals: bool = True, detailed_arm: bool = False) -> None:
        """`visuals=False`: nothing to draw; else the arm drawn as its hulls, or with `detailed_arm` its meshes."""
        self.bullet = bullet
        spec = world.robot
        urdf = mobile_manipulator_urdf(spec)
        with tempfile.TemporaryDirectory(prefix="tether-sim-") as tmp:
            path = Path(tmp) / "mobile_panda.urdf"
            if not visuals:
                urdf = without_visuals(urdf)
            elif detailed_arm:
                urdf = with_small_textures(urdf, Path(tmp))
            else:
                urdf = hulls_as_visuals(urdf)
            path.write_text(urdf)
            self.id: int = bullet.loadURDF(str(path), useFixedBase=True)
        self.joint_index: dict[str, int] = {}
        self.link_index: dict[str, int] = {}
        # Every joint that is not fixed, in index order: what Poses carries of the robot.
        self.movable: list[int] = []
        for i in range(bullet.getNumJoints(self.id)):
            info = bullet.getJointInfo(self.id, i)
            self.joint_index[info[1].decode()] = i
            self.link_index[info[12].decode()] = i
            if info[2] != pybullet.JOINT_FIXED:
                self.movable.append(i)
        self.base_joints = [self.joint_index[n] for n in (BASE_X_JOINT, BASE_Y_JOINT, BASE_YAW_JOINT)]
        self.arm_joints = [self.joint_index[n] for n in ARM_JOINTS]
        self.finger_joints = [self.joint_index[n] for n in FINGER_JOINTS]
        self.hand = self.link_index[HAND_LINK]
        self.fingers = [self.link_index[n] for n in FINGER_LINKS]
        self.base_link = self.link_index[BASE_LINK]
        infos = [bullet.getJointInfo(self.id, j) for j in self.arm_joints]
        # Plain lists, so a trajectory can be checked on any thread without touching pybullet.
        self.arm_limits = ([float(i[8]) for i in infos], [float(i[9]) for i in infos])
        start = spec.start
        for joint, value in zip(self.base_joints, (start.x, start.y, start.yaw), strict=True):
            bullet.resetJointState(self.id, joint, value)
        for joint, value in zip(self.arm_joints, spec.home_joints, strict=True):
            bullet.resetJointState(self.id, joint, value)
        for joint in self.finger_joints:
            bullet.resetJointState(self.id, joint, GRIPPER_OPEN / 2)
            bullet.changeDynamics(self.id, joint, lateralFriction=1.0)

    # Motors

    def drive_base(self, linear_x: float, angular_z: float) -> None:
        """Velocity in the base frame, applied to the planar joints in the map frame."""
        yaw = self.base_pose().yaw
        self.bullet.setJointMotorControlArray(
            self.id,
            self.base_joints,
            pybullet.VELOCITY_CONTROL,
            targetVelocities=[linear_x * math.cos(yaw), linear_x * math.sin(yaw), angular_z],
            forces=[BASE_FORCE, BASE_FORCE, BASE_TORQUE],
        )

    def drive_arm(self, positions: np.ndarray, velocities: np.ndarray) -> None:
        self.bullet.setJointMotorControlArray(
            self.id,
            self.arm_joints,
            pybullet.POSITION_CONTROL,
            targetPositions=positions.tolist(),
            targetVelocities=velocities.tolist(),
            forces=list(ARM_FORCES),
            positionGains=[ARM_POSITION_GAIN] * 7,
        )

    def drive_fingers(self, each: float, force: float) -> None:
        """Each finger to `each` metres from the middle, pushing with at most `force`."""
        for joint in self.finger_joints:
            self.bullet.setJointMotorControl2(
                self.id, joint, pybullet.POSITION_CONTROL, targetPosition=each, force=force, maxVelocity=FINGER_SPEED
            )

    # Encoders

    def base_pose(self) -> Pose2D:
        x, y, yaw = (s[0] for s in self.bullet.getJointStates(self.id, self.base_joints))
        return Pose2D(x=x, y=y, yaw=wrap_angle(yaw))

    def base_velocity(self) -> tuple[float, float]:
        """Measured linear_x and angular_z in the base frame."""
        states = self.bullet.getJointStates(self.id, self.base_joints)
        yaw = states[2][0]
        vx, vy, w = (s[1] for s in states)
        return vx * math.cos(yaw) + vy * math.sin(yaw), w

    def base_speed(self) -> float:
        vx, vy = (s[1] for s in self.bullet.getJointStates(self.id, self.base_joints[:2]))
        return math.hypot(vx, vy)

    def arm_positions(self) -> list[float]:
        return [s[0] for s in self.bullet.getJointStates(self.id, self.arm_joints)]

    def gripper_gap(self) -> float:
        return float(sum(s[0] for s in self.bullet.getJointStates(self.id, self.finger_joints)))

    def finger_speed(self) -> float:
        return float(max(abs(s[1]) for s in self.bullet.getJointStates(self.id, self.finger_joints)))

    def joints(self) -> tuple[list[float], list[float]]:
        """Positions and velocities of the arm's seven joints, then the two fingers'."""
        states = self.bullet.getJointStates(self.id, [*self.arm_joints, *self.finger_joints])
        return [s[0] for s in states], [s[1] for s in states]


class Drop(Motion[None, Moved]):
    """An object teleported by sim/move and let go: done once it lies still (or has rolled for too long)."""

    kind = "move"

    def __init__(self, world: SimWorld, object_id: str) -> None:
        super().__init__(world.sim_time)
        self.object_id = object_id
        self.still_since = world.sim_time

    def result_now(self, world: SimWorld) -> Moved:
        return Moved(id=self.object_id, position=world.object_position(self.object_id))

    def tick(self, world: SimWorld) -> None:
        if world.object_speed(self.object_id) > SETTLED_OBJECT_SPEED:
            self.still_since = world.sim_time
        if world.sim_time - self.still_since >= SETTLED_OBJECT_TIME:
            self.finish(GoalState.SUCCEEDED, self.result_now(world), f"{self.object_id} at rest")
        elif world.sim_time - self.started > SETTLE_TIMEOUT:
            self.finish(GoalState.SUCCEEDED, self.result_now(world), f"{self.object_id} still moving")


class SimWorld:
    """The household and the robot's body in one pybullet client, stepped by whoever owns it (one thread)."""

    def __init__(
        self,
        world: World,
        *,
        physics_hz: float = 240.0,
        solver_iterations: int = 50,
        visuals: bool = True,
        detailed_arm: bool = False,
    ) -> None:
        self.spec = world
        # Without the robot's visual meshes (visuals=False) nothing here can be rendered: the sim's
        # camera then renders in a process of its own (services/sim/renderer.py).
        self.visuals = visuals
        self.model = WorldModel(world)
        self.dt = 1.0 / physics_hz
        self.sim_time = 0.0
        # What the hand holds: a fixed constraint stands in for the grip (see grasp).
        self.holding: str | None = None
        self._grasp_constraint: int | None = None
        # Bodies the hand let go of that the fingers pass through until they are clear of them (release).
        self._let_go: set[int] = set()
        self._drops: list[Drop] = []
        self.bullet: Any = _Client(connection_mode=pybullet.DIRECT)
        self.bullet.setAdditionalSearchPath(pybullet_data.getDataPath())
        self.bullet.setGravity(0.0, 0.0, GRAVITY)
        self.bullet.setTimeStep(self.dt)
        self.bullet.setPhysicsEngineParameter(numSolverIterations=solver_iterations)
        self.floor: int = self.bullet.loadURDF("plane.urdf")
        self.wall_bodies = {w.id: self._add_wall(w) for w in world.walls}
        self.furniture_bodies = {f.id: self._add_furniture(f.center, f.size, f.rgba) for f in world.furniture}
        self.object_shapes: dict[str, int] = {}  # each object's collision shape (robot_part_in)
        self.object_bodies = {o.id: self._add_object(o) for o in world.objects}
        self.human_bodies = {h.id: self._add_human(h.pose) for h in world.humans}
        # A person's body as a collision shape, only ever asked where it would go (sim/move): the
        # bodies themselves have none, so nothing in the physics pushes them or is pushed by them.
        self.human_shape: int = self.bullet.createCollisionShape(
            pybullet.GEOM_CYLINDER, radius=HUMAN_RADIUS, height=HUMAN_HEIGHT
        )
        # Where people stand now: they move (sim/move), the world file only says where they start.
        self.human_poses = {h.id: h.pose for h in world.humans}
        # Temporary obstacles (sim/fault block), by id, with their bodies.
        self.blocks: dict[str, tuple[BlockShape, int]] = {}
        # Box collision shapes by half extents: a block's, made once however often it is put up
        # (pybullet never frees a shape), and asked where the robot is before it goes up (robot_part_in).
        self._box_shapes: dict[Position, int] = {}
        self.robot = RobotBody(self.bullet, world, visuals=visuals, detailed_arm=detailed_arm)
        log.info("world %s loaded: %d furniture, %d objects", world.name, len(world.furniture), len(world.objects))

    # Building

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
        self.object_shapes[obj.id] = shape
        where = self.model.initial_position(obj)
        body: int = self.bullet.createMultiBody(obj.mass, shape, visual, [where.x, where.y, where.z])
        # An object at rest sleeps (Bullet stops solving its contacts) until something active touches
        # it or it is moved (`_wake`): a dozen resting objects made each step two to three times dearer.
        self.bullet.changeDynamics(
            body,
            -1,
            lateralFriction=1.0,
            spinningFriction=0.01,
            rollingFriction=0.001,
            activationState=pybullet.ACTIVATION_STATE_ENABLE_SLEEPING,
        )
        return body

    def _wake(self, body: int) -> None:
        """Back into the solver: a sleeping body would hang where it was put, or ignore the grip."""
        self.bullet.changeDynamics(body, -1, activationState=pybullet.ACTIVATION_STATE_WAKE_UP)

    def _add_human(self, pose: Pose2D) -> int:
        visual = self.bullet.createVisualShape(
            pybullet.GEOM_CYLINDER, radius=HUMAN_RADIUS, length=HUMAN_HEIGHT, rgbaColor=[0.9, 0.7, 0.5, 1.0]
        )
        body: int = self.bullet.createMultiBody(0.0, -1, visual, [pose.x, pose.y, HUMAN_HEIGHT / 2])
        return body

    def add_block(self, block: BlockShape) -> int:
        """A static box the base cannot drive through and the camera sees, until remove_block."""
        shape = self.box_shape(block.half)
        visual = self.bullet.createVisualShape(pybullet.GEOM_BOX, halfExtents=list(block.half), rgbaColor=BLOCK_RGBA)
        orientation = self.bullet.getQuaternionFromEuler([0.0, 0.0, block.yaw])
        body: int = self.bullet.createMultiBody(0.0, shape, visual, list(block.centre), orientation)
        self.blocks[block.id] = (block, body)
        return body

    def box_shape(self, half: Position) -> int:
        """The collision shape of a box `half` its sides."""
        if half not in self._box_shapes:
            self._box_shapes[half] = self.bullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=list(half))
        shape: int = self._box_shapes[half]
        return shape

    def robot_part_in(self, shape: int, centre: Position, yaw: float = 0.0) -> str | None:
        """Which part of the robot is within ROBOT_CLEARANCE of collision shape `shape` were it put
        at `centre`, turned `yaw`: "base", "arm" (any link above the base, fingers too), the id of
        the object the hand holds, or None. Every link is asked, not the base's outline alone: an arm
        reaching out of it would have a box or an object put up inside it, and pybullet then throws
        the robot or the object off."""
        orientation = self.bullet.getQuaternionFromEuler([0.0, 0.0, yaw])
        held = [(self.holding, self.object_bodies[self.holding])] if self.holding is not None else []
        for name, body in [(None, self.robot.id), *held]:
            points = self.bullet.getClosestPoints(
                bodyA=body,
                bodyB=-1,
                distance=ROBOT_CLEARANCE,
                collisionShapeB=shape,
                collisionShapePositionB=list(centre),
                collisionShapeOrientationB=orientation,
            )
            if points:
                if name is not None:
                    return name
                return "base" if any(p[3] == self.robot.base_link for p in points) else "arm"
        return None

    def remove_block(self, block_id: str) -> None:
        _, body = self.blocks.pop(block_id)
        self.bullet.removeBody(body)

    def close(self) -> None:
        self.bullet.disconnect()

    def step(self) -> None:
        """One physics tick, after the controllers have set the motors; objects let go settle meanwhile."""
        for drop in self._drops:
            drop.tick(self)
        self._drops = [d for d in self._drops if d.running]
        self.bullet.stepSimulation()
        self.sim_time += self.dt
        if self._let_go:
            self._touch_when_clear()

    def rest_step(self) -> None:
        """A tick of a world at rest (Simulation.step): time passes, physics is not stepped."""
        self.sim_time += self.dt

    @property
    def settling(self) -> bool:
        """An object moved (sim/move) is still let go to settle."""
        return bool(self._drops)

    def still(self) -> bool:
        """Nothing settles and nothing moves faster than REST_SPEED: no robot joint, no object."""
        if self._drops:
            return False
        bullet = self.bullet
        if any(abs(s[1]) > REST_SPEED for s in bullet.getJointStates(self.robot.id, self.robot.movable)):
            return False
        for body in self.object_bodies.values():
            linear, angular = bullet.getBaseVelocity(body)
            if max(map(abs, linear)) > REST_SPEED or max(map(abs, angular)) > REST_SPEED:
                return False
        return True

    # Grasping

    def object_between_fingers(self) -> str | None:
        """The object both fingers touch: only that one is held."""
        robot = self.robot
        for object_id, body in self.object_bodies.items():
            if all(self.bullet.getContactPoints(robot.id, body, link, -1) for link in robot.fingers):
                return object_id
        return None

    def grasp(self, object_id: str, payload_limit: float | None = None) -> str | None:
        """Fix the object to the hand; the reason when it cannot be held (too heavy), else None."""
        obj = self.model.objects[object_id]
        payload = min(self.spec.robot.payload, payload_limit or self.spec.robot.payload)
        if obj.mass > payload:
            if self.holding == object_id:
                self.release()  # as the words say
            return f"{object_id} weighs {obj.mass:g} kg, over the {payload:g} kg payload; it slips out"
        if self.holding == object_id:
            # Closed again on it: one grip. A second would hold it on after `release` removed the other.
            return None
        if self.holding is not None:
            self.release()  # the hand holds one thing: the other's grip goes, not left behind
        body, robot = self.object_bodies[object_id], self.robot
        self._wake(body)
        hand_com = self.bullet.getLinkState(robot.id, robot.hand)[0:2]
        object_pose = self.bullet.getBasePositionAndOrientation(body)
        inverse = self.bullet.invertTransform(*hand_com)
        relative = self.bullet.multiplyTransforms(inverse[0], inverse[1], *object_pose)
        # A real friction grasp in pybullet is flaky; a fixed constraint stands in for the grip.
        self._grasp_constraint = self.bullet.createConstraint(
            robot.id,
            robot.hand,
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

    def hand_position(self) -> Position:
        """Where the hand is on the map (its link frame)."""
        x, y, z = self.bullet.getLinkState(self.robot.id, self.robot.hand)[0]
        return (float(x), float(y), float(z))

    def release(self) -> None:
        """Let go of what the hand holds. The fingers pass through it until they are clear of it: a
        finger that had squeezed into it kept, now and then, a contact whose friction held it in the
        air after the grip went (one place in about forty on a loaded machine: a cup left hanging
        1.8 cm over the table, then carried off as the arm drew back)."""
        if self._grasp_constraint is not None:
            self.bullet.removeConstraint(self._grasp_constraint)
        if self.holding is not None:
            body = self.object_bodies[self.holding]
            self._wake(body)
            self._set_finger_contact(body, enabled=False)
            self._let_go.add(body)
        self._grasp_constraint = None
        self.holding = None

    def _set_finger_contact(self, body: int, *, enabled: bool) -> None:
        for finger in self.robot.fingers:
            self.bullet.setCollisionFilterPair(self.robot.id, body, finger, -1, int(enabled))

    def fingers_touch_all(self) -> None:
        """Every object let go of collides with the fingers again, clear of them or not: they close."""
        for body in self._let_go:
            self._set_finger_contact(body, enabled=True)
        self._let_go.clear()

    def _touch_when_clear(self) -> None:
        """The fingers collide again with each object let go of that they are LET_GO_CLEARANCE from."""
        robot = self.robot
        for body in list(self._let_go):
            near = (
                self.bullet.getClosestPoints(robot.id, body, LET_GO_CLEARANCE, finger, -1) for finger in robot.fingers
            )
            if not any(near):
                self._set_finger_contact(body, enabled=True)
                self._let_go.discard(body)

    # Ground truth

    def object_position(self, object_id: str) -> Vec3:
        (x, y, z), _ = self.bullet.getBasePositionAndOrientation(self.object_bodies[object_id])
        return Vec3(x=x, y=y, z=z)

    def object_speed(self, object_id: str) -> float:
        linear, _ = self.bullet.getBaseVelocity(self.object_bodies[object_id])
        return float(np.linalg.norm(linear))

    def report(
        self, obj: WorldObject, position: Vec3, on: str | None, stamp: float, yaw: float | None = None
    ) -> PerceivedObject:
        """An object as perception reports it, `position` from wherever it was found."""
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

    def exact(self, obj: WorldObject, stamp: float) -> PerceivedObject:
        """The object exactly where it is, `on` the gripper when held."""
        position = self.object_position(obj.id)
        on = "gripper" if obj.id == self.holding else self.model.support_under(position, obj.size.z / 2)
        yaw = None
        if has_heading(obj):
            _, orientation = self.bullet.getBasePositionAndOrientation(self.object_bodies[obj.id])
            heading = self.bullet.getEulerFromQuaternion(orientation)[2]
            yaw = math.atan(math.tan(heading)) if abs(math.cos(heading)) > 1e-9 else math.pi / 2
        return self.report(obj, position, on, stamp, yaw)

    def ground_truth(self) -> GroundTruth:
        """The simulator's own state: every object exactly where it is, seen or not."""
        return GroundTruth(
            sim_time=self.sim_time,
            robot=self.robot.base_pose(),
            linear_speed=self.robot.base_speed(),
            holding=self.holding,
            objects=[self.exact(o, self.sim_time) for o in self.spec.objects],
        )

    # What another client needs to draw this scene (services/sim/renderer.py)

    def poses(self, stamp: float) -> Poses:
        """Where every movable body stands now: the robot's joints, the objects, the people."""
        bullet, robot = self.bullet, self.robot
        joints = tuple(s[0] for s in bullet.getJointStates(robot.id, robot.movable))
        objects = {name: bullet.getBasePositionAndOrientation(b) for name, b in self.object_bodies.items()}
        humans = {name: bullet.getBasePositionAndOrientation(b) for name, b in self.human_bodies.items()}
        blocks = tuple(block for block, _ in self.blocks.values())
        return Poses(stamp=stamp, joints=joints, objects=objects, humans=humans, holding=self.holding, blocks=blocks)

    def pose_as(self, poses: Poses) -> None:
        """Put every movable body where `poses` says, and hold what it holds: for a copy of the world
        that only draws (it is never stepped, so nothing falls or collides)."""
        bullet, robot = self.bullet, self.robot
        for joint, value in zip(robot.movable, poses.joints, strict=True):
            bullet.resetJointState(robot.id, joint, value)
        for bodies, where in ((self.object_bodies, poses.objects), (self.human_bodies, poses.humans)):
            for name, (position, orientation) in where.items():
                bullet.resetBasePositionAndOrientation(bodies[name], position, orientation)
        self.holding = poses.holding
        wanted = {block.id: block for block in poses.blocks}
        for block_id, (block, _) in list(self.blocks.items()):
            if wanted.get(block_id) != block:
                self.remove_block(block_id)
        for block_id, block in wanted.items():
            if block_id not in self.blocks:
                self.add_block(block)

    # The world changing under the robot's feet (sim/move)

    def move(self, request: MoveEntity) -> Drop | Moved | ServiceError:
        """Teleport a person (done at once) or an object (let go to settle: wait for the Drop), or say
        why not."""
        refusal = self._move_refusal(request)
        if refusal is not None:
            return refusal
        # Where the body would go, found once: checked for room there, then put there.
        shape, centre, yaw = self._placed(request)
        refusal = self._placing_refusal(request, shape, centre, yaw)
        if refusal is not None:
            return refusal
        if request.id in self.human_bodies:
            return self._move_human(request.id, centre, yaw)
        return self._drop_object(request.id, centre, yaw)

    def _move_refusal(self, request: MoveEntity) -> ServiceError | None:
        entities = [*self.object_bodies, *self.human_bodies]
        if request.id not in entities:
            message = f"no object or person {request.id!r} in the world {self.spec.name!r}"
            return ServiceError(kind=ErrorKind.INVALID_REQUEST, message=message, candidates=sorted(entities))
        if self.model.room_of(request.x, request.y) is None:
            message = f"({request.x:g}, {request.y:g}) is outside every room of the world {self.spec.name!r}"
            return ServiceError(kind=ErrorKind.INVALID_REQUEST, message=message)
        if request.id == self.holding:
            message = f"{request.id} is in the robot's gripper; the robot has to put it down first"
            return ServiceError(kind=ErrorKind.PRECONDITION, message=message)
        if self._under_the_robot(request.x, request.y):
            message = f"({request.x:g}, {request.y:g}) is where the robot stands"
            return ServiceError(kind=ErrorKind.INVALID_REQUEST, message=message)
        if request.z is not None and not 0.0 <= request.z <= MOVE_MAX_Z:
            message = f"z = {request.z:g} m is not between the floor and {MOVE_MAX_Z:g} m above it"
            return ServiceError(kind=ErrorKind.INVALID_REQUEST, message=message)
        furniture = self._furniture_at(request.x, request.y)
        if furniture is not None and request.z is not None and request.z < furniture.size.z:
            message = f"z = {request.z:g} m is inside the {furniture.name}, whose top is at {furniture.size.z:g} m"
            return ServiceError(kind=ErrorKind.INVALID_REQUEST, message=message)
        return None

    def _placing_refusal(self, request: MoveEntity, shape: int, centre: Position, yaw: float) -> ServiceError | None:
        """Why the body `request` moves cannot be put at `centre`, turned `yaw` (see _placed), or None."""
        # The whole body, not only its centre: pybullet throws out what is put inside something solid
        # (a cup put among the fingers landed 9 cm off, on its side; a book put into a wall sank
        # through the floor), and a person's body over the base reads as the robot running into them.
        name = self._entity_name(request.id)
        part = self.robot_part_in(shape, centre, yaw)
        if part is not None:
            message = (
                f"({request.x:g}, {request.y:g}) is where {self.robot_part_said(part)}: the {name} would be put into it"
            )
            return ServiceError(kind=ErrorKind.INVALID_REQUEST, message=message)
        # People have no collision body (nothing in the physics pushes them), so a person is kept out of
        # solids, and objects and other people out of a person, here.
        solid = self._solid_in(shape, centre, yaw, request.id) or self.person_in(shape, centre, yaw, request.id)
        if solid is None and request.id in self.object_bodies:
            # Let go over a person's head, an object falls through them to the floor: their whole height.
            solid = self.person_in(shape, (centre[0], centre[1], HUMAN_HEIGHT / 2), yaw, request.id)
        if solid is None:
            return None
        if request.id in self.object_bodies:
            message = f"the {name} set down at ({request.x:g}, {request.y:g}) would go into {solid}"
        else:
            message = f"the {name} put at ({request.x:g}, {request.y:g}) would stand in {solid}"
        return ServiceError(kind=ErrorKind.INVALID_REQUEST, message=message)

    def _entity_name(self, entity_id: str) -> str:
        if entity_id in self.model.objects:
            return self.model.objects[entity_id].name
        return next(h.name for h in self.spec.humans if h.id == entity_id)

    def robot_part_said(self, part: str) -> str:
        """What `robot_part_in` found, as the subject of a refusal ("the robot's arm reaches")."""
        if part == "base":
            return "the robot stands"
        if part == "arm":
            return "the robot's arm reaches"
        return f"the {self.model.objects[part].name} in the robot's gripper is"

    def _placed(self, request: MoveEntity) -> tuple[int, Position, float]:
        """The collision shape of what `request` moves, and the centre and yaw it would be put at."""
        if request.id in self.human_bodies:
            yaw = self.human_poses[request.id].yaw if request.yaw is None else request.yaw
            return self.human_shape, (request.x, request.y, HUMAN_HEIGHT / 2), yaw
        obj = self.model.objects[request.id]
        if request.z is not None:
            bottom = request.z
        else:
            furniture = self._furniture_at(request.x, request.y)
            bottom = furniture.size.z if furniture is not None else 0.0
        if request.yaw is not None:
            yaw = request.yaw
        else:
            _, orientation = self.bullet.getBasePositionAndOrientation(self.object_bodies[request.id])
            yaw = self.bullet.getEulerFromQuaternion(orientation)[2]
        return self.object_shapes[request.id], (request.x, request.y, bottom + obj.size.z / 2 + DROP_HEIGHT), yaw

    def _solid_in(self, shape: int, centre: Position, yaw: float, moving: str) -> str | None:
        """The wall, furniture, fault's box or other object that collision shape `shape` would touch
        or cut into were it put at `centre`, turned `yaw` (the object `moving` itself aside), named
        as a refusal says it, or None."""
        solids = [(f"the {w.name}", self.wall_bodies[w.id]) for w in self.spec.walls]
        solids += [(f"the {f.name}", self.furniture_bodies[f.id]) for f in self.spec.furniture]
        solids += self._objects_but(moving)
        solids += [(block.name, body) for block, body in self.blocks.values()]  # "a box in the ..."
        return self._first_touched(solids, shape, centre, yaw)

    def object_in(self, shape: int, centre: Position, yaw: float = 0.0, moving: str = "") -> str | None:
        """The object (`moving` aside) that collision shape `shape` would touch or cut into were it put
        at `centre`, turned `yaw`, named as a refusal says it ("the red cup"), or None."""
        return self._first_touched(self._objects_but(moving), shape, centre, yaw)

    def _objects_but(self, moving: str) -> list[tuple[str, int]]:
        return [(f"the {o.name}", self.object_bodies[o.id]) for o in self.spec.objects if o.id != moving]

    def _first_touched(self, solids: list[tuple[str, int]], shape: int, centre: Position, yaw: float) -> str | None:
        orientation = self.bullet.getQuaternionFromEuler([0.0, 0.0, yaw])
        for name, body in solids:
            points = self.bullet.getClosestPoints(
                bodyA=body,
                bodyB=-1,
                distance=0.0,
                collisionShapeB=shape,
                collisionShapePositionB=list(centre),
                collisionShapeOrientationB=orientation,
            )
            if points:
                return name
        return None

    def touch(
        self,
        shape_a: int,
        centre_a: Position,
        shape_b: int,
        centre_b: Position,
        yaw_a: float = 0.0,
        yaw_b: float = 0.0,
    ) -> bool:
        """Whether collision shapes `shape_a` and `shape_b`, upright at those centres and turned those
        yaws, would touch or cut into each other."""
        points = self.bullet.getClosestPoints(
            bodyA=-1,
            bodyB=-1,
            distance=0.0,
            collisionShapeA=shape_a,
            collisionShapeB=shape_b,
            collisionShapePositionA=list(centre_a),
            collisionShapePositionB=list(centre_b),
            collisionShapeOrientationA=self.bullet.getQuaternionFromEuler([0.0, 0.0, yaw_a]),
            collisionShapeOrientationB=self.bullet.getQuaternionFromEuler([0.0, 0.0, yaw_b]),
        )
        return bool(points)

    def person_in(self, shape: int, centre: Position, yaw: float, moving: str = "") -> str | None:
        """The person (`moving` aside) whose body collision shape `shape` would touch or cut into were
        it put at `centre`, turned `yaw`, named as a refusal says it ("the operator"), or None."""
        for human in self.spec.humans:
            if human.id == moving:
                continue
            stands = self.human_poses[human.id]
            body = (stands.x, stands.y, HUMAN_HEIGHT / 2)
            if self.touch(self.human_shape, body, shape, centre, stands.yaw, yaw):
                return f"the {human.name}"
        return None

    def _under_the_robot(self, x: float, y: float) -> bool:
        base, size = self.robot.base_pose(), self.spec.robot.base_size
        dx, dy = x - base.x, y - base.y
        ahead = dx * math.cos(base.yaw) + dy * math.sin(base.yaw)
        left = -dx * math.sin(base.yaw) + dy * math.cos(base.yaw)
        return abs(ahead) <= size.x / 2 and abs(left) <= size.y / 2

    def _furniture_at(self, x: float, y: float) -> Furniture | None:
        point = Point(x, y)
        return next((f for f in self.spec.furniture if self.model.footprint(f).covers(point)), None)

    def _move_human(self, human_id: str, centre: Position, yaw: float) -> Moved:
        x, y, _ = centre
        self.human_poses[human_id] = Pose2D(x=x, y=y, yaw=yaw)
        orientation = self.bullet.getQuaternionFromEuler([0.0, 0.0, yaw])
        self.bullet.resetBasePositionAndOrientation(self.human_bodies[human_id], centre, orientation)
        log.info("moved %s to (%.2f, %.2f)", human_id, x, y)
        return Moved(id=human_id, position=Vec3(x=x, y=y, z=0.0))

    def set_down(self, object_id: str, x: float, y: float, bottom: float | None = None) -> Drop:
        """Put an object upright at (x, y) with its bottom at `bottom` (None: on the furniture there,
        else the floor) and let it settle: for faults, which choose the spot themselves."""
        _, centre, yaw = self._placed(MoveEntity(id=object_id, x=x, y=y, z=bottom))
        return self._drop_object(object_id, centre, yaw)

    def settle(self, object_id: str) -> Drop:
        """Watch an object that is falling where it is until it comes to rest."""
        drop = Drop(self, object_id)
        self._drops.append(drop)
        return drop

    def _drop_object(self, object_id: str, centre: Position, yaw: float) -> Drop:
        """Upright at `centre`, turned `yaw` (see _placed), let go to settle."""
        body = self.object_bodies[object_id]
        # Put elsewhere while it still fell from an earlier move (or a fault's): that move's reply
        # would have said it came to rest where this one put it.
        for earlier in self._drops:
            if earlier.object_id == object_id:
                message = f"{object_id} was moved again before it came to rest where this move put it"
                earlier.finish(GoalState.CANCELED, earlier.result_now(self), message)
        self.bullet.resetBasePositionAndOrientation(body, centre, self.bullet.getQuaternionFromEuler([0.0, 0.0, yaw]))
        self.bullet.resetBaseVelocity(body, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
        self._wake(body)
        log.info("moved %s to (%.2f, %.2f, %.2f); letting it settle", object_id, *centre)
        drop = Drop(self, object_id)
        self._drops.append(drop)
        return drop
