"""The core library must not pull service or training frameworks (DESIGN.md: library first)."""

from __future__ import annotations

import subprocess
import sys

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
    out = subprocess.run([sys.executable, "-m", "metricslam.cli.main", "--help"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "eval" in out.stdout


def test_import_contract_lists_every_core_module(repo_root):
    """The static import contract (pyproject ``[tool.importlinter]``, run by ``make lint``) names
    the core's modules one by one; a new core module must be added there."""
    import pkgutil
    import tomllib

    import metricslam

    contracts = tomllib.loads((repo_root / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    (listed,) = [c["source_modules"] for c in contracts if c["forbidden_modules"] == ["metricslam.cli"]]
    core = {f"metricslam.{m.name}" for m in pkgutil.iter_modules(metricslam.__path__) if m.name != "cli"}
    assert set(listed) == core
