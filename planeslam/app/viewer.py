"""The rerun viewer of a run: live (`planeslam run --viewer`), recorded (`--rrd FILE`), or
replayed from a finished run's outputs (`planeslam view RUN_DIR`).

Everything is logged on one timeline, `frame` (the frame's position in the run), under:

    world/camera                  Transform3D: the camera pose T_world_cam
    world/camera/image            Pinhole (the frustum) and the colour image (JPEG) with the
                                  front end's planes tinted (PALETTE by id, as overlay.png)
    world/camera/image/edges/convex, .../concave
                                  LineStrips2D: real intersections (orange, cyan)
    world/camera/image/corners    Points2D: trihedral corners (magenta)
    world/camera/image/objects    Points2D labelled with class and size
    world/trajectory/estimate     LineStrips3D: the poses so far (online; final in a replay)
    world/trajectory/final        LineStrips3D: the optimised trajectory (at the end)
    world/trajectory/groundtruth  LineStrips3D: the ground truth up to the frame, when known
    world/keyframes, world/lost   Points3D: keyframe and lost-frame camera positions so far
                                  (these four hold their last CHUNK points; each earlier
                                  chunk is logged once, when full, under <path>/past/<k>,
                                  so a frame sends O(1) data, not the whole run so far)
    world/map/planes              Mesh3D: plane polygons coloured by object
    world/map/outlines            LineStrips3D: plane outlines, same colours
    world/map/edges               LineStrips3D: real intersections (convex orange, concave cyan)
    world/map/corners             Points3D: trihedral corners
    world/map/objects             Points3D at each object's planes, labelled class and size
    world/map/sparse              Points3D: the sparse non-planar cloud (at the end)
    tracking/path                 Scalars: index of the TrackingPath (first 0 ... lost 7)
    tracking/planes               Scalars: planes the front end found
    timing/<stage>                Scalars: stage times [ms]
    log                           TextLog: keyframes, lost frames and fallbacks with reasons

The live map is logged at every `map_every`-th keyframe and at the end (after the final
optimisation); a replay has only the final map. The planes are tinted into the JPEG rather
than logged as a SegmentationImage: 1000 640x480 label images made 7-Scenes recordings
three times larger. rerun-sdk is an optional extra
(`pip install planeslam[viewer]`); it is imported when a viewer is asked for.
"""

from __future__ import annotations

import logging
import os
import sys
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from planeslam.app.overlay import (
    CONCAVE_RGB,
    CONVEX_RGB,
    CORNER_RGB,
    format_size,
    project_points,
    tint_planes,
)
from planeslam.app.progress import progress_bar
from planeslam.app.run_folder import open_run
from planeslam.config import PlaneSlamConfig
from planeslam.core.camera import CameraConfig
from planeslam.core.errors import ConfigError
from planeslam.core.types import TrackingPath
from planeslam.frontend.pipeline import FrameObservation, FrontEnd
from planeslam.io.sequence import RgbdDataset
from planeslam.io.trajectory import Trajectory
from planeslam.mapping.world_map import Map
from planeslam.slam import SLAM, FrameResult

if TYPE_CHECKING:
    import rerun as rr

log = logging.getLogger(__name__)

TIMELINE = "frame"
APPLICATION_ID = "planeslam"
PATH_CODES = {p: k for k, p in enumerate(TrackingPath)}
"""TrackingPath -> the value of `tracking/path`."""
JPEG_QUALITY = 85
IMAGE_PLANE_M = 0.15
"""Distance of the drawn image plane from the camera centre (frustum size) [m]."""
TRAJECTORY_RGB = (31, 119, 180)
FINAL_RGB = (44, 160, 44)
GROUNDTRUTH_RGB = (90, 90, 90)
KEYFRAME_RGB = (20, 20, 20)
LOST_RGB = (214, 39, 40)
FLUSH_TIMEOUT_S = 20.0
"""How long closing a recording waits for a viewer to take the rest of the data [s]."""
GT_MARGIN_S = 0.05
"""Ground truth this close before the first frame and after the current one is drawn [s]."""
CHUNK = 256
"""Points of a growing trajectory or point set re-sent per frame (see `GrowingPoints`)."""


class GrowingPoints:
    """A point set or line strip that grows frame by frame, logged without re-sending the
    past: `path` holds the last chunk (at most `chunk` points), and every full chunk is
    logged once under `path/past/<k>` (a strip's chunks share their end points)."""

    def __init__(self, path: str, draw: Any, chunk: int = CHUNK) -> None:
        """`draw`: (N, 3) array -> the rerun archetype to log."""
        self.path, self.draw, self.chunk = path, draw, chunk
        self._points: list[np.ndarray] = []
        self._done = 0

    def add(self, rec: Any, points: np.ndarray) -> None:
        """Append (K, 3) points [m] (K may be 0) and log at the recording's current time."""
        self._points.extend(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        while len(self._points) > self.chunk:
            rec.log(
                f"{self.path}/past/{self._done}", self.draw(np.array(self._points[: self.chunk]))
            )
            self._done += 1
            self._points = self._points[self.chunk - 1 :]
        rec.log(self.path, self.draw(np.array(self._points).reshape(-1, 3)))


def _rerun() -> Any:
    try:
        import rerun
    except ImportError:
        raise ConfigError(
            "the viewer needs rerun-sdk: pip install 'planeslam[viewer]' (or rerun-sdk)"
        ) from None
    return rerun


def has_display() -> bool:
    """Whether a native viewer window can open here (X11 / Wayland on Linux)."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


class RunLogger:
    """Logs frames, maps and trajectories of one run into a rerun RecordingStream, under
    the entity paths of the module docstring."""

    def __init__(self, rec: rr.RecordingStream) -> None:
        self.rr = _rerun()
        self.rec = rec
        rr = self.rr
        self._estimate = GrowingPoints(
            "world/trajectory/estimate",
            lambda p: rr.LineStrips3D([p], colors=[TRAJECTORY_RGB], radii=0.004),
        )
        self._groundtruth_strip = GrowingPoints(
            "world/trajectory/groundtruth",
            lambda p: rr.LineStrips3D([p], colors=[GROUNDTRUTH_RGB], radii=0.004),
        )
        self._keyframes = GrowingPoints(
            "world/keyframes", lambda p: rr.Points3D(p, colors=[KEYFRAME_RGB], radii=0.01)
        )
        self._lost = GrowingPoints(
            "world/lost", lambda p: rr.Points3D(p, colors=[LOST_RGB], radii=0.02)
        )
        self._groundtruth_until = -np.inf
        """Time stamp [s] up to which the ground truth is logged."""
        self._up_logged = False
        self._groundtruth: Trajectory | None = None

    def setup(self, camera: CameraConfig, groundtruth: Trajectory | None) -> None:
        """The camera model (static) and the ground truth to draw frame by frame."""
        rr = self.rr
        self.camera = camera
        self._groundtruth = groundtruth if groundtruth is not None and len(groundtruth) else None
        self.rec.log(
            "world/camera/image",
            rr.Pinhole(
                image_from_camera=camera.K,
                resolution=[camera.width, camera.height],
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=IMAGE_PLANE_M,
            ),
            static=True,
        )

    def set_frame(self, index: int) -> None:
        self.rec.set_time(TIMELINE, sequence=int(index))

    def frame(self, result: FrameResult) -> None:
        """One frame at its time: camera (its pose `result.T_world_cam`), image (`result.rgb`)
        with the front end's result, scalars, events, and the trajectory, keyframes and lost
        frames so far."""
        rr, rec = self.rr, self.rec
        self.set_frame(result.index)
        T = np.asarray(result.T_world_cam, dtype=np.float64)
        rec.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        if result.rgb is not None:
            tinted = tint_planes(result.rgb, np.asarray(result.observation.segmentation.labels))
            ok, jpeg = cv2.imencode(
                ".jpg",
                cv2.cvtColor(tinted, cv2.COLOR_RGB2BGR),
                [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY],
            )
            if ok:
                rec.log(
                    "world/camera/image",
                    rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg"),
                )
        self._log_observation(result.observation)
        position = T[None, :3, 3]
        self._estimate.add(rec, position)
        if self._groundtruth is not None:  # over the same time span as the estimate
            if self._groundtruth_until == -np.inf:  # the first frame
                self._groundtruth_until = np.nextafter(result.timestamp - GT_MARGIN_S, -np.inf)
            t = self._groundtruth.timestamps
            until = result.timestamp + GT_MARGIN_S
            span = (t > self._groundtruth_until) & (t <= until)
            self._groundtruth_until = max(self._groundtruth_until, until)
            self._groundtruth_strip.add(rec, self._groundtruth.positions[span])
        if result.keyframe:
            self._keyframes.add(rec, position)
            rec.log("log", rr.TextLog(f"frame {result.index}: keyframe", level="INFO"))
        if result.lost:
            self._lost.add(rec, position)
            rec.log("log", rr.TextLog(f"frame {result.index} lost: {result.reason}", level="WARN"))
        elif result.path not in (TrackingPath.FIRST, TrackingPath.PLANES):  # a fallback
            text = f"frame {result.index}: {result.path.value}: {result.reason}"
            rec.log("log", rr.TextLog(text, level="INFO"))
        rec.log("tracking/path", rr.Scalars(PATH_CODES[result.path]))
        rec.log("tracking/planes", rr.Scalars(len(result.observation.segmentation.planes)))
        for stage, ms in result.stage_ms.items():
            rec.log(f"timing/{stage}", rr.Scalars(float(ms)))

    def _log_observation(self, observation: FrameObservation) -> None:
        """The front end's edges, corners and objects on the image (camera frame)."""
        rr, rec, cam = self.rr, self.rec, self.camera
        seg, st = observation.segmentation, observation.structure
        for convex, name, colour in ((True, "convex", CONVEX_RGB), (False, "concave", CONCAVE_RGB)):
            strips = []
            for edge in st.edges:
                if bool(edge.convex) != convex:
                    continue
                uv, ok = project_points(np.asarray(edge.segment, dtype=np.float64), cam)
                if ok.all():
                    strips.append(uv)
            rec.log(
                f"world/camera/image/edges/{name}",
                rr.LineStrips2D(strips, colors=[colour], radii=2.0),
            )
        corners = np.array([c.point for c in st.corners], dtype=np.float64).reshape(-1, 3)
        uv, ok = project_points(corners, cam)
        rec.log("world/camera/image/corners", rr.Points2D(uv[ok], colors=[CORNER_RGB], radii=5.0))
        centroids = {p.id: np.asarray(p.centroid, dtype=np.float64) for p in seg.planes}
        anchors, texts = [], []
        for obj in st.objects:
            pts = [centroids[k] for k in obj.planes if k in centroids]
            if pts:
                uv, ok = project_points(np.mean(pts, axis=0)[None], cam)
                if ok[0]:
                    anchors.append(uv[0])
                    texts.append(f"{obj.cls} {format_size(obj.size_m)}".strip())
        self._log_labels("world/camera/image/objects", rr.Points2D, anchors, texts, 2, 3.0)

    def map(self, world_map: Map, sparse: bool = False) -> None:
        """The map at the current time (world frame); with `sparse`, its sparse cloud too."""
        rr, rec = self.rr, self.rec
        self._log_up(world_map)
        mesh = world_map.plane_mesh()
        rec.log(
            "world/map/planes",
            rr.Mesh3D(
                vertex_positions=mesh.vertices,
                triangle_indices=mesh.triangles,
                vertex_colors=mesh.colors,
            ),
        )
        colors = world_map.plane_colors()
        planes = [p for p in world_map.planes.values() if len(p.outline) >= 3]
        rec.log(
            "world/map/outlines",
            rr.LineStrips3D(
                [np.vstack([p.outline, p.outline[:1]]) for p in planes],
                colors=[colors[p.id] for p in planes],
                radii=0.003,
            ),
        )
        edges = list(world_map.edges.values())
        rec.log(
            "world/map/edges",
            rr.LineStrips3D(
                [e.segment for e in edges],
                colors=[CONVEX_RGB if e.convex else CONCAVE_RGB for e in edges],
                radii=0.006,
            ),
        )
        corners = list(world_map.corners.values())
        rec.log(
            "world/map/corners",
            rr.Points3D(
                np.array([c.point for c in corners]).reshape(-1, 3),
                colors=[CORNER_RGB],
                radii=0.02,
            ),
        )
        centres, texts = [], []
        for obj in world_map.objects:
            pts = [world_map.planes[k].outline for k in obj.planes if k in world_map.planes]
            if pts:
                centres.append(np.concatenate(pts).mean(axis=0))
                texts.append(f"{obj.cls} {obj.id}: {format_size(obj.size_m)}".strip(": "))
        self._log_labels("world/map/objects", rr.Points3D, centres, texts, 3, 0.01)
        if sparse:
            rec.log(
                "world/map/sparse",
                rr.Points3D(world_map.sparse_points, colors=world_map.sparse_colors, radii=0.005),
            )

    def _log_labels(
        self, path: str, archetype: Any, points: list, texts: list[str], dim: int, radius: float
    ) -> None:
        """Labelled white points (objects): `archetype` Points2D or Points3D, `dim` 2 or 3."""
        self.rec.log(
            path,
            archetype(
                np.array(points, dtype=np.float64).reshape(-1, dim),
                labels=texts,
                colors=[(255, 255, 255)],
                radii=radius,
                show_labels=True,
            ),
        )

    def _log_up(self, world_map: Map) -> None:
        """The world's up axis for the 3-D view, once the map knows it (nearest world axis)."""
        up = world_map.gravity_up
        if self._up_logged or up is None:
            return
        k = int(np.argmax(np.abs(up)))
        name = ("X", "Y", "Z")[k]
        sign = "UP" if up[k] > 0 else "DOWN"
        coords = getattr(self.rr.ViewCoordinates, f"RIGHT_HAND_{name}_{sign}")
        self.rec.log("world", coords, static=True)
        self._up_logged = True

    def final(self, trajectory: Trajectory) -> None:
        """The optimised trajectory, at the current time."""
        if len(trajectory):
            self.rec.log(
                "world/trajectory/final",
                self.rr.LineStrips3D([trajectory.positions], colors=[FINAL_RGB], radii=0.005),
            )


class RerunViewer:
    """A `RunObserver` (planeslam.app.runner) that streams a run to rerun: a spawned
    viewer and / or an .rrd file. Use as a context manager."""

    def __init__(
        self,
        name: str,
        rrd: str | Path | None = None,
        live: bool = False,
        map_every: int = 5,
    ) -> None:
        if map_every < 1:
            raise ConfigError(f"map_every must be >= 1 keyframe, got {map_every}")
        self.rec, self.where = open_recording(name, rrd, live)
        self.logger = RunLogger(self.rec)
        self.map_every = map_every
        self._keyframes = 0
        self._last_index = 0

    def start(self, dataset: RgbdDataset, config: PlaneSlamConfig) -> None:
        self.logger.setup(config.camera, dataset.groundtruth)

    def frame(self, slam: SLAM, result: FrameResult) -> None:
        self._last_index = result.index
        self.logger.frame(result)
        if result.keyframe:
            if self._keyframes % self.map_every == 0:
                self.logger.map(slam.map)
            self._keyframes += 1

    def finish(self, slam: SLAM) -> None:
        self.logger.set_frame(self._last_index)
        self.logger.map(slam.map, sparse=True)
        self.logger.final(slam.trajectory())

    def close(self) -> None:
        close_recording(self.rec)

    def __enter__(self) -> RerunViewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_recording(name: str, rrd: str | Path | None, live: bool) -> tuple[Any, str]:
    """A RecordingStream writing to `rrd` (when given) and, with `live`, to a viewer it
    spawns (ConfigError without a display: record to an .rrd file instead). Returns it and
    a phrase saying where the data goes."""
    rr = _rerun()
    if rrd is not None and Path(rrd).is_dir():
        raise ConfigError(f"{rrd}: is a folder; the recording needs a file name (e.g. run.rrd)")
    if rrd is None and not live:
        raise ConfigError("nowhere to send the recording: give an .rrd file or ask for live")
    if live and not has_display():
        raise ConfigError(
            "no display to open the rerun viewer in (DISPLAY / WAYLAND_DISPLAY unset): record "
            "with --rrd FILE and open it with `rerun FILE` where there is one"
        )
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=f"{name}-{uuid.uuid4().hex[:8]}")
    sinks, where = [], []
    if live:
        rr.spawn(connect=False, executable_path=_viewer_executable(), recording=rec)
        sinks.append(rr.GrpcSink())
        where.append("the rerun viewer")
    if rrd is not None:
        Path(rrd).parent.mkdir(parents=True, exist_ok=True)
        sinks.append(rr.FileSink(str(rrd)))
        where.append(str(rrd))
    if sinks:
        rec.set_sinks(*sinks, default_blueprint=default_layout())
    return rec, " and ".join(where)


def close_recording(rec: Any) -> None:
    """Flush and close a RecordingStream; a viewer that does not take the data within
    FLUSH_TIMEOUT_S (it failed to start, or was closed) is not waited for."""
    try:
        rec.flush(timeout_sec=FLUSH_TIMEOUT_S)
    except RuntimeError as exc:  # e.g. the spawned viewer went away
        log.warning("rerun: could not deliver everything: %s", exc)
    rec.disconnect()


def _viewer_executable() -> str | None:
    """The `rerun` viewer installed beside this Python (a virtual environment's bin/, which
    need not be on PATH), else None: rerun looks it up on PATH."""
    beside = Path(sys.executable).parent / ("rerun.exe" if sys.platform == "win32" else "rerun")
    return str(beside) if beside.is_file() else None


def default_layout() -> Any:
    """The viewer's first layout: the 3-D map and trajectory beside the camera image, the
    stage times and tracking scalars, and the event log."""
    rrb = _rerun().blueprint
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="map, camera and trajectories"),
            rrb.Vertical(
                rrb.Spatial2DView(origin="world/camera/image", name="camera: front end"),
                rrb.Tabs(
                    rrb.TimeSeriesView(origin="timing", name="stage times [ms]"),
                    rrb.TimeSeriesView(origin="tracking/path", name="tracking path"),
                    rrb.TimeSeriesView(origin="tracking/planes", name="planes per frame"),
                ),
                rrb.TextLogView(origin="log", name="keyframes, lost frames, fallbacks"),
                row_shares=[3, 2, 1],
            ),
            column_shares=[3, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline=TIMELINE, play_state="following"),  # the latest frame
    )


@dataclass(frozen=True)
class ViewResult:
    """What `view_run` logged and where."""

    frames: int
    where: str
    rrd: Path | None


def view_run(
    run_dir: str | Path,
    rrd: str | Path | None = None,
    every: int = 1,
    dataset: str | Path | None = None,
    progress: bool = False,
) -> ViewResult:
    """Turn a finished run's outputs into a recording: every `every`-th frame's image with
    the front end's result (recomputed with the run's config), its final pose, tracking
    path and stage times; the final map and trajectory; the ground truth. Opens a viewer
    where a display exists and no `rrd` is given; otherwise records to `rrd` (default
    RUN_DIR/run.rrd)."""
    if every < 1:
        raise ConfigError(f"every must be >= 1, got {every}")
    run = open_run(run_dir, dataset)
    config = run.config()
    front_end = FrontEnd(config, seed=config.run.seed)
    world_map = Map.load(run.run_dir / "map.json") if (run.run_dir / "map.json").is_file() else None
    chosen = [f for k, f in enumerate(run.frames) if k % every == 0 and f.T_world_cam is not None]
    live = rrd is None and has_display()
    if rrd is None and not live:
        rrd = run.run_dir / "run.rrd"
    rec, where = open_recording(run.run_dir.name, rrd, live)
    logger = RunLogger(rec)
    logger.setup(run.camera, run.dataset.groundtruth)
    try:
        with progress_bar(
            len(chosen), f"view {run.run_dir.name}", "frame", enabled=progress
        ) as bar:
            for k, (f, frame) in enumerate(run.read(chosen)):
                assert f.T_world_cam is not None
                record = f.record
                result = FrameResult(
                    index=int(record["index"]),
                    timestamp=frame.timestamp,
                    T_world_cam=f.T_world_cam,
                    path=TrackingPath(record["path"]),
                    reason=str(record.get("reason", "")),
                    keyframe=f.keyframe,
                    observation=front_end.process(frame.depth_m, frame.timestamp),
                    stage_ms={str(s): float(v) for s, v in record.get("stage_ms", {}).items()},
                    rgb=frame.rgb,
                )
                logger.frame(result)
                if k == 0 and world_map is not None:
                    logger.map(world_map, sparse=True)
                    logger.final(run.trajectory)
                bar.step()
    finally:
        close_recording(rec)
    return ViewResult(frames=len(chosen), where=where, rrd=None if rrd is None else Path(rrd))
