"""Opening a session on the loopback stack without Zenoh's half-second wait: which ports listen (read from
the kernel's tables), and over real sessions, a query and a publication sent the moment a session is
open still reach the service, while a key nobody serves still fails as nothing answering."""

from __future__ import annotations

import threading
import uuid
from pathlib import Path

import pytest

from schemas.common import ErrorKind
from schemas.keys import Service, Topic
from schemas.plan import PlanText
from services.errors import CallError
from services.listening import listening_in, listening_ports
from services.runtime import Node, NodeSettings, open_session
from tests.sessions import free_port

WAIT = 5.0
MANY = 200
ECHO: Service[PlanText, PlanText] = Service("test/echo", PlanText, PlanText)
NOBODY: Service[PlanText, PlanText] = Service("test/nobody", PlanText, PlanText)
NEWS: Topic[PlanText] = Topic("test/news", PlanText)

# Two sockets listening (ports 0x1D24 = 7460 on 127.0.0.1, 0x1D25 = 7461 on all addresses), one
# connection established (state 01) whose local port 0x9C40 must not count, and a line cut short.
TCP_TABLE = """\
  sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode
   0: 0100007F:1D24 00000000:0000 0A 00000000:00000000 00:00000000 00000000     0        0 1 1 0 100 0 0 10 0
   1: 00000000:1D25 00000000:0000 0A 00000000:00000000 00:00000000 00000000     0        0 2 1 0 100 0 0 10 0
   2: 0100007F:9C40 0100007F:1D24 01 00000000:00000000 00:00000000 00000000     0        0 3 1 0 20 4 30 10 -1
   3: 0100007F:ZZZZ
"""
TCP6_TABLE = """\
  sl  local_address                         remote_address                        st tx_queue rx_queue
   0: 00000000000000000000000000000000:1D2C 00000000000000000000000000000000:0000 0A 00000000:00000000
"""


def test_the_listening_ports_are_those_in_state_listen() -> None:
    assert listening_in(TCP_TABLE) == {7460, 7461}
    assert listening_in(TCP6_TABLE) == {7468}
    assert listening_in("") == set()


def test_both_tables_are_read_and_none_stands_for_no_tables(tmp_path: Path) -> None:
    (tmp_path / "tcp").write_text(TCP_TABLE)
    (tmp_path / "tcp6").write_text(TCP6_TABLE)
    assert listening_ports((tmp_path / "tcp", tmp_path / "tcp6")) == {7460, 7461, 7468}
    assert listening_ports((tmp_path / "tcp", tmp_path / "missing")) == {7460, 7461}
    assert listening_ports((tmp_path / "missing",)) is None


@pytest.fixture
def settings() -> NodeSettings:
    return NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())


def test_a_session_just_opened_reaches_the_service_with_its_first_query_and_publication(
    settings: NodeSettings,
) -> None:
    heard: list[str] = []
    arrived = threading.Condition()

    def on_news(message: PlanText) -> None:
        with arrived:
            heard.append(message.text)
            arrived.notify_all()

    with Node("sim", settings) as server:
        # Many declarations before the ones used: the new session hears of them all after its link is up.
        for n in range(MANY):
            server.subscribe_raw(f"{settings.robot}/test/other/{n}", lambda key, payload: None)
        server.serve(ECHO, lambda request: PlanText(text=f"echo {request.text}"))
        server.subscribe(NEWS, on_news)
        server.declare_alive()
        for attempt in range(8):
            with Node("cli", settings) as client:
                assert client.call(ECHO, PlanText(text=str(attempt)), timeout=WAIT).text == f"echo {attempt}"
                client.publish(NEWS, PlanText(text=str(attempt)))
                with arrived:
                    assert arrived.wait_for(lambda text=str(attempt): text in heard, timeout=WAIT), heard


def test_a_key_nobody_serves_still_fails_as_nothing_answering(settings: NodeSettings) -> None:
    with Node("sim", settings), Node("cli", settings) as client, pytest.raises(CallError) as failed:
        client.call(NOBODY, PlanText(text="anyone?"), timeout=WAIT)
    assert failed.value.error.kind is ErrorKind.UNAVAILABLE
    assert "nothing answered" in failed.value.error.message


def test_a_session_from_a_config_file_opens_as_zenoh_opens_it(tmp_path: Path) -> None:
    config = tmp_path / "zenoh.json5"
    config.write_text('{mode: "peer", listen: {endpoints: []}, scouting: {multicast: {enabled: false}}}')
    session, discovering_until = open_session(NodeSettings(zenoh_config=config), None)
    session.close()
    assert discovering_until == 0.0


def test_a_node_closes_while_another_thread_publishes_on_it(settings: NodeSettings) -> None:
    """zenoh refuses to undeclare a publisher another thread is putting on ("Already borrowed"): the
    node's close goes on, and the session's close takes it down. What the thread publishes after the
    close is dropped (zenoh: "Undeclared publisher", "session closed"), not raised on it."""
    node = Node("test", settings)
    publisher = node.publisher(NEWS)
    sent = threading.Semaphore(0)
    done = threading.Event()
    errors: list[BaseException] = []

    def publish() -> None:
        while not done.is_set():
            try:
                publisher.put(PlanText(text="news"))
            except BaseException as exc:
                errors.append(exc)
                return
            sent.release()

    thread = threading.Thread(target=publish, daemon=True)
    thread.start()
    try:
        assert sent.acquire(timeout=WAIT), "nothing was published"
        node.close()
        while sent.acquire(blocking=False):  # the puts counted before the close
            pass
        for _ in range(MANY):  # puts after the close, each dropped
            assert sent.acquire(timeout=WAIT), f"the publishing thread stopped: {errors}"
    finally:
        done.set()
        thread.join(WAIT)
        node.close()  # again, if the test failed before it: a second close does nothing
    assert not errors and not thread.is_alive()
