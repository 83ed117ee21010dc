"""The gateway as a real process: the demo robots and sensor through the generated stub."""

from __future__ import annotations

import asyncio
import shutil
import subprocess
import sys

import grpc
import pytest
from google.protobuf.duration_pb2 import Duration
from support.gateway_process import ROOT, GatewayProcess

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 10.0

FAST_ROBOT = """
[[services]]
name = "rover"
type = "sim-robot"
options = { start = [0.0, 0.0], speed = 20.0, tick_hz = 50.0 }
"""


async def rpc_error(awaitable) -> grpc.aio.AioRpcError:
    with pytest.raises(grpc.aio.AioRpcError) as err:
        await awaitable
    return err.value


async def test_get_on_the_demo_robots(demo_gateway: GatewayProcess) -> None:
    async with grpc.aio.insecure_channel(demo_gateway.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        reply = await stub.Get(
            pb.GetRequest(
                service="scout1",
                property="location",
                more=[pb.PropertyRef(service="scout2", property="location")],
            )
        )
        assert reply.value == "(0 0 0 0 0 0)"
        assert [(m.service, m.value) for m in reply.more] == [("scout2", "(1 0 0 0 0 0)")]
        assert (
            "behaviors.moveto"
            in (await stub.Get(pb.GetRequest(service="scout1", property="properties"))).value
        )


async def test_registry_lists_every_service_and_itself(demo_gateway: GatewayProcess) -> None:
    async with grpc.aio.insecure_channel(demo_gateway.address) as channel:
        listing = (
            await pb_grpc.PropertyServiceStub(channel).Get(
                pb.GetRequest(service="registry", property="properties")
            )
        ).value
    for name in ("registry", "scout1", "scout2", "thermo1"):
        assert f"services.{name}" in listing


async def test_errors_have_precise_codes(demo_gateway: GatewayProcess) -> None:
    async with grpc.aio.insecure_channel(demo_gateway.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        err = await rpc_error(stub.Get(pb.GetRequest(service="scoot1", property="location")))
        assert err.code() == grpc.StatusCode.NOT_FOUND
        assert "scout1" in err.details()
        err = await rpc_error(stub.Get(pb.GetRequest(service="scout1", property="nothing")))
        assert err.code() == grpc.StatusCode.NOT_FOUND
        err = await rpc_error(stub.Get(pb.GetRequest(service="scout1", property="location..x")))
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
        bad_target = "<marker><location>(1 x)</location></marker>"
        err = await rpc_error(
            stub.Set(pb.SetRequest(service="scout1", property="behaviors.moveto", value=bad_target))
        )
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
        err = await rpc_error(
            stub.Set(pb.SetRequest(service="scout1", property="location", value="(1 2 0 0 0 0)"))
        )
        assert err.code() == grpc.StatusCode.FAILED_PRECONDITION


async def test_a_malformed_service_name_is_invalid_in_every_call(demo_gateway: GatewayProcess) -> None:
    async with grpc.aio.insecure_channel(demo_gateway.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        for name in ("scout 1", "", "s" * 100_000, "scout1.x"):
            shown = repr(name[:20])
            err = await rpc_error(stub.Get(pb.GetRequest(service=name, property="location"), timeout=WAIT))
            assert err.code() == grpc.StatusCode.INVALID_ARGUMENT, (shown, err.details())
            assert len(err.details()) < 300
            err = await rpc_error(
                stub.Set(pb.SetRequest(service=name, property="behaviors.stop", value=""), timeout=WAIT)
            )
            assert err.code() == grpc.StatusCode.INVALID_ARGUMENT, (shown, err.details())
            # An empty service in `more` means the request's own service. (A huge one is left out:
            # the call layer repeats the whole name in the message of a failed `more` path.)
            if 0 < len(name) <= 64:
                err = await rpc_error(
                    stub.Get(
                        pb.GetRequest(
                            service="scout1",
                            property="location",
                            more=[pb.PropertyRef(service=name, property="x")],
                        ),
                        timeout=WAIT,
                    )
                )
                assert err.code() == grpc.StatusCode.INVALID_ARGUMENT, (shown, err.details())
            call = stub.Listen(pb.ListenRequest(service=name, property="location"), timeout=WAIT)
            err = await rpc_error(call.read())
            assert err.code() == grpc.StatusCode.INVALID_ARGUMENT, (shown, err.details())
        # A well-formed name that is not served stays NOT_FOUND.
        err = await rpc_error(
            stub.Set(pb.SetRequest(service="scout9", property="x", value="1"), timeout=WAIT)
        )
        assert err.code() == grpc.StatusCode.NOT_FOUND


async def test_moveto_streams_location_then_goes_quiet(gateway_process) -> None:
    gw = gateway_process(FAST_ROBOT)
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        options = pb.ListenOptions(heartbeat_interval=Duration(nanos=300_000_000))
        call = stub.Listen(pb.ListenRequest(service="rover", property="location", options=options))
        async with asyncio.timeout(WAIT):
            first = await call.read()
            assert [e.value for e in first.events] == ["(0 0 0 0 0 0)"]
            assert (await call.read()).sync
            target = "<marker><location>(2 0)</location></marker>"
            await stub.Set(pb.SetRequest(service="rover", property="behaviors.moveto", value=target))
            values: list[str] = []
            while not values or values[-1] != "(2 0 0 0 0 0)":
                msg = await call.read()
                values += [e.value for e in msg.events]
            assert len(values) >= 2  # it drove there, it did not jump
            quiet = await call.read()
            assert quiet.heartbeat and not quiet.events
        call.cancel()


async def test_wildcard_listen_over_every_service(demo_gateway: GatewayProcess) -> None:
    async with grpc.aio.insecure_channel(demo_gateway.address) as channel:
        call = pb_grpc.PropertyServiceStub(channel).Listen(
            pb.ListenRequest(service="*", property="sensors.*")
        )
        events: list[pb.Event] = []
        async with asyncio.timeout(WAIT):
            while not (msg := await call.read()).sync:
                events += msg.events
        assert {(e.service, e.property) for e in events} == {
            (robot, prop)
            for robot in ("scout1", "scout2", "rover1", "rover2")
            for prop in ("sensors.battery", "sensors.bumper", "sensors.temperature")
        }
        call.cancel()


async def test_a_client_that_vanishes_does_not_affect_another(gateway_process) -> None:
    gw = gateway_process(FAST_ROBOT)
    staying = grpc.aio.insecure_channel(gw.address)
    leaving = grpc.aio.insecure_channel(gw.address)
    request = pb.ListenRequest(service="rover", property="location")
    kept = pb_grpc.PropertyServiceStub(staying).Listen(request)
    dropped = pb_grpc.PropertyServiceStub(leaving).Listen(request)
    async with asyncio.timeout(WAIT):
        for call in (kept, dropped):
            while not (await call.read()).sync:
                pass
        await leaving.close(grace=None)
        stub = pb_grpc.PropertyServiceStub(staying)
        await stub.Set(
            pb.SetRequest(
                service="rover",
                property="behaviors.moveto",
                value="<marker><location>(1 1)</location></marker>",
            )
        )
        values: list[str] = []
        while not values or not values[-1].startswith("(1 1 0 0 0 "):
            msg = await kept.read()
            assert msg is not grpc.aio.EOF, f"the staying stream ended: {await kept.code()}"
            values += [e.value for e in msg.events]
    # The staying client saw the robot drive there, not only its final place.
    assert len(values) > 1 and values[0] != values[-1]
    kept.cancel()
    await staying.close()


async def test_sigterm_ends_streams_with_unavailable(gateway_process) -> None:
    gw = gateway_process(FAST_ROBOT)
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        listen = stub.Listen(pb.ListenRequest(service="rover", property="location"))
        session = stub.Session()
        await session.write(
            pb.SessionRequest(
                requests=[pb.Request(id=1, listen=pb.ListenRequest(service="rover", property="speed"))]
            )
        )
        async with asyncio.timeout(WAIT):
            while not (await listen.read()).sync:
                pass
            while not any(r.listen.sync for r in (await session.read()).replies):
                pass
            code = await asyncio.to_thread(gw.stop)
            for call in (listen, session):
                with pytest.raises(grpc.aio.AioRpcError) as ended:
                    while await call.read() is not grpc.aio.EOF:
                        pass
                assert ended.value.code() == grpc.StatusCode.UNAVAILABLE
                assert ended.value.details() == "gateway shutting down"
    assert code == 0
    assert "listening on" in gw.output


def test_reflection_lets_grpcurl_list_and_describe(demo_gateway: GatewayProcess) -> None:
    grpcurl = shutil.which("grpcurl")
    if grpcurl is None:
        pytest.skip("grpcurl is not installed")
    listed = subprocess.run(
        [grpcurl, "-plaintext", demo_gateway.address, "list"],
        check=False,
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert "propertyservice.v1.PropertyService" in listed.stdout
    assert "grpc.health.v1.Health" in listed.stdout
    described = subprocess.run(
        [grpcurl, "-plaintext", demo_gateway.address, "describe", "propertyservice.v1.PropertyService"],
        check=False,
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert "rpc Listen" in described.stdout


def test_config_errors_exit_with_code_2(tmp_path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[gateway]\nlisten = "127.0.0.1:0"\nspeed = 3\n')
    for args in (["serve", "--config", str(bad)], ["check-config", str(bad)]):
        done = subprocess.run(
            [sys.executable, "-m", "gateway.cli", *args],
            cwd=ROOT,
            check=False,
            capture_output=True,
            text=True,
            timeout=30,
        )
        assert done.returncode == 2
        assert "bad.toml" in done.stderr and "gateway.speed" in done.stderr
