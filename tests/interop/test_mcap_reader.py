"""The MCAP format's own TypeScript reader (npm ``@mcap/core``, what Foxglove opens files with) reads a
recording of a real gateway: through its summary and chunk indexes, the same messages per topic,
the same channels and schemas and the same metadata as the Python ``mcap`` reader.

``tests/interop/mcap/count.mjs`` prints what each file holds as JSON. The packages (``@mcap/core``,
and ``fzstd`` to decompress the zstd chunks) are pinned by ``tests/interop/mcap/package-lock.json``
and installed by ``npm ci`` once per lock file; without npm or its registry the test skips, saying so.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
from collections import Counter
from pathlib import Path

import pytest
from mcap.reader import make_reader
from support.gateway_process import StartGateway
from support.npm import NPM_TIMEOUT, npm_ci, tool

from clients.aio import AsyncClient

ROOT = Path(__file__).resolve().parents[2]
READER_DIR = ROOT / "tests" / "interop" / "mcap"
COUNT = READER_DIR / "count.mjs"
READ_TIMEOUT = 40.0

pytestmark = pytest.mark.timeout(NPM_TIMEOUT + 120)

CONFIG = """
[[services]]
name = "scout1"
type = "sim-robot"

[[services]]
name = "thermo1"
type = "sim-sensor"

[[services]]
name = "recorder"
type = "recorder"
options = {{ folder = "{folder}" }}
"""


@pytest.fixture(scope="session")
def node() -> str:
    """``node``, with the reader's packages installed by ``npm ci`` (once per lock file)."""
    what = "the MCAP reader tests"
    node = tool("node", what)
    npm_ci(READER_DIR, what)
    return node


def python_report(path: Path) -> dict[str, object]:
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        channels = {
            c.topic: {
                "messageEncoding": c.message_encoding,
                "schema": summary.schemas[c.schema_id].name,
                "schemaEncoding": summary.schemas[c.schema_id].encoding,
            }
            for c in summary.channels.values()
        }
        topics = Counter(channel.topic for _, channel, _ in reader.iter_messages())
        metadata = [m.name for m in reader.iter_metadata()]
        return {
            "library": reader.get_header().library,
            "topics": dict(topics),
            "channels": channels,
            "metadata": metadata,
        }


async def test_the_typescript_reader_finds_what_the_python_reader_finds_in_a_recording(
    node: str, gateway_process: StartGateway, tmp_path: Path
) -> None:
    folder = tmp_path / "recordings"
    gw = gateway_process(CONFIG.format(folder=folder))
    async with AsyncClient(gw.address, timeout=15.0) as client:
        await client.set("scout1", "behaviors.moveto", "<marker><location>(4 3)</location></marker>")
        await client.set("recorder", "start", "scout1/* thermo1/*", name="both", max_duration=2.0)

        async def state() -> str:
            listed = json.loads(str(await client.get("recorder", "recordings")))
            return str(listed[0]["state"])

        for _ in range(100):
            if await state() == "stopped":
                break
            await asyncio.sleep(0.1)
        assert await state() == "stopped"
    path = folder / "both" / "both-0001.mcap"
    done = await asyncio.to_thread(
        subprocess.run,
        [node, str(COUNT), str(path)],
        capture_output=True,
        text=True,
        timeout=READ_TIMEOUT,
        check=False,
        cwd=READER_DIR,
    )
    assert done.returncode == 0, done.stderr
    theirs = json.loads(done.stdout)[str(path)]
    ours = python_report(path)
    assert theirs["topics"] == ours["topics"]
    assert theirs["channels"] == ours["channels"]
    assert sorted(theirs["metadata"]) == sorted(ours["metadata"])  # type: ignore[call-overload]
    assert theirs["library"] == ours["library"]
    assert theirs["topics"]["/_events"] > 10
    assert {"/scout1/location", "/scout1/pose", "/scene", "/thermo1/data"} <= set(theirs["topics"])
