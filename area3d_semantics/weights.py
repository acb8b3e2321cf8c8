"""Per-image weight maps from VLM regions and the semantic uncertainty they modulate.

W_i(u) = sum_k alpha_type_k * beta_prio_k * s_size_k * M_k(u), normalised per image to [0, 1];
U_sem_i(u) = Norm(sigma_i(u) * (1 + lambda * W_i(u))) (paper, Eq. 4-5 and supplement Table 6).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields

import cv2
import numpy as np
from numba import njit

from area3d_msgs_py.errors import InputError
from area3d_msgs_py.param_fields import described, description_of
from area3d_semantics.masks import DEFAULT_DILATION, DEFAULT_TAPER_SIGMA, region_profiles
from area3d_semantics.region import PRIORITIES, SIZES, TYPES, Region


def _alpha() -> dict[str, float]:
    # Type weights are not published; start from the prompt's ranking (configurable).
    return {"OCCLUSION": 1.0, "GEOMETRIC": 1.0, "LIGHTING": 0.6, "BOUNDARY": 0.6, "TEXTURE": 0.3}


def _beta() -> dict[str, float]:
    # Priority weights: paper, supplement Table 6.
    return {"HIGH": 3.0, "MEDIUM": 1.5, "LOW": 0.5}


def _s() -> dict[str, float]:
    # Size weights: paper, supplement Table 6.
    return {"small": 0.8, "medium": 1.0, "large": 1.2}


def _size_extent() -> dict[str, float]:
    # The paper uses SIZE only through s; the mask keeps the cell's extent unless configured.
    return {"small": 1.0, "medium": 1.0, "large": 1.0}


@dataclass(frozen=True)
class SemanticParams:
    """Every tunable of the semantic field, paper values as defaults."""

    # Tables: one parameter per key ("{key}" in a description is the key).
    alpha: dict[str, float] = described(
        _alpha(), "type weight alpha of {key} regions (the prompt's ranking)", "", (0.0, 100.0)
    )
    beta: dict[str, float] = described(
        _beta(), "priority weight beta of {key} priority regions (paper)", "", (0.0, 100.0)
    )
    s: dict[str, float] = described(
        _s(), "size weight s of {key} regions (paper)", "", (0.0, 100.0)
    )
    lam: float = described(
        1.0, "modulation strength lambda in U_sem = Norm(sigma (1 + lambda W)) (paper)", "",
        (0.0, 100.0),
    )  # fmt: skip
    dilation: float = described(
        DEFAULT_DILATION, "dilation of a region's mask (masks.py)", "fraction of its grid cell",
        (0.0, 10.0),
    )  # fmt: skip
    taper_sigma: float = described(
        DEFAULT_TAPER_SIGMA, "Gaussian taper of a region's mask (masks.py)",
        "fraction of its grid cell", (0.0, 10.0),
    )  # fmt: skip
    size_extent: dict[str, float] = described(
        _size_extent(),
        "extent of the mask of {key} regions (the paper uses size only through s)",
        "fraction of its grid cell",
        (0.0, 10.0),
    )

    def __post_init__(self) -> None:
        for name, keys in (
            ("alpha", TYPES),
            ("beta", PRIORITIES),
            ("s", SIZES),
            ("size_extent", SIZES),
        ):
            table = getattr(self, name)
            if not isinstance(table, Mapping) or set(table) != set(keys):
                raise InputError(name, table, f"a table with exactly the keys {', '.join(keys)}")
            bad = {k: v for k, v in table.items() if not np.isfinite(v) or v < 0}
            if bad:
                raise InputError(name, bad, "finite values >= 0")
        for name in ("lam", "dilation", "taper_sigma"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise InputError(name, value, "a finite value >= 0")

    @classmethod
    def from_flat(cls, values: Mapping[str, float]) -> SemanticParams:
        """Build from flat ROS-style names: alpha_occlusion, beta_high, s_small, lambda, ...

        Unknown names raise InputError; missing names keep the defaults.
        """
        alpha, beta, s, extent = _alpha(), _beta(), _s(), _size_extent()
        scalars: dict[str, float] = {}
        scalar_names = {f.name for f in fields(cls)} - {"alpha", "beta", "s", "size_extent"}
        for key, value in values.items():
            prefix, _, rest = key.partition("_")
            if prefix == "alpha" and rest.upper() in alpha:
                alpha[rest.upper()] = float(value)
            elif prefix == "beta" and rest.upper() in beta:
                beta[rest.upper()] = float(value)
            elif prefix == "s" and rest in s:
                s[rest] = float(value)
            elif key.startswith("size_extent_") and key[12:] in extent:
                extent[key[12:]] = float(value)
            elif key in ("lambda", "lam"):
                scalars["lam"] = float(value)
            elif key in scalar_names:
                scalars[key] = float(value)
            else:
                raise InputError(
                    key,
                    value,
                    "a known semantic parameter (alpha_<type>, beta_<priority>, s_<size>, lambda, dilation, taper_sigma, size_extent_<size>)",
                )
        return cls(alpha=alpha, beta=beta, s=s, size_extent=extent, **scalars)

    @classmethod
    def flat_parameters(cls) -> list[tuple[str, float, str, tuple[float, float]]]:
        """(flat name, default, description with unit, range) of every tunable, the names of
        `to_flat`: what the semantics node declares."""
        defaults = cls().to_flat()
        out = []
        for f in fields(cls):
            flat = {"lam": "lambda"}.get(f.name, f.name)
            text, bounds = description_of(f), f.metadata["range"]
            if isinstance(getattr(cls(), f.name), Mapping):
                for key in getattr(cls(), f.name):
                    name = f"{flat}_{key.lower()}"
                    out.append((name, defaults[name], text.format(key=key), bounds))
            else:
                out.append((flat, defaults[flat], text, bounds))
        return out

    def to_flat(self) -> dict[str, float]:
        flat = {f"alpha_{k.lower()}": v for k, v in self.alpha.items()}
        flat |= {f"beta_{k.lower()}": v for k, v in self.beta.items()}
        flat |= {f"s_{k}": v for k, v in self.s.items()}
        flat |= {f"size_extent_{k}": v for k, v in self.size_extent.items()}
        return flat | {
            "lambda": self.lam,
            "dilation": self.dilation,
            "taper_sigma": self.taper_sigma,
        }


@njit(cache=True)
def _sum_of_outer_products(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(H, W) sum_k outer(a[:, k], b[k, :]) for a (H, K), b (K, W) C-contiguous.

    Single-threaded on purpose: with K ~ 8 a threaded BLAS matmul is dominated by thread start-up
    and, on a busy machine, runs 10x slower than this loop. The innermost loop runs along a
    contiguous row of b and of the output, so it vectorises.
    """
    h, k = a.shape
    w = b.shape[1]
    out = np.zeros((h, w), dtype=np.float32)
    for i in range(h):
        row = out[i]
        for r in range(k):
            ai = a[i, r]
            if ai != 0.0:
                br = b[r]
                for j in range(w):
                    row[j] += ai * br[j]
    return out


@njit(cache=True)
def _modulate(sigma: np.ndarray, weight: np.ndarray, lam: np.float32) -> np.ndarray:
    """sigma * (1 + lam * weight) divided by its largest finite value, in two passes over (H, W)."""
    flat_sigma, flat_weight = sigma.ravel(), weight.ravel()
    out = np.empty(flat_sigma.size, dtype=np.float32)
    peak = np.float32(0.0)
    for n in range(out.size):
        value = flat_sigma[n] * (np.float32(1.0) + lam * flat_weight[n])
        out[n] = value
        if np.isfinite(value) and value > peak:
            peak = value
    if peak > 0:
        for n in range(out.size):
            out[n] /= peak
    return out.reshape(sigma.shape)


def region_weight(region: Region, params: SemanticParams) -> float:
    """alpha_type * beta_priority * s_size of one region."""
    return params.alpha[region.type] * params.beta[region.priority] * params.s[region.size]


def weight_map(
    regions: Iterable[Region],
    height: int,
    width: int,
    params: SemanticParams | None = None,
    normalise: bool = True,
) -> np.ndarray:
    """(H, W) float32 W_i of one image's regions, divided by its max so it spans [0, 1].

    With normalise=False it is the raw weighted sum. No regions (or all-zero weights) -> zeros.
    """
    params = params or SemanticParams()
    regions = list(regions)
    if height < 1 or width < 1:
        raise InputError("height, width", (height, width), "positive image size")
    if not regions:
        return np.zeros((height, width), dtype=np.float32)
    m_y = np.empty((height, len(regions)), dtype=np.float32)
    m_x = np.empty((len(regions), width), dtype=np.float32)
    w = np.empty(len(regions), dtype=np.float32)
    for k, region in enumerate(regions):
        m_y[:, k], m_x[k] = region_profiles(
            region,
            height,
            width,
            params.dilation,
            params.taper_sigma,
            params.size_extent[region.size],
        )
        w[k] = region_weight(region, params)
    out = _sum_of_outer_products(m_y * w, m_x)
    if normalise:
        peak = float(out.max())
        if peak > 0:
            out /= peak
    return out.astype(np.float32, copy=False)


def weight_maps(
    regions: Iterable[Region],
    num_images: int,
    height: int,
    width: int,
    params: SemanticParams | None = None,
) -> np.ndarray:
    """(N, H, W) float32 weight maps, one per image index 0..N-1."""
    by_image: list[list[Region]] = [[] for _ in range(num_images)]
    for region in regions:
        if 0 <= region.image_index < num_images:
            by_image[region.image_index].append(region)
    return (
        np.stack([weight_map(r, height, width, params) for r in by_image])
        if num_images
        else (np.zeros((0, height, width), dtype=np.float32))
    )


def sigma_from_confidence(confidence: np.ndarray) -> np.ndarray:
    """Backbone per-pixel uncertainty sigma = 1 - confidence, confidence (H, W) in [0, 1] (NaN kept)."""
    return (1.0 - np.clip(np.asarray(confidence, dtype=np.float32), 0.0, 1.0)).astype(np.float32)


def semantic_uncertainty(sigma: np.ndarray, weight: np.ndarray, lam: float = 1.0) -> np.ndarray:
    """U_sem = Norm(sigma * (1 + lam * W)), Norm = divide by the largest finite value.

    sigma: (H, W) >= 0 backbone uncertainty (NaN = no estimate, kept NaN); weight: (H, W) in [0, 1].
    All-zero (or all-NaN) input stays zero (NaN). Returns (H, W) float32 in [0, 1].
    """
    sigma = np.asarray(sigma, dtype=np.float32)
    weight = np.asarray(weight, dtype=np.float32)
    if sigma.ndim != 2:
        raise InputError("sigma", sigma.shape, "an (H, W) array")
    if weight.shape != sigma.shape:
        raise InputError("weight", weight.shape, f"the shape of sigma {sigma.shape}")
    return _modulate(np.ascontiguousarray(sigma), np.ascontiguousarray(weight), np.float32(lam))


#: sigma of U_sem = Norm(sigma (1 + lambda W)): "confidence" (1 - perception's confidence, the
#: paper's backbone uncertainty: the VLM's weights raise what the backbone is unsure of, and a
#: confidently reconstructed surface carries no semantic uncertainty) or "constant" (1: U_sem
#: carries the VLM's weights alone; the no_ff preset uses it, so that no confidence reaches the
#: planner by either field).
SIGMA_SOURCES = ("constant", "confidence")


def frame_uncertainty(
    weight: np.ndarray, lam: float, confidence: np.ndarray | None = None
) -> np.ndarray:
    """U_sem (h, w) float32 in [0, 1] of one frame from its weight map W (H, W) in [0, 1]:
    sigma = 1 - `confidence` (h, w) (sigma source "confidence"), or 1 where `confidence` is None
    (sigma source "constant", then h, w = H, W). A weight map of another size than the
    confidence is resampled to it (perception may run at another resolution; the mask is smooth,
    so resampling is exact enough)."""
    weight = np.asarray(weight, dtype=np.float32)
    if confidence is None:
        sigma = np.ones(weight.shape, np.float32)
    else:
        sigma = sigma_from_confidence(confidence)
    if weight.shape != sigma.shape:
        weight = cv2.resize(
            weight, (sigma.shape[1], sigma.shape[0]), interpolation=cv2.INTER_LINEAR
        )
    return semantic_uncertainty(sigma, weight, lam)
