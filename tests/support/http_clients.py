"""Clients of a module's gateway process, for the HTTP front end's tests.

A test module defines a ``gateway`` fixture (a :class:`GatewayProcess`, usually module-scoped)
and imports these fixtures by name: ``http`` (an aiohttp session on its HTTP front end) and
``grpc_client`` (the SDK on its gRPC port), so that every HTTP result can be checked by gRPC.
"""

from __future__ import annotations

from collections.abc import AsyncIterator

import aiohttp
import pytest

from clients import AsyncClient
from support.gateway_process import GatewayProcess

__all__ = ["grpc_client", "http"]


@pytest.fixture
async def http(gateway: GatewayProcess) -> AsyncIterator[aiohttp.ClientSession]:
    async with aiohttp.ClientSession(base_url=gateway.http_url) as session:
        yield session


@pytest.fixture
async def grpc_client(gateway: GatewayProcess) -> AsyncIterator[AsyncClient]:
    async with AsyncClient(gateway.address, timeout=10) as client:
        yield client
