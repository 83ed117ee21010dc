"""The gateway's TOML configuration: defaults, the demo, and a clear error for every mistake."""

from __future__ import annotations

from pathlib import Path

import pytest

from gateway.backends import PROXY_SCHEMES, open_proxy
from gateway.config import ConfigError, default_config, load_config, loads_config
from services.kernel.errors import InvalidArgument

FULL = """
[gateway]
listen = "127.0.0.1:0"
line_listen = "127.0.0.1:7000"
call_timeout = 2
log_level = "DEBUG"

[limits]
max_streams = 10
min_interval_floor = 0.01

[[services]]
name = "scout1"
type = "sim-robot"
options = { start = [0.0, 0.0], speed = 0.5 }

[[services]]
name = "arm"
url = "tcp://127.0.0.1:7001"
"""


def test_a_full_config_reads_back() -> None:
    cfg = loads_config(FULL, "site.toml")
    assert cfg.gateway.listen == "127.0.0.1:0"
    assert cfg.gateway.line_listen == "127.0.0.1:7000"
    assert cfg.gateway.call_timeout == 2.0
    assert cfg.gateway.log_level == "debug"
    assert cfg.limits.max_streams == 10
    assert cfg.limits.min_interval_floor == 0.01
    assert cfg.limits.max_batch == 256  # untouched defaults stay
    assert [(s.name, s.type, s.url) for s in cfg.services] == [
        ("scout1", "sim-robot", ""),
        ("arm", "", "tcp://127.0.0.1:7001"),
    ]
    assert cfg.services[0].options == {"start": [0.0, 0.0], "speed": 0.5}


def test_the_demo_config() -> None:
    cfg = default_config()
    assert cfg.gateway.listen == "127.0.0.1:50051"
    assert [(s.name, s.type) for s in cfg.services] == [
        ("scout1", "sim-robot"),
        ("scout2", "sim-robot"),
        ("thermo1", "sim-sensor"),
        ("swarm", "group"),
        ("files", "storage"),
        ("missions", "statemachine"),
        ("camera1", "camera"),
        ("scout1cam", "camera"),
        ("environment", "environment"),
        ("recorder", "recorder"),
    ]
    assert [(d.name, d.tcp or d.serial) for d in cfg.devices] == [
        ("rover1", "127.0.0.1:0"),
        ("rover2", "pty"),
    ]
    assert cfg.services[1].options["start"] == [1.0, 0.0]


def test_overrides_from_the_command_line() -> None:
    cfg = default_config().with_overrides(listen="127.0.0.1:0", log_level="warning")
    assert (cfg.gateway.listen, cfg.gateway.log_level) == ("127.0.0.1:0", "warning")
    with pytest.raises(ConfigError, match="--listen"):
        default_config().with_overrides(listen="nowhere")


@pytest.mark.parametrize(
    ("text", "where"),
    [
        ('[gateway]\nlisten = "127.0.0.1:1"\nport = 3', "gateway.port: unknown key"),
        ("[gateway]\ncall_timeout = 'soon'", "gateway.call_timeout: expected a number"),
        ("[gateway]\ncall_timeout = 0", "gateway.call_timeout: must be a positive number of seconds"),
        ("[gateway]\nlisten = '50051'", "gateway.listen: expected host:port"),
        ("[gateway]\nlog_level = 'loud'", "gateway.log_level: expected one of"),
        ("[limits]\nmax_streams = true", "limits.max_streams: expected an integer"),
        ("[limits]\nmax_batch = 0", "limits.max_batch: must be at least 1"),
        ("[limits]\nmax_calls = 0", "limits.max_calls: must be at least 1"),
        (
            "[limits]\nline_max_connections_per_address = 0",
            "limits.line_max_connections_per_address: must be",
        ),
        ("[gateway]\nmax_connections = 0", "gateway.max_connections: must be at least 1"),
        ("[gateway]\nhandshake_timeout = 0", "gateway.handshake_timeout: must be a positive number"),
        ("[gateway]\nidle_timeout = inf", "gateway.idle_timeout: must be a positive number"),
        ('[http]\nlisten = "127.0.0.1:0"\nmax_connections = 0', "http.max_connections: must be at least 1"),
        (
            '[http]\nlisten = "127.0.0.1:0"\nmax_connections_per_address = 0',
            "http.max_connections_per_address",
        ),
        ('[http]\nlisten = "127.0.0.1:0"\nidle_timeout = 0.0', "http.idle_timeout: must be a positive"),
        ("[limit]\nmax_batch = 1", "unknown key 'limit'"),
        (
            '[[services]]\nname = "a"\ntype = "sim-robot"\n[[services]]\nname = "a"\ntype = "sim-robot"',
            "duplicate",
        ),
        ('[[services]]\nname = "a.b"\ntype = "sim-robot"', "services[0].name: bad service name"),
        ('[[services]]\nname = "registry"\ntype = "sim-robot"', "reserved"),
        ('[[services]]\nname = "a"', "exactly one of 'type'"),
        ('[[services]]\nname = "a"\ntype = "x"\nurl = "tcp://h:1"', "exactly one of 'type'"),
        ('[[services]]\nname = "a"\nurl = "127.0.0.1:7001"', "scheme://address"),
        ('[[services]]\nname = "a"\ntype = "x"\ncolour = 1', "services[0].colour: unknown key"),
        ('[[services]]\ntype = "x"', "missing key 'name'"),
        ("services = 3", "expected an array of tables"),
        ("[gateway\n", "not valid TOML"),
    ],
)
def test_mistakes_name_the_file_and_key(text: str, where: str) -> None:
    with pytest.raises(ConfigError) as err:
        loads_config(text, "site.toml")
    assert str(err.value).startswith("site.toml")
    assert where in str(err.value)


def test_load_config_from_a_file(tmp_path: Path) -> None:
    path = tmp_path / "gw.toml"
    path.write_text('[gateway]\nlisten = "127.0.0.1:0"\n')
    assert load_config(path).source == str(path)
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.toml")


def test_unknown_url_scheme_is_a_clear_error() -> None:
    assert "nope" not in PROXY_SCHEMES
    with pytest.raises(InvalidArgument, match="unknown URL scheme"):
        open_proxy("arm", "nope://somewhere", {})


def test_websocket_origins_are_read_as_origins_and_anything_else_is_refused() -> None:
    config = loads_config(
        '[http]\nwebsocket_origins = ["https://app.foxglove.dev", "http://localhost:5173"]\n'
    )
    assert config.http.websocket_origins == ("https://app.foxglove.dev", "http://localhost:5173")
    assert loads_config("").http.websocket_origins == ()
    with pytest.raises(ConfigError, match="expected an array of origins"):
        loads_config('[http]\nwebsocket_origins = "https://app.foxglove.dev"\n')
    with pytest.raises(ConfigError, match="is no origin"):
        loads_config('[http]\nwebsocket_origins = ["app.foxglove.dev"]\n')
