"""Recovery on the real stack: the red cup slips out of the gripper during a carry, the planner gives the scripted
model the failure and the scene, and the model's recovery plan picks the cup up again and finishes."""

from __future__ import annotations

import json

from schemas import keys
from schemas.planner import PlannerAttempt, Recovery, RecoveryOutcome
from schemas.world import Empty, FaultInjected, FaultKind, GroundTruth, InjectFault, Moved, MoveEntity
from tests.integration import test_agents
from tests.integration.conftest import Stack, tether_cli
from tests.integration.test_agents import ScriptedLLM, text_reply
from tests.watch import Watch

# The planner stack of test_agents (every service but the recorder, the sim at 10x, the planner on the
# scripted endpoint), started again for this module.
llm_server = test_agents.llm_server
agent_stack = test_agents.agent_stack


def plan(*steps: dict[str, str]) -> str:
    return json.dumps({"plan": list(steps)})


def slip_next_carry(stack: Stack) -> None:
    injected = stack.node.call(keys.SIM_FAULT, InjectFault(kind=FaultKind.SLIP, target="red_cup"), timeout=5.0)
    assert isinstance(injected, FaultInjected), injected


def truth(stack: Stack) -> GroundTruth:
    return stack.node.call(keys.GROUND_TRUTH, Empty(), timeout=10.0)  # type: ignore[no-any-return]


def cup_on(stack: Stack) -> tuple[str | None, str | None]:
    now = truth(stack)
    cup = next(o for o in now.objects if o.id == "red_cup")
    return cup.on, now.holding


def put_cup_on(stack: Stack, furniture: str, offset: tuple[float, float]) -> None:
    """The red cup set down on `furniture` (at `offset` from its centre) by the sim, whatever the tests
    before did with it; ground truth confirms it rests there and the hand is empty."""
    centre = test_agents.WORLD.furniture[furniture].center
    where = MoveEntity(id="red_cup", x=centre[0] + offset[0], y=centre[1] + offset[1])
    moved = stack.node.call(keys.SIM_MOVE, where, timeout=10.0)
    assert isinstance(moved, Moved), moved
    assert cup_on(stack) == (furniture, None)


def user_message(received: test_agents.Received) -> str:
    return str(received.body["messages"][-1]["content"])


def test_a_cup_that_slips_during_the_carry_is_picked_up_again_and_placed(
    agent_stack: Stack, llm_server: ScriptedLLM
) -> None:
    put_cup_on(agent_stack, "kitchen_counter", (-0.3, 0.2))  # where the world file has it
    recoveries = Watch(agent_stack.node, keys.PLANNER_RECOVERIES)
    attempts: Watch[PlannerAttempt] = Watch(agent_stack.node, keys.PLANNER_ATTEMPTS)
    carry = plan(
        {"action": "navigate_to", "target": "kitchen counter"},
        {"action": "pick", "target": "red cup"},
        {"action": "navigate_to", "target": "coffee table"},
        {"action": "place", "target": "coffee table"},
    )
    again = plan(
        {"action": "pick", "target": "red cup"},
        {"action": "navigate_to", "target": "coffee table"},
        {"action": "place", "target": "coffee table"},
    )
    llm_server.play(text_reply(carry), text_reply(again))
    slip_next_carry(agent_stack)

    asked = tether_cli(agent_stack, "ask", "put the red cup on the coffee table", "--wait", "--json")
    outcome = json.loads(asked.stdout)
    assert asked.returncode == 0, (outcome, asked.stderr)
    assert outcome["status"] == "succeeded", outcome
    [recovery] = outcome["recoveries"]
    assert (recovery["number"], recovery["outcome"], recovery["attempts"]) == (1, "succeeded", 1), recovery
    assert recovery["failure"] in ("precondition", "postcondition", "execution"), recovery
    assert recovery["goal_id"] == outcome["goal_id"] and recovery["failed_goal"] not in ("", outcome["goal_id"])
    assert json.loads(outcome["plan"]) == json.loads(again)

    # Ground truth, not the executor's word: the cup rests on the coffee table and the hand is empty.
    assert cup_on(agent_stack) == ("coffee_table", None)

    # The recovery conversation: the scene read after the failure, the failure and its step, as data.
    first, second = llm_server.received
    system, asking = second.body["messages"][0]["content"], user_message(second)
    assert "<robot-data source='world model'>" in system and "red cup" in system
    assert "<robot-data source='executor'>" in asking
    assert f"failure kind: {recovery['failure']}" in asking and f"index {recovery['step']}" in asking
    assert "<robot-data source='the plan that ran'>" in asking and "coffee table" in asking
    assert "<robot-data source='incident memory'>" in asking
    assert user_message(first) == "put the red cup on the coffee table"

    # Published for the recorder: the recovery as sent and as it ended, its attempt as recovery 1.
    ended = recoveries.wait_for(lambda r: r.outcome is RecoveryOutcome.SUCCEEDED, timeout=5.0)
    assert isinstance(ended, Recovery) and ended.request_id == outcome["request_id"]
    assert [r.outcome for r in recoveries.messages] == [RecoveryOutcome.SENT, RecoveryOutcome.SUCCEEDED]
    mine = [(a.recovery, a.attempt) for a in attempts.messages if a.request_id == outcome["request_id"]]
    assert mine == [(0, 1), (1, 1)]


def test_send_recover_sends_a_given_plan_and_recovers_it_with_the_model(
    agent_stack: Stack, llm_server: ScriptedLLM
) -> None:
    """A plan given as is: no model call for it, the model asked only for the recovery; the outcome in
    `tether send`'s terms (its JSON object and exit codes) with the recoveries added."""
    put_cup_on(agent_stack, "coffee_table", (-0.3, 0.0))  # clear of the blue book
    given = plan(
        {"action": "navigate_to", "target": "coffee table"},
        {"action": "pick", "target": "red cup"},
        {"action": "navigate_to", "target": "kitchen counter"},
        {"action": "place", "target": "kitchen counter"},
    )
    again = plan(
        {"action": "pick", "target": "red cup"},
        {"action": "navigate_to", "target": "kitchen counter"},
        {"action": "place", "target": "kitchen counter"},
    )
    llm_server.play(text_reply(again))
    slip_next_carry(agent_stack)

    sent = tether_cli(agent_stack, "send", given, "--recover", "--wait", "--json")
    outcome = json.loads(sent.stdout)
    assert sent.returncode == 0, (outcome, sent.stderr)
    assert (outcome["status"], outcome["stage"], outcome["failure"], outcome["steps"]) == (
        "succeeded",
        "execute",
        None,
        [],
    ), outcome
    [recovery] = outcome["recoveries"]
    assert recovery["outcome"] == "succeeded" and recovery["attempts"] == 1, recovery
    # goal_id is the goal first sent (the given plan's), final_goal_id the recovery's.
    assert recovery["failed_goal"] == outcome["goal_id"] and recovery["goal_id"] == outcome["final_goal_id"]
    assert outcome["goal_id"] != outcome["final_goal_id"] and outcome["request_id"] == recovery["request_id"]
    assert cup_on(agent_stack) == ("kitchen_counter", None)
    [asked] = llm_server.received
    assert "Carry out the plan given by an operator" in user_message(asked)
    assert "kitchen counter" in user_message(asked) and "<robot-data source='executor'>" in user_message(asked)
