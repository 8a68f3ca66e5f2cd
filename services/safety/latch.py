"""The e-stop latch: anyone may set it; only a valid operator token clears it."""

from __future__ import annotations

import threading
import time

from schemas.safety import EstopState
from services.safety.errors import Unauthorized
from services.safety.operator import token_matches


class EstopLatch:
    def __init__(self, operator_token: str) -> None:
        self._token = operator_token
        self._state = EstopState(latched=False)
        self._lock = threading.Lock()

    @property
    def state(self) -> EstopState:
        with self._lock:
            return self._state

    def trigger(self, source: str, reason: str) -> bool:
        """Latch; returns True if this call latched it (False if it already was)."""
        with self._lock:
            if self._state.latched:
                return False
            self._state = EstopState(latched=True, source=source, reason=reason, stamp=time.time())
            return True

    def reset(self, operator: str, token: str) -> EstopState:
        with self._lock:
            if not token_matches(self._token, token):
                raise Unauthorized(f"reset refused for '{operator}': not the operator's token")
            self._state = EstopState(latched=False, source=operator, reason="reset by operator", stamp=time.time())
            return self._state
