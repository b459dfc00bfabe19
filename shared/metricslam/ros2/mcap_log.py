"""One camera's SLAM output as an MCAP file that Foxglove opens as it is.

Encoding: ROS 2 messages — ``schema_encoding="ros2msg"`` (the ``.msg`` text with its
dependencies), ``message_encoding="cdr"``, profile ``ros2`` — the same bytes a ROS 2 node gets
from the live bridge (``docs/recordings.md`` lists the topics). Each message's ``log_time`` and
``publish_time`` are the frame's ``t_ns`` (sensor time, ns), so the file replays on the
sequence's own clock. Thread-safe: depth maps arrive from the back end's depth thread.

Frames: a pose, path or cloud is in its camera's SLAM world (``frame_id="world"``, the default:
parent frame ``<tok>/world``) or in a saved map the camera relocalized into (``frame_id="map"``:
parent frame ``map``), named as the live ROS 2 bridge names them
(:func:`~metricslam.ros2.rmw_zenoh.parent_frame_id`).

Example::

    with McapLog("run.mcap", camera_id="cam0") as log:
        log.pose(t_ns, T_world_cam)
        log.landmarks(t_ns, points_world)
        log.path(t_ns, stamps_ns, T_map_cam, frame_id="map")  # parent frame "map"
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.errors import ConfigError, ImageError
from metricslam.ros2 import messages
from metricslam.ros2.rmw_zenoh import frame_ids, parent_frame_id, ros_token
from metricslam.ros2.typestore import msgdef, serialize, typestore
from metricslam.slam.events import SCALE_RECORD_VALUES


class McapTopics:
    """Topic and frame names of one camera (``tok`` = :func:`ros_token` of its id).

    Attributes:
        pose: ``/metricslam/<tok>/pose`` geometry_msgs/PoseStamped, every frame's live pose.
        path: ``/metricslam/<tok>/path`` nav_msgs/Path, the optimized trajectory when it changed.
        image: ``/metricslam/<tok>/keyframe/image/compressed`` sensor_msgs/CompressedImage (JPEG).
        camera_info: ``/metricslam/<tok>/keyframe/camera_info`` sensor_msgs/CameraInfo.
        depth: ``/metricslam/<tok>/keyframe/depth/image`` sensor_msgs/Image ``32FC1``, coarse depth (m).
        depth_info: ``/metricslam/<tok>/keyframe/depth/camera_info`` sensor_msgs/CameraInfo of that
            depth image at its own (coarse) resolution — the live bridge's topics, same names.
        landmarks: ``/metricslam/<tok>/landmarks`` sensor_msgs/PointCloud2 (x, y, z float32).
        tf: ``/tf`` tf2_msgs/TFMessage, ``<tok>/world`` (or ``map``) -> ``<tok>/camera_optical``
            every frame.
        tf_static: ``/tf_static`` tf2_msgs/TFMessage, ``map`` -> ``<tok>/world`` once, when a
            session placed in a map is rigidly in it (:meth:`McapLog.map_to_world`).
        scale: ``/metricslam/<tok>/scale/<name>`` per keyframe scale record (:meth:`McapLog.scale_health`):
            ``learned``, ``ground`` (m per keyframe VO unit), ``disagreement_log``
            (log learned / ground), ``learned_spread_log``, ``sigma_log`` (the back end's σ of
            log scale) as std_msgs/Float64 and ``warning`` as std_msgs/Bool.
        world_frame, camera_frame: the ``frame_id`` values ``<tok>/world`` and
            ``<tok>/camera_optical``; a pose in the map frame has parent :meth:`parent` ``map``.
    """

    def __init__(self, camera_id: str) -> None:
        tok = ros_token(camera_id)
        base = f"/metricslam/{tok}"
        self.pose, self.path, self.landmarks = f"{base}/pose", f"{base}/path", f"{base}/landmarks"
        self.image = f"{base}/keyframe/image/compressed"
        self.camera_info = f"{base}/keyframe/camera_info"
        self.depth = f"{base}/keyframe/depth/image"
        self.depth_info = f"{base}/keyframe/depth/camera_info"
        self.tf, self.tf_static = "/tf", "/tf_static"
        self.scale = {name: f"{base}/scale/{name}" for name in SCALE_RECORD_VALUES + ("warning",)}
        self.camera_id = camera_id
        self.world_frame, self.camera_frame = frame_ids(camera_id)

    def parent(self, frame_id: str = "world") -> str:
        """The ROS parent frame of a pose in the native ``frame_id`` (``"world"`` or ``"map"``)."""
        return parent_frame_id(self.camera_id, frame_id)


class McapLog:
    """Writes ROS 2 messages of one camera to ``path`` (see the module docstring).

    Args:
        path: the ``.mcap`` file (parent folders are created).
        camera_id: names the topics and frames (:class:`McapTopics`).
        jpeg_quality: keyframe image compression (0-100).

    Attributes:
        counts: topic -> messages written.
    """

    def __init__(self, path: str | Path, camera_id: str = "cam0", jpeg_quality: int = 85) -> None:
        try:
            from mcap.writer import Writer
        except ImportError:
            raise ConfigError("--mcap needs the mcap package: pip install 'metricslam[ros]'") from None
        typestore()  # the ros extra's other half: fail before the file exists, not mid-run
        self.file_path = Path(path)
        self.file_path.parent.mkdir(parents=True, exist_ok=True)
        self.topics = McapTopics(camera_id)
        self.jpeg_quality = int(jpeg_quality)
        self.counts: dict[str, int] = {}
        self._lock = threading.Lock()
        self._file = open(self.file_path, "wb")
        self._writer = Writer(self._file)
        self._writer.start(profile="ros2", library="metricslam")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._closed = False

    # -- one call per kind of output ----------------------------------------------------------
    def pose(self, t_ns: int, T_world_cam: np.ndarray, frame_id: str = "world") -> None:
        """The live pose (4, 4) of one frame in ``frame_id`` (``"world"``: the session's world,
        ``"map"``: ``T_map_cam``, m): PoseStamped and the matching ``/tf`` transform, both with
        parent frame :meth:`McapTopics.parent`."""
        tp = self.topics
        parent = tp.parent(frame_id)
        self.write(tp.pose, messages.pose_stamped(T_world_cam, t_ns, parent), t_ns)
        self.write(tp.tf, messages.tf_message(T_world_cam, t_ns, parent, tp.camera_frame), t_ns)

    def path(self, t_ns: int, stamps_ns: np.ndarray, T_world_cam: np.ndarray, frame_id: str = "world") -> None:
        """The optimized trajectory (N,) ns / (N, 4, 4) as it stood at ``t_ns``, in ``frame_id``
        (``"world"`` or ``"map"``, :meth:`pose`)."""
        tp = self.topics
        self.write(tp.path, messages.path(stamps_ns, T_world_cam, t_ns, tp.parent(frame_id)), t_ns)

    def map_to_world(self, t_ns: int, T_map_world: np.ndarray) -> None:
        """The session's world (4, 4 rigid, m) in the map it relocalized into, on ``/tf_static``
        (parent ``map``, child ``<tok>/world``): the poses, paths and clouds recorded in the world
        frame then show in the map beside those recorded in it. Logged at ``t_ns`` (the first
        frame's, so a player has it from the start)."""
        tp = self.topics
        self.write(tp.tf_static, messages.tf_message(T_map_world, t_ns, tp.parent("map"), tp.world_frame), t_ns)

    def keyframe_image(self, t_ns: int, pixels: np.ndarray, camera: PinholeCamera | None) -> None:
        """A keyframe image, JPEG-compressed (gray or RGB), and its CameraInfo (when known)."""
        import cv2

        a = np.asarray(pixels)
        bgr = a if a.ndim == 2 else cv2.cvtColor(a, cv2.COLOR_RGB2BGR)
        ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            raise ImageError(f"JPEG encoding of a {a.shape} {a.dtype} image failed")
        tp = self.topics
        self.write(tp.image, messages.compressed_image(jpeg.tobytes(), t_ns, tp.camera_frame), t_ns)
        if camera is not None:
            self.write(tp.camera_info, messages.camera_info(camera, t_ns, tp.camera_frame), t_ns)

    def keyframe_depth(self, t_ns: int, inv_depth_per_m: np.ndarray, camera: PinholeCamera | None = None,
                       image_size_px: tuple[int, int] | None = None) -> None:
        """A keyframe's coarse metric inverse depth (h, w) 1/m as a ``32FC1`` depth image in metres
        (NaN where the inverse depth is not positive), and, when the keyframe's ``camera`` and
        image size (width, height) px are known, the CameraInfo of the coarse grid beside it."""
        inv = np.asarray(inv_depth_per_m, dtype=np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            depth_m = np.where(inv > 0, 1.0 / inv, np.nan).astype(np.float32)
        tp = self.topics
        self.write(tp.depth, messages.image(depth_m, t_ns, tp.camera_frame), t_ns)
        if camera is not None:
            size = image_size_px or (camera.width_px, camera.height_px)
            grid = messages.depth_grid_camera(camera, size, depth_m.shape)
            self.write(tp.depth_info, messages.camera_info(grid, t_ns, tp.camera_frame), t_ns)

    def landmarks(self, t_ns: int, points_world: np.ndarray, frame_id: str = "world") -> None:
        """Landmark positions (N, 3) in ``frame_id`` (``"world"``: the SLAM world; ``"map"``: m)."""
        tp = self.topics
        self.write(tp.landmarks, messages.point_cloud2(points_world, t_ns, tp.parent(frame_id)), t_ns)

    def scale_health(self, t_ns: int, values: dict[str, float | None], warning: bool) -> None:
        """One keyframe's scale record: each finite number of ``values`` (keys of
        :data:`SCALE_RECORD_VALUES`; None or NaN: not known, nothing written) and the health flag."""
        for name in SCALE_RECORD_VALUES:
            value = values.get(name)
            if value is not None and np.isfinite(value):
                self.write(self.topics.scale[name], messages.float64(value), t_ns)
        self.write(self.topics.scale["warning"], messages.flag(warning), t_ns)

    # -- plumbing -------------------------------------------------------------------------------
    def write(self, topic: str, message: Any, log_time_ns: int) -> None:
        """Append one ``rosbags`` message on ``topic`` (channel and schema made on first use)."""
        data = serialize(message)
        t = max(int(log_time_ns), 0)
        with self._lock:
            if self._closed:
                return  # a late depth answer after close: nothing to write it into
            channel_id = self._channel(topic, message.__msgtype__)
            sequence = self.counts.get(topic, 0)
            self._writer.add_message(channel_id, log_time=t, data=data, publish_time=t, sequence=sequence)
            self.counts[topic] = sequence + 1

    def _channel(self, topic: str, msgtype: str) -> int:
        if topic not in self._channels:
            if msgtype not in self._schemas:
                self._schemas[msgtype] = self._writer.register_schema(
                    name=msgtype, encoding="ros2msg", data=msgdef(msgtype).encode())
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding="cdr", schema_id=self._schemas[msgtype])
        return self._channels[topic]

    def close(self) -> None:
        """Write the summary and close the file (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._writer.finish()
            self._file.close()

    def __enter__(self) -> "McapLog":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
