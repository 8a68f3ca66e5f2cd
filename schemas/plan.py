"""Plans: the raw text an LLM wrote, the parsed plan, and the grounded plan with ids and poses."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Annotated, ClassVar, Literal, get_args

from msgspec import Meta

from schemas.common import (
    Frozen,
    Id,
    Kilograms,
    Metres,
    Name,
    Pose2D,
    ServiceError,
    Text,
    Vec3,
    fmt_pose,
    preview,
)

# Requests larger than this are refused before any parsing is attempted.
MAX_PLAN_BYTES = 256 * 1024
# Steps in a whole plan, sub-steps and on_failure alternatives included.
MAX_STEPS = 100
# Levels of sub-steps and on_failure alternatives below the plan's own steps.
MAX_NESTING = 8

PlanFormat = Literal["auto", "json", "yaml", "text"]
# The shape a plan was found in, reported with the parsed plan.
SourceFormat = Literal[
    "json",
    "yaml",
    "text",
    "openai_tool_calls",
    "openai_function_call",
    "anthropic_tool_use",
    "mcp_tools_call",
    "openai_responses",
    "gemini_function_call",
]


class Action(enum.StrEnum):
    """Canonical actions. Synonyms, parameters and units live in the parser's vocabulary file."""

    NAVIGATE_TO = "navigate_to"
    PICK = "pick"
    PLACE = "place"
    DETECT = "detect"
    LOOK_AT = "look_at"
    DRIVE = "drive"
    TURN = "turn"
    STOP = "stop"
    SAY = "say"
    GESTURE = "gesture"
    WAIT = "wait"
    OPEN_GRIPPER = "open_gripper"
    CLOSE_GRIPPER = "close_gripper"
    MOVE_ARM = "move_arm"


class PlanText(Frozen):
    """What an LLM or a person wrote, untouched, with a hint of its format."""

    text: Annotated[str, Meta(max_length=MAX_PLAN_BYTES)]
    format: PlanFormat = "auto"


ParamValue = float | int | bool | str


ParamName = Annotated[str, Meta(max_length=64)]


class Coordinates(Frozen):
    """A point a plan wrote down, in the map frame (metres). Untrusted: the resolver uses it only when
    the step names nothing (and then only inside the map, off obstacles); a named entity wins."""

    x: Metres
    y: Metres
    z: Metres | None = None


class Step(Frozen):
    """One action, or (with `action` None) a group of sub-steps run in order.

    Numbers in `params` are SI; `units` names the unit of each one that has a unit ("m", "m/s",
    "rad", "s"). `on_failure` runs instead when this step (or any of its sub-steps) fails; the plan
    then goes on after this step. `description` is the LLM's own words, carried along and never
    read as a command.
    """

    action: Action | None = None
    target: Name | None = None
    location: Name | None = None
    params: dict[ParamName, ParamValue] = {}
    units: dict[ParamName, Annotated[str, Meta(max_length=16)]] = {}
    description: Text = ""
    coordinates: Coordinates | None = None
    substeps: Annotated[list[Step], Meta(max_length=MAX_STEPS)] = []
    on_failure: Annotated[list[Step], Meta(max_length=MAX_STEPS)] = []


class Plan(Frozen, tag="plan"):
    steps: Annotated[list[Step], Meta(min_length=1, max_length=MAX_STEPS)]
    description: Text = ""
    warnings: list[Text] = []
    source_format: SourceFormat = "json"


def walk(steps: list[Step]) -> list[Step]:
    """Every step, depth first: each step, then its sub-steps, then its on_failure alternatives."""
    out: list[Step] = []
    for step in steps:
        out.append(step)
        out.extend(walk(step.substeps))
        out.extend(walk(step.on_failure))
    return out


ParseReply = Plan | ServiceError


# Grounded steps: every name replaced by an id and a pose from the world model or perception.


@dataclass(frozen=True)
class StepSpec:
    """What one kind of grounded step declares once, as its class's `spec`; the class also says
    what it is doing, in words, with `describe()` (progress feedback) and `brief()` (the timeline).

    `moves_base`: running it may drive the base (pick and place drive to their approach first), so
    safety refuses it while the robot's pose is unknown and the resolver forgets the base's pose
    across its on_failure. `timeout` (seconds of motion time) and `retries` are the defaults of
    its key in the executor's `[executor.timeouts]` and `[executor.retries]` tables.
    """

    moves_base: bool
    timeout: float
    retries: int


class NavigateStep(Frozen, tag="navigate_to"):
    """Drive the base to `goal`. Also drive, turn and look_at: relative moves grounded as a goal pose.

    `max_speed` (m/s) is the plan's own speed limit, when it gave one; safety clamps it further.
    """

    spec: ClassVar[StepSpec] = StepSpec(moves_base=True, timeout=300.0, retries=2)

    target: Name
    goal: Pose2D
    max_speed: Annotated[float, Meta(gt=0.0, le=5.0)] | None = None

    def describe(self) -> str:
        return f"moving the base: {self.target} -> {fmt_pose(self.goal)}"

    def brief(self) -> str:
        return f"navigate_to {self.target} {fmt_pose(self.goal)}"


# How far the executor may look for an object it does not see (its README): not at all, in the room
# the base is in (turning round, then the furniture tops), or in every room. A step may narrow the
# executor's configured scope, never widen it.
SearchScope = Literal["none", "room", "flat"]


class PickStep(Frozen, tag="pick"):
    spec: ClassVar[StepSpec] = StepSpec(moves_base=True, timeout=240.0, retries=2)

    object_id: Id
    object_name: Name
    position: Vec3
    mass: Kilograms
    support_id: Id
    approach: Pose2D
    search: SearchScope | None = None

    def describe(self) -> str:
        return f"picking {self.object_name}"

    def brief(self) -> str:
        return f"pick {self.object_name}"


class PlaceStep(Frozen, tag="place"):
    spec: ClassVar[StepSpec] = StepSpec(moves_base=True, timeout=240.0, retries=2)

    surface_id: Id
    surface_name: Name
    position: Vec3
    approach: Pose2D

    def describe(self) -> str:
        return f"placing on {self.surface_name}"

    def brief(self) -> str:
        return f"place on {self.surface_name}"


class DetectStep(Frozen, tag="detect"):
    # It turns the base round and drives to furniture when the object is not in view (a search).
    spec: ClassVar[StepSpec] = StepSpec(moves_base=True, timeout=240.0, retries=1)

    object_id: Id
    object_name: Name
    search: SearchScope | None = None

    def describe(self) -> str:
        return f"looking for {self.object_name}"

    def brief(self) -> str:
        return f"detect {self.object_name}"


class SayStep(Frozen, tag="say"):
    spec: ClassVar[StepSpec] = StepSpec(moves_base=False, timeout=10.0, retries=0)

    text: Text

    def describe(self) -> str:
        return f"saying: {self.text}"

    def brief(self) -> str:
        return f"say {preview(self.text, 30)!r}"


class WaitStep(Frozen, tag="wait"):
    spec: ClassVar[StepSpec] = StepSpec(moves_base=False, timeout=120.0, retries=0)  # lasts 60 s at most

    duration: Annotated[float, Meta(ge=0.0, le=60.0)]

    def describe(self) -> str:
        return f"waiting {self.duration:g} s"

    def brief(self) -> str:
        return f"wait {self.duration:g} s"


class StopStep(Frozen, tag="stop"):
    spec: ClassVar[StepSpec] = StepSpec(moves_base=False, timeout=10.0, retries=0)

    def describe(self) -> str:
        return "stop"

    def brief(self) -> str:
        return "stop"


class GripperStep(Frozen, tag="gripper"):
    """open_gripper / close_gripper."""

    spec: ClassVar[StepSpec] = StepSpec(moves_base=False, timeout=30.0, retries=0)

    open: bool

    def describe(self) -> str:
        return "opening the gripper" if self.open else "closing the gripper"

    def brief(self) -> str:
        return "open_gripper" if self.open else "close_gripper"


GroundedStep = NavigateStep | PickStep | PlaceStep | DetectStep | SayStep | WaitStep | StopStep | GripperStep
# Every kind of grounded step, in the union's order.
STEP_TYPES: tuple[type[GroundedStep], ...] = get_args(GroundedStep)


class Fallback(Frozen):
    """The parsed plan's `on_failure`: when any of steps first..last (indices into
    GroundedPlan.steps) fails, `steps` run instead and the plan goes on after `last`."""

    first: Annotated[int, Meta(ge=0, lt=MAX_STEPS)]
    last: Annotated[int, Meta(ge=0, lt=MAX_STEPS)]
    steps: Annotated[list[GroundedStep], Meta(min_length=1, max_length=MAX_STEPS)]
    labels: list[Annotated[str, Meta(max_length=64)]] = []


def step_kind(step: GroundedStep | type[GroundedStep]) -> str:
    """The action a grounded step (or a kind of step) performs: its tag."""
    return str(step.__struct_config__.tag)


ResolvedVia = Literal["name", "fuzzy", "attribute", "relation", "context", "pronoun", "coordinates"]


class Resolution(Frozen):
    """What one name in the plan was taken to mean, and how sure the resolver is.

    `via` says what settled it: the name itself, a near-miss of a name ("fuzzy"), a colour or size,
    a spatial relation, the robot's room, a pronoun, or bare coordinates. `confidence` is 1.0 for an
    exact name and the match score (0..1) for a near-miss."""

    label: Annotated[str, Meta(max_length=64)]
    text: Name
    kind: Literal["room", "furniture", "place", "object", "human", "point"]
    name: Name
    id: Id | None = None
    via: ResolvedVia = "name"
    confidence: Annotated[float, Meta(ge=0.0, le=1.0)] = 1.0


class GroundedPlan(Frozen, tag="grounded_plan"):
    """Sub-steps flattened into one list; `labels[i]` names where steps[i] came from ("2", "3.1").

    `warnings` are the resolver's: a near-miss name, coordinates that disagree with the named
    entity, an object not seen for a while. `resolutions` lists every name and what it became."""

    steps: Annotated[list[GroundedStep], Meta(min_length=1, max_length=MAX_STEPS)]
    source: Plan
    labels: list[Annotated[str, Meta(max_length=64)]] = []
    fallbacks: list[Fallback] = []
    warnings: list[Text] = []
    resolutions: list[Resolution] = []


def step_labels(plan: GroundedPlan) -> list[str]:
    """Where each step came from in the parsed plan ("2", "3.1"); step numbers if not given."""
    if len(plan.labels) == len(plan.steps):
        return list(plan.labels)
    return [str(i + 1) for i in range(len(plan.steps))]


def fallback_labels(fallback: Fallback, labels: list[str]) -> list[str]:
    """Labels of a fallback's steps ("2 on_failure 1"); `labels` are the plan's step_labels."""
    if len(fallback.labels) == len(fallback.steps):
        return list(fallback.labels)
    owner = labels[fallback.first] if fallback.first < len(labels) else str(fallback.first + 1)
    return [f"{owner} on_failure {k + 1}" for k in range(len(fallback.steps))]


ResolveReply = GroundedPlan | ServiceError


class PlanApproved(Frozen, tag="approved"):
    """`checks`: what safety checked. `warnings`: what it remembers of the places the plan goes and the
    objects it handles (earlier incidents, caution zones): never a refusal, only something to know."""

    checks: list[Text] = []
    warnings: list[Text] = []


PlanCheckReply = PlanApproved | ServiceError
