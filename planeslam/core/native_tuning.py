"""Process-wide settings of native libraries, applied only where a caller asks.

`single_native_threads`: one thread for each native library's pool (OpenCV, BLAS,
OpenMP, Open3D's TBB) within a block, restored afterwards. `keep_freed_memory`: a glibc
allocator setting for the whole process; the CLI turns it on, the library never does.

The pipeline brings its own parallelism: frames are read on a thread and the iSAM2
backend runs in a process. Native pools that spread each call over both cores then
fight those for them: beside a busy process, 60 7-Scenes frames took the front end
3.3 s with the default pools and 0.65-0.93 s with one thread each (0.62 s alone).
One thread also makes a run repeat: Open3D's RGB-D odometry (the dense fallback) sums
its normal equations over TBB threads in whatever order they finish, so two runs of
one sequence parted in the last bit and, where tracking decides a tie, by centimetres.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import sys
from collections.abc import Iterator

log = logging.getLogger(__name__)


@contextlib.contextmanager
def single_native_threads() -> Iterator[None]:
    """Within the block, OpenCV, Open3D (when imported) and every pool threadpoolctl
    knows (OpenBLAS, MKL, OpenMP) use one thread; the previous settings come back
    afterwards. Open3D is not imported here: the backend worker never loads it."""
    import cv2
    from threadpoolctl import threadpool_limits

    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    open3d_threads = _open3d_max_threads(1)
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        cv2.setNumThreads(before)
        if open3d_threads is not None:
            _open3d_max_threads(open3d_threads)


def _open3d_max_threads(limit: int) -> int | None:
    """Set Open3D's thread limit (`open3d.utility.set_max_threads`, Open3D >= 0.20) when
    Open3D is imported; returns the limit before, or None when not imported or too old."""
    o3d = sys.modules.get("open3d")
    utility = getattr(o3d, "utility", None)
    if utility is None or not hasattr(utility, "set_max_threads"):
        return None
    before = int(utility.get_max_threads())
    utility.set_max_threads(limit)
    return before


_MALLOC_TUNED = False


def keep_freed_memory() -> bool:
    """Ask glibc malloc to serve blocks up to 32 MB from its heap and keep freed memory
    (mallopt M_MMAP_THRESHOLD = 32 MB, M_TRIM_THRESHOLD = 256 MB), once per process.

    By default every array above 128 kB is a fresh mmap that the kernel zero-fills
    page by page on first touch and unmaps on free: per 640x480 frame the front end
    makes dozens of such arrays, and those page faults cost about a sixth of its
    time. Returns True when applied; a no-op (False) off Linux/glibc.
    """
    global _MALLOC_TUNED
    if _MALLOC_TUNED:
        return True
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        ok = libc.mallopt(-3, 32 * 1024 * 1024) == 1  # M_MMAP_THRESHOLD
        ok &= libc.mallopt(-1, 256 * 1024 * 1024) == 1  # M_TRIM_THRESHOLD
    except (OSError, AttributeError):
        return False
    _MALLOC_TUNED = bool(ok)
    log.debug("malloc tuned for large temporaries: %s", _MALLOC_TUNED)
    return _MALLOC_TUNED
