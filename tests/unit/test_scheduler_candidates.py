"""Narrowing the providers with numpy never changes the scheduler's decision."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from services.backend import BackendInfo
from services.errors import PropertyError
from services.registry import Registry
from services.registry.scheduling import Plan, Request, Scheduler

CAPS = ("survey", "video", "ptz", "power")


@st.composite
def registries(draw: st.DrawFn) -> tuple[Registry, list[tuple[str, float]], Request]:
    n = draw(st.integers(1, 40))
    features = {}
    for i in range(n):
        features[f"p{i}"] = tuple(draw(st.sets(st.sampled_from(CAPS), max_size=3)))
    registry = Registry(period=0, features=features)
    for i in range(n):
        name = f"p{i}"
        registry.add(name, BackendInfo(type="mobile_robot", url="local"))
        if draw(st.booleans()):
            registry.set_location(name, np.array([draw(st.floats(-50, 50)), draw(st.floats(-50, 50)), 0.0]))
        state = draw(st.sampled_from(["up", "up", "up", "down"]))
        if state == "down":
            registry.set_state(name, "down")
        if draw(st.integers(0, 5)) == 0:
            registry.set_dormant(name, True)
    assessments = [
        (f"p{draw(st.integers(0, n - 1))}", draw(st.floats(0, 1))) for _ in range(draw(st.integers(0, 6)))
    ]
    wanted = frozenset(draw(st.sets(st.sampled_from(CAPS), min_size=1, max_size=3)))
    request = Request(
        "consumer",
        wanted,
        count=draw(st.integers(1, 3)),
        location=np.array([draw(st.floats(-50, 50)), draw(st.floats(-50, 50))])
        if draw(st.booleans())
        else None,
        duration=10.0,
        weight=draw(st.sampled_from([0.0, 0.5, 1.0])),
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
