"""Grasps and place poses for the Panda hand from an object's shape and size, in panda_link0.

The grasp frame is the URDF's panda_grasptarget: 0.105 m out from the hand along its z (the
approach, palm towards fingertips), between the fingers and 7 mm short of their tips; its y is the
axis the fingers close along. Top grasps point the hand down, side grasps hold it level from the
robot's side, angled ones tilt it down towards the object where neither reaches. Each candidate
carries its pre-grasp, lift pose, finger gap and the object's pose in the grasp frame, with which
the held object is attached to the hand for planning and put down later.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from schemas.common import Pose2D, Vec3
from schemas.robot import GRIPPER_MAX_GAP
from schemas.world import WorldObject
from services.executor.kinematics import arm_from_map, hand_rotation, rotation_z, top_down_rotation

# The Panda hand about its grasp frame (franka_panda/panda.urdf and its collision meshes).
FINGERTIP_BEYOND = 0.0072  # the fingertips reach this far past the grasp frame along the approach
PALM_BEHIND = 0.039  # the hand's body ends this far before the grasp frame: the palm
FINGER_HALF_WIDTH = 0.0105  # a finger's half extent along the grasp frame's x
# link7, 0.105 to 0.16 m behind the grasp frame, reaches this far from the approach axis along x:
# on a side grasp it is the lowest part of the arm, over the surface the object stands on.
WRIST_HALF_THICKNESS = 0.044
UP = np.array([0.0, 0.0, 1.0])
# Ways a top-down hand comes in and leaves: from straight above, or down a 45 degree slope from
# the robot's side where straight above is out of reach.
TOP_WAYS = ("from above", "from above and nearer the robot")
# A level hand comes in straight, or down a 45 degree slope where straight is too low (a low table).
SIDE_WAYS = ("straight in", "from above and behind")


@dataclass(frozen=True)
class GraspConfig:
    """Distances in metres. pregrasp_distance and lift_height: how far the hand backs off before
    closing in, and rises with the object; grasp_depth: fingertips at most this far below the top
    of a tall object on a top grasp (the palm sits 4 cm above them: deeper, it presses on the rim
    and tips the object in the fingers)."""

    pregrasp_distance: float = 0.12
    lift_height: float = 0.12
    grasp_depth: float = 0.03
    fingertip_clearance: float = 0.015  # fingertips above the support at a top grasp
    hand_clearance: float = 0.015  # the hand and wrist above the support at a side grasp
    palm_clearance: float = 0.005  # between the palm and the object on a side grasp
    min_overlap: float = 0.005  # the fingers on the object at least this much
    gap_margin: float = 0.004  # objects up to GRIPPER_MAX_GAP less this fit between the fingers
    round_headings: int = 8  # hand headings tried for top grasps of round objects, over a full turn
    side_angles: tuple[float, ...] = (0.0, 0.35, -0.35, 0.7, -0.7)  # side approaches off the reach direction (rad)
    tilts: tuple[float, ...] = (math.pi / 4,)  # angled grasps: the approach this far from straight down (rad)
    place_clearance: float = 0.02  # the object's bottom above the surface when let go
    place_headings: int = 12  # object headings tried when placing, over a full turn
    retreat_distance: float = 0.12  # the hand backs off this far after letting go

    def __post_init__(self) -> None:
        for name in (
            "pregrasp_distance",
            "lift_height",
            "grasp_depth",
            "fingertip_clearance",
            "hand_clearance",
            "palm_clearance",
            "min_overlap",
            "gap_margin",
            "place_clearance",
            "retreat_distance",
        ):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and 0 <= value <= 0.5):
                raise ValueError(f"GraspConfig.{name} must be in [0, 0.5] m, got {value!r}")
        if self.round_headings < 1 or self.place_headings < 1:
            raise ValueError(
                f"GraspConfig.round_headings and place_headings must be >= 1, "
                f"got {self.round_headings} and {self.place_headings}"
            )
        if self.gap_margin >= GRIPPER_MAX_GAP:
            raise ValueError(f"GraspConfig.gap_margin {self.gap_margin} m leaves no room between the fingers")


@dataclass(frozen=True)
class Grasp:
    """One way to take the object; poses of the grasp frame in panda_link0."""

    kind: str  # "top", "side" or "angled"
    pose: pin.SE3  # where the fingers close on the object
    pregrasp: pin.SE3  # where the hand comes in from, fingers open: a straight line to `pose`
    lift: pin.SE3  # where the hand takes the object, straight from `pose`
    gap: float  # the finger gap once closed on the object (m)
    object_in_grasp: pin.SE3  # the object's pose (its centre) in the grasp frame
    description: str


@dataclass(frozen=True)
class Placement:
    """One way to put a held object down; poses of the grasp frame in panda_link0."""

    pose: pin.SE3  # where the hand lets go
    preplace: pin.SE3  # where it comes in from: a straight line to `pose`
    retreat: pin.SE3  # where it leaves to after opening, straight from `pose`
    object_pose: pin.SE3  # where the object then stands (its centre), panda_link0
    description: str


def object_pose(position: Vec3, yaw: float, base: Pose2D, mount: Vec3) -> pin.SE3:
    """An object's pose in panda_link0 from its centre and heading in the map frame."""
    return arm_from_map(base, mount) * pin.SE3(rotation_z(yaw), np.array([position.x, position.y, position.z]))


def fits(width: float, config: GraspConfig) -> bool:
    """Whether something `width` across fits between the open fingers with the margin."""
    return width <= GRIPPER_MAX_GAP - config.gap_margin


def narrowest_width(obj: WorldObject) -> float:
    """The narrowest width of `obj` the candidates put the fingers across: a box's shorter side, a
    round object's diameter. Wider than fits, no grasp of it exists wherever it stands."""
    return min(obj.size.x, obj.size.y) if obj.shape == "box" else obj.size.x


def grasps(
    obj: WorldObject, position: Vec3, yaw: float, base: Pose2D, mount: Vec3, config: GraspConfig | None = None
) -> list[Grasp]:
    """Grasp candidates for `obj` with its centre at `position` and heading `yaw` (map frame), the
    base at `base`: top grasps, then side grasps, then angled ones; within each kind, the most
    comfortable hand for the arm first. Empty when nothing about it fits between the fingers."""
    config = config or GraspConfig()
    pose = object_pose(position, yaw, base, mount)
    return [*top_grasps(obj, pose, config), *side_grasps(obj, pose, config), *angled_grasps(obj, pose, config)]


def top_height(obj: WorldObject, config: GraspConfig) -> float:
    """How far above the object's centre the grasp frame closes on a top grasp: the fingertips at
    most grasp_depth below its top, and clear of the surface under it."""
    half = obj.size.z / 2
    return max(half - config.grasp_depth, FINGERTIP_BEYOND + config.fingertip_clearance - half)


def side_height(obj: WorldObject, config: GraspConfig) -> float:
    """How far above the object's centre the grasp frame closes on a side grasp: at the centre,
    or higher to keep the hand and the wrist behind it clear of the surface."""
    return max(0.0, WRIST_HALF_THICKNESS + config.hand_clearance - obj.size.z / 2)


def top_grasps(obj: WorldObject, pose: pin.SE3, config: GraspConfig) -> list[Grasp]:
    """The hand pointing down, the fingers across a side that fits (both ways round), each from
    above and, after, from above and nearer the robot; the hand's x along the reach first."""
    half = obj.size.z / 2
    height = top_height(obj, config)
    if height - FINGERTIP_BEYOND > half - config.min_overlap:
        return []  # too flat: the fingertips would stay above its top
    centre = pose.translation
    reach = _heading(centre)
    heading = _heading(pose.rotation[:, 0])
    options: list[tuple[float, float]] = []  # (hand heading, gap)
    if obj.shape == "box":
        for side, across in ((obj.size.x, heading + math.pi / 2), (obj.size.y, heading)):
            if fits(side, config):
                options += [(across, side), (across + math.pi, side)]
    elif fits(obj.size.x, config):
        radius = obj.size.x / 2
        gap = 2 * math.sqrt(max(radius**2 - height**2, 0.0)) if obj.shape == "sphere" else obj.size.x
        options = [(reach + k * math.tau / config.round_headings, gap) for k in range(config.round_headings)]
    # The stowed pose's hand has its x along the reach: the wrist least turned from there first.
    options.sort(key=lambda option: (round(_off(option[0], reach), 6), math.remainder(option[0] - reach, math.tau)))
    at = centre + UP * height
    toward_robot = -_horizontal(centre)
    grasps = []
    for hand, gap in options:
        rotation = top_down_rotation(hand)
        for way, back in zip(TOP_WAYS, (UP, _unit(UP + toward_robot)), strict=True):
            text = (
                f"top grasp of {obj.name} {way}, hand turned {_degrees(hand - reach)} deg from the reach, "
                f"fingers {gap * 100:.1f} cm apart"
            )
            grasps.append(_grasp("top", rotation, at, back, back, pose, gap, config, text))
    return grasps


def side_grasps(obj: WorldObject, pose: pin.SE3, config: GraspConfig) -> list[Grasp]:
    """The hand level, coming from the robot's side (straight along the reach first, then turned
    by side_angles; for a box, square to a face whose width fits), both ways up; for objects tall
    enough to keep the hand clear of the surface. Not for spheres: with the wrist clear of the
    surface, the fingers would close high on one, where it slips out from between them."""
    if obj.shape == "sphere":
        return []
    half = obj.size.z / 2
    height = side_height(obj, config)
    if height + FINGER_HALF_WIDTH > half - config.min_overlap:
        return []  # too low: the fingers would not be on it with the wrist clear of the surface
    centre = pose.translation
    reach = _heading(centre)
    options: list[tuple[float, float, float]] = []  # (approach heading, depth to the centre, gap)
    if obj.shape == "box":
        heading = _heading(pose.rotation[:, 0])
        widest = max(abs(a) for a in config.side_angles)
        for face in range(4):
            normal = heading + face * math.pi / 2
            depth, across = (obj.size.x, obj.size.y) if face % 2 == 0 else (obj.size.y, obj.size.x)
            if fits(across, config) and _off(normal, reach) <= widest + 1e-9:
                options.append((normal, depth / 2, across))
    elif fits(obj.size.x, config):
        options = [(reach + angle, obj.size.x / 2, obj.size.x) for angle in config.side_angles]
    options.sort(key=lambda option: round(_off(option[0], reach), 6))
    grasps = []
    for towards, depth, gap in options:
        approach = np.array([math.cos(towards), math.sin(towards), 0.0])
        # Back from the centre as far as the palm must stay off the object's near side.
        at = centre + UP * height - approach * max(0.0, depth + config.palm_clearance - PALM_BEHIND)
        for upright, fingers in ((True, np.cross(UP, approach)), (False, -np.cross(UP, approach))):
            for way, back in zip(SIDE_WAYS, (-approach, _unit(UP - approach)), strict=True):
                text = (
                    f"side grasp of {obj.name} {way}, {_degrees(towards - reach)} deg off the reach, "
                    f"hand {'upright' if upright else 'upside down'}, fingers {gap * 100:.1f} cm apart"
                )
                rotation = hand_rotation(approach, fingers)
                grasps.append(_grasp("side", rotation, at, back, UP, pose, gap, config, text))
    return grasps


def angled_grasps(obj: WorldObject, pose: pin.SE3, config: GraspConfig) -> list[Grasp]:
    """The hand tilted down towards the object from the robot's side (by each of `tilts` from
    straight down), the fingers level and across: for where neither straight down nor level
    reaches, a far spot on a high shelf. For a box, square to a face whose width fits. The grasp
    frame starts where a top grasp closes and backs off along the approach until the palm clears
    the object; the fingers must still close on it, their tips clear of the surface."""
    half = obj.size.z / 2
    centre = pose.translation
    reach = _heading(centre)
    options: list[tuple[float, float]] = []  # (approach heading, width across)
    if obj.shape == "box":
        heading = _heading(pose.rotation[:, 0])
        widest = max(abs(a) for a in config.side_angles)
        for face in range(4):
            normal = heading + face * math.pi / 2
            width = obj.size.y if face % 2 == 0 else obj.size.x
            if fits(width, config) and _off(normal, reach) <= widest + 1e-9:
                options.append((normal, width))
        options.sort(key=lambda option: round(_off(option[0], reach), 6))
    elif fits(obj.size.x, config):
        options = [(reach, obj.size.x)]
    grasps = []
    for towards_heading, width in options:
        towards = np.array([math.cos(towards_heading), math.sin(towards_heading), 0.0])
        across = np.cross(UP, towards)
        for tilt in config.tilts:
            approach = towards * math.sin(tilt) - UP * math.cos(tilt)
            start = centre + UP * max(0.0, top_height(obj, config))
            clear = _extent(obj, pose, -approach) - float(-approach @ (start - centre)) + config.palm_clearance
            at = start - approach * max(0.0, clear - PALM_BEHIND)
            local = pose.actInv(at)
            if abs(local[2]) > half - config.min_overlap or math.hypot(local[0], local[1]) > width / 2:
                continue  # backed off past the object: the fingers would close on nothing
            for upright, fingers in ((True, across), (False, -across)):
                rotation = hand_rotation(approach, fingers)
                lowest = float(at[2] + approach[2] * FINGERTIP_BEYOND - abs(rotation[2, 0]) * FINGER_HALF_WIDTH)
                if lowest < centre[2] - half + config.fingertip_clearance:
                    continue  # the fingertips would dig into the surface
                text = (
                    f"angled grasp of {obj.name}, {math.degrees(tilt):.0f} deg from straight down, "
                    f"{_degrees(towards_heading - reach)} deg off the reach, "
                    f"hand {'upright' if upright else 'upside down'}, fingers {width * 100:.1f} cm apart"
                )
                grasps.append(_grasp("angled", rotation, at, -approach, UP, pose, width, config, text))
    return grasps


def _extent(obj: WorldObject, pose: pin.SE3, direction: np.ndarray) -> float:
    """How far the object reaches from its centre along `direction` (panda_link0, unit)."""
    local = pose.rotation.T @ direction
    size = obj.size
    if obj.shape == "sphere":
        return size.x / 2
    if obj.shape == "cylinder":
        return size.x / 2 * math.hypot(local[0], local[1]) + size.z / 2 * abs(local[2])
    return float(np.abs(local) @ np.array([size.x, size.y, size.z]) / 2)


def placements(
    obj: WorldObject,
    object_in_grasp: pin.SE3,
    spot: Vec3,
    base: Pose2D,
    mount: Vec3,
    config: GraspConfig | None = None,
) -> list[Placement]:
    """Grasp-frame poses standing the held object upright on a surface: its centre over `spot`
    (map frame; z is the surface's top), its bottom place_clearance above it. The object keeps its
    place in the hand, so candidates differ in its heading; the most comfortable hand first, each
    lowered from above and then, as for grasps, from above and nearer the robot."""
    config = config or GraspConfig()
    to_arm = arm_from_map(base, mount)
    centre = to_arm.act(np.array([spot.x, spot.y, spot.z + config.place_clearance + obj.size.z / 2]))
    reach = _heading(centre)
    toward_robot = -_horizontal(centre)
    in_object = object_in_grasp.inverse()  # the grasp frame in the object's frame
    hand_down = in_object.rotation[2, 2] < -0.99
    # The hand's reference direction (its x when pointing straight down, else its approach) in the
    # object's frame: turning the object to put it along the reach is the comfortable heading.
    reference = in_object.rotation[:, 0] if hand_down else in_object.rotation[:, 2]
    comfortable = -_heading(reference)
    ranked: list[tuple[float, int, int, Placement]] = []
    for k in range(config.place_headings):
        turn = comfortable + k * math.tau / config.place_headings
        placed = pin.SE3(rotation_z(reach + turn), centre)
        pose = placed * in_object
        rotation = pose.rotation
        approach = rotation[:, 2]
        cost = _off(_heading(rotation[:, 0] if hand_down else approach), reach)
        ways = ((UP, UP), (_unit(UP + toward_robot), _unit(UP + toward_robot)))
        if not hand_down:
            ways = ((UP, -approach), (_unit(UP + toward_robot), -approach))
        for w, (come_from, leave_to) in enumerate(ways):
            text = (
                f"{obj.name} at {_degrees(reach + turn)} deg, hand "
                f"{math.degrees(cost):.0f} deg off its comfortable heading, {TOP_WAYS[w]}"
            )
            placement = Placement(
                pose=pose,
                preplace=pin.SE3(rotation, pose.translation + come_from * config.pregrasp_distance),
                retreat=pin.SE3(rotation, pose.translation + leave_to * config.retreat_distance),
                object_pose=placed,
                description=text,
            )
            ranked.append((round(cost, 6), k, w, placement))
    ranked.sort(key=lambda r: r[:3])
    return [r[3] for r in ranked]


def _grasp(
    kind: str,
    rotation: np.ndarray,
    at: np.ndarray,
    back: np.ndarray,
    up: np.ndarray,
    obj_pose: pin.SE3,
    gap: float,
    config: GraspConfig,
    text: str,
) -> Grasp:
    pose = pin.SE3(rotation, at)
    return Grasp(
        kind=kind,
        pose=pose,
        pregrasp=pin.SE3(rotation, at + back * config.pregrasp_distance),
        lift=pin.SE3(rotation, at + up * config.lift_height),
        gap=gap,
        object_in_grasp=pose.actInv(obj_pose),
        description=text,
    )


def _heading(vector: np.ndarray) -> float:
    return math.atan2(float(vector[1]), float(vector[0]))


def _degrees(angle: float) -> str:
    return f"{math.degrees(math.remainder(angle, math.tau)):.0f}"


def _off(heading: float, reference: float) -> float:
    """The angle between two headings, 0 to pi."""
    return abs(math.remainder(heading - reference, math.tau))


def _horizontal(vector: np.ndarray) -> np.ndarray:
    flat = np.array([vector[0], vector[1], 0.0])
    norm = float(np.linalg.norm(flat))
    return flat / norm if norm > 1e-9 else np.array([1.0, 0.0, 0.0])


def _unit(vector: np.ndarray) -> np.ndarray:
    return vector / float(np.linalg.norm(vector))
