"""Record the messages an episode sees as a rosbag2 (MCAP) file that `ros2 bag play` and Foxglove open."""

from __future__ import annotations

import threading
from pathlib import Path

from rosbags.rosbag2 import StoragePlugin, Writer

from area3d_msgs_py import msgs


class BagRecorder:
    """Append messages to `path` (a new rosbag2 directory, storage MCAP).

    `write(topic, type_name, stamp_ns, msg)` may be called from any thread.
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
        self.count = 0

    def write(self, topic: str, type_name: str, stamp_ns: int, msg: object) -> None:
        data = msgs.serialize(msg)
        with self._lock:
            if self._writer is None:
                return
            conn = self._connections.get(topic)
            if conn is None:
                conn = self._writer.add_connection(topic, type_name, typestore=msgs.typestore)
                self._connections[topic] = conn
            self._writer.write(conn, int(stamp_ns), data)
            self.count += 1

    def close(self) -> None:
        with self._lock:
            if self._writer is not None:
                self._writer.close()
                self._writer = None
