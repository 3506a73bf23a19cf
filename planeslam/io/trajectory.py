"""Camera trajectories and the TUM trajectory file format.

A TUM row is `timestamp tx ty tz qx qy qz qw`: the camera-to-world pose
T_world_cam at that time (metres, seconds, quaternion xyzw).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from planeslam.core.errors import DatasetFormatError
from planeslam.core.geometry import pose_from_quat, quat_from_pose
from planeslam.core.safe_files import LineWriter
from planeslam.io.tum_text import row_error, tum_rows


@dataclass(frozen=True)
class Trajectory:
    """Timestamped camera poses."""

    timestamps: np.ndarray
    """(N,) seconds, increasing."""
    T_world_cam: np.ndarray
    """(N, 4, 4) camera-to-world poses."""

    def __post_init__(self) -> None:
        if self.timestamps.shape[0] != self.T_world_cam.shape[0]:
            raise ValueError("timestamps and poses differ in length")

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) camera centres in the world frame [m]."""
        return self.T_world_cam[:, :3, 3]

    def path_length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum())

    def pose_near(self, timestamp: float, max_difference_s: float) -> np.ndarray | None:
        """(4, 4) T_world_cam of the pose nearest to `timestamp` [s], or None when there is
        none within `max_difference_s` [s]."""
        if not len(self):
            return None
        k = int(np.argmin(np.abs(self.timestamps - timestamp)))
        if abs(self.timestamps[k] - timestamp) > max_difference_s:
            return None
        return np.array(self.T_world_cam[k], dtype=np.float64)

    def interpolated(self, timestamp: float) -> np.ndarray | None:
        """(4, 4) T_world_cam at `timestamp` [s], interpolated between the poses around it
        (position linearly, rotation by slerp), or None outside the poses' time span."""
        from scipy.spatial.transform import Rotation, Slerp

        if not len(self) or not self.timestamps[0] <= timestamp <= self.timestamps[-1]:
            return None
        k = int(np.clip(np.searchsorted(self.timestamps, timestamp), 1, len(self) - 1))
        if len(self) == 1 or self.timestamps[k - 1] == self.timestamps[k]:
            return np.array(self.T_world_cam[k], dtype=np.float64)
        t0, t1 = self.timestamps[k - 1], self.timestamps[k]
        a = (timestamp - t0) / (t1 - t0)
        pair = Rotation.from_matrix(self.T_world_cam[k - 1 : k + 1, :3, :3])
        T = np.eye(4)
        T[:3, :3] = Slerp([t0, t1], pair)(timestamp).as_matrix()
        T[:3, 3] = (1 - a) * self.T_world_cam[k - 1, :3, 3] + a * self.T_world_cam[k, :3, 3]
        return T


QUATERNION_NORM_TOLERANCE = 0.01
"""|norm - 1| allowed for a TUM row's quaternion (files round to 4 decimals or more);
farther off, the columns are not what the format says."""


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file ('timestamp tx ty tz qx qy qz qw' rows), sorted by time.

    Raises DatasetFormatError naming the file and line on a malformed row (not 8 finite
    numbers, a quaternion far from unit norm), and on a missing file or one with no poses.
    """
    path = Path(path)
    expected = "timestamp tx ty tz qx qy qz qw"
    rows: list[list[float]] = []
    linenos: list[int] = []
    for lineno, fields in tum_rows(path, "trajectory", expected, entries="poses"):
        try:
            values = [float(p) for p in fields]
        except ValueError:
            values = []
        if len(values) != 8 or not np.all(np.isfinite(values)):
            raise row_error(path, lineno, f"8 numbers '{expected}'", fields)
        rows.append(values)
        linenos.append(lineno)
    data = np.asarray(rows)
    with np.errstate(over="ignore"):  # a huge component: norm inf, refused below
        norms = np.linalg.norm(data[:, 4:8], axis=1)
    off = np.abs(norms - 1.0)
    if np.any(off > QUATERNION_NORM_TOLERANCE):
        bad = int(np.argmax(off))
        raise DatasetFormatError(
            f"{path}:{linenos[bad]}: quaternion qx qy qz qw has norm {norms[bad]:.4g}, expected "
            f"a unit quaternion (rows '{expected}')"
        )
    order = np.argsort(data[:, 0], kind="stable")
    data = data[order]
    return Trajectory(timestamps=data[:, 0], T_world_cam=pose_from_quat(data[:, 1:4], data[:, 4:8]))


def format_tum_row(timestamp: float, T_world_cam: np.ndarray) -> str:
    """One TUM row for one pose (no line end)."""
    t, q = quat_from_pose(T_world_cam)
    values = " ".join(f"{v:.9f}" for v in (*t, *q))
    return f"{timestamp:.6f} {values}"


def write_tum(path: str | Path, trajectory: Trajectory, header: str = "") -> None:
    """Write a whole trajectory as a TUM file."""
    with TumWriter(path, header=header) as writer:
        for stamp, T in zip(trajectory.timestamps, trajectory.T_world_cam, strict=True):
            writer.write(float(stamp), T)


class TumWriter:
    """Append poses to a TUM file as they are estimated, each row whole on disk as soon as
    it is written (`LineWriter`), so an interrupted or killed run keeps every pose it wrote."""

    def __init__(self, path: str | Path, header: str = "") -> None:
        self.path = Path(path)
        self._lines = LineWriter(self.path)
        for line in header.splitlines() if header else []:
            self._lines.write_line(f"# {line}")
        self._lines.write_line("# timestamp tx ty tz qx qy qz qw")

    def write(self, timestamp: float, T_world_cam: np.ndarray) -> None:
        self._lines.write_line(format_tum_row(timestamp, T_world_cam))

    def close(self) -> None:
        self._lines.close()

    def __enter__(self) -> TumWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
