"""The TF benchmark times real lookups that give the trajectory's pose (no speed is asserted)."""

from area3d_bench.tf import run_bench


def test_the_tf_benchmark_times_lookups_that_are_right():
    figures = run_bench(seconds=12.0)
    assert figures["frames"] > 300
    assert figures["error_m"] < 1e-4  # interpolated between 50 Hz samples of a 0.5 m/s circle
    for path in ("tf", "odometry"):
        assert 0 < figures[f"{path}_lookup_p50_us"] <= figures[f"{path}_frame_p50_us"]
        assert figures[f"{path}_frame_p50_us"] < 1e6  # a sanity bound, not a speed requirement
