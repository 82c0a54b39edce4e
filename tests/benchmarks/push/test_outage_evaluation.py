"""The outage conditions the push experiments compare, and the decision timer."""

from __future__ import annotations

from benchmarks.push.outage_evaluation import Condition, Timed, outage_conditions


def test_conditions_are_all_sensors_then_each_sensor_failing_each_way():
    assert outage_conditions(["episode", "bursts"]) == [
        Condition("all", None, None),
        Condition("no-camera (episode)", "image", "episode"),
        Condition("no-force (episode)", "force", "episode"),
        Condition("no-camera (bursts)", "image", "bursts"),
        Condition("no-force (bursts)", "force", "bursts"),
    ]


def test_timed_returns_the_policy_output_and_records_each_call():
    timed = Timed(lambda tensordict: {**tensordict, "action": 1})
    assert timed({"obs": 0}) == {"obs": 0, "action": 1}
    timed({"obs": 1})
    assert len(timed.seconds) == 2 and all(s >= 0 for s in timed.seconds)
