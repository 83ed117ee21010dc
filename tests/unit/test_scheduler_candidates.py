"""Narrowing the providers with numpy never changes the scheduler's decision."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from services.apps.registry import Registry
from services.apps.registry.scheduling import Plan, Request, Scheduler
from services.kernel.backend import BackendInfo
from services.kernel.errors import PropertyError

CAPS = ("survey", "video", "ptz", "power")


#: One provider: its capabilities, where it is (or nowhere), whether it is down, whether it is dormant.
#: Built once: a strategy made afresh for every provider of every example costs Hypothesis more than
#: the drawing does.
PROVIDERS = st.lists(
    st.tuples(
        st.sets(st.sampled_from(CAPS), max_size=3),
        st.none() | st.tuples(st.floats(-50, 50), st.floats(-50, 50)),
        st.sampled_from(["up", "up", "up", "down"]),
        st.integers(0, 5).map(lambda roll: roll == 0),
    ),
    min_size=1,
    max_size=40,
)
REQUESTS = st.tuples(
    st.sets(st.sampled_from(CAPS), min_size=1, max_size=3),
    st.integers(1, 3),
    st.none() | st.tuples(st.floats(-50, 50), st.floats(-50, 50)),
    st.sampled_from([0.0, 0.5, 1.0]),
)


@st.composite
def registries(draw: st.DrawFn) -> tuple[Registry, list[tuple[str, float]], Request]:
    providers = draw(PROVIDERS)
    n = len(providers)
    registry = Registry(period=0, features={f"p{i}": tuple(caps) for i, (caps, *_) in enumerate(providers)})
    for i, (_, place, state, dormant) in enumerate(providers):
        name = f"p{i}"
        registry.add(name, BackendInfo(type="mobile_robot", url="local"))
        if place is not None:
            registry.set_location(name, np.array([*place, 0.0]))
        if state == "down":
            registry.set_state(name, "down")
        if dormant:
            registry.set_dormant(name, True)
    assessments = draw(
        st.lists(st.tuples(st.integers(0, n - 1).map("p{}".format), st.floats(0, 1)), max_size=6)
    )
    wanted, count, location, weight = draw(REQUESTS)
    request = Request(
        "consumer",
        frozenset(wanted),
        count=count,
        location=None if location is None else np.array(location),
        duration=10.0,
        weight=weight,
    )
    return registry, assessments, request


def decide(scheduler: Scheduler, request: Request, providers: list) -> tuple[str, ...] | str:  # type: ignore[type-arg]
    try:
        plan = scheduler.submit(request, providers, 0.0)
    except PropertyError as e:
        return type(e).__name__
    assert isinstance(plan, Plan)
    return plan.providers


@settings(max_examples=200, deadline=None)
@given(registries())
def test_the_narrowed_providers_give_the_same_decision_as_all_of_them(case) -> None:  # type: ignore[no-untyped-def]
    registry, assessments, request = case
    dispatcher = registry._dispatcher
    for name, score in assessments:
        dispatcher.scheduler.qos.record(name, score)
    narrowed, scale = dispatcher.providers_for(request, None)
    every = dispatcher.providers()
    scaled = replace(request, cost_scale=scale)
    full = Scheduler()
    for name, score in assessments:
        full.qos.record(name, score)
    assert decide(dispatcher.scheduler, scaled, narrowed) == decide(full, scaled, every)
    assert len(narrowed) <= len(every)
