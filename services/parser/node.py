"""The parser on the wire: PlanText on plan/parse, answered with a Plan or a ServiceError."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from schemas import keys
from schemas.common import ServiceError
from schemas.plan import MAX_PLAN_BYTES, ParseReply, PlanText
from services.parser.config import ParserConfig
from services.parser.parser import Parser, answer
from services.parser.text import load_grammar
from services.parser.vocabulary import load_vocabulary
from services.runtime import Node

log = logging.getLogger(__name__)


def build_parser(config: ParserConfig) -> Parser:
    vocabulary = load_vocabulary(Path(config.vocabulary) if config.vocabulary else None)
    grammar = load_grammar(Path(config.grammar) if config.grammar else None)
    return Parser(vocabulary, grammar, config=config)


def handler(parser: Parser) -> Callable[[PlanText], ParseReply]:
    """A handler that always answers: a Plan, or a ServiceError saying what was wrong."""

    def handle(request: PlanText) -> ParseReply:
        return answer(parser, request)

    return handle


def logged(_request: PlanText, reply: ParseReply) -> None:
    """The log line of one answer, written once it has gone: formatting and writing it took a fifth
    of a plan/parse's time in the service when written before the reply."""
    if isinstance(reply, ServiceError):
        log.info("refused plan: %s", reply.message)
    else:
        log.info("parsed plan: %d steps, %d warnings", len(reply.steps), len(reply.warnings))


def declare(node: Node, parser: Parser) -> None:
    # The size limit is checked on the raw bytes before decoding: a 10 MB request is refused unread.
    # Parsing is quick and never blocks (hostile 256 KiB inputs take milliseconds): answered inline.
    node.serve(keys.PLAN_PARSE, handler(parser), max_request_bytes=MAX_PLAN_BYTES + 4096, inline=True, after=logged)
