"""The world file (the prior) and what perception reports about it."""

from __future__ import annotations

import enum
from typing import Annotated, Literal

import msgspec
from msgspec import Meta

from schemas.common import Frozen, Id, Kilograms, Metres, Name, Pose2D, Radians, ServiceError, Text, Vec3

Point2 = Annotated[list[Metres], Meta(min_length=2, max_length=2)]
Polygon = Annotated[list[Point2], Meta(min_length=3, max_length=256)]
Rgba = Annotated[list[Annotated[float, Meta(ge=0.0, le=1.0)]], Meta(min_length=4, max_length=4)]
Size = Annotated[float, Meta(gt=0.0, le=50.0)]


class Extent(Frozen):
    x: Size
    y: Size
    z: Size


class Room(Frozen):
    id: Id
    name: Name
    polygon: Polygon
    synonyms: list[Name] = []


class KeepOut(Frozen):
    id: Id
    name: Name
    polygon: Polygon
    reason: Text = ""


class Place(Frozen):
    """A named spot the base can go to (a charging dock, a room's centre)."""

    id: Id
    name: Name
    pose: Pose2D
    synonyms: list[Name] = []


class Wall(Frozen):
    """A straight wall on the floor plan: `thickness` across the line from `start` to `end`, which it
    covers end to end (a doorway is the gap between two walls). `name` is for people ("the wall
    between the kitchen and the living room")."""

    id: Id
    start: Point2
    end: Point2
    thickness: Annotated[float, Meta(gt=0.0, le=1.0)] = 0.1
    height: Size = 2.4
    name: Name = "wall"


class Furniture(Frozen):
    """An axis-aligned box whose top is a surface; `approach` is where the base stands to use it."""

    id: Id
    name: Name
    center: Point2
    size: Extent
    approach: Pose2D
    rgba: Rgba = msgspec.field(default_factory=lambda: [0.6, 0.45, 0.3, 1.0])
    synonyms: list[Name] = []
    # What kind of furniture it is ("table"), for "the table"; default: the last word of its name.
    cls: Name | None = None


class WorldObject(Frozen):
    """A movable object resting on the furniture `support`; `offset` is its place on that top."""

    id: Id
    name: Name
    cls: Name
    color: Name
    shape: Annotated[str, Meta(pattern="^(cylinder|box|sphere)$")]
    size: Extent
    mass: Kilograms
    support: Id
    offset: Point2 = msgspec.field(default_factory=lambda: [0.0, 0.0])
    rgba: Rgba = msgspec.field(default_factory=lambda: [0.5, 0.5, 0.5, 1.0])
    synonyms: list[Name] = []


class Human(Frozen):
    id: Id
    name: Name
    pose: Pose2D
    synonyms: list[Name] = []


class RobotSpec(Frozen):
    """The mobile manipulator: a box base carrying the arm at `arm_mount` (base frame)."""

    base_size: Extent
    arm_mount: Vec3
    start: Pose2D
    home_joints: Annotated[list[float], Meta(min_length=7, max_length=7)]
    payload: Kilograms
    max_linear_speed: Annotated[float, Meta(gt=0.0, le=3.0)]
    max_angular_speed: Annotated[float, Meta(gt=0.0, le=6.0)]
    # How hard the base speeds up and brakes in normal driving (an e-stop stops it at once).
    max_linear_acceleration: Annotated[float, Meta(gt=0.0, le=20.0)] = 1.5
    max_angular_acceleration: Annotated[float, Meta(gt=0.0, le=40.0)] = 3.0
    # How close the base must stand to an object for the arm to reach it.
    reach: Annotated[float, Meta(gt=0.0, le=2.0)] = 0.85
    arm_urdf: Name = "franka_panda/panda.urdf"


class World(Frozen):
    name: Name
    rooms: Annotated[list[Room], Meta(min_length=1)]
    furniture: list[Furniture]
    objects: list[WorldObject]
    robot: RobotSpec
    keep_out: list[KeepOut] = []
    places: list[Place] = []
    humans: list[Human] = []
    walls: list[Wall] = []


# What perception reports.


class PerceivedObject(Frozen):
    id: Id
    name: Name
    cls: Name
    color: Name
    position: Vec3
    room: Id | None = None
    on: Id | None = None  # a furniture id, "gripper", or None when on the floor
    # When it was seen (wall clock, seconds). In the resolver's memory: when it was last seen, and
    # `stale` once that is longer ago than its `stale_after`.
    stamp: float = 0.0
    stale: bool = False
    # The heading of its footprint's x side (world file `size.x`), modulo a half turn, for an
    # object whose footprint is not round (a book); None for round ones or when not seen well.
    yaw: Radians | None = None


class CameraImage(Frozen):
    """What the robot's camera sees now, for people and for models to look at: a PNG, base64-encoded.

    Not what perception works from (that is depth and segmentation): a picture of the scene."""

    stamp: float
    width: Annotated[int, Meta(ge=1, le=4096)]
    height: Annotated[int, Meta(ge=1, le=4096)]
    data: Annotated[str, Meta(max_length=16 * 1024 * 1024)]  # base64
    mime_type: Literal["image/png"] = "image/png"


class PerceivedObjects(Frozen):
    stamp: float
    objects: list[PerceivedObject]


class PerceivedHuman(Frozen):
    id: Id
    name: Name
    pose: Pose2D
    room: Id | None = None


class PerceivedHumans(Frozen):
    stamp: float
    humans: list[PerceivedHuman]


class Empty(Frozen):
    pass


class GroundTruth(Frozen):
    """The simulator's own state, for verifying outcomes: never used to decide anything."""

    sim_time: float
    robot: Pose2D
    linear_speed: float
    holding: Id | None
    objects: list[PerceivedObject]


# The scene as the resolver knows it: for people and LLM prompts.

RelationName = Literal["on", "in", "near", "left_of", "right_of"]


class SceneRelation(Frozen):
    """`subject` is `relation` `object`: "red_cup on kitchen_counter", "apple right_of blue_cup"
    (left and right as seen from the robot)."""

    subject: Id
    relation: RelationName
    object: Id


class SceneDescription(Frozen):
    """What the robot knows about the world now: objects where last seen (or where the world file
    puts them, `stamp` 0), the relations between things, and `text`, a short description in English."""

    stamp: float
    robot: Pose2D | None = None
    robot_room: Id | None = None
    objects: list[PerceivedObject] = []
    relations: list[SceneRelation] = []
    text: Text = ""


# The simulated world changing under the robot's feet (tests, demos).


class MoveEntity(Frozen):
    """Put an object or a person somewhere else in the simulation. An object is dropped at (x, y)
    with its bottom at `z` (metres; None: on top of whatever furniture is there, else the floor)."""

    id: Id
    x: Metres
    y: Metres
    z: Metres | None = None
    yaw: Radians | None = None


class Moved(Frozen, tag="moved"):
    id: Id
    position: Vec3


MoveReply = Moved | ServiceError


class FaultKind(enum.StrEnum):
    """Faults the sim can be told to inject (tests and demos of recovery)."""

    SLIP = "slip"  # the object held now (or the next one picked) slips out of the gripper during its next carry
    BLOCK = "block"  # a temporary obstacle in a room or a doorway (`target`: a room or door id)
    HIDE = "hide"  # an object moved out of the camera's sight (`target`: an object id)
    CLEAR = "clear"  # every pending fault and temporary obstacle removed


class InjectFault(Frozen):
    """A fault in the SIMULATED world, recorded like sim/move. `target` as FaultKind says ("" for slip
    and clear; a slip may name the object whose carry it waits for)."""

    kind: FaultKind
    target: Annotated[str, Meta(max_length=64, pattern=r"^[A-Za-z0-9_.:-]*(?!\n)$")] = ""


class FaultInjected(Frozen, tag="injected"):
    """`message`: what the sim did ("the next carry drops what the gripper holds", "a box blocks the
    kitchen door at (2.10, 3.00)"); `position`: where, when the fault has one."""

    kind: FaultKind
    target: str = ""
    message: Text = ""
    position: Vec3 | None = None


FaultReply = FaultInjected | ServiceError
