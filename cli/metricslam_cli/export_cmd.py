"""``metricslam export CKPT [CKPT ...] --out model.onnx``: a training checkpoint to ONNX with its contract.

Several checkpoints (seeds of one recipe) make one ensemble graph whose output is the mean of the
members' L3 disparity: the same contract, one file, one forward pass per member.
"""

from __future__ import annotations

import argparse

TRAIN_HINT = "training needs the train extra: pip install 'metricslam[train]'"


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("export", help="export a depth training checkpoint to ONNX", description=__doc__)
    p.add_argument("checkpoint", nargs="+",
                   help="a .pt file written by `metricslam train` (e.g. runs/depth/final.pt); several: an "
                        "ensemble (mean of their outputs) in one ONNX graph")
    p.add_argument("--out", required=True, help="output .onnx path")
    p.add_argument("--model-id", help="override the model id written into the metadata")
    p.add_argument("--weights", choices=("auto", "ema", "raw"), default="auto",
                   help="ema: the moving average of the weights (configs with ema_decay); raw: the last "
                        "optimizer weights; auto (default): the average when the checkpoint has one")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from metricslam.errors import TrainingError

    try:
        from metricslam_train.export import export_ensemble
    except ImportError as exc:
        raise TrainingError(f"{TRAIN_HINT} ({exc})") from exc
    contract = export_ensemble(args.checkpoint, args.out, args.model_id, args.weights)
    print(f"{args.out}: {contract.model_id}, {contract.params} params, input {contract.input_height}x"
          f"{contract.input_width}, output {contract.output_height}x{contract.output_width} d_frac, "
          f"baseline {contract.baseline_m} m, trained on {contract.training_data}")
    return 0
