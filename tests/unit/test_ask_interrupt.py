"""What `tether ask` and `tether send --recover` print when interrupted: their usual JSON object, with
`tether send`'s status and exit code for the canceled plan's end."""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any, NoReturn

import msgspec
import pytest
import typer

from schemas import keys
from schemas.common import Stage
from schemas.executor import ExecutePlanResult, PlanStatus
from schemas.planner import AskCancelReply, AskReply, AskRequest, AskStatus
from tether import ask, sendrecover
from tether.ask import Interrupted, show_interrupted

CANCELED = ExecutePlanResult(status=PlanStatus.CANCELED, stage=Stage.EXECUTE, reason="canceled")
SENT = AskReply(status=AskStatus.ACCEPTED, request_id="r1", goal_id="g2")
WAIT = 10.0  # s: a deadline for what happens at once


def printed(
    capsys: pytest.CaptureFixture[str], conclude: Callable[[Interrupted, bool], NoReturn], stop: Interrupted
) -> tuple[int, dict[str, object]]:
    with pytest.raises(typer.Exit) as ended:
        conclude(stop, True)
    return ended.value.exit_code, json.loads(capsys.readouterr().out)


@pytest.mark.parametrize(
    ("stop", "code", "status"),
    [
        (Interrupted(["g1", "g2"], CANCELED), 1, "canceled"),
        (Interrupted(["g1", "g2"], None, "no outcome: it did not end"), 3, "unreachable"),
        (Interrupted([], CANCELED), 1, "canceled"),
    ],
)
def test_an_interrupted_ask_prints_its_usual_object_with_sends_codes(
    capsys: pytest.CaptureFixture[str], stop: Interrupted, code: int, status: str
) -> None:
    exit_code, document = printed(capsys, show_interrupted, stop)
    assert (exit_code, document["status"], document["goal_id"]) == (code, status, stop.goal_id)
    assert set(document) == set(msgspec.to_builtins(SENT)) and document["reason"] == stop.reason


@pytest.mark.parametrize(
    ("stop", "code", "status", "like"),
    [
        (Interrupted(["g1", "g2"], CANCELED), 1, "canceled", AskStatus.FAILED),
        (Interrupted(["g1", "g2"], None, "no outcome: it did not end"), 3, "unreachable", AskStatus.UNREACHABLE),
    ],
)
def test_an_interrupted_send_recover_prints_sends_object_first_and_final_goal(
    capsys: pytest.CaptureFixture[str], stop: Interrupted, code: int, status: str, like: AskStatus
) -> None:
    """The keys of the object --recover prints for a plan that ended (or for no outcome)."""
    exit_code, document = printed(capsys, sendrecover.interrupted, stop)
    assert (exit_code, document["status"], document["goal_id"], document["final_goal_id"]) == (code, status, "g1", "g2")
    usual, _ = sendrecover.outcome(msgspec.structs.replace(SENT, status=like))
    assert set(document) == set(usual)


@pytest.mark.parametrize("request_id", ["4f1c2a", ""], ids=["through the service", "none made"])
def test_an_interrupted_send_recover_names_the_request_it_stopped(
    capsys: pytest.CaptureFixture[str], request_id: str
) -> None:
    """As `tether ask`'s: the planner service's request this command made and canceled by its id,
    "" only when it made none (it printed "" always)."""
    stop = Interrupted(["g1"], CANCELED)
    stop.request_id = request_id
    _, document = printed(capsys, sendrecover.interrupted, stop)
    assert document["request_id"] == request_id
    no_end = Interrupted([], None, "no outcome: interrupted again before the planner canceled")
    no_end.request_id = request_id
    _, document = printed(capsys, sendrecover.interrupted, no_end)
    assert (document["status"], document["request_id"]) == ("unreachable", request_id)


class PlannerOnTheWire:
    """What ask_service touches of a Node: plan/ask goes and is answered only when released; a cancel
    by request id is taken (the planner had sent no goal yet)."""

    def __init__(self) -> None:
        self.asked = threading.Event()
        self.release = threading.Event()
        self.cancels: list[str] = []

    def call(self, service: Any, request: Any, *, timeout: float = 5.0) -> Any:
        if service is keys.PLAN_ASK_CANCEL:
            self.cancels.append(request.request_id)
            return AskCancelReply(request_id=request.request_id, known=True, running=True, reason="canceled")
        self.asked.set()
        self.release.wait(WAIT)
        return SENT


def test_a_ctrl_c_while_the_ask_thread_starts_cancels_the_request_it_may_have_sent(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A Ctrl-C that lands while ask_service starts its thread (the request on its way, the planner
    maybe acting on it: seen under load) cancels the request by its id like any other, instead of
    ending the command with the plan left to run."""
    node = PlannerOnTheWire()

    class StartedThenInterrupted(threading.Thread):
        def start(self) -> None:
            super().start()
            assert node.asked.wait(WAIT)
            raise KeyboardInterrupt

    monkeypatch.setattr(ask, "threading", SimpleNamespace(Thread=StartedThenInterrupted))
    request = AskRequest(text="go to the kitchen", request_id="req-7")
    try:
        with pytest.raises(Interrupted) as stopped:
            ask.ask_service(node, request, timeout=WAIT)  # type: ignore[arg-type]
    except KeyboardInterrupt:
        pytest.fail("the Ctrl-C ended the ask without canceling the request it had sent")
    finally:
        node.release.set()
    assert node.cancels == ["req-7"]
    assert stopped.value.request_id == "req-7" and stopped.value.result is not None
    assert stopped.value.result.status is PlanStatus.CANCELED
