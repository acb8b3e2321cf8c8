"""Nodes spread over hosts: the camera and perception in one network namespace, semantics, the
planner and the runner in another, joined by a veth pair with addresses of their own. Namespaces
share /dev/shm, so the graph runs UDP-only (no shared-memory transport) and the veth's packet
counters must rise by at least the images that crossed it. Needs root and `ip netns` (CI runs as
root); the namespaces are created and removed here."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import pytest

BUDGET = 5
W, H = 240, 180


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check)


def _netns_unavailable() -> str | None:
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is not installed"
    if os.geteuid() != 0:
        return "creating network namespaces needs root"
    probe = f"a3dprobe{os.getpid() % 100000}"
    result = _ip("netns", "add", probe, check=False)
    if result.returncode != 0:
        return f"`ip netns add` failed: {result.stderr.strip()}"
    _ip("netns", "delete", probe, check=False)
    return None


@pytest.fixture()
def two_hosts():
    reason = _netns_unavailable()
    if reason:
        pytest.skip(f"ip netns unavailable: {reason}")
    tag = os.getpid() % 10000
    subnet = 10 + os.getpid() % 200
    hosts = {"a": f"a3d{tag}a", "b": f"a3d{tag}b"}
    links = {"a": f"a3dv{tag}a", "b": f"a3dv{tag}b"}
    addresses = {"a": f"10.200.{subnet}.1", "b": f"10.200.{subnet}.2"}
    try:
        for ns in hosts.values():
            _ip("netns", "add", ns)
        _ip("link", "add", links["a"], "type", "veth", "peer", "name", links["b"])
        for side in ("a", "b"):
            ns, link = hosts[side], links[side]
            _ip("link", "set", link, "netns", ns)
            _ip("-n", ns, "addr", "add", f"{addresses[side]}/24", "dev", link)
            _ip("-n", ns, "link", "set", link, "up", "multicast", "on")
            _ip("-n", ns, "link", "set", "lo", "up")
            # DDS discovery is multicast: send it over the veth
            _ip("-n", ns, "route", "add", "224.0.0.0/4", "dev", link)
        yield hosts, links, addresses
    finally:
        for ns in hosts.values():
            _ip("netns", "delete", ns, check=False)


def _rx_bytes(ns: str, link: str) -> int:
    stats = json.loads(_ip("-n", ns, "-s", "-j", "link", "show", "dev", link).stdout)[0]
    return int(stats["stats64"]["rx"]["bytes"])


def test_camera_and_perception_on_one_host_the_rest_on_another_complete_an_episode(
    two_hosts, tmp_path, interrupt
):
    hosts, links, addresses = two_hosts
    env = dict(
        os.environ,
        AREA3D_TRANSPORT="udp",  # no shared memory: the data must cross the veth
        ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET",
    )
    for name in ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE"):
        env.pop(name, None)
    size = ["-p", f"sim_bridge.width={W}", "-p", f"sim_bridge.height={H}"]
    size += ["-p", f"planner.width={W}", "-p", f"planner.height={H}"]
    before = {side: _rx_bytes(hosts[side], links[side]) for side in hosts}
    camera_host = subprocess.Popen(
        [
            "ip", "netns", "exec", hosts["a"], sys.executable, "-m", "area3d_bringup.cli",
            "launch", "--nodes", "sim_bridge,perception",
            "-p", "sim_bridge.readers.all=[mission_manager]", *size,
        ],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path,
    )  # fmt: skip
    try:
        episode = subprocess.run(
            [
                "ip", "netns", "exec", hosts["b"], sys.executable, "-m", "area3d_bringup.cli",
                "run", "--nodes", "semantics,planner,reconstruction", "--budget", str(BUDGET),
                "--no-evaluate", "--out", str(tmp_path / "runs"), *size,
            ],
            env=env, capture_output=True, text=True, timeout=600, cwd=tmp_path,
        )  # fmt: skip
    finally:
        camera_log = interrupt(camera_host)
    assert episode.returncode == 0, (episode.stderr[-3000:], camera_log[-3000:])
    (run_dir,) = (tmp_path / "runs").iterdir()
    data = json.loads((run_dir / "episode.json").read_text())
    assert len(data["views"]) == BUDGET
    assert data["recorded"]["/area3d/perception/depth"] == BUDGET  # perception ran on host a
    # the planner on host b published its grid: after every fusion but within a burst (the 4
    # initial views), so at least after the last of the burst and after each planned view
    assert data["recorded"]["/area3d/planner/uncertainty_grid"] >= BUDGET - 4 + 1
    log = (run_dir / "nodes.log").read_text()
    assert "[planner]" in log and "[sim_bridge]" not in log and "[perception]" not in log
    assert "sim_bridge" in camera_log and "perception" in camera_log
    # Host b received at least every colour + depth frame (to semantics and the runner) and
    # perception's depth + confidence (to the planner and the runner) over the veth.
    frame_bytes = W * H * (3 + 4 + 4 + 4)
    received = _rx_bytes(hosts["b"], links["b"]) - before["b"]
    assert received > BUDGET * frame_bytes, (received, BUDGET * frame_bytes)
    assert _rx_bytes(hosts["a"], links["a"]) > before["a"]  # goals and discovery went the other way
