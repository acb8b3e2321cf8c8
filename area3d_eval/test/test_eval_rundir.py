"""The run directory round-trips frames and episodes."""

import json
import math

import numpy as np
import pytest

from area3d_eval.rundir import (
    check_frames,
    frame_path,
    iter_frames,
    read_episode,
    read_frame,
    read_metrics,
    reconstruction_input,
    to_jsonable,
    write_episode,
    write_frame,
)
from area3d_msgs_py.errors import InputError
from area3d_perception.sensor_model import rgbd_confidence


def test_frames_round_trip_in_index_order(tmp_path):
    rng = np.random.default_rng(0)
    for i in (10, 2, 7):
        rgb = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
        depth = np.where(rng.random((6, 8)) > 0.5, 1.5, np.nan).astype(np.float32)
        T = np.eye(4)
        T[0, 3] = i
        write_frame(tmp_path, i, rgb, depth, np.eye(3), T, stamp_ns=i * 100)
    frames = list(iter_frames(tmp_path))
    assert [f.index for f in frames] == [2, 7, 10]
    assert [f.stamp_ns for f in frames] == [200, 700, 1000]
    assert frames[1].T_world_cam[0, 3] == 7
    assert np.isnan(frames[0].depth).any() and frames[0].rgb.dtype == np.uint8
    assert len(list(iter_frames(tmp_path, limit=2))) == 2


def test_episode_views_are_sorted_and_counted(tmp_path):
    views = [
        {"index": 1, "T_world_cam": np.eye(4), "kind": "planned"},
        {"index": 0, "T_world_cam": np.eye(4), "kind": "initial"},
    ]
    write_episode(tmp_path, {"scene": "s", "policy": "p", "seed": 3, "budget": 1, "views": views})
    ep = read_episode(tmp_path)
    assert [v["index"] for v in ep.views] == [0, 1] and ep.num_initial == 1
    assert ep.poses().shape == (2, 4, 4) and ep.kinds() == ["initial", "planned"]


def test_non_finite_numbers_become_null_in_json():
    text = json.dumps(to_jsonable({"a": math.inf, "b": [np.float64("nan"), np.int64(2)]}))
    assert json.loads(text) == {"a": None, "b": [None, 2]}


def test_missing_episode_and_bad_frames_are_rejected(tmp_path):
    with pytest.raises(InputError, match="run_dir"):
        read_episode(tmp_path)
    with pytest.raises(InputError, match="depth"):
        write_frame(
            tmp_path, 0, np.zeros((4, 4, 3), np.uint8), np.zeros((4, 5)), np.eye(3), np.eye(4)
        )


def _run(tmp_path, views: int = 3):
    for i in range(views):
        write_frame(
            tmp_path, i, np.zeros((4, 4, 3), np.uint8), np.ones((4, 4)), np.eye(3), np.eye(4)
        )
    listed = [{"index": i, "T_world_cam": np.eye(4), "kind": "initial"} for i in range(views)]
    write_episode(tmp_path, {"scene": "s", "policy": "p", "budget": views, "views": listed})
    return read_episode(tmp_path)


def test_a_damaged_run_directory_is_refused_naming_the_file_and_what_is_wrong(tmp_path):
    episode = _run(tmp_path)
    assert len(check_frames(tmp_path, episode)) == 3
    # a frame file lost: the evaluation would score two views as if they were the run
    frame_path(tmp_path, 1).unlink()
    with pytest.raises(InputError, match=r"frames: got 'no frame file for views \[1\]'"):
        check_frames(tmp_path, episode)
    cut = frame_path(tmp_path, 2)
    cut.write_bytes(cut.read_bytes()[:100])
    with pytest.raises(InputError, match=f"{cut}: got 'unreadable"):
        read_frame(cut)
    (tmp_path / "metrics.json").write_text('{"final": 3}')
    with pytest.raises(InputError, match="metrics.json: final: got 3"):
        read_metrics(tmp_path)
    episode_file = tmp_path / "episode.json"
    episode_file.write_text(episode_file.read_text()[:40])
    with pytest.raises(InputError, match="episode.json: got 'not JSON"):
        read_episode(tmp_path)
    episode_file.write_text('{"scene": "s", "policy": "p", "views": [{"kind": "initial"}]}')
    with pytest.raises(
        InputError, match="episode.json: got .an entry of another kind .KeyError: 'index'"
    ):
        read_episode(tmp_path)


def test_perception_estimates_round_trip_and_feed_the_tsdf_only_when_asked(tmp_path):
    rgb = np.zeros((6, 8, 3), np.uint8)
    depth = np.full((6, 8), 1.5, np.float32)
    estimate, confidence = depth + 0.1, np.full((6, 8), 0.25, np.float32)
    write_frame(tmp_path, 0, rgb, depth, np.eye(3), np.eye(4), 1, estimate, confidence)
    write_frame(tmp_path, 1, rgb, depth, np.eye(3), np.eye(4), 2)
    with_estimate, without = iter_frames(tmp_path)
    np.testing.assert_array_equal(with_estimate.estimated_depth, estimate)
    np.testing.assert_array_equal(with_estimate.confidence, confidence)
    assert without.estimated_depth is None and without.confidence is None
    used, weights = reconstruction_input(with_estimate, "estimated")
    np.testing.assert_array_equal(used, estimate)
    np.testing.assert_array_equal(weights, confidence)
    used, weights = reconstruction_input(without, "sensor")
    np.testing.assert_array_equal(used, depth)
    # the camera's depth is weighted by the camera's sensor model, not by what perception said
    np.testing.assert_array_equal(weights, rgbd_confidence(depth, np.eye(3)))
    with pytest.raises(InputError, match="frames/0001.npz estimated_depth"):
        reconstruction_input(without, "estimated")
    with pytest.raises(InputError, match="depth_source: got 'lidar'"):
        reconstruction_input(with_estimate, "lidar")
    with pytest.raises(InputError, match="estimated_depth"):
        write_frame(tmp_path, 2, rgb, depth, np.eye(3), np.eye(4), 3, estimate[:5])
    # a fusion weight of its own, when perception gave one, is what the TSDF integrates with
    weight = np.full((6, 8), 0.75, np.float32)
    write_frame(tmp_path, 2, rgb, depth, np.eye(3), np.eye(4), 3, estimate, confidence, weight)
    weighted = list(iter_frames(tmp_path))[2]
    np.testing.assert_array_equal(weighted.confidence, confidence)
    np.testing.assert_array_equal(reconstruction_input(weighted, "estimated")[1], weight)
    assert with_estimate.weight is None  # a run that kept none: its confidence, as before
    # a weight equal to the confidence is stored once and read back as the confidence
    write_frame(tmp_path, 3, rgb, depth, np.eye(3), np.eye(4), 4, estimate, confidence, confidence)
    same = list(iter_frames(tmp_path))[3]
    assert same.weight is None
    np.testing.assert_array_equal(reconstruction_input(same, "estimated")[1], confidence)
    with pytest.raises(InputError, match="weight"):
        write_frame(tmp_path, 4, rgb, depth, np.eye(3), np.eye(4), 5, estimate, None, weight[:5])
