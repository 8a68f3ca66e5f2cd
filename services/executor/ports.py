"""What the executor's logic needs from the outside, as protocols: the node implements them."""

from __future__ import annotations

import threading
from typing import Any, Protocol

from schemas.actions import ResultResponse
from schemas.common import Pose2D
from schemas.plan import GroundedPlan, ParseReply, Plan, PlanCheckReply, ResolveReply
from schemas.robot import FollowJointTrajectoryGoal, GripperCommandGoal, NavigateToPoseGoal, Twist
from schemas.world import PerceivedObject


class PlanServices(Protocol):
    """The planner-side services. Each may raise services.errors.CallError when unreachable."""

    def parse(self, text: str, fmt: str) -> ParseReply: ...
    def resolve(self, plan: Plan) -> ResolveReply: ...
    def check(self, plan: GroundedPlan) -> PlanCheckReply: ...


class Robot(Protocol):
    """The robot as seen through safety: goals are checked there and may be rejected."""

    def navigate(self, goal: NavigateToPoseGoal, cancel: threading.Event) -> ResultResponse[Any]: ...
    def trajectory(self, goal: FollowJointTrajectoryGoal, cancel: threading.Event) -> ResultResponse[Any]: ...
    def gripper(self, goal: GripperCommandGoal, cancel: threading.Event) -> ResultResponse[Any]: ...
    def cmd_vel(self, twist: Twist) -> None: ...
    def base_pose(self) -> Pose2D | None: ...
    def arm_positions(self) -> list[float] | None: ...
    def held_object(self) -> str | None:
        """The id of what perception last saw in the gripper, if anything."""
        ...

    def look(self, timeout: float, *, new: bool = False) -> list[PerceivedObject] | None:
        """Every object perception reports (in view, or in the gripper) in its latest report made
        after the last motion ended (and received lately: a stopped perception's last report is not
        what is there now), or with `new` in its next report from now on, waiting up to `timeout`
        for one; None if none comes."""
        ...

    def safety_stop(self) -> str | None:
        """Why safety holds the robot still right now (e-stop latched, no heartbeat), or None."""
        ...

    def speed_scale(self) -> float:
        """The fraction of full speed safety allows now (0 while paused for a person or stopped)."""
        ...

    def people(self) -> list[Pose2D]:
        """Where the people perception reports stand now."""
        ...

    def remembered(self, object_id: str) -> PerceivedObject | None:
        """Where the object was last seen (the resolver's memory), or None if it was never seen."""
        ...
