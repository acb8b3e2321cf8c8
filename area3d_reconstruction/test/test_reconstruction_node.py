"""The reconstruction node over rclpy (in-process, real topics and services): it integrates the
frames it is sent into the evaluation's TSDF volume, publishes the mesh, exports what the offline
reconstruction of the same frames gives, saves and loads its volume, refuses files and paths that
do not fit with the running volume kept, and resets."""

from __future__ import annotations

import contextlib
import json
import os
import time

import numpy as np
import pytest
import rclpy
from rclpy.executors import MultiThreadedExecutor
from rclpy.parameter import Parameter

from area3d_eval.open3d_loader import import_open3d
from area3d_eval.reconstruct import TsdfFusion, TsdfParams
from area3d_eval.render import canonical_mesh
from area3d_msgs_py import codecs, msgs, services, topics
from area3d_msgs_py.camera_pose import look_at
from area3d_msgs_py.spinning import Spinner
from area3d_reconstruction import map_io
from area3d_reconstruction.node import ReconstructionNode
from tests.map_files import MISSING, rewrite_map

TIMEOUT_S = 120.0  # generous: a loaded machine is slow (every wait ends once its condition holds)
OPTICAL = "camera_optical_frame"
W, H = 96, 72
K = np.array([[48.0, 0, 48], [0, 48.0, 36], [0, 0, 1]])
ROI = ([-0.2, -0.2, -0.2], [0.2, 0.2, 0.2])
RADIUS = 0.1
PARAMETERS = {"roi_min": ROI[0], "roi_max": ROI[1], "level": "object", "voxel_length": 0.01}


def sphere_frame(i: int):
    """A camera 0.5 m from a sphere of RADIUS at the origin, from direction i: colour by the
    surface normal, confidence falling towards the silhouette, no return beside the sphere."""
    a = 2 * np.pi * i / 5
    T = look_at(np.array([0.5 * np.cos(a), 0.5 * np.sin(a), 0.15]), np.zeros(3))
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    d = rays @ T[:3, :3].T
    o = T[:3, 3]
    b = d @ o
    c = o @ o - RADIUS**2
    a2 = np.sum(d * d, -1)
    disc = b * b - a2 * c
    t = (-b - np.sqrt(np.maximum(disc, 0))) / a2
    depth = np.where(disc > 0, t, np.nan).astype(np.float32)  # z of the ray is 1 per unit t
    normal = (o + t[..., None] * d) / RADIUS
    rgb = np.where(disc[..., None] > 0, (normal + 1) * 127.5, 0).astype(np.uint8)
    facing = np.clip(-np.sum(normal * d, -1) / np.sqrt(a2), 0, 1)
    confidence = np.where(disc > 0, 0.3 + 0.7 * facing, np.nan).astype(np.float32)
    return (i + 1) * 10**9, rgb, depth, confidence, T


class Rig:
    """The reconstruction node under test and a peer that feeds frames and calls its services."""

    count = 0

    def __init__(self, parameters: dict | None = None):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        overrides = [Parameter(k, value=v) for k, v in {**PARAMETERS, **(parameters or {})}.items()]
        # a namespace of its own: other tests' nodes on this domain (a perception node's latched
        # outputs) must not reach it
        Rig.count += 1
        namespace = f"/reconstruction_test_{os.getpid()}_{Rig.count}"
        self.node = ReconstructionNode(
            context=self.context, parameter_overrides=overrides, namespace=namespace
        )
        self.peer = rclpy.create_node("feeder", context=self.context, namespace=namespace)
        self.status, self.meshes = [], []
        self.peer.create_subscription(
            msgs.String,
            topics.RECONSTRUCTION_STATUS.name,
            lambda m: self.status.append(json.loads(m.data)),
            topics.RECONSTRUCTION_STATUS.qos(),
        )
        self.peer.create_subscription(
            msgs.Marker,
            topics.RECONSTRUCTION_MESH.name,
            self.meshes.append,
            topics.RECONSTRUCTION_MESH.qos(),
        )
        self.pubs = {
            key: self.peer.create_publisher(topic.msg_type, topic.name, topic.qos())
            for key, topic in (
                ("color", topics.PERCEPTION_COLOR),
                ("depth", topics.PERCEPTION_DEPTH),
                ("weight", topics.PERCEPTION_WEIGHT),
                ("pose", topics.POSE),
                ("info", topics.CAMERA_INFO),
            )
        }
        self.clients = {
            s.name: self.peer.create_client(s.srv_type, s.name)
            for s in (
                topics.RECONSTRUCTION_SAVE_MAP,
                topics.RECONSTRUCTION_LOAD_MAP,
                topics.RECONSTRUCTION_EXPORT_MESH,
                topics.RECONSTRUCTION_RESET,
            )
        }
        self.executor = MultiThreadedExecutor(num_threads=4, context=self.context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.peer)
        self.spinner = Spinner(self.executor)
        assert self.wait(lambda: all(p.get_subscription_count() >= 1 for p in self.pubs.values()))
        assert all(c.wait_for_service(timeout_sec=TIMEOUT_S) for c in self.clients.values())

    @staticmethod
    def wait(done, timeout_s: float = TIMEOUT_S) -> bool:
        deadline = time.monotonic() + timeout_s
        while not done() and time.monotonic() < deadline:
            time.sleep(0.02)
        return bool(done())

    def send(self, stamp, rgb, depth, confidence, T) -> None:
        self.pubs["info"].publish(codecs.intrinsics_to_camera_info(K, W, H, stamp, OPTICAL))
        self.pubs["pose"].publish(
            msgs.PoseStamped(header=codecs.header(stamp, "world"), pose=codecs.matrix_to_pose(T))
        )
        self.pubs["color"].publish(codecs.image_to_msg(rgb, "rgb8", stamp, OPTICAL))
        self.pubs["depth"].publish(codecs.image_to_msg(depth, "32FC1", stamp, OPTICAL))
        self.pubs["weight"].publish(codecs.image_to_msg(confidence, "32FC1", stamp, OPTICAL))

    def integrated(self, count: int) -> bool:
        return self.wait(lambda: self.status and self.status[-1]["frames_integrated"] == count)

    def call(self, service: topics.Service, path=None):
        request = service.srv_type.Request()
        if path is not None:
            request.path = str(path)
        return services.call(self.clients[service.name], request, TIMEOUT_S)

    def close(self):
        self.node.stop()
        self.spinner.stop(TIMEOUT_S)
        self.peer.destroy_node()
        self.node.destroy_node()
        self.context.try_shutdown()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def offline(frames) -> object:
    fusion = TsdfFusion(
        TsdfParams(voxel_length=0.01, sdf_trunc=0.04), np.array(ROI[0]), np.array(ROI[1])
    )
    for _, rgb, depth, confidence, T in frames:
        fusion.integrate(rgb, depth, K, T, confidence)
    return fusion.extract_mesh()


def mesh_arrays(mesh):
    return canonical_mesh(
        np.asarray(mesh.vertices), np.asarray(mesh.triangles), np.asarray(mesh.vertex_colors)
    )


def read_ply(path):
    return import_open3d().io.read_triangle_mesh(str(path))


def test_frames_become_a_published_mesh_and_the_export_is_the_offline_reconstruction(rig, tmp_path):
    frames = [sphere_frame(i) for i in range(4)]
    for f in frames:
        rig.send(*f)
    assert rig.integrated(4)
    assert rig.wait(lambda: rig.meshes and rig.meshes[-1].header.stamp.sec == 4)
    marker = rig.meshes[-1]
    assert marker.type == msgs.Marker.TRIANGLE_LIST and marker.header.frame_id == "world"
    points, colours = codecs.marker_to_mesh(marker)
    assert len(points) > 300 and len(colours) == len(points)
    # the mesh lies on the sphere
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), RADIUS, atol=0.01)
    answer = rig.call(topics.RECONSTRUCTION_EXPORT_MESH, tmp_path / "mesh.ply")
    assert answer.success, answer.message
    assert answer.path == str(tmp_path / "mesh.ply") and answer.size_bytes > 0
    exported, expected = mesh_arrays(read_ply(answer.path)), mesh_arrays(offline(frames))
    assert len(exported[1]) == len(points) // 3 == len(expected[1])
    np.testing.assert_allclose(exported[0], expected[0], atol=1e-6)
    np.testing.assert_array_equal(exported[1], expected[1])
    np.testing.assert_allclose(exported[2], expected[2], atol=1 / 255)
    # a frame sent again is integrated once
    rig.send(*frames[0])
    rig.send(*sphere_frame(4))
    assert rig.integrated(5)


def test_a_saved_volume_loads_into_another_node_and_bad_files_leave_the_volume_as_it_was(
    rig, tmp_path, monkeypatch
):
    frames = [sphere_frame(i) for i in range(3)]
    for f in frames:
        rig.send(*f)
    assert rig.integrated(3)
    saved = rig.call(topics.RECONSTRUCTION_SAVE_MAP, tmp_path / "volume.a3map")
    assert saved.success and "saved 3 frames" in saved.message and saved.size_bytes > 0
    # refusals: nothing written, nothing changed, each says why
    refusals = [
        (topics.RECONSTRUCTION_SAVE_MAP, tmp_path / "nowhere" / "v.a3map", "existing directory"),
        (topics.RECONSTRUCTION_EXPORT_MESH, tmp_path / "mesh.txt", ".ply"),
        # a map file under a mesh's name would fail in every mesh viewer
        (topics.RECONSTRUCTION_SAVE_MAP, tmp_path / "volume.ply", "ending in .a3map"),
        (topics.RECONSTRUCTION_LOAD_MAP, tmp_path / "missing.a3map", "existing map file"),
    ]
    (tmp_path / "foreign.a3map").write_text("not a map")
    refusals.append((topics.RECONSTRUCTION_LOAD_MAP, tmp_path / "foreign.a3map", "complete"))
    volume = tmp_path / "volume.a3map"
    data = volume.read_bytes()
    (tmp_path / "cut.a3map").write_bytes(data[: len(data) // 3])
    refusals.append((topics.RECONSTRUCTION_LOAD_MAP, tmp_path / "cut.a3map", "complete"))
    # damaged headers and arrays (which crashed the node before): refused, each named
    with np.load(volume) as archive:
        nan_tsdf = np.full_like(archive["tsdf"], np.nan)
        keys, tsdf = archive["block_keys"], archive["tsdf"]
        weight, color = archive["weight"], archive["color"]
    repeated = keys.copy()
    repeated[1] = repeated[0]
    for name, change, why in (
        # blocks 320 m off the region (a damaged file whose checksum was made again), one
        # block twice: loaded, they left an empty or a wrong volume with "loaded 3 frames"
        ("far", {"arrays": {"block_keys": keys + 1000}}, "blocks off the region"),
        ("twice", {"arrays": {"block_keys": repeated}}, "repeated blocks"),
        ("ten", {"header": {"frames": "ten"}}, "frames: got 'ten', expected an integer >= 0"),
        ("noframes", {"header": {"frames": MISSING}}, "frames: got 'missing'"),
        ("stamps", {"header": {"frames": 10}}, "array 'stamps': got (3,), expected shape (10,)"),
        ("nan", {"arrays": {"tsdf": nan_tsdf}}, "array 'tsdf': got 'NaN or inf'"),
        # values no volume holds (loaded, they left an empty mesh or noise, "loaded 3 frames")
        ("negative", {"arrays": {"weight": -weight}}, "array 'weight': got '"),
        ("scaled", {"arrays": {"tsdf": tsdf * 50}}, "array 'tsdf': got '"),
        ("bright", {"arrays": {"color": color * 1e4}}, "expected values in [0, 255.01]"),
        ("blocks", {"arrays": {"tsdf": tsdf[:, :4]}}, "blocks.a3map: array 'tsdf'"),
        ("zero", {"header": {"frames": 0}, "arrays": {"stamps": np.zeros(0, np.int64)}},
         "frames: got 0, expected at least 1 frame"),
        ("words", {"header": {"roi_min": ["a", "b", "c"]}}, "roi_min: got"),
    ):  # fmt: skip
        bad = rewrite_map(volume, tmp_path / f"{name}.a3map", **change)
        refusals.append((topics.RECONSTRUCTION_LOAD_MAP, bad, why))
    for service, path, why in refusals:
        answer = rig.call(service, path)
        assert not answer.success and why in answer.message, answer.message
    assert not (tmp_path / "nowhere").exists() and not (tmp_path / "mesh.txt").exists()
    assert rig.node._status()["frames_integrated"] == 3

    # a file that passes the checks and still fails to load (a bug): said, the volume kept
    def broken(*args):
        raise RuntimeError("a file the checks let through")

    with monkeypatch.context() as patch:
        patch.setattr(map_io, "restore", broken)
        answer = rig.call(topics.RECONSTRUCTION_LOAD_MAP, volume)
    assert not answer.success and "could not be done: RuntimeError" in answer.message
    assert rig.node._status()["frames_integrated"] == 3
    # one node at a time from here: two would both serve area3d/reconstruction/load_map
    rig.close()
    rig.close = lambda: None  # for the fixture

    other = Rig({"voxel_length": 0.02})  # another voxel length: refused by name
    try:
        answer = other.call(topics.RECONSTRUCTION_LOAD_MAP, tmp_path / "volume.a3map")
        assert not answer.success and "tsdf_voxel_length" in answer.message
        assert other.node._status()["frames_integrated"] == 0
    finally:
        other.close()
    fresh = Rig()
    try:
        loaded = fresh.call(topics.RECONSTRUCTION_LOAD_MAP, tmp_path / "volume.a3map")
        assert loaded.success and "loaded 3 frames" in loaded.message, loaded.message
        assert fresh.wait(lambda: fresh.meshes and len(fresh.meshes[-1].points) > 0)
        exported = fresh.call(topics.RECONSTRUCTION_EXPORT_MESH, tmp_path / "after.ply")
        a, b = mesh_arrays(read_ply(exported.path)), mesh_arrays(offline(frames))
        np.testing.assert_allclose(a[0], b[0], atol=1e-6)
        np.testing.assert_array_equal(a[1], b[1])
        # a frame integrated before the save is not integrated again; a new one is
        fresh.send(*frames[1])
        fresh.send(*sphere_frame(3))
        assert fresh.integrated(4)
        reset = fresh.call(topics.RECONSTRUCTION_RESET)
        assert reset.success and "4 frames integrated" in reset.message
        assert fresh.integrated(0)
        assert fresh.wait(lambda: len(fresh.meshes[-1].points) == 0)
        # nothing to export: said so, nothing written
        empty = fresh.call(topics.RECONSTRUCTION_EXPORT_MESH, tmp_path / "empty.ply")
        assert not empty.success and "mesh: got '0 triangles'" in empty.message, empty.message
        assert not (tmp_path / "empty.ply").exists()
    finally:
        fresh.close()


def test_an_export_the_disk_cannot_hold_is_refused_the_mesh_there_kept_and_no_file_held(
    tmp_path,
):
    """A write that fails midway (the process's file size limit, which fails it as a full disk
    does) is refused with the system's reason; the mesh already at the path is kept, nothing else
    is left beside it, and no file stays open. (On a full tmpfs, open3d's PLY writer, used
    before, kept its handle to the deleted file, and its space, until the node stopped; this
    limit does not make it do so, so here both writers pass the handle check.)"""
    import resource
    import signal

    mesh = offline([sphere_frame(i) for i in range(2)])
    path = tmp_path / "mesh.ply"
    map_io.export_mesh(mesh, path)
    good = path.read_bytes()
    back = read_ply(path)
    assert len(back.triangles) == len(mesh.triangles) and back.has_vertex_normals()
    np.testing.assert_allclose(np.asarray(back.vertices), np.asarray(mesh.vertices), atol=1e-6)
    np.testing.assert_allclose(
        np.asarray(back.vertex_colors), np.asarray(mesh.vertex_colors), atol=0.5 / 255 + 1e-6
    )
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a failed write, not a signal
    resource.setrlimit(resource.RLIMIT_FSIZE, (len(good) // 2, hard))
    try:
        with pytest.raises(OSError, match="not written: File too large"):
            map_io.export_mesh(mesh, path)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, previous)
    assert path.read_bytes() == good and [p.name for p in tmp_path.iterdir()] == ["mesh.ply"]
    held = []
    for fd in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):  # the listing's own descriptor is gone by now
            held.append(os.readlink(f"/proc/self/fd/{fd}"))
    assert not [h for h in held if h.startswith(str(tmp_path))], held


def test_a_saved_volume_becomes_a_mesh_file_with_no_graph_running(tmp_path):
    """`area3d export MAP MESH.ply`: the mesh of a saved volume (a run's maps/, or save_map's),
    the same as the running volume's; a planner's map, a missing file, a header of another kind
    and a mesh name without .ply are refused by name, nothing written."""
    from typer.testing import CliRunner

    from area3d_bringup import cli
    from area3d_planner import map_io as planner_map
    from area3d_planner.config import PlannerConfig
    from area3d_planner.server import NextBestViewServer

    fusion = TsdfFusion(
        TsdfParams(voxel_length=0.01, sdf_trunc=0.04), np.array(ROI[0]), np.array(ROI[1])
    )
    for _, rgb, depth, confidence, T in (sphere_frame(i) for i in range(3)):
        fusion.integrate(rgb, depth, K, T, confidence)
    volume, _ = map_io.save(fusion, [1, 2, 3], tmp_path / "reconstruction.a3map", "world")

    def export(*args):
        result = CliRunner().invoke(cli.app, ["export", *map(str, args)], env={"COLUMNS": "300"})
        return result.exit_code, " ".join(result.output.split())

    code, said = export(volume, tmp_path / "mesh.ply")
    assert code == 0 and f"written to {tmp_path / 'mesh.ply'}" in said, said
    a, b = mesh_arrays(read_ply(tmp_path / "mesh.ply")), mesh_arrays(fusion.extract_mesh())
    np.testing.assert_allclose(a[0], b[0], atol=1e-6)
    np.testing.assert_array_equal(a[1], b[1])
    planner, _, _ = planner_map.save(NextBestViewServer(PlannerConfig()), tmp_path / "p.a3map")
    other = rewrite_map(volume, tmp_path / "other.a3map", header={"tsdf_voxel_length": "x"})
    for args, why in (
        ((planner, tmp_path / "a.ply"), "content: got 'planner', expected 'reconstruction'"),
        ((tmp_path / "none.a3map", tmp_path / "b.ply"), "expected an existing map file"),
        ((other, tmp_path / "c.ply"), "tsdf_voxel_length: got 'x', expected a number > 0"),
        ((volume, tmp_path / "mesh.obj"), "expected a file name ending in .ply"),
    ):
        code, said = export(*args)
        assert code == 2 and why in said, said
        assert not args[1].exists()
