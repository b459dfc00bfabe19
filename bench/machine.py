"""What every benchmark results file shares: the machine it ran on, and how OUT.json / OUT.md are written."""

from __future__ import annotations

import json
import os
import platform
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np


def describe() -> str:
    """CPU model, cores, RAM, OS, Python, numpy and the 1/5/15-min load average now (a load well
    above 0 before a run on this often shared 2-core machine: its wall-clock numbers are pessimistic)."""
    cpu = platform.processor() or platform.machine()
    mem = "RAM unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
        mem_kb = int(Path("/proc/meminfo").read_text().split()[1])
        mem = f"{mem_kb / 2**20:.0f} GiB RAM"
    except (OSError, ValueError, IndexError):
        pass
    try:
        load = "/".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        load = "unknown"
    return (f"{cpu}, {os.cpu_count()} cores, {mem}, {platform.platform()}, Python "
            f"{platform.python_version()}, numpy {np.__version__}; load average {load}")


def command_line(module: str, argv: Sequence[str] | None = None) -> str:
    """The command that reproduces a run, for its results file: ``.venv/bin/python -m MODULE ARGS``.

    ``module`` is the benchmark's dotted name (``"bench.speed"``), ``argv`` its arguments
    (``sys.argv[1:]`` when ``None``). The interpreter is shown relative to the working directory,
    the repository root where benchmarks run (``python -m bench.NAME``).
    """
    args = sys.argv[1:] if argv is None else list(argv)
    return " ".join([os.path.relpath(sys.executable), "-m", module, *([shlex.join(args)] if args else [])])


def write_results(out: str | Path, payload: dict, markdown: str) -> None:
    """Write ``OUT.json`` (``payload``; non-JSON values as strings) and ``OUT.md`` beside it."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(payload, indent=1, default=str) + "\n")
    out.with_suffix(".md").write_text(markdown)


def publish(out: str | Path | None, result: dict, command: str, render) -> str:
    """Render ``result`` with ``render(result, command, machine)``, print it, and write
    ``OUT.json`` (``result`` plus ``command`` and ``machine``) and ``OUT.md`` when ``out`` is given."""
    machine = describe()
    text = render(result, command, machine)
    print(text)
    if out:
        write_results(out, {**result, "command": command, "machine": machine}, text)
    return text
