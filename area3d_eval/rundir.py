"""The run directory: what an episode leaves on disk and what evaluation reads back.

Layout (all paths relative to RUN_DIR):

- `episode.json`: {"scene", "policy", "seed", "budget", "level", "mode", "depth_source",
  "views": [{"index", "stamp_ns", "T_world_cam" (4x4 list), "kind": "initial" | "planned",
  "stage_times_s": {...}}], "timings_s": {stage: seconds}, "config": {...},
  "ros": {"domain_id", "namespace"}, "recorded": {topic: message count in the bag},
  "respawns": {node: restarts during the run}, "planner_status": the planner's last status,
  "stopped_early": why the episode ended before its budget was spent ("" when it was not:
  `stopped_early`)}
- `frames/NNNN.npz`: rgb (H, W, 3) uint8, depth (H, W) float32 metres NaN = no return,
  K (3, 3), T_world_cam (4, 4) optical frame, stamp_ns (int64); NNNN = the view's index. Optional:
  estimated_depth (H, W) float32 metres (NaN = no estimate, +Inf = no return within range),
  confidence (H, W) float32 in [0, 1] (what the planner read) and weight (H, W) float32 in
  [0, 1]: what perception made of the frame (the depth and the weights the TSDF uses with
  depth_source "estimated"; a frame without `weight`, one equal to its confidence or from an
  older run, uses the confidence).
- `grid_initial.npz`, `grid_final.npz` (optional): the planner's uncertainty grid as 1-D arrays
  x, y, z, uncertainty, geometric, semantic, occupancy, hard (one entry per voxel; older runs
  have no `hard`).
- `bag/`: rosbag2 MCAP of everything the graph published (`bag_N/` for resumed parts); the
  message count of each topic is in episode.json under "recorded".
- `nodes.log`, `params.yaml`: every node's log and the parameters it was started with.
- `metrics.json` (written by `area3d_eval.evaluate.evaluate_run`).

Every file is written to a temporary name in the same directory and renamed over its final name
(`os.replace`, atomic on POSIX), so a run killed mid-write leaves the previous complete version of
each file, never half of one; leftover temporary files (hidden, `.NAME.*.tmp*`) are ignored by the
readers.
- `maps/`: what the graph held when the episode ended, saved over its services: the planner's
  map (`planner.a3map`) and the reconstruction's volume (`reconstruction.a3map`), loadable with
  `load_map` (docs/map_format.md), and the live mesh (`mesh.ply`, `export_mesh`).
- `eval/` (written by evaluation): `reconstruction.ply` (final TSDF mesh cropped to the ROI) and
  `gt_sample.npy` (a few thousand ground-truth surface points for plots).
"""

from __future__ import annotations

import json
import math
import shutil
import tempfile
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from area3d_msgs_py.errors import InputError
from area3d_msgs_py.mapfile import replace_atomically

EPISODE_FILE = "episode.json"
# What the TSDF integrates: the camera's depth, or the depth perception estimated from the images
# (stored in each frame as estimated_depth; views that fix bad estimates then show in the metrics).
DEPTH_SOURCES = ("sensor", "estimated")
METRICS_FILE = "metrics.json"
FRAMES_DIR = "frames"
EVAL_DIR = "eval"
MESH_FILE = "reconstruction.ply"  # in EVAL_DIR: the final TSDF mesh
GRID_INITIAL_FILE = "grid_initial.npz"
GRID_FINAL_FILE = "grid_final.npz"
LOG_FILE = "nodes.log"
BAG_DIR = "bag"
MAPS_DIR = "maps"  # what the graph held at the end: its maps and the live mesh
PLANNER_MAP_FILE = "planner.a3map"
RECONSTRUCTION_MAP_FILE = "reconstruction.a3map"
LIVE_MESH_FILE = "mesh.ply"
GRID_FIELDS = ("x", "y", "z", "uncertainty", "geometric", "semantic", "occupancy", "hard")
# Free space a new episode asks for before it starts: a 40-view room episode at 640x480 writes
# about 90 MB of frames, and its bag holds every image and grid the graph published.
MIN_FREE_MB = 1024.0


@dataclass(frozen=True)
class Frame:
    """One captured view. rgb (H, W, 3) uint8; depth (H, W) float32 metres, NaN = no return;
    K (3, 3); T_world_cam (4, 4) optical frame in `world`; stamp_ns capture time;
    estimated_depth / confidence / weight: perception's output for the view (None when not
    recorded)."""

    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    T_world_cam: np.ndarray
    stamp_ns: int = 0
    index: int = 0
    estimated_depth: np.ndarray | None = None
    confidence: np.ndarray | None = None
    weight: np.ndarray | None = None

    def __iter__(self):
        """Unpacks as (rgb, depth, K, T_world_cam), the tuple `tsdf_reconstruct` takes."""
        return iter((self.rgb, self.depth, self.K, self.T_world_cam))


@dataclass(frozen=True)
class Episode:
    """episode.json as read back; `views` keeps the raw dicts (T_world_cam as (4, 4) arrays)."""

    scene: str
    policy: str
    seed: int
    budget: int
    level: str
    mode: str
    views: list[dict[str, Any]]
    timings_s: dict[str, float] = field(default_factory=dict)
    config: dict[str, Any] = field(default_factory=dict)
    depth_source: str = "sensor"
    stopped_early: str = ""  # why the episode ended before its budget ("": it did not)
    # where the regions of the last semantic query came from: {"backend", "fallback_used" (None
    # or the analyser that stood in), "error" (why the backend's answer was not used)}; {}: none
    semantics: dict[str, Any] = field(default_factory=dict)

    @property
    def scene_name(self) -> str:
        """The scene as titles and tables name it (`scene_name`)."""
        return scene_name(self.scene)

    @property
    def num_initial(self) -> int:
        return sum(1 for v in self.views if v.get("kind") == "initial")

    def poses(self) -> np.ndarray:
        """(N, 4, 4) float64 T_world_cam of every view, in index order."""
        if not self.views:
            return np.zeros((0, 4, 4))
        return np.stack([np.asarray(v["T_world_cam"], dtype=np.float64) for v in self.views])

    def kinds(self) -> list[str]:
        return [str(v.get("kind", "planned")) for v in self.views]


def scene_name(scene: str) -> str:
    """How titles and tables name the scene of episode.json's "scene" field: a bundled scene by its
    name, a scene given as an MJCF path by the file's stem (never the path, which stays in
    episode.json for loading the scene again)."""
    text = str(scene)
    return Path(text).stem if "/" in text or text.endswith(".xml") else text


def stopped_early(views_left: int, reason: str) -> str:
    """episode.json's "stopped_early" when the planner returned no view with `views_left` views
    of the budget left, `reason` being the planner's (the graph's runner and an in-process
    episode say it alike)."""
    return f"the planner returned no view with {views_left} left ({reason})"


def read_episode(run_dir: Path) -> Episode:
    """Parse RUN_DIR/episode.json; views are sorted by index."""
    path = Path(run_dir) / EPISODE_FILE
    if not path.is_file():
        raise InputError("run_dir", str(run_dir), f"a run directory containing {EPISODE_FILE}")
    data = read_json_object(path, "the episode.json a run writes")
    for key in ("scene", "policy"):
        if key not in data:
            raise InputError(f"{path}: {key}", "missing", "a string")
    try:
        views = sorted(data.get("views", []), key=lambda v: int(v["index"]))
        return Episode(
            scene=str(data["scene"]),
            policy=str(data["policy"]),
            seed=int(data.get("seed", 0)),
            budget=int(data.get("budget", len(views))),
            level=str(data.get("level", "object")),
            mode=str(data.get("mode", "")),
            views=views,
            timings_s={str(k): float(v) for k, v in data.get("timings_s", {}).items()},
            config=dict(data.get("config", {})),
            depth_source=str(data.get("depth_source", "sensor")),
            stopped_early=str(data.get("stopped_early", "")),
            semantics=dict(data.get("semantics") or {}),
        )
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise InputError(
            str(path),
            f"an entry of another kind ({type(exc).__name__}: {exc})",
            "the episode.json a run writes",
        ) from exc


def read_json_object(path: Path, expected: str) -> dict:
    """The JSON object in `path`; a file that is no JSON object refused, the file named."""
    try:
        data = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(str(path), f"not JSON ({exc})", expected) from exc
    if not isinstance(data, dict):
        raise InputError(str(path), type(data).__name__, f"a JSON object: {expected}")
    return data


def check_output_dir(directory: Path, min_free_mb: float = MIN_FREE_MB) -> None:
    """Refuse, before anything is written, a directory that cannot hold a run: one that cannot be
    created or written to, or whose file system has less than `min_free_mb` MiB free."""
    directory = Path(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=directory, prefix=".area3d-write-check-"):
            pass  # permissions alone do not tell (root, read-only mounts): try a real write
    except OSError as exc:
        raise InputError(
            "output directory",
            str(directory),
            f"a directory this process can write to ({exc.strerror or exc})",
        ) from exc
    free_mb = shutil.disk_usage(directory).free / 2**20
    if free_mb < min_free_mb:
        raise InputError(
            "output directory",
            str(directory),
            f"at least {min_free_mb:.0f} MiB free (has {free_mb:.0f} MiB); free space or lower min_free_mb",
        )


def write_atomic(path: Path, write: Callable[[Path], None], sync: bool = False) -> Path:
    """Call `write(tmp)` on a temporary file next to `path`, then rename it over `path`
    (`mapfile.replace_atomically`; the folder made first): a reader (or a run resumed after a
    crash) sees the old complete file or the new one, never a torn one. `sync` flushes the data
    to the disk first, so it also survives a power cut."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    replace_atomically(path, write, suffix=f".tmp{path.suffix}", sync=sync)
    return path


def write_json(path: Path, data: Any, indent: int = 1) -> Path:
    """JSON (numpy values made plain), written atomically and synced: the run's small index files."""
    text = json.dumps(to_jsonable(data), indent=indent)
    return write_atomic(path, lambda tmp: tmp.write_text(text), sync=True)


def write_episode(run_dir: Path, episode: dict[str, Any]) -> Path:
    """Write episode.json (numpy arrays in it become lists)."""
    return write_json(Path(run_dir) / EPISODE_FILE, episode)


def check_depth_source(depth_source: str) -> str:
    """The name itself, or InputError naming the field when it is not one of DEPTH_SOURCES."""
    if depth_source not in DEPTH_SOURCES:
        raise InputError("depth_source", depth_source, f"one of {', '.join(DEPTH_SOURCES)}")
    return depth_source


def reconstruction_input(frame: Frame, depth_source: str) -> tuple[np.ndarray, np.ndarray]:
    """(depth, confidence), both (H, W) float32, that the TSDF integrates for `frame` under
    `depth_source`: the camera's depth weighted by the camera's sensor model
    (`area3d_perception.sensor_model.rgbd_confidence`, whatever the planner was told), or
    perception's estimate weighted by perception's fusion weight (both kept in the frame; the
    confidence in runs that kept no weight)."""
    if check_depth_source(depth_source) == "sensor":
        from area3d_perception.sensor_model import rgbd_confidence

        return frame.depth, rgbd_confidence(frame.depth, frame.K)
    for name in ("estimated_depth", "confidence"):
        if getattr(frame, name) is None:
            raise InputError(
                f"frames/{frame.index:04d}.npz {name}",
                None,
                "perception's depth and confidence in every frame (run the episode with "
                "depth_source estimated)",
            )
    weight = frame.weight if frame.weight is not None else frame.confidence
    return frame.estimated_depth, weight


def frame_path(run_dir: Path, index: int) -> Path:
    return Path(run_dir) / FRAMES_DIR / f"{int(index):04d}.npz"


def write_frame(
    run_dir: Path,
    index: int,
    rgb: np.ndarray,
    depth: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    stamp_ns: int = 0,
    estimated_depth: np.ndarray | None = None,
    confidence: np.ndarray | None = None,
    weight: np.ndarray | None = None,
) -> Path:
    """Write RUN_DIR/frames/NNNN.npz in the layout above (uncompressed: it is read back often).

    Written to a temporary file and renamed, so a crash never leaves half a frame."""
    rgb = np.asarray(rgb)
    depth = np.asarray(depth)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise InputError("rgb", f"{rgb.dtype} {rgb.shape}", "(H, W, 3) uint8")
    if depth.shape != rgb.shape[:2]:
        raise InputError("depth", f"shape {depth.shape}", f"(H, W) = {rgb.shape[:2]} like rgb")
    if weight is not None and confidence is not None and np.array_equal(weight, confidence):
        weight = None  # read back as the confidence: the same image is not written twice
    estimates = {}
    named = (("estimated_depth", estimated_depth), ("confidence", confidence), ("weight", weight))
    for name, image in named:
        if image is not None:
            if np.shape(image) != rgb.shape[:2]:
                raise InputError(name, f"shape {np.shape(image)}", f"(H, W) = {rgb.shape[:2]}")
            estimates[name] = np.asarray(image, dtype=np.float32)
    arrays = {
        "rgb": rgb,
        "depth": depth.astype(np.float32),
        "K": np.asarray(K, dtype=np.float64),
        "T_world_cam": np.asarray(T_world_cam, dtype=np.float64),
        "stamp_ns": np.int64(stamp_ns),
        **estimates,
    }
    return write_atomic(frame_path(run_dir, index), lambda tmp: np.savez(tmp, **arrays))


def attach_estimates(
    run_dir: Path,
    frames: list[Frame],
    estimates: dict[int, dict[str, np.ndarray]],
    log: Callable[[str], None],
) -> None:
    """Rewrite each frame file with perception's output for it: `estimates` is
    {stamp_ns: {"depth": (H, W), "confidence": (H, W), "weight": (H, W)}}. A frame with no depth
    there keeps what it has (an estimate saved before a resume) or is logged: the TSDF will
    refuse it."""
    for index, frame in enumerate(frames):
        got = estimates.get(frame.stamp_ns, {})
        if frame.estimated_depth is not None and "depth" not in got:
            continue  # kept from before a resume
        if "depth" not in got:
            log(f"no perception depth for view {index}; the TSDF will refuse it")
            continue
        write_frame(
            run_dir,
            index,
            *frame,
            stamp_ns=frame.stamp_ns,
            estimated_depth=got["depth"],
            confidence=got.get("confidence"),
            weight=got.get("weight"),
        )


def read_frame(path: Path) -> Frame:
    """One frames/NNNN.npz; a file that is not a whole frame refused, the file named."""
    try:
        return _read_frame(path)
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError) as exc:
        raise InputError(
            str(path), f"unreadable ({type(exc).__name__}: {exc})", "a whole frame file of a run"
        ) from exc


def _read_frame(path: Path) -> Frame:
    with np.load(path, allow_pickle=False) as data:
        return Frame(
            rgb=data["rgb"],
            depth=data["depth"].astype(np.float32),
            K=data["K"].astype(np.float64),
            T_world_cam=data["T_world_cam"].astype(np.float64),
            stamp_ns=int(data["stamp_ns"]) if "stamp_ns" in data else 0,
            index=int(Path(path).stem),
            estimated_depth=data["estimated_depth"] if "estimated_depth" in data else None,
            confidence=data["confidence"] if "confidence" in data else None,
            weight=data["weight"] if "weight" in data else None,
        )


def frame_files(run_dir: Path) -> list[Path]:
    """RUN_DIR/frames/*.npz sorted by view index."""
    files = (Path(run_dir) / FRAMES_DIR).glob("*.npz")
    return sorted((p for p in files if p.stem.isdigit()), key=lambda p: int(p.stem))


def iter_frames(run_dir: Path, limit: int | None = None) -> Iterator[Frame]:
    """Frames in view-index order, at most `limit` of them."""
    files = frame_files(run_dir)
    for path in files if limit is None else files[:limit]:
        yield read_frame(path)


def write_grid(path: Path, cloud: np.ndarray) -> Path:
    """Write a grid_*.npz from the planner's cloud (structured array with GRID_FIELDS)."""
    arrays = {name: np.asarray(cloud[name]) for name in cloud.dtype.names}
    return write_atomic(path, lambda tmp: np.savez_compressed(tmp, **arrays))


def bag_path(run_dir: Path) -> Path:
    """A new bag directory: `bag/` for the first part of an episode, `bag_N/` after N resumes."""
    parts = len(list(Path(run_dir).glob(BAG_DIR + "*")))
    return Path(run_dir) / (f"{BAG_DIR}_{parts}" if parts else BAG_DIR)


def read_grid(path: Path) -> dict[str, np.ndarray] | None:
    """A grid_*.npz as {field: (N,) array}, or None if the file is absent."""
    path = Path(path)
    if not path.is_file():
        return None
    with np.load(path) as data:
        return {k: np.asarray(data[k]) for k in GRID_FIELDS if k in data}


def to_jsonable(value: Any) -> Any:
    """Plain JSON values: arrays become lists, NaN and inf become null (strict JSON has neither)."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


def read_metrics(run_dir: Path) -> dict[str, Any] | None:
    """RUN_DIR/metrics.json (None when the run was not evaluated); a file that is not what the
    evaluation writes ({"final": {...}, ...}) refused, the file named."""
    path = Path(run_dir) / METRICS_FILE
    if not path.is_file():
        return None
    metrics = read_json_object(path, "the metrics.json the evaluation writes")
    if not isinstance(metrics.get("final"), dict):
        raise InputError(f"{path}: final", metrics.get("final"), "an object of the final figures")
    return metrics


def check_frames(run_dir: Path, episode: Episode) -> list[Path]:
    """The run's frame files, refused when a view episode.json lists has none (a frame file
    deleted or lost: the evaluation would silently score fewer views)."""
    files = frame_files(run_dir)
    have = {int(p.stem) for p in files}
    missing = sorted(int(v["index"]) for v in episode.views if int(v["index"]) not in have)
    if missing:
        raise InputError(
            f"{Path(run_dir) / FRAMES_DIR}",
            f"no frame file for views {missing}",
            f"frames/NNNN.npz of every view {EPISODE_FILE} lists ({len(episode.views)})",
        )
    return files
