"""Voxelised clouds, world frame: the map's sparse cloud for what is not planar (one
running-mean point and colour per voxel, capped to the best-supported voxels), and the
size of the dense point-cloud map the plane map is compared with (`FusedCloudSize`)."""

from __future__ import annotations

import logging
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from planeslam.core.errors import MapError
from planeslam.core.geometry import transform_points
from planeslam.frontend.kernels import sampled_voxel_keys_kernel

logger = logging.getLogger(__name__)

GREY = np.array([160, 160, 160], dtype=np.uint8)
"""Colour of points given without one (and of map planes in no object)."""

_KEY_BITS = 21
"""Bits per axis of a packed voxel key: +-2^20 voxels (+-52 km at 5 cm)."""
_KEY_OFFSET = 1 << (_KEY_BITS - 1)


class SparseCloud:
    """Voxel-averaged points: integer voxel keys (V, 3), mean points (V, 3) [m], point
    counts (V,) and mean uint8 colours (V, 3), rows in increasing packed-key order."""

    def __init__(self, voxel_m: float, max_points: int) -> None:
        """`voxel_m`: voxel edge [m]; `max_points`: most voxels kept."""
        self.voxel_m = voxel_m
        self.max_points = max_points
        self.keys = np.zeros((0, 3), dtype=np.int64)
        self.points = np.zeros((0, 3))
        self.counts = np.zeros(0, dtype=np.int64)
        self.colors = np.zeros((0, 3), dtype=np.uint8)

    @classmethod
    def from_arrays(
        cls,
        voxel_m: float,
        max_points: int,
        keys: np.ndarray,
        points: np.ndarray,
        counts: np.ndarray,
        colors: np.ndarray,
    ) -> SparseCloud:
        """A cloud with the given rows (as `add` leaves them); MapError when their
        lengths differ."""
        if not len(keys) == len(points) == len(counts) == len(colors):
            raise MapError("sparse_cloud arrays differ in length")
        cloud = cls(voxel_m, max_points)
        cloud.keys, cloud.points, cloud.counts, cloud.colors = keys, points, counts, colors
        return cloud

    def __len__(self) -> int:
        return len(self.keys)

    @property
    def nbytes(self) -> int:
        """Bytes of the four arrays."""
        return self.keys.nbytes + self.points.nbytes + self.counts.nbytes + self.colors.nbytes

    def add(self, points_world: np.ndarray, colors: np.ndarray | None = None) -> None:
        """Add (N, 3) world points [m] (and (N, 3) uint8 colours, grey when None).

        Non-finite rows are dropped. Beyond `max_points` voxels the least-supported
        ones go (ties: the later voxel in key order). MapError for bad shapes or points
        too far out to voxelise.
        """
        pts = np.asarray(points_world, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise MapError(f"points_world has shape {pts.shape}, expected (N, 3)")
        if colors is None:
            cols = np.broadcast_to(GREY, pts.shape)
        else:
            cols = np.asarray(colors)
            if cols.shape != pts.shape:
                raise MapError(f"colors has shape {cols.shape}, expected {pts.shape} uint8")
        finite = np.all(np.isfinite(pts), axis=1)
        pts, cols = pts[finite], cols[finite].astype(np.float64)
        if len(pts) == 0:
            return
        keys = np.floor(pts / self.voxel_m).astype(np.int64)
        if np.abs(keys).max() >= _KEY_OFFSET:
            raise MapError(
                f"points beyond +-{_KEY_OFFSET * self.voxel_m:.0f} m cannot be voxelised"
            )
        n_old = len(self.keys)
        all_keys = np.concatenate([self.keys, keys])
        uniq, first, inv = np.unique(_pack(all_keys), return_index=True, return_inverse=True)
        w = np.concatenate([self.counts.astype(np.float64), np.ones(len(pts))])
        sums = np.concatenate([self.points * w[:n_old, None], pts])
        csums = np.concatenate([self.colors.astype(np.float64) * w[:n_old, None], cols])
        counts = np.bincount(inv, weights=w, minlength=len(uniq))
        mean = _sum_by(inv, sums, len(uniq)) / counts[:, None]
        cmean = _sum_by(inv, csums, len(uniq)) / counts[:, None]
        keep = np.arange(len(uniq))
        if len(uniq) > self.max_points:
            order = np.argsort(-counts, kind="stable")
            keep = np.sort(order[: self.max_points])
            logger.debug("sparse cloud capped: %d of %d voxels kept", self.max_points, len(uniq))
        self.keys = all_keys[first[keep]]
        self.points = mean[keep]
        self.counts = np.rint(counts[keep]).astype(np.int64)
        self.colors = np.clip(np.rint(cmean[keep]), 0, 255).astype(np.uint8)


def _pack(keys: np.ndarray) -> np.ndarray:
    """(N,) int64 of (N, 3) voxel keys, ordered like the keys lexicographically."""
    k = keys + _KEY_OFFSET
    return (k[:, 0] << (2 * _KEY_BITS)) | (k[:, 1] << _KEY_BITS) | k[:, 2]


def _sum_by(inv: np.ndarray, values: np.ndarray, groups: int) -> np.ndarray:
    """(groups, 3) sums of the (N, 3) `values` rows by group index `inv` (N,)."""
    return np.stack(
        [np.bincount(inv, weights=values[:, i], minlength=groups) for i in range(3)], axis=1
    )


def _merged(keys: np.ndarray, new: np.ndarray) -> np.ndarray:
    """The sorted distinct union of two sorted distinct (N,) and (M,) int64 arrays, in
    O(N + M log N): the new values absent from `keys` inserted where they belong (sorting
    the concatenation again cost a long run's fused cloud O(N log N) per flush)."""
    at = np.searchsorted(keys, new)
    present = np.zeros(len(new), dtype=bool)
    inside = at < len(keys)
    present[inside] = keys[at[inside]] == new[inside]
    return np.insert(keys, at[~present], new[~present])


def _distinct(keys: np.ndarray) -> np.ndarray:
    """(K,) sorted distinct values of the (N,) int64 `keys`. A sort: numpy 2.4's
    `np.unique` hashes plain integer arrays, 70x slower on the millions of voxel keys of a
    long run (2.7 s against 38 ms on 2.6 M keys)."""
    keys = np.sort(keys)
    return keys[np.r_[True, keys[1:] != keys[:-1]]] if len(keys) else keys


class FusedCloudSize:
    """How many voxels of `voxel_m` the frames' points fill once fused (world frame): the
    size of a voxel-downsampled point-cloud map, the fair thing to compare a map with.

    A figure, not part of the map: with `background` the work (moving the points, keying,
    merging) runs in one worker thread, off the caller's per-frame path (numpy releases
    the GIL for it); the thread ends with the object. Keys are merged in batches
    (`flush_every` additions)."""

    def __init__(self, voxel_m: float = 0.01, flush_every: int = 16, background: bool = True):
        if not voxel_m > 0:
            raise MapError(f"voxel_m must be > 0 [m], got {voxel_m!r}")
        self.voxel_m = voxel_m
        self._flush_every = flush_every
        self._keys = np.zeros(0, dtype=np.int64)
        self._pending: list[np.ndarray] = []
        self._worker = (
            ThreadPoolExecutor(1, thread_name_prefix="fused-cloud") if background else None
        )
        self._queued: list[Future[None]] = []

    def add(self, points: np.ndarray, T_world_points: np.ndarray | None = None) -> None:
        """(N, 3) points [m] (world frame, or moved there by T_world_points (4, 4));
        non-finite rows are ignored. The caller must not change `points` afterwards."""
        if self._worker is None:
            self._add(points, T_world_points)
            return
        self._queued = [f for f in self._queued if not f.done()] + [
            self._worker.submit(self._add, points, T_world_points)
        ]

    def add_sampled(self, cloud: np.ndarray, stride: int, T_world_cam: np.ndarray) -> None:
        """The valid points (z > 0, finite) of every `stride`-th pixel in each direction of
        an organised (H, W, 3) camera-frame cloud [m], moved to the world by T_world_cam
        (4, 4). With `background` the sampling runs on the worker too, off the caller's
        path. The caller must change neither array afterwards."""
        if self._worker is None:
            self._add_sampled(cloud, stride, T_world_cam)
            return
        self._queued = [f for f in self._queued if not f.done()] + [
            self._worker.submit(self._add_sampled, cloud, stride, T_world_cam)
        ]

    @property
    def voxels(self) -> int:
        """Occupied voxels so far (waits for the queued additions)."""
        for future in self._queued:
            future.result()
        self._queued = []
        self._flush()
        return len(self._keys)

    def _add(self, points: np.ndarray, T_world_points: np.ndarray | None) -> None:
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if T_world_points is not None:
            points = transform_points(T_world_points, points)
        points = points[np.all(np.isfinite(points), axis=1)]
        keys = np.floor(points / self.voxel_m).astype(np.int64)
        keys = keys[np.all(np.abs(keys) < _KEY_OFFSET, axis=1)]
        self._pend(_pack(keys))

    def _add_sampled(self, cloud: np.ndarray, stride: int, T_world_cam: np.ndarray) -> None:
        """`add`'s keys of the sampled valid points in one compiled pass (no temporaries;
        the GIL released): the same keys, bit for bit."""
        T = np.asarray(T_world_cam, dtype=np.float64)
        self._pend(
            sampled_voxel_keys_kernel(
                np.asarray(cloud, dtype=np.float32), stride, T, self.voxel_m, _KEY_BITS
            )
        )

    def _pend(self, packed: np.ndarray) -> None:
        """Queue the (N,) packed keys of one addition; merged every `flush_every`."""
        self._pending.append(_distinct(packed))
        if len(self._pending) >= self._flush_every:
            self._flush()

    def _flush(self) -> None:
        if self._pending:
            self._keys = _merged(self._keys, _distinct(np.concatenate(self._pending)))
            self._pending = []
