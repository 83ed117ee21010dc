"""The C device library's own unit tests (services/device/c/tests/test_ps_device.c), compiled and run,
and the example firmware's size on the ATmega328P against its budget."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

from support.c_device import build

#: The budget of the example device on an ATmega328P (docs/c-device-library.md).
FLASH_BUDGET = 8 * 1024
RAM_BUDGET = 1024


def test_the_c_unit_tests_pass(tmp_path: Path) -> None:
    output = build("test", tmp_path)
    summary = re.search(r"(\d+) checks, (\d+) failed", output)
    assert summary, output
    assert int(summary.group(1)) > 100 and summary.group(2) == "0", output


def test_the_example_firmware_fits_the_atmega328p_budget(tmp_path: Path) -> None:
    output = build("avr", tmp_path)
    # avr-size's Berkeley table: text data bss dec hex filename
    sizes = re.search(r"^\s*(\d+)\s+(\d+)\s+(\d+)\s+\d+\s+[0-9a-f]+\s+\S+thermostat\.elf$", output, re.M)
    assert sizes, output
    text, data, bss = (int(g) for g in sizes.groups())
    print(f"ATmega328P example device: flash {text + data} bytes, RAM {data + bss} bytes (static)")
    assert text + data <= FLASH_BUDGET, output
    assert data + bss <= RAM_BUDGET, output
    hex_file = tmp_path / "avr" / "thermostat.hex"
    assert hex_file.read_text().startswith(":"), "the build also writes the Intel HEX to flash"
    # No floating point and no malloc in the firmware: their library routines are not linked in.
    symbols = subprocess.run(
        ["avr-nm", str(tmp_path / "avr" / "thermostat.elf")], capture_output=True, text=True, check=True
    ).stdout
    for routine in ("malloc", "__addsf3", "__mulsf3", "__divsf3", "__fixsfsi", "__floatsisf"):
        assert not re.search(rf"\b{routine}\b", symbols), f"{routine} is linked in"
