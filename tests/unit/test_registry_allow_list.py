"""The ``[registry] allow`` list: its syntax, what it admits, and what it refuses before any connection."""

from __future__ import annotations

import pytest
from support.group_support import MemoryDirectory, sim_robot

from services.apps.registry import AllowList, Registry, RegistryService, parse_allow_entry
from services.kernel.errors import Code, InvalidArgument, PropertyError


@pytest.mark.parametrize(
    ("entry", "url", "admitted"),
    [
        ("127.0.0.0/8", "tcp://127.0.0.5:7001", True),
        ("127.0.0.0/8", "tcp://10.0.0.1:7001", False),
        ("10.0.0.0/8:7000-7100", "tcp://10.2.3.4:7100", True),
        ("10.0.0.0/8:7000-7100", "tcp://10.2.3.4:7101", False),
        ("192.168.1.5:7001", "grpc://192.168.1.5:7001/bot", True),
        ("::1", "grpc://[::1]:50051", True),
        ("[fd00::/8]:7000-7001", "tcp://[fd00::7]:7001", True),
        ("[fd00::/8]:7000-7001", "tcp://[fd00::7]:7002", False),
        ("serial:/dev/ttyUSB*", "serial:///dev/ttyUSB3?baudrate=9600", True),
        ("serial:/dev/ttyUSB*", "serial:///dev/pts/3", False),
    ],
)
async def test_an_entry_admits_its_addresses_only(entry: str, url: str, admitted: bool) -> None:
    allow = AllowList([entry])
    if admitted:
        await allow.check("x", url)
        return
    with pytest.raises(PropertyError) as info:
        await allow.check("x", url)
    assert info.value.code is Code.PERMISSION_DENIED


@pytest.mark.parametrize(
    "entry", ["10.0.0.0/33", "host.example", "10.0.0.0/8:0", "10.0.0.0/8:9-1", "serial:ttyS0"]
)
def test_a_bad_entry_is_refused(entry: str) -> None:
    with pytest.raises(InvalidArgument):
        parse_allow_entry(entry)


async def test_the_gateway_itself_is_a_loop_and_a_reserved_line_is_never_registrable() -> None:
    allow = AllowList(own_ports=lambda: [50051], reserved_paths=["/dev/ttyUSB0"])
    for url in ("grpc://127.0.0.1:50051", "grpc://localhost:50051/bot", "tcp://0.0.0.0:50051"):
        with pytest.raises(PropertyError) as info:
            await allow.check("x", url)
        assert info.value.code is Code.INVALID_ARGUMENT
    with pytest.raises(PropertyError) as info:
        await allow.check("x", "serial:///dev/ttyUSB0")
    assert info.value.code is Code.PERMISSION_DENIED


async def test_registrations_are_bounded_and_configured_services_stay() -> None:
    directory = MemoryDirectory()
    for port in (7001, 7002, 7003, 7009):
        directory.devices[f"tcp://127.0.0.1:{port}"] = lambda: sim_robot(1, 1)
    await directory.register("bot", "tcp://127.0.0.1:7009")  # a configured proxy
    registry = Registry(directory=directory, period=0, static=["bot"], max_registrations=2)
    service = RegistryService(registry)
    await directory.add("registry", service)
    try:
        await service.set("services.a", "tcp://127.0.0.1:7001")
        await service.set("services.b", "tcp://127.0.0.1:7002")
        with pytest.raises(PropertyError) as info:
            await service.set("services.c", "tcp://127.0.0.1:7003")
        assert info.value.code is Code.RESOURCE_EXHAUSTED
        assert "c" not in directory.names()
        with pytest.raises(PropertyError) as info:
            await service.set("services.bot", "")
        assert info.value.code is Code.PERMISSION_DENIED
        assert "bot" in directory.names()
        registry.set_admin_check(lambda name: name == "bot")
        await service.set("services.bot", "")
        assert "bot" not in directory.names()
    finally:
        await directory.aclose()
