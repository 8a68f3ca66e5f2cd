"""The planner's configuration: the `[planner]` table, overridden by TETHER_LLM_* in the environment."""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import httpx2 as httpx
import msgspec
from msgspec import Meta

from schemas.planner import MAX_ATTEMPTS, MAX_RECOVERIES
from services.planner.errors import NotConfigured

URL_ENV = "TETHER_LLM_URL"
MODEL_ENV = "TETHER_LLM_MODEL"
KEY_ENV = "TETHER_LLM_API_KEY"
# A file holding the key instead (a compose secret, a systemd credential): not in the process's
# environment, where `docker inspect` and /proc/PID/environ show it. Empty file: no key.
KEY_FILE_ENV = "TETHER_LLM_API_KEY_FILE"

HOW_TO_CONFIGURE = f"""no LLM endpoint is configured. Any OpenAI-compatible chat-completions endpoint works
(Ollama, llama.cpp server, vLLM, or a hosted one). Either set, in the environment:
  export {URL_ENV}=http://127.0.0.1:11434/v1    # Ollama; llama.cpp server: http://127.0.0.1:8080/v1
  export {MODEL_ENV}=llama3.1
  export {KEY_ENV}=...                            # only if the endpoint wants a key
or write a [planner] table in a config file and pass it with --config
(`tether ask --config tether.toml ...`, `tether up --config tether.toml`):
  [planner]
  url = "https://api.openai.com/v1"
  model = "gpt-4o-mini"
  api_key_env = "OPENAI_API_KEY"   # the NAME of the variable that holds the key, never the key itself"""


class PlannerConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    # The endpoint's base URL up to /v1 (".../chat/completions" is added), or the full URL. Empty: none.
    url: Annotated[str, Meta(max_length=2000, pattern=r"^(https?://\S+)?$")] = ""
    model: Annotated[str, Meta(max_length=200)] = ""
    # The NAME of the environment variable holding the API key. The key itself never goes in a file.
    api_key_env: Annotated[str, Meta(max_length=100, pattern=r"^([A-Za-z_][A-Za-z0-9_]*)?$")] = ""
    # Seconds for one model call.
    timeout: Annotated[float, Meta(gt=0.0, le=600.0)] = 60.0
    # Model calls per request: each answer is dry-run, and a refusal goes back to the model.
    max_attempts: Annotated[int, Meta(ge=1, le=MAX_ATTEMPTS)] = 3
    temperature: Annotated[float, Meta(ge=0.0, le=2.0)] = 0.0
    # Offer the tools natively (`tools` in the request, replies as tool_calls); false: their schemas
    # go in the system prompt instead, for servers or models without tool calling.
    native_tools: bool = True
    # Seconds for each dry run (parse, resolve, safety check) of a plan.
    check_timeout: Annotated[float, Meta(gt=0.0, le=600.0)] = 60.0
    # A model reply bigger than this is refused before decoding.
    max_reply_bytes: Annotated[int, Meta(ge=1024, le=16 * 1024 * 1024)] = 1024 * 1024
    # Recovery plans asked for when a plan sent for a request fails at a step (an object dropped, not
    # where it was expected, a route blocked); each is dry-run and checked like any plan. 0: none.
    max_recoveries: Annotated[int, Meta(ge=0, le=MAX_RECOVERIES)] = 2


class Secret:
    """A value that never shows itself in a repr, a log line or a traceback's locals."""

    __slots__ = ("_value",)

    def __init__(self, value: str) -> None:
        self._value = value

    def reveal(self) -> str:
        return self._value

    def __repr__(self) -> str:
        return "Secret('***')"

    __str__ = __repr__


@dataclass(frozen=True)
class Endpoint:
    """Where the model is and how to call it, with the key resolved from the environment."""

    url: str = field(repr=False)  # it may hold credentials (user:password@, ?key=)
    model: str
    api_key: Secret | None = field(default=None, repr=False)
    # Where the key came from (a variable's name), for error messages: never the key.
    key_source: str = ""
    timeout: float = 60.0
    temperature: float = 0.0
    max_reply_bytes: int = 1024 * 1024

    @property
    def shown_url(self) -> str:
        """The URL for messages: without user:password@ and without a query (either may hold a secret)."""
        scheme, _, rest = self.chat_url.partition("://")
        host, slash, path = rest.partition("/")
        return f"{scheme}://{host.rpartition('@')[2]}{slash}{path.partition('?')[0]}"

    @property
    def chat_url(self) -> str:
        url, query, rest = self.url.partition("?")
        url = url.rstrip("/")
        url = url if url.endswith("/chat/completions") else f"{url}/chat/completions"
        return f"{url}{query}{rest}"

    def url_error(self) -> str:
        """Why httpx cannot call the URL ("" when it can), without the URL's credentials: httpx's own
        reason only when the URL has none (it may quote a part of the URL)."""
        try:
            port = httpx.URL(self.chat_url).port
        except httpx.InvalidURL as exc:
            return str(exc) if self.shown_url == self.chat_url else "httpx cannot parse it"
        if port is not None and not 0 < port < 65536:
            return f"port {port} is not between 1 and 65535"
        return ""


def resolve_endpoint(config: PlannerConfig, environ: Mapping[str, str] | None = None) -> Endpoint | None:
    """The endpoint from the environment (TETHER_LLM_URL, _MODEL, _API_KEY), else from the config;
    None when no URL is set anywhere. A URL without a model, or an `api_key_env` naming a variable
    that is not set, is a NotConfigured error naming what is missing."""
    env = os.environ if environ is None else environ
    url = env.get(URL_ENV, "").strip() or config.url
    if not url:
        return None
    if not url.startswith(("http://", "https://")):
        raise NotConfigured(f"{URL_ENV} must be an http:// or https:// URL")
    # The pattern of PlannerConfig.url lets through what httpx refuses ('http://[::1/v1'): checked here,
    # once, and named without the credentials a URL may hold.
    where = Endpoint(url=url, model="")
    problem = where.url_error()
    if problem:
        source = URL_ENV if env.get(URL_ENV, "").strip() else "[planner] url"
        raise NotConfigured(f"{source} {where.shown_url} is not a valid URL: {problem}")
    model = env.get(MODEL_ENV, "").strip() or config.model
    if not model:
        raise NotConfigured(f"the LLM endpoint {where.shown_url} has no model: set {MODEL_ENV} or [planner] model")
    key: Secret | None = None
    source = ""
    if env.get(KEY_ENV):
        key, source = Secret(env[KEY_ENV]), KEY_ENV
    elif env.get(KEY_FILE_ENV):
        path = env[KEY_FILE_ENV]
        try:
            text = Path(path).read_text().strip()
        except (OSError, UnicodeDecodeError) as exc:
            raise NotConfigured(
                f"{KEY_FILE_ENV} names {path}, which cannot be read: {exc.__class__.__name__}"
            ) from None
        if text:
            key, source = Secret(text), f"{KEY_FILE_ENV} ({path})"
    elif config.api_key_env:
        if not env.get(config.api_key_env):
            raise NotConfigured(
                f"[planner] api_key_env names the variable {config.api_key_env}, which is not set in the environment"
            )
        key, source = Secret(env[config.api_key_env]), config.api_key_env
    return Endpoint(
        url=url,
        model=model,
        api_key=key,
        key_source=source,
        timeout=config.timeout,
        temperature=config.temperature,
        max_reply_bytes=config.max_reply_bytes,
    )
