"""What an attack must leave alone: a gateway process's memory, a bystander's Get latency, and
the registry's view of a service; measured the same way by every test that tries an attack."""

from __future__ import annotations

import time

import grpc

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 10.0


def rss_mb(pid: int) -> float:
    """Resident memory of process ``pid`` in MiB (Linux ``/proc``)."""
    with open(f"/proc/{pid}/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise AssertionError(f"no VmRSS for process {pid}")


async def get_p99(stub: pb_grpc.PropertyServiceStub, service: str, prop: str, count: int = 100) -> float:
    """The 99th percentile, in seconds, of ``count`` Gets of ``service`` ``prop`` in a row."""
    times = []
    for _ in range(count):
        began = time.perf_counter()
        await stub.Get(pb.GetRequest(service=service, property=prop), timeout=WAIT)
        times.append(time.perf_counter() - began)
    times.sort()
    return times[int(0.99 * (len(times) - 1))]


async def registry_state(stub: pb_grpc.PropertyServiceStub, name: str) -> str:
    """``services.<name>.state`` in the registry, or the status code's name when that fails."""
    try:
        reply = await stub.Get(
            pb.GetRequest(service="registry", property=f"services.{name}.state"), timeout=WAIT
        )
    except grpc.aio.AioRpcError as exc:
        return exc.code().name
    return str(reply.value)
