"""Foxglove's well-known messages (JSON) for the 3D scene, frames, camera and log, made from tether's. Pure logic.

Foxglove recognises a message by its schema name (`foxglove.SceneUpdate`, ...) and reads the JSON
encoding of the same fields its protobuf and ROS definitions have: times are `{sec, nsec}`, enums
are integers, bytes are base64 strings marked `contentEncoding: base64` in the schema. The Structs
below carry the fields Foxglove requires (every one of them, as its own JSON Schemas require); the
schema documents are generated from them, as the recorder does for tether's own messages. The live
view (`tether view`) and the recorder both use this module, so a recording opened in Foxglove shows
what the live view shows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import msgspec
from msgspec import Meta

from schemas import keys
from schemas.actions import Feedback, GoalStatus
from schemas.common import Pose2D
from schemas.executor import ExecutePlanFeedback, StepStatus
from schemas.robot import Odometry
from schemas.safety import Decision, SafetyEvent
from schemas.world import CameraImage, KeepOut, PerceivedHumans, PerceivedObjects, World, WorldObject

# Topics: the same in the live view and in recordings, so one layout (deploy/foxglove-layout.json) opens both.
# Walls, furniture, rooms, keep-out zones, the robot's body: once (and again for each new viewer).
SCENE_TOPIC = "foxglove/scene"
OBJECTS_TOPIC = "foxglove/objects"  # where perception last saw each object
PEOPLE_TOPIC = "foxglove/people"  # people with their separation rings
ROUTE_TOPIC = "foxglove/route"  # the base's planned route
TF_TOPIC = "foxglove/tf"  # map -> base (and the arm's links in the live view)
CAMERA_TOPIC = "foxglove/camera"
LOG_TOPIC = "foxglove/log"  # safety events, step feedback, the plan's status
MAP_FRAME = "map"
BASE_FRAME = "base"
CAMERA_FRAME = "camera"

# foxglove.LinePrimitive's type; foxglove.SceneEntityDeletion's type; foxglove.Log's level.
LINE_STRIP, LINE_LOOP = 0, 1
DELETE_ALL = 1
LOG_DEBUG, LOG_INFO, LOG_WARNING, LOG_ERROR = 1, 2, 3, 4

PERSON_HEIGHT = 1.7  # m: how tall a person is drawn
RING_SEGMENTS = 48


class Message(msgspec.Struct, frozen=True, kw_only=True):
    pass


Base64 = Annotated[str, Meta(extra_json_schema={"contentEncoding": "base64"})]


# Foxglove's Time holds its seconds in a uint32.
MAX_STAMP_SEC = 2**32 - 1


class Time(Message, kw_only=True):
    sec: Annotated[int, Meta(ge=0, le=MAX_STAMP_SEC)]
    nsec: Annotated[int, Meta(ge=0, le=999_999_999)]


class Vector3(Message, kw_only=True):
    x: float
    y: float
    z: float


class Quaternion(Message, kw_only=True):
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    w: float = 1.0


class Pose(Message, kw_only=True):
    position: Vector3
    orientation: Quaternion = Quaternion()


class Color(Message, kw_only=True):
    r: float
    g: float
    b: float
    a: float = 1.0


class Point3(Message, kw_only=True):
    x: float
    y: float
    z: float


class KeyValuePair(Message, kw_only=True):
    key: str
    value: str


class CubePrimitive(Message, kw_only=True):
    pose: Pose
    size: Vector3
    color: Color


class SpherePrimitive(Message, kw_only=True):
    pose: Pose
    size: Vector3
    color: Color


class CylinderPrimitive(Message, kw_only=True):
    pose: Pose
    size: Vector3
    bottom_scale: float = 1.0
    top_scale: float = 1.0
    color: Color


class LinePrimitive(Message, kw_only=True):
    type: int
    pose: Pose
    thickness: float
    scale_invariant: bool = False
    points: list[Point3]
    color: Color
    colors: list[Color] = []
    indices: list[int] = []


class TextPrimitive(Message, kw_only=True):
    pose: Pose
    billboard: bool = True
    font_size: float
    scale_invariant: bool = False
    color: Color
    text: str


class SceneEntity(Message, kw_only=True):
    timestamp: Time
    frame_id: str
    id: str
    lifetime: Time = Time(sec=0, nsec=0)  # zero: until replaced or deleted
    frame_locked: bool = False
    metadata: list[KeyValuePair] = []
    # Arrows, triangles and models are not drawn here; Foxglove requires the fields all the same.
    arrows: list[dict[str, Any]] = []
    cubes: list[CubePrimitive] = []
    spheres: list[SpherePrimitive] = []
    cylinders: list[CylinderPrimitive] = []
    lines: list[LinePrimitive] = []
    triangles: list[dict[str, Any]] = []
    texts: list[TextPrimitive] = []
    models: list[dict[str, Any]] = []


class SceneEntityDeletion(Message, kw_only=True):
    timestamp: Time
    type: int
    id: str = ""


class SceneUpdate(Message, kw_only=True):
    deletions: list[SceneEntityDeletion] = []
    entities: list[SceneEntity] = []


class FrameTransform(Message, kw_only=True):
    timestamp: Time
    parent_frame_id: str
    child_frame_id: str
    translation: Vector3
    rotation: Quaternion


class FrameTransforms(Message, kw_only=True):
    transforms: list[FrameTransform]


class CompressedImage(Message, kw_only=True):
    timestamp: Time
    frame_id: str
    data: Base64
    format: str


class Log(Message, kw_only=True):
    timestamp: Time
    level: int
    message: str
    name: str
    file: str = ""
    line: int = 0


SCHEMA_NAMES: dict[type[Message], str] = {
    SceneUpdate: "foxglove.SceneUpdate",
    FrameTransforms: "foxglove.FrameTransforms",
    CompressedImage: "foxglove.CompressedImage",
    Log: "foxglove.Log",
}
TOPIC_TYPES: dict[str, type[Message]] = {
    SCENE_TOPIC: SceneUpdate,
    OBJECTS_TOPIC: SceneUpdate,
    PEOPLE_TOPIC: SceneUpdate,
    ROUTE_TOPIC: SceneUpdate,
    TF_TOPIC: FrameTransforms,
    CAMERA_TOPIC: CompressedImage,
    LOG_TOPIC: Log,
}
_encoder = msgspec.json.Encoder()


def encode(message: Message) -> bytes:
    return _encoder.encode(message)


def schema_document(type_: type[Message]) -> bytes:
    """The JSON Schema of a Foxglove message, its root inlined (Foxglove wants `"type": "object"` at the top)."""
    document: dict[str, Any] = msgspec.json.schema(type_)
    defs: dict[str, Any] = document.pop("$defs", {})
    root = defs[type_.__name__]
    return msgspec.json.encode({**root, "title": SCHEMA_NAMES[type_], "$defs": defs})


def stamp(seconds: float) -> Time:
    """`seconds` as Foxglove's time, whose seconds are a uint32. A stamp no such time holds (NaN,
    before 1970, after 2106: anything a peer sends) is the nearest one, not an error that ends the
    view or loses the recorder's derived message."""
    if not seconds > 0.0:  # also NaN
        return Time(sec=0, nsec=0)
    if seconds >= MAX_STAMP_SEC + 1:
        return Time(sec=MAX_STAMP_SEC, nsec=999_999_999)
    sec = int(seconds)
    return Time(sec=sec, nsec=min(999_999_999, max(0, round((seconds - sec) * 1e9))))


def yaw_rotation(yaw: float) -> Quaternion:
    return Quaternion(z=math.sin(yaw / 2), w=math.cos(yaw / 2))


def rgba(values: list[float]) -> Color:
    return Color(r=values[0], g=values[1], b=values[2], a=values[3])


def at(x: float, y: float, z: float = 0.0, yaw: float = 0.0) -> Pose:
    return Pose(position=Vector3(x=x, y=y, z=z), orientation=yaw_rotation(yaw))


def label(text: str, x: float, y: float, z: float, color: Color, size: float = 0.25) -> TextPrimitive:
    return TextPrimitive(pose=at(x, y, z), font_size=size, color=color, text=text)


def outline(points: list[list[float]], z: float, color: Color, thickness: float = 0.04) -> LinePrimitive:
    return LinePrimitive(
        type=LINE_LOOP,
        pose=at(0.0, 0.0),
        thickness=thickness,
        points=[Point3(x=p[0], y=p[1], z=z) for p in points],
        color=color,
    )


def circle(x: float, y: float, radius: float, color: Color, thickness: float = 0.03) -> LinePrimitive:
    points = [
        [x + radius * math.cos(2 * math.pi * i / RING_SEGMENTS), y + radius * math.sin(2 * math.pi * i / RING_SEGMENTS)]
        for i in range(RING_SEGMENTS)
    ]
    return outline(points, 0.02, color, thickness)


WALL_COLOR = Color(r=0.75, g=0.75, b=0.72, a=1.0)
ROOM_COLOR = Color(r=0.55, g=0.55, b=0.6, a=1.0)
KEEP_OUT_COLOR = Color(r=0.9, g=0.1, b=0.1, a=1.0)
ROBOT_COLOR = Color(r=0.2, g=0.45, b=0.85, a=0.9)
PERSON_COLOR = Color(r=0.95, g=0.75, b=0.3, a=0.9)
STOP_RING_COLOR = Color(r=0.9, g=0.1, b=0.1, a=1.0)
SLOW_RING_COLOR = Color(r=1.0, g=0.6, b=0.0, a=1.0)
ROUTE_COLOR = Color(r=0.1, g=0.8, b=0.3, a=1.0)
TEXT_COLOR = Color(r=1.0, g=1.0, b=1.0, a=1.0)


@dataclass(frozen=True)
class Separation:
    """Safety's distances around a person (the policy's `[humans]`): the rings drawn around each one."""

    person_radius: float = 0.2
    stop_distance: float = 0.2
    slow_distance: float = 1.5


class _PolicyHumans(msgspec.Struct, frozen=True):
    person_radius: float = 0.2
    stop_distance: float = 0.2
    slow_distance: float = 1.5


class _PolicyDrawn(msgspec.Struct, frozen=True):
    """Only what is drawn; safety checks the whole policy when it starts, this reads past the rest."""

    humans: _PolicyHumans = _PolicyHumans()
    keep_out: list[KeepOut] = []


def policy_drawn(data: bytes, path: Path) -> tuple[Separation, list[KeepOut]]:
    """The separation distances and the policy's own keep-out zones, from the policy file's bytes.

    Raises ValueError naming the file if it cannot be read as a policy."""
    try:
        if path.suffix == ".toml":
            drawn = msgspec.toml.decode(data, type=_PolicyDrawn)
        else:
            drawn = msgspec.yaml.decode(data, type=_PolicyDrawn)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise ValueError(f"policy file {path}: {exc}") from None
    h = drawn.humans
    return Separation(h.person_radius, h.stop_distance, h.slow_distance), list(drawn.keep_out)


@dataclass(frozen=True)
class Scene:
    """What the 3D view draws that does not move: the world file, and the policy's zones and distances."""

    world: World
    extra_keep_out: list[KeepOut] = field(default_factory=list)
    separation: Separation = Separation()

    def static(self, now: float) -> SceneUpdate:
        """Walls, furniture, rooms, keep-out zones and places in the map frame; the robot's body in the base frame."""
        t = stamp(now)
        world = self.world
        entities: list[SceneEntity] = []
        walls = []
        for wall in world.walls:
            (x0, y0), (x1, y1) = wall.start[:2], wall.end[:2]
            length = math.hypot(x1 - x0, y1 - y0)
            walls.append(
                CubePrimitive(
                    pose=at((x0 + x1) / 2, (y0 + y1) / 2, wall.height / 2, math.atan2(y1 - y0, x1 - x0)),
                    size=Vector3(x=length + wall.thickness, y=wall.thickness, z=wall.height),
                    color=WALL_COLOR,
                )
            )
        entities.append(SceneEntity(timestamp=t, frame_id=MAP_FRAME, id="walls", cubes=walls))
        for item in world.furniture:
            x, y = item.center[:2]
            entities.append(
                SceneEntity(
                    timestamp=t,
                    frame_id=MAP_FRAME,
                    id=f"furniture/{item.id}",
                    metadata=[KeyValuePair(key="name", value=item.name)],
                    cubes=[
                        CubePrimitive(
                            pose=at(x, y, item.size.z / 2),
                            size=Vector3(x=item.size.x, y=item.size.y, z=item.size.z),
                            color=rgba(item.rgba),
                        )
                    ],
                    texts=[label(item.name, x, y, item.size.z + 0.15, TEXT_COLOR, 0.18)],
                )
            )
        for room in world.rooms:
            cx = sum(p[0] for p in room.polygon) / len(room.polygon)
            cy = sum(p[1] for p in room.polygon) / len(room.polygon)
            entities.append(
                SceneEntity(
                    timestamp=t,
                    frame_id=MAP_FRAME,
                    id=f"room/{room.id}",
                    lines=[outline(room.polygon, 0.005, ROOM_COLOR, 0.02)],
                    texts=[label(room.name, cx, cy, 0.05, ROOM_COLOR, 0.3)],
                )
            )
        for zone in [*world.keep_out, *self.extra_keep_out]:
            cx = sum(p[0] for p in zone.polygon) / len(zone.polygon)
            cy = sum(p[1] for p in zone.polygon) / len(zone.polygon)
            entities.append(
                SceneEntity(
                    timestamp=t,
                    frame_id=MAP_FRAME,
                    id=f"keep_out/{zone.id}",
                    metadata=[KeyValuePair(key="reason", value=zone.reason)],
                    lines=[outline(zone.polygon, 0.01, KEEP_OUT_COLOR, 0.06)],
                    texts=[label(f"keep out: {zone.name}", cx, cy, 0.1, KEEP_OUT_COLOR, 0.25)],
                )
            )
        for place in world.places:
            entities.append(
                SceneEntity(
                    timestamp=t,
                    frame_id=MAP_FRAME,
                    id=f"place/{place.id}",
                    texts=[label(place.name, place.pose.x, place.pose.y, 0.05, TEXT_COLOR, 0.15)],
                )
            )
        body = world.robot.base_size
        entities.append(
            SceneEntity(
                timestamp=t,
                frame_id=BASE_FRAME,
                id="robot/base",
                frame_locked=True,  # moves with the base frame
                cubes=[
                    CubePrimitive(
                        pose=at(0.0, 0.0, body.z / 2), size=Vector3(x=body.x, y=body.y, z=body.z), color=ROBOT_COLOR
                    )
                ],
            )
        )
        return SceneUpdate(entities=entities)

    def objects(self, seen: PerceivedObjects) -> SceneUpdate:
        """Each object where perception last saw it, with the shape, size and colour of the world file."""
        t = stamp(seen.stamp)
        known: dict[str, WorldObject] = {o.id: o for o in self.world.objects}
        entities = []
        for obj in seen.objects:
            spec = known.get(obj.id)
            extent = (0.08, 0.08, 0.08) if spec is None else (spec.size.x, spec.size.y, spec.size.z)
            size = Vector3(x=extent[0], y=extent[1], z=extent[2])
            color = Color(r=0.6, g=0.6, b=0.6) if spec is None else rgba(spec.rgba)
            if obj.stale:  # not seen lately: drawn faded
                color = Color(r=color.r, g=color.g, b=color.b, a=0.35)
            pose = at(obj.position.x, obj.position.y, obj.position.z, obj.yaw or 0.0)
            shape = "box" if spec is None else spec.shape
            entity = SceneEntity(
                timestamp=t,
                frame_id=MAP_FRAME,
                id=f"object/{obj.id}",
                metadata=[KeyValuePair(key="on", value=obj.on or ""), KeyValuePair(key="room", value=obj.room or "")],
                cubes=[CubePrimitive(pose=pose, size=size, color=color)] if shape == "box" else [],
                spheres=[SpherePrimitive(pose=pose, size=size, color=color)] if shape == "sphere" else [],
                cylinders=[CylinderPrimitive(pose=pose, size=size, color=color)] if shape == "cylinder" else [],
                texts=[label(obj.name, obj.position.x, obj.position.y, obj.position.z + 0.15, TEXT_COLOR, 0.12)],
            )
            entities.append(entity)
        # The whole set each time: an object perception no longer reports disappears.
        return SceneUpdate(deletions=[SceneEntityDeletion(timestamp=t, type=DELETE_ALL)], entities=entities)

    def people(self, seen: PerceivedHumans) -> SceneUpdate:
        """Each person as a body `person_radius` wide, ringed where safety stops the robot (red) and slows it (orange).

        Safety measures from the robot's footprint (or its hand) to the body: the robot's outline
        inside the red ring is a stop, inside the orange one reduced speed."""
        t = stamp(seen.stamp)
        sep = self.separation
        entities = []
        for person in seen.humans:
            x, y = person.pose.x, person.pose.y
            radius = max(sep.person_radius, 0.05)
            entities.append(
                SceneEntity(
                    timestamp=t,
                    frame_id=MAP_FRAME,
                    id=f"person/{person.id}",
                    cylinders=[
                        CylinderPrimitive(
                            pose=at(x, y, PERSON_HEIGHT / 2),
                            size=Vector3(x=2 * radius, y=2 * radius, z=PERSON_HEIGHT),
                            color=PERSON_COLOR,
                        )
                    ],
                    lines=[
                        circle(x, y, sep.person_radius + sep.stop_distance, STOP_RING_COLOR),
                        circle(x, y, sep.person_radius + sep.slow_distance, SLOW_RING_COLOR),
                    ],
                    texts=[label(person.name, x, y, PERSON_HEIGHT + 0.2, TEXT_COLOR, 0.2)],
                )
            )
        return SceneUpdate(deletions=[SceneEntityDeletion(timestamp=t, type=DELETE_ALL)], entities=entities)


def route(path: list[Pose2D], goal: Pose2D, now: float) -> SceneUpdate:
    """The base's route as the navigation goal gave it (its waypoints, then the goal)."""
    t = stamp(now)
    points = [Point3(x=p.x, y=p.y, z=0.03) for p in [*path, goal]]
    entity = SceneEntity(
        timestamp=t,
        frame_id=MAP_FRAME,
        id="route",
        lines=[LinePrimitive(type=LINE_STRIP, pose=at(0.0, 0.0), thickness=0.05, points=points, color=ROUTE_COLOR)],
        spheres=[
            SpherePrimitive(pose=at(goal.x, goal.y, 0.05), size=Vector3(x=0.15, y=0.15, z=0.15), color=ROUTE_COLOR)
        ],
    )
    return SceneUpdate(deletions=[SceneEntityDeletion(timestamp=t, type=DELETE_ALL)], entities=[entity])


def base_transform(odom: Odometry) -> FrameTransform:
    """map -> base from odometry (the base on the floor, turned by its yaw)."""
    p = odom.pose
    return FrameTransform(
        timestamp=stamp(odom.stamp),
        parent_frame_id=MAP_FRAME,
        child_frame_id=BASE_FRAME,
        translation=Vector3(x=p.x, y=p.y, z=0.0),
        rotation=yaw_rotation(p.yaw),
    )


def camera_image(image: CameraImage) -> CompressedImage:
    """The camera's PNG as it came (already base64)."""
    return CompressedImage(
        timestamp=stamp(image.stamp), frame_id=CAMERA_FRAME, data=image.data, format=image.mime_type.split("/")[-1]
    )


SAFETY_LEVELS = {
    Decision.APPROVED: LOG_DEBUG,
    Decision.RESET: LOG_INFO,
    Decision.LIMITED: LOG_INFO,
    Decision.CLAMPED: LOG_WARNING,
    Decision.VETOED: LOG_WARNING,
    Decision.STOPPED: LOG_WARNING,
    Decision.LATCHED: LOG_ERROR,
}


def safety_log(event: SafetyEvent) -> Log:
    rule = f" [{event.rule}]" if event.rule is not None else ""
    reason = f": {event.reason}" if event.reason else ""
    return Log(
        timestamp=stamp(event.stamp),
        level=SAFETY_LEVELS.get(event.decision, LOG_INFO),
        message=f"{event.decision} {event.key}{rule}{reason}",
        name="safety",
    )


def feedback_log(goal_id: str, feedback: ExecutePlanFeedback, now: float) -> Log:
    where = f"step {feedback.label or feedback.step} " if feedback.step is not None else ""
    action = f"{feedback.action} " if feedback.action else ""
    message = f" {feedback.message}" if feedback.message else ""
    failed = feedback.status is StepStatus.FAILED
    return Log(
        timestamp=stamp(now),
        level=LOG_WARNING if failed else LOG_INFO,
        message=f"plan {goal_id[:8]} {feedback.stage}: {where}{action}{feedback.status}{message}",
        name="executor",
    )


def plan_status_log(status: GoalStatus, now: float) -> Log:
    bad = status.state in ("aborted", "rejected")
    message = f": {status.message}" if status.message else ""
    return Log(
        timestamp=stamp(status.stamp or now),
        level=LOG_WARNING if bad else LOG_INFO,
        message=f"plan {status.goal_id[:8]} {status.state}{message}",
        name="plan",
    )


def scene_from_files(world: bytes, world_path: Path, policy: bytes | None, policy_path: Path | None) -> Scene:
    """The scene from the bytes of the world and policy files (as a recording keeps them); ValueError names the file."""
    from services.datafile import decode_struct  # msgspec only: no shapely for the recorder

    drawn = decode_struct(world, world_path, World, "world", ValueError)
    separation, zones = Separation(), list[KeepOut]()
    if policy is not None and policy_path is not None:
        separation, zones = policy_drawn(policy, policy_path)
    return Scene(drawn, zones, separation)


def is_derived(topic: str) -> bool:
    """Whether a recording's channel holds messages made for Foxglove from the traffic, not traffic itself."""
    return topic in TOPIC_TYPES


class Derived:
    """What a recording adds for Foxglove to each message of the traffic: frames from odometry, the scene's
    objects and people, and log lines from safety events and plan progress. Pure: bytes in, messages out."""

    def __init__(self, robot: str, scene: Scene | None) -> None:
        plan = keys.EXECUTE_PLAN
        self.scene = scene
        self._decoders: dict[str, tuple[str, msgspec.json.Decoder[Any]]] = {
            keys.ODOM.key(robot): ("odom", msgspec.json.Decoder(Odometry)),
            keys.SAFETY_EVENTS.key(robot): ("safety", msgspec.json.Decoder(SafetyEvent)),
            plan.feedback.key(robot): ("feedback", msgspec.json.Decoder(Feedback[ExecutePlanFeedback])),  # type: ignore[misc]
            plan.status.key(robot): ("plan", msgspec.json.Decoder(GoalStatus)),
        }
        if scene is not None:
            self._decoders[keys.OBJECTS.key(robot)] = ("objects", msgspec.json.Decoder(PerceivedObjects))
            self._decoders[keys.HUMANS.key(robot)] = ("humans", msgspec.json.Decoder(PerceivedHumans))

    def wants(self, key: str) -> bool:
        return key in self._decoders

    def messages(self, key: str, payload: bytes, now: float) -> list[tuple[str, Message]]:
        """The Foxglove messages (topic, message) made from one message on `key`; none if it does not decode."""
        found = self._decoders.get(key)
        if found is None:
            return []
        kind, decoder = found
        try:
            message = decoder.decode(payload)
        except (msgspec.DecodeError, msgspec.ValidationError):
            return []
        if kind == "odom":
            return [(TF_TOPIC, FrameTransforms(transforms=[base_transform(message)]))]
        if kind == "safety":
            return [(LOG_TOPIC, safety_log(message))]
        if kind == "feedback":
            return [(LOG_TOPIC, feedback_log(message.goal_id, message.feedback, now))]
        if kind == "plan":
            return [(LOG_TOPIC, plan_status_log(message, now))]
        assert self.scene is not None
        if kind == "objects":
            return [(OBJECTS_TOPIC, self.scene.objects(message))]
        return [(PEOPLE_TOPIC, self.scene.people(message))]
