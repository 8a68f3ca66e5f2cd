"""Ids in messages are whole-string matches: Python's `$` also matches before a last newline."""

from __future__ import annotations

import json
from typing import Any, get_args, get_type_hints

import msgspec
import pytest

from schemas.actions import GoalId
from schemas.common import Id
from schemas.planner import CallerRequestId, RequestId
from schemas.world import InjectFault
from services.agent.tools import FORMATS, Format, all_tools, render

IDS: dict[str, Any] = {
    "Id": Id,
    "GoalId": GoalId,
    "RequestId": RequestId,
    "CallerRequestId": CallerRequestId,
    "InjectFault.target": get_type_hints(InjectFault, include_extras=True)["target"],
}


@pytest.mark.parametrize("name", IDS)
def test_an_id_with_a_newline_is_refused(name: str) -> None:
    kind = IDS[name]
    assert msgspec.convert("kitchen_1", kind) == "kitchen_1"
    for bad in ("kitchen_1\n", "kitchen_1\n\n", "\nkitchen_1", "kitchen_1\r\n"):
        with pytest.raises(msgspec.ValidationError, match="matching regex"):
            msgspec.convert(bad, kind)
        with pytest.raises(msgspec.ValidationError, match="matching regex"):
            msgspec.json.decode(msgspec.json.encode(bad), type=kind)


@pytest.mark.parametrize("name", IDS)
def test_the_json_schema_carries_the_same_pattern(name: str) -> None:
    """Tool schemas give models and MCP clients the pattern as an ECMA regex, which has no \\Z: the
    lookahead before `$` is read the same there."""
    (meta,) = [m for m in get_args(IDS[name])[1:] if isinstance(m, msgspec.Meta)]
    assert meta.pattern is not None and meta.pattern.endswith("(?!\\n)$")
    assert msgspec.json.schema(IDS[name])["pattern"] == meta.pattern


@pytest.mark.parametrize("strict", [False, True])
@pytest.mark.parametrize("fmt", FORMATS)
def test_tool_schemas_give_the_plain_end(fmt: Format, strict: bool) -> None:
    """A lookahead may not be taken by a provider's constrained decoding: tools say `$`, ECMA's end of text."""
    text = json.dumps(render(all_tools(), fmt, strict))
    assert "(?!" not in text
    assert '"pattern": "^[A-Za-z0-9_-]+$"' in text  # goal ids
