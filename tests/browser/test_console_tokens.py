"""The console under rules: the bearer token typed into the page decides, for requests and the stream.

The gateway lets nobody in without a token; ``guest`` may read scout1 and the
registry, ``operator`` may also write scout1. The page carries the token in the
Authorization header of its requests and, since EventSource cannot set headers,
in the ``ps_token`` cookie of its event stream: values shown live prove the cookie.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jwt
import pytest
from console_support import page_errors, save_screenshot, wait_for
from support.gateway_process import GatewayProcess, start_gateway

from clients.credentials import ClientCredentials
from clients.sync import Client

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(120)]

CSS = "css selector"
SECRET = "a test secret of thirty-two bytes or more, for HS256"
CONFIG = """
[auth]
jwt_secret_file = "jwt.secret"
issuer = "lab"

[[services]]
name = "scout1"
type = "sim-robot"

[[rules]]
subject = ["guest", "operator"]
service = "scout1"
operations = ["read"]
effect = "permit"

[[rules]]
subject = ["guest", "operator"]
service = "registry"
operations = ["read"]
effect = "permit"

[[rules]]
subject = "operator"
service = "scout1"
operations = ["write", "invoke"]
effect = "permit"
"""


def token(subject: str) -> str:
    return jwt.encode(
        {"sub": subject, "iss": "lab", "exp": int(time.time()) + 600}, SECRET, algorithm="HS256"
    )


@pytest.fixture
def secured(tmp_path: Path) -> Iterator[GatewayProcess]:
    (tmp_path / "jwt.secret").write_text(SECRET)
    gw = start_gateway(tmp_path, CONFIG)
    yield gw
    gw.stop()


def use_token(driver: Any, subject: str) -> None:
    """Open the header's token box, type the subject's token, submit."""
    box = driver.find_element(CSS, "details.token")
    if box.get_attribute("open") is None:
        driver.find_element(CSS, "#token-state").click()
    field = driver.find_element(CSS, "#token")
    field.send_keys(token(subject))
    driver.find_element(CSS, '#token-form button[type="submit"]').click()


def speed_widget(driver: Any) -> Any:
    return driver.find_element(CSS, '#service-view [data-property="speed"]')


def set_speed(driver: Any, text: str) -> None:
    widget = wait_for(driver, speed_widget, "the speed widget")
    field = widget.find_element(CSS, "input")
    field.clear()
    field.send_keys(text)
    widget.find_element(CSS, '[data-action="set"]').click()


def test_the_token_typed_into_the_page_decides(browser: Any, secured: GatewayProcess) -> None:
    operator = Client(secured.address, timeout=10.0, credentials=ClientCredentials(token=token("operator")))
    try:
        page_errors(browser)  # read and so dropped: what earlier tests left
        browser.get(secured.http_url)
        browser.delete_all_cookies()
        browser.execute_script("sessionStorage.clear()")
        browser.refresh()
        # No token: the registry refuses to list anything.
        wait_for(
            browser,
            lambda d: "UNAUTHENTICATED" in d.find_element(CSS, "#status").text,
            "UNAUTHENTICATED in #status without a token",
        )
        assert not browser.find_elements(CSS, "#services [data-service]")

        use_token(browser, "guest")
        wait_for(
            browser,
            lambda d: d.find_element(CSS, '#services [data-service="scout1"]').click() or True,
            "scout1 listed for guest, and clicked",
        )
        # Only the stream, authorised by its cookie, brings the value.
        wait_for(browser, lambda d: speed_widget(d).find_element(CSS, ".value").text == "0.5", "speed 0.5")
        set_speed(browser, "0.9")
        wait_for(
            browser,
            lambda d: speed_widget(d).find_element(CSS, ".error").text.startswith("PERMISSION_DENIED: "),
            "PERMISSION_DENIED beside the speed for guest",
        )
        assert operator.get("scout1", "speed") == "0.5"

        use_token(browser, "operator")
        set_speed(browser, "0.9")
        wait_for(browser, lambda d: speed_widget(d).find_element(CSS, ".value").text == "0.9", "speed 0.9")
        assert operator.get("scout1", "speed") == "0.9"
        assert not page_errors(browser), "the page threw or logged errors"
    finally:
        save_screenshot(browser, "test_the_token_typed_into_the_page_decides")
        operator.close()
        # The session's browser goes on without a token.
        browser.delete_all_cookies()
        browser.execute_script("sessionStorage.clear()")
