"""What the service tells callers about itself — and what it keeps for its own log.

Answers never carry file paths, exception class names or exception text: those help an attacker
map the host and say nothing a caller can act on. The full story goes to the server log, where
an operator reads it; callers get a stable sentence that says what to do.
"""

from __future__ import annotations

import re

from metricslam.depth import ModelContract

#: public reason for a model that failed to load (the log has the exception and the path)
MODEL_LOAD_FAILED = "the depth model failed to load (the server log says why)"

# a path-like token: optional ./ ../ or / prefix, then at least one "name/" segment
_PATH = re.compile(r"(?:\.{1,2}/|/)?(?:[\w.~-]+/)+[\w.~-]*")
# ", <path>" inside a parenthesis, e.g. "kitti01 (51 pairs, ../data/sequences/01)"
_LISTED_PATH = re.compile(r",\s*" + _PATH.pattern + r"(?=\s*[);])")


def without_paths(text: str) -> str:
    """``text`` with file-system paths removed (a path listed after a comma goes with its comma)."""
    return _PATH.sub("<path>", _LISTED_PATH.sub("", text))


def public_contract(contract: ModelContract) -> ModelContract:
    """The contract as served by ``GET /v1/model``: the training-set description without the
    paths of the machine the model was trained on (everything else as in the ONNX file)."""
    return contract.model_copy(update={"training_data": without_paths(contract.training_data)})
