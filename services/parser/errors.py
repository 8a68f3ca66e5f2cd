"""Why a plan text was refused: each error carries the ServiceError sent back to the caller."""

from __future__ import annotations

from collections.abc import Iterable

from schemas.common import ErrorKind, ServiceError, Stage

MAX_MESSAGE_CHARS = 4000


class ParseError(Exception):
    """The text is not a plan we can run; the message names what was wrong and where.

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
            stage=Stage.PARSE,
            step=step,
            candidates=list(candidates),
        )


class VocabularyError(Exception):
    """The vocabulary file is missing, malformed or contradicts itself; the message names the file."""
