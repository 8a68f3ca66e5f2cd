"""Plans: the raw text an LLM wrote, the parsed plan, and the grounded plan with ids and poses."""

from __future__ import annotations

import enum
from typing import Annotated, Literal

from msgspec import Meta

from schemas.common import Frozen, Id, Kilograms, Name, Pose2D, ServiceError, Text, Vec3

# Requests larger than this are refused before any parsing is attempted.
MAX_PLAN_BYTES = 256 * 1024
MAX_STEPS = 100

PlanFormat = Literal["auto", "json", "yaml", "text"]


class Action(enum.StrEnum):
    """Canonical actions. Synonyms live in the parser's vocabulary file, not here."""

    NAVIGATE_TO = "navigate_to"
    PICK = "pick"
    PLACE = "place"
    DETECT = "detect"
    SAY = "say"
    WAIT = "wait"
    STOP = "stop"


class PlanText(Frozen):
    """What an LLM or a person wrote, untouched, with a hint of its format."""

    text: Annotated[str, Meta(max_length=MAX_PLAN_BYTES)]
    format: PlanFormat = "auto"


ParamValue = float | int | bool | str


class Step(Frozen):
    action: Action
    target: Name | None = None
    location: Name | None = None
    params: dict[Annotated[str, Meta(max_length=64)], ParamValue] = {}
    description: Text = ""


class Plan(Frozen, tag="plan"):
    steps: Annotated[list[Step], Meta(min_length=1, max_length=MAX_STEPS)]
    description: Text = ""
    warnings: list[Text] = []


ParseReply = Plan | ServiceError


# Grounded steps: every name replaced by an id and a pose from the world model or perception.


class NavigateStep(Frozen, tag="navigate_to"):
    target: Name
    goal: Pose2D


class PickStep(Frozen, tag="pick"):
    object_id: Id
    object_name: Name
    position: Vec3
    mass: Kilograms
    support_id: Id
    approach: Pose2D


class PlaceStep(Frozen, tag="place"):
    surface_id: Id
    surface_name: Name
    position: Vec3
    approach: Pose2D


class DetectStep(Frozen, tag="detect"):
    object_id: Id
    object_name: Name


class SayStep(Frozen, tag="say"):
    text: Text


class WaitStep(Frozen, tag="wait"):
    duration: Annotated[float, Meta(ge=0.0, le=60.0)]


class StopStep(Frozen, tag="stop"):
    pass


GroundedStep = NavigateStep | PickStep | PlaceStep | DetectStep | SayStep | WaitStep | StopStep


def step_kind(step: GroundedStep) -> str:
    """The action a grounded step performs: its tag."""
    return str(type(step).__struct_config__.tag)


class GroundedPlan(Frozen, tag="grounded_plan"):
    steps: Annotated[list[GroundedStep], Meta(min_length=1, max_length=MAX_STEPS)]
    source: Plan


ResolveReply = GroundedPlan | ServiceError


class PlanApproved(Frozen, tag="approved"):
    checks: list[Text] = []


PlanCheckReply = PlanApproved | ServiceError
