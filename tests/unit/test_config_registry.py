"""``[registry]`` and groups in the gateway config; ``services.apps.catalog`` and the gateway's directory."""

from __future__ import annotations

from pathlib import Path

import pytest

from gateway.backends import open_backend
from gateway.cli import main
from gateway.config import ConfigError, RegistrySection, default_config, load_config, loads_config
from gateway.engine.router import Router
from services.apps.catalog import create, needs_directory
from services.apps.group import Group
from services.kernel.core import LocalService
from services.kernel.errors import InvalidArgument


def test_registry_settings_default_to_the_registry_s_own() -> None:
    assert loads_config("").registry == RegistrySection(period=5.0, timeout=2.0, misses=3, grace=60.0)


def test_registry_settings_are_read_and_persist_is_taken_from_the_config_folder(tmp_path: Path) -> None:
    path = tmp_path / "site.toml"
    path.write_text(
        '[registry]\nperiod = 0.5\ntimeout = 1\nmisses = 2\ngrace = 10\npersist = "state/reg.json"\n'
    )
    section = load_config(path).registry
    assert (section.period, section.timeout, section.misses, section.grace) == (0.5, 1.0, 2, 10.0)
    assert section.persist == str(tmp_path / "state" / "reg.json")
    absolute = tmp_path / "elsewhere.json"
    assert loads_config(f'[registry]\npersist = "{absolute}"').registry.persist == str(absolute)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[registry]\nperiod = -1", "registry.period: must not be negative"),
        ("[registry]\ntimeout = 0", "registry.timeout: must be a positive number of seconds"),
        ("[registry]\nmisses = 0", "registry.misses: must be at least 1"),
        ("[registry]\nmisses = 1.5", "registry.misses: expected an integer"),
        ("[registry]\ngrace = inf", "registry.grace: must be a finite number"),
        ('[registry]\nperiod = "often"', "registry.period: expected a number"),
        ("[registry]\nlease = 3", "registry.lease: unknown key"),
        ("[registry]\nmax_licences_per_holder = 0", "registry.max_licences_per_holder: must be at least 1"),
        ("registry = 3", "registry: expected a table"),
    ],
)
def test_bad_registry_settings_are_refused_by_key(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        loads_config(text, "site.toml")


def test_persist_naming_a_folder_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="is a folder"):
        loads_config(f'[registry]\npersist = "{tmp_path}"')


def test_the_catalog_hands_a_directory_only_to_groups() -> None:
    router = Router()
    assert needs_directory("group") and not needs_directory("sim-robot") and not needs_directory("nope")
    group = create("group", directory=router.directory, members=["a", "b"])
    assert isinstance(group, Group)
    assert create("sim-robot", directory=router.directory, start=[1, 2]).location[:2].tolist() == [1.0, 2.0]
    with pytest.raises(InvalidArgument, match="runs only inside a gateway"):
        create("group", members=["a"])
    with pytest.raises(InvalidArgument, match="'within' is not an option"):
        create("group", directory=router.directory, within="x")
    with pytest.raises(InvalidArgument, match="it accepts: members, query, registry, member_timeout"):
        create("group", directory=router.directory, colour="red")


def test_group_entries_build_a_group_over_the_router_s_directory() -> None:
    cfg = loads_config(
        """
        [[services]]
        name = "pair"
        type = "group"
        options = { members = ["scout1", "scout2"] }

        [[services]]
        name = "near"
        type = "group"
        options = { query = { type = "mobile_robot", near = [5, 5, 0], radius = 3 }, member_timeout = 1.5 }
        """
    )
    router = Router()
    pair, near = (open_backend(entry, router.directory) for entry in cfg.services)
    assert isinstance(pair, LocalService) and isinstance(near, LocalService)
    assert isinstance(near.obj, Group)
    assert near.obj.query == "type=mobile_robot&near=(5 5 0)&radius=3"
    assert near.obj.member_timeout == 1.5
    assert pair.info.type == "group"


def test_a_group_with_a_bad_query_is_a_clear_error() -> None:
    cfg = loads_config('[[services]]\nname = "g"\ntype = "group"\noptions = { query = { colour = "red" } }')
    with pytest.raises(InvalidArgument, match="unknown query parameter 'colour'"):
        open_backend(cfg.services[0], Router().directory)


def test_a_group_cannot_be_a_device_process() -> None:
    with pytest.raises(ConfigError, match=r"devices\[0\] \(g\)\.type: a 'group' reaches other services"):
        loads_config('[[devices]]\nname = "g"\ntype = "group"\ntcp = "127.0.0.1:0"')


def test_the_demo_has_a_swarm_of_every_mobile_robot() -> None:
    (swarm,) = [s for s in default_config().services if s.name == "swarm"]
    assert (swarm.type, dict(swarm.options)) == ("group", {"query": {"type": "mobile_robot"}})


def test_check_config_builds_groups_and_device_options(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(
        """
        [[services]]
        name = "swarm"
        type = "group"
        options = { query = { type = "mobile_robot", colour = "red" } }

        [[devices]]
        name = "rover1"
        type = "sim-robot"
        tcp = "127.0.0.1:0"
        options = { spede = 1 }
        """
    )
    assert main(["check-config", str(bad)]) == 2
    out = capsys.readouterr().err
    assert "services (swarm): bad options for 'group': unknown query parameter 'colour'" in out
    assert "devices (rover1): bad options for 'sim-robot'" in out and "speed" in out
    good = tmp_path / "good.toml"
    good.write_text(
        """
        [registry]
        period = 1
        [[services]]
        name = "swarm"
        type = "group"
        options = { members = ["rover1"] }
        [[devices]]
        name = "rover1"
        type = "sim-robot"
        tcp = "127.0.0.1:0"
        options = { start = [1, 2] }
        """
    )
    assert main(["check-config", str(good)]) == 0
    assert "fine (1 services, 1 devices" in capsys.readouterr().out


def test_check_config_says_how_many_services_a_services_state_listen_follows(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    site = tmp_path / "site.toml"
    site.write_text("[limits]\nmax_stream_properties = 20001\n")
    assert main(["check-config", str(site)]) == 0
    said = capsys.readouterr().out
    assert "a Listen matches at most 20001 properties (limits.max_stream_properties)" in said
    assert "registry services.*.state follows at most 20000 services" in said
