"""Shell completion of the CLI's values: service names, robot backends, plan formats.

Typer calls these with the word being typed (`tether --install-completion` sets the shell up). Light
on purpose: `tether run` (tether.runservice) uses them and must not load rich or the CLI.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import get_args

from schemas.plan import PlanFormat
from services.runtime import ALL_SERVICES, ROBOT_BACKENDS

PLAN_FORMATS: tuple[str, ...] = get_args(PlanFormat)


def starting(values: Iterable[str], incomplete: str) -> list[str]:
    """The values that begin with what was typed, in their order."""
    return [value for value in values if value.startswith(incomplete)]


def complete_service(incomplete: str) -> list[str]:
    """A service name: sim, safety, ..., ros2sim."""
    return starting(ALL_SERVICES, incomplete)


def complete_services(incomplete: str) -> list[str]:
    """A comma-separated list of services (`--only sim,safety`): the names before the last comma stay
    as typed, the last one is completed with a service not named yet."""
    named, comma, last = incomplete.rpartition(",")
    before = [name.strip() for name in named.split(",")] if comma else []
    return [named + comma + name for name in starting(ALL_SERVICES, last.strip()) if name not in before]


def complete_backend(incomplete: str) -> list[str]:
    """A robot backend: sim, ros2, ros2-standin."""
    return starting(ROBOT_BACKENDS, incomplete)


def complete_plan_format(incomplete: str) -> list[str]:
    """A plan's format: auto, json, yaml, text."""
    return starting(PLAN_FORMATS, incomplete)


def one_of(*values: str) -> Callable[[str], list[str]]:
    """Completion of one of `values` (a choice a command spells out itself)."""

    def complete(incomplete: str) -> list[str]:
        return starting(values, incomplete)

    return complete
