"""Why a plan could not be grounded."""

from __future__ import annotations

from schemas.common import Stage
from services.refusal import Refusal


class ResolveError(Refusal):
    """A name in the plan does not pick out one thing, or a step cannot apply to what it names."""

    stage = Stage.RESOLVE
