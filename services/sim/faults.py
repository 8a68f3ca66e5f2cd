"""Faults injected into the simulated world (sim/fault), and what only the sim feels: the robot
touching something, and an object leaving the gripper other than by an open command.

The geometry (doorways, where a block stands, where a slipped object lands) is pure logic over the
world file; `Faults` applies it to a SimWorld and is ticked after every physics step.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from shapely.geometry import Point
from shapely.geometry.base import BaseGeometry
from shapely.ops import nearest_points, unary_union

from schemas.common import ErrorKind, Pose2D, ServiceError, Vec3
from schemas.incidents import IncidentKind, IncidentReport
from schemas.world import FaultInjected, FaultKind, FaultReply, InjectFault, World
from services.footprint import distance_to_footprint, footprint
from services.sim.world import DROP_HEIGHT, HUMAN_RADIUS, BlockShape, Drop, Position, SimWorld
from services.worldmodel import WorldModel

log = logging.getLogger(__name__)

# A gap between two walls on one line counts as a doorway when it is this wide (metres).
DOOR_MIN, DOOR_MAX = 0.5, 2.5
# The rooms on either side of a doorway are looked up this far from its middle, across the wall.
DOOR_PROBE = 0.3
# A block: a box this high; across a doorway this deep (its width is the doorway's); in a room a
# square of this side where "go to the room" would park the base.
BLOCK_HEIGHT = 0.6
BLOCK_DEPTH = 0.3
ROOM_BLOCK_SIDE = 0.8

# slip: the held object slips once the base has driven this far while holding it.
SLIP_DISTANCE = 0.3
# Where it lands: on a top, this far in from its edge (beyond the object's radius); on the floor,
# this far beyond the base's edge; and this far from any other object.
TOP_INSET = 0.04
FLOOR_GAP = 0.12
OBJECT_GAP = 0.03
# Spots tried along a top's edge, each this far from the last, on both sides of the nearest.
ALONG_STEP = 0.08
ALONG_TRIES = 8

# hide: objects are set down outside the house, behind its outer walls and beyond the camera's
# range from anywhere inside, this far apart.
HIDE_AT = (-3.0, -3.0)
HIDE_STEP = 0.5

# Collisions and drops are checked this often (sim seconds): the robot touching something is
# reported once per contact episode, which ends when that thing was not touched for CONTACT_GAP.
CHECK_PERIOD = 0.05
CONTACT_GAP = 1.0
# A held object farther than this from the hand has left the gripper (pushed off, torn away).
GRIP_LOST = 0.15


@dataclass(frozen=True)
class Doorway:
    """The gap between two walls on one line that joins two rooms. `id`: the two room ids, in the
    world file's order, joined by "-" ("kitchen-living_room"); `yaw`: the walls' direction."""

    id: str
    rooms: tuple[str, str]
    centre: tuple[float, float]
    width: float
    yaw: float
    thickness: float


def doorways(world: World) -> dict[str, Doorway]:
    """Every doorway of the world file: a gap of DOOR_MIN to DOOR_MAX between two walls on one line,
    no other wall in it, with a different room on each side."""
    model = WorldModel(world)
    order = {room.id: i for i, room in enumerate(world.rooms)}
    found: dict[str, Doorway] = {}
    walls = world.walls
    for i, a in enumerate(walls):
        (ax, ay), (bx, by) = a.start, a.end
        length = math.hypot(bx - ax, by - ay)
        if length < 1e-9:
            continue
        ux, uy = (bx - ax) / length, (by - ay) / length

        def along(point: Sequence[float], ax: float = ax, ay: float = ay, ux: float = ux, uy: float = uy) -> float:
            return (point[0] - ax) * ux + (point[1] - ay) * uy

        def off(point: Sequence[float], ax: float = ax, ay: float = ay, ux: float = ux, uy: float = uy) -> float:
            return abs(-(point[0] - ax) * uy + (point[1] - ay) * ux)

        on_line = [w for w in walls if off(w.start) < 1e-6 and off(w.end) < 1e-6]
        spans = [tuple(sorted((along(w.start), along(w.end)))) for w in on_line]
        mine = tuple(sorted((along(a.start), along(a.end))))
        for j, b in enumerate(walls):
            if j <= i or b not in on_line:
                continue
            theirs = tuple(sorted((along(b.start), along(b.end))))
            low, high = (mine, theirs) if mine[0] <= theirs[0] else (theirs, mine)
            gap = (low[1], high[0])
            width = gap[1] - gap[0]
            if not DOOR_MIN <= width <= DOOR_MAX:
                continue
            if any(s[0] < gap[1] - 1e-6 and s[1] > gap[0] + 1e-6 for s in spans):
                continue  # another wall stands in the gap
            middle = (gap[0] + gap[1]) / 2
            cx, cy = ax + ux * middle, ay + uy * middle
            sides = [model.room_of(cx - uy * d, cy + ux * d) for d in (DOOR_PROBE, -DOOR_PROBE)]
            if sides[0] is None or sides[1] is None or sides[0] == sides[1]:
                continue
            first, second = sorted((sides[0], sides[1]), key=lambda r: order[r])
            door_id = f"{first}-{second}"
            if door_id in found:
                door_id = f"{door_id}-{sum(1 for d in found.values() if d.rooms == (first, second)) + 1}"
            thickness = max(a.thickness, b.thickness)
            found[door_id] = Doorway(door_id, (first, second), (cx, cy), width, math.atan2(uy, ux), thickness)
    return found


def find_doorway(doors: dict[str, Doorway], target: str) -> Doorway | None:
    """The doorway `target` names: its id, or its two rooms the other way round ("living_room-kitchen")."""
    if target in doors:
        return doors[target]
    rooms = tuple(target.split("-", 1))
    return next((d for d in doors.values() if len(rooms) == 2 and d.rooms == (rooms[1], rooms[0])), None)


def block_for(model: WorldModel, doors: dict[str, Doorway], target: str) -> BlockShape | ServiceError:
    """The obstacle `block TARGET` puts up: across a doorway, filling it; in a room, where "go to
    the room" parks the base. An unknown target is an error naming the rooms and doorways."""
    door = find_doorway(doors, target)
    if door is not None:
        half = (door.width / 2, max(BLOCK_DEPTH, door.thickness) / 2, BLOCK_HEIGHT / 2)
        centre = (door.centre[0], door.centre[1], BLOCK_HEIGHT / 2)
        names = [model.world.rooms[[r.id for r in model.world.rooms].index(r)].name for r in door.rooms]
        name = f"a box in the doorway between the {names[0]} and the {names[1]}"
        return BlockShape(id=door.id, name=name, centre=centre, half=half, yaw=door.yaw)
    room = next((r for r in model.world.rooms if r.id == target), None)
    if room is not None:
        pose = model.room_pose(room.id)
        side = ROOM_BLOCK_SIDE / 2
        centre = (pose.x, pose.y, BLOCK_HEIGHT / 2)
        return BlockShape(
            id=room.id,
            name=f"a box in the middle of the {room.name}",
            centre=centre,
            half=(side, side, BLOCK_HEIGHT / 2),
        )
    known = [r.id for r in model.world.rooms] + sorted(doors)
    message = f"no room or doorway {target!r} in the world {model.world.name!r} to block"
    return ServiceError(kind=ErrorKind.INVALID_REQUEST, message=message, candidates=known)


def block_outline(block: BlockShape) -> BaseGeometry:
    """The block's outline on the floor."""
    x, y, _ = block.centre
    return footprint(x, y, block.yaw, 2 * block.half[0], 2 * block.half[1])


@dataclass(frozen=True)
class Landing:
    """Where a slipped object comes down: (x, y) with its bottom at `bottom`, on furniture `on` (None: the floor)."""

    x: float
    y: float
    bottom: float
    on: str | None = None


def landing_spot(
    model: WorldModel,
    base: Pose2D,
    radius: float,
    others: Iterable[tuple[float, float, float]] = (),
    blocks: Iterable[BaseGeometry] = (),
    people: Iterable[tuple[float, float]] = (),
) -> Landing | None:
    """Where an object of `radius` that slips out of the gripper of a base at `base` lands: on the top
    of the nearest furniture within the arm's reach (`robot.reach` from the base's centre), at the
    point nearest the base, TOP_INSET in from the edge, or along that edge where the point is taken;
    else on free floor FLOOR_GAP beyond the base's back, left, right or front edge (then twice and
    four times as far): inside a room, clear of walls, furniture, keep-out zones, blocks, people and
    `others` (x, y, radius of each other object). None when there is no such spot."""
    robot = model.world.robot
    centre = Point(base.x, base.y)
    others = list(others)
    blocked = list(blocks)
    people_at = [Point(x, y) for x, y in people]

    def clear_of_things(spot: Point) -> bool:
        if any(math.hypot(spot.x - x, spot.y - y) < radius + r + OBJECT_GAP for x, y, r in others):
            return False
        area = spot.buffer(radius)
        return not any(area.intersects(b) for b in blocked)

    tops = sorted(model.world.furniture, key=lambda f: model.footprint(f).distance(centre))
    for item in tops:
        if model.footprint(item).distance(centre) > robot.reach:
            break
        inner = model.footprint(item).buffer(-(radius + TOP_INSET), join_style="mitre")
        if inner.is_empty:
            continue
        nearest = nearest_points(inner, centre)[0]
        edge = inner.exterior
        start = edge.project(nearest)
        for k in range(2 * ALONG_TRIES + 1):
            offset = (k + 1) // 2 * ALONG_STEP * (1 if k % 2 else -1)
            spot = edge.interpolate((start + offset) % edge.length)
            if spot.distance(centre) <= robot.reach and clear_of_things(spot):
                return Landing(float(spot.x), float(spot.y), item.size.z, item.id)
    solid = unary_union([o.shape for o in model.obstacles] + list(model.keep_out_shapes.values()))
    body = footprint(base.x, base.y, base.yaw, robot.base_size.x, robot.base_size.y)
    c, s = math.cos(base.yaw), math.sin(base.yaw)
    for gap in (FLOOR_GAP, 2 * FLOOR_GAP, 4 * FLOOR_GAP):
        back, side = robot.base_size.x / 2 + gap + radius, robot.base_size.y / 2 + gap + radius
        for ahead, left in ((-back, 0.0), (0.0, side), (0.0, -side), (back, 0.0)):
            spot = Point(base.x + c * ahead - s * left, base.y + s * ahead + c * left)
            area = spot.buffer(radius)
            if model.room_of(spot.x, spot.y) is None or area.intersects(solid) or area.intersects(body):
                continue
            if any(p.distance(spot) < HUMAN_RADIUS + radius for p in people_at) or not clear_of_things(spot):
                continue
            return Landing(float(spot.x), float(spot.y), 0.0, None)
    return None


def _quiet(report: IncidentReport) -> None:
    log.info("incident (not published): %s", report.reason)


@dataclass
class _Slip:
    """An armed slip: for `object_id`'s next carry, or (None) whatever the gripper carries next."""

    object_id: str | None
    carrying: str | None = None
    driven: float = 0.0
    last: tuple[float, float] = (0.0, 0.0)


@dataclass
class _Fall:
    drop: Drop
    name: str
    why: str


class Faults:
    """The faults in force in one SimWorld, and its reports of what only the sim feels.

    `inject` (on the sim thread) answers sim/fault; `tick` after every physics step makes an armed
    slip happen and checks, every CHECK_PERIOD, for contacts and a grip lost; `report` gets each
    IncidentReport (the sim node publishes them on safety/incidents/report)."""

    def __init__(self, world: SimWorld, report: Callable[[IncidentReport], None] = _quiet) -> None:
        self.world = world
        self.report = report
        self.model = world.model
        self.doors = doorways(world.spec)
        self.slip: _Slip | None = None
        self.hidden: dict[str, tuple[float, float, float]] = {}  # object id -> where it stood (x, y, bottom)
        self._hides = 0  # since the last clear: each hides at a spot of its own, HIDE_STEP further west
        self._falls: list[_Fall] = []
        self._touched: dict[str, float] = {}  # what the robot touched -> sim time it last did
        self._touching: list[str] = []  # what the last check found touched (keys of _touched)
        self._next_check = 0.0
        spec = world.spec
        self._solid = {world.wall_bodies[w.id]: w.name for w in spec.walls}
        self._solid |= {world.furniture_bodies[f.id]: f.name for f in spec.furniture}

    # sim/fault

    def inject(self, request: InjectFault) -> FaultReply:
        """Do what `request` asks, or say why not (nothing changes then)."""
        try:
            match request.kind:
                case FaultKind.SLIP:
                    return self._arm_slip(request.target)
                case FaultKind.BLOCK:
                    return self._block(request.target)
                case FaultKind.HIDE:
                    return self._hide(request.target)
                case FaultKind.CLEAR:
                    return self._clear(request.target)
        except _Refused as refused:
            return refused.error
        raise AssertionError(request.kind)  # pragma: no cover - every kind is matched above

    def _arm_slip(self, target: str) -> FaultInjected:
        if target and target not in self.model.objects:
            raise _Refused.unknown_object(self.world, target)
        if self.slip is not None:
            raise _Refused(ErrorKind.PRECONDITION, "a slip is already armed; `clear` it first")
        holding = self.world.holding
        self.slip = _Slip(target or None)
        what = self.model.objects[target].name if target else None
        if what is None:
            what = f"the {self.model.objects[holding].name} held now" if holding else "the next object picked"
        message = (
            f"{what} will slip out of the gripper once the base has driven {SLIP_DISTANCE:g} m carrying it; "
            "it lands on a top within the arm's reach, else on the floor beside the base"
        )
        log.info("fault: %s", message)
        return FaultInjected(kind=FaultKind.SLIP, target=target, message=message)

    def _block(self, target: str) -> FaultInjected:
        if not target:
            raise _Refused(ErrorKind.INVALID_REQUEST, "block needs a room or doorway id", self._block_targets())
        block = block_for(self.model, self.doors, target)
        if isinstance(block, ServiceError):
            raise _Refused(block.kind, block.message, block.candidates)
        if block.id in self.world.blocks:
            raise _Refused(ErrorKind.PRECONDITION, f"{block.id} is blocked already")
        shape = self.world.box_shape(block.half)
        part = self.world.robot_part_in(shape, block.centre, block.yaw)
        if part is not None:
            raise _Refused(ErrorKind.PRECONDITION, f"{self.world.robot_part_said(part)} where {block.name} would go")
        # People have no collision body: a box put up over one would stand inside them, unnoticed.
        person = self.world.person_in(shape, block.centre, block.yaw)
        if person is not None:
            raise _Refused(ErrorKind.PRECONDITION, f"{person} stands where {block.name} would go")
        # Bullet throws out what a static box goes up around: a cup under one sank through the floor.
        thing = self.world.object_in(shape, block.centre, block.yaw)
        if thing is not None:
            raise _Refused(
                ErrorKind.PRECONDITION, f"{thing} lies where {block.name} would go; move it (sim/move) first"
            )
        self.world.add_block(block)
        x, y, z = block.centre
        message = f"{block.name} at ({x:.2f}, {y:.2f}) blocks the way until `clear`"
        log.info("fault: %s", message)
        return FaultInjected(kind=FaultKind.BLOCK, target=block.id, message=message, position=Vec3(x=x, y=y, z=z))

    def _block_targets(self) -> list[str]:
        return [r.id for r in self.world.spec.rooms] + sorted(self.doors)

    def _hide(self, target: str) -> FaultInjected:
        if target not in self.model.objects:
            raise _Refused.unknown_object(self.world, target)
        obj = self.model.objects[target]
        if target == self.world.holding:
            raise _Refused(ErrorKind.PRECONDITION, f"{target} is in the robot's gripper; it cannot be hidden there")
        if target in self.hidden:
            raise _Refused(ErrorKind.PRECONDITION, f"{target} is hidden already")
        was = self.world.object_position(target)
        self.hidden[target] = (was.x, was.y, was.z - obj.size.z / 2)
        x, y = HIDE_AT[0] - HIDE_STEP * self._hides, HIDE_AT[1]
        self._hides += 1
        self._forget_falls(target)
        self.world.set_down(target, x, y, 0.0)
        message = (
            f"the {obj.name} was taken from ({was.x:.2f}, {was.y:.2f}) to ({x:.2f}, {y:.2f}), outside the house "
            "where no camera pose sees it, until `clear` puts it back"
        )
        log.info("fault: %s", message)
        return FaultInjected(kind=FaultKind.HIDE, target=target, message=message, position=was)

    def _clear(self, target: str) -> FaultInjected:
        if target:
            raise _Refused(ErrorKind.INVALID_REQUEST, f"clear takes no target (got {target!r}): it clears everything")
        # Checked before anything changes: clear does all of it, or nothing.
        going_back: list[tuple[str, int, Position]] = []  # each hidden object checked: name, shape, centre
        for object_id, (x, y, bottom) in self.hidden.items():
            obj = self.model.objects[object_id]
            centre = (x, y, bottom + obj.size.z / 2 + DROP_HEIGHT)
            shape = self.world.object_shapes[object_id]
            part = self.world.robot_part_in(shape, centre)
            if part is not None:
                raise _Refused(
                    ErrorKind.PRECONDITION,
                    f"{self.world.robot_part_said(part)} where the {obj.name} would be put back, "
                    f"at ({x:.2f}, {y:.2f}); "
                    "move the robot, or the object elsewhere (sim/move), first",
                )
            thing = self.world.object_in(shape, centre, moving=object_id)
            for name, other, at in going_back:
                # Two hidden from one spot (one moved there while the other was away) go back into each other.
                if thing is None and self.world.touch(other, at, shape, centre):
                    thing = f"the {name}, hidden too,"
            if thing is not None:
                raise _Refused(
                    ErrorKind.PRECONDITION,
                    f"{thing} stands where the {obj.name} would be put back, at ({x:.2f}, {y:.2f}); "
                    "move it elsewhere (sim/move) first",
                )
            going_back.append((obj.name, shape, centre))
        done = []
        if self.slip is not None:
            self.slip = None
            done.append("the armed slip")
        for block_id in list(self.world.blocks):
            done.append(self.world.blocks[block_id][0].name)
            self.world.remove_block(block_id)
        for object_id, (x, y, bottom) in self.hidden.items():
            self.world.set_down(object_id, x, y, bottom)
            done.append(f"the {self.model.objects[object_id].name} put back at ({x:.2f}, {y:.2f})")
        self.hidden.clear()
        self._hides = 0
        message = "cleared " + "; ".join(done) if done else "no fault was in force"
        log.info("fault: %s", message)
        return FaultInjected(kind=FaultKind.CLEAR, message=message)

    def moved(self, entity_id: str) -> None:
        """sim/move put it somewhere: hidden no more (`clear` leaves it there, `hide` takes it again),
        and no fall of it is to be reported."""
        self.hidden.pop(entity_id, None)
        self._forget_falls(entity_id)

    def _forget_falls(self, object_id: str) -> None:
        self._falls = [f for f in self._falls if f.drop.object_id != object_id]

    # After every physics step

    @property
    def idle(self) -> bool:
        """No object falling that an incident is still to be reported for."""
        return not self._falls

    def tick(self) -> None:
        world = self.world
        for fall in [f for f in self._falls if not f.drop.running]:
            self._falls.remove(fall)
            p = world.object_position(fall.drop.object_id)
            where = self.model.furniture[s].name if (s := self._support(fall.drop.object_id)) else "floor"
            reason = f"the {fall.name} {fall.why} and landed on the {where} at ({p.x:.2f}, {p.y:.2f})"
            self._send(IncidentReport(kind=IncidentKind.DROPPED, reason=reason, objects=[fall.name], x=p.x, y=p.y))
        if world.sim_time < self._next_check:
            return
        self._next_check = world.sim_time + CHECK_PERIOD
        self._check_grip()
        self._check_slip()
        self._check_contacts()

    def rest_tick(self) -> None:
        """`tick` for a world at rest (Simulation.step: physics not stepped, nothing moved, nothing
        falling): what the checks would find is what the last one found, so nothing is asked of
        pybullet, and a contact that lasts through the rest is still the same episode after it. At
        twenty times real time (400 checks a wall second) they were about a sixth of an idle sim's CPU."""
        now = self.world.sim_time
        if now < self._next_check:
            return
        self._next_check = now + CHECK_PERIOD
        for name in self._touching:
            self._touched[name] = now

    def _send(self, report: IncidentReport) -> None:
        # On the sim thread: a report that cannot go out must not stop physics.
        try:
            self.report(report)
        except Exception:
            log.exception("incident report not sent: %s", report.reason)

    def _support(self, object_id: str) -> str | None:
        obj = self.model.objects[object_id]
        return self.model.support_under(self.world.object_position(object_id), obj.size.z / 2)

    def _check_grip(self) -> None:
        held = self.world.holding
        if held is None:
            return
        p = self.world.object_position(held)
        if math.dist((p.x, p.y, p.z), self.world.hand_position()) > GRIP_LOST:
            self.world.release()
            name = self.model.objects[held].name
            self._falls.append(_Fall(self.world.settle(held), name, "fell out of the gripper"))
            log.warning("%s left the gripper", held)

    def _check_slip(self) -> None:
        slip, held = self.slip, self.world.holding
        if slip is None:
            return
        if held is None or slip.object_id not in (None, held):
            slip.carrying = None
            return
        pose = self.world.robot.base_pose()
        if slip.carrying != held:
            slip.carrying, slip.driven, slip.last = held, 0.0, (pose.x, pose.y)
            return
        slip.driven += math.dist(slip.last, (pose.x, pose.y))
        slip.last = (pose.x, pose.y)
        if slip.driven >= SLIP_DISTANCE:
            self._slip_now(held, pose)

    def _slip_now(self, held: str, base: Pose2D) -> None:
        world, obj = self.world, self.model.objects[held]
        others = []
        for other in world.spec.objects:
            if other.id != held and other.id not in self.hidden:
                p = world.object_position(other.id)
                others.append((p.x, p.y, max(other.size.x, other.size.y) / 2))
        blocks = [block_outline(b) for b, _ in world.blocks.values()]
        people = [(h.x, h.y) for h in world.human_poses.values()]
        spot = landing_spot(self.model, base, max(obj.size.x, obj.size.y) / 2, others, blocks, people)
        world.release()
        self.slip = None
        # Nowhere free: it falls from where it is (onto the base, likely).
        drop = world.settle(held) if spot is None else world.set_down(held, spot.x, spot.y, spot.bottom)
        self._falls.append(_Fall(drop, obj.name, "slipped out of the gripper during a carry (an injected fault)"))
        log.info("fault: %s slipped out of the gripper at (%.2f, %.2f)", held, base.x, base.y)

    def _check_contacts(self) -> None:
        world, now = self.world, self.world.sim_time
        robot = world.robot
        blocks = {body: block.name for block, body in world.blocks.values()}
        things: dict[str, str] = {}  # what was touched -> by which part
        for point in world.bullet.getContactPoints(bodyA=robot.id):
            name = self._solid.get(point[2]) or blocks.get(point[2])
            if name is not None:
                things.setdefault(name, "base" if point[3] == robot.base_link else "arm")
        base, size = robot.base_pose(), world.spec.robot.base_size
        people = [
            world.spec.humans[i].name
            for i, pose in enumerate(world.human_poses.values())
            if distance_to_footprint(base.x, base.y, base.yaw, size.x, size.y, (pose.x, pose.y)) < HUMAN_RADIUS
        ]
        new_things = [t for t in things if now - self._touched.get(t, -math.inf) > CONTACT_GAP]
        new_people = [p for p in people if now - self._touched.get(f"person:{p}", -math.inf) > CONTACT_GAP]
        self._touching = [*things, *(f"person:{name}" for name in people)]
        for name in self._touching:
            self._touched[name] = now
        if not new_things and not new_people:
            return
        parts = [f"the robot's {things[t]} touched {_the(t)}" for t in new_things]
        parts += [f"the robot's base touched {p}" for p in new_people]
        reason = "; ".join(parts)
        log.warning("collision: %s", reason)
        self._send(
            IncidentReport(kind=IncidentKind.COLLISION, reason=reason, objects=new_things[:16], people=new_people[:16])
        )


def _the(name: str) -> str:
    """'the kitchen counter', 'a box in the ...' as it is."""
    return name if name.startswith(("a ", "an ", "the ")) else f"the {name}"


class _Refused(Exception):
    def __init__(self, kind: ErrorKind, message: str, candidates: list[str] | None = None) -> None:
        super().__init__(message)
        self.error = ServiceError(kind=kind, message=message, candidates=candidates or [])

    @classmethod
    def unknown_object(cls, world: SimWorld, target: str) -> _Refused:
        what = f"no object {target!r}" if target else "no object named"
        return cls(ErrorKind.INVALID_REQUEST, f"{what} in the world {world.spec.name!r}", sorted(world.object_bodies))
