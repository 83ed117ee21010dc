"""Recordings played back: as live services (:class:`Replay`, ``type = "replay"``) and as a
ROS 2 bag (:mod:`services.apps.replay.ros2`, ``psgateway export-ros2``).

* :mod:`~services.apps.replay.recording` — a recording's files read: its services' models and its
  changes in time order (the ``/_events`` channel; docs/recording.md);
* :mod:`~services.apps.replay.timeline` — where a replay stands as the wall clock moves it;
* :mod:`~services.apps.replay.replayed` — one recorded service served again, read-only;
* :mod:`~services.apps.replay.service` — the replay service and its player;
* :mod:`~services.apps.replay.ros2` — the export to a ROS 2 bag (imports ``rosbags`` only there).
"""

from services.apps.replay.recording import RecordedEvent, RecordedService, Recording
from services.apps.replay.replayed import ReplayedService
from services.apps.replay.service import Replay

__all__ = ["RecordedEvent", "RecordedService", "Recording", "Replay", "ReplayedService"]
