"""The pipe between the recorder and its writer process: length-prefixed frames, each one message.

A frame is a 4-byte big-endian length and that many bytes of a pickled tuple whose first item
names the message. Both ends are this package's own code, started together by the recorder
(:mod:`services.apps.recorder.feed` on the gateway's side,
:mod:`services.apps.recorder.process` on the writer's), so pickle is safe here, and it is the
cheapest encoding of a batch of plain tuples CPython has (one C call for a whole batch).

Sans-IO: :func:`frame` makes the bytes of a message, :class:`FrameReader` cuts received bytes into
messages; the two ends bring their own pipes.

The recorder sends:

* ``("open", root, max_total_bytes, when_full)``: first, once: the folder and its disk budget;
* ``("start", name, selectors, folder, version, started_ns, limits)``: a recording begins
  (``limits``: the fields of :class:`~services.apps.recorder.writer.Limits` as a dict);
* ``("events", name, groups)``: changes to write, ``groups`` a list of ``(log_ns, events)``, each
  event an :data:`EventFields` tuple;
* ``("service", service, type, model)``: the answer to a ``describe`` (``model``: a
  :class:`~services.kernel.model.ServiceModel`, or None when it could not be read);
* ``("stop", name)``: write what is left, finish the file, answer ``ended``.

The end of the pipe (EOF: the recorder closed it, or the gateway died) finishes every file.

The writer process sends:

* ``("progress", name, taken_events, taken_bytes, stats)``: it has written that many more events
  (of that many value bytes) of the recording; ``stats`` as :meth:`RecordingWriter.stats` says;
* ``("ended", name, state, reason, stats)``: the recording ended (a stop, a limit, an error);
* ``("describe", service)``: it needs the service's type and model (answered by ``service``);
* ``("removed", path)``: the disk budget removed a file to make room;
* ``("budget", used)``: the bytes every recording takes now;
* ``("log", level, text)``: a line for the gateway's log.
"""

from __future__ import annotations

import pickle
import struct
from typing import Any

__all__ = [
    "HEADER_BYTES",
    "MAX_FRAME_BYTES",
    "EventFields",
    "FrameError",
    "FrameReader",
    "frame",
    "read_header",
    "read_payload",
]

_HEADER = struct.Struct(">I")
#: Bytes of a frame's header (its length).
HEADER_BYTES = _HEADER.size
#: The largest frame either end accepts: a batch is cut long before (the recorder sends one at
#: 1 MiB of values), a single value is bounded by the gateway's value size limit (16 MiB at most).
MAX_FRAME_BYTES = 64 * 1024 * 1024

#: One change as it crosses the pipe: service, path, value, sequence, time_ns, conflated, gap,
#: removed (a :class:`~services.kernel.follow.FollowedEvent` as a plain tuple: a named tuple would
#: pickle its class with every change, at eight times the cost).
EventFields = tuple[str, str, str | bytes, int, int, int, bool, bool]


class FrameError(ValueError):
    """A frame that cannot be: longer than :data:`MAX_FRAME_BYTES`, or not a message."""


def frame(message: tuple[Any, ...]) -> bytes:
    """The bytes of one message: its length, then the message pickled."""
    payload = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    if len(payload) > MAX_FRAME_BYTES:
        raise FrameError(f"a frame of {len(payload)} bytes is over {MAX_FRAME_BYTES}")
    return _HEADER.pack(len(payload)) + payload


class FrameReader:
    """Cuts a byte stream into messages: :meth:`feed` bytes as they come, take what is complete."""

    __slots__ = ("_buffer",)

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[tuple[Any, ...]]:
        """The messages ``data`` completes (none when a frame is still partial)."""
        buffer = self._buffer
        buffer += data
        messages: list[tuple[Any, ...]] = []
        start = 0
        while len(buffer) - start >= _HEADER.size:
            (length,) = _HEADER.unpack_from(buffer, start)
            if length > MAX_FRAME_BYTES:
                raise FrameError(f"a frame of {length} bytes is over {MAX_FRAME_BYTES}")
            end = start + _HEADER.size + length
            if len(buffer) < end:
                break
            messages.append(read_payload(buffer[start + _HEADER.size : end]))
            start = end
        if start:
            del buffer[:start]
        return messages

    @property
    def pending(self) -> int:
        """Bytes of a frame not complete yet."""
        return len(self._buffer)


def read_header(data: bytes) -> int:
    """The length a frame's 4-byte header gives (for a reader that reads the header first)."""
    (length,) = _HEADER.unpack(data)
    if length > MAX_FRAME_BYTES:
        raise FrameError(f"a frame of {length} bytes is over {MAX_FRAME_BYTES}")
    return int(length)


def read_payload(data: bytes | bytearray) -> tuple[Any, ...]:
    """The message of a frame's payload (the bytes after its header)."""
    message = pickle.loads(data)
    if not isinstance(message, tuple) or not message or not isinstance(message[0], str):
        raise FrameError(f"not a message: {type(message).__name__}")
    return message
