"""The world file loaded and queried: rooms, surfaces and where things rest. Pure logic."""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import pybullet_data
import shapely
from shapely.geometry import LineString, Point, Polygon, box
from shapely.geometry.base import BaseGeometry
from shapely.ops import unary_union

from schemas.common import Pose2D, Vec3
from schemas.world import Furniture, Wall, World, WorldObject
from services.bundled import DEFAULT_WORLD, world_path  # importable from here too, as before
from services.datafile import MAX_FILE_BYTES, decode_struct, read_bounded, read_struct
from services.footprint import footprint

# The base drives the last leg straight in from this far behind the goal, along the goal's
# heading, so its corners never swing around next to the furniture it parks at.
PRE_GOAL_DISTANCE = 0.4
# A pre-goal point is only added when the last leg is longer than this.
PRE_GOAL_MIN_LEG = 0.55
# An object counts as resting on a surface when its bottom is within this of the top.
SUPPORT_TOLERANCE = 0.05
# "Go to the kitchen" stands the base this far clear of furniture, walls and keep-out zones.
ROOM_POSE_CLEARANCE = 0.1
# A free spot found on the edge of the free area is moved this far inside it, so rounding keeps it free.
SPOT_INSET = 0.01
# Two rooms may share an edge; sharing more floor than this (m^2) leaves "which room" to the file's order.
ROOM_OVERLAP_TOLERANCE = 1e-6


class WorldFileError(Exception):
    """The world file is missing or does not validate; the message names the file and the field."""


def arm_urdf_path(arm_urdf: str | Path) -> Path:
    """Where the world file's `robot.arm_urdf` is: a relative path inside pybullet_data's folder
    (the URDFs that ship with it: "franka_panda/panda.urdf"), an absolute path as is."""
    return Path(pybullet_data.getDataPath()) / arm_urdf


def read_arm_urdf(arm_urdf: str | Path) -> bytes:
    """The bytes of the arm's URDF as the other data files are read (services/datafile.py): a regular
    file of at most MAX_FILE_BYTES, or ValueError naming robot.arm_urdf and where it was looked for.
    The world file may name any path, and pinocchio read whatever it was given: a FIFO hung the load,
    /dev/zero was read until memory ran out."""
    path = arm_urdf_path(arm_urdf)
    field = f"robot.arm_urdf {str(arm_urdf)!r}"
    return read_bounded(path, MAX_FILE_BYTES, "URDF", lambda message: ValueError(f"{field}: {message}"))[1]


def load_world(name_or_path: str | Path = DEFAULT_WORLD) -> World:
    path = world_path(name_or_path)
    world = read_struct(path, World, "world", WorldFileError)
    _check_world(world, path)
    return world


def parse_world(data: bytes, path: Path) -> World:
    """The world from the bytes of a file named `path` (a file kept in a recording, say)."""
    world = decode_struct(data, path, World, "world", WorldFileError)
    _check_world(world, path)
    return world


def _check_world(world: World, path: Path) -> None:
    """What the types cannot say: references resolve, and the geometry is what the checks assume.
    Safety decides with these shapes (a crossed keep-out polygon does not contain what it seems to)."""

    def bad(entry: str, why: str) -> WorldFileError:
        return WorldFileError(f"world file {path}: {entry}: {why}")

    ids = [
        *(x.id for x in world.rooms),
        *(x.id for x in world.keep_out),
        *(x.id for x in world.furniture),
        *(x.id for x in world.objects),
        *(x.id for x in world.places),
        *(x.id for x in world.humans),
        *(x.id for x in world.walls),
    ]
    duplicates = sorted(i for i, n in Counter(ids).items() if n > 1)
    if duplicates:
        raise WorldFileError(f"world file {path}: duplicate ids {duplicates}")
    furniture = {f.id: f for f in world.furniture}
    for i, obj in enumerate(world.objects):
        support = furniture.get(obj.support)
        if support is None:
            raise WorldFileError(f"world file {path}: object {obj.id!r} rests on unknown furniture {obj.support!r}")
        if abs(obj.offset[0]) > support.size.x / 2 or abs(obj.offset[1]) > support.size.y / 2:
            raise bad(f"objects[{i}] ({obj.id}).offset", f"{obj.offset} is off the top of {obj.support!r}")
    rooms = [_area(f"rooms[{i}] ({r.id})", r.polygon, bad) for i, r in enumerate(world.rooms)]
    zones = [_area(f"keep_out[{i}] ({z.id})", z.polygon, bad) for i, z in enumerate(world.keep_out)]
    # Pairs from a tree: a file of many rooms is no reason to compare each with each.
    for i, j in sorted(zip(*shapely.STRtree(rooms).query(rooms, predicate="intersects").tolist(), strict=True)):
        if j < i and rooms[i].intersection(rooms[j]).area > ROOM_OVERLAP_TOLERANCE:
            raise bad(f"rooms[{i}] ({world.rooms[i].id})", f"overlaps rooms[{j}] ({world.rooms[j].id})")
    floor = unary_union(rooms)
    for i, (zone, shape) in enumerate(zip(world.keep_out, zones, strict=True)):
        # Corners typed in the wrong place (or frame) keep the robot out of nothing, and what the
        # zone was for goes unguarded.
        if not floor.intersects(shape):
            raise bad(
                f"keep_out[{i}] ({zone.id}).polygon", "is outside every room; it would keep the robot out of nothing"
            )
    for i, wall in enumerate(world.walls):
        if wall.start == wall.end:
            raise bad(f"walls[{i}] ({wall.id})", "starts where it ends")
    model = WorldModel(world)
    for i, item in enumerate(world.furniture):
        if not floor.covers(model.footprint(item)):
            raise bad(f"furniture[{i}] ({item.id})", "is not inside the rooms")
    poses = [
        *((f"furniture[{i}] ({f.id}).approach", f.approach) for i, f in enumerate(world.furniture)),
        *((f"places[{i}] ({p.id}).pose", p.pose) for i, p in enumerate(world.places)),
        *((f"humans[{i}] ({h.id}).pose", h.pose) for i, h in enumerate(world.humans)),
        ("robot.start", world.robot.start),
    ]
    for entry, pose in poses:
        if not floor.covers(Point(pose.x, pose.y)):
            raise bad(entry, f"({pose.x:g}, {pose.y:g}) is outside every room")
    start, size = world.robot.start, world.robot.base_size
    base = footprint(start.x, start.y, start.yaw, size.x, size.y)
    for zone, shape in zip(world.keep_out, zones, strict=True):
        if base.intersects(shape):
            raise bad("robot.start", f"the base would start in keep-out zone {zone.id!r}")
    for obstacle in model.obstacles:
        if base.intersects(obstacle.shape):
            raise bad("robot.start", f"the base would start in {obstacle.id!r}")
    if not all(math.isfinite(q) for q in world.robot.home_joints):
        raise bad("robot.home_joints", "every joint position must be a finite number")
    # Every part that reads the URDF (the sim, safety, the executor, the robot bridge) loads the
    # world first: one that is no file to read stops them all here, with one error.
    try:
        read_arm_urdf(world.robot.arm_urdf)
    except ValueError as exc:
        raise WorldFileError(f"world file {path}: {exc}") from None


def _area(entry: str, points: list[list[float]], bad: Callable[[str, str], WorldFileError]) -> Polygon:
    """The polygon, refused unless it is simple: no edge crosses another, so it has an area (GEOS)."""
    shape = Polygon(points)
    if not shape.is_valid:
        why = shapely.is_valid_reason(shape)
        raise bad(f"{entry}.polygon", f"is not a simple polygon ({why}); list its corners in order around it")
    return shape


def wall_shape(wall: Wall) -> Polygon:
    """The wall's outline on the floor: from `start` to `end`, `thickness` across."""
    return LineString([wall.start, wall.end]).buffer(wall.thickness / 2, cap_style="flat")


@dataclass(frozen=True)
class Obstacle:
    """Something the base cannot drive through: a wall or a piece of furniture, as its outline."""

    id: str
    name: str
    shape: Polygon
    height: float


@dataclass(frozen=True)
class WorldModel:
    """Geometry over a World: which room a point is in, which surface holds an object."""

    world: World

    @cached_property
    def room_shapes(self) -> dict[str, Polygon]:
        return {r.id: Polygon(r.polygon) for r in self.world.rooms}

    @cached_property
    def keep_out_shapes(self) -> dict[str, Polygon]:
        return {k.id: Polygon(k.polygon) for k in self.world.keep_out}

    @cached_property
    def furniture(self) -> dict[str, Furniture]:
        return {f.id: f for f in self.world.furniture}

    @cached_property
    def objects(self) -> dict[str, WorldObject]:
        return {o.id: o for o in self.world.objects}

    @cached_property
    def obstacles(self) -> list[Obstacle]:
        """Walls and furniture: what the base must keep clear of."""
        walls = [Obstacle(w.id, w.name, wall_shape(w), w.height) for w in self.world.walls]
        furniture = [Obstacle(f.id, f.name, self.footprint(f), f.size.z) for f in self.world.furniture]
        return walls + furniture

    @cached_property
    def base_radius(self) -> float:
        """Half the base's diagonal: turning in place, it stays within this of its centre."""
        size = self.world.robot.base_size
        return math.hypot(size.x, size.y) / 2

    def footprint(self, item: Furniture) -> Polygon:
        cx, cy = item.center
        return box(cx - item.size.x / 2, cy - item.size.y / 2, cx + item.size.x / 2, cy + item.size.y / 2)

    def room_of(self, x: float, y: float) -> str | None:
        point = Point(x, y)
        for room_id, shape in self.room_shapes.items():
            if shape.covers(point):
                return room_id
        return None

    def support_under(self, position: Vec3, half_height: float) -> str | None:
        """The furniture whose top the object at `position` rests on, or None."""
        bottom = position.z - half_height
        point = Point(position.x, position.y)
        for item in self.world.furniture:
            if abs(bottom - item.size.z) <= SUPPORT_TOLERANCE and self.footprint(item).covers(point):
                return item.id
        return None

    def initial_position(self, obj: WorldObject) -> Vec3:
        """Where the world file puts an object: on its support's top at its offset."""
        support = self.furniture[obj.support]
        return Vec3(
            x=support.center[0] + obj.offset[0],
            y=support.center[1] + obj.offset[1],
            z=support.size.z + obj.size.z / 2,
        )

    def approach_near(self, furniture_id: str, x: float, y: float) -> Pose2D:
        """The furniture's approach pose moved along the edge it faces, to stand opposite (x, y)
        (kept within the furniture's length), at the same distance and heading."""
        item = self.furniture[furniture_id]
        approach = item.approach
        half = (item.size.x / 2, item.size.y / 2)
        _, along = approach_axes(item)
        point = [approach.x, approach.y]
        wanted = (x, y)[along]
        centre = item.center[along]
        point[along] = min(max(wanted, centre - half[along]), centre + half[along])
        return Pose2D(x=round(point[0], 3), y=round(point[1], 3), yaw=approach.yaw)

    def room_pose(self, room_id: str) -> Pose2D:
        """Where the base goes for 'go to the kitchen': the room's centroid, or the free spot nearest
        it where the base can turn round clear of furniture, walls and keep-out zones; facing the
        first of east, north, west, south (then the diagonals) from which it can drive straight in
        (drive_route parks from PRE_GOAL_DISTANCE behind the goal)."""
        room = self.room_shapes[room_id]
        c = room.centroid
        radius = self.base_radius + ROOM_POSE_CLEARANCE
        spot = self.free_spot(c.x, c.y, radius, room)
        x, y = spot if spot is not None else (c.x, c.y)
        headings = [k * math.pi / 2 for k in range(4)] + [math.pi / 4 + k * math.pi / 2 for k in range(4)]
        for yaw in headings:
            behind = Point(x - PRE_GOAL_DISTANCE * math.cos(yaw), y - PRE_GOAL_DISTANCE * math.sin(yaw))
            if not self._blocked.intersects(behind.buffer(radius)):
                return Pose2D(x=round(x, 3), y=round(y, 3), yaw=round(math.remainder(yaw, math.tau), 4))
        return Pose2D(x=round(x, 3), y=round(y, 3), yaw=0.0)

    @cached_property
    def _blocked(self) -> BaseGeometry:
        """Walls, furniture and keep-out zones: where the base may not be."""
        return unary_union([o.shape for o in self.obstacles] + list(self.keep_out_shapes.values()))

    def clear_by(self, shape: BaseGeometry) -> float:
        """How far `shape` (a footprint) keeps from every wall, piece of furniture and keep-out zone."""
        return float(self._blocked.distance(shape))

    def free_spot(self, x: float, y: float, radius: float, within: Polygon) -> tuple[float, float] | None:
        """The point nearest (x, y) inside `within` whose `radius` around it touches no obstacle or
        keep-out zone; None when there is none."""
        blocked = self._blocked
        allowed = within.difference(blocked.buffer(radius)) if not blocked.is_empty else within
        if allowed.is_empty:
            return None
        target = Point(x, y)
        if allowed.covers(target):
            return x, y
        inside = allowed.buffer(-SPOT_INSET)
        area = inside if not inside.is_empty else allowed
        nearest = area.boundary.interpolate(area.boundary.project(target))
        return float(nearest.x), float(nearest.y)


def approach_axes(item: Furniture) -> tuple[int, int]:
    """Which map axis (0: x, 1: y) runs across the edge the furniture's approach pose faces, and
    which along it: the axis along which the approach pose lies farther out, relative to size."""
    (cx, cy), approach = item.center, item.approach
    across = 0 if abs(approach.x - cx) / (item.size.x / 2) >= abs(approach.y - cy) / (item.size.y / 2) else 1
    return across, 1 - across


def approach_towards(target_x: float, target_y: float, distance: float, from_x: float, from_y: float) -> Pose2D:
    """A pose `distance` short of the target on the line from (from_x, from_y), facing the target."""
    yaw = math.atan2(target_y - from_y, target_x - from_x)
    return Pose2D(x=target_x - distance * math.cos(yaw), y=target_y - distance * math.sin(yaw), yaw=yaw)


def drive_route(start: Pose2D, path: list[Pose2D], goal: Pose2D) -> list[tuple[float, float]]:
    """The points the base actually drives through, in order: the path, a pre-goal, the goal.

    The sim follows exactly this route and safety checks exactly this route.
    """
    points = [(p.x, p.y) for p in path]
    leg_start = points[-1] if points else (start.x, start.y)
    if math.dist(leg_start, (goal.x, goal.y)) > PRE_GOAL_MIN_LEG:
        back = PRE_GOAL_DISTANCE
        points.append((goal.x - back * math.cos(goal.yaw), goal.y - back * math.sin(goal.yaw)))
    points.append((goal.x, goal.y))
    return points
