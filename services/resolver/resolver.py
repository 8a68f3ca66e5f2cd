"""Plan -> GroundedPlan: every name becomes an id and a pose, from the world model and perception."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import assert_never, get_args

import msgspec
from shapely.geometry import Point
from shapely.ops import unary_union

from schemas.common import ErrorKind, Pose2D, Vec3
from schemas.plan import (
    MAX_STEPS,
    Action,
    Coordinates,
    DetectStep,
    Fallback,
    GripperStep,
    GroundedPlan,
    GroundedStep,
    NavigateStep,
    PickStep,
    PlaceStep,
    Plan,
    Resolution,
    ResolveReply,
    SayStep,
    SearchScope,
    Step,
    StopStep,
    WaitStep,
)
from schemas.world import Furniture, PerceivedHumans, PerceivedObjects, SceneDescription
from services.footprint import TRACKING_TOLERANCE, footprint
from services.resolver.config import ResolverConfig
from services.resolver.errors import ResolveError
from services.resolver.match import Matcher, NoMatch
from services.resolver.memory import Origin
from services.resolver.names import KIND_NOUNS, Entity, Kind, NameIndex, normalise_name
from services.resolver.placement import place_position
from services.resolver.reference import parse_reference
from services.resolver.scene import GRIPPER, Belief, Scene, describe_scene, perceived, scene_graph
from services.worldmodel import PRE_GOAL_MIN_LEG, WorldModel, approach_towards

FLOOR = "floor"
MAX_WAIT = 60.0
# Bounds of the relative moves, as the parser's vocabulary states them.
MAX_DRIVE = 5.0
# Sides round an object on the floor the base may approach it from (every 15 degrees), the robot's first.
APPROACH_SIDES = 24
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
# Parameters the vocabulary takes (a model writes them) that nothing carries out, and why: a plan
# giving one is told so in its warnings, not left to think the robot did it.
UNUSED_PARAMS = {
    (Action.PICK, "approach"): "the executor chooses the grasp",
    (Action.PLACE, "approach"): "the executor chooses how the hand comes down",
    (Action.OPEN_GRIPPER, "width"): "the gripper opens fully",
    (Action.CLOSE_GRIPPER, "force"): "the gripper closes with its own force",
    (Action.SAY, "volume"): "this robot has no speaker",
}
# A spot a plan gives for place must be this far in from the edge of the top.
PLACE_EDGE_MARGIN = 0.05
# A delivery spot is at least this far (xy) from where the person stands or sits, and the base's
# approach pose at least this plus the base's half-diagonal: never on or into them.
PERSON_CLEARANCE = 0.4
# schemas.common.Name's bound, for names the resolver puts together.
MAX_NAME_CHARS = 200
# Surfaces named when a delivery finds none near enough.
DELIVERY_SUGGESTIONS = 3
# How far outside a piece of furniture's top a sighting said to be on it may be (a camera's estimate
# of an object at the edge) before the report contradicts itself.
ON_MARGIN = 0.15
# How far below the floor, and above the highest furniture top, a sighting may be before it cannot be right.
BELOW_FLOOR = 0.2
MAP_MARGIN = 0.5
ABOVE_TOPS = 1.5


def _echo(name: str) -> str:
    return repr(name if len(name) <= ECHO_CHARS else name[:ECHO_CHARS] + "...")


def _wrap(angle: float) -> float:
    return math.atan2(math.sin(angle), math.cos(angle))


@dataclass(frozen=True)
class _Unknown:
    """The gripper's content when perception does not say it: why not."""

    why: str = "not known yet (no camera frame)"


UNKNOWN = _Unknown()


@dataclass
class _Notes:
    """What the resolution says back besides the steps: warnings, and what each name became."""

    warnings: list[str] = field(default_factory=list)
    resolutions: list[Resolution] = field(default_factory=list)


@dataclass
class _State:
    """What the resolver predicts as the plan unfolds: where things are, what the gripper holds,
    where the base stands, which object "it" is, where each held object was before the gripper took
    it (`origins`: that place and how it is known, for "put it back"). `robot` is None when that is
    not known; `pose_note` then says why, if it is not simply missing odometry. `humans` and `notes`
    are shared by every copy."""

    beliefs: dict[str, Belief]
    holding: str | _Unknown | None
    robot: Pose2D | None
    humans: dict[str, Pose2D]
    notes: _Notes
    pose_note: str | None = None
    last_object: str | None = None
    origins: dict[str, tuple[Origin, str]] = field(default_factory=dict)

    def copy(self) -> _State:
        beliefs = {k: dataclasses.replace(b) for k, b in self.beliefs.items()}
        return dataclasses.replace(self, beliefs=beliefs, origins=dict(self.origins))

    def scene(self, model: WorldModel) -> Scene:
        return Scene(model, self.beliefs, self.robot, self.humans)


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

    def warn(self, state: _State, message: str) -> None:
        state.notes.warnings.append(f"step {self.label}: {message}")


@dataclass
class _Grounded:
    steps: list[GroundedStep] = field(default_factory=list)
    labels: list[str] = field(default_factory=list)
    fallbacks: list[Fallback] = field(default_factory=list)


class Resolver:
    """Grounds plans against one world. Pure: no transport, no clock, safe to share across threads."""

    def __init__(self, world_model: WorldModel, config: ResolverConfig | None = None) -> None:
        self.model = world_model
        self.world = world_model.world
        self.config = config if config is not None else ResolverConfig()
        self.names = NameIndex(self.world)
        self.matcher = Matcher(
            self.names,
            world_model,
            min_confidence=self.config.min_confidence,
            margin=self.config.confidence_margin,
            near=self.config.near_distance,
        )
        self._places = {p.id: p for p in self.world.places}
        base = self.world.robot.base_size
        self._base_radius = math.hypot(base.x / 2, base.y / 2)
        self._put_back = frozenset(normalise_name(p) for p in self.config.put_back_phrases) - {""}
        # Where a sighting can be: over the map (give or take MAP_MARGIN), between the floor and above the tops.
        self._map = unary_union(list(world_model.room_shapes.values())).buffer(MAP_MARGIN)
        self._highest = max((f.size.z for f in self.world.furniture), default=0.0) + ABOVE_TOPS
        # Where a sighting said to be on each piece of furniture may be: its top and ON_MARGIN round it.
        self._near_tops = {f.id: world_model.footprint(f).buffer(ON_MARGIN) for f in self.world.furniture}

    def resolve(
        self,
        plan: Plan,
        objects: PerceivedObjects | None = None,
        robot: Pose2D | None = None,
        *,
        humans: PerceivedHumans | None = None,
        origins: Mapping[str, Origin] | None = None,
    ) -> GroundedPlan:
        """The grounded plan, or ResolveError naming the step: `step` is the 0-based top-level step,
        the message says "step N" (1-based) or, for a sub-step or an alternative, its label.
        `origins`: where perception last saw each held object before the gripper took it."""
        state = self._initial_state(objects, robot, humans, origins)
        out = _Grounded()
        self._ground_steps(plan.steps, "", None, state, out, in_alternative=False)
        too_long = [len(out.steps), *(len(f.steps) for f in out.fallbacks)]
        if max(too_long) > MAX_STEPS:
            raise ResolveError(
                f"the plan needs {max(too_long)} robot steps in a row (long turns and backward drives take "
                f"more than one); the limit is {MAX_STEPS}: split it into several plans"
            )
        return GroundedPlan(
            steps=out.steps,
            source=plan,
            labels=out.labels,
            fallbacks=out.fallbacks,
            warnings=list(dict.fromkeys(state.notes.warnings)),
            resolutions=state.notes.resolutions,
        )

    def describe(
        self,
        objects: PerceivedObjects | None = None,
        robot: Pose2D | None = None,
        *,
        humans: PerceivedHumans | None = None,
        stamp: float = 0.0,
    ) -> SceneDescription:
        """The scene as plans are resolved in it: objects where last seen (or where the world file
        puts them), the relations between things, and a few sentences for an LLM prompt."""
        scene = self._initial_state(objects, robot, humans).scene(self.model)
        things = self.names.of_kind("object")
        objects_known = self.model.objects
        return SceneDescription(
            stamp=stamp,
            robot=robot,
            robot_room=self.model.room_of(robot.x, robot.y) if robot is not None else None,
            objects=[perceived(e, scene, objects_known[e.id].cls, objects_known[e.id].color) for e in things],
            relations=scene_graph(scene, things, self.names.of_kind("furniture"), self.matcher.near),
            text=describe_scene(
                scene,
                things,
                self.names.of_kind("human"),
                payload=self.world.robot.payload,
                masses={o.id: o.mass for o in self.world.objects},
            ),
        )

    def _initial_state(
        self,
        objects: PerceivedObjects | None,
        robot: Pose2D | None,
        humans: PerceivedHumans | None,
        origins: Mapping[str, Origin] | None = None,
    ) -> _State:
        beliefs = {o.id: Belief(self.model.initial_position(o), o.support, o.size.z / 2) for o in self.world.objects}
        holding: str | _Unknown | None = UNKNOWN
        notes = _Notes()
        if objects is not None:
            held: list[str] = []
            for seen in objects.objects:
                known = beliefs.get(seen.id)
                if known is None:
                    continue  # perception of something the world file does not know: no name to refer to it
                doubt = self._implausible(seen.position)
                if doubt is not None:
                    # Not believed: the object is where the world file (or an earlier belief) puts it.
                    notes.warnings.append(
                        f"the camera's report of {self._display_name(seen.id)} is not believed: {doubt}"
                    )
                    continue
                on = self._support_of(seen.id, seen.position, seen.on, known.half_height, notes)
                beliefs[seen.id] = Belief(seen.position, on, known.half_height, seen.stamp, seen.stale)
                if on == GRIPPER and seen.id not in held:
                    held.append(seen.id)
            holding = held[0] if len(held) == 1 else None
            if len(held) > 1:
                names = " and ".join(self._display_name(h) for h in held)
                holding = _Unknown(f"not known: the camera reports both {names} in the gripper")
                notes.warnings.append(f"the camera reports both {names} in the gripper, which holds one thing")
        people = {h.id: h for h in self.world.humans}
        human_poses = {h.id: h.pose for h in self.world.humans}
        for seen_person in humans.humans if humans is not None else ():
            if seen_person.id not in people:
                continue
            pose = seen_person.pose
            if not self.on_map(pose.x, pose.y):
                # Evidence like an object's sighting: a delivery or "come to me" there would be grounded off the map.
                notes.warnings.append(
                    f"the report of the {people[seen_person.id].name} is not believed: it puts them at "
                    f"({pose.x:.2f}, {pose.y:.2f}), off the map"
                )
                continue
            human_poses[seen_person.id] = pose
        state = _State(beliefs, holding, robot, human_poses, notes)
        if isinstance(holding, str) and origins and holding in origins:
            state.origins[holding] = (origins[holding], "where the camera last saw it before it was in the gripper")
        return state

    def on_map(self, x: float, y: float) -> bool:
        """Whether a sighting at (x, y) may be believed: over the map, give or take MAP_MARGIN."""
        return bool(self._map.covers(Point(x, y)))

    def _implausible(self, position: Vec3) -> str | None:
        """Why a sighting at `position` cannot be right (off the map, under the floor, in the air), or None."""
        where = f"({position.x:.2f}, {position.y:.2f}, {position.z:.2f})"
        if not self.on_map(position.x, position.y):
            return f"it puts it at {where}, off the map"
        if not -BELOW_FLOOR <= position.z <= self._highest:
            return f"it puts it at {where}, {'under the floor' if position.z < 0 else 'in the air'}"
        return None

    def _support_of(
        self, object_id: str, position: Vec3, on: str | None, half_height: float, notes: _Notes
    ) -> str | None:
        """What a sighting rests on: the furniture it names when its position is over that furniture,
        else the furniture under its position (the position is what the robot acts on), said in a warning."""
        if on is None or on == GRIPPER:
            return on
        item = self.model.furniture.get(on)
        if item is not None and self._near_tops[on].covers(Point(position.x, position.y)):
            return on
        under = self.model.support_under(position, half_height)
        said = item.name if item is not None else _echo(on)
        actual = self.model.furniture[under].name if under is not None else "the floor"
        notes.warnings.append(
            f"the camera reports {self._display_name(object_id)} on {said}, but at ({position.x:.2f}, "
            f"{position.y:.2f}), not over it: taken to be on {actual}"
        )
        return under

    # Groups, sub-steps and alternatives

    def _ground_steps(
        self, steps: list[Step], prefix: str, top: int | None, state: _State, out: _Grounded, *, in_alternative: bool
    ) -> None:
        """Flatten `steps` into `out` in the order they run, labelled `prefix` + 1-based position."""
        for position, step in enumerate(steps):
            at = _At(position if top is None else top, f"{prefix}{position + 1}")
            self._ground_step(at, step, state, out, in_alternative=in_alternative)

    def _ground_step(self, at: _At, step: Step, state: _State, out: _Grounded, *, in_alternative: bool) -> None:
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
            self._ground_steps(step.substeps, f"{at.label}.", at.index, state, out, in_alternative=in_alternative)
        else:
            if step.substeps:
                raise at.error(f"{step.action} cannot also have sub-steps: put the action in the group as a sub-step")
            for grounded in self._step(at, step.action, step, state):
                out.steps.append(grounded)
                out.labels.append(at.label)
            if len(out.steps) > MAX_STEPS:
                # Refused as soon as it is certain, not after grounding the rest: groups of groups let a
                # plan of a megabyte name ten thousand steps, seconds of CPU each.
                raise ResolveError(
                    f"the plan needs more than {MAX_STEPS} robot steps in a row (step {at.label} brings it to "
                    f"{len(out.steps)}; long turns and backward drives take more than one): split it into "
                    "several plans"
                )
        if before is not None:
            self._alternatives(at, step, before, first, state, out)

    def _alternatives(self, at: _At, step: Step, before: _State, first: int, state: _State, out: _Grounded) -> None:
        """Ground `step.on_failure` as a Fallback over the grounded steps from `first` on.

        The alternatives are grounded from the state predicted at the start of that range. When the
        range drives the base, where it stands when a step fails is not known in advance, so moves
        relative to the base (drive, turn, look_at) are refused there until an absolute one."""
        last = len(out.steps) - 1
        if last < first:  # the step itself grounded to nothing (a pick of what is already held): it cannot fail
            at.warn(state, "its on_failure is left out: the step has nothing to do, so it cannot fail")
            return
        if any(s.spec.moves_base for s in out.steps[first:]):
            before.robot = None
            before.pose_note = f"where the robot stands when step {at.label} fails is not known in advance"
        alternative = _Grounded()
        self._ground_steps(
            step.on_failure, f"{at.label} on_failure ", at.index, before, alternative, in_alternative=True
        )
        out.fallbacks.append(Fallback(first=first, last=last, steps=alternative.steps, labels=alternative.labels))
        # The plan goes on from the step's own outcome; objects are followed along that path (the
        # executor checks the gripper through perception), but the base's pose must agree.
        if not _same_pose(state.robot, before.robot):
            state.robot = None
            state.pose_note = f"where the robot stands after step {at.label} depends on whether its on_failure ran"

    # One step

    def _step(self, at: _At, action: Action, step: Step, state: _State) -> list[GroundedStep]:
        for name in step.params:
            if (why := UNUSED_PARAMS.get((action, name))) is not None:
                at.warn(state, f"parameter '{name}' is not used: {why}")
        match action:
            case Action.NAVIGATE_TO:
                return [self._navigate(at, step, state)]
            case Action.PICK:
                pick = self._pick(at, step, state)
                return [] if pick is None else [pick]
            case Action.PLACE:
                return [self._place(at, step, state)]
            case Action.DETECT:
                return [self._detect(at, step, state)]
            case Action.LOOK_AT:
                return [self._look_at(at, step, state)]
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
                return [self._gripper(action is Action.OPEN_GRIPPER, state)]
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
            case _:
                assert_never(action)

    # Names

    def _required(self, at: _At, name: str | None, message: str) -> str:
        if name is None or not name.strip():
            raise at.error(message)
        return name

    def _find(
        self,
        at: _At,
        text: str,
        state: _State,
        prefer: tuple[Kind, ...] = (),
        *,
        hint: str | None = None,
        coordinates: Coordinates | None = None,
    ) -> Entity:
        """The one thing `text` means at this point of the plan; kinds in `prefer` win a tie, then
        the place named by `hint` (the step's location), then the robot's room. Recorded in the notes."""
        scene = state.scene(self.model)
        antecedent = self.names.by_id.get(state.last_object) if state.last_object else None
        where = parse_reference(hint) if hint and hint.strip() else None
        try:
            match = self.matcher.find(parse_reference(text), scene, prefer, antecedent=antecedent, hint=where)
        except NoMatch as exc:
            raise at.error(exc.message, exc.kind, exc.candidates) from None
        entity = match.entity
        state.notes.resolutions.append(
            Resolution(
                label=at.label,
                text=text,
                kind=entity.kind,
                id=entity.id,
                name=entity.name,
                via=match.via,
                confidence=round(match.confidence, 3),
            )
        )
        for said in (match.reading, match.elsewhere):
            if said is not None:
                at.warn(state, said)
        if entity.kind == "object" and state.beliefs[entity.id].stale:
            at.warn(
                state,
                f"{entity.name} has not been seen for a while; it is taken to be {scene.where(entity)}, "
                "where perception last saw it",
            )
        if coordinates is not None:
            self._check_coordinates(at, state, scene, entity, coordinates)
        return entity

    def _check_coordinates(self, at: _At, state: _State, scene: Scene, entity: Entity, point: Coordinates) -> None:
        """A named entity wins over coordinates the plan gave it; a disagreement is said back."""
        off = scene.gap(point.x, point.y, entity)
        if off > self.config.coordinate_tolerance:
            x, y = scene.point(entity)
            at.warn(
                state,
                f"the plan gives ({point.x:.2f}, {point.y:.2f}) for {entity.name}, {off:.1f} m from where it is "
                f"({x:.2f}, {y:.2f}); the position of {entity.name} is used",
            )

    def _expect_kind(self, at: _At, verb: str, name: str, entity: Entity, kinds: tuple[Kind, ...]) -> None:
        if entity.kind not in kinds:
            wanted = " or ".join(KIND_NOUNS[k] for k in kinds)
            raise at.error(f"cannot {verb} {_echo(name)}: {entity.name} is {KIND_NOUNS[entity.kind]}, not {wanted}")

    def _handled(self, state: _State, entity: Entity) -> None:
        """`entity` is what "it" means from here on, if it is an object."""
        if entity.kind == "object":
            state.last_object = entity.id

    # Bare coordinates: used only when the step names nothing, and only where the robot can be

    def _point(self, at: _At, state: _State, point: Coordinates, verb: str) -> tuple[float, float]:
        """(x, y) when it lies on the map: inside a room. Recorded in the notes."""
        x, y = point.x, point.y
        if self.model.room_of(x, y) is None:
            raise at.error(f"cannot {verb} ({x:.2f}, {y:.2f}): that point is outside the map (outside every room)")
        label = f"({x:.2f}, {y:.2f})"
        state.notes.resolutions.append(
            Resolution(label=at.label, text=label, kind="point", name=label, via="coordinates")
        )
        return x, y

    def _free_point(self, at: _At, state: _State, point: Coordinates) -> tuple[float, float]:
        """A point on the map where the base fits, clear of every piece of furniture."""
        x, y = self._point(at, state, point, "go to")
        for item in self.world.furniture:
            if self.model.footprint(item).distance(Point(x, y)) < self._base_radius:
                raise at.error(
                    f"cannot go to ({x:.2f}, {y:.2f}): the base (radius {self._base_radius:.2f} m) would stand in "
                    f"the {item.name}; give a point clear of it, or name the {item.name}"
                )
        return x, y

    def _object_at(self, at: _At, state: _State, point: Coordinates) -> Entity:
        """The object perception places at the given coordinates (within coordinate_tolerance)."""
        scene = state.scene(self.model)
        objects = [e for e in self.names.of_kind("object") if not scene.in_gripper(e)]
        ranked = sorted(objects, key=lambda e: math.dist(scene.point(e), (point.x, point.y)))
        near = [e for e in ranked if math.dist(scene.point(e), (point.x, point.y)) <= self.config.coordinate_tolerance]
        where = f"({point.x:.2f}, {point.y:.2f})"
        if not near:
            closest = f"; the nearest is the {scene.describe(ranked[0])}" if ranked else ""
            raise at.error(
                f"no object is within {self.config.coordinate_tolerance:g} m of {where}{closest}; name the object",
                ErrorKind.UNKNOWN_NAME,
                [e.name for e in ranked[:1]],
            )
        if len(near) > 1:
            first, second = (math.dist(scene.point(e), (point.x, point.y)) for e in near[:2])
            if second - first < self.config.coordinate_tolerance / 2:
                described = [scene.describe(e) for e in near]
                raise at.error(
                    f"more than one object is near {where}: the {', the '.join(described)}; name the object",
                    ErrorKind.AMBIGUOUS_NAME,
                    described,
                )
        entity = near[0]
        state.notes.resolutions.append(
            Resolution(label=at.label, text=where, kind="object", id=entity.id, name=entity.name, via="coordinates")
        )
        return entity

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

    def _navigate(self, at: _At, step: Step, state: _State) -> NavigateStep:
        speed = self._speed(at, step)
        name = step.target or step.location
        if (name is None or not name.strip()) and step.coordinates is not None:
            x, y = self._free_point(at, state, step.coordinates)
            start = state.robot
            yaw = start.yaw if start is not None else 0.0
            if start is not None and math.hypot(x - start.x, y - start.y) > 1e-6:
                yaw = math.atan2(y - start.y, x - start.x)  # arrive facing the way it drove
            spot = _rounded(Pose2D(x=x, y=y, yaw=yaw))
            self._moved_to(state, spot)
            return NavigateStep(target=f"({x:.2f}, {y:.2f})", goal=spot, max_speed=speed)
        name = self._required(at, name, "navigate_to needs a target: where to go")
        entity = self._find(at, name, state, coordinates=step.coordinates)
        goal: Pose2D
        if entity.kind == "room":
            goal = self.model.room_pose(entity.id)
        elif entity.kind == "furniture":
            goal = self.model.furniture[entity.id].approach
        elif entity.kind == "place":
            goal = self._places[entity.id].pose
        elif entity.kind == "human":
            goal = self._towards_human(state.humans[entity.id], state.robot)
        else:
            belief = state.beliefs[entity.id]
            if belief.on == GRIPPER:
                raise at.error(f"cannot go to {entity.name}: it is in the gripper", ErrorKind.PRECONDITION)
            goal = self._object_approach(at, entity.name, belief, state.robot)
            self._handled(state, entity)
        goal = _rounded(goal)
        self._moved_to(state, goal)
        return NavigateStep(target=entity.name, goal=goal, max_speed=speed)

    def _moved_to(self, state: _State, pose: Pose2D) -> None:
        state.robot, state.pose_note = pose, None

    def _towards_human(self, human: Pose2D, robot: Pose2D | None) -> Pose2D:
        if robot is not None and math.dist((robot.x, robot.y), (human.x, human.y)) > 1e-6:
            return approach_towards(human.x, human.y, self.config.human_standoff, robot.x, robot.y)
        # No robot pose: stand in front of the person, where they are facing.
        ahead = (human.x + math.cos(human.yaw), human.y + math.sin(human.yaw))
        return approach_towards(human.x, human.y, self.config.human_standoff, *ahead)

    def _object_approach(self, at: _At, name: str, belief: Belief, robot: Pose2D | None) -> Pose2D:
        """Where the base stands to reach an object: its furniture's approach pose, or, on the floor,
        `object_standoff` from it facing it, from the robot's side if the footprint fits there (clear of
        walls, furniture and keep-out zones by TRACKING_TOLERANCE, in the object's room), else from the
        nearest side round it that fits. Refused when none does: the straight line from the robot put
        the base inside a table, or on the far side of a wall."""
        if belief.on is not None and belief.on in self.model.furniture:
            return self.model.furniture[belief.on].approach
        start = robot or self.world.robot.start
        x, y = belief.position.x, belief.position.y
        room = self.model.room_of(x, y)
        towards = math.atan2(start.y - y, start.x - x) if math.dist((start.x, start.y), (x, y)) > 1e-6 else 0.0
        size, standoff = self.world.robot.base_size, self.config.object_standoff
        for k in range(APPROACH_SIDES):
            side = towards + (k + 1) // 2 * (1 if k % 2 else -1) * math.tau / APPROACH_SIDES
            pose = approach_towards(x, y, standoff, x + math.cos(side), y + math.sin(side))
            fits = self.model.clear_by(footprint(pose.x, pose.y, pose.yaw, size.x, size.y)) >= TRACKING_TOLERANCE
            if fits and (room is None or self.model.room_of(pose.x, pose.y) == room):
                return pose
        raise at.error(
            f"cannot reach {name} at ({x:.2f}, {y:.2f}): the base fits nowhere {standoff:g} m from it "
            "(walls, furniture or keep-out zones all round); move it, or reach it some other way",
            ErrorKind.PRECONDITION,
        )

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

    def _detect(self, at: _At, step: Step, state: _State) -> DetectStep:
        if step.target is None and step.coordinates is not None:
            entity = self._object_at(at, state, step.coordinates)
        else:
            target = self._required(at, step.target, "detect needs a target: which object")
            entity = self._find(
                at, target, state, ("object", "human"), hint=step.location, coordinates=step.coordinates
            )
            if entity.kind == "human":
                # The executor's detect waits for the camera's object detections; people come from the
                # person tracker, so a detect of one could only fail (after driving round to search).
                raise at.error(
                    f"cannot detect {_echo(target)}: the {entity.name} is a person, and detect looks for "
                    f"objects with the camera (people are followed by the person tracker); use look_at to "
                    f"face the {entity.name}, or navigate_to to go to them"
                )
            self._expect_kind(at, "detect", target, entity, ("object",))
        self._handled(state, entity)
        return DetectStep(object_id=entity.id, object_name=entity.name, search=_search_scope(step))

    def _look_at(self, at: _At, step: Step, state: _State) -> NavigateStep:
        name = step.target or step.location
        x: float
        y: float
        if (name is None or not name.strip()) and step.coordinates is not None:
            x, y = self._point(at, state, step.coordinates, "look at")
            facing = f"({x:.2f}, {y:.2f})"
        else:
            name = self._required(at, name, "look_at needs a target: what to face")
            hint = step.location if step.target else None
            entity = self._find(at, name, state, ("human", "object"), hint=hint, coordinates=step.coordinates)
            if entity.kind == "object" and state.beliefs[entity.id].on == GRIPPER:
                raise at.error(f"cannot look at {entity.name}: it is in the gripper", ErrorKind.PRECONDITION)
            x, y = state.scene(self.model).point(entity)
            facing = entity.name
            self._handled(state, entity)
        start = self._base_pose(at, "look_at", state)
        yaw = start.yaw if math.hypot(x - start.x, y - start.y) < 1e-6 else math.atan2(y - start.y, x - start.x)
        goal = _rounded(Pose2D(x=start.x, y=start.y, yaw=yaw))
        self._moved_to(state, goal)
        return NavigateStep(target=f"facing {facing}", goal=goal)

    def _gripper(self, open_: bool, state: _State) -> GripperStep:
        if open_:
            held = state.holding
            if isinstance(held, str) and held in state.beliefs:
                # It falls; the resolver only needs to know it is no longer on anything.
                belief = state.beliefs[held]
                x, y = (state.robot.x, state.robot.y) if state.robot else (belief.position.x, belief.position.y)
                state.beliefs[held] = Belief(Vec3(x=x, y=y, z=belief.half_height), None, belief.half_height)
            state.holding = None
        # Closing on nothing holds nothing; closing on what is held keeps holding it.
        return GripperStep(open=open_)

    def _pick(self, at: _At, step: Step, state: _State) -> PickStep | None:
        """The pick, or None when the gripper already holds that object ("pick up the cup, bring it to
        me": the bring's own pick is done already)."""
        if step.target is None and step.coordinates is not None:
            entity = self._object_at(at, state, step.coordinates)
            name = entity.name
        else:
            name = self._required(at, step.target, "pick needs a target: which object")
            entity = self._find(at, name, state, ("object",), hint=step.location, coordinates=step.coordinates)
            self._expect_kind(at, "pick", name, entity, ("object",))
        if state.holding == entity.id:
            at.warn(state, f"{entity.name} is already in the gripper: nothing to pick up")
            self._handled(state, entity)
            return None
        if isinstance(state.holding, str):
            held = self._display_name(state.holding)
            raise at.error(
                f"cannot pick {entity.name}: the gripper already holds {held}; place it first",
                ErrorKind.PRECONDITION,
            )
        obj = self.model.objects[entity.id]
        belief = state.beliefs[entity.id]
        support = belief.on if belief.on is not None and belief.on in self.model.furniture else FLOOR
        approach = _rounded(self._object_approach(at, entity.name, belief, state.robot))
        pick = PickStep(
            object_id=entity.id,
            object_name=entity.name,
            position=_vec(belief.position),
            mass=obj.mass,  # from the world file: a plan never says how heavy something is
            support_id=support,
            approach=approach,
            search=_search_scope(step),
        )
        state.holding = entity.id
        on = belief.on if belief.on in self.model.furniture else None
        state.origins[entity.id] = (Origin(on, belief.position), f"where step {at.label} picked it up")
        belief.on = GRIPPER
        self._handled(state, entity)
        self._moved_to(state, approach)
        return pick

    def _place(self, at: _At, step: Step, state: _State) -> GroundedStep:
        if (
            step.target is not None
            and (step.location is None or not step.location.strip())
            and step.coordinates is None
            and (self._means_put_back(step.target) or self._names_a_person(step.target))
        ):
            # {"action": "place", "target": "me"}: the target is where, not what.
            step = msgspec.structs.replace(step, target=None, location=step.target)
        held = state.holding
        if step.target is not None:
            obj = self._find(at, step.target, state, ("object",))
            self._expect_kind(at, "place", step.target, obj, ("object",))
            if held is None:
                raise at.error(f"cannot place {obj.name}: the gripper holds nothing", ErrorKind.PRECONDITION)
            if isinstance(held, str) and held != obj.id:
                raise at.error(
                    f"cannot place {obj.name}: the gripper holds {self._display_name(held)}", ErrorKind.PRECONDITION
                )
            held = obj.id
        if step.location is not None and self._means_put_back(step.location):
            surface, position = self._put_back_spot(at, step.location, state, held)
        elif (step.location is None or not step.location.strip()) and step.coordinates is not None:
            surface, position = self._spot_at(at, state, step.coordinates, held)
        else:
            name = self._required(
                at, step.location, "place needs a location: the furniture to put the object on (none given)"
            )
            entity = self._find(at, name, state, ("furniture",), coordinates=step.coordinates)
            if entity.kind == "human" and self.config.deliver == "hand":
                return self._hand_over(at, state, entity, held)
            if entity.kind == "human":
                surface, position = self._delivery_spot(at, name, state, entity, held)
            else:
                surface, position = self._put_down_spot(at, name, entity, state, held)
        if held is None:
            raise at.error(f"cannot place on {surface.name}: the gripper holds nothing", ErrorKind.PRECONDITION)
        if isinstance(held, str):
            belief = state.beliefs.get(held)
            half = belief.half_height if belief else 0.0
            state.beliefs[held] = Belief(Vec3(x=position.x, y=position.y, z=position.z + half), surface.id, half)
            state.origins.pop(held, None)
            state.last_object = held
        state.holding = None
        self._moved_to(state, surface.approach)
        return PlaceStep(surface_id=surface.id, surface_name=surface.name, position=position, approach=surface.approach)

    def _means_put_back(self, location: str) -> bool:
        """Whether a place location means where the object was: one of the config's phrases ("where
        it was found", "back", ...), unless the world has a thing of that name."""
        return normalise_name(location) in self._put_back and not self.names.lookup(location)

    def _names_a_person(self, name: str) -> bool:
        found = self.names.lookup(name)
        return bool(found) and all(e.kind == "human" for e in found)

    def _put_down_spot(
        self, at: _At, name: str, entity: Entity, state: _State, held: str | _Unknown | None
    ) -> tuple[Furniture, Vec3]:
        """The surface the location names and a free spot on it: near the edge the robot stands
        at, next to a named object if the location is one ("next to the apple")."""
        beside: Belief | None = None
        if entity.kind == "object" and entity.id != held:
            beside = state.beliefs[entity.id]
            if beside.on is None or beside.on not in self.model.furniture:
                raise at.error(
                    f"cannot place next to {entity.name}: it is not on a piece of furniture", ErrorKind.PRECONDITION
                )
            entity = self.names.by_id[beside.on]
            state.notes.resolutions[-1] = msgspec.structs.replace(  # the surface is what the location means
                state.notes.resolutions[-1], kind="furniture", id=entity.id, name=entity.name, via="relation"
            )
        self._expect_kind(at, "place on", name, entity, ("furniture",))
        surface = self.model.furniture[entity.id]
        occupied = self._occupied(state, surface.id, held)
        near = (beside.position.x, beside.position.y) if beside is not None else None
        position = place_position(
            surface, occupied, inset=self.config.place_inset, clearance=self.config.place_clearance, near=near
        )
        if position is None:
            raise at.error(
                f"no free spot on {entity.name}: every spot near its edge is within "
                f"{self.config.place_clearance:g} m of another object",
                ErrorKind.PRECONDITION,
            )
        return surface, position

    def _surface_named(self, at: _At, text: str, state: _State, surface: Furniture) -> None:
        """Record that the location `text` was read as `surface`."""
        state.notes.resolutions.append(
            Resolution(label=at.label, text=text, kind="furniture", id=surface.id, name=surface.name, via="relation")
        )

    def _holding_for(self, at: _At, verb: str, held: str | _Unknown | None) -> str:
        """What the gripper holds, for a place that needs to know it."""
        if held is None:
            raise at.error(f"cannot {verb}: the gripper holds nothing", ErrorKind.PRECONDITION)
        if isinstance(held, _Unknown):
            raise at.error(
                f"cannot {verb}: what the gripper holds is {held.why}; name the object", ErrorKind.PRECONDITION
            )
        return held

    def _delivery_spot(
        self, at: _At, name: str, state: _State, person: Entity, held: str | _Unknown | None
    ) -> tuple[Furniture, Vec3]:
        """The free furniture top nearest the person (in their room first) that the arm reaches
        from the top's approach pose, and the spot on it nearest them."""
        thing = self._display_name(held) if isinstance(held, str) else "the object"
        pose = state.humans[person.id]
        room = self.model.room_of(pose.x, pose.y)
        keep_out = list(self.model.keep_out_shapes.values())
        limit = self.config.deliver_max_distance
        free: list[tuple[bool, float, Furniture, Vec3]] = []
        unusable: list[tuple[float, Furniture, str]] = []
        for surface in self.world.furniture:
            approach = surface.approach
            gap = float(self.model.footprint(surface).distance(Point(pose.x, pose.y)))
            stands_on_them = math.dist((approach.x, approach.y), (pose.x, pose.y)) < (
                self._base_radius + PERSON_CLEARANCE
            )
            if stands_on_them:
                unusable.append((gap, surface, ", the robot would stand where they are"))
                continue
            if any(zone.covers(Point(approach.x, approach.y)) for zone in keep_out):
                unusable.append((gap, surface, ", its approach pose is in a keep-out zone"))
                continue

            def allowed(x: float, y: float, approach: Pose2D = approach) -> bool:
                return (
                    math.dist((x, y), (approach.x, approach.y)) <= self.config.deliver_reach
                    and math.dist((x, y), (pose.x, pose.y)) >= PERSON_CLEARANCE
                    and not any(zone.covers(Point(x, y)) for zone in keep_out)
                )

            spot = place_position(
                surface,
                self._occupied(state, surface.id, held),
                inset=self.config.place_inset,
                clearance=self.config.place_clearance,
                near=(pose.x, pose.y),
                allowed=allowed,
            )
            if spot is None:
                unusable.append((gap, surface, ", no free spot the arm reaches"))
            else:
                distance = math.dist((spot.x, spot.y), (pose.x, pose.y))
                free.append((self.model.room_of(spot.x, spot.y) != room, distance, surface, spot))
        choices = sorted((c for c in free if c[1] <= limit), key=lambda c: (c[0], c[1]))
        if not choices:
            nearest = sorted([(d, f, "") for _, d, f, _ in free] + unusable, key=lambda c: c[0])
            listed = [f"the {f.name} ({d:.1f} m{why})" for d, f, why in nearest[:DELIVERY_SUGGESTIONS]]
            raise at.error(
                f"cannot place {thing} at {_echo(name)} ({person.name}): no furniture top with a free spot the arm "
                f"reaches is within {limit:g} m of them; the nearest: {', '.join(listed)}; name the surface",
                ErrorKind.PRECONDITION,
                [f.name for _, f, _ in nearest[:DELIVERY_SUGGESTIONS]],
            )
        _, distance, surface, spot = choices[0]
        self._surface_named(at, name, state, surface)
        at.warn(
            state,
            f"{_echo(name)} is the {person.name}: {thing} goes on the {surface.name}, the free surface nearest "
            f"them ({distance:.1f} m), not into their hands",
        )
        return surface, spot

    def _hand_over(self, at: _At, state: _State, person: Entity, held: str | _Unknown | None) -> NavigateStep:
        """deliver = "hand": drive up to the person and keep holding the object out to them."""
        if held is None:
            raise at.error(
                f"cannot hand anything to the {person.name}: the gripper holds nothing", ErrorKind.PRECONDITION
            )
        thing = self._display_name(held) if isinstance(held, str) else "what the gripper holds"
        goal = _rounded(self._towards_human(state.humans[person.id], state.robot))
        at.warn(
            state,
            f"{thing} is handed to the {person.name}: the robot stops {self.config.human_standoff:g} m from them "
            'and keeps holding it (deliver = "hand"); the gripper does not open',
        )
        if isinstance(held, str):
            state.last_object = held
        self._moved_to(state, goal)
        return NavigateStep(target=f"{person.name} (handing over {thing})"[:MAX_NAME_CHARS], goal=goal)

    def _put_back_spot(
        self, at: _At, phrase: str, state: _State, held: str | _Unknown | None
    ) -> tuple[Furniture, Vec3]:
        """Where the held object stood before the gripper took it: the same spot if it is still
        free, else the free spot on that top nearest it."""
        held_id = self._holding_for(at, "put it back", held)
        thing = self._display_name(held_id)
        if held_id not in state.origins:
            raise at.error(
                f"cannot put {thing} back ({_echo(phrase)}): this plan did not pick it up, and the camera never "
                "saw it anywhere before it was in the gripper; name the surface to put it on",
                ErrorKind.PRECONDITION,
            )
        origin, how = state.origins[held_id]
        if origin.on is None or origin.on not in self.model.furniture:
            raise at.error(
                f"cannot put {thing} back ({_echo(phrase)}): {how} it was on the floor, and place puts things "
                "on furniture only; name a surface",
                ErrorKind.PRECONDITION,
            )
        surface = self.model.furniture[origin.on]
        occupied = self._occupied(state, surface.id, held_id)
        was = (origin.position.x, origin.position.y)
        clearance = self.config.place_clearance
        position: Vec3 | None
        if all(math.dist(was, other) >= clearance - 1e-9 for other in occupied):
            position = Vec3(x=round(was[0], 3), y=round(was[1], 3), z=round(surface.size.z, 3))
            spot = "the same spot"
        else:
            position = place_position(surface, occupied, inset=self.config.place_inset, clearance=clearance, near=was)
            spot = "the free spot nearest its old one (something else stands there now)"
        if position is None:
            raise at.error(
                f"cannot put {thing} back on the {surface.name}: every spot on it is within {clearance:g} m "
                "of another object",
                ErrorKind.PRECONDITION,
            )
        self._surface_named(at, phrase, state, surface)
        at.warn(state, f"{_echo(phrase)}: {thing} goes back on the {surface.name}, {how}, at {spot}")
        return surface, position

    def _occupied(self, state: _State, surface_id: str, held: str | _Unknown | None) -> list[tuple[float, float]]:
        return [(b.position.x, b.position.y) for oid, b in state.beliefs.items() if b.on == surface_id and oid != held]

    def _spot_at(
        self, at: _At, state: _State, point: Coordinates, held: str | _Unknown | None
    ) -> tuple[Furniture, Vec3]:
        """The plan's own spot, when it lies on a surface, clear of what is on it."""
        spot = Point(point.x, point.y)
        where = f"({point.x:.2f}, {point.y:.2f})"
        surface = next((f for f in self.world.furniture if self.model.footprint(f).covers(spot)), None)
        if surface is None:
            raise at.error(f"cannot place at {where}: no furniture top is there; name the surface")
        inner = self.model.footprint(surface).buffer(-PLACE_EDGE_MARGIN)
        if not inner.covers(spot):
            raise at.error(
                f"cannot place at {where}: it is within {PLACE_EDGE_MARGIN:g} m of the edge of the {surface.name}"
            )
        for x, y in self._occupied(state, surface.id, held):
            if math.dist((x, y), (point.x, point.y)) < self.config.place_clearance:
                raise at.error(
                    f"cannot place at {where}: another object on the {surface.name} is within "
                    f"{self.config.place_clearance:g} m of it",
                    ErrorKind.PRECONDITION,
                )
        self._point(at, state, point, "place at")
        return surface, Vec3(x=round(point.x, 3), y=round(point.y, 3), z=round(surface.size.z, 3))

    def _display_name(self, object_id: str) -> str:
        obj = self.model.objects.get(object_id)
        return obj.name if obj else object_id


def _same_pose(a: Pose2D | None, b: Pose2D | None) -> bool:
    if a is None or b is None:
        return a is b
    return math.dist((a.x, a.y), (b.x, b.y)) <= SAME_POSITION and abs(_wrap(a.yaw - b.yaw)) <= SAME_YAW


def _vec(v: Vec3) -> Vec3:
    return Vec3(x=round(v.x, 4), y=round(v.y, 4), z=round(v.z, 4))


def _search_scope(step: Step) -> SearchScope | None:
    """The search a detect or pick asks for (`search` in its parameters; the parser checked the word)."""
    value = step.params.get("search")
    return next((scope for scope in get_args(SearchScope) if scope == value), None)


def _rounded(pose: Pose2D) -> Pose2D:
    return Pose2D(x=round(pose.x, 4), y=round(pose.y, 4), yaw=round(pose.yaw, 4))


def answer(
    resolver: Resolver,
    plan: Plan,
    objects: PerceivedObjects | None = None,
    robot: Pose2D | None = None,
    humans: PerceivedHumans | None = None,
    origins: Mapping[str, Origin] | None = None,
) -> ResolveReply:
    """What plan/resolve replies: the GroundedPlan, or the refusal as a value. Never raises ResolveError."""
    try:
        return resolver.resolve(plan, objects, robot, humans=humans, origins=origins)
    except ResolveError as exc:
        return exc.error
