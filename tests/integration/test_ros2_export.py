"""``psgateway export-ros2`` run as a user runs it, and its bag read back with rosbags' own reader."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from support.recordings import FRAME_A, FRAME_B, SWARM_SERVICES, swarm_changes, swarm_recording

from services.kernel.pose import quaternion
from services.kernel.values import parse_vector

pytestmark = pytest.mark.timeout(120)

PSGATEWAY = [sys.executable, "-m", "gateway.cli"]
#: The message type each property of the test swarm is exported as.
TYPES = {
    "location": "geometry_msgs/msg/PoseStamped",
    "speed": "std_msgs/msg/Float64",
    "sensors.battery": "std_msgs/msg/Float64",
    "status": "std_msgs/msg/String",
    "frame": "sensor_msgs/msg/CompressedImage",
}


def export(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*PSGATEWAY, "export-ros2", *args], capture_output=True, text=True, timeout=60, check=False
    )


def test_a_recording_exported_as_a_ros2_bag_reads_back_message_for_message(tmp_path: Path) -> None:
    recording = swarm_recording(tmp_path / "recordings", files=2)
    bag = tmp_path / "swarm-bag"
    done = export(str(recording), str(bag))
    assert done.returncode == 0, done.stderr
    changes = swarm_changes()
    kept = sorted((c for c in changes if not c.removed), key=lambda c: c.log_time_ns)
    assert f"{len(kept)} messages on 9 topics from {len(changes)} changes of 3 services" in done.stdout
    assert "1 removals" in done.stdout

    store = get_typestore(Stores.ROS2_HUMBLE)
    read: list[tuple[str, str, int, object]] = []
    with Reader(bag) as reader:
        assert reader.message_count == len(kept)
        for connection, timestamp, raw in reader.messages():
            message = store.deserialize_cdr(raw, connection.msgtype)
            read.append((connection.topic, connection.msgtype, timestamp, message))
    read.sort(key=lambda m: m[2])
    assert [(topic, stamp) for topic, _, stamp, _ in read] == [
        (f"/{c.service}/{c.path.replace('.', '/')}", c.log_time_ns) for c in kept
    ]
    for change, (_topic, msgtype, _stamp, message) in zip(kept, read, strict=True):
        assert msgtype == TYPES[change.path], change
        assert change.path in {p.name for p in SWARM_SERVICES[change.service].properties}
        if msgtype == "std_msgs/msg/Float64":
            assert message.data == float(str(change.value))
        elif msgtype == "std_msgs/msg/String":
            assert message.data == change.value
        elif msgtype == "geometry_msgs/msg/PoseStamped":
            x, y, z, roll, pitch, yaw = (float(v) for v in parse_vector(str(change.value)))
            pose = message.pose
            assert (pose.position.x, pose.position.y, pose.position.z) == (x, y, z)
            orientation = pose.orientation
            assert np.allclose(
                (orientation.x, orientation.y, orientation.z, orientation.w), quaternion(roll, pitch, yaw)
            )
            assert message.header.frame_id == "world"
            # The header carries the change's own time (a device's clock), the bag the log time.
            assert message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec == change.time_ns
        else:
            assert bytes(message.data) == change.value
            assert message.format == "png"
    frames = [bytes(m.data) for _, t, _, m in read if t == TYPES["frame"]]
    assert frames == [FRAME_A, FRAME_B]


def test_an_export_refuses_a_bag_folder_that_exists_and_a_recording_that_does_not(tmp_path: Path) -> None:
    recording = swarm_recording(tmp_path / "recordings", files=1)
    taken = tmp_path / "taken"
    taken.mkdir()
    refused = export(str(recording), str(taken))
    assert refused.returncode == 1
    assert "exists already" in refused.stderr
    assert list(taken.iterdir()) == []
    missing = export(str(tmp_path / "nothing-here"), str(tmp_path / "bag"))
    assert missing.returncode == 1
    assert "no such file or folder" in missing.stderr
    assert not (tmp_path / "bag").exists()


def test_export_ros2_help_says_what_goes_in_and_what_comes_out() -> None:
    shown = subprocess.run(
        [*PSGATEWAY, "export-ros2", "--help"], capture_output=True, text=True, timeout=30, check=True
    )
    for words in ("RECORDING", "OUT_DIR", "must not exist", "PoseStamped", "ros2 bag info"):
        assert words in shown.stdout
