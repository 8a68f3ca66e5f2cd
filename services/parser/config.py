"""The parser's configuration: its word lists, its limits and how lenient it is with broken JSON."""

from __future__ import annotations

from typing import Annotated

import msgspec
from msgspec import Meta

from schemas.plan import MAX_NESTING, MAX_PLAN_BYTES, MAX_STEPS


class ParserConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    # A vocabulary file; empty means the bundled services/parser/vocabulary.yaml.
    vocabulary: str = ""
    # An English grammar file; empty means the bundled services/parser/grammar.yaml.
    grammar: str = ""
    # Limits. Each may only be tightened below the schema's own bound.
    max_input_bytes: Annotated[int, Meta(ge=64, le=MAX_PLAN_BYTES)] = MAX_PLAN_BYTES
    # All steps, sub-steps and on_failure alternatives included.
    max_steps: Annotated[int, Meta(ge=1, le=MAX_STEPS)] = MAX_STEPS
    # Levels of sub-steps and on_failure below the plan's steps.
    max_nesting: Annotated[int, Meta(ge=0, le=MAX_NESTING)] = MAX_NESTING
    # JSON or YAML nested deeper than this is refused before decoding: a plan needs a few levels.
    max_depth: Annotated[int, Meta(ge=4, le=200)] = 32
    # A said sentence or a description.
    max_string_chars: Annotated[int, Meta(ge=16, le=4000)] = 4000
    # YAML nodes with anchors and aliases expanded.
    max_yaml_nodes: Annotated[int, Meta(ge=100, le=1_000_000)] = 20_000
    # Repair malformed JSON (trailing commas, single quotes...) when its brackets balance.
    lenient_json: bool = True
    # Bigger malformed candidates are refused rather than repaired, keeping repair time bounded.
    max_repair_chars: Annotated[int, Meta(ge=0, le=256 * 1024)] = 64 * 1024
