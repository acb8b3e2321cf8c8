"""The graph's own ROS 2 interfaces (area3d_interfaces) and tf2_msgs, generated and built into the
venv by `make install` (tools/build_interfaces.py): their definitions, their wire format, a call
between two processes, and the build's checks."""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from area3d_interfaces.msg import HardRegion, HardRegionArray
from area3d_interfaces.srv import NextBestView
from geometry_msgs.msg import Pose, PoseStamped, TransformStamped
from rclpy.serialization import deserialize_message, serialize_message
from tf2_msgs.msg import TFMessage

from area3d_msgs_py import qos
from area3d_msgs_py.probe import Probe

ROOT = Path(__file__).resolve().parent.parent
SERVER = Path(__file__).parent / "clients" / "next_best_view_server.py"
# `ros2 topic info -v /tf` against ROS 2 Jazzy nodes prints this type hash.
JAZZY_TFMESSAGE_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
TIMEOUT_S = 120.0  # generous: processes and DDS discovery on a loaded machine


def load_build_script():
    spec = importlib.util.spec_from_file_location(
        "build_interfaces", ROOT / "tools" / "build_interfaces.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_next_best_view_has_exactly_the_documented_fields():
    assert NextBestView.Request.get_fields_and_field_types() == {
        "count": "uint32",
        "mode": "string",
        "current": "geometry_msgs/PoseStamped",
        "request_id": "uint64",
    }
    assert NextBestView.Response.get_fields_and_field_types() == {
        "success": "boolean",
        "message": "string",
        "views": "geometry_msgs/PoseArray",
        "gains": "sequence<float>",
    }
    assert TFMessage.get_fields_and_field_types() == {
        "transforms": "sequence<geometry_msgs/TransformStamped>"
    }


def test_the_generated_types_round_trip_through_cdr():
    current = PoseStamped()
    current.header.frame_id = "odom"
    current.header.stamp.sec, current.header.stamp.nanosec = 1_700_000_000, 123
    current.pose.position.x, current.pose.orientation.z, current.pose.orientation.w = 0.5, 0.6, 0.8
    request = NextBestView.Request(count=7, mode="batch", current=current)
    response = NextBestView.Response(success=True, message="", gains=[0.5, 0.25])
    response.views.header = current.header
    response.views.poses = [Pose(), current.pose]
    edge = TransformStamped(child_frame_id="camera_link")
    edge.header = current.header
    edge.transform.translation.y = -2.0
    tf = TFMessage(transforms=[edge, edge])
    regions = HardRegionArray(regions=[HardRegion(voxel_count=12, direction_count=4)])
    regions.regions[0].centroid.x, regions.regions[0].mean_uncertainty = 0.25, 0.75
    for message in (request, response, tf, regions):
        data = serialize_message(message)
        assert deserialize_message(data, type(message)) == message
    # what crossed is the content, not a default message
    back = deserialize_message(serialize_message(request), NextBestView.Request)
    assert (back.count, back.mode, back.current.header.frame_id) == (7, "batch", "odom")
    assert list(deserialize_message(serialize_message(response), type(response)).gains) == [
        0.5,
        0.25,
    ]


def test_a_next_best_view_call_and_tf_between_two_processes_with_jazzys_type_hash(
    tmp_path, interrupt
):
    server = subprocess.Popen(
        [sys.executable, str(SERVER)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=tmp_path,  # nothing of the project on its path but what the venv installed
        env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"},
    )
    try:
        with Probe("mission_manager") as probe:
            tf = probe.listen(TFMessage, "/tf", qos.reliable())
            current = PoseStamped()
            current.header.frame_id = "odom"
            current.header.stamp.sec = 1_700_000_000
            current.pose.position.x = 0.5
            answer = probe.call(
                NextBestView,
                "area3d/planner/select_views",
                NextBestView.Request(count=2, mode="closed_loop", current=current),
                timeout_s=TIMEOUT_S,
            )
            assert answer.success, answer.message
            assert [p.position.x for p in answer.views.poses] == [1.5, 2.5]
            assert answer.views.header == current.header
            assert list(answer.gains) == [1.0, 0.5]
            refused = probe.call(
                NextBestView,
                "area3d/planner/select_views",
                NextBestView.Request(mode="sideways", current=current),
                timeout_s=TIMEOUT_S,
            )
            assert not refused.success and "mode" in refused.message
            assert refused.views.poses == [] and list(refused.gains) == []

            assert probe.wait_for(lambda: tf, TIMEOUT_S), "no /tf from the server"
            assert tf[0].transforms[0].child_frame_id == "camera_link"

            # the writer's node name comes with its participant's discovery data, which can
            # trail the endpoint's on a loaded machine ("_NODE_NAME_UNKNOWN_" until then)
            def writers() -> list[str]:
                return [p.node_name for p in probe.node.get_publishers_info_by_topic("/tf")]

            assert probe.wait_for(lambda: writers() == ["next_best_view_server"], TIMEOUT_S), (
                writers()
            )
            publishers = probe.node.get_publishers_info_by_topic("/tf")
            assert str(publishers[0].topic_type_hash) == JAZZY_TFMESSAGE_HASH
    finally:
        log = interrupt(server, TIMEOUT_S)
    assert server.returncode == 0, log[-3000:]


# the build ------------------------------------------------------------------------------------
def test_missing_build_tools_are_each_named_with_the_install_line(monkeypatch, tmp_path):
    build = load_build_script()
    monkeypatch.setattr(shutil, "which", lambda name: None)
    monkeypatch.delenv("CC", raising=False)
    monkeypatch.delenv("CXX", raising=False)
    monkeypatch.setattr(build.sysconfig, "get_paths", lambda: {"include": str(tmp_path)})
    with pytest.raises(SystemExit) as stopped:
        build.check_prerequisites()
    message = str(stopped.value)
    for missing in (
        "a C compiler",
        "a C++ compiler",
        "make (on PATH)",
        "cmake >= 3.21",
        "Python.h",
    ):
        assert missing in message
    assert "apt install build-essential cmake python3-dev" in message


def test_an_old_cmake_and_a_compiler_named_but_absent_are_told(monkeypatch):
    build = load_build_script()
    monkeypatch.setattr(build, "_cmake_version", lambda cmake: (3, 16))
    monkeypatch.setenv("CXX", "/nowhere/g++-99")
    missing = build.missing_prerequisites()
    assert any("cmake >= 3.21" in m and "3.16" in m for m in missing), missing
    assert any("$CXX is '/nowhere/g++-99'" in m for m in missing), missing


def test_the_build_runs_again_when_an_interface_changes_and_not_for_its_readme(
    monkeypatch, tmp_path
):
    build = load_build_script()
    package = tmp_path / "area3d_interfaces"
    shutil.copytree(ROOT / "area3d_interfaces", package)
    (package / "README.md").write_text("about the package\n")
    monkeypatch.setattr(build, "ROOT", tmp_path)
    monkeypatch.setattr(build, "PACKAGES", (package,))
    monkeypatch.setattr(build, "WHEEL_TARGETS_HOOK", tmp_path / "hook.cmake")
    monkeypatch.setattr(build, "__file__", str(tmp_path / "build_interfaces.py"))
    (tmp_path / "hook.cmake").write_text("# hook\n")
    (tmp_path / "build_interfaces.py").write_text("# script\n")
    first = build.inputs_digest()
    (package / "README.md").write_text("about the package, reworded\n")
    assert build.inputs_digest() == first
    srv = package / "srv" / "NextBestView.srv"
    srv.write_text(srv.read_text().replace("float32[] gains", "float64[] gains"))
    changed = build.inputs_digest()
    assert changed != first
    (tmp_path / "build_interfaces.py").write_text("# script, changed\n")
    assert build.inputs_digest() != changed


def test_a_build_kept_in_the_cache_is_copied_into_another_prefix_with_its_paths(
    monkeypatch, tmp_path
):
    """The installed files of a build (its install manifests) are cached by digest, the building
    prefix's path marked in text files; another prefix gets them with its own path, if they load
    there. A binary that holds the prefix is never cached (its path cannot be rewritten)."""
    script = load_build_script()
    monkeypatch.setenv("AREA3D_CACHE_DIR", str(tmp_path / "cache"))
    built, other = tmp_path / "venv-a", tmp_path / "somewhere" / "venv-b"
    build_root = built / "build" / "interfaces"
    files = {
        "lib/libarea3d_interfaces__rosidl_typesupport_c.so": b"\x7fELF\0\1 no path",
        "share/area3d_interfaces/local_setup.sh": f"PREFIX={built}/share\n".encode(),
        "lib/python3.11/site-packages/tf2_msgs/__init__.py": b"",
    }
    for i, (name, data) in enumerate(files.items()):
        (built / name).parent.mkdir(parents=True, exist_ok=True)
        (built / name).write_bytes(data)
        package = script.PACKAGES[i % 2].name
        (build_root / package).mkdir(parents=True, exist_ok=True)
        with (build_root / package / "install_manifest.txt").open("a") as manifest:
            manifest.write(f"{built / name}\n")
    script.keep_in_cache(built, build_root, "d1")
    assert (tmp_path / "cache" / "interfaces" / "d1" / "manifest.txt").is_file()

    loads = []
    monkeypatch.setattr(script, "_load_error", lambda: loads.pop(0))
    loads.append("")
    assert script.restore_from_cache(other, "d1")
    assert (other / "share/area3d_interfaces/local_setup.sh").read_text() == (
        f"PREFIX={other}/share\n"
    )
    assert (other / next(iter(files))).read_bytes() == next(iter(files.values()))
    assert (other / "lib/python3.11/site-packages/tf2_msgs/__init__.py").is_file()
    loads.append("ImportError: libfoo.so: cannot open shared object file")
    assert not script.restore_from_cache(other, "d1")  # copied, but does not load: built
    assert not script.restore_from_cache(other, "never-built")

    # a binary holding the prefix: not cached
    (built / next(iter(files))).write_bytes(b"\x7fELF\0" + bytes(built))
    script.keep_in_cache(built, build_root, "d2")
    assert not (tmp_path / "cache" / "interfaces" / "d2").exists()
    assert [p.name for p in (tmp_path / "cache" / "interfaces").iterdir()] == ["d1"]
