"""The console's floor plan (``[console] map_image``), served by a real gateway process's HTTP front."""

from __future__ import annotations

import json
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

from support.gateway_process import ROOT, StartGateway

FLOOR = """
[console]
map_image = "floor.png"
map_extent = [-2.0, -1.5, 8.0, 6.0]

[[services]]
name = "scout1"
type = "sim-robot"
"""


def floor_png(folder: Path) -> bytes:
    from PIL import Image, ImageDraw

    picture = Image.new("RGB", (200, 150), "white")
    ImageDraw.Draw(picture).rectangle((10, 10, 190, 140), outline="black", width=4)
    path = folder / "floor.png"
    picture.save(path)
    return path.read_bytes()


def fetch(url: str) -> tuple[int, str, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=10) as answer:
            return answer.status, answer.headers.get("Content-Type", ""), answer.read()
    except urllib.error.HTTPError as error:
        return error.code, error.headers.get("Content-Type", ""), error.read()


def test_the_console_gets_the_floor_plan_the_config_names_and_where_it_lies(
    gateway_process: StartGateway, tmp_path: Path
) -> None:
    picture = floor_png(tmp_path)
    gw = gateway_process(FLOOR)
    status, _, body = fetch(gw.http_url + "console/floor-plan.json")
    assert status == 200
    assert json.loads(body) == {"image": "/console/floor-plan", "extent": [-2.0, -1.5, 8.0, 6.0]}
    status, content_type, body = fetch(gw.http_url + "console/floor-plan")
    assert (status, content_type, body) == (200, "image/png", picture)


def test_a_gateway_without_a_floor_plan_says_so(gateway_process: StartGateway) -> None:
    gw = gateway_process('[[services]]\nname = "scout1"\ntype = "sim-robot"\n')
    status, _, body = fetch(gw.http_url + "console/floor-plan.json")
    assert (status, json.loads(body)) == (200, {"image": None, "extent": None})
    status, _, body = fetch(gw.http_url + "console/floor-plan")
    assert status == 404 and json.loads(body)["error"]["code"] == "NOT_FOUND"


def test_a_missing_floor_plan_stops_the_gateway_at_its_start_naming_the_key(tmp_path: Path) -> None:
    config = tmp_path / "gateway.toml"
    config.write_text(FLOOR)  # no floor.png beside it
    started = subprocess.run(
        [sys.executable, "-m", "gateway.cli", "serve", "--config", str(config), "--listen", "127.0.0.1:0"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert started.returncode != 0
    assert f"console.map_image: no such file '{tmp_path / 'floor.png'}'" in started.stderr, started.stderr
    assert "Traceback" not in started.stderr


def test_a_floor_plan_removed_while_serving_is_not_found_and_logged_once(
    gateway_process: StartGateway, tmp_path: Path
) -> None:
    floor_png(tmp_path)
    gw = gateway_process(FLOOR)
    (tmp_path / "floor.png").unlink()
    for _ in range(3):
        status, _, body = fetch(gw.http_url + "console/floor-plan")
        assert status == 404 and "gone" in json.loads(body)["error"]["message"]
    gw.stop()
    assert gw.output.count("([console] map_image) is gone") == 1, gw.output
