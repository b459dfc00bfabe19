"""``training/configs/``: every recipe parses, its lineage is closed and documented.

``shipped/`` holds the stages that produced the models in ``shared/metricslam/models/``; a shipped
stage may only start from another shipped stage, and every shipped model's ``model_id`` is the
last stage's. ``README.md`` there has one row per config. No torch needed.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from metricslam.depth import DepthModel
from metricslam_train.config import TrainConfig

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "training" / "configs"
MODELS = REPO / "shared" / "metricslam" / "models"
ALL = sorted(CONFIGS.glob("*/*.yaml"))


def _load() -> dict[Path, TrainConfig]:
    return {p: TrainConfig.from_yaml(p) for p in ALL}


def _run_owner(configs: dict[Path, TrainConfig], init_from: str) -> Path | None:
    """The config whose ``run_dir`` holds ``init_from`` (``runs/X/final.pt`` -> the ``runs/X`` config)."""
    owners = [p for p, c in configs.items() if Path(init_from).parent == Path(c.run_dir)]
    return owners[0] if len(owners) == 1 else None


def test_both_folders_hold_configs() -> None:
    assert {p.parent.name for p in ALL} == {"shipped", "experiments"}


@pytest.mark.parametrize("path", ALL, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_config_parses_and_its_parent_exists(path: Path) -> None:
    configs = _load()
    init = configs[path].init_from
    if init is None:
        return
    if init.startswith("runs/"):
        assert _run_owner(configs, init) is not None, f"{path.name}: no config here writes {init}"
    else:
        assert (REPO / init).is_file(), f"{path.name}: init_from {init} is neither a run here nor a file"


def test_shipped_stages_start_only_from_shipped_stages() -> None:
    configs = _load()
    for path, cfg in configs.items():
        if path.parent.name == "shipped" and cfg.init_from:
            owner = _run_owner(configs, cfg.init_from)
            assert owner is not None and owner.parent.name == "shipped", f"{path.name} <- {cfg.init_from}"


def test_every_shipped_model_is_the_last_stage_of_a_shipped_recipe() -> None:
    """An ensemble's id joins its members' ids with ``+``: each member is a shipped recipe."""
    shipped_ids = {c.model_id for p, c in _load().items() if p.parent.name == "shipped"}
    for onnx in sorted(MODELS.glob("*.onnx")):
        model_id = DepthModel.load(onnx).contract.model_id
        for member in model_id.split("+"):
            assert member in shipped_ids, f"{onnx.name} ({member}) has no recipe in training/configs/shipped/"


def test_readme_has_a_row_per_config() -> None:
    readme = (CONFIGS / "README.md").read_text()
    missing = [f"{p.parent.name}/{p.name}" for p in ALL if f"`{p.parent.name}/{p.name}`" not in readme]
    assert not missing, f"training/configs/README.md has no row for {missing}"
