"""Small procedural textures (PNG) so that rendered RGB has something to match on."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

TEXTURE_SIZE = 128  # pixels; small keeps the scene data light


def make_texture(
    kind: str, colour_a, colour_b, seed: int = 0, size: int = TEXTURE_SIZE
) -> np.ndarray:
    """(size, size, 3) uint8 texture: kind in {"checker", "stripes", "noise", "dots"}."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:size, 0:size] / size
    if kind == "checker":
        t = ((np.floor(u * 8) + np.floor(v * 8)) % 2).astype(np.float64)
    elif kind == "stripes":
        t = 0.5 + 0.5 * np.sin(2 * np.pi * (6 * u + 2 * v))
    elif kind == "noise":
        coarse = rng.random((9, 9))
        t = np.kron(coarse[:8, :8], np.ones((size // 8, size // 8)))
        t = 0.6 * t + 0.4 * rng.random((size, size))
    elif kind == "dots":
        cu, cv = (u * 6) % 1 - 0.5, (v * 6) % 1 - 0.5
        t = (cu**2 + cv**2 < 0.09).astype(np.float64)
    else:
        raise ValueError(f"kind: got {kind!r}, expected one of checker, stripes, noise, dots")
    a = np.asarray(colour_a, dtype=np.float64)
    b = np.asarray(colour_b, dtype=np.float64)
    return (a + (b - a) * t[..., None]).clip(0, 255).astype(np.uint8)


def write_texture(path: Path, kind: str, colour_a, colour_b, seed: int = 0) -> None:
    Image.fromarray(make_texture(kind, colour_a, colour_b, seed)).save(path, optimize=True)
