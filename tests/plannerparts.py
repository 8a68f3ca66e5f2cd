"""What the planner (services/planner/node.py Planner) touches of a Node, stood in for its unit tests
of the logic around its threads and sends (no Zenoh)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from schemas import keys
from schemas.common import ErrorKind, ServiceError
from schemas.planner import Recovery
from schemas.world import SceneDescription
from services.errors import CallError


class PlannerNode:
    """Publishers keeping what is put, subscriptions taking nothing, the scene answered with `scene`;
    every other query goes to `answer`, which leaves it unanswered unless a test's node answers it."""

    def __init__(self, scene: str) -> None:
        self.scene = scene
        self.published: list[Any] = []

    def publisher(self, topic: Any) -> Any:
        return SimpleNamespace(put=self.published.append)

    def subscribe(self, topic: Any, callback: Any) -> None:
        pass

    def call(self, service: Any, request: Any, timeout: float) -> Any:
        if service is keys.SCENE:
            return SceneDescription(stamp=0.0, text=self.scene)
        return self.answer(service, request, timeout)

    def answer(self, service: Any, request: Any, timeout: float) -> Any:
        name = getattr(service, "path", service)  # a Service, or an action's key name a stand-in executor gives
        raise CallError(ServiceError(kind=ErrorKind.UNAVAILABLE, message=f"no {name} here"))

    def recoveries(self) -> list[Recovery]:
        return [m for m in self.published if isinstance(m, Recovery)]
