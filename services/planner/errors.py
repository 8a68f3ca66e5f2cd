"""What goes wrong in the planner, each named for what it is."""

from __future__ import annotations


class LLMError(Exception):
    """The model's endpoint failed or misbehaved: HTTP error, timeout, not JSON, no choices, a refusal.
    The message names what was wrong and never holds the API key."""


class NotConfigured(Exception):
    """No endpoint is configured; the message says how to configure one."""


class ExecutorUnreachable(Exception):
    """No executor answered a dry run or the real send."""
