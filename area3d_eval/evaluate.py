"""Evaluate one run directory: reconstruct after n = 4, 8, ... views, compare with the ground truth,
write RUN_DIR/metrics.json.

Held-out images: the scene's eval views are rendered by the simulator (ground truth, lit by the
scene's own lights, not by MuJoCo's camera-mounted headlight) and the TSDF mesh is rendered at the
same poses by ray casting. The reference image keeps only pixels whose ground-truth surface lies in
the region to reconstruct (the ROI); the rest is black, as is every pixel where the reconstruction
has no surface. `psnr_roi`/`ssim_roi`, the headline figures, are over the pixels where the ground
truth sees the ROI; `psnr`/`ssim` over whole images (secondary: they also score the black
background, which every reconstruction matches).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from area3d_eval.metrics import (
    NUM_SURFACE_POINTS,
    SURFACE_SEED,
    ReferenceSurface,
    mean_ssim,
    psnr,
    ssim_map,
)
from area3d_eval.open3d_loader import import_open3d
from area3d_eval.reconstruct import TsdfFusion, TsdfParams
from area3d_eval.render import MeshRenderer
from area3d_eval.rundir import (
    EVAL_DIR,
    MESH_FILE,
    METRICS_FILE,
    check_depth_source,
    check_frames,
    read_episode,
    read_frame,
    reconstruction_input,
    write_json,
)
from area3d_msgs_py.backproject import roi_pixels
from area3d_msgs_py.camera import PAPER_HFOV_DEG
from area3d_msgs_py.errors import InputError

CHECKPOINT_STEP = (
    4  # evaluate after every 4th view (4 = |O_0| at object level, the paper's setting)
)
# ... and after this share of the views (rounded): the "fewer views" figure, when a policy reaches
# another's final completion (15 of 25 at object level, 24 of 40 at room level)
FEWER_VIEWS_SHARE = 0.6
EVAL_WIDTH = (
    320  # held-out images at half the camera's 640 x 480: 4x fewer rays, same field of view
)
EVAL_HEIGHT = 240
EVAL_HFOV_DEG = PAPER_HFOV_DEG  # held-out views see what the camera sees
GT_PREVIEW_POINTS = 4000  # GT points saved next to the metrics for the views plot

RendererFactory = Callable[[Any, int, int, float], Any]


def default_checkpoints(
    num_frames: int, num_initial: int = 0, step: int = CHECKPOINT_STEP
) -> list[int]:
    """Numbers of views to evaluate at: |O_0|, every multiple of `step`, FEWER_VIEWS_SHARE of the
    frames, and all frames."""
    points = set(range(step, num_frames + 1, step)) | {num_frames}
    points.add(int(round(FEWER_VIEWS_SHARE * num_frames)))
    if 0 < num_initial <= num_frames:
        points.add(num_initial)
    return sorted(p for p in points if p >= 1)


def _sim_renderer(scene: Any, width: int, height: int, hfov_deg: float) -> Any:
    from sim_bridge.render import RgbdRenderer

    # Scene lights only, as for the captured frames (the simulated camera uses the same renderer):
    # a camera-mounted light would make the reference colours depend on the held-out view.
    return RgbdRenderer(
        scene, width=width, height=height, hfov_deg=hfov_deg, camera_headlight=False
    )


def _load_scene(scene: Any, name: str) -> Any:
    if scene is None or isinstance(scene, str | Path):
        from sim_bridge.scenes import load_scene

        return load_scene(str(scene) if scene is not None else name)
    return scene


def reference_images(
    scene: Any, renderer_factory: RendererFactory, width: int, height: int, hfov_deg: float
) -> tuple[np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """(K, ROI-masked GT rgb per eval view, ROI pixel mask per eval view) rendered by the simulator."""
    renderer = renderer_factory(scene, width, height, hfov_deg)
    lo, hi = scene.roi_min, scene.roi_max
    images, masks = [], []
    try:
        K = np.asarray(renderer.K, dtype=np.float64)
        for T in np.asarray(scene.eval_views, dtype=np.float64):
            rgb, depth = renderer.render(T)
            inside = roi_pixels(depth, K, T, lo, hi)
            images.append(np.where(inside[..., None], rgb, 0).astype(np.uint8))
            masks.append(inside)
    finally:
        renderer.close()
    return K, images, masks


def image_metrics(
    mesh_renderer: MeshRenderer,
    K: np.ndarray,
    poses: np.ndarray,
    images: Sequence[np.ndarray],
    masks: Sequence[np.ndarray],
) -> dict[str, float]:
    """Mean PSNR / SSIM (all pixels and ROI pixels) of the mesh rendered at `poses` vs `images`,
    and what splits a region PSNR into coverage and appearance: `roi_unreconstructed`, the share
    of ROI pixels where the reconstruction has no surface (black against a lit surface: these
    dominate a low PSNR), and `psnr_roi_reconstructed`, the PSNR over the ROI pixels it has."""
    scores: dict[str, list[float]] = {
        "psnr": [],
        "ssim": [],
        "psnr_roi": [],
        "ssim_roi": [],
        "psnr_roi_reconstructed": [],
    }
    missing, roi_pixels = 0, 0
    for T, ref, mask in zip(poses, images, masks, strict=True):
        h, w = ref.shape[:2]
        rgb, depth = mesh_renderer.render(K, T, w, h)
        scores["psnr"].append(psnr(rgb, ref))
        s = ssim_map(rgb, ref)
        scores["ssim"].append(mean_ssim(s))
        scores["psnr_roi"].append(psnr(rgb, ref, mask))
        scores["ssim_roi"].append(mean_ssim(s, mask))
        surface = np.isfinite(depth)
        scores["psnr_roi_reconstructed"].append(psnr(rgb, ref, mask & surface))
        missing += int(np.count_nonzero(mask & ~surface))
        roi_pixels += int(np.count_nonzero(mask))
    out = {}
    for key, values in scores.items():
        arr = np.asarray(values, dtype=np.float64)
        # inf (a perfect view) would swamp a mean in dB; cap PSNR at 100 dB, drop undefined views
        arr = np.minimum(arr, 100.0) if key.startswith("psnr") else arr
        arr = arr[np.isfinite(arr)]
        out[key] = float(arr.mean()) if arr.size else float("nan")
    out["roi_unreconstructed"] = missing / roi_pixels if roi_pixels else float("nan")
    return out


def evaluate_run(
    run_dir: Path,
    scene: Any = None,
    checkpoints: Sequence[int] | None = None,
    *,
    tsdf: TsdfParams | None = None,
    eval_width: int = EVAL_WIDTH,
    eval_height: int = EVAL_HEIGHT,
    hfov_deg: float = EVAL_HFOV_DEG,
    num_surface_points: int = NUM_SURFACE_POINTS,
    renderer_factory: RendererFactory | None = None,
    write: bool = True,
    depth_source: str | None = None,
) -> dict[str, Any]:
    """Metrics of the run after each number of views in `checkpoints`, written to RUN_DIR/metrics.json.

    scene: a sim_bridge Scene (or anything with its fields: level, roi_min, roi_max, eval_views,
    tau, ground_truth_mesh()), a scene name, or None for the one named in episode.json.
    checkpoints: numbers of views (reconstruction from the first n frames); default |O_0|, 4, 8, ...
    and all frames. renderer_factory(scene, width, height, hfov_deg) -> object with .K,
    .render(T) -> (rgb, depth), .close(); default sim_bridge.render.RgbdRenderer.
    depth_source: "sensor" (the camera's depth) or "estimated" (perception's depth stored in the
    frames) for the TSDF; None = what the episode was run with (episode.json "depth_source").
    Returns the dict written: {"final": {...}, "curve": [{"num_views": n, ...}], ...}.
    """
    o3d = import_open3d()
    run_dir = Path(run_dir)
    episode = read_episode(run_dir)
    scene = _load_scene(scene, episode.scene)
    depth_source = check_depth_source(depth_source or episode.depth_source)
    files = check_frames(run_dir, episode)
    if not files:
        raise InputError("run_dir", str(run_dir), "a run directory with frames/NNNN.npz files")
    checkpoints = sorted(
        set(int(n) for n in (checkpoints or default_checkpoints(len(files), episode.num_initial)))
    )
    checkpoints = [n for n in checkpoints if 1 <= n <= len(files)] or [len(files)]
    params = tsdf or TsdfParams.for_level(getattr(scene, "level", episode.level))
    tau = float(scene.tau)
    timings = {"reference": 0.0, "tsdf": 0.0, "mesh": 0.0, "surface": 0.0, "render": 0.0}

    t0 = time.perf_counter()
    reference = ReferenceSurface(scene.ground_truth_mesh(), num_surface_points, SURFACE_SEED)
    eval_poses = np.asarray(scene.eval_views, dtype=np.float64).reshape(-1, 4, 4)
    images: list[np.ndarray] = []
    masks: list[np.ndarray] = []
    K_eval = np.eye(3)
    if len(eval_poses):
        K_eval, images, masks = reference_images(
            scene, renderer_factory or _sim_renderer, eval_width, eval_height, hfov_deg
        )
    timings["reference"] = time.perf_counter() - t0

    fusion = TsdfFusion(params, scene.roi_min, scene.roi_max)
    curve = []
    mesh = None
    for n in checkpoints:
        t = time.perf_counter()
        for path in files[fusion.num_frames : n]:
            frame = read_frame(path)
            depth, confidence = reconstruction_input(frame, depth_source)
            fusion.integrate(frame.rgb, depth, frame.K, frame.T_world_cam, confidence)
        timings["tsdf"] += time.perf_counter() - t
        t = time.perf_counter()
        mesh = fusion.extract_mesh()
        timings["mesh"] += time.perf_counter() - t
        t = time.perf_counter()
        surface = MeshRenderer(mesh)  # one ray-casting scene for the distances and the images
        row: dict[str, Any] = {"num_views": n, **reference.compare(mesh, tau, surface)}
        timings["surface"] += time.perf_counter() - t
        t = time.perf_counter()
        if images:
            row.update(image_metrics(surface, K_eval, eval_poses, images, masks))
        timings["render"] += time.perf_counter() - t
        curve.append(row)

    result = {
        "scene": episode.scene,
        "policy": episode.policy,
        "seed": episode.seed,
        "level": episode.level,
        "mode": episode.mode,
        "depth_source": depth_source,
        "tau": tau,
        "num_views": len(files),
        "num_initial": episode.num_initial,
        "final": curve[-1],
        "curve": curve,
        "eval": {
            "num_eval_views": len(eval_poses),
            "eval_width": eval_width,
            "eval_height": eval_height,
            "hfov_deg": hfov_deg,
            "num_surface_points": num_surface_points,
            "tsdf": {k: getattr(params, k) for k in params.__dataclass_fields__},
        },
        "timings_s": timings,
    }
    if write:
        out = run_dir / EVAL_DIR
        out.mkdir(exist_ok=True)
        if mesh is not None and len(mesh.triangles) > 0:
            o3d.io.write_triangle_mesh(str(out / MESH_FILE), mesh)
        np.save(
            out / "gt_sample.npy",
            reference.points[:: max(1, len(reference.points) // GT_PREVIEW_POINTS)].astype(
                np.float32
            ),
        )
        write_json(run_dir / METRICS_FILE, result, indent=2)
    return result
