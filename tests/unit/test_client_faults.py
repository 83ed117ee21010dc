"""A client's failures as one rate-limited line without a traceback; a bug's traceback untouched."""

from __future__ import annotations

import logging

import pytest

from gateway.client_faults import ClientFaultFilter, FaultLines


class BadRequest(Exception):
    """Stands for a library's "the client sent garbage" exception."""


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def library_log(caplog: pytest.LogCaptureFixture) -> tuple[logging.Logger, Clock, pytest.LogCaptureFixture]:
    clock = Clock()
    logger = logging.getLogger("test.library.server")
    fault_filter = ClientFaultFilter((BadRequest,), lines=FaultLines(rate=1.0, burst=3, clock=clock))
    logger.addFilter(fault_filter)
    caplog.set_level(logging.INFO, logger="test.library.server")
    yield logger, clock, caplog
    logger.removeFilter(fault_filter)


def log_bad_request(logger: logging.Logger, text: str = "Invalid header token:\n\n  b'Bad Header'") -> None:
    try:
        raise BadRequest(text)
    except BadRequest:
        logger.exception("Error handling request from %s", "127.0.0.1")


def test_a_client_fault_is_one_warning_line_without_its_traceback(library_log) -> None:  # type: ignore[no-untyped-def]
    logger, _, caplog = library_log
    log_bad_request(logger)
    [record] = caplog.records
    assert record.levelno == logging.WARNING and record.exc_info is None
    assert record.getMessage() == (
        "Error handling request from 127.0.0.1: BadRequest: Invalid header token: b'Bad Header'"
    )
    assert "Traceback" not in caplog.text


def test_a_flood_of_faults_is_held_to_the_rate_and_the_next_line_counts_what_was_dropped(  # type: ignore[no-untyped-def]
    library_log,
) -> None:
    logger, clock, caplog = library_log
    for _ in range(100):
        log_bad_request(logger)
    assert len(caplog.records) == 3  # the burst
    clock.now += 1.0  # room for one more line
    log_bad_request(logger)
    assert len(caplog.records) == 4
    assert caplog.records[-1].getMessage().endswith("(97 more like it not logged)")


def test_other_exceptions_keep_their_traceback(library_log) -> None:  # type: ignore[no-untyped-def]
    logger, _, caplog = library_log
    try:
        {}["crash"]  # a bug in a handler
    except KeyError:
        logger.exception("Unhandled exception")
    [record] = caplog.records
    assert record.levelno == logging.ERROR and record.exc_info is not None
    assert "Traceback (most recent call last)" in caplog.text


def test_a_long_client_text_is_clipped() -> None:
    logger = logging.getLogger("test.library.clipped")
    fault_filter = ClientFaultFilter((BadRequest,), lines=FaultLines(rate=1.0, burst=3))
    fault = BadRequest("x" * 70_000)
    record = logger.makeRecord(logger.name, logging.ERROR, __file__, 1, "bad", (), (BadRequest, fault, None))
    assert fault_filter.filter(record)
    assert len(record.getMessage()) <= 300
