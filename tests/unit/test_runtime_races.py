"""The serving machinery as a node closes under it: handlers still running, their replies and traces."""

from __future__ import annotations

import gc
import threading
import time
import uuid
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import pytest

from schemas.keys import Service
from schemas.plan import PlanText
from services.errors import CallError
from services.querypool import QueryPool
from services.runtime import Node, NodeSettings, prepare_types
from tests.sessions import free_port

WAIT = 5.0
SLOW: Service[PlanText, PlanText] = Service("test/slow", PlanText, PlanText)


def wait_until(condition: Callable[[], bool], what: str) -> None:
    """Poll `condition` (a pool's count, which nothing announces) until it holds, for at most WAIT."""
    deadline = time.monotonic() + WAIT
    while not condition():
        assert time.monotonic() < deadline, f"{what} not within {WAIT} s"
        time.sleep(0.002)  # polling, with the deadline above


@pytest.mark.parametrize("raises", [False, True], ids=["returns", "raises"])
def test_a_handler_still_running_when_its_node_closes_ends_quietly(
    caplog: pytest.LogCaptureFixture, raises: bool
) -> None:
    """The first query of a path, its handler still running as the node closed (a get_result waiting
    for its goal at shutdown): declaring its trace's publisher on the closed session raised, logged
    at ERROR with a traceback as a failed task of the pool."""
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    inside, release = threading.Event(), threading.Event()

    def handler(request: PlanText) -> PlanText:
        inside.set()
        assert release.wait(WAIT), "never released"
        if raises:
            raise ValueError("gone wrong")
        return request

    server = Node("sim", settings)
    try:
        server.queries = QueryPool("q:test", workers=1)
        server.serve(SLOW, handler)
        with Node("executor", settings) as client, ThreadPoolExecutor(1) as callers:
            call = callers.submit(client.call, SLOW, PlanText(text="hello"), timeout=WAIT)
            assert inside.wait(WAIT), "the handler never ran"
            server.close()
            release.set()
            wait_until(lambda: server.queries.busy == 0, "the handler's task done")
            with pytest.raises(CallError):
                call.result(WAIT)
    finally:
        release.set()
        if not server.closed:
            server.close()
    failed = [r.getMessage() for r in caplog.records if r.name == "services.querypool"]
    assert failed == []


def test_a_worker_that_cannot_be_started_is_not_counted_and_the_query_is_answered_busy(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The system out of threads for a moment: submit raised into Zenoh's callback (no reply at all),
    and the pool counted the worker it never started, so a pool of one never started another and
    ran nothing again."""
    pool = QueryPool("starved", workers=1)
    ran = threading.Event()

    def no_thread(_thread: threading.Thread) -> None:
        raise RuntimeError("can't start new thread")

    with monkeypatch.context() as patched:
        patched.setattr(threading.Thread, "start", no_thread)
        assert not pool.submit(lambda: None)
    assert pool.load() == "0 of 1 workers busy, 0 of 0 waiting"
    assert "workers not started on query pool starved: can't start new thread" in caplog.messages
    assert pool.submit(ran.set)
    assert ran.wait(WAIT), "the task never ran"


def test_a_task_that_raises_systemexit_leaves_its_pool_serving(caplog: pytest.LogCaptureFixture) -> None:
    """A task ending in a BaseException (SystemExit, from a library's sys.exit) ended its worker's
    thread, still counted idle: a pool of one queued every later task for a worker that was gone."""
    pool = QueryPool("exiting", workers=1)
    ran = threading.Event()

    def exits() -> None:
        raise SystemExit(3)

    assert pool.submit(exits)
    wait_until(lambda: pool.load() == "0 of 1 workers busy, 0 of 0 waiting", "the task done")
    assert pool.submit(ran.set)
    assert ran.wait(WAIT), "the task after it never ran"
    wait_until(lambda: pool.busy == 0, "the pool idle")
    assert pool.load() == "0 of 1 workers busy, 0 of 0 waiting"
    assert "a task of query pool exiting failed" in caplog.messages


def test_a_struct_type_left_by_an_import_cut_short_does_not_stop_the_types_being_prepared() -> None:
    """A Ctrl-C in `tether send --recover` landed in a lazy import: the half-imported module's struct
    type names what the module never got to define, and prepare_types (every Node opening) raised
    NameError, so the cancel the Ctrl-C asked for crashed the command, no JSON printed."""
    half_imported: dict[str, Any] = {"__name__": "cut_short"}
    exec(
        "from __future__ import annotations\nimport msgspec\nclass Cut(msgspec.Struct):\n    kind: NeverDefined\n",
        half_imported,
    )
    try:
        prepare_types()
    finally:
        del half_imported["Cut"]
        gc.collect()  # Struct.__subclasses__ holds it weakly: gone for the tests after this one


def test_what_follows_a_reply_does_not_run_when_the_reply_could_not_be_encoded() -> None:
    """A handler's value that does not encode is answered with an internal error, yet `after` ran as if
    the reply had gone: an action's send_goal would start a goal its asker was told had failed."""
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    followed: list[tuple[PlanText, PlanText]] = []
    with Node("sim", settings) as server, Node("executor", settings) as client:
        server.serve(SLOW, lambda _request: PlanText(text=object()), after=lambda q, a: followed.append((q, a)))  # type: ignore[arg-type]
        with pytest.raises(CallError, match="test/slow failed: Encoding objects of type object is unsupported"):
            client.call(SLOW, PlanText(text="hello"), timeout=WAIT)
        wait_until(lambda: server.queries.busy == 0, "the handler's task done")
    assert followed == []
