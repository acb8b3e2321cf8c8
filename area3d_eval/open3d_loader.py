"""Import open3d with the libusb it links against preloaded from the `libusb-package` wheel.

The open3d wheel links libusb-1.0 (for RealSense support) but does not ship it; on a machine
without the system package, `import open3d` fails. The `libusb-package` wheel carries the library,
so loading it globally first makes open3d importable with nothing but the package registries.
"""

from __future__ import annotations

import ctypes
import functools
from types import ModuleType


@functools.cache
def import_open3d() -> ModuleType:
    """The `open3d` module, importable whether or not the system has libusb-1.0."""
    try:
        import libusb_package

        path = libusb_package.get_library_path()
        if path is not None:
            ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
    except (ImportError, OSError):
        pass  # fall back to a system libusb, if any; the import below says what is missing
    import open3d

    return open3d
