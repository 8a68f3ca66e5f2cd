"""Where everything is as far as the resolver knows, the relations between things, and a description."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from shapely.geometry import Point

from schemas.common import Pose2D, Vec3
from schemas.world import PerceivedObject, SceneRelation
from services.resolver.names import Entity
from services.worldmodel import WorldModel

GRIPPER = "gripper"
# Two things less than this apart sideways (as the robot sees them) are neither left nor right of each other.
SIDEWAYS_MARGIN = 0.05
COMPASS = ("east", "north-east", "north", "north-west", "west", "south-west", "south", "south-east")


@dataclass
class Belief:
    """Where an object is thought to be: perceived (`stamp`, when last seen), or from the world file
    (`stamp` 0), or where the plan put it."""

    position: Vec3
    on: str | None  # a furniture id, GRIPPER, or None for the floor
    half_height: float = 0.0
    stamp: float = 0.0
    stale: bool = False


class Scene:
    """Positions, rooms and relations of every entity, for one moment of a plan."""

    def __init__(
        self,
        model: WorldModel,
        beliefs: Mapping[str, Belief],
        robot: Pose2D | None,
        humans: Mapping[str, Pose2D],
    ) -> None:
        self.model = model
        self.beliefs = beliefs
        self.robot = robot
        self.humans = humans
        self._places = {p.id: p.pose for p in model.world.places}

    def point(self, entity: Entity) -> tuple[float, float]:
        """The entity's position on the floor plan (xy): a room's centroid, furniture's centre."""
        if entity.kind == "object":
            position = self.beliefs[entity.id].position
            return position.x, position.y
        if entity.kind == "furniture":
            cx, cy = self.model.furniture[entity.id].center
            return cx, cy
        if entity.kind == "place":
            pose = self._places[entity.id]
            return pose.x, pose.y
        if entity.kind == "human":
            pose = self.humans[entity.id]
            return pose.x, pose.y
        centre = self.model.room_shapes[entity.id].centroid
        return centre.x, centre.y

    def room(self, entity: Entity) -> str | None:
        if entity.kind == "room":
            return entity.id
        return self.model.room_of(*self.point(entity))

    def gap(self, x: float, y: float, other: Entity) -> float:
        """How far the point (x, y) is from `other` (xy): from its footprint when furniture, its
        area when a room, its position otherwise."""
        if other.kind == "furniture":
            return float(self.model.footprint(self.model.furniture[other.id]).distance(Point(x, y)))
        if other.kind == "room":
            return float(self.model.room_shapes[other.id].distance(Point(x, y)))
        return math.dist((x, y), self.point(other))

    def distance(self, entity: Entity, other: Entity) -> float:
        return self.gap(*self.point(entity), other)

    def robot_distance(self, entity: Entity) -> float | None:
        if self.robot is None:
            return None
        return math.dist((self.robot.x, self.robot.y), self.point(entity))

    def leftward(self, entity: Entity) -> float | None:
        """How far left of the robot's heading the entity is (metres, negative: right); None without a pose."""
        if self.robot is None:
            return None
        x, y = self.point(entity)
        dx, dy = x - self.robot.x, y - self.robot.y
        return -math.sin(self.robot.yaw) * dx + math.cos(self.robot.yaw) * dy

    def is_on(self, entity: Entity, support: Entity) -> bool:
        return entity.kind == "object" and support.kind == "furniture" and self.beliefs[entity.id].on == support.id

    def in_gripper(self, entity: Entity) -> bool:
        return entity.kind == "object" and self.beliefs[entity.id].on == GRIPPER

    def where(self, entity: Entity) -> str:
        """A phrase placing the entity: 'on the kitchen counter', 'in the gripper', 'in the office'."""
        if entity.kind == "object":
            on = self.beliefs[entity.id].on
            if on == GRIPPER:
                return "in the gripper"
            if on is not None and on in self.model.furniture:
                return f"on the {self.model.furniture[on].name}"
        room = self.room(entity)
        if room is None:
            return "outside every room"
        room_name = next(r.name for r in self.model.world.rooms if r.id == room)
        if entity.kind == "object":
            return f"on the floor in the {room_name}"
        return f"in the {room_name}"

    def describe(self, entity: Entity) -> str:
        """'red cup on the kitchen counter': the name and where it is, to tell candidates apart."""
        if entity.kind == "room":
            return entity.name
        return f"{entity.name} {self.where(entity)}"


def lateral_relations(scene: Scene, group: Iterable[Entity]) -> list[SceneRelation]:
    """left_of / right_of between entities in `group`, as seen from the robot."""
    placed = [(e, scene.leftward(e)) for e in group]
    relations = []
    for a, left_a in placed:
        for b, left_b in placed:
            if a.id != b.id and left_a is not None and left_b is not None and left_a > left_b + SIDEWAYS_MARGIN:
                relations.append(SceneRelation(subject=a.id, relation="left_of", object=b.id))
                relations.append(SceneRelation(subject=b.id, relation="right_of", object=a.id))
    return relations


def scene_graph(scene: Scene, objects: list[Entity], furniture: list[Entity], near: float) -> list[SceneRelation]:
    """on (object on furniture), in (object or furniture in a room), near (objects within `near` of
    each other), left_of / right_of (objects on one top, as the robot sees them)."""
    relations: list[SceneRelation] = []
    by_support: dict[str, list[Entity]] = {}
    for obj in objects:
        on = scene.beliefs[obj.id].on
        if on is not None and on in scene.model.furniture:
            relations.append(SceneRelation(subject=obj.id, relation="on", object=on))
            by_support.setdefault(on, []).append(obj)
    for entity in [*objects, *furniture]:
        room = None if scene.in_gripper(entity) else scene.room(entity)
        if room is not None:
            relations.append(SceneRelation(subject=entity.id, relation="in", object=room))
    for i, a in enumerate(objects):
        for b in objects[i + 1 :]:
            if not scene.in_gripper(a) and not scene.in_gripper(b) and scene.distance(a, b) <= near:
                relations.append(SceneRelation(subject=a.id, relation="near", object=b.id))
                relations.append(SceneRelation(subject=b.id, relation="near", object=a.id))
    for group in by_support.values():
        relations.extend(lateral_relations(scene, group))
    return relations


def heading_word(yaw: float) -> str:
    return COMPASS[round(yaw / (math.pi / 4)) % len(COMPASS)]


def _listing(items: list[str]) -> str:
    return items[0] if len(items) == 1 else f"{', '.join(items[:-1])} and {items[-1]}"


def describe_scene(
    scene: Scene,
    objects: list[Entity],
    humans: list[Entity],
    *,
    payload: float,
    masses: Mapping[str, float],
) -> str:
    """A few sentences for an LLM prompt: where the robot is, what is on each surface and where
    the people are; objects the robot cannot lift and objects not seen lately are marked."""
    sentences = []
    if scene.robot is not None:
        robot = scene.robot
        room = scene.model.room_of(robot.x, robot.y)
        room_name = next((r.name for r in scene.model.world.rooms if r.id == room), None)
        where = f"in the {room_name}" if room_name else "outside every room"
        sentences.append(f"The robot is {where} at ({robot.x:.1f}, {robot.y:.1f}), facing {heading_word(robot.yaw)}.")
    else:
        sentences.append("The robot's position is not known.")
    held = [o for o in objects if scene.in_gripper(o)]
    if held:
        sentences.append(f"It is holding the {held[0].name}.")
    surfaces: dict[str, list[str]] = {}
    for obj in objects:
        if obj in held:
            continue
        notes = []
        if masses.get(obj.id, 0.0) > payload:
            notes.append("too heavy to lift")
        if scene.beliefs[obj.id].stale:
            notes.append("not seen lately")
        label = f"the {obj.name}" + (f" ({', '.join(notes)})" if notes else "")
        surfaces.setdefault(scene.where(obj), []).append(label)
    for where, names in surfaces.items():
        verb = "is" if len(names) == 1 else "are"
        listed = _listing(names)
        sentences.append(f"{listed[0].upper()}{listed[1:]} {verb} {where}.")
    for human in humans:
        distance = scene.robot_distance(human)
        away = f", {distance:.1f} m from the robot" if distance is not None else ""
        sentences.append(f"The {human.name} is {scene.where(human)}{away}.")
    return " ".join(sentences)


def perceived(entity: Entity, scene: Scene, cls: str, color: str) -> PerceivedObject:
    """An object as the scene description lists it."""
    belief = scene.beliefs[entity.id]
    position = belief.position
    return PerceivedObject(
        id=entity.id,
        name=entity.name,
        cls=cls,
        color=color,
        position=Vec3(x=round(position.x, 3), y=round(position.y, 3), z=round(position.z, 3)),
        room=None if belief.on == GRIPPER else scene.room(entity),
        on=belief.on,
        stamp=belief.stamp,
        stale=belief.stale,
    )
