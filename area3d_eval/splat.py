"""The paper's evaluation path: 3D Gaussian Splatting trained on the selected views, scored by
PSNR / SSIM / LPIPS at held-out views (gsplat on a CUDA GPU).

torch, gsplat and lpips are imported only when training or evaluating; without them, or without
CUDA, the functions raise SplatUnavailable saying what to install. The pure-numpy parts (Gaussian
initialisation from the RGB-D frames, camera conversion) work everywhere.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from area3d_msgs_py.backproject import backproject
from area3d_msgs_py.errors import InputError

INSTALL_HINT = 'pip install -e ".[ml]" gsplat lpips  (on a machine with an NVIDIA GPU and CUDA)'
SH_C0 = 0.28209479177387814  # zeroth spherical-harmonic basis constant, 1 / (2 sqrt(pi))
INIT_MAX_POINTS = 200_000  # initial Gaussians, subsampled from all back-projected pixels
INIT_OPACITY = 0.1  # initial opacity of every Gaussian (3DGS, Kerbl et al. 2023)
INIT_SCALE_NEIGHBOURS = 3  # initial scale = mean distance to the 3 nearest points (3DGS)
SH_DEGREE = 3  # view-dependent colour degree (3DGS)
TRAIN_ITERS = 7_000  # 3DGS's short schedule; the paper does not give its count
SSIM_LAMBDA = 0.2  # loss = (1 - l) L1 + l (1 - SSIM) (3DGS)
DEPTH_LAMBDA = 0.1  # weight of an L1 loss on the rendered depth where the sensor has a return
LPIPS_NET = "alex"  # LPIPS backbone most novel-view-synthesis papers report


class SplatUnavailable(RuntimeError):
    """The Gaussian-splatting path needs torch, gsplat, lpips and a CUDA GPU."""


def _require(device: str = "cuda") -> tuple[Any, Any]:
    """(torch, gsplat) or SplatUnavailable naming what is missing."""
    try:
        import torch
    except ImportError as exc:
        raise SplatUnavailable(f"Gaussian splatting needs torch: {INSTALL_HINT}") from exc
    try:
        import gsplat
    except ImportError as exc:
        raise SplatUnavailable(
            f"Gaussian splatting needs the gsplat package: {INSTALL_HINT}"
        ) from exc
    if str(device).startswith("cuda") and not torch.cuda.is_available():
        raise SplatUnavailable(
            f"Gaussian splatting needs a CUDA GPU (torch sees none): {INSTALL_HINT}"
        )
    return torch, gsplat


def init_points_from_frames(
    frames: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    max_points: int = INIT_MAX_POINTS,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Back-project every pixel with a return: (points (N, 3) float32 world metres, colours (N, 3)
    float32 in [0, 1]), at most `max_points` of them (uniform random subsample, fixed seed).

    frames: (rgb (H, W, 3) uint8, depth (H, W) float32 NaN = no return, K (3, 3), T_world_cam (4, 4)).
    """
    points, colours = [], []
    for rgb, depth, K, T in frames:
        world, pixel = backproject(depth, K, T)
        points.append(world)
        colours.append(np.asarray(rgb).reshape(-1, 3)[pixel].astype(np.float64) / 255.0)
    if not points or sum(len(p) for p in points) == 0:
        raise InputError(
            "frames",
            "no pixel with a finite depth",
            "at least one depth return to start the Gaussians from",
        )
    pts, cols = np.concatenate(points), np.concatenate(colours)
    if len(pts) > max_points:
        keep = np.random.default_rng(seed).choice(len(pts), size=max_points, replace=False)
        pts, cols = pts[keep], cols[keep]
    return pts.astype(np.float32), cols.astype(np.float32)


def initial_scales(points: np.ndarray, neighbours: int = INIT_SCALE_NEIGHBOURS) -> np.ndarray:
    """(N,) float32 isotropic scale per point: mean distance to its `neighbours` nearest others
    (3DGS's initialisation), floored at 1e-4 m for duplicated points."""
    from scipy.spatial import cKDTree

    k = min(neighbours + 1, len(points))
    if k < 2:
        return np.full(len(points), 0.01, np.float32)
    dist, _ = cKDTree(points).query(points, k=k, workers=-1)
    return np.maximum(dist[:, 1:].mean(axis=1), 1e-4).astype(np.float32)


def rgb_to_sh0(colours: np.ndarray) -> np.ndarray:
    """Zeroth-order SH coefficient (N, 3) whose rendered colour is `colours` (N, 3) in [0, 1]."""
    return (np.asarray(colours, dtype=np.float32) - 0.5) / SH_C0


def cameras_to_gsplat(
    poses: np.ndarray, Ks: np.ndarray | Sequence[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """(viewmats (C, 4, 4) float32 world-to-camera, Ks (C, 3, 3) float32) for gsplat.rasterization.

    poses (C, 4, 4) T_world_cam of optical frames: gsplat's camera is the same OpenCV frame (x right,
    y down, z forward), so a viewmat is the inverse pose. gsplat samples pixel centres at
    (u + 0.5, v + 0.5), our convention, so K is passed unchanged.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim == 2:
        poses = poses[None]
    Ks = np.asarray(Ks, dtype=np.float64)
    if Ks.ndim == 2:
        Ks = np.broadcast_to(Ks, (len(poses), 3, 3))
    if poses.shape[1:] != (4, 4) or Ks.shape != (len(poses), 3, 3):
        raise InputError(
            "poses/Ks",
            (poses.shape, Ks.shape),
            "(C, 4, 4) poses and (C, 3, 3) or (3, 3) intrinsics",
        )
    R = poses[:, :3, :3]
    t = poses[:, :3, 3]
    view = np.zeros_like(poses)
    view[:, :3, :3] = np.transpose(R, (0, 2, 1))
    view[:, :3, 3] = -np.einsum("cji,cj->ci", R, t)
    view[:, 3, 3] = 1.0
    return view.astype(np.float32), Ks.astype(np.float32)


@dataclass
class GaussianModel:
    """Trained Gaussians: `params` is gsplat's dict (means, scales (log), quats, opacities (logit),
    sh0, shN) of torch parameters on `device`."""

    params: Any
    device: str
    sh_degree: int = SH_DEGREE
    history: list[float] = field(default_factory=list)

    @property
    def num_gaussians(self) -> int:
        return int(self.params["means"].shape[0])


def _frames_list(
    frames: Iterable[Any],
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    out = [tuple(f) for f in frames]
    if not out:
        raise InputError("frames", "0 frames", "at least one (rgb, depth, K, T_world_cam) frame")
    return out


def _render(
    torch: Any,
    gsplat: Any,
    model: GaussianModel,
    viewmats: Any,
    Ks: Any,
    width: int,
    height: int,
    sh_degree: int,
) -> tuple[Any, Any, Any, dict]:
    p = model.params
    colours = torch.cat([p["sh0"], p["shN"]], dim=1)
    out, alphas, info = gsplat.rasterization(
        means=p["means"],
        quats=p["quats"],
        scales=torch.exp(p["scales"]),
        opacities=torch.sigmoid(p["opacities"]),
        colors=colours,
        viewmats=viewmats,
        Ks=Ks,
        width=width,
        height=height,
        sh_degree=sh_degree,
        render_mode="RGB+ED",
    )
    return out[..., :3], out[..., 3], alphas, info


def _torch_ssim(torch: Any, a: Any, b: Any) -> Any:
    """Mean SSIM of (B, 3, H, W) images in [0, 1], 11 x 11 Gaussian window, sigma 1.5."""
    import torch.nn.functional as F

    x = torch.arange(11, device=a.device, dtype=a.dtype) - 5
    g = torch.exp(-(x**2) / (2 * 1.5**2))
    g = g / g.sum()
    window = (g[:, None] * g[None, :]).expand(3, 1, 11, 11).contiguous()

    def blur(t: Any) -> Any:
        return F.conv2d(t, window, groups=3)

    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a**2
    var_b = blur(b * b) - mu_b**2
    cov = blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / (
        (mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2)
    )
    return s.mean()


def train_gaussians(
    frames: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    iters: int = TRAIN_ITERS,
    device: str = "cuda",
    seed: int = 0,
    max_points: int = INIT_MAX_POINTS,
    depth_lambda: float = DEPTH_LAMBDA,
) -> GaussianModel:
    """Fit 3D Gaussians to the captured RGB-D frames (rgb, depth, K, T_world_cam) with gsplat.

    Gaussians start at the back-projected pixels (colour = pixel colour, scale = neighbour spacing,
    opacity 0.1); loss = 0.8 L1 + 0.2 (1 - SSIM) on colour plus depth_lambda x L1 on depth where the
    sensor has a return; 3DGS densification (gsplat DefaultStrategy). Raises SplatUnavailable without
    torch / gsplat / CUDA.
    """
    torch, gsplat = _require(device)
    frames = _frames_list(frames)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    points, colours = init_points_from_frames(frames, max_points, seed)
    n = len(points)
    scene_scale = float(np.linalg.norm(points - points.mean(axis=0), axis=1).max()) * 1.1
    num_sh = (SH_DEGREE + 1) ** 2
    quats = rng.normal(size=(n, 4)).astype(np.float32)
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)

    def param(array: np.ndarray) -> Any:
        return torch.nn.Parameter(torch.as_tensor(array, device=device))

    params = torch.nn.ParameterDict(
        {
            "means": param(points),
            "scales": param(np.repeat(np.log(initial_scales(points))[:, None], 3, axis=1)),
            "quats": param(quats),
            "opacities": param(np.full(n, np.log(INIT_OPACITY / (1 - INIT_OPACITY)), np.float32)),
            "sh0": param(rgb_to_sh0(colours)[:, None, :]),
            "shN": param(np.zeros((n, num_sh - 1, 3), np.float32)),
        }
    )
    # learning rates of gsplat's simple_trainer (3DGS), means scaled by the scene size
    lrs = {
        "means": 1.6e-4 * scene_scale,
        "scales": 5e-3,
        "quats": 1e-3,
        "opacities": 5e-2,
        "sh0": 2.5e-3,
        "shN": 2.5e-3 / 20,
    }
    optimizers = {
        k: torch.optim.Adam([{"params": params[k], "lr": lr, "name": k}], eps=1e-15)
        for k, lr in lrs.items()
    }
    means_decay = 0.01 ** (1.0 / max(iters, 1))  # means' lr decays 100x over training (3DGS)
    strategy = gsplat.DefaultStrategy(refine_stop_iter=int(iters * 0.5))
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=scene_scale)

    poses = np.stack([np.asarray(f[3]) for f in frames])
    viewmats, Ks = cameras_to_gsplat(poses, np.stack([np.asarray(f[2]) for f in frames]))
    viewmats_t = torch.as_tensor(viewmats, device=device)
    Ks_t = torch.as_tensor(Ks, device=device)
    images = [torch.as_tensor(np.asarray(f[0]), device=device).float() / 255.0 for f in frames]
    depths = [
        torch.as_tensor(np.nan_to_num(np.asarray(f[1], np.float32), nan=0.0), device=device)
        for f in frames
    ]
    model = GaussianModel(params=params, device=device)
    for step in range(iters):
        i = int(rng.integers(len(frames)))
        h, w = images[i].shape[:2]
        rgb, depth, _, info = _render(
            torch,
            gsplat,
            model,
            viewmats_t[i : i + 1],
            Ks_t[i : i + 1],
            w,
            h,
            min(step // 1000, SH_DEGREE),
        )
        strategy.step_pre_backward(params, optimizers, state, step, info)
        target = images[i][None]
        l1 = (rgb - target).abs().mean()
        ssim_term = 1.0 - _torch_ssim(torch, rgb.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2))
        loss = (1 - SSIM_LAMBDA) * l1 + SSIM_LAMBDA * ssim_term
        valid = depths[i] > 0
        if depth_lambda > 0 and bool(valid.any()):
            loss = loss + depth_lambda * (depth[0][valid] - depths[i][valid]).abs().mean()
        loss.backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        for group in optimizers["means"].param_groups:
            group["lr"] *= means_decay
        strategy.step_post_backward(params, optimizers, state, step, info)
        if step % 100 == 0:
            model.history.append(float(loss.detach()))
    return model


def evaluate_gaussians(
    model: GaussianModel,
    poses: np.ndarray,
    K: np.ndarray,
    images: Sequence[np.ndarray],
    masks: Sequence[np.ndarray] | None = None,
) -> dict[str, float]:
    """Mean PSNR / SSIM (this package's numpy definitions) and LPIPS (AlexNet) of the Gaussians
    rendered at held-out `poses` (M, 4, 4) with intrinsics K (3, 3) against `images` (M of (H, W, 3)
    uint8). LPIPS needs the `lpips` package (its AlexNet weights come from torchvision's cache).
    Also returns the rendered images under "renders" (list of uint8 arrays)."""
    torch, gsplat = _require(model.device)
    try:
        import lpips
    except ImportError as exc:
        raise SplatUnavailable(f"LPIPS needs the lpips package: {INSTALL_HINT}") from exc
    from area3d_eval.metrics import psnr, ssim

    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(images) != len(poses):
        raise InputError("images", f"{len(images)} images", f"one per pose ({len(poses)})")
    viewmats, Ks = cameras_to_gsplat(poses, K)
    metric = lpips.LPIPS(net=LPIPS_NET, verbose=False).to(model.device)
    scores: dict[str, list[float]] = {"psnr": [], "ssim": [], "lpips": []}
    renders = []
    with torch.no_grad():
        for i, ref in enumerate(images):
            h, w = ref.shape[:2]
            vm = torch.as_tensor(viewmats[i : i + 1], device=model.device)
            ks = torch.as_tensor(Ks[i : i + 1], device=model.device)
            rgb, _, _, _ = _render(torch, gsplat, model, vm, ks, w, h, model.sh_degree)
            out = (rgb[0].clamp(0, 1) * 255).round().byte().cpu().numpy()
            renders.append(out)
            mask = None if masks is None else masks[i]
            scores["psnr"].append(psnr(out, ref, mask))
            scores["ssim"].append(ssim(out, ref, mask))
            a = rgb[0].clamp(0, 1).permute(2, 0, 1)[None] * 2 - 1  # LPIPS takes [-1, 1]
            b = torch.as_tensor(ref, device=model.device).float().permute(2, 0, 1)[None] / 127.5 - 1
            scores["lpips"].append(float(metric(a, b).mean()))
    result: dict[str, Any] = {k: float(np.mean(np.minimum(v, 100.0))) for k, v in scores.items()}
    result["renders"] = renders
    return result
