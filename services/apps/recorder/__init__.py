"""The recorder: what Listens of selectors hear, written as MCAP files (docs/recording.md).

* :mod:`~services.apps.recorder.service` — the service: ``start``, ``stop``, ``recordings``.
* :mod:`~services.apps.recorder.feed` — the writer process started and fed: each recording's
  bounded intake, sent in batches.
* :mod:`~services.apps.recorder.process` — the writer process (``python -m``): every recording's files.
* :mod:`~services.apps.recorder.frames` — the messages on the pipe between the two.
* :mod:`~services.apps.recorder.writer` — one recording's files, written batch by batch in the process.
* :mod:`~services.apps.recorder.layout` — one MCAP file: metadata, channels, schemas, messages.
* :mod:`~services.apps.recorder.budget` — every recording's files together under a disk budget.
* :mod:`~services.apps.recorder.reading` — the recorded changes read back (replay, history).
"""

from services.apps.recorder.service import Recorder, RecorderService

__all__ = ["Recorder", "RecorderService"]
