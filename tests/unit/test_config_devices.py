"""``[[devices]]`` in the gateway configuration: what is accepted, what is refused and why."""

from __future__ import annotations

import pytest

from gateway.config import ConfigError, default_config, loads_config
from gateway.devices import device_command


def test_devices_are_read_with_their_defaults() -> None:
    cfg = loads_config(
        """
        [[devices]]
        name = "rover1"
        type = "sim-robot"
        tcp = "127.0.0.1:0"
        options = { start = [3.0, 0.0] }
        proxy = { timeout = 2.0 }

        [[devices]]
        name = "rover2"
        type = "sim-sensor"
        serial = "pty"
        baudrate = 9600
        """
    )
    one, two = cfg.devices
    assert (one.name, one.type, one.tcp, one.serial) == ("rover1", "sim-robot", "127.0.0.1:0", "")
    assert one.options == {"start": [3.0, 0.0]} and one.proxy == {"timeout": 2.0}
    assert (two.serial, two.baudrate, two.tcp, two.options) == ("pty", 9600, "", {})
    assert device_command(one)[-2:] == ["--tcp", "127.0.0.1:0"]
    assert device_command(two)[-1] == "--pty"


def test_a_devices_proxy_maxline_is_its_processs_max_line_too() -> None:
    # Large binary values (docs/line-protocol.md §11): both ends take the longer lines.
    cfg = loads_config(
        """
        [[devices]]
        name = "cam"
        type = "sim-sensor"
        tcp = "127.0.0.1:0"
        proxy = { maxline = 1048576 }
        """
    )
    (cam,) = cfg.devices
    command = device_command(cam)
    assert command[command.index("--max-line") + 1] == "1048576"


def test_the_demo_has_a_tcp_and_a_serial_device() -> None:
    devices = default_config().devices
    assert [(d.name, bool(d.tcp), d.serial) for d in devices] == [
        ("rover1", True, ""),
        ("rover2", False, "pty"),
    ]


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        ('type = "sim-robot"\ntcp = "127.0.0.1:0"', "missing key 'name'"),
        ('name = "r"\ntcp = "127.0.0.1:0"', "missing key 'type'"),
        ('name = "r"\ntype = "toaster"\ntcp = "127.0.0.1:0"', "unknown service type 'toaster'"),
        ('name = "r"\ntype = "sim-robot"', "exactly one of 'tcp'"),
        ('name = "r"\ntype = "sim-robot"\ntcp = "127.0.0.1:0"\nserial = "pty"', "exactly one of 'tcp'"),
        ('name = "r"\ntype = "sim-robot"\ntcp = "localhost"', "expected host:port"),
        ('name = "r"\ntype = "sim-robot"\nserial = "/dev/ttyUSB0"', "only 'pty'"),
        ('name = "r"\ntype = "sim-robot"\nserial = "pty"\nbaudrate = 0', "baudrate: must be positive"),
        ('name = "r"\ntype = "sim-robot"\nserial = "pty"\noptions = 3', "options: expected a table"),
        ('name = "r"\ntype = "sim-robot"\nserial = "pty"\ncolour = "red"', "colour: unknown key"),
        ('name = "scout1"\ntype = "sim-robot"\nserial = "pty"', "duplicate service name 'scout1'"),
        ('name = "registry"\ntype = "sim-robot"\nserial = "pty"', "reserved"),
    ],
)
def test_bad_device_entries_are_refused_naming_the_key(entry: str, message: str) -> None:
    text = f'[[services]]\nname = "scout1"\ntype = "sim-robot"\n\n[[devices]]\n{entry}\n'
    with pytest.raises(ConfigError, match="devices\\[0\\]") as info:
        loads_config(text, "site.toml")
    assert message in str(info.value)
    assert str(info.value).startswith("site.toml: ")


def test_device_start_timeout_defaults_to_30_s_and_must_be_positive() -> None:
    assert default_config().gateway.device_start_timeout == 30.0
    assert loads_config("[gateway]\ndevice_start_timeout = 90\n").gateway.device_start_timeout == 90.0
    with pytest.raises(ConfigError, match=r"device_start_timeout: must be a positive number of seconds"):
        loads_config("[gateway]\ndevice_start_timeout = 0\n")
