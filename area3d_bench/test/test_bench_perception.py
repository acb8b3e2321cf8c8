"""The perception benchmark times frames the node really processes (no speed is asserted)."""

import pytest

from area3d_bench.perception import node_frames, synthetic_frame, timed


def test_a_node_frame_goes_through_the_node_and_is_timed():
    depth, K, T = synthetic_frame(width=64, height=48)
    with node_frames(depth, K, T) as frame:
        figures = timed(frame, repeats=3)
    assert 0 < figures["wall_p10"] <= figures["wall"] <= figures["wall_p90"]
    assert 0 < figures["cpu_p10"] <= figures["cpu"] <= figures["cpu_p90"]
    assert figures["wall"] < 60_000  # a sanity bound, not a speed requirement


def test_frames_the_node_does_not_publish_fail_the_measurement():
    depth, K, T = synthetic_frame(width=64, height=48)
    # The stereo backend waits for a right image that never comes: nothing is published.
    with pytest.raises(RuntimeError, match="published 0 of 1 frames"):
        with node_frames(depth, K, T, {"backend": "stereo"}) as frame:
            frame()
