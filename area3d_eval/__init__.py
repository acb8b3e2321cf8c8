"""TSDF reconstruction, metrics, baselines and reports."""
