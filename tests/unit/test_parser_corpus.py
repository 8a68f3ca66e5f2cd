"""The parser corpus: realistic LLM outputs, each with the parse it must give.

A case is two files in tests/corpus/parser: NAME.txt, the raw text exactly as a model emitted it,
and NAME.expect.yaml, which opens with a one-line comment saying what the case is about:

    format: auto             # the PlanText format hint; optional, default auto
    source_format: json      # the Plan's source_format (required for accepted plans)
    steps:                   # the expected steps; an omitted field is not compared, except action
      - {action: navigate_to, target: kitchen}
      - {action: drive, params: {distance: -0.3}}
      - {action: navigate_to, coordinates: {x: 3.5, y: 2.0}}   # null: no coordinates
    warnings: [leniently]    # substrings, each in some warning; absent: the plan has no warnings

or, for text that must be refused at stage parse:

    refusal:
      contains: ["step 2", "did you mean 'place'"]   # substrings of the message
      step: 1                                        # optional: ServiceError.step (0-based)
      line: 3                                        # optional: ServiceError.line (1-based)

Strings in `contains` and `warnings` match case-insensitively. `params` compares numbers with an
absolute tolerance of 1e-4 and needs exactly the keys given; `coordinates` compares x, y and z the
same way (an omitted z must be absent); `substeps` and `on_failure` are compared with the same
rules and must have the same length.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, get_args

import pytest
import yaml

from schemas.common import ServiceError, Stage
from schemas.plan import Plan, PlanFormat, PlanText, SourceFormat, Step

CORPUS = Path(__file__).resolve().parents[1] / "corpus" / "parser"
TEXT_SUFFIX = ".txt"
EXPECT_SUFFIX = ".expect.yaml"
MIN_CASES = 60
ABS_TOLERANCE = 1e-4

TOP_KEYS = {"format", "source_format", "steps", "warnings", "refusal"}
NESTED_KEYS = ("substeps", "on_failure")
STEP_KEYS = {"action", "target", "location", "params", "units", "description", "coordinates", *NESTED_KEYS}
AXES = ("x", "y", "z")
REFUSAL_KEYS = {"contains", "step", "line"}


def _stems(suffix: str) -> set[str]:
    return {p.name[: -len(suffix)] for p in CORPUS.glob(f"*{suffix}") if p.is_file()}


CASES = sorted(_stems(TEXT_SUFFIX))


def _read_text(name: str) -> str:
    # Bytes, not read_text(): the text goes to the parser exactly as stored, "\r\n" included.
    return (CORPUS / f"{name}{TEXT_SUFFIX}").read_bytes().decode("utf-8")


def _read_expect(name: str) -> Any:
    return yaml.safe_load((CORPUS / f"{name}{EXPECT_SUFFIX}").read_text(encoding="utf-8"))


# The expectation files themselves: a typo in a key must fail, not silently compare less.


def _step_problems(steps: Any, where: str) -> list[str]:
    if not isinstance(steps, list) or not steps:
        return [f"{where}: must be a non-empty list of steps"]
    problems: list[str] = []
    for i, step in enumerate(steps):
        at = f"{where}[{i}]"
        if not isinstance(step, dict):
            problems.append(f"{at}: must be a mapping")
            continue
        if "action" not in step:
            problems.append(f"{at}: 'action' is always compared and must be given (null for a group)")
        problems.extend(f"{at}: unknown key {key!r}" for key in step if key not in STEP_KEYS)
        for key in ("params", "units"):
            if key in step and not isinstance(step[key], dict):
                problems.append(f"{at}.{key}: must be a mapping")
        point = step.get("coordinates")
        if point is not None and (
            not isinstance(point, dict)
            or not {"x", "y"} <= set(point) <= set(AXES)
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in point.values())
        ):
            problems.append(f"{at}.coordinates: must be null or a mapping of numbers x, y and optionally z")
        for key in NESTED_KEYS:
            if key in step and step[key] != []:
                problems.extend(_step_problems(step[key], f"{at}.{key}"))
    return problems


def _expect_problems(expect: Any) -> list[str]:
    if not isinstance(expect, dict):
        return ["the file must hold a mapping"]
    problems = [f"unknown key {key!r}" for key in expect if key not in TOP_KEYS]
    if ("steps" in expect) == ("refusal" in expect):
        problems.append("give exactly one of 'steps' and 'refusal'")
    if expect.get("format", "auto") not in get_args(PlanFormat):
        problems.append(f"format {expect['format']!r} is not one of {get_args(PlanFormat)}")
    if "refusal" in expect:
        refusal = expect["refusal"]
        if not isinstance(refusal, dict):
            return [*problems, "refusal: must be a mapping"]
        problems.extend(f"refusal: unknown key {key!r}" for key in refusal if key not in REFUSAL_KEYS)
        contains = refusal.get("contains", [])
        if not isinstance(contains, list) or not all(isinstance(c, str) for c in contains):
            problems.append("refusal.contains: must be a list of strings")
        for key in ("step", "line"):
            if key in refusal and (not isinstance(refusal[key], int) or isinstance(refusal[key], bool)):
                problems.append(f"refusal.{key}: must be an integer")
        for key in ("source_format", "warnings"):
            if key in expect:
                problems.append(f"'{key}' means nothing for a refusal")
        return problems
    if expect.get("source_format") not in get_args(SourceFormat):
        problems.append(f"source_format must be one of {get_args(SourceFormat)}")
    warnings = expect.get("warnings", [])
    if not isinstance(warnings, list) or not all(isinstance(w, str) for w in warnings):
        problems.append("warnings: must be a list of strings")
    problems.extend(_step_problems(expect.get("steps"), "steps"))
    return problems


# Comparing a parse with its expectation.


def _same_value(expected: Any, actual: Any) -> bool:
    if isinstance(expected, bool) or isinstance(actual, bool):
        return isinstance(expected, bool) and isinstance(actual, bool) and expected == actual
    if isinstance(expected, int | float):
        return isinstance(actual, int | float) and math.isclose(expected, actual, rel_tol=0.0, abs_tol=ABS_TOLERANCE)
    return bool(expected == actual)


def _compare_steps(expected: list[dict[str, Any]], actual: list[Step], where: str, problems: list[str]) -> None:
    if len(expected) != len(actual):
        problems.append(f"{where}: expected {len(expected)} step(s), got {len(actual)}")
    for i, (want, got) in enumerate(zip(expected, actual, strict=False)):
        _compare_step(want, got, f"{where}[{i}]", problems)


def _compare_step(want: dict[str, Any], got: Step, where: str, problems: list[str]) -> None:
    action = None if got.action is None else got.action.value
    if want["action"] != action:
        problems.append(f"{where}.action: expected {want['action']!r}, got {action!r}")
    for key in ("target", "location", "description"):
        if key in want and want[key] != getattr(got, key):
            problems.append(f"{where}.{key}: expected {want[key]!r}, got {getattr(got, key)!r}")
    if "params" in want:
        expected_params: dict[str, Any] = want["params"]
        if set(expected_params) != set(got.params):
            problems.append(f"{where}.params: expected keys {sorted(expected_params)}, got {sorted(got.params)}")
        for key, value in expected_params.items():
            if key in got.params and not _same_value(value, got.params[key]):
                problems.append(f"{where}.params.{key}: expected {value!r}, got {got.params[key]!r}")
    if "units" in want and want["units"] != got.units:
        problems.append(f"{where}.units: expected {want['units']!r}, got {got.units!r}")
    if "coordinates" in want:
        point = want["coordinates"]
        got_point = None if got.coordinates is None else {a: getattr(got.coordinates, a) for a in AXES}
        if point is None or got_point is None:
            same = point is None and got_point is None
        else:
            same = all(_same_value(point[a], got_point[a]) if a in point else got_point[a] is None for a in AXES)
        if not same:
            problems.append(f"{where}.coordinates: expected {point!r}, got {got_point!r}")
    for key in NESTED_KEYS:
        if key in want:
            _compare_steps(want[key], getattr(got, key), f"{where}.{key}", problems)


def _plan_problems(expect: dict[str, Any], plan: Plan) -> list[str]:
    problems: list[str] = []
    if expect["source_format"] != plan.source_format:
        problems.append(f"source_format: expected {expect['source_format']!r}, got {plan.source_format!r}")
    _compare_steps(expect["steps"], plan.steps, "steps", problems)
    if "warnings" not in expect:
        if plan.warnings:
            problems.append(f"warnings: expected none, got {plan.warnings!r}")
    else:
        for wanted in expect["warnings"]:
            if not any(wanted.lower() in warning.lower() for warning in plan.warnings):
                problems.append(f"warnings: none contains {wanted!r}; got {plan.warnings!r}")
    return problems


def _refusal_problems(expect: dict[str, Any], error: ServiceError) -> list[str]:
    problems: list[str] = []
    if error.stage is not Stage.PARSE:
        problems.append(f"stage: expected parse, got {error.stage!r}")
    message = error.message.lower()
    problems.extend(
        f"message does not contain {wanted!r}" for wanted in expect.get("contains", []) if wanted.lower() not in message
    )
    for key in ("step", "line"):
        if key in expect and expect[key] != getattr(error, key):
            problems.append(f"{key}: expected {expect[key]!r}, got {getattr(error, key)!r}")
    return problems


@pytest.mark.timeout(60)
@pytest.mark.parametrize("name", CASES, ids=CASES)
def test_corpus_case(name: str) -> None:
    expect = _read_expect(name)
    shape = _expect_problems(expect)
    assert not shape, f"{name}{EXPECT_SUFFIX} is malformed: " + "; ".join(shape)
    # Imported here so that the corpus's own checks run even while the parser does not import.
    from services.parser.parser import answer, default_parser

    reply = answer(default_parser(), PlanText(text=_read_text(name), format=expect.get("format", "auto")))
    if "refusal" in expect:
        if not isinstance(reply, ServiceError):
            pytest.fail(f"expected a refusal, got a plan: {reply!r}")
        problems = _refusal_problems(expect["refusal"], reply)
        assert not problems, "\n".join([*problems, f"refusal: {reply.message!r}"])
    else:
        if not isinstance(reply, Plan):
            pytest.fail(f"expected a plan, got a refusal: {reply!r}")
        problems = _plan_problems(expect, reply)
        assert not problems, "\n".join([*problems, f"plan: {reply!r}"])


def test_corpus_is_complete_and_well_formed() -> None:
    texts, expects = _stems(TEXT_SUFFIX), _stems(EXPECT_SUFFIX)
    assert len(texts) >= MIN_CASES, f"{len(texts)} cases in {CORPUS}; at least {MIN_CASES} are needed"
    assert not texts - expects, f"texts without {EXPECT_SUFFIX}: {sorted(texts - expects)}"
    assert not expects - texts, f"expectations without {TEXT_SUFFIX}: {sorted(expects - texts)}"
    unexpected = sorted(p.name for p in CORPUS.iterdir() if not p.name.endswith((TEXT_SUFFIX, EXPECT_SUFFIX)))
    assert not unexpected, f"files that are neither a case text nor an expectation: {unexpected}"
    malformed: list[str] = []
    for name in sorted(expects):
        source = (CORPUS / f"{name}{EXPECT_SUFFIX}").read_text(encoding="utf-8")
        if not source.startswith("# "):
            malformed.append(f"{name}: the first line must be a comment saying what the case is about")
        malformed.extend(f"{name}: {problem}" for problem in _expect_problems(yaml.safe_load(source)))
    assert not malformed, "\n".join(malformed)
