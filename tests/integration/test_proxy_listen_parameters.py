"""Two listens of one path with different request parameters, through the TCP proxy, stay two."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path

import pytest
from line_device_support import tcp_device
from support.gateway_process import ROOT

from gateway.proxies import TcpProxy, open_tcp_backend
from services.kernel.backend import Change

SCALE = """
from services.kernel.core import Resource, query


class Scale(Resource):
    resource_type = "scale"
    grams: float = 1500.0

    @query
    def weight(self, *, unit: str = "kg") -> float:
        return self.grams / 1000 if unit == "kg" else self.grams
"""

FAST = {"timeout": 2.0, "connect_timeout": 2.0, "backoff_initial": 0.05, "poll_interval": 0.05}


@pytest.fixture
def scale_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Device processes started by the test import ``scales:Scale``."""
    (tmp_path / "scales.py").write_text(SCALE)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), str(ROOT)]))


async def test_listens_differing_only_in_parameters_are_not_merged(scale_path: None) -> None:
    with tcp_device("--service", "scales:Scale", "--no-push") as (host, port):
        proxy = open_tcp_backend("scale", f"tcp://{host}:{port}", FAST)
        assert isinstance(proxy, TcpProxy)
        await proxy.start()
        try:
            await proxy.wait_connected(5)
            kilograms: asyncio.Queue[Change] = asyncio.Queue()
            grams: asyncio.Queue[Change] = asyncio.Queue()
            in_kg = await proxy.listen("weight", kilograms.put_nowait, {"unit": "kg"})
            in_g = await proxy.listen("weight", grams.put_nowait, {"unit": "g"})
            assert proxy.shared_listens.paths() == ["weight", "weight"]
            await proxy.set("grams", "2500")
            assert (await asyncio.wait_for(kilograms.get(), 5)).value == "2.5"
            assert (await asyncio.wait_for(grams.get(), 5)).value == "2500"
            await in_kg.close()
            assert proxy.shared_listens.paths() == ["weight"]
            await in_g.close()
            assert proxy.shared_listens.paths() == []
        finally:
            await proxy.aclose()
