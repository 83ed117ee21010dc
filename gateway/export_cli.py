"""psgateway export-ros2 RECORDING OUT_DIR: a recording as a ROS 2 bag (MCAP storage).

  psgateway export-ros2 recordings/patrol patrol-bag
  psgateway export-ros2 recordings/patrol/patrol-0001.mcap patrol-bag
  ros2 bag info patrol-bag

RECORDING is a recording's folder (every .mcap file in it, in order) or one file. OUT_DIR is the
bag's folder, made by the export: it must not exist yet. Each property becomes a topic named as
the rosbridge front names it (/scout1/sensors/battery), of a standard message type: numbers
std_msgs/msg/Float64 (integers Int64, booleans Bool), text String, vectors Float64MultiArray, a
location geometry_msgs/msg/PoseStamped, images sensor_msgs/msg/CompressedImage (docs/recording.md).

Exit status: 0 written, 1 the recording could not be read or the bag not written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any


def add_parser(subparsers: Any) -> None:
    """Add the ``export-ros2`` subcommand to ``subparsers`` (from ``ArgumentParser.add_subparsers``)."""
    parser: argparse.ArgumentParser = subparsers.add_parser(
        "export-ros2",
        help="write a recording as a ROS 2 bag (MCAP storage)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "recording", metavar="RECORDING", help="a recording's folder, or one of its .mcap files"
    )
    parser.add_argument("out_dir", metavar="OUT_DIR", help="the bag's folder (made here; must not exist)")
    parser.add_argument("--quiet", action="store_true", help="no progress line, only the summary")
    parser.set_defaults(func=_export)


def _export(args: argparse.Namespace) -> int:
    # Imported here: rosbags is needed by this command only, not by a gateway that serves.
    from services.apps.replay.recording import Recording
    from services.kernel.errors import PropertyError

    try:
        from services.apps.replay.ros2 import ProgressLine, export_ros2
    except ModuleNotFoundError as exc:
        install = "pip install 'propertyservice-gateway[ros2]'"
        print(f"psgateway export-ros2: needs the {exc.name} package: {install}", file=sys.stderr)
        return 1

    try:
        recording = Recording(args.recording)
        # On a terminal one line rewritten twice a second; in a log a line every 5 s of a long export.
        terminal = sys.stderr.isatty()
        progress = None if args.quiet else ProgressLine(sys.stderr.write, terminal=terminal)
        report = export_ros2(recording, Path(args.out_dir), progress=progress)
    except PropertyError as exc:
        print(f"psgateway export-ros2: {exc.message}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"psgateway export-ros2: {exc}", file=sys.stderr)
        return 1
    if progress is not None and terminal:
        print(file=sys.stderr)
    print(
        f"{args.out_dir}: {report.written} messages on {len(report.messages)} topics"
        f" from {recording.event_count} changes of {len(recording.services)} services"
        f" ({report.removals} removals and {report.unreadable_count} unreadable values have no message)"
    )
    for topic in sorted(report.messages):
        print(f"  {topic}  {report.types[topic]}  {report.messages[topic]}")
    for topic, why in report.unreadable:
        print(f"  left out on {topic}: {why}", file=sys.stderr)
    return 0
