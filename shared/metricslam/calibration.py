"""Camera calibration files: the one loader for every format metricslam reads, and undistortion.

Metric scale comes from the depth network, which predicts disparity as a fraction of the image
width and turns it into metres with the focal length: wrong intrinsics give a wrong scale. So
nothing here guesses; a missing or malformed file is a :class:`~metricslam.errors.CalibrationError`
that names the file, the key and what to write instead. How to calibrate a camera:
``docs/calibration.md`` (``metricslam calibrate``).

Formats, told apart by their keys (:func:`load_calibration`):

* **metricslam YAML** (what ``metricslam calibrate`` writes, what ``--calib`` documents)::

      width: 640            # image size the intrinsics are for (px)
      height: 480
      fx: 517.3             # focal lengths and principal point (px)
      fy: 516.5
      cx: 318.6
      cy: 255.3
      distortion_model: radtan    # none | radtan | equidistant
      distortion_coefficients: [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]
      mount_height_m: 1.65  # optional: optical centre above the road (m), for ground scale

* **OpenCV FileStorage YAML** (``cv2.FileStorage``, OpenCV's calibration sample):
  ``camera_matrix`` and ``distortion_coefficients`` as ``!!opencv-matrix``, ``image_width``,
  ``image_height``; ``fisheye_model: 1`` or ``distortion_model: equidistant`` for a fisheye.
  Other keys the sample writes (``avg_reprojection_error`` …) are ignored.
* **EuRoC / Kalibr ``sensor.yaml``**: ``intrinsics: [fu, fv, cu, cv]``, ``resolution: [w, h]``,
  ``distortion_model``, ``distortion_coefficients``, ``camera_model: pinhole``.

Distortion models: ``radtan`` is OpenCV's (``k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [τx τy]]]]``,
aliases ``radial-tangential``, ``plumb_bob``); ``equidistant`` is OpenCV's fisheye (``k1 k2 k3
k4``, alias ``fisheye``). Images are undistorted once, at load, to a pinhole camera **with the
same K** (:meth:`Calibration.undistort_maps`), so everything downstream is an exact pinhole model
(:class:`~metricslam.camera.PinholeCamera`).

Example::

    calib = load_calibration("my_camera.yaml")
    seq = open_sequence("SEQ", calibration=calib)   # overrides what the reader would use
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from metricslam.camera import PinholeCamera
from metricslam.errors import CalibrationError, CameraError, validation_problems

log = logging.getLogger(__name__)

DistortionModel = Literal["none", "radtan", "equidistant"]
#: names other tools use for the models, -> ours
MODEL_ALIASES = {"none": "none", "radtan": "radtan", "radial-tangential": "radtan", "plumb_bob": "radtan",
                 "opencv": "radtan", "equidistant": "equidistant", "fisheye": "equidistant"}
#: coefficient counts OpenCV accepts per model
COEFFICIENT_COUNTS = {"none": (0,), "radtan": (4, 5, 8, 12, 14), "equidistant": (4,)}
#: keys of the metricslam YAML format
METRICSLAM_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "distortion_model", "distortion_coefficients",
                   "mount_height_m")
#: largest relative aspect-ratio difference for which intrinsics are rescaled to another image size
ASPECT_TOLERANCE = 0.01


class Calibration(BaseModel):
    """A camera's intrinsics and lens distortion, for images of ``camera.width_px × height_px``.

    Attributes:
        camera: pinhole intrinsics (px). After undistortion they describe the images exactly.
        distortion_model: ``none``, ``radtan`` (OpenCV) or ``equidistant`` (OpenCV fisheye).
        distortion_coefficients: the model's coefficients (see the module docstring).
        source: where the calibration came from (a path, or "published TUM fr1"), for logs.
        mount_height_m: the camera's optical centre above the road plane (m), 0 < h <= 10, for
            ground-plane scale (docs/ground_scale.md); None when not given.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    camera: PinholeCamera
    distortion_model: DistortionModel = "none"
    distortion_coefficients: tuple[float, ...] = ()
    source: str = ""
    mount_height_m: float | None = Field(default=None, gt=0, le=10)

    @model_validator(mode="after")
    def _check_coefficients(self) -> "Calibration":
        n = len(self.distortion_coefficients)
        if self.distortion_model == "none" and any(self.distortion_coefficients):
            raise ValueError("distortion_model none with non-zero distortion_coefficients")
        if self.distortion_model != "none" and n not in COEFFICIENT_COUNTS[self.distortion_model]:
            raise ValueError(f"distortion_model {self.distortion_model} takes "
                             f"{' or '.join(map(str, COEFFICIENT_COUNTS[self.distortion_model]))} "
                             f"coefficients, got {n}")
        if not all(np.isfinite(self.distortion_coefficients)):
            raise ValueError("distortion_coefficients contain NaN or inf")
        return self

    @property
    def has_distortion(self) -> bool:
        """True when images need undistorting (some coefficient is non-zero)."""
        return self.distortion_model != "none" and any(self.distortion_coefficients)

    def for_image(self, width_px: int, height_px: int) -> "Calibration":
        """This calibration for images of ``width × height``: itself, or rescaled (with a warning)
        when the image has the same aspect ratio at another resolution.

        Raises:
            CalibrationError: the aspect ratio differs (another camera, or a cropped image).
        """
        cam = self.camera
        if (cam.width_px, cam.height_px) == (width_px, height_px):
            return self
        if abs((width_px / height_px) / (cam.width_px / cam.height_px) - 1.0) > ASPECT_TOLERANCE:
            raise CalibrationError(
                f"calibration {self.source or ''} is for {cam.width_px}x{cam.height_px} images but "
                f"these are {width_px}x{height_px} (another aspect ratio: cropped, or another "
                "camera); calibrate at this resolution (docs/calibration.md)")
        log.warning("calibration %s is for %dx%d images; rescaling it to %dx%d", self.source,
                    cam.width_px, cam.height_px, width_px, height_px)
        return self.model_copy(update={"camera": cam.resized(width_px, height_px)})

    def undistort_maps(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(map_x, map_y)`` (H, W) float32 for ``cv2.remap`` to the pinhole model with the same
        K, or None when there is nothing to undo."""
        if not self.has_distortion:
            return None
        import cv2

        K = self.camera.K
        D = np.asarray(self.distortion_coefficients, dtype=np.float64)
        size = (self.camera.width_px, self.camera.height_px)
        if self.distortion_model == "equidistant":
            return cv2.fisheye.initUndistortRectifyMap(K, D, np.eye(3), K, size, cv2.CV_32FC1)
        return cv2.initUndistortRectifyMap(K, D, None, K, size, cv2.CV_32FC1)

    def to_yaml(self) -> str:
        """The metricslam YAML format (what :func:`load_calibration` reads back)."""
        c = self.camera
        coeffs = ", ".join(repr(float(v)) for v in self.distortion_coefficients)
        return (f"# metricslam camera calibration ({self.source or 'metricslam'}); docs/calibration.md\n"
                f"width: {c.width_px}\nheight: {c.height_px}\n"
                f"fx: {c.fx_px!r}\nfy: {c.fy_px!r}\ncx: {c.cx_px!r}\ncy: {c.cy_px!r}\n"
                f"distortion_model: {self.distortion_model}\n"
                f"distortion_coefficients: [{coeffs}]\n"
                + (f"mount_height_m: {self.mount_height_m!r}\n" if self.mount_height_m is not None else ""))


def make_calibration(K: np.ndarray, width_px: int, height_px: int, model: str = "none",
                     coefficients=(), source: str = "", path: object = None,
                     mount_height_m: float | None = None) -> Calibration:
    """A checked :class:`Calibration` from a 3x3 ``K``; raises :class:`CalibrationError` naming
    ``path`` on bad values."""
    name = MODEL_ALIASES.get(str(model).lower())
    if name is None:
        raise CalibrationError(f"distortion_model {model!r} is not supported; expected one of "
                               f"{sorted(MODEL_ALIASES)}", path)
    coeffs = tuple(float(v) for v in np.asarray(coefficients, dtype=float).reshape(-1))
    if name == "none" and not any(coeffs):
        coeffs = ()
    try:
        camera = PinholeCamera.from_K(K, width_px, height_px)
        return Calibration(camera=camera, distortion_model=name, distortion_coefficients=coeffs,
                           source=source or ("" if path is None else str(path)),
                           mount_height_m=mount_height_m)
    except (CameraError, ValueError) as exc:
        raise CalibrationError(f"invalid calibration: {validation_problems(exc)}", path) from None


def read_yaml_document(path: Path) -> dict:
    """A calibration YAML file as a dict: OpenCV's ``%YAML:1.0`` header and ``!!opencv-matrix``
    tags are understood (a matrix becomes ``{rows, cols, dt, data}``)."""
    import yaml

    path = Path(path)
    if path.is_dir():
        raise CalibrationError("is a folder: pass the calibration file inside it", path)
    if not path.is_file():
        raise CalibrationError("calibration file does not exist", path)

    class _Loader(yaml.SafeLoader):
        pass

    _Loader.add_constructor("tag:yaml.org,2002:opencv-matrix",
                            lambda loader, node: loader.construct_mapping(node, deep=True))
    # OpenCV writes "%YAML:1.0", which is not a YAML directive PyYAML accepts
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise CalibrationError(f"cannot read the calibration file: {exc.strerror}", path) from None
    try:
        decoded = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise CalibrationError(
            f"not a text file (byte 0x{raw[exc.start]:02x} at offset {exc.start} is not UTF-8): pass "
            "a YAML calibration file (docs/calibration.md)", path) from None
    text = "\n".join("" if line.startswith("%") else line for line in decoded.splitlines())
    try:
        doc = yaml.load(text, Loader=_Loader)  # noqa: S506 -- a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        raise CalibrationError(f"not valid YAML: {exc}", path,
                               None if mark is None else mark.line + 1) from None
    if not isinstance(doc, dict):
        raise CalibrationError("expected a YAML mapping of calibration keys (docs/calibration.md)", path)
    return doc


def numbers(doc: dict, key: str, sizes: int | tuple[int, ...] | None, path: object) -> np.ndarray:
    """``doc[key]`` as a flat float array of one of ``sizes`` (any size: None), from a list or an
    OpenCV/EuRoC ``{data: [...]}`` matrix."""
    val = doc.get(key)
    if isinstance(val, dict):
        val = val.get("data")
    sizes = (sizes,) if isinstance(sizes, int) else sizes
    if val is None:
        raise CalibrationError(f"missing '{key}'", path)
    try:
        arr = np.asarray([float(v) for v in np.asarray(val, dtype=object).reshape(-1)], dtype=float)
    except (TypeError, ValueError):
        raise CalibrationError(f"'{key}' must be a list of numbers, got {val!r}", path) from None
    if (sizes is not None and arr.size not in sizes) or not np.all(np.isfinite(arr)):
        count = "" if sizes is None else " or ".join(map(str, sizes)) + " "
        raise CalibrationError(f"'{key}' must hold {count}finite numbers, got {arr.size}: {val!r}", path)
    return arr


def calibration_from_document(doc: dict, path: object = None) -> Calibration:
    """A :class:`Calibration` from a parsed YAML mapping in any supported format."""
    if "camera_matrix" in doc:
        return _from_opencv(doc, path)
    if "intrinsics" in doc:
        return _from_sensor_yaml(doc, path)
    if "fx" in doc:
        return _from_metricslam(doc, path)
    raise CalibrationError(
        "unknown calibration format: expected fx/fy/cx/cy/width/height (metricslam), "
        "camera_matrix/image_width/image_height (OpenCV) or intrinsics/resolution (EuRoC "
        "sensor.yaml); see docs/calibration.md", path)


def load_calibration(path: str | Path) -> Calibration:
    """Read a calibration file in any supported format (module docstring).

    Raises:
        CalibrationError: missing file, unknown format, a missing or malformed key.
    """
    return calibration_from_document(read_yaml_document(Path(path)), Path(path))


def _scalar(doc: dict, key: str, path: object, kind: type = float):
    if key not in doc:
        raise CalibrationError(f"missing '{key}'", path)
    try:
        value = kind(doc[key])
    except (TypeError, ValueError):
        raise CalibrationError(f"'{key}' must be a number, got {doc[key]!r}", path) from None
    if kind is int and value != float(doc[key]):
        raise CalibrationError(f"'{key}' must be a whole number of pixels, got {doc[key]!r}", path)
    return value


def _from_metricslam(doc: dict, path: object) -> Calibration:
    unknown = sorted(set(doc) - set(METRICSLAM_KEYS))
    if unknown:
        raise CalibrationError(f"unknown key(s) {unknown}; the metricslam format has "
                               f"{list(METRICSLAM_KEYS)}", path)
    fx, fy, cx, cy = (_scalar(doc, k, path) for k in ("fx", "fy", "cx", "cy"))
    w, h = (_scalar(doc, k, path, int) for k in ("width", "height"))
    model = doc.get("distortion_model", "none")
    coeffs = (numbers(doc, "distortion_coefficients", None, path)
              if doc.get("distortion_coefficients") is not None else ())
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    mount = _scalar(doc, "mount_height_m", path) if doc.get("mount_height_m") is not None else None
    if mount is not None and not 0.0 < mount <= 10.0:  # also NaN; pydantic would say it less plainly
        raise CalibrationError(f"'mount_height_m' must be the camera's height above the road in metres, "
                               f"0 < h <= 10 (KITTI's cam 0: 1.65), got {doc['mount_height_m']!r}", path)
    return make_calibration(K, w, h, model, coeffs, path=path, mount_height_m=mount)


def _from_opencv(doc: dict, path: object) -> Calibration:
    K = numbers(doc, "camera_matrix", 9, path).reshape(3, 3)
    w, h = (_scalar(doc, k, path, int) for k in ("image_width", "image_height"))
    fisheye = bool(doc.get("fisheye_model", 0))
    model = doc.get("distortion_model", "equidistant" if fisheye else "radtan")
    coeffs = (numbers(doc, "distortion_coefficients", (4, 5, 8, 12, 14), path)
              if doc.get("distortion_coefficients") is not None else ())
    if not len(coeffs):
        model = "none"
    return make_calibration(K, w, h, model, coeffs, path=path)


def _from_sensor_yaml(doc: dict, path: object) -> Calibration:
    camera_model = doc.get("camera_model", "pinhole")
    if camera_model != "pinhole":
        raise CalibrationError(f"camera_model {camera_model!r} is not supported; expected pinhole", path)
    fu, fv, cu, cv = numbers(doc, "intrinsics", 4, path)
    w, h = (int(v) for v in numbers(doc, "resolution", 2, path))
    coeffs = (numbers(doc, "distortion_coefficients", (4, 5, 8), path)
              if "distortion_coefficients" in doc else ())
    model = doc.get("distortion_model", "radial-tangential")
    K = np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
    return make_calibration(K, w, h, model if len(coeffs) else "none", coeffs, path=path)


def reader_camera(calibration: Calibration | None, K_file: np.ndarray, width_px: int, height_px: int,
                  calib_path: Path) -> tuple[PinholeCamera, tuple[np.ndarray, np.ndarray] | None]:
    """The camera (and undistortion maps) a dataset reader uses: the user's ``calibration``
    (``--calib``) wins over the intrinsics ``K_file`` (3x3 or 3x4) its own ``calib_path`` gives."""
    if calibration is not None:
        log.info("%s: intrinsics from %s instead of %s", calib_path.parent, calibration.source, calib_path.name)
        return camera_and_maps(calibration, width_px, height_px)
    try:
        return PinholeCamera.from_K(K_file, width_px, height_px), None
    except CameraError as exc:
        raise CalibrationError(f"its intrinsics are not a valid camera: {exc}", calib_path) from exc


def camera_and_maps(calibration: Calibration, width_px: int, height_px: int
                    ) -> tuple[PinholeCamera, tuple[np.ndarray, np.ndarray] | None]:
    """What a dataset reader needs from a calibration for images of ``width × height``: the
    pinhole camera of the (undistorted) images and the undistortion maps (None: none needed)."""
    calib = calibration.for_image(width_px, height_px)
    return calib.camera, calib.undistort_maps()
