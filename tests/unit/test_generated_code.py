"""The checked-in code generated from protos/ must equal a fresh generation."""

from pathlib import Path

from protos import generate


def test_generated_code_is_fresh(tmp_path: Path) -> None:
    written = generate.generate(tmp_path)
    assert len(written) == 3
    for fresh in written:
        rel = fresh.relative_to(tmp_path)
        checked_in = generate.ROOT / rel
        assert checked_in.exists(), f"protos/{rel} is missing; run python -m protos.generate"
        assert checked_in.read_text() == fresh.read_text(), (
            f"protos/{rel} is stale; run python -m protos.generate"
        )
