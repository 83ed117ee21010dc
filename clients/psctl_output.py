"""Where psctl's results go: one :class:`TargetOutput` per gateway named by ``-t``, and the JSON-lines
file of ``--output FILE`` (:class:`RecordFile`).

With one target psctl prints as it always has. With several, every line names its target
(``[gw1:50051] ...``), every ``--json`` document carries a ``"target"`` key, and the results of a
command that ends by itself are held until their target is done, so that one target's lines stay
together in the order the targets were given. ``--format jsonl`` writes records: one JSON object a
line with ``target``, ``service``, ``property``, ``value``, ``time`` and ``kind`` always present.
"""

from __future__ import annotations

import base64
import contextlib
import json
import logging
import logging.handlers
import sys
from collections.abc import Callable
from datetime import UTC, datetime
from typing import Any, TextIO

from clients.values import Value

__all__ = ["FORMATS", "RecordFile", "RecordFileError", "TargetOutput", "record_json"]

#: ``--format`` choices: lines for people, one JSON document per result, one JSON record a line.
FORMATS = ("text", "json", "jsonl")


def record_json(
    *,
    target: str,
    kind: str,
    service: str | None,
    prop: str | None,
    value: Value | None,
    time: datetime | None,
    extra: dict[str, Any],
) -> str:
    """One ``--format jsonl`` record: the six keys every record has, then ``extra``. A binary value
    is ``"value": null`` with its bytes in ``"data"`` (base64)."""
    record: dict[str, Any] = {
        "target": target,
        "service": service,
        "property": prop,
        "value": value if not isinstance(value, bytes) else None,
        "time": None if time is None else time.astimezone(UTC).isoformat(),
        "kind": kind,
    }
    if isinstance(value, bytes):
        record["data"] = base64.b64encode(value).decode("ascii")
    record.update(extra)
    return json.dumps(record, ensure_ascii=False)


class _RaisingRotatingHandler(logging.handlers.RotatingFileHandler):
    """logging's rotating file writer, with a failed write raised to the caller (a full disk is
    psctl's error to report) rather than printed by logging as a traceback."""

    def handleError(self, record: logging.LogRecord) -> None:
        error = sys.exception()  # the one emit() is handling
        if error is not None:
            raise error


class RecordFileError(Exception):
    """A record could not be written to the ``--output`` file (a full disk, a file removed under it)."""


class RecordFile:
    """``--output FILE`` for ``--format jsonl``: records appended to FILE, one a line.

    ``max_bytes`` bounds the file: a record that would take it past the bound first moves FILE to
    FILE.1 (FILE.1 to FILE.2, and so on, ``keep`` old files at most; the oldest is dropped), as
    logging's RotatingFileHandler does, which does the writing (it counts a record's characters, so
    a file of non-ASCII values may pass the bound by their extra bytes). ``max_bytes`` 0 appends
    without a bound, for a user who asks for that. A FILE that is not a regular file (a pipe,
    /dev/stdout) is never moved.
    """

    def __init__(self, path: str, *, max_bytes: int, keep: int) -> None:
        # delay=False: a file that cannot be opened is an error now, before any gateway is asked.
        self._handler = _RaisingRotatingHandler(
            path, mode="a", maxBytes=max_bytes, backupCount=keep, encoding="utf-8"
        )
        self._handler.setFormatter(logging.Formatter("%(message)s"))
        self.path = path

    def write(self, line: str) -> None:
        """Append one record (a line without its newline), flushed to the file before this returns."""
        try:
            self._handler.emit(logging.makeLogRecord({"msg": line, "args": None}))
        except OSError as e:
            raise RecordFileError(f"--output {self.path}: {e.strerror or e}") from None

    def close(self) -> None:
        # A write that failed was said already; closing must not raise it a second time.
        with contextlib.suppress(OSError):
            self._handler.close()


class TargetOutput:
    """What one target of a psctl command prints: its lines, JSON documents, records and errors.

    ``tagged`` (several targets): each line starts with ``[TARGET] ``, each JSON document gets a
    ``"target"`` key. ``held``: nothing is printed until :meth:`release`, so that concurrent
    targets do not mix their lines. ``records``: where ``--format jsonl`` records go (stdout when None).
    """

    def __init__(
        self,
        target: str,
        *,
        tagged: bool = False,
        held: bool = False,
        format: str = "text",
        records: RecordFile | None = None,
    ) -> None:
        self.target = target
        self.tagged = tagged
        self.format = format
        self._records = records
        self._held: list[tuple[Callable[[str], None], str]] | None = [] if held else None

    @property
    def as_json(self) -> bool:
        """``--json``: one JSON document per result."""
        return self.format == "json"

    @property
    def as_records(self) -> bool:
        """``--format jsonl``: one record a line."""
        return self.format == "jsonl"

    def _emit(self, sink: Callable[[str], None], text: str) -> None:
        if self._held is not None:
            self._held.append((sink, text))
        else:
            sink(text)

    def _tag(self, text: str) -> str:
        if not self.tagged:
            return text
        return "\n".join(f"[{self.target}] {line}" for line in text.split("\n"))

    def line(self, text: str) -> None:
        """A line of text on stdout."""
        self._emit(_stdout, self._tag(text))

    def json(self, doc: Any) -> None:
        """A ``--json`` document on one line; with several targets, ``{"target": T, ...doc}`` (a
        list: ``{"target": T, "result": [...]}``)."""
        if self.tagged:
            doc = (
                {"target": self.target, **doc}
                if isinstance(doc, dict)
                else {"target": self.target, "result": doc}
            )
        self._emit(_stdout, json.dumps(doc, ensure_ascii=False))

    def record(
        self,
        kind: str,
        service: str | None,
        prop: str | None,
        value: Value | None = None,
        *,
        time: datetime | None = None,
        extra: dict[str, Any] | None = None,
    ) -> None:
        """A ``--format jsonl`` record (see :func:`record_json`); ``time`` None: now."""
        when = time if time is not None else datetime.now(UTC)
        text = record_json(
            target=self.target,
            kind=kind,
            service=service,
            prop=prop,
            value=value,
            time=when,
            extra=extra or {},
        )
        self._emit(self._records.write if self._records is not None else _stdout, text)

    def table(self, rows: list[list[str]]) -> None:
        """Rows of cells as aligned columns, the first row being the header."""
        widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
        for row in rows:
            self.line("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip())

    def error(self, message: str) -> None:
        """``error: MESSAGE`` on stderr (``[TARGET] error: ...`` with several targets)."""
        self._emit(_stderr, self._tag(f"error: {message}"))

    def note(self, message: str) -> None:
        """A line on stderr that is not an error (a stream that ended, a target that moved on)."""
        self._emit(_stderr, self._tag(message))

    def release(self) -> None:
        """Print what was held, in order; from now on print at once."""
        held, self._held = self._held or [], None
        for sink, text in held:
            sink(text)


def _print(stream: TextIO, text: str) -> None:
    print(text, file=stream, flush=True)


def _stdout(text: str) -> None:
    _print(sys.stdout, text)


def _stderr(text: str) -> None:
    _print(sys.stderr, text)
