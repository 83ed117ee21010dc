"""The compatibility check's own logic, with stand-in interpreters (shell scripts) instead of real ones.

The real run, on the interpreters the machine has, is ``tests/run.sh`` calling
``tests/compat/check.py`` after pytest.
"""

from __future__ import annotations

import stat
from pathlib import Path

import pytest

from tests.compat import check


def _script(path: Path, body: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"#!/bin/sh\n{body}\n")
    path.chmod(path.stat().st_mode | stat.S_IEXEC)
    return path


def _fake_python(path: Path, version: str) -> Path:
    return _script(path, f'echo "CPython {version}"')


@pytest.fixture
def empty_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """No python3.X on PATH: only the fake pyenv root can offer interpreters."""
    bare = tmp_path / "bare-bin"
    bare.mkdir()
    monkeypatch.setenv("PATH", str(bare))


@pytest.mark.usefixtures("empty_path")
def test_the_newest_working_pyenv_release_of_a_minor_version_is_chosen(tmp_path: Path) -> None:
    root = tmp_path / "pyenv"
    _fake_python(root / "versions/3.12.1/bin/python3.12", "3.12.1")
    _fake_python(root / "versions/3.12.9/bin/python3.12", "3.12.9")
    _script(root / "versions/3.12.10/bin/python3.12", "exit 1")  # newest but broken
    _fake_python(root / "versions/3.12-dev/bin/python3.12", "3.12.99")  # not a release
    _fake_python(root / "versions/3.13.0/bin/python3.13", "3.13.0")

    found = check.find_interpreter((3, 12), root)
    assert found == check.Interpreter(root / "versions/3.12.9/bin/python3.12", "3.12.9")
    assert found.minor == (3, 12)
    assert check.find_interpreter((3, 11), root) is None


@pytest.mark.usefixtures("empty_path")
def test_another_implementation_or_a_mislabelled_binary_is_not_taken(tmp_path: Path) -> None:
    root = tmp_path / "pyenv"
    _script(root / "versions/3.11.7/bin/python3.11", 'echo "PyPy 3.11.7"')
    _fake_python(root / "versions/3.13.1/bin/python3.13", "3.12.1")
    assert check.find_interpreter((3, 11), root) is None
    assert check.find_interpreter((3, 13), root) is None


def test_the_venv_key_changes_with_the_interpreter_and_pyproject(tmp_path: Path) -> None:
    a = check.Interpreter(tmp_path / "a/python3.12", "3.12.1")
    key = check.venv_key(a, b"[project]")
    assert key.startswith("cpython-3.12.1-")
    assert check.venv_key(a, b"[project]") == key
    assert check.venv_key(a, b"[project]\nx = 1") != key
    assert check.venv_key(check.Interpreter(tmp_path / "b/python3.12", "3.12.1"), b"[project]") != key
    assert check.venv_key(check.Interpreter(a.path, "3.12.2"), b"[project]") != key


def test_only_the_gateways_own_listening_line_gives_the_address() -> None:
    assert check._LISTENING.match("listening on 127.0.0.1:40123")
    assert not check._LISTENING.match("2026-01-01 INFO gateway.devices: rover1 listening on 127.0.0.1:9")


def test_an_index_pip_cannot_reach_is_a_skip(tmp_path: Path) -> None:
    _script(tmp_path / "venv/bin/python", 'echo "no route to the index" >&2; exit 1')
    with pytest.raises(check.Skip, match="cannot reach the package index"):
        check.install(tmp_path / "venv")


def test_a_failing_install_once_the_index_answered_is_a_failure(tmp_path: Path) -> None:
    index_answers = 'case "$3" in index) exit 0;; *) echo "no numpy for you"; exit 1;; esac'
    _script(tmp_path / "venv/bin/python", index_answers)
    with pytest.raises(check.Failed, match="no numpy for you"):
        check.install(tmp_path / "venv")


def test_the_gateway_is_found_by_its_line_and_stopped_by_its_pid(tmp_path: Path) -> None:
    body = 'trap "echo stopping; exit 0" TERM\necho "INFO starting"\necho "listening on 127.0.0.1:4321"\n'
    body += "while :; do sleep 0.05; done"
    _script(tmp_path / "venv/bin/python", body)
    gateway = check.GatewayProcess(tmp_path / "venv")
    assert gateway.wait_listening() == "127.0.0.1:4321"
    assert gateway.stop() == 0
    assert gateway.process.returncode == 0


def test_a_gateway_that_exits_before_listening_is_a_failure_with_its_output(tmp_path: Path) -> None:
    _script(tmp_path / "venv/bin/python", 'echo "TypeError: unsupported value type"; exit 1')
    gateway = check.GatewayProcess(tmp_path / "venv")
    with pytest.raises(check.Failed, match="unsupported value type"):
        gateway.wait_listening()
    gateway.stop()


@pytest.mark.usefixtures("empty_path")
def test_with_no_other_interpreter_the_check_notes_it_and_passes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("PYENV_ROOT", str(tmp_path / "no-pyenv"))
    assert check.main(["--python", "3.12", "--python", "3.13"]) == 0
    out = capsys.readouterr().out
    assert "Python 3.12: not on this machine" in out
    assert "Python 3.13: not on this machine" in out
    assert "no failure" in out
