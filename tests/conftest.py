"""Shared fixtures for the cross-package tests: each DDS test gets its own loopback domain."""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator

import pytest

from area3d_msgs_py import dds_config

_counter = itertools.count()


@pytest.fixture()
def dds_domain() -> Iterator[int]:
    """A test-unique ROS_DOMAIN_ID with Cyclone DDS pinned to 127.0.0.1 (for this process and children)."""
    with dds_config.loopback_domain(1 + (os.getpid() + 53 + 7 * next(_counter)) % 200) as domain_id:
        yield domain_id
