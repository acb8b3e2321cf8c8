"""Record what an episode's graph publishes as a rosbag2 (MCAP) that `ros2 bag play` and Foxglove open.

Messages arrive as the CDR bytes rclpy received (``raw=True`` subscriptions) and are written as
they are; each topic's connection carries the ROS 2 message definition (from the rosbags Jazzy
type store), so readers without the message packages can decode the bag.
"""

from __future__ import annotations

import threading
from collections import Counter
from pathlib import Path

from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

_TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


class BagRecorder:
    """Append serialised messages to `path` (a new rosbag2 directory, storage MCAP).

    `write(topic, type_name, stamp_ns, cdr)` may be called from any thread; `counts` says how many
    messages each topic holds.
    """

    def __init__(self, path: Path):
        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(
                f"bag path: got {str(self.path)!r}, expected a path that does not exist yet"
            )
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._connections: dict[str, object] = {}
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()

    @property
    def count(self) -> int:
        return sum(self.counts.values())

    def write(self, topic: str, type_name: str, stamp_ns: int, cdr: bytes) -> None:
        with self._lock:
            if self._writer is None:
                return
            conn = self._connections.get(topic)
            if conn is None:
                conn = self._writer.add_connection(topic, type_name, typestore=_TYPESTORE)
                self._connections[topic] = conn
            self._writer.write(conn, int(stamp_ns), bytes(cdr))
            self.counts[topic] += 1

    def close(self) -> None:
        with self._lock:
            if self._writer is not None:
                self._writer.close()
                self._writer = None
