"""ROS 2 over Zenoh for the SLAM service (``SLAM_ROS2=1``): no ROS install needed.

Speaks rmw_zenoh's conventions (:mod:`metricslam.ros2.rmw_zenoh`: data key expressions, node and
endpoint liveliness tokens, the per-sample attachment), so a node on ``rmw_zenoh_cpp`` in the
same ``ROS_DOMAIN_ID`` sees ordinary topics. Per camera ``<cam>`` (its id as a ROS name token):

out (CDR, reliable, volatile, keep-last 10)::

    /metricslam/<cam>/odom       nav_msgs/Odometry        every TRACKING frame: the CONTINUOUS pose
                                                          (native ``…/odom``; never jumps) and its twist
    /metricslam/<cam>/pose       geometry_msgs/PoseStamped every TRACKING frame: the live pose
                                                          (native ``…/pose``; jumps when a correction lands)
    /metricslam/<cam>/path       nav_msgs/Path            the optimized trajectory, on change
    /metricslam/<cam>/landmarks  sensor_msgs/PointCloud2  the local window's landmarks, per keyframe
    /metricslam/<cam>/keyframe/depth/image        sensor_msgs/Image 32FC1: a keyframe's coarse
                                                  metric depth (m; NaN unknown), per depth answer
    /metricslam/<cam>/keyframe/depth/camera_info  sensor_msgs/CameraInfo of that depth image, AT
                                                  ITS OWN (coarse) resolution: the camera's K
                                                  scaled to the grid (image_transport's pairing)
    /tf                          tf2_msgs/TFMessage       ``<cam>/world`` -> ``<cam>/camera_optical``
                                                          with every ``…/pose``, as the MCAP
                                                          recordings carry it (keep-last 100)

in::

    /metricslam/<cam>/image        sensor_msgs/Image (mono8, rgb8, bgr8; rectified)
    /metricslam/<cam>/camera_info  sensor_msgs/CameraInfo (K; D must be zero)

Frames: ``header.frame_id = <cam>/world`` (the SLAM world: the first camera pose's optical
frame), or ``map`` once the camera relocalized into the service's saved map (``frame_id "map"``
on the native message; docs/maps.md), ``child_frame_id = <cam>/camera_optical`` (x right, y down, z forward). Images are refused
(and counted; ``…/status`` and the log say why) until that camera's CameraInfo arrived. The
bridge translates the native messages the service publishes (:meth:`Ros2Bridge.forward`); it owns
no SLAM state.

Scale state in the standard messages: the Odometry's pose covariance diagonal (x, y, z) is exactly
``position_sigma_m²`` when the pose is ``metric``, :data:`PROVISIONAL_VARIANCE` (100 m²) when
``provisional`` and :data:`UNKNOWN_VARIANCE` (1e6) when ``unscaled`` (:func:`odometry_covariances`;
a ROS node reads it back with :func:`scale_state_from_covariance`: ≥ 5e5 unscaled, ≥ 50
provisional, else metric). The twist's linear variances follow the same three levels (a velocity
is only as metric as the pose); its angular ones are ``rotation_sigma_rad²`` (rotation needs no
scale). The PoseStamped of the same stamp has the same scale state.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from typing import Callable

import numpy as np
import zenoh

from metricslam.camera import PinholeCamera
from metricslam.errors import CodecError, ConfigError
from metricslam.ros2 import messages
from metricslam.ros2.rmw_zenoh import (
    PUBLISHER, SUBSCRIPTION, Node, Qos, attachment, frame_ids, gid, parent_frame_id, ros_token, topic_key,
)
from metricslam.ros2.typestore import (
    CAMERA_INFO, IMAGE, ODOMETRY, PATH, POINT_CLOUD2, POSE_STAMPED, TF_MESSAGE, dds_type_name, deserialize,
    serialize, typestore,
)
from metricslam.slam.types import ScaleState, TrackingState
from metricslam.wire import keys
from metricslam.wire.codec import FrameMessage, Message, PoseMessage, StatusMessage, TrajectoryMessage, encode
from metricslam.wire.map_messages import KeyframeDepthMessage, LandmarksMessage
from metricslam.wire.odometry_message import OdometryMessage

log = logging.getLogger(__name__)
QOS = Qos()  # reliable, volatile, keep-last 10: "::,10:,:,:,,"
TF_QOS = Qos(depth=100)  # tf2_ros's listener QoS (reliable, volatile, keep-last 100)
TF_TOPIC = "/tf"
#: variance (m², rad², (m/s)², …) meaning "no information": a fusing filter gives it no weight
UNKNOWN_VARIANCE = 1e6
#: position variance (m²) of a ``provisional`` pose: metric-ish, from few scale measurements
PROVISIONAL_VARIANCE = 100.0


def odometry_covariances(scale_state: ScaleState | bool, position_sigma_m: float,
                         rotation_sigma_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """``(pose_covariance, twist_covariance)`` (6, 6) for ``nav_msgs/Odometry``.

    The SLAM computes no per-frame marginal covariance, so the pose gets a NOMINAL diagonal
    (``position_sigma_m``², ``rotation_sigma_rad``²) whose position variance says the scale
    state (module docstring): ``position_sigma_m``² when ``metric``, :data:`PROVISIONAL_VARIANCE`
    when ``provisional``, :data:`UNKNOWN_VARIANCE` when ``unscaled`` (a bool is
    ``scale_established``: True metric, False unscaled). The twist (from the continuous
    odometry) gets the same position-level variance on its linear part (per s²) and
    ``rotation_sigma_rad``² on its angular part.
    """
    if isinstance(scale_state, bool):
        scale_state = ScaleState.METRIC if scale_state else ScaleState.UNSCALED
    if position_sigma_m ** 2 >= PROVISIONAL_VARIANCE / 2:
        raise ValueError(f"position_sigma_m={position_sigma_m} would read as provisional; keep it < 7 m")
    var_p = {ScaleState.METRIC: position_sigma_m ** 2, ScaleState.PROVISIONAL: PROVISIONAL_VARIANCE,
             ScaleState.UNSCALED: UNKNOWN_VARIANCE}[ScaleState(scale_state)]
    diag = [var_p] * 3 + [rotation_sigma_rad ** 2] * 3
    return np.diag(diag), np.diag(diag)


def scale_state_from_covariance(pose_covariance: np.ndarray) -> ScaleState:
    """The scale state an Odometry's pose covariance (36,) or (6, 6) says (module docstring)."""
    var_p = float(np.asarray(pose_covariance, dtype=float).reshape(36)[0])
    if var_p >= UNKNOWN_VARIANCE / 2:
        return ScaleState.UNSCALED
    return ScaleState.PROVISIONAL if var_p >= PROVISIONAL_VARIANCE / 2 else ScaleState.METRIC


def depth_camera(camera: PinholeCamera | None, msg: KeyframeDepthMessage) -> PinholeCamera | None:
    """The intrinsics of a keyframe's coarse depth grid (:func:`metricslam.ros2.messages.depth_grid_camera`);
    None when the camera is unknown."""
    if camera is None:
        return None
    return messages.depth_grid_camera(camera, (msg.image_width_px, msg.image_height_px), msg.inv_depth_per_m.shape)


class RosPublisher:
    """One ROS 2 publisher: a Zenoh publisher on the topic's key, its ``MP`` liveliness token,
    its GID, and the sequence number each sample's attachment carries (from 1)."""

    def __init__(self, session: zenoh.Session, node: Node, entity_id: int, topic: str, msgtype: str,
                 qos: Qos = QOS) -> None:
        self.topic, self.msgtype = topic, msgtype
        self.key = topic_key(node.domain_id, topic, msgtype)
        self.token_key = node.endpoint_token(entity_id, PUBLISHER, topic, msgtype, qos)
        self.gid = gid(self.token_key)
        self._lock = threading.Lock()
        self._sequence = 0
        self._token = session.liveliness().declare_token(self.token_key)
        self._publisher = session.declare_publisher(self.key)

    def put(self, message: object) -> None:
        payload = serialize(message)
        with self._lock:
            self._sequence += 1
            self._publisher.put(payload, attachment=attachment(self._sequence, time.time_ns(), self.gid))

    def close(self) -> None:
        self._publisher.undeclare()
        self._token.undeclare()


class _CameraInput:
    """Input state of one camera: its intrinsics (None until a CameraInfo arrived)."""

    def __init__(self) -> None:
        self.camera: PinholeCamera | None = None
        self.images = 0
        self.refused = 0
        self.next_index = 0
        self.last_note_s = -1e9


def parent_frame(camera_id: str, message: Message) -> str:
    """``map`` for a message in the saved map's frame, else the camera's ``<tok>/world``
    (:func:`~metricslam.ros2.rmw_zenoh.parent_frame_id` of the message's ``frame_id``)."""
    return parent_frame_id(camera_id, getattr(message, "frame_id", "world"))


class Ros2Bridge:
    """The service's ROS 2 face (module docstring).

    Args:
        session: the service's open Zenoh session.
        domain_id / node_name: ``ROS_DOMAIN_ID`` and the node the topics belong to.
        position_sigma_m / rotation_sigma_rad: :func:`odometry_covariances`.
        offer_frame: ``(camera_id, FrameMessage bytes)`` -> the camera's worker queue.
        publish_native: ``(camera_id, topic, message)`` -> ``metricslam/<camera_id>/<topic>``
            (for the ``…/status`` note while images are refused).
        serves: whether this service instance handles a camera (its ``frame_key_expr``).
        camera_of: the intrinsics a camera's frames carry (None until known): the keyframe depth's
            CameraInfo is derived from them.

    Raises:
        ConfigError: the ``ros`` extra (rosbags) is not installed (:meth:`check_available`).
    """

    def __init__(self, session: zenoh.Session, domain_id: int, node_name: str,
                 offer_frame: Callable[[str, bytes], None],
                 publish_native: Callable[[str, str, Message], None],
                 serves: Callable[[str], bool] = lambda camera_id: True,
                 position_sigma_m: float = 0.5, rotation_sigma_rad: float = 0.02,
                 camera_of: Callable[[str], PinholeCamera | None] = lambda camera_id: None) -> None:
        self.check_available()
        self._camera_of = camera_of
        self._tf: RosPublisher | None = None
        self.node = Node(domain_id=domain_id, zid=str(session.info.zid()), node_id=0, name=node_name)
        self._session = session
        self._offer_frame, self._publish_native, self._serves = offer_frame, publish_native, serves
        self._sigmas = (position_sigma_m, rotation_sigma_rad)
        self._lock = threading.Lock()
        self._entity_ids = itertools.count(1)
        self._outputs: dict[str, dict[str, RosPublisher]] = {}
        self._inputs: dict[str, _CameraInput] = {}
        self._tokens = [session.liveliness().declare_token(self.node.token())]
        self.malformed = 0
        self._subscribers = [
            session.declare_subscriber(self._input_key("image", IMAGE), self._on_image),
            session.declare_subscriber(self._input_key("camera_info", CAMERA_INFO), self._on_camera_info),
        ]
        log.info("ROS 2 bridge: node /%s on domain %d (zenoh session %s)", node_name, domain_id, self.node.zid)

    @staticmethod
    def check_available() -> None:
        """Raise :class:`ConfigError` now, naming the fix, when ROS 2 messages cannot be built
        (no ``rosbags``): otherwise ``SLAM_ROS2=1`` would fail on every publish, later."""
        try:
            typestore()
        except ConfigError as exc:
            raise ConfigError(f"SLAM_ROS2=1 / --ros2: {exc} (the slam image installs it)") from None

    def _input_key(self, leaf: str, msgtype: str) -> str:
        # any camera, any version (type hash) of the type
        return f"{self.node.domain_id}/metricslam/*/{leaf}/{dds_type_name(msgtype)}/*"

    # -- outputs --------------------------------------------------------------------------------
    def forward(self, camera_id: str, topic: str, message: Message) -> None:
        """Publish the ROS 2 counterpart of a native message, if it has one (never raises)."""
        try:
            if isinstance(message, PoseMessage) and topic == "pose":
                self._forward_pose(camera_id, message)
            elif isinstance(message, OdometryMessage) and topic == "odom":
                self._forward_odometry(camera_id, message)
            elif isinstance(message, TrajectoryMessage) and topic == "path":
                out = self._camera_outputs(camera_id)
                out["path"].put(messages.path(message.t_ns, message.T_world_cam,
                                              int(message.t_ns[-1]) if len(message.t_ns) else 0,
                                              parent_frame(camera_id, message)))
            elif isinstance(message, LandmarksMessage):
                out = self._camera_outputs(camera_id)
                out["landmarks"].put(messages.point_cloud2(message.points_world, message.t_ns,
                                                           parent_frame(camera_id, message)))
            elif isinstance(message, KeyframeDepthMessage):
                self._forward_keyframe_depth(camera_id, message)
        except Exception:  # noqa: BLE001 -- the ROS face must never disturb the native one
            log.exception("ROS 2 publish of %s/%s failed", camera_id, topic)

    def _forward_pose(self, camera_id: str, msg: PoseMessage) -> None:
        if msg.state != TrackingState.TRACKING:
            return  # initializing / lost / invalid frames carry no pose of their own
        world, cam = parent_frame(camera_id, msg), frame_ids(camera_id)[1]
        self._camera_outputs(camera_id)["pose"].put(messages.pose_stamped(msg.T_world_cam, msg.t_ns, world))
        self._tf_publisher().put(messages.tf_message(msg.T_world_cam, msg.t_ns, world, cam))

    def _forward_keyframe_depth(self, camera_id: str, msg: KeyframeDepthMessage) -> None:
        _, cam = frame_ids(camera_id)
        out = self._camera_outputs(camera_id)
        out["depth"].put(messages.image(msg.depth_m(), msg.t_ns, cam))
        info = depth_camera(self._camera_of(camera_id), msg)
        if info is not None:
            out["depth_info"].put(messages.camera_info(info, msg.t_ns, cam))

    def _tf_publisher(self) -> RosPublisher:
        with self._lock:
            if self._tf is None:
                self._tf = RosPublisher(self._session, self.node, next(self._entity_ids), TF_TOPIC,
                                        TF_MESSAGE, TF_QOS)
            return self._tf

    def _forward_odometry(self, camera_id: str, msg: OdometryMessage) -> None:
        if msg.state != TrackingState.TRACKING:
            return
        world, cam = parent_frame(camera_id, msg), frame_ids(camera_id)[1]
        pose_cov, twist_cov = odometry_covariances(msg.scale_state, *self._sigmas)
        self._camera_outputs(camera_id)["odom"].put(messages.odometry(
            msg.T_world_cam, msg.t_ns, world, cam, pose_cov, twist_cov, twist_cam=msg.twist_cam))

    def _camera_outputs(self, camera_id: str) -> dict[str, RosPublisher]:
        with self._lock:
            if camera_id not in self._outputs:
                base = f"/metricslam/{ros_token(camera_id)}"
                self._outputs[camera_id] = {
                    leaf: RosPublisher(self._session, self.node, next(self._entity_ids), f"{base}/{leaf}", msgtype)
                    for leaf, msgtype in (("odom", ODOMETRY), ("pose", POSE_STAMPED), ("path", PATH),
                                          ("landmarks", POINT_CLOUD2))}
                depth = {"depth": ("keyframe/depth/image", IMAGE),
                         "depth_info": ("keyframe/depth/camera_info", CAMERA_INFO)}
                self._outputs[camera_id].update({
                    name: RosPublisher(self._session, self.node, next(self._entity_ids), f"{base}/{leaf}", msgtype)
                    for name, (leaf, msgtype) in depth.items()})
            return self._outputs[camera_id]

    # -- inputs ---------------------------------------------------------------------------------
    def _camera_input(self, key_expr: str) -> tuple[str, _CameraInput] | None:
        parts = str(key_expr).split("/")
        try:
            camera_id = keys.check_camera_id(parts[2])
        except (CodecError, IndexError):
            self._count_malformed(f"ROS 2 input on an unusable key {key_expr!r}")
            return None
        if not self._serves(camera_id):
            return None
        with self._lock:
            inp = self._inputs.get(camera_id)
            if inp is None:
                inp = self._inputs[camera_id] = _CameraInput()
                base = f"/metricslam/{parts[2]}"
                self._tokens += [self._session.liveliness().declare_token(self.node.endpoint_token(
                    next(self._entity_ids), SUBSCRIPTION, f"{base}/{leaf}", msgtype, QOS))
                    for leaf, msgtype in (("image", IMAGE), ("camera_info", CAMERA_INFO))]
        return camera_id, inp

    def _on_camera_info(self, sample: zenoh.Sample) -> None:
        found = self._camera_input(str(sample.key_expr))
        if found is None:
            return
        camera_id, inp = found
        try:
            camera = messages.camera_from_info(deserialize(sample.payload.to_bytes(), CAMERA_INFO))
        except CodecError as exc:
            self._count_malformed(str(exc))
            if inp.camera is None:
                self._note(camera_id, inp, f"CameraInfo refused: {exc}")
            return
        if inp.camera is None:
            log.info("camera %s: intrinsics from sensor_msgs/CameraInfo: %s", camera_id, camera)
        inp.camera = camera

    def _on_image(self, sample: zenoh.Sample) -> None:
        found = self._camera_input(str(sample.key_expr))
        if found is None:
            return
        camera_id, inp = found
        inp.images += 1
        if inp.camera is None:
            inp.refused += 1
            self._note(camera_id, inp, f"waiting for sensor_msgs/CameraInfo on /metricslam/"
                       f"{ros_token(camera_id)}/camera_info: {inp.refused} image(s) refused so far")
            return
        try:
            msg = deserialize(sample.payload.to_bytes(), IMAGE)
            frame = FrameMessage(camera_id=camera_id, frame_index=inp.next_index,
                                 t_ns=max(messages.stamp_ns(msg.header), 0), camera=inp.camera,
                                 t_sent_ns=time.time_ns(), image=messages.image_pixels(msg))
        except (CodecError, ValueError) as exc:  # ValueError: image size != CameraInfo size
            self._count_malformed(f"camera {camera_id}: sensor_msgs/Image refused: {exc}")
            return
        inp.next_index += 1
        self._offer_frame(camera_id, encode(frame))

    def _note(self, camera_id: str, inp: _CameraInput, text: str) -> None:
        """Say why input is refused: in the log and on ``…/status`` (at most once a second)."""
        now = time.monotonic()
        if now - inp.last_note_s < 1.0:
            return
        inp.last_note_s = now
        log.warning("camera %s: %s", camera_id, text)
        self._publish_native(camera_id, "status", StatusMessage(
            camera_id=camera_id, t_ns=time.time_ns(), frames_received=inp.images, frames_processed=0,
            queue_drops=0, malformed=self.malformed, queue_depth=0, fps=0.0,
            session_stats={"ros2_input": text}))

    def _count_malformed(self, why: str) -> None:
        self.malformed += 1
        if self.malformed <= 5 or self.malformed % 100 == 0:
            log.warning("ROS 2 input #%d dropped: %s", self.malformed, why)

    # -- housekeeping ---------------------------------------------------------------------------
    def stats(self) -> dict:
        """For the service's health JSON."""
        with self._lock:
            cams = {cid: {"camera_info": inp.camera is not None, "images": inp.images,
                          "refused_without_camera_info": inp.refused}
                    for cid, inp in self._inputs.items()}
            outputs = sorted(self._outputs)
        return {"domain_id": self.node.domain_id, "node": self.node.name, "zid": self.node.zid,
                "inputs": cams, "outputs": outputs, "malformed": self.malformed}

    def close_inputs(self) -> None:
        """Stop taking images (first step of the service's stop)."""
        for sub in self._subscribers:
            sub.undeclare()
        self._subscribers = []

    def close(self) -> None:
        """Undeclare everything (publishers, tokens); the session stays open."""
        self.close_inputs()
        with self._lock:
            outputs = [p for pubs in self._outputs.values() for p in pubs.values()]
            outputs += [self._tf] if self._tf is not None else []
            tokens, self._tokens, self._outputs, self._tf = self._tokens, [], {}, None
        for pub in outputs:
            pub.close()
        for token in tokens:
            token.undeclare()
