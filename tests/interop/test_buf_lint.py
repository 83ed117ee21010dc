"""``buf lint`` and ``buf format`` keep the contract (protos/) clean, with the rules of buf.yaml.

buf comes pinned from npm (tests/interop/buf/package.json: the @bufbuild/buf package ships the
binary), installed by ``npm ci`` once per lock file. The last test breaks a copy of the contract
and sees buf refuse it, so that a passing lint means the rules ran.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
from support.npm import NPM_TIMEOUT, npm_ci

ROOT = Path(__file__).resolve().parents[2]
BUF_DIR = ROOT / "tests" / "interop" / "buf"
BUF = BUF_DIR / "node_modules" / ".bin" / "buf"
BUF_TIMEOUT = 60.0
PROTO = Path("propertyservice") / "v1" / "property_service.proto"

pytestmark = pytest.mark.timeout(NPM_TIMEOUT + 60)


@pytest.fixture(scope="session")
def buf() -> Path:
    """The buf binary, installed by `npm ci` in tests/interop/buf (once per lock file)."""
    npm_ci(BUF_DIR, "the buf lint tests", installed=BUF)
    return BUF


def run_buf(buf: Path, *args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(buf), *args], cwd=cwd, capture_output=True, text=True, timeout=BUF_TIMEOUT, check=False
    )


def test_the_contract_passes_buf_lint(buf: Path) -> None:
    done = run_buf(buf, "lint")
    assert (done.returncode, done.stdout, done.stderr) == (0, "", "")


def test_the_contract_is_buf_formatted(buf: Path) -> None:
    done = run_buf(buf, "format", "--diff", "--exit-code")
    assert (done.returncode, done.stdout, done.stderr) == (0, "", "")


def test_buf_lint_refuses_a_field_that_breaks_the_style(buf: Path, tmp_path: Path) -> None:
    shutil.copy(ROOT / "buf.yaml", tmp_path / "buf.yaml")
    broken = tmp_path / "protos" / PROTO
    broken.parent.mkdir(parents=True)
    text = (ROOT / "protos" / PROTO).read_text()
    broken.write_text(text.replace("  string service = 1;\n", "  string serviceName = 1;\n", 1))
    done = run_buf(buf, "lint", cwd=tmp_path)
    assert done.returncode != 0
    assert 'Field name "serviceName" should be lower_snake_case' in done.stdout, done.stdout
