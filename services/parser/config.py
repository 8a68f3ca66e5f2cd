"""The parser's configuration: where its vocabulary is and how lenient it is with broken JSON."""

from __future__ import annotations

from typing import Annotated

import msgspec
from msgspec import Meta


class ParserConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    # A vocabulary file; empty means the bundled services/parser/vocabulary.yaml.
    vocabulary: str = ""
    # JSON nested deeper than this is refused before decoding: a plan needs three or four levels.
    max_depth: Annotated[int, Meta(ge=4, le=200)] = 32
    # Repair malformed JSON (trailing commas, single quotes...) when its brackets balance.
    lenient_json: bool = True
    # Bigger malformed candidates are refused rather than repaired, keeping repair time bounded.
    max_repair_chars: Annotated[int, Meta(ge=0, le=256 * 1024)] = 64 * 1024
