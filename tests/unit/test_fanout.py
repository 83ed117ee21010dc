"""services.kernel.backend.tell_each: the one fan-out, and what it does with a listener that raises."""

from __future__ import annotations

import pytest

from gateway.engine.listen.topics import Topic, TopicChange
from services.kernel.backend import Change, OnRaise, tell_each
from tests.support.fake_backend import DictBackend


def _broken(change: Change) -> None:
    raise RuntimeError("listener bug")


def test_a_listener_that_raises_is_dropped_when_the_caller_says_so(caplog: pytest.LogCaptureFixture) -> None:
    heard: list[str] = []
    listeners = {1: _broken, 2: lambda change: heard.append(change.value)}
    tell_each(listeners, Change("speed", "1"), what="speed", on_raise=OnRaise.DROP)
    tell_each(listeners, Change("speed", "2"), what="speed", on_raise=OnRaise.DROP)
    assert heard == ["1", "2"]
    assert list(listeners) == [2]
    assert "a listener of speed failed; it is dropped" in caplog.text
    assert caplog.text.count("it is dropped") == 1


def test_a_listener_that_raises_keeps_its_place_when_the_caller_says_so(
    caplog: pytest.LogCaptureFixture,
) -> None:
    heard: list[str] = []
    listeners = {1: _broken, 2: lambda change: heard.append(change.value)}
    tell_each(listeners, Change("speed", "1"), what="speed", on_raise=OnRaise.KEEP)
    tell_each(listeners, Change("speed", "2"), what="speed", on_raise=OnRaise.KEEP)
    assert heard == ["1", "2"]
    assert list(listeners) == [1, 2]
    assert caplog.text.count("a listener of speed failed; it keeps its place") == 2


def test_a_listener_that_leaves_during_the_fan_out_does_not_disturb_it() -> None:
    heard: list[str] = []
    listeners: dict[int, object] = {}

    def leave(change: Change) -> None:
        heard.append("left")
        listeners.pop(2)  # the one after it: it was in the list when the change came

    listeners.update({1: leave, 2: lambda change: heard.append(change.value)})
    tell_each(listeners, Change("speed", "1"), what="speed", on_raise=OnRaise.DROP)  # type: ignore[arg-type]
    assert heard == ["left", "1"] and list(listeners) == [1]


class _Sink:
    def __init__(self, broken: bool) -> None:
        self.broken = broken
        self.heard: list[tuple[Topic, str]] = []

    def topic_changed(self, news: TopicChange) -> None:
        topic, change, _ = news
        self.heard.append((topic, str(change.value)))
        if self.broken:
            raise RuntimeError("sink bug")


def test_a_topic_sink_that_raises_keeps_hearing_the_topic_and_the_others_hear_it_too(
    caplog: pytest.LogCaptureFixture,
) -> None:
    topic = Topic(("scout1", "speed", ()), DictBackend({"speed": "0"}))
    broken, good = _Sink(broken=True), _Sink(broken=False)
    topic.sinks[broken] = broken.topic_changed
    topic.sinks[good] = good.topic_changed
    topic.notify(Change("speed", "1"))
    topic.notify(Change("speed", "2"))
    assert broken.heard == good.heard == [(topic, "1"), (topic, "2")]
    assert topic.value == "2"
    assert "a listener of scout1/speed failed; it keeps its place" in caplog.text
