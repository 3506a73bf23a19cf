"""One thread for each native library's pool (OpenCV, BLAS, OpenMP) while SLAM runs.

The pipeline brings its own parallelism: frames are read on a thread and the iSAM2
backend runs in a process. Native pools that spread each call over both cores then
fight those for them: beside a busy process, 60 7-Scenes frames took the front end
3.3 s with the default pools and 0.65-0.93 s with one thread each (0.62 s alone).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator


@contextlib.contextmanager
def single_native_threads() -> Iterator[None]:
    """Within the block, OpenCV and every pool threadpoolctl knows (OpenBLAS, MKL,
    OpenMP) use one thread; the previous settings come back afterwards."""
    import cv2
    from threadpoolctl import threadpool_limits

    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        cv2.setNumThreads(before)
