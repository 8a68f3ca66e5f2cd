"""Plan -> GroundedPlan: every name becomes an id and a pose, from the world model and perception."""

from __future__ import annotations

import math
from dataclasses import dataclass

from schemas.common import ErrorKind, Pose2D, Vec3
from schemas.plan import (
    Action,
    DetectStep,
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
from services.worldmodel import WorldModel, approach_towards

GRIPPER = "gripper"
FLOOR = "floor"
MAX_WAIT = 60.0
ECHO_CHARS = 60


def _echo(name: str) -> str:
    return repr(name if len(name) <= ECHO_CHARS else name[:ECHO_CHARS] + "...")


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
    beliefs: dict[str, _Belief]
    holding: str | _Unknown | None
    robot: Pose2D | None


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
        """The grounded plan, or ResolveError naming the step (0-based `step`, "step N" 1-based)."""
        state = self._initial_state(objects, robot)
        human_poses = {h.id: h.pose for h in self.world.humans}
        if humans is not None:
            human_poses.update({h.id: h.pose for h in humans.humans})
        steps: list[GroundedStep] = []
        for index, step in enumerate(plan.steps):
            steps.append(self._step(index, step, state, human_poses))
        return GroundedPlan(steps=steps, source=plan)

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

    def _step(self, index: int, step: Step, state: _State, humans: dict[str, Pose2D]) -> GroundedStep:
        match step.action:
            case Action.NAVIGATE_TO:
                return self._navigate(index, step, state, humans)
            case Action.PICK:
                return self._pick(index, step, state)
            case Action.PLACE:
                return self._place(index, step, state)
            case Action.DETECT:
                target = self._required(index, step.target, "detect needs a target: which object")
                entity = self._entity(index, target, ("object", "human"), hint=step.location)
                self._expect_kind(index, "detect", target, entity, ("object", "human"))
                return DetectStep(object_id=entity.id, object_name=entity.name)
            case Action.SAY:
                text = step.params.get("text", step.target)
                if not isinstance(text, str) or not text.strip():
                    raise ResolveError("say needs the words to speak (parameter 'text')", step=index)
                return SayStep(text=text)
            case Action.WAIT:
                duration = step.params.get("duration")
                if isinstance(duration, bool) or not isinstance(duration, int | float):
                    raise ResolveError("wait needs a 'duration' in seconds", step=index)
                if not 0.0 <= duration <= MAX_WAIT:
                    raise ResolveError(f"wait duration {duration:g} s is outside 0..{MAX_WAIT:g} s", step=index)
                return WaitStep(duration=float(duration))
            case Action.STOP:
                return StopStep()
        raise ResolveError(f"action {step.action!r} has no grounding", step=index)  # pragma: no cover

    # Names

    def _required(self, index: int, name: str | None, message: str) -> str:
        if name is None or not name.strip():
            raise ResolveError(message, step=index)
        return name

    def _entity(self, index: int, name: str, prefer: tuple[Kind, ...] = (), *, hint: str | None = None) -> Entity:
        """The one thing `name` means; kinds in `prefer` win a tie, then the support named by `hint`."""
        found = self.names.lookup(name)
        if not found:
            suggestions = self.names.suggestions(name)
            if suggestions:
                listed = " or ".join(f"'{s}'" for s in suggestions)
                detail = f" (did you mean {listed}?)"
            else:
                detail = f": no room, furniture, place, object or person in world '{self.world.name}' has that name"
            raise ResolveError(
                f"unknown name {_echo(name)}{detail}", kind=ErrorKind.UNKNOWN_NAME, step=index, candidates=suggestions
            )
        if len(found) > 1 and prefer:
            found = [e for e in found if e.kind in prefer] or found
        if len(found) > 1 and hint:
            supports = {e.id for e in self.names.lookup(hint) if e.kind == "furniture"}
            on_hint = [e for e in found if e.kind == "object" and self._support_of(e.id) in supports]
            found = on_hint or found
        if len(found) > 1:
            names = [e.name for e in found]
            raise ResolveError(
                f"{_echo(name)} is ambiguous: it could be {', '.join(names[:-1])} or {names[-1]}; name one of them",
                kind=ErrorKind.AMBIGUOUS_NAME,
                step=index,
                candidates=names,
            )
        return found[0]

    def _support_of(self, object_id: str) -> str | None:
        obj = self.model.objects.get(object_id)
        return obj.support if obj else None

    def _expect_kind(self, index: int, verb: str, name: str, entity: Entity, kinds: tuple[Kind, ...]) -> None:
        if entity.kind not in kinds:
            wanted = " or ".join(KIND_NOUNS[k] for k in kinds)
            raise ResolveError(
                f"cannot {verb} {_echo(name)}: {entity.name} is {KIND_NOUNS[entity.kind]}, not {wanted}", step=index
            )

    # Steps

    def _navigate(self, index: int, step: Step, state: _State, humans: dict[str, Pose2D]) -> NavigateStep:
        name = self._required(index, step.target or step.location, "navigate_to needs a target: where to go")
        entity = self._entity(index, name)
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
                raise ResolveError(
                    f"cannot go to {entity.name}: it is in the gripper", kind=ErrorKind.PRECONDITION, step=index
                )
            goal = self._object_approach(belief, state.robot)
        state.robot = goal
        return NavigateStep(target=entity.name, goal=_rounded(goal))

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

    def _pick(self, index: int, step: Step, state: _State) -> PickStep:
        name = self._required(index, step.target, "pick needs a target: which object")
        entity = self._entity(index, name, ("object",), hint=step.location)
        self._expect_kind(index, "pick", name, entity, ("object",))
        if state.holding == entity.id:
            raise ResolveError(
                f"cannot pick {entity.name}: it is already in the gripper", kind=ErrorKind.PRECONDITION, step=index
            )
        if isinstance(state.holding, str):
            held = self._display_name(state.holding)
            raise ResolveError(
                f"cannot pick {entity.name}: the gripper already holds {held}; place it first",
                kind=ErrorKind.PRECONDITION,
                step=index,
            )
        obj = self.model.objects[entity.id]
        belief = state.beliefs[entity.id]
        support = belief.on if belief.on is not None and belief.on in self.model.furniture else FLOOR
        approach = self._object_approach(belief, state.robot)
        pick = PickStep(
            object_id=entity.id,
            object_name=entity.name,
            position=_vec(belief.position),
            mass=obj.mass,  # from the world file: a plan never says how heavy something is
            support_id=support,
            approach=_rounded(approach),
        )
        state.holding = entity.id
        belief.on = GRIPPER
        return pick

    def _place(self, index: int, step: Step, state: _State) -> PlaceStep:
        name = self._required(
            index, step.location, "place needs a location: the furniture to put the object on (none given)"
        )
        entity = self._entity(index, name, ("furniture",))
        self._expect_kind(index, "place on", name, entity, ("furniture",))
        held = state.holding
        if step.target is not None:
            obj = self._entity(index, step.target, ("object",))
            self._expect_kind(index, "place", step.target, obj, ("object",))
            if held is None:
                raise ResolveError(
                    f"cannot place {obj.name}: the gripper holds nothing", kind=ErrorKind.PRECONDITION, step=index
                )
            if isinstance(held, str) and held != obj.id:
                raise ResolveError(
                    f"cannot place {obj.name}: the gripper holds {self._display_name(held)}",
                    kind=ErrorKind.PRECONDITION,
                    step=index,
                )
            held = obj.id
        if held is None:
            raise ResolveError(
                f"cannot place on {entity.name}: the gripper holds nothing", kind=ErrorKind.PRECONDITION, step=index
            )
        surface = self.model.furniture[entity.id]
        occupied = [
            (b.position.x, b.position.y) for oid, b in state.beliefs.items() if b.on == entity.id and oid != held
        ]
        position = place_position(surface, occupied, inset=self.place_inset, clearance=self.place_clearance)
        if position is None:
            raise ResolveError(
                f"no free spot on {entity.name}: every spot near its edge is within "
                f"{self.place_clearance:g} m of another object",
                kind=ErrorKind.PRECONDITION,
                step=index,
            )
        if isinstance(held, str):
            belief = state.beliefs.get(held)
            half = belief.half_height if belief else 0.0
            state.beliefs[held] = _Belief(Vec3(x=position.x, y=position.y, z=position.z + half), entity.id, half)
        state.holding = None
        return PlaceStep(surface_id=entity.id, surface_name=entity.name, position=position, approach=surface.approach)

    def _display_name(self, object_id: str) -> str:
        obj = self.model.objects.get(object_id)
        return obj.name if obj else object_id


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
