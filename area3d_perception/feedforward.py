"""Feed-forward multi-view depth + confidence backends (VGGT, Depth Anything 3) and their alignment.

The models predict depth up to an unknown scale and a raw confidence C >= 1 per pixel (VGGT's
depth head activates confidence as 1 + exp(x)). Before the depth is used it is brought to metres,
either by the median ratio to a metric depth image of the same view (`align_depth_median`) or by a
Sim(3) fit of the predicted camera centres to the known ones (`align_scale_to_poses`, Umeyama
1991). The confidence is mapped to [0, 1] by `normalize_confidence`.

torch, vggt and depth_anything_3 are imported only when a backend is constructed; the pure numpy
parts here work without them.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from area3d_msgs_py.errors import InputError

# VGGT's training resolution: images are resized to 518 px on the long side, sides multiple of 14
# (its ViT patch size), as in vggt.utils.load_fn.load_and_preprocess_images.
VGGT_RESOLUTION = 518
VGGT_PATCH = 14
# Percentiles of log C used by the "percentile" normalisation (our choice: robust to outliers).
PERCENTILE_RANGE = (5.0, 95.0)

INSTALL_HINT = (
    'pip install -e ".[ml]" (torch), then pip install git+https://github.com/facebookresearch/vggt'
)
DA3_INSTALL_HINT = 'pip install -e ".[ml]" (torch), then pip install depth-anything-3'


class BackendUnavailableError(RuntimeError):
    """A feed-forward backend cannot start: a package or the weights are missing."""


def normalize_confidence(confidence: np.ndarray, method: str = "inverse") -> np.ndarray:
    """Map a raw confidence C >= 1 to [0, 1], monotonically (the paper's "simple normalisation").

    confidence: (..., H, W) raw C; NaN or C <= 1 means no confidence.
    method: "inverse" (default): 1 - 1/C, a fixed map with C = 1 -> 0, C = 2 -> 0.5, C -> inf -> 1,
    comparable across images and frames; "percentile": per image, log C scaled linearly so that
    its 5th percentile maps to 0 and its 95th to 1 (clipped), which spreads the values of one image
    but is not comparable across images.
    Returns float32 of the same shape, in [0, 1], 0 where C is NaN or <= 1.
    """
    c = np.asarray(confidence, dtype=np.float32)
    c = np.where(np.isfinite(c) | (c == np.inf), c, np.float32(1.0))
    c = np.maximum(c, np.float32(1.0))
    if method == "inverse":
        return (1.0 - 1.0 / c).astype(np.float32)
    if method == "percentile":
        if c.ndim < 2:
            raise InputError(
                "confidence", f"shape {c.shape}", "(..., H, W) for per-image percentiles"
            )
        log_c = np.log(np.minimum(c, np.finfo(np.float32).max))
        lo, hi = np.percentile(log_c, PERCENTILE_RANGE, axis=(-2, -1), keepdims=True)
        span = np.maximum(hi - lo, 1e-6)
        out = np.clip((log_c - lo) / span, 0.0, 1.0).astype(np.float32)
        out[c <= 1.0] = 0.0
        return out
    raise InputError("method", method, 'one of "inverse", "percentile"')


def align_scale_to_poses(
    pred_centres: np.ndarray, known_centres: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares Sim(3) with known ~= s R pred + t (Umeyama 1991).

    pred_centres: (N, 3) predicted camera centres (model frame, arbitrary scale).
    known_centres: (N, 3) the same cameras' centres in `world`, metres. N >= 3 and not collinear for
    a unique rotation; the scale is defined from N >= 2 distinct centres.
    Returns (s float, R (3, 3), t (3,)).
    """
    src = np.asarray(pred_centres, dtype=np.float64)
    dst = np.asarray(known_centres, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape[0] < 2:
        raise InputError("pred_centres", f"shape {src.shape}", "an (N, 3) array with N >= 2")
    if dst.shape != src.shape:
        raise InputError(
            "known_centres", f"shape {dst.shape}", f"the shape of pred_centres {src.shape}"
        )
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise InputError("pred_centres/known_centres", "non-finite values", "finite coordinates")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = float((xs**2).sum()) / len(src)
    if var_s <= 1e-12 or float((xd**2).sum()) <= 1e-12:
        raise InputError(
            "pred_centres", "coincident centres", "at least two distinct camera centres"
        )
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_s)
    t = mu_d - s * R @ mu_s
    return s, R, t


def align_depth_median(pred_depth: np.ndarray, metric_depth: np.ndarray) -> float:
    """Scale s with metric ~= s * pred: the median of metric / pred over pixels valid in both.

    pred_depth, metric_depth: (H, W) depth of the same view (pred in model units, metric in metres,
    NaN = missing). The median ignores outliers (edges, dropouts) that a mean would not.
    """
    pred = np.asarray(pred_depth, dtype=np.float64)
    metric = np.asarray(metric_depth, dtype=np.float64)
    if pred.shape != metric.shape:
        raise InputError(
            "metric_depth", f"shape {metric.shape}", f"the shape of pred_depth {pred.shape}"
        )
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = np.isfinite(pred) & np.isfinite(metric) & (pred > 0) & (metric > 0)
    if not ok.any():
        raise InputError("metric_depth", "no pixel valid in both", "overlapping finite depths > 0")
    return float(np.median(metric[ok] / pred[ok]))


def apply_alignment(depths: Sequence[np.ndarray] | np.ndarray, scale: float) -> list[np.ndarray]:
    """Predicted depth maps rescaled to metres: D_metric = s * D_pred (rotation and translation of a
    Sim(3) do not change depth along each camera's own optical axis). Returns float32 maps."""
    if not (np.isfinite(scale) and scale > 0):
        raise InputError("scale", scale, "a finite scale > 0")
    return [(np.asarray(d, dtype=np.float32) * np.float32(scale)) for d in depths]


@dataclass
class FeedForwardOutput:
    """One multi-view prediction, resized to the input images.

    depth: list of (H, W) float32 in model units; confidence: list of (H, W) float32 raw C >= 1;
    cam_centres: (N, 3) predicted camera centres in the model frame (None when not predicted).
    """

    depth: list[np.ndarray]
    confidence: list[np.ndarray]
    cam_centres: np.ndarray | None


def _missing_parts(
    modules: Sequence[str], weights: Path | None, weights_what: str, directory: bool = False
) -> list[str]:
    """What a backend lacks: its packages, and its weights (a file, or a `directory`) where
    `weights` says."""
    missing = [f"python package `{m}`" for m in modules if importlib.util.find_spec(m) is None]
    there = weights is not None and (weights.is_dir() if directory else weights.is_file())
    if weights is not None and not there:
        kind = "a directory" if directory else "a file"
        found = "a file is there" if weights.is_file() else "a directory is there"
        found = found if weights.exists() else "not found there"
        missing.append(f"{weights_what} at '{weights}' ({kind}; {found})")
    return missing


def _load_weights(backend: str, path: Path, what: str, load):
    """`load()`, the weights at `path` read by the model's own code; any failure there (a file
    that is no checkpoint, another model's, a torn download) is BackendUnavailableError naming
    the path: the node says it cannot start instead of ending in a traceback."""
    try:
        return load()
    except Exception as exc:
        raise BackendUnavailableError(
            f"{backend} backend cannot start: {path} is not {what} this backend can load "
            f"({type(exc).__name__}: {str(exc)[:300]})"
        ) from exc


def _check_images(images: Sequence[np.ndarray]) -> None:
    if len(images) == 0:
        raise InputError("images", "an empty list", "one or more (H, W, 3) uint8 images")
    for n, image in enumerate(images):
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise InputError(
                f"images[{n}]", f"{image.dtype} {image.shape}", "an (H, W, 3) uint8 rgb image"
            )


def _pick_device(torch, device: str) -> str:
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return device


def vggt_input_size(height: int, width: int) -> tuple[int, int]:
    """(h, w) VGGT runs at for an (height, width) image: long side 518, both multiples of 14."""
    scale = VGGT_RESOLUTION / max(height, width)
    h = max(VGGT_PATCH, int(round(height * scale / VGGT_PATCH)) * VGGT_PATCH)
    w = max(VGGT_PATCH, int(round(width * scale / VGGT_PATCH)) * VGGT_PATCH)
    return h, w


class VggtBackend:
    """VGGT (Wang et al., CVPR 2025) from a local checkpoint; never downloads.

    checkpoint: path of `model.pt` from the Hugging Face repository facebook/VGGT-1B.
    device: "auto" (cuda if available, else cpu), "cuda", "cpu", ...
    """

    def __init__(self, checkpoint: str, device: str = "auto") -> None:
        path = (
            Path(checkpoint).expanduser() if checkpoint else Path("<checkpoint parameter is empty>")
        )
        missing = _missing_parts(("torch", "vggt"), path, "the VGGT checkpoint model.pt")
        if missing:
            raise BackendUnavailableError(
                "vggt backend cannot start; missing: "
                + "; ".join(missing)
                + f". Install: {INSTALL_HINT}. Weights: download model.pt from the Hugging Face "
                "repository facebook/VGGT-1B and pass its path as the `checkpoint` parameter."
            )
        import torch
        from vggt.models.vggt import VGGT

        self._torch = torch
        self.device = _pick_device(torch, device)
        model = VGGT()
        _load_weights(
            "vggt",
            path,
            "a VGGT-1B checkpoint (model.pt of facebook/VGGT-1B)",
            lambda: model.load_state_dict(torch.load(str(path), map_location="cpu")),
        )
        self.model = model.to(self.device).eval()

    def predict_views(self, images: Sequence[np.ndarray]) -> FeedForwardOutput:
        """Depth, raw confidence and camera centres for N views of one scene, in one forward pass.

        images: N (H, W, 3) uint8 rgb images (any sizes; all are resized to VGGT's input size of
        the first). Outputs are resized back to each image's own size.
        """
        _check_images(images)
        torch = self._torch
        from vggt.utils.pose_enc import pose_encoding_to_extri_intri

        h, w = vggt_input_size(*images[0].shape[:2])
        batch = np.stack([cv2.resize(im, (w, h), interpolation=cv2.INTER_CUBIC) for im in images])
        x = torch.from_numpy(batch).permute(0, 3, 1, 2).float().div(255.0)[None].to(self.device)
        use_amp = self.device.startswith("cuda")
        dtype = (
            torch.bfloat16
            if use_amp and torch.cuda.get_device_capability()[0] >= 8
            else torch.float16
        )
        with torch.no_grad(), torch.autocast(device_type="cuda", dtype=dtype, enabled=use_amp):
            tokens, ps_idx = self.model.aggregator(x)
            pose_enc = self.model.camera_head(tokens)[-1]
            depth, conf = self.model.depth_head(tokens, x, ps_idx)
        extrinsic, _ = pose_encoding_to_extri_intri(pose_enc, x.shape[-2:])
        depth = depth[0, ..., 0].float().cpu().numpy()
        conf = conf[0].float().cpu().numpy()
        E = extrinsic[0].float().cpu().numpy()  # (N, 3, 4) camera-from-world, OpenCV convention
        centres = -np.einsum("nji,nj->ni", E[:, :, :3], E[:, :, 3])
        return FeedForwardOutput(
            depth=[_resize_to(d, im, nearest=True) for d, im in zip(depth, images, strict=True)],
            confidence=[_resize_to(c, im) for c, im in zip(conf, images, strict=True)],
            cam_centres=centres,
        )


class DepthAnything3Backend:
    """Depth Anything 3 (`depth-anything-3` on PyPI) from a local model directory; never downloads.

    model_dir: a directory holding a DA3 model's config and weights (as saved from its Hugging Face
    repository, e.g. depth-anything/DA3-LARGE). device: "auto", "cuda", "cpu", ...
    """

    def __init__(self, model_dir: str, device: str = "auto") -> None:
        path = (
            Path(model_dir).expanduser() if model_dir else Path("<checkpoint parameter is empty>")
        )
        missing = _missing_parts(
            ("torch", "depth_anything_3"), path, "the Depth Anything 3 model directory", True
        )
        if missing:
            raise BackendUnavailableError(
                "depth_anything_3 backend cannot start; missing: "
                + "; ".join(missing)
                + f". Install: {DA3_INSTALL_HINT}. Weights: download a model repository such as "
                "depth-anything/DA3-LARGE from Hugging Face into a local directory and pass that "
                "directory as the `checkpoint` parameter."
            )
        import torch
        from depth_anything_3.api import DepthAnything3

        self.device = _pick_device(torch, device)
        model = _load_weights(
            "depth_anything_3",
            path,
            "a Depth Anything 3 model directory",
            lambda: DepthAnything3.from_pretrained(str(path)),
        )
        self.model = model.to(self.device).eval()

    def predict_views(self, images: Sequence[np.ndarray]) -> FeedForwardOutput:
        """Depth, raw confidence and camera centres for N views, resized back to the inputs."""
        _check_images(images)
        pred = self.model.inference([np.asarray(im) for im in images])
        E = np.asarray(pred.extrinsics, dtype=np.float64)  # (N, 3, 4) world-to-camera
        centres = -np.einsum("nji,nj->ni", E[:, :, :3], E[:, :, 3])
        return FeedForwardOutput(
            depth=[
                _resize_to(np.asarray(d), im, nearest=True)
                for d, im in zip(pred.depth, images, strict=True)
            ],
            confidence=[
                _resize_to(np.asarray(c), im) for c, im in zip(pred.conf, images, strict=True)
            ],
            cam_centres=centres,
        )


def _resize_to(array: np.ndarray, image: np.ndarray, nearest: bool = False) -> np.ndarray:
    # Depth is resized nearest-neighbour: interpolating across an occlusion edge would invent
    # flying pixels between the two surfaces. Confidence is smooth enough for bilinear.
    h, w = image.shape[:2]
    mode = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return cv2.resize(np.asarray(array, dtype=np.float32), (w, h), interpolation=mode)
