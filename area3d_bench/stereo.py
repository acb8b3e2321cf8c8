"""`area3d bench stereo`: the stereo backend on the simulator's rectified pairs, per bundled scene.

For each scene, the initial views and the first held-out views are rendered as a stereo pair
(sim_bridge, 640x480, 90 degree FOV, `STEREO_BASELINE`) and matched by the perception core
(`FrameEstimator("stereo")`). Figures: time per frame (SGBM on both images + confidence) against a
60 ms target on 2 CPU cores; depth error against the renderer's exact depth (median absolute
relative error, share of pixels off by more than 5 %, density = share of the true depth's pixels
that get an estimate); and how well confidence ranks error: AUSE of the absolute relative error
(0 = perfect ranking), beside the AUSE of a random ranking and the error left when the 50 % least
confident estimates are removed; and the share of the true depth's pixels estimated within 1 cm
(what the reconstruction's completion at tau = 1 cm is made of). Each scene runs twice: the
defaults, and beside them `REFERENCE`, the configuration before full-size "3way" matching.
"""

from __future__ import annotations

import time

import numpy as np
from rich.console import Console
from rich.table import Table

from area3d_eval.depth_metrics import ause, depth_errors, sparsification_curve
from area3d_perception.estimator import FrameEstimator
from area3d_perception.stereo import StereoParams
from sim_bridge.camera import STEREO_BASELINE, SimCamera
from sim_bridge.scenes import list_scenes, load_scene

TARGET_MS = 60.0  # stereo depth per 640x480 frame on a 2-core machine (issue 14)
HELD_OUT_VIEWS = 6  # held-out views per scene besides O_0 (room scenes: O_0 has 15 views)
# the defaults until full-size "3way" matching: OpenCV's one-pass SGBM at half size, unrefined
REFERENCE = StereoParams(mode="sgbm", downscale=2, num_disparities=64, refine=False)


def _views(scene, max_views: int) -> np.ndarray:
    views = np.concatenate([scene.initial_views, scene.eval_views[:HELD_OUT_VIEWS]])
    return views[:max_views]


def bench_scene(
    name: str,
    max_views: int = 10,
    baseline: float = STEREO_BASELINE,
    params: StereoParams | None = None,
) -> dict:
    """Figures of one scene: {"ms": [...], "median_abs_rel", "share_off", "density", "ause", ...}."""
    scene = load_scene(name)
    camera = SimCamera(scene, stereo_baseline=baseline)
    estimator = FrameEstimator("stereo", stereo=params)
    times, errors, confidences, densities, within_cm = [], [], [], [], []
    try:
        for T in _views(scene, max_views):
            cap = camera.capture(T)
            if not cap.ok:
                continue
            t = time.perf_counter()
            out = estimator.process(
                cap.rgb, None, camera.K, T, right=cap.rgb_right, baseline=baseline
            )
            times.append((time.perf_counter() - t) * 1e3)
            err = depth_errors(out.depth, cap.depth, out.confidence)
            errors.append(err.abs_rel)
            confidences.append(err.confidence)
            densities.append(err.density)
            truth = np.isfinite(cap.depth) & (cap.depth > 0)
            with np.errstate(invalid="ignore"):
                close = np.abs(out.depth[truth] - cap.depth[truth]) < 0.01  # NaN compares False
            within_cm.append(float(close.mean()))
    finally:
        camera.close()
        estimator.matcher.close()
    abs_rel, conf = np.concatenate(errors), np.concatenate(confidences)
    rng = np.random.default_rng(0)
    half = sparsification_curve(abs_rel, conf, 2)[1]  # mean error of the 50 % most confident
    return {
        "level": scene.level,
        "views": len(times),
        "ms": times[1:] if len(times) > 1 else times,  # the first frame warms up OpenCV's pools
        "median_abs_rel": float(np.median(abs_rel)),
        "share_off": float(np.mean(abs_rel > 0.05)),
        "density": float(np.mean(densities)),
        "within_1cm": float(np.mean(within_cm)),
        "mean_abs_rel": float(np.mean(abs_rel)),
        "mean_abs_rel_half": float(half),
        "ause": ause(abs_rel, conf),
        "ause_random": ause(abs_rel, rng.random(abs_rel.size)),
    }


def _config(params: StereoParams) -> str:
    return f"{params.mode}, 1/{params.downscale}, {params.num_disparities} disp."


def run_bench(
    scenes: list[str] | None = None, max_views: int = 10, params: StereoParams | None = None
) -> dict:
    """Every bundled scene (or `scenes`) with `params` (the defaults) and with `REFERENCE`; prints
    the table and returns {scene: {"default": figures, "reference": figures}}."""
    params = params or StereoParams()
    results = {
        name: {
            "default": bench_scene(name, max_views, params=params),
            "reference": bench_scene(name, max_views, params=REFERENCE),
        }
        for name in scenes or list_scenes()
    }
    table = Table(
        title=f"stereo backend: 640x480, baseline {STEREO_BASELINE * 100:.0f} cm, SGBM "
        f"({_config(params)}) + confidence, beside the reference ({_config(REFERENCE)})"
    )
    for column in (
        "scene",
        "config",
        "views",
        "ms/frame (median, p10-p90)",
        "target ms",
        "time / ref.",
        "median |rel| err",
        "off > 5 %",
        "within 1 cm",
        "density",
        "AUSE (random)",
        "mean err all / 50 % most confident",
    ):
        table.add_column(column, justify="left" if column in ("scene", "config") else "right")
    for name, pair in results.items():
        ref_ms = np.median(pair["reference"]["ms"])
        for which, config in (("default", params), ("reference", REFERENCE)):
            r = pair[which]
            ms = np.asarray(r["ms"])
            style = "green" if np.median(ms) <= TARGET_MS else "red"
            table.add_row(
                name if which == "default" else "",
                _config(config),
                str(r["views"]),
                f"[{style}]{np.median(ms):.0f}[/{style}] ({np.percentile(ms, 10):.0f}-"
                f"{np.percentile(ms, 90):.0f})",
                f"{TARGET_MS:.0f}",
                f"{np.median(ms) / ref_ms:.2f}x",
                f"{100 * r['median_abs_rel']:.2f} %",
                f"{100 * r['share_off']:.1f} %",
                f"{100 * r['within_1cm']:.0f} %",
                f"{100 * r['density']:.0f} %",
                f"{r['ause']:.4f} ({r['ause_random']:.4f})",
                f"{100 * r['mean_abs_rel']:.2f} % / {100 * r['mean_abs_rel_half']:.2f} %",
            )
    Console(width=max(Console().width, 180)).print(table)
    return results


if __name__ == "__main__":
    run_bench()
