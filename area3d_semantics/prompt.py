"""The VLM query: one versioned prompt text and the OpenAI-style chat messages that carry it."""

from __future__ import annotations

import base64
import io
from pathlib import Path

import numpy as np
from PIL import Image

from area3d_msgs_py.errors import InputError

# Bump together with the file name when the wording changes; it is published with every answer.
PROMPT_VERSION = "v1"
PROMPT_PATH = Path(__file__).parent / "prompts" / f"region_analysis_{PROMPT_VERSION}.txt"


def prompt_text(num_images: int) -> str:
    """The instruction text for a query with `num_images` images."""
    if num_images < 1:
        raise InputError("num_images", num_images, "at least 1 image")
    return PROMPT_PATH.read_text(encoding="utf-8").format(num_images=num_images)


def check_image(image: np.ndarray, field: str = "image") -> np.ndarray:
    """Validate an (H, W, 3) uint8 RGB image at the boundary and return it."""
    if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3:
        shape = getattr(image, "shape", type(image).__name__)
        raise InputError(field, shape, "an (H, W, 3) RGB array")
    if image.dtype != np.uint8:
        raise InputError(f"{field}.dtype", image.dtype, "uint8")
    return image


def image_data_url(image: np.ndarray, fmt: str = "png") -> str:
    """(H, W, 3) uint8 RGB -> "data:image/png;base64,..." (or JPEG with fmt="jpeg")."""
    check_image(image)
    if fmt not in ("png", "jpeg"):
        raise InputError("fmt", fmt, '"png" or "jpeg"')
    buffer = io.BytesIO()
    if fmt == "png":
        # Fastest zlib level: the server decodes it anyway, and a 640x480 frame stays under 1 MB.
        Image.fromarray(image).save(buffer, format="PNG", compress_level=1)
    else:
        Image.fromarray(image).save(buffer, format="JPEG", quality=90)
    encoded = base64.b64encode(buffer.getvalue()).decode("ascii")
    return f"data:image/{fmt};base64,{encoded}"


def build_messages(images: list[np.ndarray], fmt: str = "png") -> list[dict]:
    """OpenAI chat messages for one query with all images.

    images: list of (H, W, 3) uint8 RGB. Returns [{"role": "user", "content": [...]}] where the
    content alternates an "Image n:" label and its image_url part, then the instruction text.
    """
    if len(images) == 0:
        raise InputError("images", 0, "at least one (H, W, 3) uint8 image")
    content: list[dict] = []
    for n, image in enumerate(images, start=1):
        check_image(image, f"images[{n - 1}]")
        content.append({"type": "text", "text": f"Image {n}:"})
        content.append({"type": "image_url", "image_url": {"url": image_data_url(image, fmt)}})
    content.append({"type": "text", "text": prompt_text(len(images))})
    return [{"role": "user", "content": content}]
