"""Queries served on kept worker threads, over two real Zenoh sessions in one process: a slow handler
beside quick ones, a full pool answered busy, work after the reply, requests a test of theirs keeps on
Zenoh's callback thread, traces of it all."""

from __future__ import annotations

import functools
import logging
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import pytest

from schemas import keys
from schemas.common import ErrorKind, ServiceError
from schemas.keys import Service, Topic
from schemas.plan import PlanText
from schemas.trace import TraceRecord
from services.errors import CallError
from services.querypool import QueryPool
from services.runtime import Node, NodeSettings, decoder, encode
from tests.sessions import free_port

WAIT = 5.0
QUICK: Service[PlanText, PlanText] = Service("test/quick", PlanText, PlanText)
SLOW: Service[PlanText, PlanText] = Service("test/slow", PlanText, PlanText)
RESULT: Service[PlanText, PlanText] = Service("test/result", PlanText, PlanText)
SECRET: Service[PlanText, PlanText] = Service("test/secret", PlanText, PlanText, redact=("text",))
# Answered where its request's text says: "here" on Zenoh's callback thread, anything else on a worker;
# "undecided" makes the test itself fail. It replies with the name of the thread that answered.
CHOOSY: Service[PlanText, PlanText] = Service("test/choosy", PlanText, PlanText)
HELLO = PlanText(text="hello")
HERE, THERE, UNDECIDED = PlanText(text="here"), PlanText(text="there"), PlanText(text="undecided")
WORKERS = ("q:test-", "w:test-")


def answered_here(request: PlanText) -> bool:
    if request.text == UNDECIDED.text:
        raise ValueError("cannot tell where")
    return request.text == HERE.text


def answering_thread(_request: PlanText) -> PlanText:
    return PlanText(text=threading.current_thread().name)


def wait_until(condition: Callable[[], bool], what: str) -> None:
    """Poll `condition` (a pool's count, which nothing announces) until it holds, for at most WAIT."""
    deadline = time.monotonic() + WAIT
    while not condition():
        assert time.monotonic() < deadline, f"{what} not within {WAIT} s"
        time.sleep(0.002)  # polling, with the deadline above


@dataclass
class Gate:
    """Handlers that block until released, counting how many are inside."""

    release: threading.Event = field(default_factory=threading.Event)
    inside: int = 0
    changed: threading.Condition = field(default_factory=threading.Condition)

    def handler(self, request: PlanText) -> PlanText:
        with self.changed:
            self.inside += 1
            self.changed.notify_all()
        assert self.release.wait(WAIT), "never released"
        return request

    def reset(self) -> None:
        self.release.set()
        self.release = threading.Event()
        self.inside = 0

    def wait_inside(self, count: int) -> None:
        with self.changed:
            assert self.changed.wait_for(lambda: self.inside >= count, WAIT), f"{self.inside} of {count} inside"


@dataclass
class After:
    """What runs after a reply: it records what it was given, then blocks until released."""

    started: threading.Event = field(default_factory=threading.Event)
    release: threading.Event = field(default_factory=threading.Event)
    seen: list[tuple[PlanText, PlanText]] = field(default_factory=list)

    def __call__(self, request: PlanText, reply: PlanText) -> None:
        self.seen.append((request, reply))
        self.started.set()
        # Longer than a call waits: run before the reply, this would make the call fail.
        assert self.release.wait(2 * WAIT), "never released"

    def reset(self) -> None:
        self.release.set()
        self.release = threading.Event()
        self.started = threading.Event()
        self.seen.clear()


@dataclass
class Rig:
    server: Node
    client: Node
    slow: Gate
    results: Gate
    after: After
    traces: list[TraceRecord]
    traced: threading.Condition
    callers: ThreadPoolExecutor

    def call_later(self, service: Service[PlanText, PlanText]) -> Future[PlanText]:
        return self.callers.submit(self.client.call, service, HELLO, timeout=WAIT)

    def wait_traced(self, path: str, error: str, query: bytes = b"") -> TraceRecord:
        def found() -> TraceRecord | None:
            return next(
                (t for t in self.traces if t.key == path and error in t.error and query in bytes(t.query)), None
            )

        with self.traced:
            assert self.traced.wait_for(lambda: found() is not None, WAIT), [t.error for t in self.traces]
        record = found()
        assert record is not None
        return record


@pytest.fixture(scope="module")
def stack() -> Iterator[Rig]:
    """One server and one client for the module's tests, with small pools, so that a few queries fill them."""
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    slow, results, after = Gate(), Gate(), After()
    traces: list[TraceRecord] = []
    traced = threading.Condition()

    def on_trace(record: TraceRecord) -> None:
        with traced:
            traces.append(record)
            traced.notify_all()

    with (
        Node("sim", settings) as server,
        Node("executor", settings) as client,
        ThreadPoolExecutor(8, thread_name_prefix="caller") as callers,
    ):
        try:
            server.queries = QueryPool("q:test", workers=2, backlog=1)
            server.waiting_queries = QueryPool("w:test", workers=1)
            server.serve(QUICK, lambda request: request)
            server.serve(SLOW, slow.handler)
            server.serve(RESULT, results.handler, waits=True)
            server.serve(SECRET, lambda request: PlanText(text=request.text.upper()), after=after)
            server.serve(CHOOSY, answering_thread, inline=answered_here)
            client.subscribe(Topic("_trace/sim/**", TraceRecord), on_trace)
            server.declare_alive()
            assert not client.wait_alive(["sim"], WAIT)
            # The trace subscription is matched once a quick query's trace comes back.
            assert client.call(QUICK, HELLO, timeout=WAIT) == HELLO
            rig = Rig(server, client, slow, results, after, traces, traced, callers)
            rig.wait_traced(QUICK.path, "")
            yield rig
        finally:
            for each in (slow, results, after):
                each.release.set()


@pytest.fixture
def rig(stack: Rig) -> Iterator[Rig]:
    """The module's stack with its handlers reset, and its pools idle again afterwards."""
    for each in (stack.slow, stack.results, stack.after):
        each.reset()
    try:
        yield stack
    finally:
        for each in (stack.slow, stack.results, stack.after):
            each.release.set()
    wait_until(lambda: stack.server.queries.load() == "0 of 2 workers busy, 0 of 1 waiting", "the pool idle")
    wait_until(lambda: stack.server.waiting_queries.load().startswith("0 of 1"), "the waiting pool idle")


def test_a_blocked_handler_holds_up_neither_quick_queries_nor_zenoh(rig: Rig) -> None:
    slow = rig.call_later(SLOW)
    result = rig.call_later(RESULT)
    rig.slow.wait_inside(1)
    rig.results.wait_inside(1)
    for _ in range(20):
        assert rig.client.call(QUICK, HELLO, timeout=WAIT) == HELLO
    assert not slow.done() and not result.done()
    rig.slow.release.set()
    rig.results.release.set()
    assert slow.result(WAIT) == HELLO
    assert result.result(WAIT) == HELLO


@pytest.mark.realtime  # busy within WAIT/2 of wall time: at normal priority, not beside the rest (tests/suite.py)
def test_a_full_pool_answers_busy_at_once_and_runs_what_it_queued(rig: Rig) -> None:
    running = [rig.call_later(SLOW) for _ in range(2)]
    rig.slow.wait_inside(2)
    queued = rig.call_later(SLOW)
    full = "2 of 2 workers busy, 1 of 1 waiting"
    wait_until(lambda: rig.server.queries.load() == full, "the third slow query queued")
    started = time.monotonic()
    with pytest.raises(CallError) as refused:
        rig.client.call(QUICK, HELLO, timeout=WAIT)
    assert time.monotonic() - started < WAIT / 2, "busy was not answered at once"
    error = refused.value.error
    assert error.kind is ErrorKind.UNAVAILABLE
    assert error.message == f"sim is too busy to answer test/quick ({full}); try again"
    assert rig.wait_traced(QUICK.path, "too busy").error.startswith(error.message)
    # Queries that wait as long as a goal runs have a pool of their own: one runs, the next is busy.
    result = rig.call_later(RESULT)
    rig.results.wait_inside(1)
    with pytest.raises(CallError, match="too busy to answer test/result"):
        rig.client.call(RESULT, HELLO, timeout=WAIT)
    rig.slow.release.set()
    rig.results.release.set()
    assert [call.result(WAIT) for call in [*running, queued, result]] == [HELLO] * 4
    assert rig.slow.inside == 3
    assert rig.client.call(QUICK, HELLO, timeout=WAIT) == HELLO


def test_work_after_the_reply_does_not_delay_it_and_is_traced(rig: Rig) -> None:
    assert rig.client.call(SECRET, HELLO, timeout=WAIT) == PlanText(text="HELLO")
    # The reply came while what follows it is still blocked.
    assert rig.after.started.wait(WAIT)
    assert rig.after.seen == [(HELLO, PlanText(text="HELLO"))]
    rig.after.release.set()
    record = rig.wait_traced(SECRET.path, "")
    # The request as it came, but for the redacted field; the reply as it went.
    assert bytes(record.query) == b'{"text":"(redacted)","format":"auto"}'
    assert bytes(record.reply) == b'{"text":"HELLO","format":"auto"}'


def fill_the_pool(rig: Rig) -> list[Future[PlanText]]:
    """Both workers blocked in the slow handler and a third slow query queued behind them."""
    slow = [rig.call_later(SLOW) for _ in range(3)]
    rig.slow.wait_inside(2)
    wait_until(lambda: rig.server.queries.load() == "2 of 2 workers busy, 1 of 1 waiting", "the pool full")
    return slow


def test_a_request_its_test_keeps_here_is_answered_on_zenohs_thread_with_every_worker_taken(rig: Rig) -> None:
    slow = fill_the_pool(rig)
    # Answered although no worker could have: on the thread Zenoh called back on.
    thread = rig.client.call(CHOOSY, HERE, timeout=WAIT).text
    assert not thread.startswith(WORKERS) and not thread.startswith("caller"), thread
    assert bytes(rig.wait_traced(CHOOSY.path, "", b'"here"').reply) == encode(PlanText(text=thread))
    # Not decodable: refused there and then too, with what was wrong.
    replies = list(rig.client.session.get(CHOOSY.key(rig.server.robot), payload=b'{"text": 7}', timeout=WAIT))
    assert len(replies) == 1 and replies[0].err is not None
    error = decoder(ServiceError).decode(replies[0].err.payload.to_bytes())
    assert error.kind is ErrorKind.INVALID_REQUEST and error.message.startswith("invalid request for test/choosy")
    # One its test sends to a worker, or whose test fails, finds none: answered busy at once, not dropped.
    for request in (THERE, UNDECIDED):
        with pytest.raises(CallError, match="too busy to answer test/choosy") as refused:
            rig.client.call(CHOOSY, request, timeout=WAIT)
        assert refused.value.error.kind is ErrorKind.UNAVAILABLE
    rig.slow.release.set()
    assert [call.result(WAIT) for call in slow] == [HELLO] * 3


def test_a_request_its_test_sends_away_or_fails_on_is_answered_by_a_worker(
    rig: Rig, caplog: pytest.LogCaptureFixture
) -> None:
    assert rig.client.call(CHOOSY, THERE, timeout=WAIT).text.startswith("q:test-")
    with caplog.at_level(logging.ERROR, logger="services.runtime"):
        # The test raising loses nothing: the request is answered, by a worker, and traced like any other.
        assert rig.client.call(CHOOSY, UNDECIDED, timeout=WAIT).text.startswith("q:test-")
    failed = [r for r in caplog.records if r.getMessage().startswith("deciding where to answer")]
    assert len(failed) == 1 and failed[0].exc_info is not None
    assert failed[0].getMessage().endswith("/test/choosy failed; answered on a worker")
    assert str(failed[0].exc_info[1]) == "cannot tell where"
    record = rig.wait_traced(CHOOSY.path, "", b'"undecided"')
    assert bytes(record.reply).startswith(b'{"text":"q:test-')


def test_a_pool_starts_no_more_threads_than_its_workers_and_refuses_past_its_backlog() -> None:
    pool = QueryPool("bounded", workers=3, backlog=2)
    release = threading.Event()
    started = threading.Semaphore(0)
    ran: list[int] = []

    def task(i: int) -> None:
        started.release()
        release.wait(WAIT)
        ran.append(i)

    try:
        assert all(pool.submit(functools.partial(task, i)) for i in range(5))
        for _ in range(3):
            assert started.acquire(timeout=WAIT)
        assert not pool.submit(functools.partial(task, 99))
        assert len([t for t in threading.enumerate() if t.name.startswith("bounded-")]) == 3
        assert pool.load() == "3 of 3 workers busy, 2 of 2 waiting"
    finally:
        release.set()
    wait_until(lambda: len(ran) == 5, "the tasks run")
    assert sorted(ran) == [0, 1, 2, 3, 4]
    assert pool.load() == "0 of 3 workers busy, 0 of 2 waiting"
    with pytest.raises(ValueError, match="needs workers >= 1"):
        QueryPool("none", workers=0)


def test_a_call_cut_by_its_own_session_closing_says_so_not_that_nothing_serves_the_key() -> None:
    """It said "nothing answered it within 0.31 s (is it running?)" of a service that was running and
    still working on it: the caller's own session had closed."""
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    slow = Gate()
    with Node("sim", settings) as server, ThreadPoolExecutor(1) as callers:
        client = Node("executor", settings)
        try:
            server.serve(SLOW, slow.handler)
            server.declare_alive()
            assert not client.wait_alive(["sim"], WAIT)
            cut = callers.submit(client.call, SLOW, HELLO, timeout=WAIT)
            slow.wait_inside(1)
            client.close()
            with pytest.raises(CallError) as raised:
                cut.result(WAIT)
        finally:
            slow.release.set()
            client.close()
    message = raised.value.error.message
    assert "session closed" in message and "is it running" not in message, message


def test_a_service_whose_token_is_heard_after_the_question_is_alive() -> None:
    """`tether world scene` said "no resolver reachable" of a running resolver: its session, opened a
    moment before on a loaded machine, had not heard the resolver's token when it asked, once (a
    liveliness get). Asked with is_alive, a token heard within the timeout counts."""
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    with Node("resolver", settings) as resolver, Node("cli", settings) as cli:
        resolver.declare_alive()
        assert not cli.wait_alive(["resolver"], WAIT)
        tokens: list[Any] = []
        declaring = threading.Event()

        def declare() -> None:
            # Set first: the token can reach `cli` before declare_token returns here (a CI run saw
            # is_alive answer while this thread had yet to append the token).
            declaring.set()
            tokens.append(resolver.session.liveliness().declare_token(keys.alive_key(settings.robot, "sim")))

        late = threading.Timer(0.3, declare)
        late.start()
        try:
            assert cli.is_alive("sim", WAIT)
            assert declaring.is_set(), "alive before its token was declared"
        finally:
            late.cancel()
