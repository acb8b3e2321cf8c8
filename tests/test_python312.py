"""Python 3.12, the Python of ROS 2 Jazzy's platform (Ubuntu 24.04): the package admits it, and
every package the install pins, with everything those pull in, has a CPython 3.12 manylinux
x86_64 wheel on the package index at the version installed here (a pure-Python package that is
published as a source archive only needs that archive).

Checked from the index's file lists alone (PEP 691 JSON), without downloading or installing a
wheel: this index serves no separate wheel metadata, so `pip install --dry-run --python-version
3.12` downloads every wheel it considers (open3d alone is 400 MB) and backtracked for minutes.
The dependency set is the one this environment resolved (`make install`), followed from the
project's requirements with their markers evaluated for Python 3.12 on Linux; a requirement that
applies only on 3.12 (not installed here) needs some version within its specifier.
"""

from __future__ import annotations

import importlib.metadata as md
import os
import re
import tomllib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import requests
from packaging import tags
from packaging.requirements import Requirement
from packaging.specifiers import SpecifierSet
from packaging.utils import canonicalize_name, parse_wheel_filename
from packaging.version import InvalidVersion, Version

ROOT = Path(__file__).resolve().parents[1]
INDEX = os.environ.get("PIP_INDEX_URL", "https://pypi.org/simple").rstrip("/")
PYTHON = (3, 12)
PYTHON_FULL = "3.12.3"  # Ubuntu 24.04's
# Ubuntu 24.04 has glibc 2.39: every manylinux tag up to 2.39 installs there
PLATFORMS = [f"manylinux_2_{minor}_x86_64" for minor in range(39, 4, -1)] + [
    "manylinux2014_x86_64",
    "manylinux2010_x86_64",
    "manylinux1_x86_64",
    "linux_x86_64",
]
MARKER_ENV = {
    "python_version": "3.12",
    "python_full_version": PYTHON_FULL,
    "implementation_name": "cpython",
    "platform_python_implementation": "CPython",
    "sys_platform": "linux",
    "platform_system": "Linux",
    "platform_machine": "x86_64",
    "os_name": "posix",
}
INSTALLED_EXTRAS = ("ros", "dev")  # what `make install` installs
TOP_LEVEL_ONLY_EXTRAS = ("ml",)  # torch: its CUDA wheels are gigabytes; its own pin is checked


def _supported() -> set[tags.Tag]:
    return set(tags.cpython_tags(PYTHON, platforms=PLATFORMS)) | set(
        tags.compatible_tags(PYTHON, "cp312", PLATFORMS)
    )


def _applies(requirement: Requirement, extras: tuple[str, ...]) -> bool:
    if requirement.marker is None:
        return True
    return any(
        requirement.marker.evaluate({**MARKER_ENV, "extra": extra}) for extra in extras or ("",)
    )


def _installed(name: str) -> md.Distribution | None:
    try:
        return md.distribution(name)
    except md.PackageNotFoundError:
        return None


def dependency_set() -> dict[str, tuple[SpecifierSet, str | None]]:
    """{package: (specifier, version installed here or None)} for the project with the extras
    `make install` installs, followed through every requirement that applies on Python 3.12."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    roots = [Requirement(text.split("#")[0]) for text in project["dependencies"]]
    for extra in INSTALLED_EXTRAS:
        roots += [Requirement(text) for text in project["optional-dependencies"][extra]]
    out: dict[str, tuple[SpecifierSet, str | None]] = {}
    todo = [(r, ()) for r in roots]
    while todo:
        requirement, extras = todo.pop()
        if not _applies(requirement, extras):
            continue
        name = canonicalize_name(requirement.name)
        if name in out:
            continue
        dist = _installed(name)
        version = dist.version if dist is not None else None
        if version is not None and not requirement.specifier.contains(version, prereleases=True):
            version = None  # a 3.12-only requirement that this environment does not have
        out[name] = (requirement.specifier, version)
        if dist is not None and version is not None:
            wanted = tuple(requirement.extras) or ("",)
            todo += [(Requirement(text), wanted) for text in dist.requires or ()]
    return out


def wheel_for_312(name: str, specifier: SpecifierSet, version: str | None) -> str | None:
    """A wheel on the index for CPython 3.12 on manylinux x86_64 at `version` (or, without one,
    at a version within `specifier`); None when there is none."""
    response = requests.get(
        f"{INDEX}/{name}/", headers={"Accept": "application/vnd.pypi.simple.v1+json"}, timeout=60
    )
    response.raise_for_status()
    supported = _supported()
    for file in response.json()["files"]:
        filename = file["filename"]
        if not filename.endswith(".whl") or file.get("yanked"):
            continue
        try:
            _, wheel_version, _, wheel_tags = parse_wheel_filename(filename)
        except (ValueError, InvalidVersion):
            continue
        if version is not None and wheel_version != Version(version):
            continue
        if version is None and not specifier.contains(wheel_version):
            continue
        requires_python = file.get("requires-python")
        if requires_python and PYTHON_FULL not in SpecifierSet(requires_python):
            continue
        if wheel_tags & supported:
            return filename
    if version is not None and _pure_python(name):
        # a pure-Python package published as a source archive only (empy, which ROS's
        # rosidl_adapter needs): it builds on any Python, as it did here
        for file in response.json()["files"]:
            if file["filename"].endswith(".tar.gz") and f"-{version}.tar.gz" in file["filename"]:
                return file["filename"]
    return None


def _pure_python(name: str) -> bool:
    """Installed here without a compiled extension module."""
    dist = _installed(name)
    return dist is not None and not any(
        str(f).endswith((".so", ".pyd")) or ".so." in str(f) for f in dist.files or ()
    )


def test_the_package_admits_python_311_and_312():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    admitted = SpecifierSet(project["requires-python"])
    assert "3.11.9" in admitted and PYTHON_FULL in admitted and "3.10.12" not in admitted


def test_the_ros_wheels_are_an_extra_that_make_install_installs():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = {Requirement(t.split("#")[0]).name for t in project["dependencies"]}
    ros = {Requirement(t).name for t in project["optional-dependencies"]["ros"]}
    assert {"ros-jazzy-rclpy", "ros-jazzy-common-interfaces", "ros-jazzy-rmw-fastrtps-cpp"} <= ros
    assert not any(name.startswith("ros-") for name in core)
    installed = re.search(
        r'pip install --quiet(?: --[a-z-]+(?: \S+)?)* -e "\.\[([a-z,]+)\]"',
        (ROOT / "Makefile").read_text(),
    )
    assert installed and "ros" in installed.group(1).split(",")


def test_every_pinned_package_and_its_dependencies_have_cpython_312_wheels():
    packages = dependency_set()
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    for extra in TOP_LEVEL_ONLY_EXTRAS:
        for text in project["optional-dependencies"][extra]:
            requirement = Requirement(text)
            (pin,) = requirement.specifier
            packages[canonicalize_name(requirement.name)] = (requirement.specifier, pin.version)
    # the pins themselves are in the set, at their pinned versions
    for text in project["dependencies"]:
        requirement = Requirement(text.split("#")[0])
        (pin,) = requirement.specifier
        assert packages[canonicalize_name(requirement.name)][1] == pin.version, requirement
    assert len(packages) > 40  # numpy, rclpy and the ROS wheels, their dependencies...
    with ThreadPoolExecutor(max_workers=8) as pool:
        wheels = dict(
            zip(
                packages,
                pool.map(lambda item: wheel_for_312(item[0], *item[1]), packages.items()),
                strict=True,
            )
        )
    missing = {
        name: packages[name][1] or str(packages[name][0]) for name, w in wheels.items() if w is None
    }
    assert not missing, f"no CPython 3.12 manylinux x86_64 wheel on {INDEX} for {missing}"
