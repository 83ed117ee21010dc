"""A property that needs a request parameter to be read, in a real headless Chromium.

A storage service's ``file`` is read and written with the parameter ``name``: the page
cannot follow it without one, so its view is a form (an input per parameter, the value,
Get and Set) rather than a value followed live, and opening the service shows no error.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from console_support import CONFIG, CSS, ConsoleGateway, eventually, prop, select, wait_for
from support.gateway_process import start_gateway

from clients.sync import Client

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(120)]

STORAGE = """
[[services]]
name = "files"
type = "storage"
options = { directory = "files" }
"""


@pytest.fixture(scope="module")
def console_gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ConsoleGateway]:
    """The console's world and a storage service ``files`` (the folder ``files`` beside the config)."""
    folder: Path = tmp_path_factory.mktemp("console-storage")
    gw = start_gateway(folder, CONFIG + STORAGE)
    try:
        assert gw.http_url, f"no 'HTTP front end and console on' line:\n{gw.output}"
        yield ConsoleGateway(gw, gw.address, gw.http_url)
    finally:
        gw.stop()


def test_a_property_that_needs_a_parameter_is_a_form_not_an_error(page: Any, client: Client) -> None:
    client.set("files", "file", "first words", name="notes.txt")
    select(page, "files")
    file = wait_for(page, lambda d: prop(d, "file"), '[data-property="file"] in #service-view')
    name = wait_for(page, lambda d: file.find_element(CSS, '[data-param="name"]'), "an input for `name`")
    time.sleep(1.0)  # what following or reading it once would have shown by now
    error = file.find_element(CSS, ".error")
    assert not error.is_displayed(), f"opening the service shows no error: {error.text!r}"

    name.send_keys("notes.txt")
    file.find_element(CSS, 'button[data-action="get"]').click()
    wait_for(page, lambda d: file.find_element(CSS, ".value").text == "first words", "the file read by name")

    field = file.find_element(CSS, "[data-value]")
    field.clear()
    field.send_keys("second words")
    file.find_element(CSS, 'button[data-action="set"]').click()
    eventually(lambda: stored(client), lambda v: v == "second words", "notes.txt stored from the page")
    assert not error.is_displayed(), error.text


def stored(client: Client) -> str:
    return client.get("files", "file", name="notes.txt")
