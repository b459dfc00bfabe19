"""The core library must not pull service or training frameworks (DESIGN.md: library first)."""

from __future__ import annotations

import subprocess
import sys

import pytest

FORBIDDEN = ("zenoh", "fastapi", "starlette", "httpx", "uvicorn", "torch")

SCRIPT = f"""
import importlib, pkgutil, sys
import metricslam
names = []
for info in pkgutil.walk_packages(metricslam.__path__, "metricslam."):
    importlib.import_module(info.name)
    names.append(info.name)
bad = sorted(m for m in sys.modules if m.split(".")[0] in {FORBIDDEN!r})
print(len(names), "modules")
print("FORBIDDEN:", ",".join(bad))
"""


def test_importing_every_core_module_pulls_no_service_or_training_framework():
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, check=True)
    lines = out.stdout.strip().splitlines()
    assert int(lines[0].split()[0]) >= 5, out.stdout
    assert lines[-1] == "FORBIDDEN:", f"core imports {lines[-1]} (move that import into a function or an adapter)"


def test_cli_help_lists_commands():
    out = subprocess.run([sys.executable, "-m", "metricslam_cli.main", "--help"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "eval" in out.stdout


def test_import_contracts_cover_the_whole_core_without_exceptions(repo_root):
    """The CLI is a package of its own (``metricslam_cli``), so the static core contract
    (pyproject ``[tool.importlinter]``, run by ``make lint``) covers all of ``metricslam``, and no
    contract lists an exception."""
    import importlib.util
    import tomllib

    contracts = tomllib.loads((repo_root / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    assert not [c["name"] for c in contracts if c.get("ignore_imports")]
    (core,) = [c for c in contracts if c.get("source_modules") == ["metricslam"]]
    assert {"metricslam_cli", "metricslam_slam", "metricslam_depth", "metricslam_train",
            *FORBIDDEN} <= set(core["forbidden_modules"])
    assert importlib.util.find_spec("metricslam.cli") is None


def test_shared_holds_only_the_core(repo_root):
    """``shared/`` is the core and nothing else; the command line, which imports services and
    training, is the top floor in ``cli/`` (docs/architecture.md), so the folder names tell the layering."""
    packages = sorted(p.name for p in (repo_root / "shared").iterdir() if (p / "__init__.py").is_file())
    assert packages == ["metricslam"]
    assert (repo_root / "cli" / "metricslam_cli" / "main.py").is_file()


#: import names of everything the extras add; a bare `pip install metricslam` has none of them
EXTRAS_ONLY = ("fastapi", "starlette", "uvicorn", "python_multipart", "multipart", "prometheus_client",
               "pydantic_settings", "zenoh", "httpx", "numba", "skimage", "matplotlib", "torch", "onnx",
               "onnxscript", "rerun", "rosbags", "mcap")

RUN_WITHOUT_EXTRAS = f"""
import importlib.abc, sys

class NotInstalled(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {EXTRAS_ONLY!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}} (an extra)", name=name)
        return None

sys.meta_path.insert(0, NotInstalled())
from metricslam_cli.main import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.slow
def test_run_needs_only_the_base_dependencies(synth_sequence, tmp_path):
    """``pip install metricslam`` (no extra) gives a working ``metricslam run`` with learned scale:
    the depth network runs in-process on onnxruntime. Every module an extra provides is made
    unimportable in the child."""
    import json

    seq = synth_sequence(60)
    out, stats = tmp_path / "est.txt", tmp_path / "stats.json"
    proc = subprocess.run([sys.executable, "-c", RUN_WITHOUT_EXTRAS, "run", str(seq), "--out", str(out),
                           "--json", str(stats), "--deterministic", "--no-progress"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert len(out.read_text().splitlines()) == 60
    assert json.loads(stats.read_text())["backend"]["scale_factors"] > 0


def test_a_missing_extra_is_named(tmp_path):
    """A command whose extra is absent says which extra to install (no traceback)."""
    proc = subprocess.run([sys.executable, "-c", RUN_WITHOUT_EXTRAS, "synth", str(tmp_path / "s"), "--frames", "2"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1
    assert "needs the synth extra" in proc.stderr and "pip install 'metricslam[synth]'" in proc.stderr
    assert "Traceback" not in proc.stderr
