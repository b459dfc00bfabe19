"""``metricslam train --config CONFIG.yaml``: train the depth network (resumable).

Preprocesses the configured stereo sequences once (uint8 pairs + SGBM disparity) into the
config's ``cache_dir``, then trains with progress bar, per-term loss log (``run_dir/log.jsonl``)
and periodic checkpoints (``run_dir/last.pt``; rerun the same command to resume).
"""

from __future__ import annotations

import argparse

TRAIN_HINT = "training needs the train extra: pip install 'metricslam[train]'"


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("train", help="train the depth network", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", required=True, help="training YAML, e.g. training/configs/shipped/train_depth.yaml")
    p.add_argument("--export", help="also export the final model to this ONNX path")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (for logs)")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from metricslam.errors import TrainingError

    try:
        import torch  # noqa: F401
    except ImportError as exc:
        raise TrainingError(f"{TRAIN_HINT} (torch is not installed)") from exc
    from metricslam_train.config import TrainConfig
    from metricslam_train.train import train

    cfg = TrainConfig.from_yaml(args.config)
    final = train(cfg, progress=not args.no_progress)
    print(f"final checkpoint: {final}")
    if args.export:
        from metricslam_train.export import export_checkpoint

        contract = export_checkpoint(final, args.export)
        print(f"exported {args.export} ({contract.model_id})")
    return 0
