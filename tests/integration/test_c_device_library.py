"""The C device library's own unit tests (services/device/c/tests/test_ps_device.c), compiled and run;
the core built in every profile; and the example firmware's size on the ATmega328P per profile
against its budget (docs/c-device-library.md, "Profiles")."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest
from support.c_device import C_DIR, build

#: The budgets on an ATmega328P (docs/c-device-library.md): any build, the full example (every
#: switch on: 6.5 KiB), the minimal profile (Get, Set and Listen of numbers and text), and static
#: RAM for any of them.
FLASH_BUDGET = 8 * 1024
FULL_EXAMPLE_FLASH_BUDGET = 6656
MINIMAL_FLASH_BUDGET = 4 * 1024
RAM_BUDGET = 512
WARNINGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic")
#: Every switch alone, and the minimal profile: each must build warning-free as portable C99.
PROFILES = [
    "-DPS_MINIMAL",
    "-DPS_MINIMAL -DPS_WITH_TAGS=0",
    *(
        f"-DPS_WITH_{name}=0"
        for name in ("BYTES", "MODEL", "CHECKSUM", "TAGS", "VECTORS", "ACTIONS", "ERROR_TEXTS")
    ),
]


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
    assert text + data <= FULL_EXAMPLE_FLASH_BUDGET, output
    assert data + bss <= RAM_BUDGET, output
    hex_file = tmp_path / "avr" / "thermostat.hex"
    assert hex_file.read_text().startswith(":"), "the build also writes the Intel HEX to flash"
    # No floating point and no malloc in the firmware: their library routines are not linked in.
    symbols = subprocess.run(
        ["avr-nm", str(tmp_path / "avr" / "thermostat.elf")], capture_output=True, text=True, check=True
    ).stdout
    for routine in ("malloc", "__addsf3", "__mulsf3", "__divsf3", "__fixsfsi", "__floatsisf"):
        assert not re.search(rf"\b{routine}\b", symbols), f"{routine} is linked in"


@pytest.mark.parametrize("profile", PROFILES)
def test_the_core_builds_in_every_profile_as_portable_c99(profile: str, tmp_path: Path) -> None:
    compiler = shutil.which("cc")
    if compiler is None:
        pytest.skip("the C device library needs a C compiler (cc): bash tests/run.sh installs it")
    for source in ("src/ps_device.c", "src/ps_values.c"):
        run = subprocess.run(
            [
                compiler,
                *WARNINGS,
                "-Iinclude",
                *profile.split(),
                "-c",
                source,
                "-o",
                str(tmp_path / "core.o"),
            ],
            cwd=C_DIR,
            capture_output=True,
            text=True,
            check=False,
        )
        assert run.returncode == 0, f"{profile} {source}:\n{run.stderr}"


def test_each_profile_fits_its_budget_and_the_minimal_one_fits_4_kib(tmp_path: Path) -> None:
    output = build("sizes", tmp_path)
    sizes = {
        (example, profile): (int(flash), int(ram))
        for example, profile, flash, ram in re.findall(
            r"^(\S+) +(\S+) +flash=(\d+) +ram=(\d+)$", output, re.M
        )
    }
    print("\n" + output)
    assert {("thermostat", "full"), ("thermostat", "minimal"), ("robot", "full")} <= set(sizes), output
    assert sizes["thermostat", "full"][0] <= FULL_EXAMPLE_FLASH_BUDGET, output
    assert sizes["thermostat", "minimal"][0] <= MINIMAL_FLASH_BUDGET, output
    for (example, profile), (flash, ram) in sizes.items():
        assert flash <= FLASH_BUDGET, f"{example} {profile}: {flash} B of flash"
        assert ram <= RAM_BUDGET, f"{example} {profile}: {ram} B of RAM"
    # Each switch takes something off the full build: none is a switch in name only.
    for (example, profile), (flash, _) in sizes.items():
        assert not profile.startswith("no-") or flash < sizes[example, "full"][0], f"{example} {profile}"
