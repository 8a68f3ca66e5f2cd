"""`tether schema`: the agent tools as OpenAI, Anthropic, MCP or JSON Schema definitions, on stdout."""

from __future__ import annotations

import enum
import json
from typing import Annotated

import typer

from services.agent.tools import all_tools, render


class SchemaFormat(enum.StrEnum):
    OPENAI = "openai"
    ANTHROPIC = "anthropic"
    MCP = "mcp"
    JSONSCHEMA = "jsonschema"


def schema(
    fmt: Annotated[
        SchemaFormat,
        typer.Option(
            "--format",
            help="openai: chat tools; anthropic: tools; mcp: MCP Tool objects; jsonschema: one document, "
            "each tool's arguments under $defs.",
        ),
    ] = SchemaFormat.OPENAI,
    strict: Annotated[
        bool,
        typer.Option(
            "--strict",
            help="Within OpenAI's strict rules: all properties required (optional ones nullable), no "
            "additional properties, unsupported keywords moved into descriptions.",
        ),
    ] = False,
) -> None:
    """Print the tool definitions an LLM agent gets, generated from the action vocabulary."""
    typer.echo(json.dumps(render(all_tools(), fmt.value, strict=strict), indent=2, ensure_ascii=False))
