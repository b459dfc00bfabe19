"""One-off diagnostics: scripts that answered one question once (their answer is in
``bench/results/`` and the docs), kept so the evidence can be reproduced, not re-run to track a
number. Run from the repository root as ``python -m bench.diagnostics.NAME``.
"""
