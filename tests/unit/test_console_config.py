"""``[console]``: a floor plan for the console's map, checked when the config is read."""

from __future__ import annotations

from pathlib import Path

import pytest

from gateway.config import ConfigError, loads_config


def test_a_floor_plan_is_taken_from_the_config_folder_with_its_extent(tmp_path: Path) -> None:
    (tmp_path / "floor.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    config = loads_config(
        '[console]\nmap_image = "floor.png"\nmap_extent = [-2, -1.5, 8, 6]\n', folder=tmp_path
    )
    assert config.console.map_image == str(tmp_path / "floor.png")
    assert config.console.map_extent == (-2.0, -1.5, 8.0, 6.0)


def test_no_console_section_means_no_floor_plan() -> None:
    config = loads_config("")
    assert config.console.map_image == "" and config.console.map_extent == ()


@pytest.mark.parametrize(
    ("text", "said"),
    [
        ('map_image = "nowhere.png"\nmap_extent = [0, 0, 1, 1]', "console.map_image: no such file"),
        ('map_image = "floor.png"', "console.map_extent: give where the floor plan lies"),
        ('map_image = "floor.png"\nmap_extent = [0, 0, 1]', "console.map_extent: expected four numbers"),
        ('map_image = "floor.png"\nmap_extent = [0, 0, "1", 1]', "console.map_extent: expected four numbers"),
        ('map_image = "floor.png"\nmap_extent = [5, 0, 1, 1]', "must lie right of and above"),
        ('map_image = "floor.txt"\nmap_extent = [0, 0, 1, 1]', "is not a picture the console draws"),
        ("map_extent = [0, 0, 1, 1]", "console.map_extent: give map_image too"),
        ('map_picture = "floor.png"', "console.map_picture: unknown key (known: map_image, map_extent)"),
    ],
)
def test_a_wrong_floor_plan_is_a_clear_error_naming_the_key(tmp_path: Path, text: str, said: str) -> None:
    (tmp_path / "floor.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    (tmp_path / "floor.txt").write_text("not a picture")
    with pytest.raises(ConfigError, match=said.replace("(", r"\(").replace(")", r"\)")):
        loads_config(f"[console]\n{text}\n", folder=tmp_path)
