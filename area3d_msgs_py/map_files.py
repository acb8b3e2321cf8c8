"""The answer of a MapFile service (area3d_interfaces/srv/MapFile: save_map, load_map,
export_mesh), the same from every node that serves one."""

from __future__ import annotations

import traceback
from pathlib import Path
from typing import Any

from area3d_msgs_py.errors import InputError


def done(response: Any, service: str, path: Path, size: int, logger: Any, what: str) -> Any:
    """Success: what was done, the absolute path and its size, logged."""
    response.success = True
    response.path = str(path)
    response.size_bytes = int(size)
    response.message = f"{what}: {path} ({size / 1e6:.2f} MB)"
    logger.info(f"{service}: {response.message}")
    return response


def refused(response: Any, service: str, exc: Exception, logger: Any) -> Any:
    """A refusal (a path that cannot be written, a file that does not fit): why, logged; the
    node's map is as it was."""
    response.success = False
    response.path = ""
    response.size_bytes = 0
    response.message = f"{type(exc).__name__}: {exc}" if isinstance(exc, OSError) else str(exc)
    logger.warning(f"{service}: {response.message}")
    return response


def load_failed(response: Any, service: str, exc: Exception, logger: Any) -> Any:
    """A load that did not happen, into a new map the node then drops: a file that does not fit
    or cannot be read (`InputError`, `OSError`) is refused; any other failure (a file the checks
    do not cover, or a bug) is said in the answer with the traceback in the log. Either way the
    node keeps its map and runs on."""
    if isinstance(exc, InputError | OSError):
        return refused(response, service, exc, logger)
    response.success = False
    response.path = ""
    response.size_bytes = 0
    response.message = (
        f"could not be done: {type(exc).__name__}: {exc} (the running map is as it was; "
        "the traceback is in the node's log)"
    )
    logger.error(f"{service}: {response.message}\n{''.join(traceback.format_exception(exc))}")
    return response
