"""The depth model's contract: what the ONNX file promises, stored in its metadata.

Two contract versions (:data:`CONTRACT_VERSIONS`); both output the **left disparity as a
fraction of width** (``d_frac``) at level L3 for a virtual stereo rig of baseline ``baseline_m``
(the training rig's), and both are served on an (h, w) grid spanning the caller's whole image.
Units: ``fx_px``/``width_px`` in pixels, ``baseline_m`` in metres, inverse depth in 1/m (see
``docs/conventions.md``, "Disparity and metric depth").

* **Version "1"** (the shipped models): the whole caller image is resized (no crop,
  anisotropically) to ``input_height × input_width``; ``d_frac`` is a fraction of the caller's
  width, so for a camera with focal length ``fx_px`` at image width ``width_px``::

      inv_depth_per_m = d_frac · width_px / (fx_px · baseline_m)

  The network has to guess the field of view (it learnt the training cameras').
* **Version "2"** (canonical camera, :mod:`metricslam.depth.canonical`): the caller image is
  warped to a virtual pinhole camera with focal lengths ``canonical_fx_px`` / ``canonical_fy_px``
  (px at the input resolution) and its principal point at the input centre — scaled by
  ``fx_c/fx``, ``fy_c/fy``, then centre-cropped or padded. ``d_frac`` is a fraction of the
  **input** width at the canonical focal length::

      inv_depth_per_m = d_frac · input_width / (canonical_fx_px · baseline_m)

  and is resampled onto the caller's grid; output cells less than ``valid_min_fraction``
  backed by real pixels are invalid (NaN on the caller grid).

Input normalization (both): gray, ``(pixel · scale − mean) / std``.

Every field is written into the ONNX ``metadata_props`` as one key (strings as they are, other
values JSON-encoded); :meth:`ModelContract.from_metadata` refuses a model whose metadata is
incomplete or whose ``contract_version`` / ``output_definition`` this code does not know.
:data:`CANONICAL_FIELDS` are required for version "2" and must be absent for version "1" (a
version-1 file carrying them, or a version-2 file lacking one, is refused).

Optional keys (:data:`OPTIONAL_FIELDS`) may be absent and then take their default, so models
exported before the key existed still load: ``weights_precision`` ("float32", or "int8-static"
for a model written by :func:`metricslam.depth.quantize.quantize_model`; any other value is
refused).
"""

from __future__ import annotations

import json
from typing import Any, Literal, get_args, get_origin

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from metricslam.depth.canonical import CanonicalCamera
from metricslam.errors import DepthModelError, validation_problems

#: the version a contract gets when none is given: "1", whole image resized (the shipped models).
CONTRACT_VERSION = "1"
#: the canonical-camera version (module docstring).
CANONICAL_CONTRACT_VERSION = "2"
#: every version this code reads; add one when the meaning of a field or of the output changes.
CONTRACT_VERSIONS: tuple[str, ...] = (CONTRACT_VERSION, CANONICAL_CONTRACT_VERSION)
#: metadata keys of version "2" only (required there, refused in version "1").
CANONICAL_FIELDS: tuple[str, ...] = ("canonical_fx_px", "canonical_fy_px", "valid_min_fraction")
#: ``valid_min_fraction`` of a version-2 contract built without one.
DEFAULT_VALID_MIN_FRACTION = 0.5
#: the only output definition this code understands.
OUTPUT_DEFINITION = "disparity_fraction_of_width"
#: Content-Type of a binary (P5) PGM upload: gray pixels as they are, the cheapest for the depth
#: service to read (its fast path; the SLAM service uploads keyframes this way)
PGM_MEDIA_TYPE = "image/x-portable-graymap"
#: weight precisions this code runs: the exported float32 graph, or its static int8 quantization.
WeightsPrecision = Literal["float32", "int8-static"]
WEIGHTS_PRECISIONS: tuple[str, ...] = get_args(WeightsPrecision)
FLOAT32, INT8_STATIC = WEIGHTS_PRECISIONS
#: metadata keys a model may omit (they take the field's default).
OPTIONAL_FIELDS: frozenset[str] = frozenset({"weights_precision"})


class Normalization(BaseModel):
    """``x = (pixel · scale − mean) / std`` for uint8 gray pixels."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    scale: float = Field(gt=0)
    mean: float
    std: float = Field(gt=0)


class ModelContract(BaseModel):
    """Everything a caller needs to run the model and interpret its output.

    Attributes:
        model_id: human-readable id, e.g. ``"pyramid-l3-kitti-no06"``.
        input_name / output_name: ONNX tensor names.
        input_height / input_width / input_channels: network input (B, C, H, W); C = 1 (gray).
        output_height / output_width: L3 output (B, h, w) = input / 8.
        output_definition: always :data:`OUTPUT_DEFINITION`.
        baseline_m: stereo baseline of the training rig, metres.
        params: number of trainable parameters.
        training_data: the exact training set (sequence list), free text.
        training_commit: git commit of the code that trained/exported the model.
        created: ISO-8601 UTC time of export.
        weights_precision: "float32" (as exported) or "int8-static" (quantized weights and
            activations, calibrated; see ``docs/depth_quantization.md``). Optional key.
        canonical_fx_px / canonical_fy_px: version "2" only: focal lengths of the canonical
            camera, px at the input resolution (None in version "1").
        valid_min_fraction: version "2" only: an output cell is valid when at least this
            fraction of its input pixels is real image (default 0.5; None in version "1").
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    model_id: str
    contract_version: str = CONTRACT_VERSION
    input_name: str = "image"
    input_height: int = Field(gt=0)
    input_width: int = Field(gt=0)
    input_channels: int = Field(default=1, ge=1, le=1)
    normalization: Normalization
    output_name: str = "d_frac_l3"
    output_height: int = Field(gt=0)
    output_width: int = Field(gt=0)
    output_definition: str = OUTPUT_DEFINITION
    baseline_m: float = Field(gt=0)
    params: int = Field(ge=0)
    training_data: str
    training_commit: str
    created: str
    weights_precision: WeightsPrecision = FLOAT32
    canonical_fx_px: float | None = Field(default=None, gt=0)
    canonical_fy_px: float | None = Field(default=None, gt=0)
    valid_min_fraction: float | None = Field(default=None, gt=0, le=1)

    @model_validator(mode="before")
    @classmethod
    def _default_valid_fraction(cls, data: Any) -> Any:
        if isinstance(data, dict) and str(data.get("contract_version")) == CANONICAL_CONTRACT_VERSION:
            data = {"valid_min_fraction": DEFAULT_VALID_MIN_FRACTION, **data}
        return data

    @model_validator(mode="after")
    def _version_fields(self) -> "ModelContract":
        if self.contract_version not in CONTRACT_VERSIONS:
            raise ValueError(f"contract_version {self.contract_version!r} is not one of {list(CONTRACT_VERSIONS)}")
        given = [name for name in CANONICAL_FIELDS if getattr(self, name) is not None]
        if self.contract_version == CONTRACT_VERSION and given:
            raise ValueError(f"contract_version '1' has no {given}: drop them, or set contract_version '2'")
        if self.contract_version == CANONICAL_CONTRACT_VERSION and len(given) != len(CANONICAL_FIELDS):
            lacking = [name for name in CANONICAL_FIELDS if name not in given]
            raise ValueError(f"contract_version '2' needs {lacking} (the canonical camera)")
        return self

    @property
    def uses_canonical_camera(self) -> bool:
        """True for version "2": images are warped to :meth:`canonical_camera`."""
        return self.contract_version == CANONICAL_CONTRACT_VERSION

    def canonical_camera(self) -> CanonicalCamera:
        """The network input's virtual camera (version "2" only)."""
        if self.canonical_fx_px is None or self.canonical_fy_px is None:
            raise DepthModelError(f"model {self.model_id!r} has contract_version {self.contract_version!r}: "
                                  "it has no canonical camera (that is version '2')")
        return CanonicalCamera(fx_px=self.canonical_fx_px, fy_px=self.canonical_fy_px,
                               width_px=self.input_width, height_px=self.input_height)

    def to_metadata(self) -> dict[str, str]:
        """Flat ``{key: str}`` for ONNX ``metadata_props`` (version-2 keys only in version 2)."""
        out: dict[str, str] = {}
        for key, value in self.model_dump(exclude_none=True).items():
            out[key] = value if isinstance(value, str) else json.dumps(value)
        return out

    @classmethod
    def from_metadata(cls, metadata: dict[str, str]) -> "ModelContract":
        """Parse ONNX metadata; raise :class:`DepthModelError` if anything is missing or mismatched."""
        missing = [name for name in cls.model_fields
                   if name not in metadata and name not in OPTIONAL_FIELDS and name not in CANONICAL_FIELDS]
        if missing:
            raise DepthModelError(
                f"model metadata lacks {missing}: not a metricslam depth model, or exported by an old "
                "version — re-export it with `metricslam export CKPT --out model.onnx`"
            )
        version = str(metadata["contract_version"])
        if version not in CONTRACT_VERSIONS:
            raise DepthModelError(
                f"model contract_version is {version!r} but this code reads {list(CONTRACT_VERSIONS)}: "
                "re-export the model with this version of metricslam, or install the matching metricslam"
            )
        present = [name for name in CANONICAL_FIELDS if name in metadata]
        if version == CONTRACT_VERSION and present:
            raise DepthModelError(
                f"model contract_version is '1' but its metadata has the version-2 keys {present}: "
                "a canonical-camera model must say contract_version '2' (re-export it), a version-1 "
                "model must not carry them"
            )
        if version == CANONICAL_CONTRACT_VERSION and len(present) != len(CANONICAL_FIELDS):
            lacking = [name for name in CANONICAL_FIELDS if name not in present]
            raise DepthModelError(
                f"model contract_version is '2' but its metadata lacks {lacking}: without the canonical "
                "camera its output cannot be converted to metres; re-export it with those keys"
            )
        if metadata["output_definition"] != OUTPUT_DEFINITION:
            raise DepthModelError(
                f"model output_definition is {metadata['output_definition']!r}, this code only understands "
                f"{OUTPUT_DEFINITION!r}: use a model exported by `metricslam export`"
            )
        precision = metadata.get("weights_precision", FLOAT32)
        if precision not in WEIGHTS_PRECISIONS:
            raise DepthModelError(
                f"model weights_precision is {precision!r}, this code runs only {list(WEIGHTS_PRECISIONS)}: "
                "use a model exported by `metricslam export` or quantized by `metricslam quantize`"
            )
        values: dict[str, Any] = {}
        for name, field in cls.model_fields.items():
            if name not in metadata:
                continue  # an optional key: the field's default
            raw = metadata[name]
            if field.annotation is str or get_origin(field.annotation) is Literal:
                values[name] = raw
            else:
                try:
                    values[name] = json.loads(raw) if isinstance(raw, str) else raw
                except json.JSONDecodeError as exc:
                    raise DepthModelError(f"model metadata {name}={raw!r} is not valid JSON: {exc}") from exc
        try:
            return cls(**values)
        except ValidationError as exc:
            raise DepthModelError(f"model metadata is invalid: {validation_problems(exc)}") from exc
