"""The depth model's contract: what the ONNX file promises, stored in its metadata.

The network outputs the **left disparity as a fraction of image width** (``d_frac``) at level
L3, for a virtual stereo rig of baseline ``baseline_m`` (the training rig's). For a caller's
camera with focal length ``fx_px`` at image width ``width_px``::

    inv_depth_per_m = d_frac · width_px / (fx_px · baseline_m)

(see ``docs/conventions.md``). The input is the whole image resized (no crop) to
``input_height × input_width``, gray, normalized as ``(pixel · scale − mean) / std``.

Every field is written into the ONNX ``metadata_props`` as one key (strings as they are, other
values JSON-encoded); :meth:`ModelContract.from_metadata` refuses a model whose metadata is
incomplete or whose ``contract_version`` / ``output_definition`` differ from this code's.

Optional keys (:data:`OPTIONAL_FIELDS`) may be absent and then take their default, so models
exported before the key existed still load: ``weights_precision`` ("float32", or "int8-static"
for a model written by :func:`metricslam.depth.quantize.quantize_model`; any other value is
refused).
"""

from __future__ import annotations

import json
from typing import Any, Literal, get_args, get_origin

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from metricslam.errors import DepthModelError

#: bump when the meaning of a field or of the output changes; models with another version are refused.
CONTRACT_VERSION = "1"
#: the only output definition this code understands.
OUTPUT_DEFINITION = "disparity_fraction_of_width"
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

    def to_metadata(self) -> dict[str, str]:
        """Flat ``{key: str}`` for ONNX ``metadata_props``."""
        out: dict[str, str] = {}
        for key, value in self.model_dump().items():
            out[key] = value if isinstance(value, str) else json.dumps(value)
        return out

    @classmethod
    def from_metadata(cls, metadata: dict[str, str]) -> "ModelContract":
        """Parse ONNX metadata; raise :class:`DepthModelError` if anything is missing or mismatched."""
        missing = [name for name in cls.model_fields if name not in metadata and name not in OPTIONAL_FIELDS]
        if missing:
            raise DepthModelError(
                f"model metadata lacks {missing}: not a metricslam depth model, or exported by an old "
                "version — re-export it with `metricslam export CKPT --out model.onnx`"
            )
        version = str(metadata["contract_version"])
        if version != CONTRACT_VERSION:
            raise DepthModelError(
                f"model contract_version is {version!r} but this code reads {CONTRACT_VERSION!r}: "
                "re-export the model with this version of metricslam, or install the matching metricslam"
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
            raise DepthModelError(f"model metadata is invalid: {exc}") from exc
