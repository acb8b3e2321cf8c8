"""Generate and build the graph's ROS 2 interface packages into a Python environment.

    python tools/build_interfaces.py            # into the running venv (what `make install` does)
    python tools/build_interfaces.py --check    # only check that the build tools are here

Builds, with the rosidl generators and ament_cmake of the ROS 2 wheels (PyPI), the packages
`tf2_msgs` (TFMessage only: `third_party/tf2_msgs`; not on PyPI) and `area3d_interfaces`, and
installs them with the environment's prefix as install prefix: the Python packages land in its
site-packages and their libraries in `<prefix>/lib`, which the ROS 2 wheels put on the library
path when Python starts. Nothing needs to be sourced afterwards.

Needs a C and a C++ compiler, make, CMake >= 3.21 and the headers of the Python that runs this
(`apt install build-essential cmake python3-dev`); they are checked first, by name. The build is
incremental: it runs again only when an interface package, this script, its CMake hook, the
Python or the ROS 2 wheels change (a digest kept in `<prefix>/.interfaces`). Only the standard
library is imported at module level, so `--check` runs before the environment exists.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import subprocess
import sys
import sysconfig
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# Built in this order; each is a plain ament_cmake interface package.
PACKAGES = (ROOT / "third_party" / "tf2_msgs", ROOT / "area3d_interfaces")
WHEEL_TARGETS_HOOK = Path(__file__).resolve().parent / "wheel_targets.cmake"
STAMP_NAME = ".interfaces"
MIN_CMAKE = (3, 21)
APT_HINT = "sudo apt install build-essential cmake python3-dev"
# Lines of a failed step's log shown on the terminal (the whole log stays on disk).
LOG_TAIL_LINES = 40
# What the generated packages must do once installed: load their C type support and serialise.
SMOKE_TEST = (
    "from rclpy.serialization import serialize_message\n"
    "from area3d_interfaces.msg import HardRegionArray\n"
    "from area3d_interfaces.srv import MapFile, NextBestView\n"
    "from tf2_msgs.msg import TFMessage\n"
    "for msg in (TFMessage(), NextBestView.Request(), MapFile.Response(), HardRegionArray()):\n"
    "    serialize_message(msg)\n"
)


def _cmake_version(cmake: str) -> tuple[int, ...] | None:
    try:
        out = subprocess.run(
            [cmake, "--version"], capture_output=True, text=True, check=True
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    words = out.split()
    if len(words) < 3 or words[:2] != ["cmake", "version"]:
        return None
    try:
        return tuple(int(part) for part in words[2].split("-")[0].split(".")[:2])
    except ValueError:
        return None


def _missing_compiler(env_var: str, names: tuple[str, ...], what: str) -> str | None:
    chosen = os.environ.get(env_var)
    if chosen:
        if shutil.which(chosen.split()[0]) is None:
            return f"{what} (${env_var} is {chosen!r}, which is not found)"
        return None
    if not any(map(shutil.which, names)):
        return f"{what} ({', '.join(names)} on PATH, or ${env_var})"
    return None


def missing_prerequisites() -> list[str]:
    """What the build lacks, one entry per missing tool, each naming where it was looked for."""
    missing = [
        problem
        for problem in (
            _missing_compiler("CC", ("cc", "gcc", "clang"), "a C compiler"),
            _missing_compiler("CXX", ("c++", "g++", "clang++"), "a C++ compiler"),
        )
        if problem
    ]
    if shutil.which("make") is None:
        missing.append("make (on PATH)")
    cmake = shutil.which("cmake")
    if cmake is None:
        missing.append(f"cmake >= {MIN_CMAKE[0]}.{MIN_CMAKE[1]} (on PATH)")
    else:
        version = _cmake_version(cmake)
        if version is None or version < MIN_CMAKE:
            found = ".".join(map(str, version)) if version else "unknown"
            missing.append(f"cmake >= {MIN_CMAKE[0]}.{MIN_CMAKE[1]} ({cmake} is version {found})")
    include = Path(sysconfig.get_paths()["include"])
    if not (include / "Python.h").is_file():
        version = f"{sys.version_info.major}.{sys.version_info.minor}"
        missing.append(
            f"the headers of Python {version} ({include / 'Python.h'} is missing; "
            f"python{version}-dev where python3 is another version)"
        )
    return missing


def check_prerequisites() -> None:
    """Exit with one message naming every missing build tool and how to install them."""
    missing = missing_prerequisites()
    if missing:
        lines = "\n".join(f"  - {item}" for item in missing)
        raise SystemExit(
            "Cannot build the ROS 2 interfaces (tf2_msgs, area3d_interfaces); missing:\n"
            f"{lines}\nOn Debian or Ubuntu: {APT_HINT}"
        )


def _package_files(package: Path) -> list[Path]:
    return sorted(
        path
        for path in package.rglob("*")
        if path.is_file() and "__pycache__" not in path.parts and path.name != "README.md"
    )


def inputs_digest() -> str:
    """Digest of everything a build depends on: the packages' files, this script and its hook,
    the Python and the versions of the installed ROS 2 wheels."""
    from importlib import metadata

    digest = hashlib.sha256()
    for path in [*(f for p in PACKAGES for f in _package_files(p)), Path(__file__).resolve(),
                 WHEEL_TARGETS_HOOK]:  # fmt: skip
        digest.update(str(path.relative_to(ROOT)).encode() + b"\0" + path.read_bytes() + b"\0")
    digest.update(sys.version.encode())
    wheels = sorted(
        f"{dist.metadata['Name']}=={dist.version}"
        for dist in metadata.distributions()
        if (dist.metadata["Name"] or "").lower().startswith(("ros-", "ros_", "numpy"))
    )
    digest.update("\n".join(wheels).encode())
    return digest.hexdigest()


def _site_packages(prefix: Path) -> Path:
    return Path(sysconfig.get_path("purelib", vars={"base": str(prefix), "platbase": str(prefix)}))


def _installed(prefix: Path) -> bool:
    site = _site_packages(prefix)
    return all((site / package.name / "__init__.py").is_file() for package in PACKAGES)


def _run_logged(command: list[str], log: Path, what: str) -> None:
    with log.open("a") as out:
        out.write(f"\n$ {' '.join(command)}\n")
        out.flush()
        result = subprocess.run(command, stdout=out, stderr=subprocess.STDOUT)
    if result.returncode != 0:
        tail = log.read_text(errors="replace").splitlines()[-LOG_TAIL_LINES:]
        raise SystemExit(
            "\n".join(tail) + f"\n{what} failed (exit {result.returncode}); full log: {log}"
        )


def build_package(package: Path, prefix: Path, build_root: Path, jobs: int) -> float:
    """Configure, build and install one interface package; returns the seconds it took."""
    import numpy

    start = time.monotonic()
    build = build_root / package.name
    build.mkdir(parents=True, exist_ok=True)
    log = build_root / f"{package.name}.log"
    log.write_text("")
    includes = ";".join((sysconfig.get_paths()["include"], numpy.get_include()))
    configure = [
        "cmake", "-S", str(package), "-B", str(build),
        f"-DCMAKE_INSTALL_PREFIX={prefix}",
        f"-DCMAKE_PREFIX_PATH={prefix}",
        "-DCMAKE_BUILD_TYPE=Release",
        "-DBUILD_TESTING=OFF",
        f"-DPython3_EXECUTABLE={sys.executable}",
        f"-DCMAKE_PROJECT_INCLUDE={WHEEL_TARGETS_HOOK}",
        f"-DAREA3D_PYTHON_INCLUDE_DIRS={includes}",
    ]  # fmt: skip
    _run_logged(configure, log, f"configuring {package.name}")
    _run_logged(
        ["cmake", "--build", str(build), "--parallel", str(jobs)], log, f"building {package.name}"
    )
    _run_logged(["cmake", "--install", str(build)], log, f"installing {package.name}")
    return time.monotonic() - start


def smoke_test() -> None:
    """Import and serialise the installed types in a fresh interpreter."""
    result = subprocess.run(
        [sys.executable, "-c", SMOKE_TEST], capture_output=True, text=True, cwd=os.sep
    )
    if result.returncode != 0:
        raise SystemExit(
            f"{result.stderr}\nThe built interfaces do not load (above); rebuild with --force."
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="only check the build tools")
    parser.add_argument("--force", action="store_true", help="build even if nothing changed")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="parallel jobs")
    args = parser.parse_args(argv)

    check_prerequisites()
    if args.check:
        return 0
    if sys.prefix == sys.base_prefix:
        raise SystemExit(
            "Not in a virtual environment: run this with the venv's python (make install does)."
        )
    prefix = Path(sys.prefix)
    stamp = prefix / STAMP_NAME
    digest = inputs_digest()
    if not args.force and _installed(prefix) and stamp.is_file():
        if stamp.read_text().strip() == digest:
            print("ROS 2 interfaces up to date (tf2_msgs, area3d_interfaces)")
            stamp.touch()
            return 0
    stamp.unlink(missing_ok=True)
    build_root = prefix / "build" / "interfaces"
    for package in PACKAGES:
        print(f"Building ROS 2 interfaces: {package.name} ...", flush=True)
        seconds = build_package(package, prefix, build_root, max(1, args.jobs))
        print(f"  {package.name} built and installed in {seconds:.0f} s", flush=True)
    smoke_test()
    stamp.write_text(digest + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
