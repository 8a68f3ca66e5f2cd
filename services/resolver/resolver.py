"""Plan -> GroundedPlan: every name becomes an id and a pose, from the world model and perception."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass, field

from schemas.common import ErrorKind, Pose2D, Vec3
from schemas.plan import (
    MAX_STEPS,
    Action,
    DetectStep,
    Fallback,
    GripperStep,
    GroundedPlan,
    GroundedStep,
    NavigateStep,
    PickStep,
    PlaceStep,
    Plan,
    ResolveReply,
    SayStep,
    Step,
    StopStep,
    WaitStep,
)
from schemas.world import PerceivedHumans, PerceivedObjects
from services.resolver.errors import ResolveError
from services.resolver.names import KIND_NOUNS, Entity, Kind, NameIndex
from services.resolver.placement import place_position
from services.worldmodel import PRE_GOAL_MIN_LEG, WorldModel, approach_towards

GRIPPER = "gripper"
FLOOR = "floor"
MAX_WAIT = 60.0
# Bounds of the relative moves, as the parser's vocabulary states them.
MAX_DRIVE = 5.0
MAX_TURN = math.tau + 1e-3
# NavigateStep.max_speed's bound.
MAX_NAVIGATE_SPEED = 5.0
# The base turns to a goal's yaw the short way round, so a longer turn is split into goals at most
# this far apart: "270 degrees left" then really turns left.
MAX_TURN_PER_GOAL = math.tau / 3
# Two poses closer than these are the same place.
SAME_POSITION = 1e-3
SAME_YAW = 1e-3
ECHO_CHARS = 60
# Steps whose grounding drives the base (pick and place drive to their approach pose first).
MOVES_BASE = (NavigateStep, PickStep, PlaceStep)


def _echo(name: str) -> str:
    return repr(name if len(name) <= ECHO_CHARS else name[:ECHO_CHARS] + "...")


def _wrap(angle: float) -> float:
    return math.atan2(math.sin(angle), math.cos(angle))


@dataclass
class _Belief:
    """Where an object is thought to be as the plan unfolds: perceived, or from the world file."""

    position: Vec3
    on: str | None  # a furniture id, GRIPPER, or None for the floor
    half_height: float = 0.0


class _Unknown:
    """The gripper's content when nothing has been perceived yet."""


UNKNOWN = _Unknown()


@dataclass
class _State:
    """What the resolver predicts as the plan unfolds: where things are, what the gripper holds,
    where the base stands. `robot` is None when that is not known; `pose_note` then says why, if
    it is not simply missing odometry."""

    beliefs: dict[str, _Belief]
    holding: str | _Unknown | None
    robot: Pose2D | None
    pose_note: str | None = None

    def copy(self) -> _State:
        beliefs = {k: dataclasses.replace(b) for k, b in self.beliefs.items()}
        return _State(beliefs, self.holding, self.robot, self.pose_note)


@dataclass(frozen=True)
class _At:
    """Where a step sits in the parsed plan: its top-level step (0-based) and its label ("3.1")."""

    index: int
    label: str

    def error(
        self, message: str, kind: ErrorKind = ErrorKind.INVALID_REQUEST, candidates: Iterable[str] = ()
    ) -> ResolveError:
        # Top-level steps keep Refusal's "step N" prefix; nested ones are named by their label.
        where = None if self.label == str(self.index + 1) else f"step {self.label}"
        return ResolveError(message, kind=kind, step=self.index, where=where, candidates=candidates)


@dataclass
class _Grounded:
    steps: list[GroundedStep] = field(default_factory=list)
    labels: list[str] = field(default_factory=list)
    fallbacks: list[Fallback] = field(default_factory=list)


class Resolver:
    """Grounds plans against one world. Pure: no transport, no clock, safe to share across threads."""

    def __init__(
        self,
        world_model: WorldModel,
        *,
        place_inset: float = 0.15,
        place_clearance: float = 0.15,
        human_standoff: float = 0.8,
        object_standoff: float = 0.6,
    ) -> None:
        self.model = world_model
        self.world = world_model.world
        self.names = NameIndex(self.world)
        self.place_inset = place_inset
        self.place_clearance = place_clearance
        self.human_standoff = human_standoff
        self.object_standoff = object_standoff
        self._places = {p.id: p for p in self.world.places}
        self._humans = {h.id: h for h in self.world.humans}

    def resolve(
        self,
        plan: Plan,
        objects: PerceivedObjects | None = None,
        robot: Pose2D | None = None,
        *,
        humans: PerceivedHumans | None = None,
    ) -> GroundedPlan:
        """The grounded plan, or ResolveError naming the step: `step` is the 0-based top-level step,
        the message says "step N" (1-based) or, for a sub-step or an alternative, its label."""
        state = self._initial_state(objects, robot)
        human_poses = {h.id: h.pose for h in self.world.humans}
        if humans is not None:
            human_poses.update({h.id: h.pose for h in humans.humans})
        out = _Grounded()
        self._ground_steps(plan.steps, "", None, state, out, human_poses, in_alternative=False)
        too_long = [len(out.steps), *(len(f.steps) for f in out.fallbacks)]
        if max(too_long) > MAX_STEPS:
            raise ResolveError(
                f"the plan needs {max(too_long)} robot steps in a row (long turns and backward drives take "
                f"more than one); the limit is {MAX_STEPS}: split it into several plans"
            )
        return GroundedPlan(steps=out.steps, source=plan, labels=out.labels, fallbacks=out.fallbacks)

    def _initial_state(self, objects: PerceivedObjects | None, robot: Pose2D | None) -> _State:
        beliefs = {o.id: _Belief(self.model.initial_position(o), o.support, o.size.z / 2) for o in self.world.objects}
        holding: str | _Unknown | None = UNKNOWN
        if objects is not None:
            holding = None
            for seen in objects.objects:
                known = beliefs.get(seen.id)
                beliefs[seen.id] = _Belief(seen.position, seen.on, known.half_height if known else 0.0)
                if seen.on == GRIPPER:
                    holding = seen.id
        return _State(beliefs, holding, robot)

    # Groups, sub-steps and alternatives

    def _ground_steps(
        self,
        steps: list[Step],
        prefix: str,
        top: int | None,
        state: _State,
        out: _Grounded,
        humans: dict[str, Pose2D],
        *,
        in_alternative: bool,
    ) -> None:
        """Flatten `steps` into `out` in the order they run, labelled `prefix` + 1-based position."""
        for position, step in enumerate(steps):
            at = _At(position if top is None else top, f"{prefix}{position + 1}")
            self._ground_step(at, step, state, out, humans, in_alternative=in_alternative)

    def _ground_step(
        self, at: _At, step: Step, state: _State, out: _Grounded, humans: dict[str, Pose2D], *, in_alternative: bool
    ) -> None:
        if step.on_failure and in_alternative:
            raise at.error(
                "an on_failure inside an on_failure alternative cannot be run (alternatives do not nest); "
                "move it out to a step of the plan, or drop it"
            )
        first = len(out.steps)
        before = state.copy() if step.on_failure else None
        if step.action is None:
            if not step.substeps:
                raise at.error("the step has neither an action nor sub-steps")
            self._ground_steps(
                step.substeps, f"{at.label}.", at.index, state, out, humans, in_alternative=in_alternative
            )
        else:
            if step.substeps:
                raise at.error(f"{step.action} cannot also have sub-steps: put the action in the group as a sub-step")
            for grounded in self._step(at, step, state, humans):
                out.steps.append(grounded)
                out.labels.append(at.label)
        if before is not None:
            self._alternatives(at, step, before, first, state, out, humans)

    def _alternatives(
        self,
        at: _At,
        step: Step,
        before: _State,
        first: int,
        state: _State,
        out: _Grounded,
        humans: dict[str, Pose2D],
    ) -> None:
        """Ground `step.on_failure` as a Fallback over the grounded steps from `first` on.

        The alternatives are grounded from the state predicted at the start of that range. When the
        range drives the base, where it stands when a step fails is not known in advance, so moves
        relative to the base (drive, turn, look_at) are refused there until an absolute one."""
        last = len(out.steps) - 1
        if any(isinstance(s, MOVES_BASE) for s in out.steps[first:]):
            before.robot = None
            before.pose_note = f"where the robot stands when step {at.label} fails is not known in advance"
        alternative = _Grounded()
        self._ground_steps(
            step.on_failure, f"{at.label} on_failure ", at.index, before, alternative, humans, in_alternative=True
        )
        out.fallbacks.append(Fallback(first=first, last=last, steps=alternative.steps, labels=alternative.labels))
        # The plan goes on from the step's own outcome; objects are followed along that path (the
        # executor checks the gripper through perception), but the base's pose must agree.
        if not _same_pose(state.robot, before.robot):
            state.robot = None
            state.pose_note = f"where the robot stands after step {at.label} depends on whether its on_failure ran"

    # One step

    def _step(self, at: _At, step: Step, state: _State, humans: dict[str, Pose2D]) -> list[GroundedStep]:
        match step.action:
            case Action.NAVIGATE_TO:
                return [self._navigate(at, step, state, humans)]
            case Action.PICK:
                return [self._pick(at, step, state)]
            case Action.PLACE:
                return [self._place(at, step, state)]
            case Action.DETECT:
                target = self._required(at, step.target, "detect needs a target: which object")
                entity = self._entity(at, target, ("object", "human"), hint=step.location)
                self._expect_kind(at, "detect", target, entity, ("object", "human"))
                return [DetectStep(object_id=entity.id, object_name=entity.name)]
            case Action.LOOK_AT:
                return [self._look_at(at, step, state, humans)]
            case Action.DRIVE:
                return self._drive(at, step, state)
            case Action.TURN:
                return self._turn(at, step, state)
            case Action.SAY:
                text = step.params.get("text", step.target)
                if not isinstance(text, str) or not text.strip():
                    raise at.error("say needs the words to speak (parameter 'text')")
                return [SayStep(text=text)]
            case Action.WAIT:
                duration = self._number(at, step, "duration", "s")
                if duration is None:
                    raise at.error("wait needs a 'duration' in seconds")
                if not 0.0 <= duration <= MAX_WAIT:
                    raise at.error(f"wait duration {duration:g} s is outside 0..{MAX_WAIT:g} s")
                return [WaitStep(duration=duration)]
            case Action.STOP:
                return [StopStep()]
            case Action.OPEN_GRIPPER | Action.CLOSE_GRIPPER:
                return [self._gripper(step.action is Action.OPEN_GRIPPER, state)]
            case Action.GESTURE:
                raise at.error(
                    "gesture: this robot cannot gesture yet (it has no gestures); remove the step, "
                    "or use 'say' to greet or acknowledge"
                )
            case Action.MOVE_ARM:
                raise at.error(
                    "move_arm: this robot cannot move its arm on its own yet (the arm moves only within pick "
                    "and place, and stows itself after each); remove the step, or use pick and place"
                )
        raise at.error(f"action {step.action!r} has no grounding")  # pragma: no cover

    # Names

    def _required(self, at: _At, name: str | None, message: str) -> str:
        if name is None or not name.strip():
            raise at.error(message)
        return name

    def _entity(self, at: _At, name: str, prefer: tuple[Kind, ...] = (), *, hint: str | None = None) -> Entity:
        """The one thing `name` means; kinds in `prefer` win a tie, then the support named by `hint`."""
        found = self.names.lookup(name)
        if not found:
            suggestions = self.names.suggestions(name)
            if suggestions:
                listed = " or ".join(f"'{s}'" for s in suggestions)
                detail = f" (did you mean {listed}?)"
            else:
                detail = f": no room, furniture, place, object or person in world '{self.world.name}' has that name"
            raise at.error(f"unknown name {_echo(name)}{detail}", ErrorKind.UNKNOWN_NAME, suggestions)
        if len(found) > 1 and prefer:
            found = [e for e in found if e.kind in prefer] or found
        if len(found) > 1 and hint:
            supports = {e.id for e in self.names.lookup(hint) if e.kind == "furniture"}
            on_hint = [e for e in found if e.kind == "object" and self._support_of(e.id) in supports]
            found = on_hint or found
        if len(found) > 1:
            names = [e.name for e in found]
            raise at.error(
                f"{_echo(name)} is ambiguous: it could be {', '.join(names[:-1])} or {names[-1]}; name one of them",
                ErrorKind.AMBIGUOUS_NAME,
                names,
            )
        return found[0]

    def _support_of(self, object_id: str) -> str | None:
        obj = self.model.objects.get(object_id)
        return obj.support if obj else None

    def _expect_kind(self, at: _At, verb: str, name: str, entity: Entity, kinds: tuple[Kind, ...]) -> None:
        if entity.kind not in kinds:
            wanted = " or ".join(KIND_NOUNS[k] for k in kinds)
            raise at.error(f"cannot {verb} {_echo(name)}: {entity.name} is {KIND_NOUNS[entity.kind]}, not {wanted}")

    # Numbers

    def _number(self, at: _At, step: Step, name: str, unit: str) -> float | None:
        """A finite number parameter in `unit` (SI), or None when the step does not give it."""
        value = step.params.get(name)
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise at.error(f"{step.action} {name} must be a number in {unit}, not {_echo(str(value))}")
        given = step.units.get(name)
        if given is not None and given != unit:
            raise at.error(f"{step.action} {name} is in {_echo(given)}; it must be in {unit}")
        return float(value)

    def _speed(self, at: _At, step: Step) -> float | None:
        speed = self._number(at, step, "speed", "m/s")
        if speed is not None and not 0.0 < speed <= MAX_NAVIGATE_SPEED:
            raise at.error(f"{step.action} speed {speed:g} m/s is outside (0, {MAX_NAVIGATE_SPEED:g}] m/s")
        return speed

    # Steps

    def _navigate(self, at: _At, step: Step, state: _State, humans: dict[str, Pose2D]) -> NavigateStep:
        name = self._required(at, step.target or step.location, "navigate_to needs a target: where to go")
        entity = self._entity(at, name)
        speed = self._speed(at, step)
        goal: Pose2D
        if entity.kind == "room":
            goal = self.model.room_pose(entity.id)
        elif entity.kind == "furniture":
            goal = self.model.furniture[entity.id].approach
        elif entity.kind == "place":
            goal = self._places[entity.id].pose
        elif entity.kind == "human":
            goal = self._towards_human(humans[entity.id], state.robot)
        else:
            belief = state.beliefs[entity.id]
            if belief.on == GRIPPER:
                raise at.error(f"cannot go to {entity.name}: it is in the gripper", ErrorKind.PRECONDITION)
            goal = self._object_approach(belief, state.robot)
        goal = _rounded(goal)
        self._moved_to(state, goal)
        return NavigateStep(target=entity.name, goal=goal, max_speed=speed)

    def _moved_to(self, state: _State, pose: Pose2D) -> None:
        state.robot, state.pose_note = pose, None

    def _towards_human(self, human: Pose2D, robot: Pose2D | None) -> Pose2D:
        if robot is not None and math.dist((robot.x, robot.y), (human.x, human.y)) > 1e-6:
            return approach_towards(human.x, human.y, self.human_standoff, robot.x, robot.y)
        # No robot pose: stand in front of the person, where they are facing.
        ahead = (human.x + math.cos(human.yaw), human.y + math.sin(human.yaw))
        return approach_towards(human.x, human.y, self.human_standoff, *ahead)

    def _object_approach(self, belief: _Belief, robot: Pose2D | None) -> Pose2D:
        if belief.on is not None and belief.on in self.model.furniture:
            return self.model.furniture[belief.on].approach
        start = robot or self.world.robot.start
        return approach_towards(belief.position.x, belief.position.y, self.object_standoff, start.x, start.y)

    def _base_pose(self, at: _At, verb: str, state: _State) -> Pose2D:
        """Where the base is predicted to stand now, for a move relative to it."""
        if state.robot is None:
            why = state.pose_note or "the robot's pose is unknown (no odometry from it yet)"
            raise at.error(
                f"{verb} moves relative to where the robot stands, and {why}; navigate_to a named place first",
                ErrorKind.PRECONDITION,
            )
        return state.robot

    def _drive(self, at: _At, step: Step, state: _State) -> list[GroundedStep]:
        distance = self._number(at, step, "distance", "m")
        if distance is None:
            raise at.error("drive needs a 'distance' in metres (negative drives backward)")
        if abs(distance) > MAX_DRIVE:
            raise at.error(f"drive distance {distance:g} m is outside -{MAX_DRIVE:g}..{MAX_DRIVE:g} m")
        speed = self._speed(at, step)
        start = self._base_pose(at, "drive", state)
        goal = _rounded(
            Pose2D(
                x=start.x + distance * math.cos(start.yaw),
                y=start.y + distance * math.sin(start.yaw),
                yaw=start.yaw,
            )
        )
        name = f"{abs(distance):.2f} m {'forward' if distance >= 0 else 'backward'}"
        self._moved_to(state, goal)
        if distance < 0 and -distance > PRE_GOAL_MIN_LEG:
            # The base only drives forward along a leg this long, and parks by driving straight in
            # along the goal's heading (worldmodel.drive_route): with the start's heading it would
            # overshoot the goal and come back. Facing back first keeps it between start and goal.
            facing_back = _rounded(Pose2D(x=goal.x, y=goal.y, yaw=_wrap(start.yaw + math.pi)))
            return [
                NavigateStep(target=f"{name} (turned round)", goal=facing_back, max_speed=speed),
                NavigateStep(target=f"{name} (turning back)", goal=goal),
            ]
        return [NavigateStep(target=name, goal=goal, max_speed=speed)]

    def _turn(self, at: _At, step: Step, state: _State) -> list[GroundedStep]:
        angle = self._number(at, step, "angle", "rad")
        if angle is None:
            raise at.error("turn needs an 'angle' in radians (positive turns left)")
        if abs(angle) > MAX_TURN:
            raise at.error(f"turn angle {angle:g} rad is outside one full turn either way")
        speed = self._number(at, step, "speed", "rad/s")
        limit = self.world.robot.max_angular_speed
        if speed is not None and speed < limit:
            raise at.error(
                f"turn speed {speed:g} rad/s: this robot cannot yet turn slower than its own limit of "
                f"{limit:g} rad/s; remove 'speed'"
            )
        start = self._base_pose(at, "turn", state)
        name = f"{math.degrees(abs(angle)):.0f}° {'left' if angle >= 0 else 'right'}"
        parts = max(1, math.ceil(abs(angle) / MAX_TURN_PER_GOAL - 1e-9))
        steps: list[GroundedStep] = []
        for part in range(1, parts + 1):
            goal = _rounded(Pose2D(x=start.x, y=start.y, yaw=_wrap(start.yaw + angle * part / parts)))
            target = name if parts == 1 else f"{name} ({part}/{parts})"
            steps.append(NavigateStep(target=target, goal=goal))
            self._moved_to(state, goal)
        return steps

    def _look_at(self, at: _At, step: Step, state: _State, humans: dict[str, Pose2D]) -> NavigateStep:
        name = self._required(at, step.target or step.location, "look_at needs a target: what to face")
        entity = self._entity(at, name, ("human", "object"), hint=step.location if step.target else None)
        x: float
        y: float
        if entity.kind == "human":
            x, y = humans[entity.id].x, humans[entity.id].y
        elif entity.kind == "object":
            belief = state.beliefs[entity.id]
            if belief.on == GRIPPER:
                raise at.error(f"cannot look at {entity.name}: it is in the gripper", ErrorKind.PRECONDITION)
            x, y = belief.position.x, belief.position.y
        elif entity.kind == "furniture":
            x, y = self.model.furniture[entity.id].center
        elif entity.kind == "place":
            x, y = self._places[entity.id].pose.x, self._places[entity.id].pose.y
        else:
            room = self.model.room_pose(entity.id)
            x, y = room.x, room.y
        start = self._base_pose(at, "look_at", state)
        yaw = start.yaw if math.hypot(x - start.x, y - start.y) < 1e-6 else math.atan2(y - start.y, x - start.x)
        goal = _rounded(Pose2D(x=start.x, y=start.y, yaw=yaw))
        self._moved_to(state, goal)
        return NavigateStep(target=f"facing {entity.name}", goal=goal)

    def _gripper(self, open_: bool, state: _State) -> GripperStep:
        if open_:
            held = state.holding
            if isinstance(held, str) and held in state.beliefs:
                # It falls; the resolver only needs to know it is no longer on anything.
                belief = state.beliefs[held]
                x, y = (state.robot.x, state.robot.y) if state.robot else (belief.position.x, belief.position.y)
                state.beliefs[held] = _Belief(Vec3(x=x, y=y, z=belief.half_height), None, belief.half_height)
            state.holding = None
        # Closing on nothing holds nothing; closing on what is held keeps holding it.
        return GripperStep(open=open_)

    def _pick(self, at: _At, step: Step, state: _State) -> PickStep:
        name = self._required(at, step.target, "pick needs a target: which object")
        entity = self._entity(at, name, ("object",), hint=step.location)
        self._expect_kind(at, "pick", name, entity, ("object",))
        if state.holding == entity.id:
            raise at.error(f"cannot pick {entity.name}: it is already in the gripper", ErrorKind.PRECONDITION)
        if isinstance(state.holding, str):
            held = self._display_name(state.holding)
            raise at.error(
                f"cannot pick {entity.name}: the gripper already holds {held}; place it first",
                ErrorKind.PRECONDITION,
            )
        obj = self.model.objects[entity.id]
        belief = state.beliefs[entity.id]
        support = belief.on if belief.on is not None and belief.on in self.model.furniture else FLOOR
        approach = _rounded(self._object_approach(belief, state.robot))
        pick = PickStep(
            object_id=entity.id,
            object_name=entity.name,
            position=_vec(belief.position),
            mass=obj.mass,  # from the world file: a plan never says how heavy something is
            support_id=support,
            approach=approach,
        )
        state.holding = entity.id
        belief.on = GRIPPER
        self._moved_to(state, approach)
        return pick

    def _place(self, at: _At, step: Step, state: _State) -> PlaceStep:
        name = self._required(
            at, step.location, "place needs a location: the furniture to put the object on (none given)"
        )
        entity = self._entity(at, name, ("furniture",))
        self._expect_kind(at, "place on", name, entity, ("furniture",))
        held = state.holding
        if step.target is not None:
            obj = self._entity(at, step.target, ("object",))
            self._expect_kind(at, "place", step.target, obj, ("object",))
            if held is None:
                raise at.error(f"cannot place {obj.name}: the gripper holds nothing", ErrorKind.PRECONDITION)
            if isinstance(held, str) and held != obj.id:
                raise at.error(
                    f"cannot place {obj.name}: the gripper holds {self._display_name(held)}", ErrorKind.PRECONDITION
                )
            held = obj.id
        if held is None:
            raise at.error(f"cannot place on {entity.name}: the gripper holds nothing", ErrorKind.PRECONDITION)
        surface = self.model.furniture[entity.id]
        occupied = [
            (b.position.x, b.position.y) for oid, b in state.beliefs.items() if b.on == entity.id and oid != held
        ]
        position = place_position(surface, occupied, inset=self.place_inset, clearance=self.place_clearance)
        if position is None:
            raise at.error(
                f"no free spot on {entity.name}: every spot near its edge is within "
                f"{self.place_clearance:g} m of another object",
                ErrorKind.PRECONDITION,
            )
        if isinstance(held, str):
            belief = state.beliefs.get(held)
            half = belief.half_height if belief else 0.0
            state.beliefs[held] = _Belief(Vec3(x=position.x, y=position.y, z=position.z + half), entity.id, half)
        state.holding = None
        self._moved_to(state, surface.approach)
        return PlaceStep(surface_id=entity.id, surface_name=entity.name, position=position, approach=surface.approach)

    def _display_name(self, object_id: str) -> str:
        obj = self.model.objects.get(object_id)
        return obj.name if obj else object_id


def _same_pose(a: Pose2D | None, b: Pose2D | None) -> bool:
    if a is None or b is None:
        return a is b
    return math.dist((a.x, a.y), (b.x, b.y)) <= SAME_POSITION and abs(_wrap(a.yaw - b.yaw)) <= SAME_YAW


def _vec(v: Vec3) -> Vec3:
    return Vec3(x=round(v.x, 4), y=round(v.y, 4), z=round(v.z, 4))


def _rounded(pose: Pose2D) -> Pose2D:
    return Pose2D(x=round(pose.x, 4), y=round(pose.y, 4), yaw=round(pose.yaw, 4))


def answer(
    resolver: Resolver,
    plan: Plan,
    objects: PerceivedObjects | None = None,
    robot: Pose2D | None = None,
    humans: PerceivedHumans | None = None,
) -> ResolveReply:
    """What plan/resolve replies: the GroundedPlan, or the refusal as a value. Never raises ResolveError."""
    try:
        return resolver.resolve(plan, objects, robot, humans=humans)
    except ResolveError as exc:
        return exc.error
