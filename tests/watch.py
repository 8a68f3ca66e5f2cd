"""Collects a topic's messages and waits on conditions over them, with deadlines."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Generic, TypeVar

from schemas.keys import Topic
from services.runtime import Node

T = TypeVar("T")


class Watch(Generic[T]):
    def __init__(self, node: Node, topic: Topic[T]) -> None:
        self.messages: list[T] = []
        self._changed = threading.Condition()
        node.subscribe(topic, self._on_message)

    def _on_message(self, msg: T) -> None:
        with self._changed:
            self.messages.append(msg)
            self._changed.notify_all()

    def wait_for(self, predicate: Callable[[T], bool], timeout: float, after: int = 0) -> T | None:
        """The first message from index `after` on that satisfies `predicate`, waiting up to `timeout`."""
        found: list[T] = []

        def check() -> bool:
            for msg in self.messages[after:]:
                if predicate(msg):
                    found.append(msg)
                    return True
            return False

        with self._changed:
            self._changed.wait_for(check, timeout)
        return found[0] if found else None

    def latest(self, timeout: float) -> T | None:
        return self.wait_for(lambda _: True, timeout, after=max(0, len(self.messages) - 1))

    def __len__(self) -> int:
        return len(self.messages)
