"""The iSAM2 backend beside tracking: in a child process (the second core) or inline.

`SLAM` submits each keyframe and goes on tracking; the keyframe's update (its
optimised pose and the estimates of the landmarks it saw) is collected
`backend.lag_frames` frames later, while the smoother has worked on it beside the
front end. `inline` runs the same schedule in this process: the same results
without the parallelism (tests, debugging, one-core machines).

Why a process: gtsam holds the GIL through `ISAM2.update`, so a thread would not
run beside the front end. What crosses the pipe is small and typed: a `KeyframeInput`
(its `FrameMeasurements`: planes' normal, offset and fit covariance, corners, edges;
none of its pixels or points) one way, a `KeyframeUpdate` or `BackendResult` back.
Errors raised in the child (a `PlaneSlamError` such as the GeometryError of an
update that cannot be made well posed) are raised again here when that keyframe's
update is collected (inline: at once).
"""

from __future__ import annotations

import collections
import logging
import multiprocessing
import os
import queue
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from planeslam.backend.base import BackendKind, BackendResult, KeyframeInput, KeyframeUpdate
from planeslam.backend.config import BackendConfig
from planeslam.backend.keyframes import is_keyframe
from planeslam.core.errors import PlaneSlamError
from planeslam.core.native_tuning import single_native_threads
from planeslam.core.resources import peak_rss_mb

if TYPE_CHECKING:
    from planeslam.backend.isam2 import Isam2Backend

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class _AddKeyframe:
    keyframe: KeyframeInput


@dataclass(frozen=True)
class _Finish:
    iterations: int
    """Gauss-Newton iterations of the final batch (0: none)."""


@dataclass(frozen=True)
class _Close:
    pass


_Request = _AddKeyframe | _Finish | _Close


@dataclass(frozen=True)
class _Reply:
    value: KeyframeUpdate | BackendResult | None = None
    error: PlaneSlamError | None = None
    gone: bool = False
    """The child's end of the connection closed (it exited or died)."""


class Isam2Worker:
    """The iSAM2 `Backend`: an `Isam2Backend` driven ahead of the caller. `submit`
    keyframes, `collect` their updates in the same order (each waits for its own),
    `finish` for the optimised whole."""

    kind = BackendKind.ISAM2
    objects_every_keyframe = False
    takes_loops = True
    map_cull_single_view_after = 5
    map_merge_segments = True

    def __init__(self, config: BackendConfig, inline: bool = False) -> None:
        self.config = config
        self.lag_frames = config.lag_frames
        self.inline = inline
        self.pending = 0
        """Keyframes submitted and not collected yet."""
        self._closed = False
        self._replies: collections.deque[_Reply] | queue.SimpleQueue[_Reply]
        if inline:
            from planeslam.backend.isam2 import Isam2Backend

            self._backend: Isam2Backend | None = Isam2Backend(config)
            self._replies = collections.deque()
            return
        self._backend = None
        self._process, self._conn = _start_worker(config)
        # Replies are drained on a thread (it waits in recv without the GIL), so neither
        # side can block on a full pipe while the other one does too.
        self._replies = queue.SimpleQueue()
        self._receiver = threading.Thread(
            target=self._receive, name="planeslam-backend-replies", daemon=True
        )
        self._receiver.start()
        self._reply()  # 'ready': the child has imported gtsam (start-up, not run time)

    def is_keyframe(
        self, T_keyframes: np.ndarray, T_now: np.ndarray, frames_since: int, new_planes: int
    ) -> bool:
        return is_keyframe(
            self.config, T_keyframes[-1], T_now, frames_since, new_planes, T_keyframes[:-1]
        )

    def submit(self, keyframe: KeyframeInput) -> None:
        """Hand a keyframe to the smoother (see `Isam2Backend.add_keyframe`) without
        waiting for it."""
        self._send(_AddKeyframe(keyframe))
        self.pending += 1

    def collect(self) -> KeyframeUpdate:
        """The update of the oldest keyframe not collected yet (waits for it)."""
        if not self.pending:
            raise PlaneSlamError("Isam2Worker.collect: no keyframe was submitted")
        self.pending -= 1
        update = self._reply()
        assert isinstance(update, KeyframeUpdate)
        return update

    def finish(self) -> BackendResult:
        """Run the final batch optimisation (`final_iterations` Gauss-Newton steps) after
        every submitted keyframe and return the smoother's final state (updates not
        collected are dropped); then close."""
        while self.pending:
            self.collect()
        self._send(_Finish(self.config.final_iterations))
        try:
            result = self._reply()
            assert isinstance(result, BackendResult)
            return result
        finally:
            self.close()

    def close(self) -> None:
        """Stop the worker process (idempotent). With keyframes still queued (an
        interrupted run) the child is stopped at once rather than after them."""
        if self._closed:
            return
        self._closed = True
        busy, self.pending = self.pending, 0
        if self.inline:
            self._backend = None
            return
        try:
            self._conn.send(_Close())
        except (OSError, ValueError):
            pass
        try:
            self._process.wait(timeout=0.2 if busy else 5)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        self._receiver.join(timeout=5)  # the child's end is closed: it has seen EOF
        self._conn.close()

    # ------------------------------------------------------------------ plumbing

    def _send(self, request: _Request) -> None:
        if self._closed:
            raise PlaneSlamError("the iSAM2 backend has finished; create a new SLAM")
        if self._backend is not None:
            self._replies.append(_answer(self._backend, request))  # type: ignore[union-attr]
            return
        try:
            self._conn.send(request)
        except (OSError, ValueError) as exc:
            raise PlaneSlamError(f"the iSAM2 backend process is gone ({exc})") from None

    def _receive(self) -> None:
        while True:
            try:
                self._replies.put(self._conn.recv())  # type: ignore[union-attr]
            except (EOFError, OSError):
                self._replies.put(_Reply(gone=True))  # type: ignore[union-attr]
                return

    def _reply(self) -> KeyframeUpdate | BackendResult | None:
        if isinstance(self._replies, collections.deque):
            reply = self._replies.popleft()
        else:
            reply = self._replies.get()
        if reply.gone:
            code = self._process.poll()
            self.close()
            raise PlaneSlamError(f"the iSAM2 backend process died (exit code {code})")
        if reply.error is not None:
            raise reply.error
        return reply.value


def _answer(backend: Isam2Backend, request: _Request) -> _Reply:
    """Run one request on `backend` (in the worker process, or inline)."""
    try:
        return _Reply(value=_handle(backend, request))
    except PlaneSlamError as exc:
        return _Reply(error=exc)
    except Exception as exc:  # anything else still reaches the caller, as one line
        return _Reply(error=PlaneSlamError(f"iSAM2 backend: {type(exc).__name__}: {exc}"))


def _handle(backend: Isam2Backend, request: _Request) -> KeyframeUpdate | BackendResult:
    if isinstance(request, _AddKeyframe):
        kf = request.keyframe
        T = backend.add_keyframe(
            kf.index,
            kf.timestamp,
            kf.T_world_cam,
            kf.measurements,
            kf.plane_ids,
            kf.corner_ids,
            kf.T_prev_cam,
            joined_planes=kf.joined_planes,
            loops=kf.loops,
            odometry=kf.odometry,
            relocalised=kf.relocalised,
        )
        return KeyframeUpdate(
            index=kf.index,
            T_world_cam=T,
            planes=backend.plane_estimates(kf.plane_ids.values()),
            corners=backend.corner_estimates(kf.corner_ids.values()),
            update_ms=backend.update_ms[-1],
            covariance=backend.pose_covariance(kf.index),
            rejected=backend.last_rejected,
        )
    if isinstance(request, _Finish):
        iterations = request.iterations
        batch_ms = backend.optimize_batch(iterations, last=True) if iterations else 0.0
        return BackendResult(
            keyframe_poses={i: T for i, (_, T) in backend.keyframe_poses().items()},
            planes=backend.plane_estimates(),
            corners=backend.corner_estimates(),
            update_ms=list(backend.update_ms),
            batch_ms=batch_ms,
            failures=backend.failures,
            num_factors=backend.num_factors,
            peak_rss_mb=peak_rss_mb() if _IN_CHILD else 0.0,
            rejected=tuple(backend.rejected),
        )
    raise ValueError(f"unknown backend request {request!r}")


def _start_worker(config: BackendConfig) -> tuple[subprocess.Popen, Connection]:
    """A fresh interpreter running `serve`, and the connection to it.

    Not `multiprocessing.Process`: 'fork' would copy gtsam's TBB threads in an unusable
    state, and 'spawn' re-runs the caller's main script (a script without an
    `if __name__ == "__main__"` guard would start SLAM again in the child). Only the
    connection comes from multiprocessing: one end of its `Pipe`, passed by descriptor.

    The child runs isolated (`python -I`): neither the working directory (`-c` would put it
    first on `sys.path`, so a gtsam.py there would run) nor PYTHONPATH nor the user's
    site-packages; `child_path` adds back the folder planeslam itself was imported from.
    """
    conn, child_conn = multiprocessing.Pipe()
    process = subprocess.Popen(
        [sys.executable, "-I", "-c", _CHILD_CODE, str(child_conn.fileno()), *child_path()],
        pass_fds=(child_conn.fileno(),),
    )
    child_conn.close()
    conn.send(config)
    return process, conn


def child_path() -> list[str]:
    """Folders an isolated child appends to its `sys.path` to import planeslam as this
    process did: the folder holding the planeslam package (a checkout run without
    installing), last, so it never shadows an installed module."""
    import planeslam

    return [str(Path(planeslam.__file__).resolve().parents[1])]


_CHILD_CODE = (
    "import sys; sys.path.extend(sys.argv[2:]); "
    "from planeslam.backend.worker import serve; serve(int(sys.argv[1]))"
)


_IN_CHILD = False
"""Set in the worker process (its memory is then the backend's own)."""


def serve(fd: int) -> None:
    """The worker process, on connection descriptor `fd`: a `BackendConfig`, then requests
    in and replies out, until 'close' or a closed connection."""
    global _IN_CHILD
    _IN_CHILD = True
    # Ctrl-C and SIGTERM (which `timeout` sends to the whole process group) are the
    # parent's to handle: it stops this process, which also exits when the parent dies.
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, signal.SIG_IGN)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    from planeslam.backend.isam2 import Isam2Backend

    conn = Connection(fd)
    try:
        backend = Isam2Backend(conn.recv())
        conn.send(_Reply())  # ready
    except (EOFError, OSError):
        return
    with single_native_threads():
        _serve_requests(conn, backend)
    # Done: skip the interpreter's teardown (freeing the smoother and every module takes
    # about 0.1 s, which the parent's `close` waits for at the end of each run).
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def _serve_requests(conn: Connection, backend: Isam2Backend) -> None:
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        if isinstance(request, _Close):
            return
        conn.send(_answer(backend, request))
