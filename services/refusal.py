"""A refusal raised inside a service and sent back as a ServiceError value."""

from __future__ import annotations

from collections.abc import Iterable
from typing import ClassVar

from schemas.common import TEXT_CHARS, ErrorKind, ServiceError, Stage

MAX_MESSAGE_CHARS = TEXT_CHARS


class Refusal(Exception):
    """Carries the ServiceError for the caller. `step` is 0-based; messages say "step N" from 1."""

    stage: ClassVar[Stage]

    def __init__(
        self,
        message: str,
        *,
        kind: ErrorKind = ErrorKind.INVALID_REQUEST,
        step: int | None = None,
        candidates: Iterable[str] = (),
        where: str | None = None,
        line: int | None = None,
        column: int | None = None,
    ) -> None:
        # `where` ("step 2.1", "line 3, column 5") replaces the default "step N" prefix.
        if where is not None:
            message = f"{where}: {message}"
        elif step is not None:
            message = f"step {step + 1}: {message}"
        super().__init__(message)
        self.error = ServiceError(
            kind=kind,
            message=message[:MAX_MESSAGE_CHARS],
            stage=self.stage,
            step=step,
            candidates=list(candidates),
            line=line,
            column=column,
        )
