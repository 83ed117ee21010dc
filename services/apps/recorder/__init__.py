"""The recorder: what Listens of selectors hear, written as MCAP files (docs/recording.md).

* :mod:`~services.apps.recorder.service` — the service: ``start``, ``stop``, ``recordings``.
* :mod:`~services.apps.recorder.writer` — one recording's writer thread and its bounded intake.
* :mod:`~services.apps.recorder.layout` — one MCAP file: metadata, channels, schemas, messages.
* :mod:`~services.apps.recorder.budget` — every recording's files together under a disk budget.
* :mod:`~services.apps.recorder.reading` — the recorded changes read back (replay, history).
"""

from services.apps.recorder.service import Recorder, RecorderService

__all__ = ["Recorder", "RecorderService"]
