"""The log line formats: what a line says about its request, and ids a client may choose."""

from __future__ import annotations

import io
import json
import logging
from collections.abc import Iterator

import pytest

from gateway.logs import (
    JsonFormatter,
    RequestContext,
    TextFormatter,
    current_request,
    outside_requests,
    request_id_from,
)
from services.kernel.directory import own_context


@pytest.fixture
def written() -> Iterator[tuple[logging.Logger, io.StringIO, logging.StreamHandler[io.StringIO]]]:
    out = io.StringIO()
    handler = logging.StreamHandler(out)
    logger = logging.getLogger("test.log_lines")
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    logger.propagate = False
    yield logger, out, handler
    logger.removeHandler(handler)


def test_a_json_line_carries_the_request_and_its_own_fields(written: tuple) -> None:
    logger, out, handler = written
    handler.setFormatter(JsonFormatter())
    token = current_request.set(RequestContext("r-1", "rover", "location", "alice"))
    try:
        logger.warning("device says %s", "h\u00e9\nllo", extra={"code": "UNAVAILABLE"})
    finally:
        current_request.reset(token)
    logger.info("no request")
    first, second = out.getvalue().splitlines()
    assert first.isascii()
    line = json.loads(first)
    assert line["message"] == "device says h\u00e9\nllo"
    assert (line["level"], line["logger"]) == ("warning", "test.log_lines")
    assert {k: line[k] for k in ("request_id", "service", "property", "subject", "code")} == {
        "request_id": "r-1",
        "service": "rover",
        "property": "location",
        "subject": "alice",
        "code": "UNAVAILABLE",
    }
    assert set(json.loads(second)) == {"time", "level", "logger", "message"}


def test_a_traceback_stays_inside_its_json_line(written: tuple) -> None:
    logger, out, handler = written
    handler.setFormatter(JsonFormatter())
    try:
        raise ValueError("broken")
    except ValueError:
        logger.exception("failed")
    (line,) = out.getvalue().splitlines()
    assert "ValueError: broken" in json.loads(line)["exception"]


def test_a_text_line_names_its_request_before_any_traceback(written: tuple) -> None:
    logger, out, handler = written
    handler.setFormatter(TextFormatter())
    token = current_request.set(RequestContext("r-2"))
    try:
        try:
            raise ValueError("broken")
        except ValueError:
            logger.exception("failed")
    finally:
        current_request.reset(token)
    first = out.getvalue().splitlines()[0]
    assert first.endswith("ERROR test.log_lines: failed [request r-2]")


def test_a_task_outside_requests_logs_none() -> None:
    token = current_request.set(RequestContext("r-3"))
    try:
        assert outside_requests().run(current_request.get) is None
        assert current_request.get() is not None
    finally:
        current_request.reset(token)


def test_a_task_for_a_service_names_it_until_a_request_does(written: tuple) -> None:
    logger, out, handler = written
    handler.setFormatter(JsonFormatter())
    background = outside_requests("rover")
    background.run(logger.info, "connected")
    background.run(current_request.set, RequestContext("r-4", service="scout1"))
    background.run(logger.info, "a call")
    first, second = (json.loads(line) for line in out.getvalue().splitlines())
    assert first["service"] == "rover" and "request_id" not in first
    assert second["service"] == "scout1" and second["request_id"] == "r-4"
    assert "service" not in json.loads(JsonFormatter().format(logging.makeLogRecord({"msg": "x"})))


def test_a_service_s_own_work_started_by_a_device_s_task_does_not_log_as_that_device(
    written: tuple,
) -> None:
    """A group's refresh started from rover1's proxy task (its reconnection reached the registry,
    whose change reached the group) calls rover2: rover2's lines must not name rover1."""
    logger, out, handler = written
    handler.setFormatter(JsonFormatter())

    def start_own_work() -> None:
        own_context().run(logger.info, "device rover2: sent a line")

    rover1_task = outside_requests("rover1")
    rover1_task.run(current_request.set, RequestContext("r-5", service="rover1"))
    rover1_task.run(start_own_work)
    [line] = (json.loads(line) for line in out.getvalue().splitlines())
    assert "service" not in line and "request_id" not in line, line


@pytest.mark.parametrize("chosen", ["", "x" * 65, "caf\u00e9", "a\nb", "tab\there", "   "])
def test_an_unusable_client_id_gets_a_fresh_one(chosen: str) -> None:
    fresh = request_id_from(chosen)
    assert fresh != chosen and len(fresh) == 16 and int(fresh, 16) >= 0


def test_a_usable_client_id_is_kept() -> None:
    assert request_id_from("3f1c2d9e-8a7b-4c6d-9e0f-1a2b3c4d5e6f") == "3f1c2d9e-8a7b-4c6d-9e0f-1a2b3c4d5e6f"
    assert request_id_from(b"trace-42") == "trace-42"
