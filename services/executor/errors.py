"""What can go wrong while executing a plan, as exceptions inside the executor, each of a FailureKind."""

from schemas.executor import FailureKind


class ExecutionError(Exception):
    """A step could not be carried out; the message says which and why."""

    kind = FailureKind.EXECUTION


class PlanningFailed(ExecutionError):
    """No motion was found: no collision-free path for the base or the arm, no grasp that reaches.
    The message says what was asked and why it cannot be done."""

    kind = FailureKind.PLANNING


class IKFailed(PlanningFailed):
    """The arm cannot reach a target; the message names the target and the residual."""


class PreconditionFailed(ExecutionError):
    """A step's precondition does not hold (placing with an empty gripper, say)."""

    kind = FailureKind.PRECONDITION


class PostconditionFailed(ExecutionError):
    """The motions went through but the world is not as the step promised."""

    kind = FailureKind.POSTCONDITION


class Canceled(ExecutionError):
    """The goal was canceled while the step ran."""

    kind = FailureKind.CANCELED


class CommandVetoed(ExecutionError):
    """Safety, or the robot behind it, refused a goal. No on_failure alternative runs after this."""

    kind = FailureKind.VETOED


class Interrupted(ExecutionError):
    """A goal was ended by someone other than this executor (safety on an e-stop). No on_failure
    alternative runs after this."""

    kind = FailureKind.VETOED


class MotionNotStopped(ExecutionError):
    """A motion went on past its cancel's grace (the robot ignored it, or never answered): it may
    still be moving the robot, so the executor latched the e-stop. No retry, no on_failure, and a
    canceled plan fails with this rather than ending canceled as if the robot had stopped."""


class GraspFailed(PostconditionFailed):
    """The gripper closed and the object was not in it: reported to safety's incident memory as a
    grasp_failed incident (services/executor/README.md, Keys: safety/incidents/report)."""

    def __init__(self, message: str, object_name: str) -> None:
        super().__init__(message)
        self.object_name = object_name
