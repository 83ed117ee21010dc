"""Regenerate the Python code for the contract in ``protos/``.

Run ``python -m protos.generate`` from the project root. The output is
checked in; ``tests/unit/test_generated_code.py`` fails when it is stale.

protoc names imports after the proto file's path (``propertyservice.v1``);
our import root is ``protos``, so the one import line in the gRPC module is
rewritten to ``protos.propertyservice.v1``. Nothing else is touched.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from importlib import resources
from pathlib import Path

ROOT = Path(__file__).resolve().parent
PROTO_FILES = ["propertyservice/v1/property_service.proto"]
GENERATED_SUFFIXES = ("_pb2.py", "_pb2.pyi", "_pb2_grpc.py")


def generate(out_dir: Path) -> list[Path]:
    """Generate the Python modules into ``out_dir`` and return their paths."""
    from grpc_tools import protoc

    include = str(resources.files("grpc_tools") / "_proto")
    args = [
        "protoc",
        f"-I{ROOT}",
        f"-I{include}",
        f"--python_out={out_dir}",
        f"--pyi_out={out_dir}",
        f"--grpc_python_out={out_dir}",
        *[str(ROOT / p) for p in PROTO_FILES],
    ]
    if protoc.main(args) != 0:
        raise SystemExit("protoc failed")
    written = sorted(p for p in out_dir.rglob("*") if p.name.endswith(GENERATED_SUFFIXES))
    for path in written:
        text = path.read_text()
        text = text.replace("from propertyservice.v1 import", "from protos.propertyservice.v1 import")
        path.write_text(text)
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        for path in generate(Path(tmp)):
            rel = path.relative_to(tmp)
            shutil.copyfile(path, ROOT / rel)
            print(f"wrote protos/{rel}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
