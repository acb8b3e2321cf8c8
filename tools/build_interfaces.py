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

A build's installed files (2 MB) are kept in a cache per user, by the digest of its inputs
(`$AREA3D_CACHE_DIR`, else `$XDG_CACHE_HOME/area3d`, else `~/.cache/area3d`; under
`interfaces/<digest>`, the newest `CACHE_KEPT`): another clone or venv with the same inputs
copies them into its prefix (about a second, where a build takes 20-25 s on 2 cores), with the
paths of the prefix that built them rewritten to its own, and loads them (the smoke test) before
it uses them; a copy that does not load is built. `--no-cache` builds and keeps nothing.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# Built in this order; each is a plain ament_cmake interface package.
PACKAGES = (ROOT / "third_party" / "tf2_msgs", ROOT / "area3d_interfaces")
WHEEL_TARGETS_HOOK = Path(__file__).resolve().parent / "wheel_targets.cmake"
STAMP_NAME = ".interfaces"
CACHE_KEPT = 4  # builds kept in the cache (the newest)
PREFIX_MARK = b"@AREA3D_INTERFACES_PREFIX@"  # the building prefix, in a cached file
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
    digest.update(sys.version.encode() + sysconfig.get_platform().encode())
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
    error = _load_error()
    if error:
        raise SystemExit(
            f"{error}\nThe built interfaces do not load (above); rebuild with --force."
        )


def _load_error() -> str:
    result = subprocess.run(
        [sys.executable, "-c", SMOKE_TEST], capture_output=True, text=True, cwd=os.sep
    )
    return "" if result.returncode == 0 else result.stderr or f"exit {result.returncode}"


def cache_root() -> Path:
    """The per-user cache of built interfaces (see the module's docstring)."""
    if os.environ.get("AREA3D_CACHE_DIR"):
        return Path(os.environ["AREA3D_CACHE_DIR"]) / "interfaces"
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "area3d" / "interfaces"


def keep_in_cache(prefix: Path, build_root: Path, digest: str) -> None:
    """Copy the files the build installed (its install manifests) into the cache, written whole
    (a temporary folder renamed) and the prefix's path in them marked; then keep the newest
    `CACHE_KEPT` builds. A cache that cannot be written is skipped with a note."""
    root = cache_root()
    staging = None
    try:
        root.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{digest[:12]}-", dir=root))
        names = []
        for package in PACKAGES:
            manifest = build_root / package.name / "install_manifest.txt"
            for line in manifest.read_text().splitlines():
                path = Path(line)
                if not path.is_file():
                    continue
                name = path.relative_to(prefix)
                data = path.read_bytes()
                if bytes(prefix) in data and b"\0" in data:  # a binary: no path rewritten in it
                    raise OSError(f"{name} holds the path {prefix} and is not text")
                target = staging / "files" / name
                target.parent.mkdir(parents=True, exist_ok=True)
                target.write_bytes(data.replace(bytes(prefix), PREFIX_MARK))
                shutil.copymode(path, target)
                names.append(str(name))
        (staging / "manifest.txt").write_text("\n".join(names) + "\n")
        final = root / digest
        if final.exists():
            shutil.rmtree(staging)
        else:
            staging.rename(final)
        builds = sorted(
            (p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")),
            key=lambda p: p.stat().st_mtime,
        )
        for old in builds[:-CACHE_KEPT]:
            shutil.rmtree(old, ignore_errors=True)
    except OSError as exc:
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)
        print(f"  (the build was not cached: {exc})", flush=True)


def restore_from_cache(prefix: Path, digest: str) -> bool:
    """The cached build of `digest` copied into `prefix` (its marked paths made `prefix`'s); True
    if there was one and it loads (the smoke test)."""
    cached = cache_root() / digest
    try:
        names = (cached / "manifest.txt").read_text().split()
        for name in names:
            source, target = cached / "files" / name, prefix / name
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(source.read_bytes().replace(PREFIX_MARK, bytes(prefix)))
            shutil.copymode(source, target)
        os.utime(cached)  # the newest used: kept longest
    except OSError:
        return False
    error = _load_error()
    if error:
        print(f"  the cached build does not load here; building ({error.splitlines()[-1]})")
    return not error


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="only check the build tools")
    parser.add_argument("--force", action="store_true", help="build even if nothing changed")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="parallel jobs")
    parser.add_argument("--no-cache", action="store_true", help="neither use nor fill the cache")
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
    start = time.monotonic()
    if not args.force and not args.no_cache and restore_from_cache(prefix, digest):
        print(
            f"ROS 2 interfaces (tf2_msgs, area3d_interfaces) copied from the cache of builds "
            f"({cache_root() / digest}) in {time.monotonic() - start:.1f} s"
        )
        stamp.write_text(digest + "\n")
        return 0
    build_root = prefix / "build" / "interfaces"
    for package in PACKAGES:
        print(f"Building ROS 2 interfaces: {package.name} ...", flush=True)
        seconds = build_package(package, prefix, build_root, max(1, args.jobs))
        print(f"  {package.name} built and installed in {seconds:.0f} s", flush=True)
    smoke_test()
    if not args.no_cache:
        keep_in_cache(prefix, build_root, digest)
    stamp.write_text(digest + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
