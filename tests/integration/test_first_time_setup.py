"""An operator's first steps, as real processes: the versions, psctl's shell completion, certificates
from `psgateway tls init` serving a mutual-TLS gateway, and a TLS mismatch that names TLS."""

from __future__ import annotations

import stat
import subprocess
import sys
import tomllib
from pathlib import Path

import grpc
import pytest
from support.gateway_process import ROOT, StartGateway
from support.ports import free_port
from support.psctl import PSCTL, psctl

from clients import AsyncClient, GatewayUnreachable

PSGATEWAY = [sys.executable, "-m", "gateway.cli"]
TLS_HINT = "if the gateway serves TLS, give --ca; with client certificates, --cert and --key"
COMMANDS = ("ls", "get", "set", "listen", "history", "cluster", "top", "completion")

SIM = """
[[services]]
name = "bot"
type = "sim-robot"
"""


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(list(args), capture_output=True, text=True, timeout=60, check=False)


def _tls_init(folder: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return _run(*PSGATEWAY, "tls", "init", str(folder), *extra)


def _printed_tls_section(output: str) -> str:
    """The `[tls]` lines `tls init` printed for the config file, up to the blank line after them."""
    lines = output.splitlines()
    start = lines.index("[tls]")
    end = lines.index("", start)
    return "\n".join(lines[start:end]) + "\n"


def test_psctl_and_psgateway_name_their_release_and_the_contract() -> None:
    release = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    for program, command in (("psctl", PSCTL), ("psgateway", PSGATEWAY)):
        done = _run(*command, "--version")
        assert done.returncode == 0, done.stderr
        assert (
            done.stdout.strip()
            == f"{program} {release} (propertyservice-gateway; contract propertyservice.v1)"
        )


def test_bash_completion_of_psctl_registers_and_offers_its_commands(tmp_path: Path) -> None:
    script = tmp_path / "psctl.bash"
    done = _run(*PSCTL, "completion", "bash")
    assert done.returncode == 0, done.stderr
    script.write_text(done.stdout)
    # Sourced as a user's shell would, then asked what follows `psctl ` and `psctl completion `.
    shell = _run(
        "bash",
        "-c",
        f'source "{script}" && complete -p psctl'
        ' && COMP_WORDS=(psctl "") COMP_CWORD=1 && _shtab_psctl && echo "first: ${COMPREPLY[*]}"'
        ' && COMP_WORDS=(psctl completion "") COMP_CWORD=2 && _shtab_psctl && echo "shell: ${COMPREPLY[*]}"'
        ' && COMP_WORDS=(psctl top scout1 --p) COMP_CWORD=3 && _shtab_psctl && echo "top: ${COMPREPLY[*]}"'
        ' && COMP_WORDS=(psctl get --form) COMP_CWORD=2 && _shtab_psctl && echo "option: ${COMPREPLY[*]}"'
        ' && COMP_WORDS=(psctl get --format "") COMP_CWORD=3 && _shtab_psctl'
        ' && echo "format: ${COMPREPLY[*]}"',
    )
    assert shell.returncode == 0, shell.stderr
    registered, first, shells, top, option, formats = shell.stdout.splitlines()
    assert registered.startswith("complete ") and registered.endswith(" psctl")
    assert sorted(first.removeprefix("first: ").split()) == sorted(COMMANDS)
    assert shells.removeprefix("shell: ").split() == ["bash", "zsh", "fish"]
    assert top.removeprefix("top: ").split() == ["--properties"]
    assert option.removeprefix("option: ").split() == ["--format"]
    assert formats.removeprefix("format: ").split() == ["text", "json", "jsonl"]


def test_zsh_and_fish_completion_scripts_name_every_command() -> None:
    zsh = _run(*PSCTL, "completion", "zsh")
    fish = _run(*PSCTL, "completion", "fish")
    assert zsh.returncode == fish.returncode == 0
    assert zsh.stdout.startswith("#compdef psctl")
    assert "complete -c psctl" in fish.stdout
    for command in COMMANDS:
        assert command in zsh.stdout and command in fish.stdout
    assert _run(*PSCTL, "completion", "tcsh").returncode == 2  # a shell it does not offer: usage error


async def test_tls_init_certificates_serve_a_mutual_tls_gateway_and_psctl(
    tmp_path: Path, gateway_process: StartGateway
) -> None:
    certs = tmp_path / "certs"
    made = _tls_init(certs, "--client", "operator", "--client", "viewer", "--host", "gw.example")
    assert made.returncode == 0, made.stderr
    for name in ("ca", "server", "operator", "viewer"):
        assert stat.S_IMODE((certs / f"{name}.key").stat().st_mode) == 0o600
        assert (certs / f"{name}.pem").read_text().startswith("-----BEGIN CERTIFICATE-----")
    section = _printed_tls_section(made.stdout)
    assert "require_client_cert = true" in section
    assert (
        f"--ca {certs / 'ca.pem'} --cert {certs / 'operator.pem'} --key {certs / 'operator.key'}"
        in made.stdout
    )

    operator = grpc.ssl_channel_credentials(
        (certs / "ca.pem").read_bytes(),
        (certs / "operator.key").read_bytes(),
        (certs / "operator.pem").read_bytes(),
    )
    gw = gateway_process(section + SIM, credentials=operator)
    ca = ("--ca", str(certs / "ca.pem"))
    signed = psctl(
        gw.address,
        *ca,
        "--cert",
        str(certs / "viewer.pem"),
        "--key",
        str(certs / "viewer.key"),
        "get",
        "bot",
        "location",
    )
    assert signed.returncode == 0, signed.stderr
    assert signed.stdout.strip().startswith("(")

    # No client certificate, and no TLS at all: refused, exit 3, and the error says what to give.
    for flags in (ca, ()):
        refused = psctl(gw.address, "--timeout", "5", *flags, "get", "bot", "location")
        assert refused.returncode == 3, refused.stderr
        assert "cannot reach the gateway" in refused.stderr and TLS_HINT in refused.stderr

    async with AsyncClient(gw.address, timeout=5) as plain:
        with pytest.raises(GatewayUnreachable) as caught:
            await plain.get("bot", "location")
    assert TLS_HINT in str(caught.value) and caught.value.hint


def test_nothing_listening_is_not_blamed_on_tls() -> None:
    done = psctl(f"127.0.0.1:{free_port()}", "--timeout", "5", "get", "bot", "location")
    assert done.returncode == 3
    assert "cannot reach the gateway" in done.stderr and "--ca" not in done.stderr


def test_tls_init_replaces_nothing_without_force(tmp_path: Path) -> None:
    certs = tmp_path / "certs"
    assert _tls_init(certs, "--client", "operator").returncode == 0
    before = {path.name: path.read_bytes() for path in certs.iterdir()}

    again = _tls_init(certs, "--client", "operator")
    assert again.returncode == 2
    assert "--force" in again.stderr and str(certs / "ca.pem") in again.stderr
    assert {path.name: path.read_bytes() for path in certs.iterdir()} == before

    forced = _tls_init(certs, "--client", "operator", "--force")
    assert forced.returncode == 0, forced.stderr
    after = {path.name: path.read_bytes() for path in certs.iterdir()}
    assert after.keys() == before.keys()
    assert all(after[name] != before[name] for name in before)
    assert stat.S_IMODE((certs / "operator.key").stat().st_mode) == 0o600


@pytest.mark.parametrize("name", ["ca", "../elsewhere", "two words"])
def test_tls_init_refuses_a_client_name_that_is_not_a_plain_file_name(tmp_path: Path, name: str) -> None:
    done = _tls_init(tmp_path / "certs", "--client", name)
    assert done.returncode == 2
    assert repr(name) in done.stderr
    assert not (tmp_path / "certs").exists()
