"""A Get, a Set and a Listen on the demo gateway through the blocking SDK, under this interpreter.

Run by ``tests/compat/check.py`` with another Python's venv:
``python tests/compat/demo_calls.py HOST:PORT``. Exit 0 when all three
behave; otherwise a line saying which call went wrong, and exit 1.
"""

from __future__ import annotations

import sys

import numpy as np

from clients.sync import Client

CALL_TIMEOUT_S = 10.0
# Listen events to read before giving up on seeing the Set's value (the first is the current value).
MAX_EVENTS = 5


def exercise(target: str) -> None:
    """Get scout1 location, Set scout1 speed, Listen for the next Set's value; AssertionError if wrong."""
    with Client(target, timeout=CALL_TIMEOUT_S) as client:
        location = client.get_vector("scout1", "location")
        assert isinstance(location, np.ndarray), f"Get scout1 location: {location!r} is not a vector"
        assert location.shape == (6,), f"Get scout1 location: expected 6 numbers, got {location!r}"

        client.set("scout1", "speed", "1.25")
        speed = client.get_number("scout1", "speed")
        assert speed == 1.25, f"Set scout1 speed 1.25, then Get: {speed!r}"

        with client.listen("scout1", "speed") as events:
            seen = [next(events).value]  # the current value first, so the stream is open before the Set
            client.set("scout1", "speed", "0.75")
            while "0.75" not in seen and len(seen) < MAX_EVENTS:
                seen.append(next(events).value)
        assert "0.75" in seen, f"Listen scout1 speed after Set 0.75: saw {seen!r}"


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: demo_calls.py HOST:PORT", file=sys.stderr)
        return 2
    try:
        exercise(argv[0])
    except AssertionError as e:
        print(f"demo calls failed: {e}", file=sys.stderr)
        return 1
    print(f"Get, Set and Listen on {argv[0]}: fine (Python {sys.version.split()[0]})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
