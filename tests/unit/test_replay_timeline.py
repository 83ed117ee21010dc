"""A replay's timeline on a fake clock: position, speed, pause, seek and the wait for a change."""

from __future__ import annotations

from services.apps.replay.timeline import Timeline


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_a_playing_timeline_moves_with_the_clock_times_its_speed_and_stops_at_the_end() -> None:
    clock = FakeClock()
    timeline = Timeline(10.0, clock)
    assert timeline.position() == 0.0
    timeline.play()
    clock.now += 2.0
    assert timeline.position() == 2.0
    timeline.set_speed(3.0)
    clock.now += 1.0
    assert timeline.position() == 5.0
    clock.now += 100.0
    assert timeline.position() == 10.0


def test_a_paused_timeline_holds_its_position_and_waits_for_nothing() -> None:
    clock = FakeClock()
    timeline = Timeline(10.0, clock)
    timeline.play()
    clock.now += 4.0
    timeline.pause()
    clock.now += 50.0
    assert timeline.position() == 4.0
    assert timeline.wait_until(6.0) is None
    assert timeline.wait_until(3.0) == 0.0


def test_a_seek_moves_the_position_within_the_recording_and_the_wait_follows_the_speed() -> None:
    clock = FakeClock()
    timeline = Timeline(10.0, clock)
    timeline.seek(8.0)
    assert timeline.position() == 8.0
    timeline.seek(-3.0)
    assert timeline.position() == 0.0
    timeline.seek(30.0)
    assert timeline.position() == 10.0
    timeline.seek(2.0)
    timeline.set_speed(4.0)
    timeline.play()
    assert timeline.wait_until(6.0) == 1.0
    clock.now += 0.5
    assert timeline.wait_until(6.0) == 0.5
