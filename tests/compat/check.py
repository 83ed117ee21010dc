"""The compatibility check: the project on every other supported CPython present, newest dependencies.

``tests/run.sh`` runs it after pytest, with the suite's interpreter, which
drives the others: ``python tests/compat/check.py``. For each of CPython
3.11, 3.12 and 3.13 found on the machine (pyenv's versions, then
``python3.X`` on PATH) other than the one running it, it

1. makes a venv under ``.compat/venvs/`` (git-ignored), named after the
   interpreter and a hash of its path, its version and ``pyproject.toml``:
   a change to either makes a fresh one, and the stale one is removed;
2. runs ``pip install --upgrade --upgrade-strategy eager pip -e '.[test]'``
   there on every run, so each run tests the newest releases pip resolves
   for that interpreter (a cached venv only saves the downloads);
3. starts the demo gateway (``python -m gateway serve --listen
   127.0.0.1:0``), runs a Get, a Set and a Listen through the SDK
   (``tests/compat/demo_calls.py``), and stops it by its PID with SIGTERM;
4. runs ``pytest tests/unit`` under that interpreter.

An interpreter that is absent, a venv that cannot be made, or a package
index pip cannot reach is a printed note and a skip. A failing install
(once the index answered), demo or unit test is a failure: exit status 1.
Every step has a time limit.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
VENVS = ROOT / ".compat" / "venvs"
DEMO_CALLS = Path(__file__).resolve().parent / "demo_calls.py"
SUPPORTED = ((3, 11), (3, 12), (3, 13))
# Written last into a venv whose creation finished: a venv without it is half-made and re-created.
COMPLETE_MARK = "compat-venv-complete"

# Seconds each step may take. The install's limit covers a first download of every wheel.
PROBE_S = 20
VENV_S = 180
INDEX_PROBE_S = 60
INSTALL_S = 900
GATEWAY_START_S = 60
DEMO_CALLS_S = 90
GATEWAY_STOP_S = 30
UNIT_TESTS_S = 900
OUTPUT_TAIL_LINES = 40

_LISTENING = re.compile(r"^listening on (\S+):(\d+)$")
_RELEASE = re.compile(r"^(\d+)\.(\d+)\.(\d+)$")
# Variables that would make the venv's Python import or run something other than the venv's own.
_FOREIGN_ENV = ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP", "PYTHONUSERBASE", "VIRTUAL_ENV", "CONDA_PREFIX")


@dataclass(frozen=True)
class Interpreter:
    """A CPython found on this machine: the executable and its full version."""

    path: Path
    version: str

    @property
    def minor(self) -> tuple[int, int]:
        major, minor, *_ = (int(part) for part in self.version.split("."))
        return major, minor


class Skip(Exception):
    """This interpreter cannot be checked on this machine now: a note, not a failure."""


class Failed(Exception):
    """The project does not work under this interpreter: the check fails."""


def minor_name(minor: tuple[int, int]) -> str:
    return f"{minor[0]}.{minor[1]}"


def parse_minor(text: str) -> tuple[int, int]:
    """``"3.12"`` (or ``"3.12.1"``) as ``(3, 12)``."""
    major, minor, *_ = text.split(".")
    return int(major), int(minor)


def pyenv_root() -> Path | None:
    """pyenv's root: $PYENV_ROOT, else what ``pyenv root`` says, else ~/.pyenv when it exists."""
    if os.environ.get("PYENV_ROOT"):
        return Path(os.environ["PYENV_ROOT"])
    if shutil.which("pyenv"):
        try:
            out = subprocess.run(
                ["pyenv", "root"], capture_output=True, text=True, timeout=PROBE_S, check=True
            )
            return Path(out.stdout.strip())
        except (OSError, subprocess.SubprocessError):
            pass
    home = Path.home() / ".pyenv"
    return home if home.is_dir() else None


def candidates(minor: tuple[int, int], root: Path | None) -> list[Path]:
    """Executables that may be CPython ``minor``: pyenv's releases of it, newest first, then PATH's."""
    name = f"python{minor_name(minor)}"
    found: list[Path] = []
    versions = root / "versions" if root else None
    if versions and versions.is_dir():
        releases = []
        for entry in versions.iterdir():
            match = _RELEASE.match(entry.name)
            if match and (int(match[1]), int(match[2])) == minor:
                releases.append((int(match[3]), entry / "bin" / name))
        found += [path for _, path in sorted(releases, reverse=True) if path.exists()]
    on_path = shutil.which(name)
    if on_path:
        found.append(Path(on_path))
    return found


def probe(path: Path) -> Interpreter | None:
    """The interpreter at ``path`` if it runs and is CPython; None otherwise (a pyenv shim of a
    version not selected, a broken install, another implementation)."""
    code = "import platform; print(platform.python_implementation(), platform.python_version())"
    try:
        out = subprocess.run(
            [str(path), "-c", code],
            check=False,
            capture_output=True,
            text=True,
            timeout=PROBE_S,
            env=clean_env(),
        )
    except (OSError, subprocess.SubprocessError):
        return None
    implementation, _, version = out.stdout.strip().partition(" ")
    if out.returncode != 0 or implementation != "CPython" or not version:
        return None
    return Interpreter(path=path, version=version)


def find_interpreter(minor: tuple[int, int], root: Path | None) -> Interpreter | None:
    """The first working CPython ``minor`` among :func:`candidates`; None when there is none."""
    for path in candidates(minor, root):
        interpreter = probe(path)
        if interpreter and interpreter.minor == minor:
            return interpreter
    return None


def clean_env(venv: Path | None = None) -> dict[str, str]:
    """This process's environment without what points Python elsewhere; ``venv``'s bin first on PATH."""
    env = {k: v for k, v in os.environ.items() if k not in _FOREIGN_ENV}
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    if venv is not None:
        env["VIRTUAL_ENV"] = str(venv)
        env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    return env


def venv_key(interpreter: Interpreter, pyproject: bytes) -> str:
    """The venv's folder name: the interpreter's version, then a hash of its path, version and
    ``pyproject.toml``, so a different interpreter or changed dependencies get a fresh venv."""
    digest = hashlib.sha256()
    digest.update(str(interpreter.path.resolve()).encode())
    digest.update(interpreter.version.encode())
    digest.update(pyproject)
    return f"cpython-{interpreter.version}-{digest.hexdigest()[:16]}"


def _text(output: str | bytes | None) -> str:
    # A timed-out run's output can be bytes even in text mode.
    return output.decode(errors="replace") if isinstance(output, bytes) else output or ""


def tail(text: str, lines: int = OUTPUT_TAIL_LINES) -> str:
    kept = text.rstrip().splitlines()[-lines:]
    return "\n".join(f"    | {line}" for line in kept)


def run_step(
    what: str, cmd: list[str], timeout: float, env: dict[str, str]
) -> subprocess.CompletedProcess[str]:
    """Run ``cmd`` in the project root, output captured; Failed when it runs past ``timeout``."""
    try:
        return subprocess.run(
            cmd,
            check=False,
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
            stdin=subprocess.DEVNULL,
        )
    except subprocess.TimeoutExpired as e:
        raise Failed(
            f"{what}: no result in {timeout:.0f} s\n{tail(_text(e.stdout) + _text(e.stderr))}"
        ) from None


def make_venv(interpreter: Interpreter) -> Path:
    """The interpreter's venv for this ``pyproject.toml``, made when missing or half-made."""
    key = venv_key(interpreter, (ROOT / "pyproject.toml").read_bytes())
    venv = VENVS / key
    for stale in VENVS.glob(f"cpython-{interpreter.version}-*"):
        if stale.name != key:
            shutil.rmtree(stale, ignore_errors=True)
    if (venv / COMPLETE_MARK).exists():
        return venv
    shutil.rmtree(venv, ignore_errors=True)
    VENVS.mkdir(parents=True, exist_ok=True)
    try:
        made = run_step(
            "python -m venv", [str(interpreter.path), "-m", "venv", str(venv)], VENV_S, clean_env()
        )
    except Failed as e:
        raise Skip(str(e)) from None
    if made.returncode != 0:
        # Debian's python3.X without python3.X-venv: this machine cannot make venvs for it.
        raise Skip(
            f"cannot make a venv with it (python -m venv exit {made.returncode})\n"
            f"{tail(made.stdout + made.stderr)}"
        )
    (venv / COMPLETE_MARK).write_text(f"{interpreter.path}\n{interpreter.version}\n")
    return venv


def install(venv: Path) -> None:
    """Install the project and its test extra with the newest releases pip resolves there."""
    python = str(venv / "bin" / "python")
    env = clean_env(venv)
    try:
        index = run_step(
            "pip index",
            [python, "-m", "pip", "index", "versions", "grpcio", "--timeout", "15", "--retries", "1"],
            INDEX_PROBE_S,
            env,
        )
    except Failed as e:
        raise Skip(f"pip cannot reach the package index: {e}") from None
    if index.returncode != 0:
        raise Skip(f"pip cannot reach the package index\n{tail(index.stdout + index.stderr, 8)}")
    cmd = [python, "-m", "pip", "install", "--upgrade", "--upgrade-strategy", "eager", "pip", "-e", ".[test]"]
    try:
        done = run_step("pip install", cmd, INSTALL_S, env)
    except Failed as e:
        raise Skip(f"the install did not finish in time (a slow index?): {e}") from None
    if done.returncode != 0:
        raise Failed(
            f"pip install --upgrade -e '.[test]' failed (exit {done.returncode})\n"
            f"{tail(done.stdout + done.stderr)}"
        )


def installed_versions(venv: Path, names: tuple[str, ...]) -> str:
    """``name version`` of each of ``names`` as installed in ``venv``, for the log."""
    code = (
        "import importlib.metadata as m, sys\nprint(', '.join(f'{n} {m.version(n)}' for n in sys.argv[1:]))"
    )
    out = run_step("versions", [str(venv / "bin" / "python"), "-c", code, *names], PROBE_S, clean_env(venv))
    return out.stdout.strip() if out.returncode == 0 else "(versions unknown)"


class GatewayProcess:
    """The demo gateway under the venv's Python, its output collected by a thread."""

    def __init__(self, venv: Path) -> None:
        self._lines: list[str] = []
        self._listening = threading.Event()
        self.address = ""
        self.process = subprocess.Popen(
            [
                str(venv / "bin" / "python"),
                "-m",
                "gateway",
                "serve",
                "--listen",
                "127.0.0.1:0",
                "--http",
                "127.0.0.1:0",
            ],
            cwd=ROOT,
            env=clean_env(venv),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,  # its device processes form a group we can end if it hangs
        )
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self._lines.append(line.rstrip("\n"))
            match = _LISTENING.match(line.strip())
            if match and not self.address:
                self.address = f"{match[1]}:{match[2]}"
                self._listening.set()

    @property
    def output(self) -> str:
        return "\n".join(self._lines)

    def wait_listening(self) -> str:
        """The address from its ``listening on HOST:PORT`` line; Failed if it exits or is silent too long."""
        deadline = time.monotonic() + GATEWAY_START_S
        while not self._listening.wait(0.2):
            if self.process.poll() is not None:
                raise Failed(
                    f"the demo gateway exited {self.process.returncode} before listening\n{tail(self.output)}"
                )
            if time.monotonic() > deadline:
                raise Failed(
                    f"the demo gateway printed no 'listening on' in {GATEWAY_START_S} s\n{tail(self.output)}"
                )
        return self.address

    def stop(self) -> int:
        """SIGTERM to its PID and its exit status; if it does not end in time, its group is killed: Failed."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
        try:
            return self.process.wait(GATEWAY_STOP_S)
        except subprocess.TimeoutExpired:
            os.killpg(self.process.pid, signal.SIGKILL)  # the group this process leads: it and its devices
            self.process.wait(GATEWAY_STOP_S)
            raise Failed(
                f"the demo gateway did not stop on SIGTERM in {GATEWAY_STOP_S} s\n{tail(self.output)}"
            ) from None


def run_demo(venv: Path) -> str:
    """Start the demo gateway, Get, Set and Listen through the SDK, stop it; the SDK's report."""
    gateway = GatewayProcess(venv)
    try:
        address = gateway.wait_listening()
        calls = run_step(
            "Get, Set and Listen",
            [str(venv / "bin" / "python"), str(DEMO_CALLS), address],
            DEMO_CALLS_S,
            clean_env(venv),
        )
    finally:
        status = gateway.stop()
    if calls.returncode != 0:
        raise Failed(
            f"Get, Set and Listen through the SDK failed (exit {calls.returncode})\n"
            f"{tail(calls.stdout + calls.stderr)}\n  the gateway said:\n{tail(gateway.output)}"
        )
    if status != 0:
        raise Failed(f"the demo gateway exited {status} on SIGTERM\n{tail(gateway.output)}")
    return calls.stdout.strip()


def run_unit_tests(venv: Path) -> str:
    """``pytest tests/unit`` under the venv's Python; its summary line."""
    cmd = [str(venv / "bin" / "python"), "-m", "pytest", "tests/unit", "-q", "-p", "no:cacheprovider"]
    done = run_step("pytest tests/unit", cmd, UNIT_TESTS_S, clean_env(venv))
    if done.returncode != 0:
        raise Failed(f"pytest tests/unit failed (exit {done.returncode})\n{tail(done.stdout + done.stderr)}")
    lines = done.stdout.strip().splitlines()
    return lines[-1] if lines else "(no output)"


def check(interpreter: Interpreter) -> None:
    """Every step for one interpreter, each reported as it ends; Skip or Failed from the first that fails."""
    started = time.monotonic()
    venv = make_venv(interpreter)
    install(venv)
    print(f"  installed: {installed_versions(venv, ('numpy', 'grpcio', 'protobuf', 'pytest'))}", flush=True)
    print(f"  demo: {run_demo(venv)}", flush=True)
    print(f"  unit tests: {run_unit_tests(venv)}", flush=True)
    print(f"  Python {interpreter.version}: fine in {time.monotonic() - started:.0f} s", flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--python",
        action="append",
        metavar="3.X",
        help="check only this minor version (repeatable); default: every supported one but this one",
    )
    args = parser.parse_args(argv)
    own = (sys.version_info.major, sys.version_info.minor)
    if args.python:
        wanted = [parse_minor(v) for v in args.python]
    else:
        wanted = [minor for minor in SUPPORTED if minor != own]
    root = pyenv_root()
    started = time.monotonic()
    failed: list[str] = []
    for minor in wanted:
        name = minor_name(minor)
        interpreter = find_interpreter(minor, root)
        if interpreter is None:
            print(
                f"== compat: Python {name}: not on this machine (pyenv or python{name} on PATH); skipped",
                flush=True,
            )
            continue
        print(f"== compat: Python {interpreter.version} ({interpreter.path})", flush=True)
        try:
            check(interpreter)
        except Skip as e:
            print(f"  Python {interpreter.version}: skipped: {e}", flush=True)
        except Failed as e:
            print(f"  Python {interpreter.version}: FAILED: {e}", flush=True)
            failed.append(interpreter.version)
    elapsed = time.monotonic() - started
    verdict = f"failed on {', '.join(failed)}" if failed else "no failure"
    print(f"== compat: {verdict} ({elapsed:.0f} s)", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
