"""What safety refuses, as exceptions inside the process."""


class Vetoed(Exception):
    """A command or plan that must not reach the robot; the message says why."""


class Unauthorized(Exception):
    """A reset without a valid operator token."""
