"""What safety refuses, as exceptions inside the process."""

from __future__ import annotations

from schemas.safety import Rule


class Vetoed(Exception):
    """A command or plan that must not reach the robot: the message says why in words an LLM can
    act on, `rule` names the rule and `values` the measured values and limits it rests on."""

    def __init__(self, message: str, rule: Rule, **values: float) -> None:
        super().__init__(message)
        self.rule = rule
        self.values = values


class Unauthorized(Exception):
    """A reset without a valid operator token."""
