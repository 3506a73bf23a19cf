"""The iSAM2 backend beside tracking: in a child process (the second core) or inline.

`SLAM` submits each keyframe and goes on tracking; the keyframe's result (its
optimised pose and the estimates of the landmarks it saw) is collected
`backend.lag_frames` frames later, while the smoother has worked on it beside the
front end. `inline` runs the same schedule in this process: the same results
without the parallelism (tests, debugging, one-core machines).

Why a process: gtsam holds the GIL through `ISAM2.update`, so a thread would not
run beside the front end. What crosses the pipe is small: a keyframe's planes
(normal, offset, fit covariance), corners and edges, none of its pixels or points.
Errors raised in the child (a `PlaneSlamError` such as the GeometryError of an
update that cannot be made well posed) are raised again here when that keyframe's
result is collected (inline: at once).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import multiprocessing
import os
import queue
import signal
import subprocess
import sys
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any

import numpy as np

from planeslam.backend.config import BackendConfig
from planeslam.backend.isam2 import Isam2Backend
from planeslam.core.errors import PlaneSlamError
from planeslam.core.native_tuning import single_native_threads

if TYPE_CHECKING:
    from planeslam.frontend.pipeline import FrameObservation


@dataclass(frozen=True)
class KeyframeUpdate:
    """What the smoother made of one keyframe."""

    index: int
    """Frame index of the keyframe."""
    T_world_cam: np.ndarray
    """(4, 4) its pose after its own update."""
    planes: dict[int, tuple[np.ndarray, float]]
    """Plane landmark id -> (n_world (3,), d_world [m]) after the update, for the planes
    this keyframe saw."""
    corners: dict[int, np.ndarray]
    """Corner landmark id -> p_world (3,) [m] after the update, for its corners."""
    update_ms: float
    """Wall-clock ms of the iSAM2 work for this keyframe (in the worker)."""


@dataclass(frozen=True)
class BackendResult:
    """The smoother's final state (after the batch optimisation of `finish`)."""

    keyframe_poses: dict[int, tuple[float, np.ndarray]]
    """Keyframe index -> (timestamp [s], optimised T_world_cam (4, 4))."""
    planes: dict[int, tuple[np.ndarray, float]]
    corners: dict[int, np.ndarray]
    update_ms: list[float]
    """Per keyframe, as in `KeyframeUpdate.update_ms`."""
    batch_ms: float
    """Wall-clock ms of the final batch optimisation."""
    failures: int
    """Indeterminate updates caught and handled."""
    num_factors: int


def landmark_observation(observation: FrameObservation) -> FrameObservation:
    """The parts of an observation the landmark factors read (planes' id, normal,
    offset and fit covariance; corners; edges), without pixels, points, outlines or
    objects: a few kB to send to another process instead of megabytes."""
    empty = np.empty((0, 3))
    planes = [
        dataclasses.replace(p, points=empty, outline=empty) for p in observation.segmentation.planes
    ]
    structure = observation.structure
    return dataclasses.replace(
        observation,
        segmentation=dataclasses.replace(
            observation.segmentation, planes=planes, labels=np.empty((0, 0), np.int32)
        ),
        structure=dataclasses.replace(structure, graph=type(structure.graph)(), objects=[]),
        cloud=None,
    )


class BackendWorker:
    """An `Isam2Backend` driven ahead of the caller: `submit` keyframes, `collect` their
    updates in the same order (each waits for its own), `finish` for the optimised whole."""

    def __init__(self, config: BackendConfig, inline: bool = False) -> None:
        self.inline = inline
        self.pending = 0
        """Keyframes submitted and not collected yet."""
        self._closed = False
        if inline:
            self._backend: Isam2Backend | None = Isam2Backend(config)
            self._replies: Any = collections.deque()
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
        self._result()  # 'ready': the child has imported gtsam (start-up, not run time)

    def submit(
        self,
        index: int,
        timestamp: float,
        T_world_cam_guess: np.ndarray,
        observation: FrameObservation,
        plane_ids: Mapping[int, int],
        corner_ids: Mapping[int, int],
        odometry_T_prev_cur: np.ndarray | None,
    ) -> None:
        """Hand keyframe `index` to the smoother (see `Isam2Backend.add_keyframe`) without
        waiting for it."""
        args = (
            index,
            timestamp,
            np.asarray(T_world_cam_guess, dtype=np.float64),
            landmark_observation(observation),
            dict(plane_ids),
            dict(corner_ids),
            odometry_T_prev_cur,
        )
        self._call("keyframe", args)
        self.pending += 1

    def collect(self) -> KeyframeUpdate:
        """The update of the oldest keyframe not collected yet (waits for it)."""
        if not self.pending:
            raise PlaneSlamError("BackendWorker.collect: no keyframe was submitted")
        self.pending -= 1
        return self._result()

    def finish(self, iterations: int) -> BackendResult:
        """Run the final batch optimisation (`iterations` Gauss-Newton steps, 0 for none)
        after every submitted keyframe and return the smoother's final state (updates
        not collected are dropped); then close."""
        while self.pending:
            self.collect()
        self._call("finish", iterations)
        try:
            return self._result()
        finally:
            self.close()

    def close(self) -> None:
        """Stop the worker process (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self.pending = 0
        if self.inline:
            self._backend = None
            return
        try:
            self._conn.send(("close", None))
        except (OSError, ValueError):
            pass
        try:
            self._process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        self._receiver.join(timeout=5)  # the child's end is closed: it has seen EOF
        self._conn.close()

    # ------------------------------------------------------------------ plumbing

    def _call(self, kind: str, payload: Any) -> None:
        if self._closed:
            raise PlaneSlamError("the iSAM2 backend has finished; create a new SLAM")
        if self.inline:
            self._replies.append(_handle(self._backend, kind, payload))
            return
        try:
            self._conn.send((kind, payload))
        except (OSError, ValueError) as exc:
            raise PlaneSlamError(f"the iSAM2 backend process is gone ({exc})") from None

    def _receive(self) -> None:
        while True:
            try:
                self._replies.put(self._conn.recv())
            except (EOFError, OSError):
                self._replies.put(("gone", None))
                return

    def _result(self) -> Any:
        if self.inline:
            return self._replies.popleft()
        status, reply = self._replies.get()
        if status == "gone":
            code = self._process.poll()
            self.close()
            raise PlaneSlamError(f"the iSAM2 backend process died (exit code {code})")
        if status == "error":
            raise reply
        return reply


def _handle(backend: Isam2Backend, kind: str, payload: Any) -> Any:
    """Run one request on `backend` (in the worker process, or inline)."""
    if kind == "keyframe":
        index, plane_ids, corner_ids = payload[0], payload[4], payload[5]
        T = backend.add_keyframe(*payload)
        return KeyframeUpdate(
            index=index,
            T_world_cam=T,
            planes=backend.plane_estimates(plane_ids.values()),
            corners=backend.corner_estimates(corner_ids.values()),
            update_ms=backend.update_ms[-1],
        )
    if kind == "finish":
        batch_ms = backend.optimize_batch(payload) if payload else 0.0
        return BackendResult(
            keyframe_poses=backend.keyframe_poses(),
            planes=backend.plane_estimates(),
            corners=backend.corner_estimates(),
            update_ms=list(backend.update_ms),
            batch_ms=batch_ms,
            failures=backend.failures,
            num_factors=backend.num_factors,
        )
    raise ValueError(f"unknown backend request {kind!r}")


def _start_worker(config: BackendConfig) -> tuple[subprocess.Popen, Connection]:
    """A fresh interpreter running `serve`, and the connection to it.

    Not `multiprocessing.Process`: 'fork' would copy gtsam's TBB threads in an unusable
    state, and 'spawn' re-runs the caller's main script (a script without an
    `if __name__ == "__main__"` guard would start SLAM again in the child). Only the
    connection comes from multiprocessing: one end of its `Pipe`, passed by descriptor.
    """
    conn, child_conn = multiprocessing.Pipe()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
    process = subprocess.Popen(
        [sys.executable, "-c", _CHILD_CODE, str(child_conn.fileno())],
        pass_fds=(child_conn.fileno(),),
        env=env,
    )
    child_conn.close()
    conn.send(config)
    return process, conn


_CHILD_CODE = "import sys; from planeslam.backend.worker import serve; serve(int(sys.argv[1]))"


def serve(fd: int) -> None:
    """The worker process, on connection descriptor `fd`: a `BackendConfig`, then requests
    in and replies out, until 'close' or a closed connection."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    conn = Connection(fd)
    try:
        backend = Isam2Backend(conn.recv())
        conn.send(("ok", "ready"))
    except (EOFError, OSError):
        return
    with single_native_threads():
        _serve_requests(conn, backend)


def _serve_requests(conn: Connection, backend: Isam2Backend) -> None:
    while True:
        try:
            kind, payload = conn.recv()
        except (EOFError, OSError):
            return
        if kind == "close":
            return
        try:
            reply = ("ok", _handle(backend, kind, payload))
        except PlaneSlamError as exc:
            reply = ("error", exc)
        except Exception as exc:  # anything else still reaches the caller, as one line
            reply = ("error", PlaneSlamError(f"iSAM2 backend: {type(exc).__name__}: {exc}"))
        conn.send(reply)
