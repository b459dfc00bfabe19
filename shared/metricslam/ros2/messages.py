"""Our poses, trajectories, landmarks and images as ROS 2 messages (``rosbags`` dataclasses),
and ROS 2 camera input back into numpy arrays and a :class:`PinholeCamera`.

Frames: ``T_world_cam`` maps camera points to the SLAM world (docs/conventions.md); the camera
frame is optical (x right, y down, z forward), so a ROS user names it ``…_optical`` and the world
is the first camera pose's optical frame, not REP-103's x-forward, z-up. Quaternions are ROS's
``(x, y, z, w)``. Times are ``t_ns`` (ns); a ROS stamp is ``sec = t_ns // 1e9``, ``nanosec = t_ns
mod 1e9``. Serialize with :func:`metricslam.ros2.typestore.serialize`.

Example::

    msg = pose_stamped(np.eye(4), t_ns=1_500_000_000, frame_id="cam0/world")
    payload = serialize(msg)          # CDR bytes, what rmw_zenoh puts on the wire
"""

from __future__ import annotations

from typing import Any

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.errors import CodecError
from metricslam.geometry import so3
from metricslam.ros2.typestore import (
    BOOL, CAMERA_INFO, COMPRESSED_IMAGE, FLOAT64, IMAGE, ODOMETRY, PATH, POINT_CLOUD2, POSE_STAMPED, TF_MESSAGE,
    msg_class,
)

#: image encodings accepted as SLAM input (sensor_msgs/image_encodings.hpp names)
INPUT_ENCODINGS = ("mono8", "rgb8", "bgr8")
_FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32


def header(t_ns: int, frame_id: str) -> Any:
    """``std_msgs/Header`` stamped ``t_ns``."""
    Time, Header = msg_class("builtin_interfaces/msg/Time"), msg_class("std_msgs/msg/Header")
    sec, nanosec = divmod(int(t_ns), 1_000_000_000)
    return Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id)


def stamp_ns(hdr: Any) -> int:
    """``t_ns`` of a ``std_msgs/Header``."""
    return int(hdr.stamp.sec) * 1_000_000_000 + int(hdr.stamp.nanosec)


def pose(T_world_cam: np.ndarray) -> Any:
    """``geometry_msgs/Pose`` of a (4, 4) rigid transform (rotation re-orthonormalized)."""
    T = np.asarray(T_world_cam, dtype=float)
    x, y, z, w = so3.to_quat_xyzw(so3.project_to_so3(T[:3, :3]))
    Point, Quaternion = msg_class("geometry_msgs/msg/Point"), msg_class("geometry_msgs/msg/Quaternion")
    return msg_class("geometry_msgs/msg/Pose")(
        position=Point(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        orientation=Quaternion(x=float(x), y=float(y), z=float(z), w=float(w)))


def pose_stamped(T_world_cam: np.ndarray, t_ns: int, frame_id: str) -> Any:
    """``geometry_msgs/PoseStamped``: the camera pose in ``frame_id`` (the SLAM world)."""
    return msg_class(POSE_STAMPED)(header=header(t_ns, frame_id), pose=pose(T_world_cam))


def odometry(T_world_cam: np.ndarray, t_ns: int, frame_id: str, child_frame_id: str,
             pose_covariance: np.ndarray, twist_covariance: np.ndarray,
             twist_cam: np.ndarray | None = None) -> Any:
    """``nav_msgs/Odometry`` with the pose of ``child_frame_id`` (camera) in ``frame_id`` (world)
    and its twist.

    Args:
        pose_covariance, twist_covariance: (6, 6) in ROS's order ``[x, y, z, rot_x, rot_y,
            rot_z]`` (pose: in ``frame_id``; twist: in ``child_frame_id``).
        twist_cam: (6,) ``[ω rad/s, v units/s]`` in ``child_frame_id`` (our tangent order,
            docs/conventions.md; ROS's ``twist.linear = v``, ``twist.angular = ω``); None: zero
            (not estimated: say so in ``twist_covariance``).
    """
    def cov(c: np.ndarray, name: str) -> np.ndarray:
        c = np.asarray(c, dtype=np.float64)
        if c.shape != (6, 6):
            raise CodecError(f"{name} must be (6, 6), got {c.shape}")
        return c.reshape(36).copy()

    Vector3 = msg_class("geometry_msgs/msg/Vector3")
    w_v = np.zeros(6) if twist_cam is None else np.asarray(twist_cam, dtype=np.float64).reshape(6)
    if not np.all(np.isfinite(w_v)):
        raise CodecError(f"twist_cam must be finite, got {w_v.tolist()}")
    twist = msg_class("geometry_msgs/msg/Twist")(
        linear=Vector3(x=float(w_v[3]), y=float(w_v[4]), z=float(w_v[5])),
        angular=Vector3(x=float(w_v[0]), y=float(w_v[1]), z=float(w_v[2])))
    return msg_class(ODOMETRY)(
        header=header(t_ns, frame_id), child_frame_id=child_frame_id,
        pose=msg_class("geometry_msgs/msg/PoseWithCovariance")(
            pose=pose(T_world_cam), covariance=cov(pose_covariance, "pose_covariance")),
        twist=msg_class("geometry_msgs/msg/TwistWithCovariance")(
            twist=twist, covariance=cov(twist_covariance, "twist_covariance")))


def path(t_ns: np.ndarray, T_world_cam: np.ndarray, stamp_t_ns: int, frame_id: str) -> Any:
    """``nav_msgs/Path`` of N poses: ``t_ns`` (N,) and ``T_world_cam`` (N, 4, 4); the path's own
    header is stamped ``stamp_t_ns`` (the newest frame when it was made)."""
    T = np.asarray(T_world_cam, dtype=float).reshape(-1, 4, 4)
    if len(T) != len(t_ns):
        raise CodecError(f"path: {len(t_ns)} stamps but {len(T)} poses")
    poses = [pose_stamped(T_k, int(t), frame_id) for t, T_k in zip(t_ns, T)]
    return msg_class(PATH)(header=header(stamp_t_ns, frame_id), poses=poses)


def point_cloud2(points: np.ndarray, t_ns: int, frame_id: str) -> Any:
    """``sensor_msgs/PointCloud2`` of (N, 3) points in ``frame_id``: one row, fields ``x, y, z``
    float32 little-endian at offsets 0, 4, 8 (12 bytes a point); non-finite points dropped."""
    p = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    p = np.ascontiguousarray(p[np.all(np.isfinite(p), axis=1)], dtype="<f4")
    PointField = msg_class("sensor_msgs/msg/PointField")
    fields = [PointField(name=n, offset=4 * i, datatype=_FLOAT32, count=1) for i, n in enumerate("xyz")]
    return msg_class(POINT_CLOUD2)(
        header=header(t_ns, frame_id), height=1, width=len(p), fields=fields, is_bigendian=False,
        point_step=12, row_step=12 * len(p), data=np.frombuffer(p.tobytes(), dtype=np.uint8).copy(),
        is_dense=True)


def image(pixels: np.ndarray, t_ns: int, frame_id: str) -> Any:
    """``sensor_msgs/Image``: (H, W) uint8 -> ``mono8``, (H, W, 3) uint8 RGB -> ``rgb8``, (H, W)
    float32 -> ``32FC1`` (e.g. depth in metres, NaN where unknown); rows unpadded."""
    a = np.ascontiguousarray(pixels)
    if a.dtype == np.uint8 and a.ndim == 2:
        encoding, channels = "mono8", 1
    elif a.dtype == np.uint8 and a.ndim == 3 and a.shape[2] == 3:
        encoding, channels = "rgb8", 3
    elif a.dtype == np.float32 and a.ndim == 2:
        encoding, channels, a = "32FC1", 1, a.astype("<f4")
    else:
        raise CodecError(f"image: unsupported array {a.dtype} {a.shape} (mono8, rgb8 or 32FC1)")
    h, w = a.shape[:2]
    return msg_class(IMAGE)(header=header(t_ns, frame_id), height=h, width=w, encoding=encoding,
                            is_bigendian=0, step=w * channels * a.itemsize,
                            data=np.frombuffer(a.tobytes(), dtype=np.uint8).copy())


def compressed_image(data: bytes, t_ns: int, frame_id: str, fmt: str = "jpeg") -> Any:
    """``sensor_msgs/CompressedImage`` holding already-compressed bytes (``fmt``: jpeg or png)."""
    return msg_class(COMPRESSED_IMAGE)(header=header(t_ns, frame_id), format=fmt,
                                       data=np.frombuffer(bytes(data), dtype=np.uint8).copy())


def depth_grid_camera(camera: PinholeCamera, image_size_px: tuple[int, int], grid_shape: tuple[int, int]) -> PinholeCamera:
    """The intrinsics of a keyframe's coarse depth grid ``(h, w)``: ``camera`` (the keyframe
    image's, brought to ``image_size_px`` = (width, height) if it differs) resized to the grid,
    which covers the whole image (pixel centres map to pixel centres,
    :meth:`~metricslam.camera.PinholeCamera.resized`) — the CameraInfo that pairs with the depth
    image (image_transport's convention), in the MCAP recordings and on the live bridge alike."""
    width_px, height_px = (int(image_size_px[0]), int(image_size_px[1]))
    if (camera.width_px, camera.height_px) != (width_px, height_px):
        camera = camera.resized(width_px, height_px)
    h, w = (int(grid_shape[0]), int(grid_shape[1]))
    return camera.resized(w, h)


def camera_info(camera: PinholeCamera, t_ns: int, frame_id: str) -> Any:
    """``sensor_msgs/CameraInfo`` of a rectified pinhole camera: ``plumb_bob`` with zero D,
    ``K`` and ``P = [K | 0]``, ``R = I``."""
    K = camera.K
    P = np.hstack([K, np.zeros((3, 1))])
    roi = msg_class("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0,
                                                        do_rectify=False)
    return msg_class(CAMERA_INFO)(
        header=header(t_ns, frame_id), height=camera.height_px, width=camera.width_px,
        distortion_model="plumb_bob", d=np.zeros(5), k=K.reshape(9).copy(), r=np.eye(3).reshape(9),
        p=P.reshape(12).copy(), binning_x=0, binning_y=0, roi=roi)


def tf_message(T_parent_child: np.ndarray, t_ns: int, parent: str, child: str) -> Any:
    """``tf2_msgs/TFMessage`` with one transform: ``child``'s pose in ``parent``."""
    p = pose(T_parent_child)
    Vector3 = msg_class("geometry_msgs/msg/Vector3")
    transform = msg_class("geometry_msgs/msg/Transform")(
        translation=Vector3(x=p.position.x, y=p.position.y, z=p.position.z), rotation=p.orientation)
    stamped = msg_class("geometry_msgs/msg/TransformStamped")(
        header=header(t_ns, parent), child_frame_id=child, transform=transform)
    return msg_class(TF_MESSAGE)(transforms=[stamped])


def float64(value: float) -> Any:
    """``std_msgs/Float64`` (a plottable number; the topic name says what and in which unit)."""
    return msg_class(FLOAT64)(data=float(value))


def flag(value: bool) -> Any:
    """``std_msgs/Bool``."""
    return msg_class(BOOL)(data=bool(value))


# -- input ------------------------------------------------------------------------------------
def image_pixels(msg: Any) -> np.ndarray:
    """A ``sensor_msgs/Image`` as (H, W) uint8 gray (``mono8``) or (H, W, 3) uint8 RGB (``rgb8``;
    ``bgr8`` is reordered to RGB). Row padding (``step`` > width · channels) is removed.

    Raises:
        CodecError: another encoding, or ``data`` shorter than ``step · height``.
    """
    if msg.encoding not in INPUT_ENCODINGS:
        raise CodecError(f"image encoding {msg.encoding!r} is not supported; publish one of "
                         f"{', '.join(INPUT_ENCODINGS)}")
    channels = 1 if msg.encoding == "mono8" else 3
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0 or step < w * channels:
        raise CodecError(f"image {w}x{h} with step {step} is inconsistent ({msg.encoding})")
    data = np.asarray(msg.data, dtype=np.uint8)
    if data.size < step * h:
        raise CodecError(f"image data has {data.size} bytes, {step} x {h} = {step * h} needed")
    rows = data[:step * h].reshape(h, step)[:, :w * channels]
    pixels = rows.reshape(h, w) if channels == 1 else rows.reshape(h, w, 3)
    if msg.encoding == "bgr8":
        pixels = pixels[:, :, ::-1]
    return np.ascontiguousarray(pixels)


def camera_from_info(msg: Any) -> PinholeCamera:
    """A ``sensor_msgs/CameraInfo`` as a :class:`PinholeCamera` (its ``K``).

    Raises:
        CodecError: non-zero distortion (the SLAM needs rectified images), or unusable ``K`` /
            image size.
    """
    d = np.asarray(msg.d, dtype=float)
    if d.size and np.any(d != 0):
        raise CodecError(f"CameraInfo has distortion D={d.tolist()}; metricslam needs rectified "
                         "images: publish rectified images (e.g. image_proc's image_rect) with a "
                         "CameraInfo whose D is zero")
    K = np.asarray(msg.k, dtype=float).reshape(3, 3)
    if int(msg.width) <= 0 or int(msg.height) <= 0:
        raise CodecError(f"CameraInfo image size {msg.width}x{msg.height} is not usable")
    try:
        return PinholeCamera.from_K(K, int(msg.width), int(msg.height))
    except Exception as exc:  # CameraError / validation: say what is wrong with K
        raise CodecError(f"CameraInfo K={K.reshape(9).tolist()} is not a pinhole camera: {exc}") from None
