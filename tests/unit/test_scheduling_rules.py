"""The scheduler's rules (a)-(f) and five steps, without I/O: plans, queue, expiry, QoS, odometry."""

from __future__ import annotations

import numpy as np
import pytest

from services.apps.registry.scheduling import (
    Plan,
    Provider,
    ProviderState,
    Request,
    Scheduler,
    Waiting,
    odometry_distance,
    parse_assessments,
    parse_capabilities,
    rank_scores,
)
from services.kernel.errors import (
    FailedPrecondition,
    InvalidArgument,
    NotFound,
    ResourceExhausted,
    Unavailable,
)

READY, DORMANT, BUSY, DOWN = (
    ProviderState.READY,
    ProviderState.DORMANT,
    ProviderState.BUSY,
    ProviderState.DOWN,
)
SURVEY = frozenset({"survey"})


def robot(name: str, x: float, state: ProviderState = READY, caps: frozenset[str] = SURVEY) -> Provider:
    return Provider(name, caps | {"mobile_robot"}, state, np.array([x, 0.0]))


def seed_robots() -> list[Provider]:
    return [robot("B", 1), robot("C", 2), robot("D", 3, DORMANT), robot("E", 4, DORMANT)]


def ask(consumer: str = "A", caps: frozenset[str] = SURVEY, **options: object) -> Request:
    fields: dict[str, object] = {"location": np.array([0.0, 0.0]), "duration": 10.0}
    fields.update(options)
    return Request(consumer, caps, **fields)  # type: ignore[arg-type]


def granted(s: Scheduler, request: Request, providers: list[Provider], now: float = 0.0) -> list[str]:
    plan = s.submit(request, providers, now)
    assert isinstance(plan, Plan)
    s.commit(plan, {p: f"L-{p}" for p in plan.providers}, now)
    return list(plan.providers)


def test_nearest_ready_providers_first_and_dormant_only_when_ready_cannot_serve() -> None:
    s = Scheduler()
    robots = seed_robots()
    first = s.submit(ask(count=2), robots, 0.0)
    assert isinstance(first, Plan) and first.providers == ("B", "C") and first.wake == ()
    s.commit(first, {"B": "L1", "C": "L2"}, 0.0)
    second = s.submit(ask(caps=frozenset({"mobile_robot"}), count=2), robots, 0.0)
    assert isinstance(second, Plan) and second.providers == ("D", "E") and second.wake == ("D", "E")


def test_rule_b_a_provider_serves_one_consumer_and_rule_c_a_consumer_holds_several() -> None:
    s = Scheduler()
    robots = seed_robots()[:2]
    assert granted(s, ask(), robots) == ["B"]
    assert granted(s, ask(caps=frozenset({"mobile_robot"})), robots) == ["C"]  # A holds two now
    with pytest.raises(Unavailable, match="busy"):
        s.submit(ask("F"), robots, 0.0)


def test_rule_a_a_consumer_is_no_provider_and_a_serving_provider_cannot_request() -> None:
    s = Scheduler()
    robots = [robot("A", 0), *seed_robots()[:2]]
    assert granted(s, ask("B"), robots) == ["A"]  # B asks: A is nearest of the others
    with pytest.raises(FailedPrecondition, match=r"rule \(a\): A is providing for B"):
        s.submit(ask("A", caps=frozenset({"mobile_robot"})), robots, 0.0)
    # B is a consumer now: never chosen as a provider for F.
    assert granted(s, ask("F"), robots) == ["C"]


def test_rule_d_the_consumer_rejects_providers() -> None:
    s = Scheduler()
    assert granted(s, ask(exclude=frozenset({"B"})), seed_robots()) == ["C"]


def test_rule_e_the_same_service_twice_is_refused_and_tout_bounds_duration() -> None:
    s = Scheduler(tout=5.0)
    with pytest.raises(InvalidArgument, match="Tout = 5 s"):
        s.submit(ask(duration=6.0), seed_robots(), 0.0)
    granted(s, ask(duration=5.0), seed_robots())
    with pytest.raises(FailedPrecondition, match=r"rule \(e\): A already holds \(survey\)"):
        s.submit(ask(duration=5.0), seed_robots(), 0.0)
    assert [a.id for a in s.expire(5.0)] == ["r1"]
    assert granted(s, ask(duration=5.0), seed_robots(), 5.0) == ["B"]  # expired: may ask again


def test_step_3_unknown_capabilities_and_impossible_compositions_are_recorded() -> None:
    s = Scheduler()
    with pytest.raises(NotFound, match=r"no provider offers \(laser\)"):
        s.submit(ask(caps=frozenset({"laser"})), seed_robots(), 0.0)
    with pytest.raises(NotFound, match="no composition covers"):
        s.submit(ask(caps=frozenset({"laser", "survey"})), seed_robots(), 0.0)
    with pytest.raises(NotFound, match="5 providers offering all of"):
        s.submit(ask(count=5), seed_robots(), 0.0)
    assert [c for c, _, _ in s.unserved] == ["A", "A", "A"]


def test_composition_covers_with_as_few_providers_as_possible() -> None:
    s = Scheduler()
    providers = [
        Provider("cam", frozenset({"video", "ptz"}), READY, np.array([1.0, 0])),
        Provider("cart", frozenset({"mobile", "power"}), READY, np.array([1.0, 0])),
        Provider(
            "all", frozenset({"video", "ptz", "mobile", "power", "communication"}), READY, np.array([9.0, 0])
        ),
        Provider("radio", frozenset({"communication"}), READY, np.array([0.5, 0])),
    ]
    minterm = frozenset({"video", "ptz", "mobile", "power", "communication"})
    assert granted(s, ask(caps=minterm), providers) == ["all"]


def test_step_4_queue_when_busy_retry_on_release_and_drop_at_deadline() -> None:
    s = Scheduler(tr=10.0)
    robots = seed_robots()[:1]
    granted(s, ask(), robots)
    waiting = s.submit(ask("F", wait=10.0), robots, 1.0)
    assert isinstance(waiting, Waiting) and waiting.deadline == 11.0
    with pytest.raises(FailedPrecondition, match="already waits"):
        s.submit(ask("F", wait=10.0), robots, 1.0)
    assert s.retry(lambda w: robots, 2.0) == ([], [])  # B still busy
    s.release("r1", "A", {"B": 0.9})
    plans, dropped = s.retry(lambda w: robots, 3.0)
    assert [p.providers for p in plans] == [("B",)] and dropped == []
    s.abort(plans[0])
    late = s.submit(ask("G", wait=1.0), robots, 3.0)
    assert isinstance(late, Plan)  # B is free again after the abort
    s.commit(late, {"B": "L"}, 3.0)
    queued = s.submit(ask("H", wait=1.0), robots, 3.0)
    assert isinstance(queued, Waiting)
    assert s.retry(lambda w: robots, 4.5) == ([], [queued])


def test_the_queue_is_bounded_in_all_and_per_consumer() -> None:
    s = Scheduler(max_queued=3)
    one = seed_robots()[:1]
    granted(s, ask("A"), one)
    s.queue.per_consumer = 2
    assert isinstance(s.submit(ask("F", wait=5.0), one, 0.0), Waiting)
    assert isinstance(s.submit(ask("F", caps=frozenset({"mobile_robot"}), wait=5.0), one, 0.0), Waiting)
    with pytest.raises(ResourceExhausted, match="F already has 2 requests waiting"):
        s.submit(ask("F", caps=frozenset({"survey", "mobile_robot"}), wait=5.0), one, 0.0)
    assert isinstance(s.submit(ask("G", wait=5.0), one, 0.0), Waiting)
    with pytest.raises(ResourceExhausted, match="queue is full"):
        s.submit(ask("H", wait=5.0), one, 0.0)


def test_release_records_qos_in_the_normalised_format_even_after_expiry() -> None:
    s = Scheduler()
    granted(s, ask(count=2, duration=1.0), seed_robots())
    granted(s, ask(caps=frozenset({"mobile_robot"}), count=2), seed_robots())
    assert [a.status for a in s.expire(1.0)] == ["expired"]
    _, records = s.release("r1", "A", parse_assessments("((B 0.86) (C 0))"))
    s.release("r2", "A", parse_assessments("((D 0.94) (E 0.82))"))
    assert {n: round(r.mean, 2) for n, r in s.qos.items()} == {"B": 0.86, "C": 0.0, "D": 0.94, "E": 0.82}
    assert records["B"].count == 1
    with pytest.raises(FailedPrecondition, match="released already"):
        s.release("r1", "A", {})
    with pytest.raises(NotFound):
        s.release("r99", "A", {})


def test_a_release_by_another_or_of_a_stranger_provider_is_refused() -> None:
    s = Scheduler()
    granted(s, ask(), seed_robots())
    with pytest.raises(FailedPrecondition, match="held by A, not F"):
        s.release("r1", "F", {})
    with pytest.raises(InvalidArgument, match="C did not serve"):
        s.release("r1", "A", {"C": 0.5})


def test_qos_counts_against_cost() -> None:
    scores = rank_scores({"near": 1.0, "far": 2.0}, {"near": 0.0, "far": 1.0}, 0.5)
    assert scores["far"] < scores["near"]
    assert rank_scores({"a": 0.0, "b": 0.0}, {}, 0.5) == {"a": 0.25, "b": 0.25}


def test_a_licence_ending_frees_its_provider() -> None:
    s = Scheduler()
    granted(s, ask(count=2), seed_robots())
    s.end_licence("L-B", "lost")
    assert s.holder("B") is None and s.holder("C") == "A"
    s.end_licence("L-C", "expired")
    assert s.allocations == {} and s.ended[-1].status == "expired"


def test_down_providers_are_unavailable_busy_ones_outside_wait() -> None:
    s = Scheduler()
    with pytest.raises(Unavailable, match="down"):
        s.submit(ask(), [robot("B", 1, DOWN)], 0.0)
    assert isinstance(s.submit(ask(wait=5.0), [robot("B", 1, BUSY)], 0.0), Waiting)


def test_odometry_is_the_sum_of_mean_wheel_speed_times_dt() -> None:
    assert odometry_distance([(1.0, 0.5, 0.5), (2.0, 1.0, 0.0), (0.5, -1.0, -1.0)]) == pytest.approx(2.0)
    assert odometry_distance([]) == 0.0
    with pytest.raises(InvalidArgument):
        odometry_distance([(-1.0, 1.0, 1.0)])


@pytest.mark.parametrize(
    "text", ["", "()", "(a b", "(a (b))", "(" + " ".join(f"c{i}" for i in range(40)) + ")", "(bad!name)"]
)
def test_bad_capability_lists_are_refused(text: str) -> None:
    with pytest.raises(InvalidArgument):
        parse_capabilities(text)


@pytest.mark.parametrize("text", ["((B 1.5))", "((B x))", "((B 0.5) (B 0.6))", "(B 0.5)", "((B nan))"])
def test_bad_assessments_are_refused(text: str) -> None:
    with pytest.raises(InvalidArgument):
        parse_assessments(text)


def test_a_waiting_request_rejected_by_its_providers_waits_again_without_them() -> None:
    s = Scheduler()
    robots = seed_robots()[:2]
    granted(s, ask(count=2), robots)
    waiting = s.submit(ask("F", wait=10.0), robots, 0.0)
    assert isinstance(waiting, Waiting)
    s.release("r1", "A", {})
    plans, _ = s.retry(lambda w: robots, 1.0)
    assert [p.providers for p in plans] == [("B",)]
    s.abort(plans[0])  # B refused its licence (rule d)
    again = s.requeue(plans[0], {"B"}, 2.0)
    assert again is not None and again.deadline == waiting.deadline and again.request.exclude == {"B"}
    plans, _ = s.retry(lambda w: robots, 3.0)
    assert [p.providers for p in plans] == [("C",)]
    s.abort(plans[0])
    assert s.requeue(plans[0], {"C"}, 11.0) is None  # past its deadline: not queued again
    assert len(s.queue) == 0


def test_ready_providers_are_used_before_dormant_ones_are_woken_even_when_farther() -> None:
    s = Scheduler()
    robots = [robot("far", 9), robot("D", 1, DORMANT), robot("E", 2, DORMANT)]
    plan = s.submit(ask(count=2), robots, 0.0)
    assert isinstance(plan, Plan) and set(plan.providers) == {"far", "D"} and plan.wake == ("D",)
    # A composition takes as few dormant providers as a smallest cover allows.
    s2 = Scheduler()
    parts = [
        Provider("cam", frozenset({"video"}), READY, np.array([9.0, 0])),
        Provider("dcam", frozenset({"video", "mobile"}), DORMANT, np.array([0.0, 0])),
        Provider("cart", frozenset({"mobile"}), DORMANT, np.array([0.0, 0])),
    ]
    plan = s2.submit(ask(caps=frozenset({"video", "mobile"})), parts, 0.0)
    assert isinstance(plan, Plan) and plan.providers == ("dcam",)  # one provider beats two
    plan = s2.submit(ask("F", caps=frozenset({"video"})), parts, 0.0)
    assert isinstance(plan, Plan) and plan.providers == ("cam",)


def test_a_provider_that_is_a_consumer_now_is_busy_not_missing() -> None:
    s = Scheduler()
    robots = [robot("A", 0, caps=frozenset({"laser"})), *seed_robots()[:2]]
    assert granted(s, ask("A"), robots) == ["B"]  # A is a consumer now (rule a)
    waiting = s.submit(ask("F", caps=frozenset({"laser"}), wait=5.0), robots, 0.0)
    assert isinstance(waiting, Waiting)  # A offers it once its allocation ends
    with pytest.raises(Unavailable, match="busy"):
        s.submit(ask("G", caps=frozenset({"mobile_robot"}), count=3, wait=0.0), robots, 0.0)
    assert not s.unserved  # A, B and C exist: nothing unserved
    s.release("r1", "A", {})
    plans, _ = s.retry(lambda w: robots, 1.0)
    assert [p.providers for p in plans] == [("A",)]
