"""The next-best-view services between two processes: a planner node process with a warm cache
at object level, and the round trip of one closed-loop view over GetPlan and over NextBestView
(area3d/planner/select_views), as a mission manager makes them (`area3d bench transport`,
`area3d bench planner`)."""

from __future__ import annotations

import time

import numpy as np

TARGET_ROUND_TRIP_P95_S = 0.05  # one closed-loop GetPlan round trip (one view), cache warm
TARGET_SELECT_VIEWS_P95_S = 0.01  # the same over NextBestView, object level (< 10 ms)


def bench_transport(requests: int = 50) -> dict:
    """Closed-loop next-best-view round trips between two processes: a planner node process
    (single_object), the scene's initial views published to it, then, once area3d/planner/status
    says the cache is ready, `requests` one-view GetPlan requests and as many NextBestView ones
    (each answered with one view)."""
    import json
    import tempfile
    import threading
    from pathlib import Path

    from area3d_bringup.launch_description import NodeSpec, scene_parameters
    from area3d_bringup.launcher import Launcher
    from area3d_msgs_py import codecs, middleware, msgs, topics
    from area3d_msgs_py.probe import Probe

    middleware.configure()
    from area3d_bench.frames import object_frames

    scene, frames = object_frames()
    params = {**scene_parameters(scene.name)["planner"], "mode": "closed_loop", "budget": 10**6}
    lines: list[str] = []
    with tempfile.TemporaryDirectory() as workdir, Probe("planner_bench") as probe:
        launcher = Launcher(
            [NodeSpec("planner", "area3d_planner.node", params)],
            Path(workdir),
            env=middleware.graph_env(),
            log_sink=lines.append,
        )
        status = topics.PLANNER_STATUS
        statuses = probe.listen(status.msg_type, status.name, status.qos())
        pubs = {
            key: probe.publisher(topic.msg_type, topic.name, topic.qos())
            for key, topic in (
                ("depth", topics.PERCEPTION_DEPTH),
                ("conf", topics.PERCEPTION_CONFIDENCE),
                ("pose", topics.POSE),
                ("info", topics.CAMERA_INFO),
            )
        }
        client = probe.node.create_client(
            topics.NEXT_BEST_VIEW.srv_type, topics.NEXT_BEST_VIEW.name
        )

        launcher.start()
        try:
            if not launcher.wait_for(lambda: client.wait_for_service(timeout_sec=0.1), 120):
                raise RuntimeError("planner service did not come up:\n" + "\n".join(lines[-20:]))
            launcher.wait_for(
                lambda: all(p.get_subscription_count() >= 1 for p in pubs.values()), 60
            )
            t0 = time.perf_counter()
            for i, (depth, conf, K, T) in enumerate(frames):
                stamp = (i + 1) * 1_000_000
                h, w = depth.shape
                pubs["info"].publish(
                    codecs.intrinsics_to_camera_info(K, w, h, stamp, "camera_optical_frame")
                )
                pubs["pose"].publish(
                    msgs.PoseStamped(
                        header=codecs.header(stamp, "world"), pose=codecs.matrix_to_pose(T)
                    )
                )
                pubs["depth"].publish(
                    codecs.image_to_msg(depth, "32FC1", stamp, "camera_optical_frame")
                )
                pubs["conf"].publish(
                    codecs.image_to_msg(conf, "32FC1", stamp, "camera_optical_frame")
                )
            n = len(frames)

            def ready() -> bool:
                states = [json.loads(m.data) for m in list(statuses)]
                return any(s.get("frames_fused") == n and s.get("cache_ready") for s in states)

            is_ready = launcher.wait_for(ready, 180)
            t_ready = time.perf_counter() - t0
            if not is_ready:
                raise RuntimeError("planner never reported cache_ready:\n" + "\n".join(lines[-20:]))
            last = n * 1_000_000
            latencies = []
            for _ in range(requests):
                req = msgs.GetPlan_Request(
                    start=msgs.PoseStamped(
                        header=codecs.header(last, "world"),
                        pose=codecs.matrix_to_pose(frames[-1][3]),
                    ),
                    goal=msgs.PoseStamped(
                        header=codecs.header(last, "world"), pose=codecs.matrix_to_pose(np.eye(4))
                    ),
                    tolerance=0.0,
                )
                req.goal.pose.position.x = 1.0
                answered = threading.Event()
                t = time.perf_counter()
                future = client.call_async(req)
                future.add_done_callback(lambda _, done=answered: done.set())
                if not answered.wait(30.0):
                    raise RuntimeError("no answer:\n" + "\n".join(lines[-20:]))
                latencies.append(time.perf_counter() - t)
                if len(future.result().plan.poses) != 1:
                    raise RuntimeError("empty plan:\n" + "\n".join(lines[-20:]))
            select_views = _select_views_round_trips(probe, frames[-1][3], last, requests, lines)
        finally:
            launcher.stop()
    lat = np.asarray(latencies)
    return {
        "frames": len(frames),
        "requests": requests,
        "fused_and_cache_ready_s": t_ready,
        "round_trip_p50_s": float(np.percentile(lat, 50)),
        "round_trip_p95_s": float(np.percentile(lat, 95)),
        "target_p95_s": TARGET_ROUND_TRIP_P95_S,
        "select_views_p50_s": float(np.percentile(select_views, 50)),
        "select_views_p95_s": float(np.percentile(select_views, 95)),
        "select_views_target_p95_s": TARGET_SELECT_VIEWS_P95_S,
    }


def _select_views_round_trips(
    probe, current: np.ndarray, stamp_ns: int, requests: int, lines: list[str]
) -> np.ndarray:
    """Seconds of `requests` one-view NextBestView calls (area3d/planner/select_views)."""
    import threading

    from area3d_msgs_py import codecs, topics

    service = topics.SELECT_VIEWS
    client = probe.node.create_client(service.srv_type, service.name)
    if not client.wait_for_service(timeout_sec=60.0):
        raise RuntimeError(f"{service.name} did not come up:\n" + "\n".join(lines[-20:]))
    latencies = []
    for _ in range(requests):
        request = codecs.view_request_to_msg(1, current, stamp_ns, "world")
        answered = threading.Event()
        t = time.perf_counter()
        future = client.call_async(request)
        future.add_done_callback(lambda _, done=answered: done.set())
        if not answered.wait(30.0):
            raise RuntimeError("no answer:\n" + "\n".join(lines[-20:]))
        latencies.append(time.perf_counter() - t)
        answer = codecs.msg_to_view_answer(future.result())
        if not answer.success or len(answer.views) != 1:
            raise RuntimeError(f"no view: {answer.message}\n" + "\n".join(lines[-20:]))
    probe.node.destroy_client(client)
    return np.asarray(latencies)
