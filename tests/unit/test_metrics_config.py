"""The ``[metrics]`` section: its defaults, a listener of its own, and what it refuses."""

from __future__ import annotations

import pytest

from gateway.config import ConfigError, MetricsSection, parse_config


def test_metrics_are_on_by_default_with_no_port_of_their_own() -> None:
    assert parse_config({}).metrics == MetricsSection(enabled=True, listen="")


def test_a_loopback_port_of_their_own_and_off() -> None:
    assert parse_config({"metrics": {"listen": "127.0.0.1:9464"}}).metrics.listen == "127.0.0.1:9464"
    assert parse_config({"metrics": {"enabled": False}}).metrics.enabled is False


@pytest.mark.parametrize(
    ("section", "says"),
    [
        ({"listen": "0.0.0.0:9464"}, "reachable from other machines"),
        ({"listen": "nowhere"}, "metrics.listen"),
        ({"enabled": "yes"}, "enabled"),
        ({"port": 9464}, "port"),
    ],
)
def test_bad_metrics_sections_are_refused_naming_the_key(section: dict[str, object], says: str) -> None:
    with pytest.raises(ConfigError) as refused:
        parse_config({"metrics": section})
    assert says in str(refused.value), refused.value


def test_off_loopback_is_accepted_when_insecure_remote_is_allowed() -> None:
    config = parse_config({"gateway": {"allow_insecure_remote": True}, "metrics": {"listen": "0.0.0.0:9464"}})
    assert config.metrics.listen == "0.0.0.0:9464"
