"""TSDF reconstruction, metrics, baselines, benchmarks and reports."""
