"""A ROS 2 style console logger: ``[LEVEL] [unix_time] [node_name]: message`` on stderr."""

from __future__ import annotations

import sys
import threading
import time

LEVELS = {"DEBUG": 10, "INFO": 20, "WARN": 30, "ERROR": 40, "FATAL": 50}


class Logger:
    """What ``Node.get_logger()`` returns; ``min_level`` filters like ``--log-level``."""

    def __init__(self, name: str, min_level: str = "INFO") -> None:
        self.name = name
        self.min_level = LEVELS.get(min_level.upper(), LEVELS["INFO"])
        self._lock = threading.Lock()

    def _log(self, level: str, message: str) -> None:
        if LEVELS[level] < self.min_level:
            return
        ns = time.time_ns()
        line = (
            f"[{level}] [{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}] [{self.name}]: {message}\n"
        )
        with self._lock:
            sys.stderr.write(line)
            sys.stderr.flush()

    def debug(self, message: str) -> None:
        self._log("DEBUG", message)

    def info(self, message: str) -> None:
        self._log("INFO", message)

    def warning(self, message: str) -> None:
        self._log("WARN", message)

    warn = warning

    def error(self, message: str) -> None:
        self._log("ERROR", message)

    def fatal(self, message: str) -> None:
        self._log("FATAL", message)
