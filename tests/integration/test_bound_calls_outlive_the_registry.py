"""When the registry's gateway fails, consumers already bound to their providers carry on.

Three real gateway processes: P serves the provider (a robot); R is the
registry where licences are acquired, serving the robot through federation
(``grpc://P/scout``); C is the consumer's own gateway, federated to P as well.
A licence held at R is enforced on calls through R, whatever the backend
(in-process, proxy, another gateway). Once R is stopped, the consumer's calls
through C to the provider go on, and so does its Listen; what needs R
(acquiring, renewing, releasing, finding) is UNAVAILABLE.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import jwt
import pytest
from support.waiting import eventually, wait_until

from clients import AsyncClient, ClientCredentials
from clients.errors import FailedPrecondition, Unavailable

SECRET = "a shared secret of the lab, long enough for HS256"


def credentials(subject: str) -> ClientCredentials:
    return ClientCredentials(
        token=jwt.encode({"sub": subject, "exp": int(time.time()) + 600}, SECRET, algorithm="HS256")
    )


async def test_calls_to_licensed_providers_go_on_while_the_registry_gateway_is_down(
    gateway_process,  # type: ignore[no-untyped-def]
    tmp_path: Path,
) -> None:
    (tmp_path / "jwt.secret").write_text(SECRET)
    provider = gateway_process(
        """
        [[services]]
        name = "scout"
        type = "sim-robot"
        """
    )
    federated = f"""
        [auth]
        jwt_secret_file = "jwt.secret"

        [[services]]
        name = "scout"
        url = "grpc://{provider.address}/scout"
        """
    registry = gateway_process(federated)
    consumer = gateway_process(federated)

    async with (
        AsyncClient(registry.address, credentials=credentials("alice")) as alice_at_registry,
        AsyncClient(registry.address, credentials=credentials("bob")) as bob_at_registry,
        AsyncClient(consumer.address, credentials=credentials("alice")) as alice,
    ):
        await eventually(
            lambda: alice_at_registry.get("registry", "services.scout.availability"), lambda v: v == "ready"
        )
        licence = await alice_at_registry.set("registry", "acquire", "", service="scout", duration="600")
        # Enforced for a federated service: bob's Set through the registry's gateway is refused.
        with pytest.raises(FailedPrecondition, match=f"licence {licence} on scout is held by alice"):
            await bob_at_registry.set("scout", "velocity", "(0.3 0)")
        await alice_at_registry.set("scout", "velocity", "(0.2 0)")
        assert (
            await alice_at_registry.get("registry", "services.scout")
        ) == f"grpc://{provider.address}/scout"

        # The consumer is bound: it follows the provider through its own gateway.
        heard: list[str] = []

        async def follow() -> None:
            async for event in alice.listen("scout", "location", min_interval=0.05):
                heard.append(event.value)

        follower = asyncio.ensure_future(follow())
        try:
            await wait_until(lambda: len(heard) >= 2, what="location events before the registry fails")
            assert registry.stop() == 0  # the registry's gateway goes away

            # What needs the registry stops ...
            with pytest.raises(Unavailable):
                await alice_at_registry.set("registry", "renew", "", licence=licence)
            with pytest.raises(Unavailable):
                await bob_at_registry.get("registry", "find", type="mobile_robot")
            # ... what the consumer and its provider do together goes on.
            before = len(heard)
            await alice.set("scout", "velocity", "(0.4 0)")
            assert await alice.get("scout", "velocity") == "(0.4 0 0 0 0 0)"
            await alice.set(
                "scout", "behaviors.moveto", "<marker><location>(1 1 0 0 0 0)</location></marker>"
            )
            await wait_until(
                lambda: len(heard) >= before + 3, what="location events after the registry failed"
            )
            assert not follower.done(), "the consumer's Listen went on"
        finally:
            follower.cancel()
