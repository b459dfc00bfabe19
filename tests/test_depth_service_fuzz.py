"""Schemathesis against the live OpenAPI of a real depth service (127.0.0.1:18104).

Every operation gets a bounded number of generated requests (valid and invalid fx, random /
truncated / valid PNG and JPEG bodies, random multipart batches); every answer must be a
non-5xx that the schema documents (status, content type, headers, body schema).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from schemathesis import checks
from schemathesis.generation import GenerationMode

from tests.depth_service_process import ServiceProcess

PORT_FUZZ = 18104


def _encoded(extension: str):
    """Strategy: small valid images, their truncations, and arbitrary bytes."""

    @st.composite
    def image(draw) -> bytes:
        width, height = draw(st.integers(2, 96)), draw(st.integers(2, 64))
        seed = draw(st.integers(0, 2**16))
        pixels = np.random.default_rng(seed).integers(0, 256, (height, width), dtype=np.uint8)
        data = cv2.imencode(extension, pixels)[1].tobytes()
        cut = draw(st.sampled_from([len(data), len(data), len(data) // 2, 30, 0]))
        return data[:cut]

    return st.one_of(image(), st.binary(max_size=2048))


schemathesis.openapi.media_type("image/png", _encoded(".png"))
schemathesis.openapi.media_type("image/jpeg", _encoded(".jpg"))


@pytest.fixture(scope="module")
def live_schema():
    with ServiceProcess(PORT_FUZZ, settings={"max_batch": 4, "max_queue": 64}) as service:
        yield schemathesis.openapi.from_url(service.url + "/openapi.json")


CHECKS = [
    checks.not_a_server_error,
    checks.status_code_conformance,
    checks.content_type_conformance,
    checks.response_headers_conformance,
    checks.response_schema_conformance,
]
OPERATIONS = [
    ("POST", "/v1/disparity"),
    ("POST", "/v1/disparity/batch"),
    ("GET", "/v1/model"),
    ("GET", "/healthz"),
    ("GET", "/readyz"),
    ("GET", "/metrics"),
]


def test_every_operation_is_fuzzed(live_schema):
    listed = {(op.ok().method.upper(), op.ok().path) for op in live_schema.get_all_operations()}
    assert listed == set(OPERATIONS)


# negative (schema-violating) data only where there is something to violate: fx and the body
CASES = [(m, p, GenerationMode.POSITIVE) for m, p in OPERATIONS] + [
    (m, p, GenerationMode.NEGATIVE) for m, p in OPERATIONS if m == "POST"
]


@pytest.mark.slow
@pytest.mark.parametrize(("method", "path", "mode"), CASES, ids=lambda v: str(v).replace("/", "_"))
def test_no_5xx_and_responses_match_schema(live_schema, method, path, mode):
    operation = live_schema[path][method]

    # schemathesis' pytest plugin (from_fixture) does not run under this pytest; drive hypothesis
    # directly with the operation's strategy instead (same generation and checks).
    @given(case=operation.as_strategy(generation_mode=mode))
    @settings(max_examples=50, deadline=None, suppress_health_check=list(HealthCheck), database=None)
    def fuzz(case) -> None:
        case.call_and_validate(checks=CHECKS, timeout=30)

    fuzz()
