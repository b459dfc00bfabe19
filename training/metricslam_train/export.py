"""Export a training checkpoint to ONNX with the :class:`ModelContract` in its metadata.

The graph takes the normalized gray image ``image`` (B, 1, H, W) float32 (dynamic batch) and
returns ``d_frac_l3`` (B, H/8, W/8) float32: the left L3 disparity as a fraction of image width.

Example::

    python -m metricslam_train.export runs/depth/last.pt --out model.onnx
"""

from __future__ import annotations

import datetime as _dt
import subprocess
from pathlib import Path

import onnx
import torch

from metricslam.depth.contract import CANONICAL_CONTRACT_VERSION, ModelContract, Normalization
from metricslam.errors import TrainingError
from metricslam_train.network import EnsembleExportWrapper, ExportWrapper, PyramidDepthNet, count_parameters

OPSET = 17


def git_commit(repo_dir: Path | None = None) -> str:
    """Current git commit id (with ``+dirty`` when the work tree has changes), or ``"unknown"``."""
    cwd = str(repo_dir or Path(__file__).resolve().parent)
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True, text=True,
                                check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return commit


def load_checkpoint(path: str | Path) -> dict:
    """Read a checkpoint written by :mod:`metricslam_train.train`."""
    ckpt_path = Path(path)
    if not ckpt_path.is_file():
        raise TrainingError(f"checkpoint {ckpt_path} does not exist: pass a .pt file written by `metricslam train`")
    ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=False)
    for key in ("model", "meta"):
        if key not in ckpt:
            raise TrainingError(f"{ckpt_path} lacks {key!r}: not a metricslam training checkpoint")
    return ckpt


def network_from_checkpoint(ckpt: dict, weights: str = "auto") -> PyramidDepthNet:
    """Rebuild the network and load its weights (eval mode).

    ``weights``: ``"ema"`` the moving average of the weights (``TrainConfig.ema_decay``),
    ``"raw"`` the optimizer's last weights, ``"auto"`` the average when the checkpoint has one.
    """
    if weights not in ("auto", "ema", "raw"):
        raise TrainingError(f"weights must be auto, ema or raw, not {weights!r}")
    if weights == "ema" and "ema" not in ckpt:
        raise TrainingError("this checkpoint has no weight average: train with ema_decay set, or export raw weights")
    use_ema = weights == "ema" or (weights == "auto" and "ema" in ckpt)
    net = PyramidDepthNet(max_d_frac=float(ckpt["meta"]["max_d_frac"]), width=float(ckpt["meta"].get("width", 1.0)))
    net.load_state_dict(ckpt["ema"] if use_ema else ckpt["model"])
    return net.eval()


def weights_from_onnx(path: str | Path, member: int | None = None) -> tuple[dict[str, torch.Tensor], ModelContract]:
    """The network weights and contract of a float32 ONNX file written by :func:`export_onnx`
    (e.g. the shipped ``depth_l3.onnx``), to fine-tune from it (``init_from: MODEL.onnx``).

    The exporter keeps every parameter as an initializer named ``net.<state_dict key>``, or, in a
    seed ensemble (:func:`export_ensemble`, the shipped default since v4), ``nets.<i>.<key>`` per
    member: an ensemble needs ``member`` (0 … N-1), and the contract returned is that member's
    (its own ``model_id``; ``params`` of one network). An int8 copy (``metricslam quantize``)
    keeps no float32 weights and is refused.

    Raises:
        TrainingError: no such file, an int8 copy, an ensemble without a valid ``member``, or a
            ``member`` for a single network.
    """
    from onnx import numpy_helper

    src = Path(path)
    if not src.is_file():
        raise TrainingError(f"{src} does not exist: pass a float32 model written by `metricslam export`")
    model = onnx.load(str(src))
    contract = ModelContract.from_metadata({p.key: p.value for p in model.metadata_props})
    inits = {i.name: i for i in model.graph.initializer}
    keys = PyramidDepthNet().state_dict().keys()
    n_members = len({name.split(".")[1] for name in inits if name.startswith("nets.")})
    if n_members:
        ids = contract.model_id.split("+")
        if member is None or not 0 <= member < n_members:
            raise TrainingError(f"{src} is a seed ensemble of {n_members} networks ({contract.model_id}): "
                                f"fine-tune one of them, init_member: 0 … {n_members - 1} in the config "
                                f"(got {member})")
        prefix = f"nets.{member}."
        contract = contract.model_copy(update={
            "model_id": ids[member] if len(ids) == n_members else f"{contract.model_id}[{member}]",
            "params": contract.params // n_members})
    elif member is not None:
        raise TrainingError(f"{src} is one network, not an ensemble: remove init_member (got {member})")
    else:
        prefix = "net."
    # (the exporter keeps one initializer for tensors of equal value, under one of their names:
    # trained networks do not share any, so a missing name is refused rather than guessed)
    missing = [k for k in keys if f"{prefix}{k}" not in inits]
    if missing:
        raise TrainingError(f"{src} lacks the float32 weights {missing[:3]}…: fine-tune from the float32 model "
                            "(e.g. depth_l3.onnx), not its int8 copy")
    state = {k: torch.from_numpy(numpy_helper.to_array(inits[f"{prefix}{k}"]).copy()) for k in keys}
    return state, contract


def contract_for(net: PyramidDepthNet, meta: dict, model_id: str | None = None) -> ModelContract:
    """Build the contract from a checkpoint's ``meta`` dict."""
    h, w = int(meta["input_height"]), int(meta["input_width"])
    return ModelContract(
        model_id=model_id or str(meta.get("model_id", "pyramid-l3")),
        input_height=h,
        input_width=w,
        normalization=Normalization(**meta["normalization"]),
        output_height=h // 8,
        output_width=w // 8,
        baseline_m=float(meta["baseline_m"]),
        params=count_parameters(net),
        training_data=str(meta["training_data"]),
        training_commit=str(meta.get("training_commit", "unknown")),
        created=_dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat(),
        **({"contract_version": CANONICAL_CONTRACT_VERSION, "canonical_fx_px": float(meta["canonical_fx_px"]),
            "canonical_fy_px": float(meta["canonical_fy_px"]), "valid_min_fraction": float(meta["valid_min_fraction"])}
           if meta.get("canonical_fx_px") is not None else {}),
    )


def export_onnx(net: PyramidDepthNet | list[PyramidDepthNet], contract: ModelContract, out_path: str | Path) -> Path:
    """Write ``net`` (or, given a list, the mean of the networks' outputs: an ensemble) to
    ``out_path`` as ONNX with ``contract`` in ``metadata_props``."""
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(net, list):
        wrapper = EnsembleExportWrapper([n.eval() for n in net])
    else:
        wrapper = ExportWrapper(net.eval())
    dummy = torch.zeros(1, contract.input_channels, contract.input_height, contract.input_width)
    with torch.no_grad():
        torch.onnx.export(
            wrapper, (dummy,), str(out), input_names=[contract.input_name], output_names=[contract.output_name],
            dynamic_axes={contract.input_name: {0: "batch"}, contract.output_name: {0: "batch"}},
            opset_version=OPSET, dynamo=False,
        )
    model = onnx.load(str(out))
    del model.metadata_props[:]
    for key, value in contract.to_metadata().items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(model)
    onnx.save(model, str(out))
    return out


def export_checkpoint(ckpt_path: str | Path, out_path: str | Path, model_id: str | None = None,
                      weights: str = "auto") -> ModelContract:
    """Checkpoint -> ONNX; returns the contract written (``weights``: see
    :func:`network_from_checkpoint`)."""
    ckpt = load_checkpoint(ckpt_path)
    net = network_from_checkpoint(ckpt, weights)
    contract = contract_for(net, ckpt["meta"], model_id)
    export_onnx(net, contract, out_path)
    return contract


def export_ensemble(ckpt_paths: list[str | Path], out_path: str | Path, model_id: str | None = None,
                    weights: str = "auto") -> ModelContract:
    """Several checkpoints of one recipe (e.g. seeds) -> one ONNX graph whose output is the mean of
    their L3 d_frac (:class:`EnsembleExportWrapper`); returns the contract written.

    The members must agree on everything the contract states (input size, normalization,
    baseline, output range, camera contract); their training data is recorded once when equal, and
    the model id is the members' ids joined by ``+`` (each one a recipe in ``training/configs/``).
    A single checkpoint is exported as itself.
    """
    if len(ckpt_paths) == 1:
        return export_checkpoint(ckpt_paths[0], out_path, model_id, weights)
    ckpts = [load_checkpoint(p) for p in ckpt_paths]
    nets = [network_from_checkpoint(c, weights) for c in ckpts]
    keys = ("input_height", "input_width", "normalization", "baseline_m", "max_d_frac", "canonical_fx_px",
            "canonical_fy_px")
    first = ckpts[0]["meta"]
    for path, ckpt in zip(ckpt_paths[1:], ckpts[1:]):
        differs = [k for k in keys if ckpt["meta"].get(k) != first.get(k)]
        if differs:
            raise TrainingError(f"{path} differs from {ckpt_paths[0]} in {differs}: ensemble members must share "
                                "one contract")
    data = sorted({str(c["meta"]["training_data"]) for c in ckpts})
    ids = [str(c["meta"].get("model_id", "?")) for c in ckpts]
    meta = dict(first, training_data=data[0] if len(data) == 1 else " | ".join(data),
                training_commit=",".join(sorted({str(c["meta"].get("training_commit", "unknown")) for c in ckpts})))
    contract = contract_for(nets[0], meta, model_id or "+".join(ids))
    contract = contract.model_copy(update={"params": sum(count_parameters(n) for n in nets)})
    export_onnx(nets, contract, out_path)
    return contract
