"""Shared fixtures for the cross-package tests: each DDS test gets its own loopback domain."""

from __future__ import annotations

import itertools
import os

import pytest

from area3d_msgs_py import dds_config

_counter = itertools.count()


@pytest.fixture()
def dds_domain() -> int:
    """A test-unique ROS_DOMAIN_ID with Cyclone DDS pinned to 127.0.0.1 (for this process and children)."""
    domain_id = 1 + (os.getpid() + 53 + 7 * next(_counter)) % 200
    dds_config.use_loopback(domain_id)
    return domain_id
