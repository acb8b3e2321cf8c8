"""Shared helpers of the cross-package tests (the ROS environment is set in the root conftest)."""
