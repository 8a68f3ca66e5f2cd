"""The parser as a real process: every query gets exactly one reply, a Plan or a ServiceError, also under load."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import msgspec
import pytest

from schemas import keys
from schemas.common import ServiceError, Stage
from schemas.plan import Coordinates, ParseReply, Plan, PlanText
from tests.integration.conftest import Stack, start_stack, stop_stack
from tests.unit.test_parser_properties import SEEDS, billion_laughs

REPLY_TIMEOUT = 10.0
HOSTILE = [
    billion_laughs(9, 9),
    "plan: &p\n  - action: wait\n    substeps: *p\n",
    "[" * 100_000 + "]" * 100_000,
    '{"plan": [{"action": "wait", "parameters": {"duration": ' + "1" * 5000 + "}}]}",
    json.dumps({"plan": [{"action": "x" * 100_000}]}),
    "```json\n{}\n```\n" * 5000,
    "\ud800 lone surrogate",
    "\x00",
]


@pytest.fixture(scope="module")
def parser_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    stack = start_stack(tmp_path_factory.mktemp("parser"), realtime_factor=1.0, services=("parser",))
    try:
        yield stack
    finally:
        stop_stack(stack)


def ask(stack: Stack, payload: bytes) -> ParseReply:
    """One plan/parse query as raw bytes; exactly one reply, decoded as the wire says it is."""
    started = time.monotonic()
    replies = list(stack.node.session.get(keys.PLAN_PARSE.key(stack.settings.robot), payload=payload, timeout=30))
    assert len(replies) == 1, f"{len(replies)} replies; expected exactly one"
    assert time.monotonic() - started < REPLY_TIMEOUT
    reply = replies[0]
    if reply.ok is not None:
        return msgspec.json.decode(reply.ok.payload.to_bytes(), type=ParseReply)  # type: ignore[no-any-return]
    assert reply.err is not None
    return msgspec.json.decode(reply.err.payload.to_bytes(), type=ServiceError)


def encode_request(text: str, fmt: str) -> bytes:
    # Lone surrogates cannot be UTF-8: send what a careless client would, with them replaced.
    return msgspec.json.encode({"text": text.encode("utf-8", "replace").decode("utf-8"), "format": fmt})


@pytest.mark.parametrize("fmt", ["auto", "json", "yaml", "text"])
def test_hostile_texts_get_one_reply_each(parser_stack: Stack, fmt: str) -> None:
    for text in HOSTILE:
        reply = ask(parser_stack, encode_request(text, fmt))
        assert isinstance(reply, ServiceError), f"{text[:40]!r} was parsed into {reply}"
        assert reply.message.strip() and len(reply.message) <= 4000
        assert reply.stage is Stage.PARSE


def test_concurrent_queries_each_get_their_own_reply(parser_stack: Stack) -> None:
    good = encode_request(SEEDS["json object"][0], "json")
    bad = encode_request("no plan here", "auto")
    with ThreadPoolExecutor(max_workers=16) as pool:
        replies = list(pool.map(lambda i: ask(parser_stack, good if i % 2 == 0 else bad), range(64)))
    assert all(isinstance(r, Plan) for r in replies[0::2])
    assert all(isinstance(r, ServiceError) for r in replies[1::2])
    assert not parser_stack.supervisor.exited(), "the parser exited while serving"
    # Still serving after the burst, through the typed client.
    assert isinstance(parser_stack.node.call(keys.PLAN_PARSE, PlanText(text=SEEDS["json array"][0])), Plan)


def test_coordinates_cross_the_wire_and_malformed_ones_are_refused(parser_stack: Stack) -> None:
    text = json.dumps([{"action": "navigate_to", "x": 3.5, "y": 2.0}, {"action": "look_at", "point": "1, 2, 1.2"}])
    reply = ask(parser_stack, encode_request(text, "auto"))
    assert isinstance(reply, Plan)
    assert [(s.target, s.coordinates) for s in reply.steps] == [
        (None, Coordinates(x=3.5, y=2.0)),
        (None, Coordinates(x=1.0, y=2.0, z=1.2)),
    ]
    refused = ask(parser_stack, encode_request('[{"action": "navigate_to", "position": [1, 2, 3, 4, 5]}]', "auto"))
    assert isinstance(refused, ServiceError) and refused.stage is Stage.PARSE
    assert "'position' must be 2 or 3 numbers" in refused.message and refused.step == 0
