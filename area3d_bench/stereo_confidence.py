"""`area3d bench stereo-confidence`: fit the stereo backend's calibrated confidence, and show how
well each confidence says whether a depth is right.

For each scene (the four bundled object scenes by default), the initial and held-out views are
rendered as a stereo pair with the simulator's read noise (`sim_bridge` defaults: 640x480, 90
degree FOV, `STEREO_BASELINE`, 1 grey level) and matched with the backend's defaults. A pixel with an
estimate is right when its depth is within 1 cm + 1 % of the renderer's exact depth. A logistic
regression of right on `calibration_features` (ln disparity, ln(1 + spread), valid share; scipy's
L-BFGS on standardised features) gives the four numbers of `StereoParams.calibration`, printed to
paste. Per scene the table shows, for the matcher's confidence and the calibrated one, the area
under the ROC curve of confidence against right (0.5: says nothing; 1: separates them) and the
share right per calibrated-confidence bin (a calibrated confidence has each bin's share inside it).
A camera other than the simulator's needs its own fit: pairs of it with a reference depth.
"""

from __future__ import annotations

import numpy as np
from rich.console import Console
from rich.table import Table
from scipy.optimize import minimize
from scipy.stats import rankdata

from area3d_eval.depth_metrics import depth_right
from area3d_perception.stereo import (
    CALIBRATION,
    StereoMatcher,
    StereoParams,
    calibration_features,
    confidence_of_features,
)
from sim_bridge.camera import STEREO_BASELINE, SimCamera
from sim_bridge.scenes import load_scene

FIT_SCENES = ("single_object", "five_objects", "clutter7_a", "scanned_objects")
IMAGE_NOISE = 1.0  # grey levels: the simulated camera's default read noise
BINS = ((0.0, 0.3), (0.3, 0.5), (0.5, 0.7), (0.7, 0.85), (0.85, 1.0))
FIT_SAMPLES = 300_000  # pixels the regression is fitted on, drawn evenly over the scenes' pixels


def scene_samples(name: str, params: StereoParams | None = None) -> dict:
    """Every estimated pixel of the scene's initial and held-out views: {"features" (N, 3),
    "right" (N,) bool, "matcher" (N,) the matcher's confidence}."""
    params = params or StereoParams()
    scene = load_scene(name)
    camera = SimCamera(scene, stereo_baseline=STEREO_BASELINE, image_noise=IMAGE_NOISE)
    matcher = StereoMatcher(params)
    features, right, confidence = [], [], []
    try:
        for T in np.concatenate([scene.initial_views, scene.eval_views]):
            cap = camera.capture(T)
            if not cap.ok:
                continue
            out = matcher.match(cap.rgb, cap.rgb_right, camera.K[0, 0], STEREO_BASELINE)
            estimated = out.confidence > 0
            truth = cap.depth[estimated]
            ok = depth_right(out.depth[estimated], truth)
            features.append(calibration_features(out.disparity, params.downscale)[estimated])
            right.append(ok)
            confidence.append(out.weight[estimated])  # the matcher's, whatever the model
    finally:
        camera.close()
        matcher.close()
    return {
        "features": np.concatenate(features),
        "right": np.concatenate(right),
        "matcher": np.concatenate(confidence),
    }


def fit_logistic(features: np.ndarray, right: np.ndarray) -> tuple[float, ...]:
    """(w_1, ..., w_k, bias) of p(right) = sigmoid(w . x + bias) by maximum likelihood (scipy's
    L-BFGS on standardised features, mapped back to the raw ones)."""
    x = np.asarray(features, np.float64)
    y = np.asarray(right, np.float64)
    mean, std = x.mean(axis=0), x.std(axis=0) + 1e-12
    z = np.column_stack([(x - mean) / std, np.ones(len(x))])

    def loss(w: np.ndarray) -> tuple[float, np.ndarray]:
        t = z @ w
        value = np.mean(np.logaddexp(0.0, t) - y * t)
        grad = z.T @ (1.0 / (1.0 + np.exp(-t)) - y) / len(y)
        return float(value), grad

    w = minimize(loss, np.zeros(z.shape[1]), jac=True, method="L-BFGS-B").x
    weights = w[:-1] / std
    bias = w[-1] - float(np.sum(w[:-1] * mean / std))
    return (*(float(v) for v in weights), float(bias))


def auc(score: np.ndarray, right: np.ndarray) -> float:
    """Area under the ROC curve of `score` against `right` (the chance that a right pixel scores
    above a wrong one; ties count half): 0.5 when the score says nothing."""
    right = np.asarray(right, bool)
    n_right, n_wrong = int(right.sum()), int((~right).sum())
    if n_right == 0 or n_wrong == 0:
        return float("nan")
    ranks = rankdata(score)
    return float((ranks[right].sum() - n_right * (n_right + 1) / 2) / (n_right * n_wrong))


def run_bench(scenes: list[str] | None = None) -> dict:
    """Fit on `scenes` (FIT_SCENES), print the weights and the per-scene table; returns
    {"calibration": fitted, "scenes": {name: figures}}."""
    names = list(scenes or FIT_SCENES)
    samples = {name: scene_samples(name) for name in names}
    rng = np.random.default_rng(0)
    per_scene = max(1, FIT_SAMPLES // len(names))
    chosen = {
        n: rng.choice(len(s["right"]), min(per_scene, len(s["right"])), replace=False)
        for n, s in samples.items()
    }
    fitted = fit_logistic(
        np.concatenate([samples[n]["features"][chosen[n]] for n in names]),
        np.concatenate([samples[n]["right"][chosen[n]] for n in names]),
    )
    table = Table(title="stereo confidence against depth within 1 cm + 1 % (AUC: 0.5 says nothing)")
    for column in ("scene", "pixels", "right", "AUC matcher", "AUC calibrated", "AUC in use"):
        table.add_column(column, justify="left" if column == "scene" else "right")
    for lo, hi in BINS:
        table.add_column(f"right at {lo:g}-{hi:g} (share)", justify="right")
    figures = {}
    for name, s in samples.items():
        p = confidence_of_features(s["features"], fitted)
        in_use = confidence_of_features(s["features"], CALIBRATION)
        bins = []
        for lo, hi in BINS:
            inside = (p >= lo) & ((p < hi) | (hi >= 1.0))
            bins.append((float(s["right"][inside].mean()) if inside.any() else float("nan"),
                         float(inside.mean())))  # fmt: skip
        figures[name] = {
            "pixels": int(len(p)),
            "right": float(s["right"].mean()),
            "auc_matcher": auc(s["matcher"], s["right"]),
            "auc_calibrated": auc(p, s["right"]),
            "auc_in_use": auc(in_use, s["right"]),
            "bins": bins,
        }
        f = figures[name]
        table.add_row(
            name,
            str(f["pixels"]),
            f"{f['right']:.2f}",
            f"{f['auc_matcher']:.3f}",
            f"{f['auc_calibrated']:.3f}",
            f"{f['auc_in_use']:.3f}",
            *(f"{share:.2f} ({n:.0%})" for share, n in bins),
        )
    console = Console(width=max(Console().width, 160))
    console.print(table)
    console.print(
        "calibration (ln disparity, ln(1 + spread), valid share, bias): "
        + "(" + ", ".join(f"{v:.3f}" for v in fitted) + ")"
        + f"   in use: {CALIBRATION}"
    )  # fmt: skip
    return {"calibration": fitted, "scenes": figures}


if __name__ == "__main__":
    run_bench()
