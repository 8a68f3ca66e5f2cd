"""What can go wrong while executing a plan, as exceptions inside the executor."""


class ExecutionError(Exception):
    """A step could not be carried out; the message says which and why."""


class IKFailed(ExecutionError):
    """The arm cannot reach a target; the message names the target and the residual."""


class PreconditionFailed(ExecutionError):
    """A step's precondition does not hold (placing with an empty gripper, say)."""


class PostconditionFailed(ExecutionError):
    """The motions went through but the world is not as the step promised."""


class Canceled(ExecutionError):
    """The goal was canceled while the step ran."""


class Vetoed(ExecutionError):
    """Safety, or the robot behind it, refused a goal. No on_failure alternative runs after this."""


class Interrupted(ExecutionError):
    """A goal was ended by someone other than this executor (safety on an e-stop). No on_failure
    alternative runs after this."""
