"""Why a plan could not be grounded: each error carries the ServiceError sent back to the caller."""

from __future__ import annotations

from collections.abc import Iterable

from schemas.common import ErrorKind, ServiceError, Stage

MAX_MESSAGE_CHARS = 4000


class ResolveError(Exception):
    """A name in the plan does not pick out one thing, or a step cannot apply to what it names.

    `step` is 0-based; messages say "step N" counting from 1, as a person would.
    """

    def __init__(
        self,
        message: str,
        *,
        kind: ErrorKind = ErrorKind.INVALID_REQUEST,
        step: int | None = None,
        candidates: Iterable[str] = (),
    ) -> None:
        if step is not None:
            message = f"step {step + 1}: {message}"
        super().__init__(message)
        self.error = ServiceError(
            kind=kind,
            message=message[:MAX_MESSAGE_CHARS],
            stage=Stage.RESOLVE,
            step=step,
            candidates=list(candidates),
        )
