"""Repeatable benchmarks: each module is run from the repository root as ``python -m bench.NAME``
and writes ``bench/results/NAME*.json`` / ``.md`` with the command that produced them
(``bench.machine.command_line``). ``bench.make_results`` renders the current numbers into the
README and ``docs/results.md``. One-off investigations live in :mod:`bench.diagnostics`.
"""
