"""Feed-forward backends: confidence normalisation, scale alignment and clear start-up errors."""

import importlib.machinery
import pickle
import sys
import types

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from area3d_msgs_py.errors import InputError
from area3d_perception.feedforward import (
    BackendUnavailableError,
    DepthAnything3Backend,
    VggtBackend,
    align_depth_median,
    align_scale_to_poses,
    apply_alignment,
    normalize_confidence,
    vggt_input_size,
)


@pytest.mark.parametrize("seed", range(8))
def test_umeyama_recovers_a_known_similarity(seed):
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed).as_matrix()
    s = rng.uniform(0.3, 3.0)
    t = rng.uniform(-5, 5, 3)
    pred = rng.normal(size=(12, 3))
    known = s * pred @ R.T + t + rng.normal(scale=1e-3, size=(12, 3))
    s_hat, R_hat, t_hat = align_scale_to_poses(pred, known)
    assert s_hat == pytest.approx(s, rel=5e-3)
    assert np.linalg.det(R_hat) == pytest.approx(1.0)
    assert np.degrees(np.arccos(np.clip((np.trace(R_hat.T @ R) - 1) / 2, -1, 1))) < 0.5
    np.testing.assert_allclose(s_hat * pred @ R_hat.T + t_hat, known, atol=5e-3)


def test_umeyama_never_returns_a_reflection():
    rng = np.random.default_rng(1)
    pred = rng.normal(size=(6, 3))
    mirrored = pred * np.array([1.0, 1.0, -1.0]) * 2.0
    _, R, _ = align_scale_to_poses(pred, mirrored)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_umeyama_scale_from_two_cameras():
    s, _, _ = align_scale_to_poses(
        np.array([[0, 0, 0], [1.0, 0, 0]]), np.array([[2, 2, 2], [2, 2, 4.5]])
    )
    assert s == pytest.approx(2.5)


def test_umeyama_rejects_bad_input():
    with pytest.raises(InputError, match="^pred_centres: "):
        align_scale_to_poses(np.zeros((1, 3)), np.zeros((1, 3)))
    with pytest.raises(InputError, match="^known_centres: "):
        align_scale_to_poses(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(InputError, match="coincident"):
        align_scale_to_poses(np.ones((3, 3)), np.arange(9.0).reshape(3, 3))


def test_median_alignment_recovers_the_scale_despite_outliers_and_holes():
    rng = np.random.default_rng(0)
    metric = rng.uniform(0.5, 4.0, (60, 80)).astype(np.float32)
    pred = metric / 2.5
    outliers = rng.random(metric.shape) < 0.2
    pred[outliers] *= rng.uniform(0.1, 10.0, outliers.sum())
    metric[:10] = np.nan
    pred[-5:] = np.nan
    assert align_depth_median(pred, metric) == pytest.approx(2.5, rel=1e-3)


def test_median_alignment_needs_overlap():
    with pytest.raises(InputError, match="^metric_depth: "):
        align_depth_median(np.ones((4, 4)), np.full((4, 4), np.nan))
    with pytest.raises(InputError, match="^metric_depth: "):
        align_depth_median(np.ones((4, 4)), np.ones((4, 5)))


def test_apply_alignment_rescales_every_map():
    out = apply_alignment([np.ones((2, 2)), np.full((2, 2), np.nan)], 3.0)
    assert out[0].dtype == np.float32 and np.all(out[0] == 3.0) and np.all(np.isnan(out[1]))
    with pytest.raises(InputError, match="^scale: "):
        apply_alignment([np.ones((2, 2))], -1.0)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(1.0, 1e6), min_size=2, max_size=50))
def test_inverse_normalisation_is_monotonic_in_unit_interval(values):
    c = np.sort(np.asarray(values, dtype=np.float32))
    n = normalize_confidence(c)
    assert np.all((n >= 0) & (n <= 1))
    assert np.all(np.diff(n) >= 0)


def test_inverse_normalisation_maps_the_lowest_confidence_to_zero():
    n = normalize_confidence(np.array([1.0, 2.0, 4.0, np.inf, np.nan, 0.5]))
    assert n.tolist() == pytest.approx([0.0, 0.5, 0.75, 1.0, 0.0, 0.0])


def test_percentile_normalisation_is_per_image_monotonic_and_bounded():
    rng = np.random.default_rng(2)
    c = 1.0 + rng.exponential(5.0, (2, 30, 40)).astype(np.float32)
    c[1] *= 10.0  # a globally more confident image still spans [0, 1]
    n = normalize_confidence(c, "percentile")
    for i in range(2):
        order = np.argsort(c[i].ravel())
        assert np.all(np.diff(n[i].ravel()[order]) >= 0)
        assert n[i].min() == 0.0 and n[i].max() == 1.0
    with pytest.raises(InputError, match="^method: "):
        normalize_confidence(c, "softmax")


def test_vggt_input_size_follows_its_preprocessing():
    # Width 518, height rounded to a multiple of the 14 px patch.
    assert vggt_input_size(480, 640) == (392, 518)
    h, w = vggt_input_size(640, 480)
    assert max(h, w) == 518 and h % 14 == 0 and w % 14 == 0


def test_vggt_backend_without_weights_says_what_is_missing_and_where_they_go(tmp_path):
    checkpoint = tmp_path / "weights" / "model.pt"
    with pytest.raises(BackendUnavailableError) as err:
        VggtBackend(str(checkpoint))
    message = str(err.value)
    assert str(checkpoint) in message
    assert "facebook/VGGT-1B" in message and "pip install" in message
    assert "git+https://github.com/facebookresearch/vggt" in message


def test_depth_anything_backend_without_weights_names_the_model_directory(tmp_path):
    with pytest.raises(BackendUnavailableError) as err:
        DepthAnything3Backend(str(tmp_path / "da3-large"))
    assert str(tmp_path / "da3-large") in str(err.value) and "depth-anything-3" in str(err.value)


def test_weights_of_the_wrong_kind_are_named_missing(tmp_path):
    # a directory where VGGT's model.pt goes, a file where Depth Anything 3's directory goes
    (tmp_path / "model.pt").mkdir()
    with pytest.raises(
        BackendUnavailableError, match=r"model.pt' \(a file; a directory is there\)"
    ):
        VggtBackend(str(tmp_path / "model.pt"))
    (tmp_path / "da3").write_text("not a directory")
    with pytest.raises(BackendUnavailableError, match=r"da3' \(a directory; a file is there\)"):
        DepthAnything3Backend(str(tmp_path / "da3"))


def _module(monkeypatch, name: str, **attrs) -> types.ModuleType:
    module = types.ModuleType(name)
    module.__spec__ = importlib.machinery.ModuleSpec(name, None)
    for key, value in attrs.items():
        setattr(module, key, value)
    monkeypatch.setitem(sys.modules, name, module)
    return module


def test_a_file_that_is_no_vggt_checkpoint_cannot_start_the_backend_naming_it(
    tmp_path, monkeypatch
):
    """torch and vggt importable (stand-ins here: neither is installed), the checkpoint a text
    file: torch.load's UnpicklingError ended the node in a traceback; now the backend cannot
    start, and says which file is not a checkpoint."""
    loaded = []

    def load(path, map_location=None):
        loaded.append(path)
        raise pickle.UnpicklingError("invalid load key, 'n'.")

    class VGGT:
        def load_state_dict(self, state):
            raise AssertionError("not reached")

    cuda = types.SimpleNamespace(is_available=lambda: False)
    _module(monkeypatch, "torch", load=load, cuda=cuda)
    for name in ("vggt", "vggt.models"):
        _module(monkeypatch, name)
    _module(monkeypatch, "vggt.models.vggt", VGGT=VGGT)
    checkpoint = tmp_path / "model.pt"
    checkpoint.write_text("not a checkpoint")
    with pytest.raises(BackendUnavailableError) as err:
        VggtBackend(str(checkpoint))
    assert loaded == [str(checkpoint)]
    assert f"{checkpoint} is not a VGGT-1B checkpoint" in str(err.value)
    assert "UnpicklingError: invalid load key" in str(err.value)
