"""A user's own Property Service class, named by import path in a config, served by a real gateway."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import grpc
import pytest
from support.gateway_process import ROOT, GatewayProcess

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

#: The class, as a module of the user's own outside the project.
LAMP = (ROOT / "tests" / "support" / "lamp.py").read_text(encoding="utf-8")


@pytest.fixture
def lamp_module(tmp_path: Path) -> Path:
    (tmp_path / "lamps.py").write_text(LAMP)
    return tmp_path


async def test_a_class_named_by_import_path_is_served(lamp_module: Path) -> None:
    config = lamp_module / "site.toml"
    config.write_text('[[services]]\nname = "lamp"\ntype = "lamps:Lamp"\n')
    env = {"PYTHONPATH": os.pathsep.join([str(lamp_module), str(ROOT)])}
    gw = GatewayProcess(
        [sys.executable, "-m", "gateway.cli", "serve", "--config", str(config), "--listen", "127.0.0.1:0"],
        env=env,
    )
    try:
        gw.wait_ready()
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            props = await stub.Get(pb.GetRequest(service="lamp", property="properties"), timeout=10)
            assert props.value == "(on watts blink)"
            await stub.Set(pb.SetRequest(service="lamp", property="on", value="true"), timeout=10)
            assert (await stub.Get(pb.GetRequest(service="lamp", property="on"), timeout=10)).value == "true"
            blink = pb.SetRequest(service="lamp", property="blink", value="3", parameters={"period": "0.2"})
            assert (await stub.Set(blink, timeout=10)).value == "blinking 3 times every 0.2 s"
            with pytest.raises(grpc.aio.AioRpcError) as err:
                await stub.Set(pb.SetRequest(service="lamp", property="watts", value="5"), timeout=10)
            assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION
            kind = await stub.Get(
                pb.GetRequest(service="registry", property="services.lamp.type"), timeout=10
            )
            assert kind.value == "light"
    finally:
        gw.stop()


def test_a_wrong_import_path_is_a_config_error(lamp_module: Path) -> None:
    config = lamp_module / "site.toml"
    config.write_text(
        textwrap.dedent("""
            [[services]]
            name = "lamp"
            type = "lamps:Lantern"
        """)
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(lamp_module), str(ROOT)])}
    done = subprocess.run(
        [sys.executable, "-m", "gateway.cli", "check-config", str(config)],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
        cwd=ROOT,
        check=False,
    )
    assert done.returncode == 2
    assert "'lamps' has no 'Lantern'" in done.stderr
