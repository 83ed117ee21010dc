"""``python -m services.device``: the device command (see :mod:`services.device.cli`)."""

from services.device.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
