"""Where region answers come from: an OpenAI-compatible VLM server, a local transformers model,
the offline heuristic analyzer, or nothing. Every backend answers in the prompt's text format:
`analyze(images, depths) -> str`, which parser.parse_answer then reads."""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path
from typing import Protocol

import numpy as np
import requests
import urllib3

from area3d_msgs_py.errors import InputError
from area3d_semantics.heuristic import HeuristicParams, analyze_image, format_answer
from area3d_semantics.prompt import build_messages, check_image, prompt_text

LOG = logging.getLogger(__name__)

BACKEND_NAMES = ("heuristic", "openai", "transformers", "none")
# an answer of regions is kilobytes; one larger is not read on (and not held in memory)
MAX_ANSWER_BYTES = 16 * 2**20
READ_CHUNK = 64 * 2**10
# the server asks to be asked again (timeout, rate limit): retried like a 5xx, after Retry-After
RETRIED_STATUS = (408, 429)


class VLMError(RuntimeError):
    """A backend could not produce an answer; the message says why and what to check."""


class VLMUnavailable(VLMError):
    """The backend cannot run here (missing package, model directory or server)."""


class Backend(Protocol):
    name: str

    def analyze(
        self, images: list[np.ndarray], depths: list[np.ndarray | None] | None = None
    ) -> str: ...


def _check_inputs(images: list[np.ndarray], depths: list | None) -> None:
    if len(images) == 0:
        raise InputError("images", 0, "at least one (H, W, 3) uint8 image")
    for i, image in enumerate(images):
        check_image(image, f"images[{i}]")
    if depths is not None and len(depths) != len(images):
        raise InputError(
            "depths", len(depths), f"one depth image (or None) per image ({len(images)})"
        )


class OpenAIBackend:
    """Any server speaking POST /v1/chat/completions with image_url parts (vLLM, LMDeploy, SGLang,
    Ollama, OpenAI). Retries timeouts, broken connections, 5xx, 408 and 429 (after Retry-After,
    at most `timeout_s`) with exponential backoff; each attempt's whole answer must arrive
    within `timeout_s` and be at most MAX_ANSWER_BYTES."""

    name = "openai"

    def __init__(
        self,
        base_url: str,
        model: str,
        api_key_env: str = "OPENAI_API_KEY",
        timeout_s: float = 60.0,
        retries: int = 2,
        max_tokens: int = 8192,
        temperature: float = 0.0,
        backoff_s: float = 1.0,
        image_format: str = "png",
    ) -> None:
        if not isinstance(base_url, str) or not base_url.startswith(("http://", "https://")):
            raise InputError("base_url", base_url, "an http:// or https:// URL of the VLM server")
        if not model:
            raise InputError("model", model, "the model name the server serves")
        if timeout_s <= 0:
            raise InputError("timeout_s", timeout_s, "a positive number of seconds")
        if retries < 0:
            raise InputError("retries", retries, "an int >= 0")
        base = base_url.rstrip("/")
        self.url = base + ("/chat/completions" if base.endswith("/v1") else "/v1/chat/completions")
        self.model = model
        self.api_key_env = api_key_env
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self.max_tokens = int(max_tokens)
        self.temperature = float(temperature)
        self.backoff_s = float(backoff_s)
        self.image_format = image_format

    def payload(self, images: list[np.ndarray]) -> dict:
        return {
            "model": self.model,
            "messages": build_messages(images, self.image_format),
            "max_tokens": self.max_tokens,
            "temperature": self.temperature,
        }

    def analyze(
        self, images: list[np.ndarray], depths: list[np.ndarray | None] | None = None
    ) -> str:
        _check_inputs(images, depths)
        payload = self.payload(images)
        headers = {"Content-Type": "application/json"}
        key = os.environ.get(self.api_key_env, "") if self.api_key_env else ""
        if key:
            headers["Authorization"] = f"Bearer {key}"
        last: VLMError | None = None
        wait = 0.0
        for attempt in range(self.retries + 1):
            if attempt:
                time.sleep(wait)
            wait = self.backoff_s * 2**attempt
            try:
                status, body, retry_after = self._post(payload, headers)
            except requests.Timeout:
                last = VLMError(
                    f"VLM server {self.url} did not answer within {self.timeout_s:g} s (timeout_s)"
                )
            except requests.ConnectionError as exc:
                last = VLMUnavailable(
                    f"cannot reach the VLM server at {self.url}: {exc.__class__.__name__}; "
                    "check that it is running and that base_url is right"
                )
            except requests.RequestException as exc:  # the connection broke off mid-answer
                last = VLMError(
                    f"VLM server {self.url}: the answer broke off ({exc.__class__.__name__}: "
                    f"{str(exc)[:200]})"
                )
            else:
                text = body[:300].decode("utf-8", errors="replace")
                if status >= 500 or status in RETRIED_STATUS:
                    last = VLMError(f"VLM server {self.url} answered HTTP {status}: {text!r}")
                    if retry_after is not None:
                        wait = min(max(wait, retry_after), self.timeout_s)
                elif status >= 400:
                    unset = "" if key or not self.api_key_env else ", which is not set"
                    raise VLMError(
                        f"VLM server {self.url} rejected the request with HTTP {status} "
                        f"(check model={self.model!r} and the API key in ${self.api_key_env}"
                        f"{unset}): {text!r}"
                    )
                else:
                    return self._content(body)
            LOG.warning("VLM attempt %d/%d failed: %s", attempt + 1, self.retries + 1, last)
        assert last is not None
        raise last

    def _post(self, payload: dict, headers: dict) -> tuple[int, bytes, float | None]:
        """One POST: (status, body, Retry-After in seconds or None). requests' timeout bounds
        each read only, so a server that drips its answer would hold the node: the body is read
        as it comes and given up `timeout_s` after the request went out (requests.Timeout), or
        once it passes MAX_ANSWER_BYTES (VLMError)."""
        deadline = time.monotonic() + self.timeout_s
        with requests.post(
            self.url, json=payload, headers=headers, timeout=self.timeout_s, stream=True
        ) as response:
            body = bytearray()
            try:
                while chunk := response.raw.read1(READ_CHUNK, decode_content=True):
                    body += chunk
                    if len(body) > MAX_ANSWER_BYTES:
                        raise VLMError(
                            f"VLM server {self.url} sent an answer larger than "
                            f"{MAX_ANSWER_BYTES // 2**20} MB (not read on): {bytes(body[:200])!r}"
                        )
                    if time.monotonic() > deadline:
                        raise requests.Timeout(f"{self.url}: answer not whole in time")
            except requests.RequestException:  # (an OSError too)
                raise
            except urllib3.exceptions.ReadTimeoutError as exc:
                raise requests.Timeout(str(exc)) from exc
            except (urllib3.exceptions.HTTPError, OSError) as exc:
                raise requests.exceptions.ChunkedEncodingError(str(exc)) from exc
            return response.status_code, bytes(body), _retry_after(response.headers)

    def _content(self, data: bytes) -> str:
        try:
            body = json.loads(data)
        except ValueError:
            raise VLMError(
                f"VLM server {self.url} returned a body that is not JSON: {data[:200]!r}"
            ) from None
        choices = body.get("choices") if isinstance(body, dict) else None
        if not choices or not isinstance(choices, list):
            raise VLMError(f"VLM server {self.url} returned no choices: {str(body)[:200]!r}")
        choice = choices[0] if isinstance(choices[0], dict) else {}
        message = choice.get("message")
        content = message.get("content") if isinstance(message, dict) else None
        if isinstance(content, list):  # some servers return content parts
            content = "".join(p.get("text", "") for p in content if isinstance(p, dict))
        if not isinstance(content, str) or not content.strip():
            raise VLMError(
                f"VLM server {self.url} returned an empty answer (finish_reason "
                f"{choice.get('finish_reason')!r}): {str(body)[:200]!r}"
            )
        if choice.get("finish_reason") == "length":
            # the images the answer did not reach would get no region, as if seen clear
            raise VLMError(
                f"VLM server {self.url} cut the answer at max_tokens ({self.max_tokens}): "
                "raise max_tokens (the server's context must hold it beside the images)"
            )
        return content


def _retry_after(headers) -> float | None:
    """A Retry-After header in seconds (its HTTP-date form is not read: None)."""
    try:
        value = float(headers.get("Retry-After", ""))
    except ValueError:
        return None
    return value if value >= 0 and np.isfinite(value) else None


class TransformersBackend:
    """A local Hugging Face checkpoint (e.g. Qwen2.5-VL-7B-Instruct, InternVL3-8B-hf) run with
    transformers. Nothing is downloaded: the model directory must already hold the weights."""

    name = "transformers"

    def __init__(
        self,
        model_dir: str | Path,
        device: str = "auto",
        trust_remote_code: bool = False,
        max_new_tokens: int = 8192,
    ) -> None:
        self.model_dir = Path(model_dir).expanduser() if model_dir else Path()
        if (
            not model_dir
            or not self.model_dir.is_dir()
            or not (self.model_dir / "config.json").is_file()
        ):
            raise VLMUnavailable(
                f"model_dir {str(model_dir)!r} is not a Hugging Face model directory (no config.json); "
                "download the checkpoint once, e.g. `huggingface-cli download Qwen/Qwen2.5-VL-7B-Instruct "
                "--local-dir <dir>`, and set model_dir to that directory"
            )
        try:
            import torch  # noqa: F401
            import transformers  # noqa: F401
        except ImportError as exc:
            raise VLMUnavailable(
                f"the transformers backend needs torch and transformers ({exc.name} is missing): "
                "pip install 'area3d[ml]' transformers accelerate"
            ) from None
        self.device = device
        self.trust_remote_code = bool(trust_remote_code)
        self.max_new_tokens = int(max_new_tokens)
        self._model = None
        self._processor = None

    def _load(self) -> None:
        import transformers

        kwargs = {"local_files_only": True, "trust_remote_code": self.trust_remote_code}
        self._processor = transformers.AutoProcessor.from_pretrained(self.model_dir, **kwargs)
        loader = (
            getattr(transformers, "AutoModelForImageTextToText", None)
            or transformers.AutoModelForVision2Seq
        )
        self._model = loader.from_pretrained(
            self.model_dir, device_map=self.device, torch_dtype="auto", **kwargs
        ).eval()

    def analyze(
        self, images: list[np.ndarray], depths: list[np.ndarray | None] | None = None
    ) -> str:
        _check_inputs(images, depths)
        import torch
        from PIL import Image

        if self._model is None:
            self._load()
        content: list[dict] = []
        for n, image in enumerate(images, start=1):
            content += [
                {"type": "text", "text": f"Image {n}:"},
                {"type": "image", "image": Image.fromarray(image)},
            ]
        content.append({"type": "text", "text": prompt_text(len(images))})
        inputs = self._processor.apply_chat_template(
            [{"role": "user", "content": content}],
            add_generation_prompt=True,
            tokenize=True,
            return_dict=True,
            return_tensors="pt",
        ).to(self._model.device)
        with torch.inference_mode():
            out = self._model.generate(
                **inputs, max_new_tokens=self.max_new_tokens, do_sample=False
            )
        new_tokens = out[:, inputs["input_ids"].shape[1] :]
        return self._processor.batch_decode(new_tokens, skip_special_tokens=True)[0]


class HeuristicBackend:
    """No model: regions from image (and depth) evidence, written in the VLM's answer format."""

    name = "heuristic"

    def __init__(self, params: HeuristicParams | None = None) -> None:
        self.params = params or HeuristicParams()

    def analyze(
        self, images: list[np.ndarray], depths: list[np.ndarray | None] | None = None
    ) -> str:
        _check_inputs(images, depths)
        depths = depths if depths is not None else [None] * len(images)
        return format_answer(
            [analyze_image(i, d, self.params) for i, d in zip(images, depths, strict=True)]
        )


class NoneBackend:
    """No regions at all: all-zero weights, the paper's "w/o VLM" ablation."""

    name = "none"

    def analyze(
        self, images: list[np.ndarray], depths: list[np.ndarray | None] | None = None
    ) -> str:
        _check_inputs(images, depths)
        return "".join(f"IMAGE {n}\n" for n in range(1, len(images) + 1))


def make_backend(name: str, **options) -> Backend:
    """Backend by name: "heuristic" | "openai" (base_url, model, api_key_env, timeout_s, retries,
    max_tokens, temperature) | "transformers" (model_dir, device, trust_remote_code, max_tokens as
    its max_new_tokens) | "none".
    Options that the chosen backend does not take are ignored."""
    if name == "heuristic":
        return HeuristicBackend(options.get("heuristic_params"))
    if name == "none":
        return NoneBackend()
    if name == "openai":
        keys = (
            "api_key_env",
            "timeout_s",
            "retries",
            "max_tokens",
            "temperature",
            "backoff_s",
            "image_format",
        )
        return OpenAIBackend(
            options.get("base_url", ""),
            options.get("model", ""),
            **{k: options[k] for k in keys if k in options},
        )
    if name == "transformers":
        keys = ("device", "trust_remote_code", "max_new_tokens")
        chosen = {k: options[k] for k in keys if k in options}
        if "max_tokens" in options:  # the node's answer length limit, as for a served VLM
            chosen.setdefault("max_new_tokens", options["max_tokens"])
        return TransformersBackend(options.get("model_dir", ""), **chosen)
    raise InputError("backend", name, f"one of {', '.join(BACKEND_NAMES)}")
