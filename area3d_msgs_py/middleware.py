"""How the graph's processes use the middleware: Fast DDS transport profile, domain, discovery, QoS.

The ROS 2 wheels bring rclpy on ``rmw_fastrtps_cpp`` (ROS 2 Jazzy's default). Fast DDS' default
shared-memory segment (0.5 MB) is smaller than one 640x480 depth image, so by default such samples
fall back to fragmented UDP. ``configure()`` therefore points Fast DDS at a participant profile of
this package (``FASTRTPS_DEFAULT_PROFILES_FILE``) unless the user gave one:

- ``shm`` (default): a shared-memory transport with a 32 MB segment, plus UDPv4 for peers on other
  hosts; builtin transports off.
- ``udp``: UDPv4 only (no shared memory), e.g. for nodes in network namespaces of one machine,
  which share /dev/shm but must talk over the network.
- ``default``: no profile, Fast DDS' own defaults.

Both profiles also announce each participant every ``ANNOUNCEMENT_PERIOD_S`` (Fast DDS: 3 s). The
graph's processes start together, and a participant's first announcements can reach a peer before
that peer listens; the pair then found each other only at the next periodic announcement, so about
half the launches of the graph waited 3 s more for a reader or the planner's service. A shorter
period bounds that wait; on a LAN it costs a few hundred bytes per participant and period.

Chosen with ``AREA3D_TRANSPORT``. ``graph_env()`` is the environment the launcher gives the node
processes: domain, discovery range (``LOCALHOST`` keeps discovery on this machine) and transport.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import os
import socket
import tempfile
from pathlib import Path

from area3d_msgs_py.errors import InputError

TRANSPORTS = ("shm", "udp", "default")
TRANSPORT_ENV = "AREA3D_TRANSPORT"
PROFILE_ENV_VARS = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")
# Largest sample that must cross shared memory in one piece: a 16 MB point cloud with headroom.
SHM_SEGMENT_BYTES = 32 * 1024 * 1024
DISCOVERY_RANGES = ("LOCALHOST", "SUBNET", "OFF", "SYSTEM_DEFAULT")
# ROS 2 domain ids that map to valid UDP ports on every platform (REP/ROS 2 docs: 0..101 on Linux
# without clashing with the ephemeral port range); 0 is left to the user's own graph.
FREE_DOMAIN_RANGE = range(1, 102)
# Period of each participant's announcements (Fast DDS' leaseAnnouncement; its default is 3 s)
ANNOUNCEMENT_PERIOD_S = 0.5
# Fast DDS well-known ports (RTPS spec defaults): PB + DG * domain + d1 (+ PG * participant).
_PORT_BASE, _DOMAIN_GAIN, _UNICAST_OFFSET = 7400, 250, 10

_UDP = """      <transport_descriptor>
        <transport_id>area3d_udp</transport_id>
        <type>UDPv4</type>
      </transport_descriptor>
"""
_SHM = f"""      <transport_descriptor>
        <transport_id>area3d_shm</transport_id>
        <type>SHM</type>
        <segment_size>{SHM_SEGMENT_BYTES}</segment_size>
      </transport_descriptor>
"""


def profile_xml(transport: str) -> str:
    """Fast DDS XML with one default participant profile for ``transport`` ('shm' or 'udp'): its
    transports and its announcement period."""
    if transport not in ("shm", "udp"):
        raise InputError("transport", transport, "'shm' or 'udp' (or 'default': no profile)")
    descriptors = (_SHM if transport == "shm" else "") + _UDP
    ids = (["area3d_shm"] if transport == "shm" else []) + ["area3d_udp"]
    uses = "".join(f"          <transport_id>{i}</transport_id>\n" for i in ids)
    return f"""<?xml version="1.0" encoding="UTF-8" ?>
<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <profiles>
    <transport_descriptors>
{descriptors}    </transport_descriptors>
    <participant profile_name="area3d_{transport}" is_default_profile="true">
      <rtps>
        <builtin>
          <discovery_config>
            <leaseAnnouncement>
              <sec>{int(ANNOUNCEMENT_PERIOD_S)}</sec>
              <nanosec>{round(ANNOUNCEMENT_PERIOD_S % 1 * 1e9)}</nanosec>
            </leaseAnnouncement>
          </discovery_config>
        </builtin>
        <userTransports>
{uses}        </userTransports>
        <useBuiltinTransports>false</useBuiltinTransports>
      </rtps>
    </participant>
  </profiles>
</dds>
"""


def profile_path(transport: str) -> Path:
    """The profile file for ``transport``, written once per user under the temp directory."""
    text = profile_xml(transport)
    directory = Path(tempfile.gettempdir()) / f"area3d-{os.getuid()}"
    directory.mkdir(mode=0o700, exist_ok=True)
    digest = hashlib.sha256(text.encode()).hexdigest()[:12]
    path = directory / f"fastdds_{transport}_{digest}.xml"
    if not path.is_file() or path.read_text() != text:
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(text)
        os.replace(tmp, path)
    return path


def transport_env(transport: str | None = None) -> dict[str, str]:
    """Environment selecting ``transport`` (default: $AREA3D_TRANSPORT, else 'shm')."""
    transport = transport or os.environ.get(TRANSPORT_ENV) or "shm"
    if transport not in TRANSPORTS:
        raise InputError(TRANSPORT_ENV, transport, f"one of {TRANSPORTS}")
    env = {TRANSPORT_ENV: transport}
    if transport != "default":
        path = str(profile_path(transport))
        env.update({name: path for name in PROFILE_ENV_VARS})
    return env


def configure() -> None:
    """Call before ``rclpy.init()`` in a node process: apply the transport profile unless the user
    set a Fast DDS profile file themselves."""
    if any(os.environ.get(name) for name in PROFILE_ENV_VARS):
        return
    os.environ.update(transport_env())


def graph_env(
    domain_id: int | None = None,
    transport: str | None = None,
    discovery_range: str | None = None,
) -> dict[str, str]:
    """Environment for the node processes of one graph (None keeps what the caller's env says)."""
    env = transport_env(transport)
    for name in PROFILE_ENV_VARS:  # a user's own profile wins over ours
        if os.environ.get(name) and transport is None and os.environ.get(TRANSPORT_ENV) is None:
            env[name] = os.environ[name]
    if domain_id is not None:
        check_domain_id(domain_id)
        env["ROS_DOMAIN_ID"] = str(domain_id)
    if discovery_range is not None:
        if discovery_range not in DISCOVERY_RANGES:
            raise InputError("discovery_range", discovery_range, f"one of {DISCOVERY_RANGES}")
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = discovery_range
    return env


def check_domain_id(domain_id: int) -> int:
    if not isinstance(domain_id, int) or not 0 <= domain_id <= 232:
        raise InputError("ROS_DOMAIN_ID", domain_id, "an int in 0..232")
    return domain_id


class DomainLease:
    """A ROS domain id held for the life of this object: by ``ROS_DOMAIN_ID`` when set, else the
    first domain in 1..101 that no other AREA3D run holds (a lock file) and no DDS participant on
    this machine uses (`domain_in_use`)."""

    def __init__(self, domain_id: int | None = None) -> None:
        self._lock_file = None
        if domain_id is None and os.environ.get("ROS_DOMAIN_ID", "").strip():
            text = os.environ["ROS_DOMAIN_ID"].strip()
            if not text.isdigit():
                raise InputError("ROS_DOMAIN_ID", text, "an int in 0..232")
            domain_id = int(text)
        if domain_id is not None:
            self.domain_id = check_domain_id(domain_id)
            self.picked = False
            return
        self.picked = True
        for candidate in FREE_DOMAIN_RANGE:
            lock = _try_lock(candidate)
            if lock is None:
                continue
            if not domain_in_use(candidate):
                self.domain_id, self._lock_file = candidate, lock
                return
            lock.close()
        raise RuntimeError(
            f"no free ROS domain in {FREE_DOMAIN_RANGE.start}..{FREE_DOMAIN_RANGE.stop - 1}; "
            "set ROS_DOMAIN_ID"
        )

    def release(self) -> None:
        if self._lock_file is not None:
            self._lock_file.close()
            self._lock_file = None

    def __enter__(self) -> DomainLease:
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def _try_lock(domain_id: int):
    directory = Path(tempfile.gettempdir()) / "area3d-domains"
    directory.mkdir(mode=0o1777, exist_ok=True)
    handle = open(directory / f"{domain_id}.lock", "a")  # noqa: SIM115 - held for the lease
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        handle.close()
        if exc.errno in (errno.EAGAIN, errno.EACCES):
            return None
        raise
    return handle


def domain_in_use(domain_id: int, participants: int = 64) -> bool:
    """Whether a DDS participant on this machine uses `domain_id` already: the unicast discovery
    port of one of its first `participants` participant ids is taken (each new participant takes
    the lowest free id, so once the first has left the others hold higher ones). A moment's
    check, before this process joins the domain."""
    return any(not _domain_port_free(domain_id, i) for i in range(participants))


def _domain_port_free(domain_id: int, participant_id: int = 0) -> bool:
    port = _PORT_BASE + _DOMAIN_GAIN * domain_id + _UNICAST_OFFSET + 2 * participant_id
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True
