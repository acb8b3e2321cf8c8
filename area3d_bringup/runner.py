"""The mission manager: runs one active-reconstruction episode over the node graph.

It launches the graph, drives the camera through the initial views O_0, then asks the planner's
next-best-view service for views and drives the camera there until the view budget is spent.
Every captured frame is saved in the run directory as it arrives (and `episode.json` rewritten), so a
crash loses nothing and `--resume RUN_DIR` continues where the episode stopped: the saved frames are
replayed onto the camera topics for the new graph, then planning goes on with the remaining budget.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from area3d_bringup.launch_description import build_graph, load_parameters, planner_region
from area3d_bringup.launcher import Launcher, NodeDied
from area3d_bringup.recorder import BagRecorder
from area3d_msgs_py import codecs, msgs
from area3d_msgs_py.node import Node

#: policy name -> parameter overrides {node: {param: value}}; ablations are configurations.
POLICIES: dict[str, dict[str, dict]] = {
    "area3d": {"planner": {"policy": "area3d"}},
    "random": {"planner": {"policy": "random"}, "semantics": {"backend": "none"}},
    "uniform": {"planner": {"policy": "uniform"}, "semantics": {"backend": "none"}},
    "vlm_naive": {"planner": {"policy": "vlm_naive"}},
    "volumetric_ig": {"planner": {"policy": "volumetric_ig"}, "semantics": {"backend": "none"}},
    "no_vlm": {
        "planner": {"policy": "area3d", "semantic_weight": 0.0},
        "semantics": {"backend": "none"},
    },
    "no_ff": {"planner": {"policy": "area3d"}, "perception": {"backend": "uniform"}},
    "gamma0": {"planner": {"policy": "area3d", "gamma": 0.0}},
}

CAMERA_TOPICS = {
    "color": ("/area3d/camera/color/image_raw", "sensor_msgs/msg/Image"),
    "depth": ("/area3d/camera/depth/image_raw", "sensor_msgs/msg/Image"),
    "info": ("/area3d/camera/camera_info", "sensor_msgs/msg/CameraInfo"),
    "pose": ("/area3d/camera/pose", "geometry_msgs/msg/PoseStamped"),
}
RECORDED_TOPICS = {
    **{topic: type_name for topic, type_name in CAMERA_TOPICS.values()},
    "/tf": "tf2_msgs/msg/TFMessage",
    "/tf_static": "tf2_msgs/msg/TFMessage",
    "/area3d/camera/status": "std_msgs/msg/String",
    "/area3d/semantics/regions": "std_msgs/msg/String",
    "/area3d/planner/next_views": "nav_msgs/msg/Path",
    "/area3d/planner/status": "std_msgs/msg/String",
}
# Readers each camera topic has once the graph is up (the runner's own included): DDS volatile
# topics drop what is published before a reader has matched, so goals and replayed frames wait.
EXPECTED_READERS = {"goal": 1, "color": 3, "depth": 3, "info": 3, "pose": 3}
GRID_TOPIC = "/area3d/planner/uncertainty_grid"
NBV_SERVICE = "/area3d/planner/next_best_view"
GOAL_TOPIC = "/area3d/camera/goal_pose"


class EpisodeError(RuntimeError):
    """The episode could not go on; the message says why and what was kept."""


@dataclass
class EpisodeConfig:
    scene: str = "single_object"
    policy: str = "area3d"
    budget: int | None = None  # total views, O_0 included; None: the paper's T (25 object, 40 room)
    mode: str = "closed_loop"
    seed: int = 0
    out_dir: Path = Path("runs")
    run_name: str | None = None
    record: bool = True
    params_file: Path | None = None
    overrides: dict[str, dict] = field(default_factory=dict)
    domain_id: int | None = None
    capture_timeout_s: float = 30.0
    plan_timeout_s: float = 120.0
    fuse_timeout_s: float = 30.0
    startup_timeout_s: float = 90.0


@dataclass
class Frame:
    stamp_ns: int
    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    T_world_cam: np.ndarray


def paper_budget(level: str) -> int:
    """The paper's view budget T (total views, O_0 included): 25 object level, 40 scene level."""
    return 25 if level == "object" else 40


def save_frame(run_dir: Path, index: int, frame: Frame) -> Path:
    path = run_dir / "frames" / f"{index:04d}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(
        tmp,
        rgb=frame.rgb,
        depth=frame.depth,
        K=frame.K,
        T_world_cam=frame.T_world_cam,
        stamp_ns=np.int64(frame.stamp_ns),
    )
    os.replace(tmp, path)
    return path


def load_frame(path: Path) -> Frame:
    with np.load(path) as data:
        return Frame(
            int(data["stamp_ns"]), data["rgb"], data["depth"], data["K"], data["T_world_cam"]
        )


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def grid_msg_to_npz(msg: object, path: Path) -> None:
    cloud = codecs.msg_to_pointcloud(msg)
    np.savez_compressed(path, **{name: np.asarray(cloud[name]) for name in cloud.dtype.names})


class MissionManager:
    """The runner's own node: sends goals, collects frames, calls the next-best-view service."""

    def __init__(
        self,
        node: Node,
        recorder: BagRecorder | None,
        alive_check: Callable[[], None] = lambda: None,
    ):
        self.node = node
        self.recorder = recorder
        self.alive_check = alive_check  # raises when a node of the graph has died
        self._lock = threading.Condition()
        self._parts: dict[int, dict[str, object]] = {}
        self._status: dict[int, dict] = {}
        self.planner_status: dict = {}
        self.latest_grid: object | None = None
        self.goal_pub = node.create_publisher("geometry_msgs/msg/PoseStamped", GOAL_TOPIC)
        self.replay_pubs = {
            key: node.create_publisher(type_name, topic)
            for key, (topic, type_name) in CAMERA_TOPICS.items()
        }
        for key, (topic, type_name) in CAMERA_TOPICS.items():
            node.create_subscription(type_name, topic, self._on_part(key, topic, type_name))
        for topic, type_name in RECORDED_TOPICS.items():
            if topic not in {t for t, _ in CAMERA_TOPICS.values()}:
                latched = topic == "/tf_static"
                node.create_subscription(
                    type_name, topic, self._on_other(topic, type_name), latched=latched
                )
        node.create_subscription(
            "sensor_msgs/msg/PointCloud2", GRID_TOPIC, self._on_grid, latched=True
        )
        self.client = node.create_client("nav_msgs/srv/GetPlan", NBV_SERVICE)

    # -- callbacks (spin thread) ------------------------------------------------------------
    def _record(self, topic: str, type_name: str, stamp_ns: int, msg: object) -> None:
        if self.recorder is not None:
            self.recorder.write(topic, type_name, stamp_ns or self.node.now_ns(), msg)

    def _on_part(self, key: str, topic: str, type_name: str) -> Callable[[object], None]:
        def callback(msg: object) -> None:
            stamp = codecs.stamp_to_ns(msg.header.stamp)
            self._record(topic, type_name, stamp, msg)
            with self._lock:
                self._parts.setdefault(stamp, {})[key] = msg
                self._lock.notify_all()

        return callback

    def _on_other(self, topic: str, type_name: str) -> Callable[[object], None]:
        def callback(msg: object) -> None:
            self._record(topic, type_name, 0, msg)
            if topic == "/area3d/camera/status":
                status = json.loads(msg.data)
                with self._lock:
                    self._status[int(status.get("stamp_ns", 0))] = status
                    self._lock.notify_all()
            elif topic == "/area3d/planner/status":
                with self._lock:
                    self.planner_status = json.loads(msg.data)
                    self._lock.notify_all()

        return callback

    def _on_grid(self, msg: object) -> None:
        with self._lock:
            self.latest_grid = msg
            self._lock.notify_all()

    # -- episode steps (main thread) --------------------------------------------------------
    def wait_for_readers(self, timeout_s: float) -> list[str]:
        """Wait until the camera topics have their graph readers; the topics still short of them."""
        pubs = {"goal": self.goal_pub, **self.replay_pubs}
        deadline = time.monotonic() + timeout_s
        while True:
            short = [
                k for k, pub in pubs.items() if pub.get_subscription_count() < EXPECTED_READERS[k]
            ]
            if not short or time.monotonic() > deadline:
                return short
            self.alive_check()
            time.sleep(0.05)

    def capture(self, T_world_cam: np.ndarray, timeout_s: float) -> Frame | str:
        """Send the camera to `T_world_cam`; the frame, or the camera's reason for refusing."""
        stamp = self.node.now_ns()
        goal = msgs.PoseStamped(
            header=codecs.header(stamp, "world"), pose=codecs.matrix_to_pose(T_world_cam)
        )
        self._record(GOAL_TOPIC, "geometry_msgs/msg/PoseStamped", stamp, goal)
        self.goal_pub.publish(goal)
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while True:
                status = self._status.get(stamp)
                if status is not None and not status.get("ok", False):
                    return str(status.get("reason", "rejected"))
                parts = self._parts.get(stamp, {})
                if len(parts) == len(CAMERA_TOPICS):
                    del self._parts[stamp]
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(
                        f"no frame from sim_bridge within {timeout_s:.0f} s for the goal stamped {stamp}"
                    )
                self._lock.wait(min(remaining, 0.1))
                self.alive_check()
        K, _, _ = codecs.camera_info_to_intrinsics(parts["info"])
        return Frame(
            stamp,
            codecs.msg_to_image(parts["color"]),
            codecs.msg_to_image(parts["depth"]),
            K,
            codecs.pose_to_matrix(parts["pose"].pose),
        )

    def replay(self, frame: Frame) -> None:
        """Publish a saved frame on the camera topics, as the camera did when it was captured."""
        h, w = frame.depth.shape
        header_args = (frame.stamp_ns, "camera_optical_frame")
        self.replay_pubs["color"].publish(codecs.image_to_msg(frame.rgb, "rgb8", *header_args))
        self.replay_pubs["depth"].publish(codecs.image_to_msg(frame.depth, "32FC1", *header_args))
        self.replay_pubs["info"].publish(
            codecs.intrinsics_to_camera_info(frame.K, w, h, *header_args)
        )
        self.replay_pubs["pose"].publish(
            msgs.PoseStamped(
                header=codecs.header(frame.stamp_ns, "world"),
                pose=codecs.matrix_to_pose(frame.T_world_cam),
            )
        )

    def wait_fused(self, count: int, timeout_s: float, key: str = "frames_fused") -> bool:
        """Wait until the planner reports at least `count` fused frames (or semantic maps, by `key`)."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while int(self.planner_status.get(key, 0)) < count:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._lock.wait(min(remaining, 0.1))
                self.alive_check()
        return True

    def plan(self, current: Frame, count: int, timeout_s: float) -> list[np.ndarray]:
        """Ask the planner for `count` views (0 = what the budget allows) from the current pose."""
        request = msgs.GetPlan_Request(
            start=msgs.PoseStamped(
                header=codecs.header(current.stamp_ns, "world"),
                pose=codecs.matrix_to_pose(current.T_world_cam),
            ),
            goal=msgs.PoseStamped(
                header=codecs.header(current.stamp_ns, "world"),
                pose=codecs.matrix_to_pose(np.eye(4)),
            ),
            tolerance=0.0,
        )
        request.goal.pose.position.x = float(count)
        # The call runs on a daemon thread so that a planner dying mid-call is noticed at once.
        result: dict[str, object] = {}

        def call() -> None:
            try:
                result["response"] = self.client.call(request, timeout_s)
            except Exception as err:  # handed to the caller below
                result["error"] = err

        caller = threading.Thread(target=call, name="next-best-view-call", daemon=True)
        caller.start()
        while caller.is_alive():
            caller.join(0.1)
            self.alive_check()
        if "error" in result:
            raise result["error"]
        response = result["response"]
        self._record(
            "/area3d/planner/next_views", "nav_msgs/msg/Path", current.stamp_ns, response.plan
        )
        return [codecs.pose_to_matrix(p.pose) for p in response.plan.poses]


def _spin_in_background(node: Node, stop: threading.Event) -> threading.Thread:
    def loop() -> None:
        while not stop.is_set():
            node.spin_once(0.05)

    thread = threading.Thread(target=loop, name="mission-manager-spin", daemon=True)
    thread.start()
    return thread


def run_episode(
    config: EpisodeConfig, resume: Path | None = None, progress: object | None = None
) -> Path:
    """Run one episode; returns the run directory (frames, episode.json, bag, grids)."""
    from area3d_msgs_py.dds_config import use_loopback
    from sim_bridge.scenes import load_scene

    if config.policy not in POLICIES:
        raise ValueError(f"policy: got {config.policy!r}, expected one of {sorted(POLICIES)}")
    if config.mode not in ("closed_loop", "batch"):
        raise ValueError(f"mode: got {config.mode!r}, expected 'closed_loop' or 'batch'")
    scene = load_scene(config.scene)
    budget = paper_budget(scene.level) if config.budget is None else int(config.budget)
    if budget < len(scene.initial_views):
        raise ValueError(
            f"budget: got {budget}, expected the total number of views, at least |O_0| = {len(scene.initial_views)}"
        )

    timings: dict[str, float] = {}
    views: list[dict] = []
    frames: list[Frame] = []
    if resume is not None:
        run_dir = Path(resume)
        episode_path = run_dir / "episode.json"
        if not episode_path.is_file():
            raise FileNotFoundError(
                f"resume: got {str(run_dir)!r}, expected a run directory with episode.json"
            )
        saved = json.loads(episode_path.read_text())
        config.scene, config.policy, config.mode = saved["scene"], saved["policy"], saved["mode"]
        config.seed, budget = saved["seed"], saved["budget"]
        scene = load_scene(config.scene)
        views = saved["views"]
        frames = [load_frame(run_dir / "frames" / f"{v['index']:04d}.npz") for v in views]
        timings = saved.get("timings_s", {})
    else:
        name = (
            config.run_name
            or f"{scene.name}_{config.policy}_s{config.seed}_{time.strftime('%Y%m%d-%H%M%S')}"
        )
        run_dir = Path(config.out_dir) / name
        run_dir.mkdir(parents=True, exist_ok=False)
    n_init = len(scene.initial_views)

    overrides: dict[str, dict] = {}
    for node, values in POLICIES[config.policy].items():
        overrides.setdefault(node, {}).update(values)
    overrides.setdefault("sim_bridge", {})["scene"] = config.scene
    overrides.setdefault("planner", {}).update(
        {"budget": budget, "mode": config.mode, "seed": config.seed, **planner_region(scene)}
    )
    overrides.setdefault("semantics", {})["num_initial_views"] = n_init
    for node, values in config.overrides.items():
        overrides.setdefault(node, {}).update(values)
    specs = build_graph(load_parameters(config.params_file), overrides)

    def save_episode() -> None:
        _write_json(
            run_dir / "episode.json",
            {
                "scene": config.scene,
                "policy": config.policy,
                "seed": config.seed,
                "budget": budget,
                "level": scene.level,
                "mode": config.mode,
                "views": views,
                "timings_s": timings,
                "config": {spec.name: spec.parameters for spec in specs},
            },
        )

    def add_time(stage: str, seconds: float) -> None:
        timings[stage] = timings.get(stage, 0.0) + seconds

    domain_id = (
        config.domain_id
        if config.domain_id is not None
        else int(os.environ.get("ROS_DOMAIN_ID", "0"))
    )
    use_loopback(domain_id)
    log_path = run_dir / "nodes.log"
    log_file = log_path.open("a")
    log_lock = threading.Lock()

    def log_sink(line: str) -> None:
        with log_lock:
            log_file.write(line + "\n")
            log_file.flush()

    bag_index = len(list(run_dir.glob("bag*")))
    recorder = (
        BagRecorder(run_dir / (f"bag_{bag_index}" if bag_index else "bag"))
        if config.record
        else None
    )
    t0 = time.monotonic()
    launcher = Launcher(specs, run_dir, log_sink=log_sink)
    stop = threading.Event()
    node = Node("mission_manager")
    manager = MissionManager(node, recorder, alive_check=launcher.check)
    spinner = _spin_in_background(node, stop)
    task = None
    try:
        launcher.start()
        deadline = time.monotonic() + config.startup_timeout_s
        while not manager.client.wait_for_service(0.5):
            launcher.check()
            if time.monotonic() > deadline:
                raise EpisodeError(
                    f"the planner service {NBV_SERVICE} did not appear within {config.startup_timeout_s:.0f} s"
                )
        short = manager.wait_for_readers(config.startup_timeout_s)
        if short:
            log_sink(
                f"[mission_manager] topics {short} have fewer readers than the graph should give them"
            )
        add_time("launch", time.monotonic() - t0)
        if progress is not None:
            task = progress.add_task(f"{scene.name} / {config.policy}", total=budget)
            progress.update(task, completed=len(frames))

        def keep(frame: Frame, kind: str, stage_times: dict) -> None:
            index = len(frames)
            save_frame(run_dir, index, frame)
            frames.append(frame)
            views.append(
                {
                    "index": index,
                    "stamp_ns": frame.stamp_ns,
                    "T_world_cam": frame.T_world_cam.tolist(),
                    "kind": kind,
                    "stage_times_s": stage_times,
                }
            )
            save_episode()
            if progress is not None:
                status = manager.planner_status
                metric = status.get("uncertainty_total")
                extra = f" | U={metric:.1f}" if isinstance(metric, int | float) else ""
                progress.update(
                    task,
                    completed=len(frames),
                    description=f"{scene.name} / {config.policy}: view {len(frames)}/{budget} ({kind}){extra}",
                )

        # Replay what an interrupted episode had already captured, so the new graph knows it.
        # One frame at a time, each waited for until fused: saved stamps may lie further apart than
        # any pairing horizon in the graph, and parts of a later frame must never overtake an
        # earlier one, or perception and the planner would drop it as too old.
        if frames:
            t = time.monotonic()
            for i, frame in enumerate(frames):
                manager.replay(frame)
                if not manager.wait_fused(i + 1, config.fuse_timeout_s):
                    log_sink(
                        f"[mission_manager] replayed frame {i} (stamp {frame.stamp_ns}) not fused "
                        f"after {config.fuse_timeout_s:.0f} s; going on"
                    )
            add_time("replay", time.monotonic() - t)

        for T in scene.initial_views[len(frames) : n_init] if len(frames) < n_init else []:
            t = time.monotonic()
            result = manager.capture(T, config.capture_timeout_s)
            launcher.check()
            if isinstance(result, str):
                raise EpisodeError(f"the camera refused initial view {len(frames)}: {result}")
            add_time("capture", time.monotonic() - t)
            keep(result, "initial", {"capture": time.monotonic() - t})
        semantics = next(spec for spec in specs if spec.name == "semantics").parameters
        if semantics.get("backend", "heuristic") != "none" and not manager.wait_fused(
            n_init, config.plan_timeout_s, key="semantic_frames_fused"
        ):
            log_sink(
                f"[mission_manager] no semantic maps for the initial views after "
                f"{config.plan_timeout_s:.0f} s; planning without them"
            )
        if not manager.wait_fused(n_init, config.fuse_timeout_s):
            log_sink(
                f"[mission_manager] the planner has not fused all {n_init} initial views after "
                f"{config.fuse_timeout_s:.0f} s; planning with what it has"
            )
        if manager.latest_grid is not None and not (run_dir / "grid_initial.npz").exists():
            grid_msg_to_npz(manager.latest_grid, run_dir / "grid_initial.npz")

        planned = len(frames) - n_init
        refused = 0
        to_plan = budget - n_init
        while planned < to_plan:
            t = time.monotonic()
            count = 1 if config.mode == "closed_loop" else to_plan - planned
            poses = manager.plan(frames[-1], count, config.plan_timeout_s)
            plan_s = time.monotonic() - t
            add_time("plan", plan_s)
            launcher.check()
            if not poses:
                log_sink(
                    f"[mission_manager] the planner returned no view with {to_plan - planned} left; stopping early"
                )
                break
            for T in poses[: to_plan - planned]:
                t = time.monotonic()
                result = manager.capture(T, config.capture_timeout_s)
                add_time("capture", time.monotonic() - t)
                if isinstance(result, str):
                    refused += 1
                    log_sink(f"[mission_manager] the camera refused a planned view: {result}")
                    if refused > budget:
                        raise EpisodeError(
                            "the camera refused more planned views than the budget; stopping"
                        )
                    continue
                planned += 1
                keep(
                    result,
                    "planned",
                    {"plan": plan_s / len(poses), "capture": time.monotonic() - t},
                )
        manager.wait_fused(len(frames), 10.0)
        if manager.latest_grid is not None:
            grid_msg_to_npz(manager.latest_grid, run_dir / "grid_final.npz")
        add_time("episode_total", time.monotonic() - t0)
        save_episode()
    except NodeDied as err:
        save_episode()
        raise EpisodeError(
            f"{err}\nkept {len(frames)} captured views in {run_dir}; continue with --resume {run_dir}"
        ) from err
    except (TimeoutError, EpisodeError) as err:
        save_episode()
        raise EpisodeError(
            f"{err}\nkept {len(frames)} captured views in {run_dir}; continue with --resume {run_dir}"
        ) from err
    finally:
        stop.set()
        spinner.join(timeout=2.0)
        launcher.stop()
        node.shutdown()
        if recorder is not None:
            recorder.close()
        log_file.close()
    return run_dir


def episode_summary(run_dir: Path) -> dict:
    data = json.loads((Path(run_dir) / "episode.json").read_text())
    return {k: data[k] for k in ("scene", "policy", "seed", "budget", "mode")} | {
        "views": len(data["views"])
    }
