"""The OpenAI-compatible client against a real HTTP server on 127.0.0.1 that replays answers."""

import base64
import io
import json
import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from area3d_semantics import backends
from area3d_semantics.analysis import analyze_views
from area3d_semantics.backends import OpenAIBackend, TransformersBackend, VLMError, VLMUnavailable
from area3d_semantics.parser import parse_answer

CORPUS = Path(__file__).parent / "corpus"
H, W = 48, 64


class FakeVLM:
    """A chat-completions server whose next replies are scripted: ("answer", text) | ("status",
    code, body[, headers]) | ("late", text): answered only once the test is over | ("raw",
    body) | ("length", text): finish_reason "length" | ("drip", body): one byte every 0.2 s,
    until the test is over | ("cut", body): the connection closed half-way through the body |
    ("huge", size): a body of `size` bytes."""

    def __init__(self):
        self.script: list[tuple] = []
        self.requests: list[dict] = []
        self.headers: list[dict] = []
        self.over = threading.Event()  # set when the test ends: the late answers go out
        fake = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):
                pass

            def do_POST(self):
                body = self.rfile.read(int(self.headers["Content-Length"]))
                fake.requests.append({"path": self.path, "json": json.loads(body)})
                fake.headers.append(dict(self.headers))
                step = fake.script.pop(0) if fake.script else ("answer", "")
                if step[0] == "late":  # later than any client waits, however slow the machine
                    fake.over.wait(60.0)
                    step = ("answer", step[1])
                if step[0] in ("answer", "length"):
                    reply = {
                        "id": "chatcmpl-1",
                        "object": "chat.completion",
                        "model": "OpenGVLab/InternVL3-8B",
                        "choices": [
                            {
                                "index": 0,
                                "message": {"role": "assistant", "content": step[1]},
                                "finish_reason": "stop" if step[0] == "answer" else "length",
                            }
                        ],
                    }
                    self._send(200, json.dumps(reply).encode())
                elif step[0] == "status":
                    self._send(step[1], step[2].encode(), *step[3:])
                elif step[0] == "drip":
                    self._send(200, step[1].encode(), drip=True)
                elif step[0] == "cut":
                    self._send(200, step[1].encode(), cut=True)
                elif step[0] == "huge":
                    self._send(200, b"x" * step[1])
                else:
                    self._send(200, step[1].encode())

            def _send(self, code, data, headers=None, drip=False, cut=False):
                try:
                    self.send_response(code)
                    self.send_header("Content-Type", "application/json")
                    self.send_header("Content-Length", str(len(data)))
                    for name, value in (headers or {}).items():
                        self.send_header(name, value)
                    self.end_headers()
                    if drip:
                        for i in range(len(data)):
                            if fake.over.wait(0.2):
                                return
                            self.wfile.write(data[i : i + 1])
                            self.wfile.flush()
                    elif cut:
                        self.wfile.write(data[: len(data) // 2])
                        self.wfile.flush()
                        self.close_connection = True
                    else:
                        self.wfile.write(data)
                except (BrokenPipeError, ConnectionResetError):
                    pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/v1"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self):
        self.over.set()
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def server():
    fake = FakeVLM()
    yield fake
    fake.close()


def images(n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(n)
    return [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(n)]


def backend(url: str, **kw) -> OpenAIBackend:
    return OpenAIBackend(url, "OpenGVLab/InternVL3-8B", backoff_s=0.01, **kw)


def test_request_carries_every_image_as_png_and_the_prompt(server):
    answer = (CORPUS / "01_internvl3_strict.txt").read_text()
    server.script = [("answer", answer)]
    views = images(4)
    text = backend(server.url).analyze(views)
    assert text == answer
    assert parse_answer(text, 4).per_image == [5, 5, 6, 5]
    (request,) = server.requests
    assert request["path"] == "/v1/chat/completions"
    body = request["json"]
    assert body["model"] == "OpenGVLab/InternVL3-8B" and body["temperature"] == 0
    parts = body["messages"][0]["content"]
    urls = [p["image_url"]["url"] for p in parts if p["type"] == "image_url"]
    assert len(urls) == 4
    for url, sent in zip(urls, views, strict=True):
        assert url.startswith("data:image/png;base64,")
        decoded = np.asarray(
            Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))).convert("RGB")
        )
        assert decoded.shape == (H, W, 3)
        np.testing.assert_array_equal(decoded, sent)
    prompt = [p["text"] for p in parts if p["type"] == "text"][-1]
    assert "4 columns and 3 rows" in prompt and "numbered 1 to 4" in prompt
    assert "REGION: <cell> | TYPE: <type>" in prompt


def test_api_key_is_sent_from_the_named_environment_variable(server, monkeypatch):
    monkeypatch.setenv("AREA3D_TEST_VLM_KEY", "sk-test-123")
    server.script = [("answer", "IMAGE 1\nREGION: left-top | TYPE: TEXTURE")]
    backend(server.url, api_key_env="AREA3D_TEST_VLM_KEY").analyze(images(1))
    assert server.headers[0]["Authorization"] == "Bearer sk-test-123"


def test_json_answer_from_the_server_parses(server):
    server.script = [("answer", (CORPUS / "04_qwen25vl_json_fenced.txt").read_text())]
    parsed = parse_answer(backend(server.url).analyze(images(2)), 2)
    assert parsed.per_image == [5, 5]


def test_timeout_is_retried_then_reported(server):
    server.script = [("late", "late"), ("late", "late")]
    client = backend(server.url, timeout_s=0.5, retries=1)
    with pytest.raises(VLMError, match=r"did not answer within 0.5 s"):
        client.analyze(images(1))
    deadline = time.monotonic() + 60.0  # the server's thread notes the request as it reads it
    while len(server.requests) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert len(server.requests) == 2


def test_timeout_then_success_returns_the_answer(server):
    server.script = [
        ("late", "late"),
        ("answer", "IMAGE 1\nREGION: left-top | TYPE: OCCLUSION"),
    ]
    text = backend(server.url, timeout_s=5.0, retries=1).analyze(images(1))
    assert "left-top" in text


def test_server_error_is_retried_then_reported_with_status_and_body(server):
    server.script = [("status", 503, "model loading")] * 3
    with pytest.raises(VLMError, match=r"HTTP 503.*model loading"):
        backend(server.url, retries=2).analyze(images(1))
    assert len(server.requests) == 3


def test_server_error_then_success_returns_the_answer(server):
    server.script = [
        ("status", 500, "oops"),
        ("answer", "IMAGE 1\nREGION: right-top | TYPE: LIGHTING"),
    ]
    assert "right-top" in backend(server.url, retries=1).analyze(images(1))


def test_an_answer_dripped_byte_by_byte_is_given_up_after_timeout_s(server):
    """Headers at once, then a byte every 0.2 s: each read is quick, the answer never whole.
    requests' timeout bounds each read only: the client hung for as long as the server went
    on; the whole answer must arrive within timeout_s (each read may take up to it more)."""
    answer = json.dumps({"choices": [{"message": {"content": "IMAGE 1"}}]}) + " " * 2000
    server.script = [("drip", answer)]
    start = time.monotonic()
    with pytest.raises(VLMError, match=r"did not answer within 1 s"):
        backend(server.url, timeout_s=1.0, retries=0).analyze(images(1))
    assert time.monotonic() - start < 60.0  # the drip lasts 400 s (loose: a loaded machine)


def test_rate_limits_and_broken_answers_are_retried_and_named(server):
    """429 with Retry-After and 408 are asked again (a 429 failed at once, its message about the
    API key); a connection that breaks off mid-answer is retried and names the URL."""
    body = json.dumps({"choices": [{"message": {"content": "IMAGE 1\nREGION: left-top"}}]})
    server.script = [
        ("status", 429, "slow down", {"Retry-After": "0"}),
        ("status", 408, "timeout"),
        ("cut", body),
        ("raw", body),
    ]
    assert "left-top" in backend(server.url, retries=3).analyze(images(1))
    assert len(server.requests) == 4
    server.script = [("cut", body)]
    with pytest.raises(VLMError, match=rf"{server.url}/chat/completions: the answer broke off"):
        backend(server.url, retries=0).analyze(images(1))


def test_an_answer_cut_at_max_tokens_or_too_large_is_refused_not_used(server):
    """finish_reason "length": the images the answer did not reach would get no region, as if
    clear; an answer of more than MAX_ANSWER_BYTES is not read on."""
    server.script = [("length", "IMAGE 1\nREGION: left-top | TYPE: OCCLUSION\nIMAGE 2")]
    with pytest.raises(VLMError, match=r"cut the answer at max_tokens \(8192\)"):
        backend(server.url).analyze(images(2))
    server.script = [("huge", backends.MAX_ANSWER_BYTES + 2**20)]
    with pytest.raises(VLMError, match=r"larger than 16 MB"):
        backend(server.url, retries=0).analyze(images(1))


def test_client_error_is_not_retried_and_names_the_status(server):
    server.script = [("status", 404, '{"error": "model InternVL3-8B not found"}')]
    with pytest.raises(VLMError, match=r"HTTP 404.*not found"):
        backend(server.url, retries=2).analyze(images(1))
    assert len(server.requests) == 1


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("<html>Bad Gateway</html>", "not JSON"),
        ('{"id": "x", "choices": []}', "no choices"),
        ('{"choices": [{"message": {"role": "assistant", "content": ""}}]}', "empty answer"),
        ('{"choices": [{"message": {"role": "assistant", "content": null}}]}', "empty answer"),
    ],
)
def test_garbage_replies_give_clear_errors(server, body, message):
    server.script = [("raw", body)]
    with pytest.raises(VLMError, match=message):
        backend(server.url).analyze(images(1))


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_server_error_names_the_url():
    url = f"http://127.0.0.1:{closed_port()}"
    with pytest.raises(VLMUnavailable, match=rf"{url}/v1/chat/completions"):
        backend(url, retries=1).analyze(images(1))


def test_unreachable_server_falls_back_to_the_heuristic():
    url = f"http://127.0.0.1:{closed_port()}/v1"
    analysis = analyze_views(backend(url, retries=0), [np.full((H, W, 3), 128, np.uint8)])
    assert analysis.fallback_used == "heuristic" and url in analysis.error
    assert analysis.regions and analysis.backend == "openai"


def test_unusable_server_answer_falls_back(server):
    server.script = [("answer", (CORPUS / "11_refusal.txt").read_text())]
    analysis = analyze_views(backend(server.url), images(2), fallback="zeros")
    assert analysis.fallback_used == "zeros" and "refused" in analysis.error


def test_transformers_backend_without_a_model_directory_says_where_the_model_goes(tmp_path):
    with pytest.raises(VLMUnavailable, match="model_dir"):
        TransformersBackend(tmp_path / "missing")
    (tmp_path / "config.json").write_text("{}")
    try:
        import torch  # noqa: F401
        import transformers  # noqa: F401
    except ImportError:
        with pytest.raises(VLMUnavailable, match="pip install"):
            TransformersBackend(tmp_path)
    else:  # with the libraries present, construction is lazy and loads nothing yet
        assert TransformersBackend(tmp_path)._model is None


def test_the_nodes_answer_length_limit_reaches_the_transformers_backend(monkeypatch):
    from area3d_semantics import backends
    from area3d_semantics.node import PARAMS, backend_from_parameters

    made = {}

    class Recorded:  # stands in for the model class: torch is not needed to check the wiring
        def __init__(self, model_dir, **options):
            made.update(options, model_dir=model_dir)

    monkeypatch.setattr(backends, "TransformersBackend", Recorded)
    p = {param.name: param.default for param in PARAMS}
    p |= {"backend": "transformers", "model_dir": "/models/qwen", "max_tokens": 300}
    backend, problem = backend_from_parameters(p)
    assert problem is None and isinstance(backend, Recorded)
    assert made["max_new_tokens"] == 300 and made["model_dir"] == "/models/qwen"
