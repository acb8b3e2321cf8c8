"""Cyclone DDS configuration that keeps all traffic on 127.0.0.1.

Multicast is often unavailable on the loopback interface, so discovery uses unicast to a list of
participant ports on 127.0.0.1 (SPDP unicast ports 7410 + 250 * domain + 10 + 2 * index).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

from area3d_msgs_py.errors import InputError

# Unicast discovery probes one port per participant index on each peer; a full graph (sim_bridge,
# perception, semantics, planner, runner, CLI tools, tests) needs about a dozen participants.
MAX_PARTICIPANTS = 32
# Cyclone DDS' largest RTPS message on loopback; bigger datagrams mean fewer fragments for
# 16 MB point clouds (UDP limit is 65507 bytes of payload).
MAX_MESSAGE_SIZE_BYTES = 65000
FRAGMENT_SIZE_BYTES = 64000
# Socket receive buffer so a burst of fragments of a large sample is not dropped by the kernel.
SOCKET_RECEIVE_BUFFER = "8MB"
ROS_DOMAIN_ID_MAX = 232  # ROS 2: domain ids 0..232 are valid with the default port mapping


def _check_domain(domain_id: int) -> int:
    if not isinstance(domain_id, int) or isinstance(domain_id, bool):
        raise InputError("domain_id", domain_id, f"an int in 0..{ROS_DOMAIN_ID_MAX}")
    if not 0 <= domain_id <= ROS_DOMAIN_ID_MAX:
        raise InputError("domain_id", domain_id, f"an int in 0..{ROS_DOMAIN_ID_MAX}")
    return domain_id


def loopback_config(domain_id: int) -> str:
    """CYCLONEDDS_URI XML that pins Cyclone DDS to 127.0.0.1 with unicast discovery.

    The XML applies to any domain (so a process may join several); ``domain_id`` is validated
    here and selected through ROS_DOMAIN_ID by ``use_loopback``.
    """
    _check_domain(domain_id)
    return (
        "<CycloneDDS>"
        '<Domain id="any">'
        "<General>"
        '<Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>'
        "<AllowMulticast>false</AllowMulticast>"
        f"<MaxMessageSize>{MAX_MESSAGE_SIZE_BYTES}B</MaxMessageSize>"
        f"<FragmentSize>{FRAGMENT_SIZE_BYTES}B</FragmentSize>"
        "</General>"
        "<Discovery>"
        "<ParticipantIndex>auto</ParticipantIndex>"
        f"<MaxAutoParticipantIndex>{MAX_PARTICIPANTS}</MaxAutoParticipantIndex>"
        '<Peers><Peer address="127.0.0.1"/></Peers>'
        "</Discovery>"
        "<Internal>"
        f'<SocketReceiveBufferSize min="default" max="{SOCKET_RECEIVE_BUFFER}"/>'
        "</Internal>"
        "</Domain>"
        "</CycloneDDS>"
    )


def use_loopback(domain_id: int) -> None:
    """Set CYCLONEDDS_URI and ROS_DOMAIN_ID for this process and the processes it starts.

    Call before the first Node is created (Cyclone reads its configuration once per domain).
    """
    os.environ["CYCLONEDDS_URI"] = loopback_config(domain_id)
    os.environ["ROS_DOMAIN_ID"] = str(domain_id)


def domain_id_from_env() -> int:
    """ROS_DOMAIN_ID from the environment, 0 when unset (as in ROS 2)."""
    text = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    try:
        return _check_domain(int(text))
    except ValueError:
        raise InputError("ROS_DOMAIN_ID", text, f"an int in 0..{ROS_DOMAIN_ID_MAX}") from None


@contextlib.contextmanager
def loopback_domain(domain_id: int) -> Iterator[int]:
    """`use_loopback(domain_id)` for the duration of a `with` block, then the previous settings."""
    saved = {key: os.environ.get(key) for key in ("CYCLONEDDS_URI", "ROS_DOMAIN_ID")}
    use_loopback(domain_id)
    try:
        yield domain_id
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
