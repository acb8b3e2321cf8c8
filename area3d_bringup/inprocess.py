"""One episode with the graph's cores called in one process, in the graph's order, no transport.

The same camera, perception estimator, semantics analysis and planner server as the nodes, fed
frame by frame in closed loop: the views chosen are those of `area3d run` with the same
parameters (the nodes add transport and timing, not decisions). Used by `area3d bench episode
--in-process` to compare policies over many scenes and seeds on a small machine; its run
directories have the layout of `area3d run` and are evaluated the same way.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from area3d_bringup.launch_description import load_parameters, planner_region
from area3d_eval.rundir import check_depth_source, write_episode, write_frame


def _policy_parameters(policy: str) -> dict[str, dict]:
    from area3d_bringup.runner import POLICIES

    if policy not in POLICIES:
        raise ValueError(f"policy: got {policy!r}, expected one of {sorted(POLICIES)}")
    return POLICIES[policy]


def run_inprocess_episode(
    scene_name: str,
    policy: str,
    seed: int,
    out_dir: Path,
    budget: int | None = None,
    overrides: dict[str, dict] | None = None,
    run_name: str | None = None,
    depth_source: str = "sensor",
) -> Path:
    """Run one closed-loop episode in this process; returns its run directory (frames and
    episode.json, as `area3d run` writes them, with a timing per stage). depth_source: what the
    TSDF of the evaluation integrates (rundir.DEPTH_SOURCES); "estimated" keeps perception's depth
    and confidence in every frame file."""
    from area3d_perception.estimator import FrameEstimator
    from area3d_perception.stereo import StereoParams
    from area3d_planner.server import NextBestViewServer, PlannerConfig, PlanRequest
    from area3d_semantics.analysis import analyze_views
    from area3d_semantics.backends import make_backend
    from area3d_semantics.weights import (
        SemanticParams,
        semantic_uncertainty,
        sigma_from_confidence,
        weight_map,
    )
    from sim_bridge.camera import STEREO_BASELINE, SimCamera
    from sim_bridge.scenes import load_scene

    check_depth_source(depth_source)
    scene = load_scene(scene_name)
    params = load_parameters()
    for node, values in _policy_parameters(policy).items():
        params.setdefault(node, {}).update(values)
    for node, values in (overrides or {}).items():
        params.setdefault(node, {}).update(values)
    perception = params.get("perception", {})
    camera_params = params.get("sim_bridge", {})
    stereo = perception.get("backend") == "stereo" or bool(camera_params.get("stereo", False))
    semantics = params.get("semantics", {})
    planner = dict(params.get("planner", {}))
    n_init = len(scene.initial_views)
    total = int(budget) if budget is not None else (25 if scene.level == "object" else 40)
    planner.update(planner_region(scene))
    planner.update({"budget": total, "mode": "closed_loop", "seed": seed})
    fields = PlannerConfig.__dataclass_fields__
    config = PlannerConfig(
        **{k: tuple(v) if isinstance(v, list) else v for k, v in planner.items() if k in fields}
    )
    server = NextBestViewServer(config)
    baseline = float(camera_params.get("stereo_baseline", STEREO_BASELINE)) if stereo else 0.0
    camera = SimCamera(
        scene,
        depth_noise=bool(camera_params.get("depth_noise", True)),
        seed=int(camera_params.get("noise_seed", 0)) + seed,
        image_noise=float(camera_params.get("image_noise", 1.0)),
        stereo_baseline=baseline,
    )
    estimator = FrameEstimator(
        backend=perception.get("backend", "rgbd"),
        uniform_confidence=bool(perception.get("uniform_confidence", False)),
        stereo=StereoParams(
            **{
                k.removeprefix("stereo."): v
                for k, v in perception.items()
                if k.startswith("stereo.")
            }
        ),
    )
    backend = make_backend(semantics.get("backend", "heuristic"))
    sem_params = SemanticParams()

    run_dir = Path(out_dir) / (run_name or f"{scene.name}_{policy}_s{seed}")
    run_dir.mkdir(parents=True, exist_ok=True)
    views: list[dict] = []
    timings: dict[str, float] = {}
    captured: list = []

    def add_time(stage: str, seconds: float) -> None:
        timings[stage] = timings.get(stage, 0.0) + seconds

    def take(T: np.ndarray, kind: str) -> bool:
        t = time.perf_counter()
        cap = camera.capture(T)
        add_time("capture", time.perf_counter() - t)
        if not cap.ok:
            return False
        stamp = (len(views) + 1) * 1_000_000_000
        t = time.perf_counter()
        result = estimator.process(
            cap.rgb, cap.depth, camera.K, cap.T_world_cam, right=cap.rgb_right, baseline=baseline
        )
        add_time("perception", time.perf_counter() - t)
        t = time.perf_counter()
        server.add_frame(stamp, result.depth, result.confidence, camera.K, cap.T_world_cam)
        add_time("fusion", time.perf_counter() - t)
        estimates = {}
        if depth_source == "estimated":
            estimates = {"estimated_depth": result.depth, "confidence": result.confidence}
        write_frame(
            run_dir, len(views), cap.rgb, cap.depth, camera.K, cap.T_world_cam, stamp, **estimates
        )
        views.append(
            {"index": len(views), "stamp_ns": stamp, "T_world_cam": cap.T_world_cam, "kind": kind}
        )
        captured.append((stamp, cap.rgb, cap.depth, result.confidence))
        return True

    try:
        for T in scene.initial_views:
            if not take(T, "initial"):
                raise ValueError(f"the camera refused an initial view of {scene.name}")
        t = time.perf_counter()
        analysis = analyze_views(
            backend, [c[1] for c in captured], [c[2] for c in captured], fallback="heuristic"
        )
        by_confidence = semantics.get("sigma_source", "constant") == "confidence"
        for i, (stamp, rgb, _, confidence) in enumerate(captured):
            weight = weight_map(analysis.regions_of(i), rgb.shape[0], rgb.shape[1], sem_params)
            sigma = sigma_from_confidence(confidence) if by_confidence else np.ones_like(weight)
            server.add_semantic(stamp, semantic_uncertainty(sigma, weight, sem_params.lam))
        add_time("semantics", time.perf_counter() - t)
        refused = 0
        while len(views) < total and refused <= total:
            t = time.perf_counter()
            poses, reason = server.plan(
                PlanRequest(np.asarray(views[-1]["T_world_cam"]), views[-1]["stamp_ns"], 1)
            )
            add_time("planning", time.perf_counter() - t)
            if not poses:
                break
            if not take(poses[0], "planned"):
                refused += 1
    finally:
        camera.close()
        server.close()
    write_episode(
        run_dir,
        {
            "scene": str(scene.mjcf_path) if "/" in str(scene_name) else scene.name,
            "policy": policy,
            "seed": seed,
            "budget": total,
            "level": scene.level,
            "mode": "closed_loop",
            "depth_source": depth_source,
            "views": views,
            "timings_s": timings,
            "config": {"planner": planner, "in_process": True, "initial_views": n_init},
        },
    )
    return run_dir
