"""Binary properties in the console, in a real headless Chromium: a live image for ``image/*``.

The test service (``tests/support/frames.py``) has a camera whose ``camera.frame`` is a new PNG
ten times a second, and a writable picture ``snapshot``. The service view shows each as an
``<img>`` fed by the gateway's stream route: the image decodes (naturalWidth > 0), the frame
counter goes up and the picture changes; a raw Set of ``snapshot`` from outside shows at once.
"""

from __future__ import annotations

import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from console_support import CONFIG, CSS, ConsoleGateway, doc_image, prop, select, wait_for
from support.frames import FRAMES_TYPE, solid_png
from support.gateway_process import start_gateway

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(120)]

CAMERA = f"""
[[services]]
name = "cam1"
type = "{FRAMES_TYPE}"
options = {{ rate_hz = 10.0, width = 160, height = 120 }}
"""


@pytest.fixture(scope="module")
def console_gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ConsoleGateway]:
    """The console's world and the camera ``cam1``."""
    folder: Path = tmp_path_factory.mktemp("console-images")
    gw = start_gateway(folder, CONFIG + CAMERA)
    try:
        assert gw.http_url, f"no 'HTTP front end and console on' line:\n{gw.output}"
        yield ConsoleGateway(gw, gw.address, gw.http_url)
    finally:
        gw.stop()


def image_state(page: Any, path: str) -> dict[str, Any]:
    """What the image widget of ``path`` shows: decoded size, frame count, source, caption."""
    state: dict[str, Any] = page.execute_script(
        """const view = document.querySelector(`#service-view [data-property="${arguments[0]}"] .image-view`);
           if (!view) return null;
           const img = view.querySelector('img');
           return {width: img.naturalWidth, height: img.naturalHeight, complete: img.complete,
                   frames: Number(view.dataset.frames), src: img.src, state: view.dataset.state,
                   caption: view.querySelector('.image-caption').textContent};""",
        path,
    )
    return state or {}


def test_a_camera_frame_is_a_live_image_that_changes(page: Any) -> None:
    select(page, "cam1")
    frame = wait_for(page, lambda d: prop(d, "camera.frame"), '[data-property="camera.frame"]')
    assert frame.get_attribute("data-type") == "bytes"
    assert frame.find_elements(CSS, "img.live-image"), "an image/png property is shown as an <img>"
    first = wait_for(
        page,
        lambda d: (s := image_state(d, "camera.frame")) and s["width"] > 0 and s["frames"] > 0 and s,
        "the first frame decoded",
    )
    assert (first["width"], first["height"]) == (160, 120)
    later = wait_for(
        page,
        lambda d: (
            (s := image_state(d, "camera.frame"))
            and s["frames"] >= first["frames"] + 5
            and s["width"] > 0
            and s["src"] != first["src"]
            and s
        ),
        "five more frames, each decoded",
    )
    assert later["state"] == "live"
    assert "160×120" in later["caption"] and "image/png" in later["caption"], later["caption"]
    # The frame is not followed as text on the page's event stream: its value text stays hidden.
    assert not frame.find_element(CSS, ".value").is_displayed()
    page.execute_script("arguments[0].scrollIntoView({block: 'center'})", frame)
    doc_image(page, "camera")


def test_a_picture_set_from_outside_shows_at_once(page: Any, console_gateway: ConsoleGateway) -> None:
    select(page, "cam1")
    wait_for(page, lambda d: image_state(d, "snapshot").get("width", 0) > 0, "the snapshot decoded")
    before = image_state(page, "snapshot")
    picture = solid_png(40, 30, (0, 128, 255))
    request = urllib.request.Request(
        console_gateway.url + "api/v1/services/cam1/properties/snapshot",
        data=picture,
        method="PUT",
        headers={"Content-Type": "image/png"},
    )
    with urllib.request.urlopen(request, timeout=10) as answer:
        assert answer.status == 200
    after = wait_for(
        page,
        lambda d: (
            (s := image_state(d, "snapshot")) and s["frames"] > before["frames"] and s["width"] == 40 and s
        ),
        "the new picture shown",
    )
    assert image_state(page, "snapshot")["height"] == 30
    assert after


def test_a_picture_set_from_a_file_on_the_page(
    page: Any, tmp_path: Path, console_gateway: ConsoleGateway
) -> None:
    select(page, "cam1")
    snapshot = wait_for(page, lambda d: prop(d, "snapshot"), '[data-property="snapshot"]')
    wait_for(page, lambda d: image_state(d, "snapshot").get("width", 0) > 0, "the snapshot decoded")
    picture = solid_png(12, 34, (255, 255, 0))
    file = tmp_path / "yellow.png"
    file.write_bytes(picture)
    snapshot.find_element(CSS, 'input[type="file"][data-action="upload"]').send_keys(str(file))
    wait_for(page, lambda d: image_state(d, "snapshot").get("width") == 12, "the uploaded picture shown")
    raw = console_gateway.url + "api/v1/services/cam1/properties/snapshot?raw=1"
    with urllib.request.urlopen(raw, timeout=10) as answer:
        assert answer.read() == picture, "the gateway holds the file's bytes"


def test_a_plain_img_shows_the_stream_route_and_a_raw_read(page: Any) -> None:
    """What docs/http-api.md promises a page of the gateway's own origin: `<img src=".../stream">`
    (multipart/x-mixed-replace) and `<img src="...?raw=1">` both decode."""
    page.execute_script(
        """for (const [id, src] of [['plain-stream', '/api/v1/services/cam1/properties/camera.frame/stream'],
                                   ['plain-raw', '/api/v1/services/cam1/properties/camera.frame?raw=1']]) {
             const img = document.createElement('img');
             img.id = id;
             img.src = src;
             document.body.append(img);
           }"""
    )
    for element in ("plain-stream", "plain-raw"):
        wait_for(
            page,
            lambda d, e=element: (
                d.execute_script(f"return document.getElementById('{e}').naturalWidth") == 160
            ),
            f"#{element} decoded",
        )
    page.execute_script(
        "for (const id of ['plain-stream', 'plain-raw']) document.getElementById(id)?.remove()"
    )
