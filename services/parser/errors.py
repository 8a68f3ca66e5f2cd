"""Why a plan text was refused."""

from __future__ import annotations

from schemas.common import Stage
from services.refusal import Refusal


class ParseError(Refusal):
    """The text is not a plan we can run; the message names what was wrong and where."""

    stage = Stage.PARSE


class VocabularyError(Exception):
    """The vocabulary file is missing, malformed or contradicts itself; the message names the file."""
