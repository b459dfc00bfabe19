"""``metricslam demo`` (what ``make demo`` runs), end to end on a short rendered loop: the real stack
(router, depth service over HTTP, SLAM service) as child processes on free loopback ports.

The demo's world is rendered, so it runs the depth model for rendered worlds
(``RENDERED_MODEL_PATH``), not the real-streets default, and says which one it runs.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from metricslam.depth import RENDERED_MODEL_PATH, DepthModel

pytestmark = pytest.mark.slow


def test_the_demo_runs_the_stack_on_a_rendered_loop_with_the_rendered_model(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, "-m", "metricslam_cli.main", "demo", "--frames", "80",
                          "--out-dir", str(tmp_path), "--rate", "20"],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    model_id = DepthModel.load(RENDERED_MODEL_PATH).contract.model_id
    assert f"depth model: {model_id}" in out.stdout, out.stdout
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["frames"] == 80
    assert (tmp_path / "trajectory.png").stat().st_size > 0
    # the metric table is printed, both rows, with numbers
    table = [line for line in out.stdout.splitlines() if line.lstrip().startswith(("live poses", "optimized"))]
    assert len(table) == 2 and all("n/a" not in line for line in table), out.stdout
    assert metrics["optimized"]["scale_error_pct"] < 15.0, metrics["optimized"]
