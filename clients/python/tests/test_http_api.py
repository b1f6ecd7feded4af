"""The HTTP API against its OpenAPI document, which the server generates from its code (utoipa).

The document must be valid OpenAPI (openapi-spec-validator, PyPI). Then every documented operation is called in an
order that makes them meaningful (create a map, fill it, read it, localise against it, export, import, delete):
with the documented example as the body and the documented path examples, each request must itself validate
against the document, and each answer against the documented response (status, content type, schema), using
openapi-core (PyPI). An unknown map's 404 must match the documented error envelope too.
"""

from __future__ import annotations

import json
import urllib.error
import urllib.request

import pytest
from openapi_core import OpenAPI
from openapi_core.testing import MockRequest, MockResponse
from openapi_spec_validator import validate

# Every operation of the document, in the order the example test calls them; the document must hold exactly these.
OPERATIONS = [
    ("GET", "/healthz"),
    ("GET", "/readyz"),
    ("GET", "/metrics"),
    ("GET", "/openapi.json"),
    ("GET", "/ui"),
    ("GET", "/ui/{file}"),
    ("POST", "/v1/maps"),
    ("POST", "/v1/maps/{map_id}/keyframes"),
    ("GET", "/v1/maps"),
    ("GET", "/v1/maps/{map_id}"),
    ("GET", "/v1/maps/{map_id}/contents"),
    ("POST", "/v1/describe"),
    ("POST", "/v1/match"),
    ("POST", "/v1/maps/{map_id}/localize"),
    ("POST", "/v1/maps/{map_id}/localize-track"),
    ("GET", "/v1/maps/{map_id}/export"),
    ("POST", "/v1/maps/{map_id}/import"),
    ("POST", "/v1/maps/{map_id}/merge"),
    ("DELETE", "/v1/maps/{map_id}/keyframes/{keyframe_id}"),
    ("DELETE", "/v1/maps/{map_id}"),
]


def call(url: str, method: str, body: bytes | None = None, content_type: str | None = None):
    req = urllib.request.Request(url, data=body, method=method)
    if content_type:
        req.add_header("Content-Type", content_type)
    try:
        with urllib.request.urlopen(req, timeout=60) as r:
            return r.status, r.headers.get("Content-Type", ""), r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.headers.get("Content-Type", ""), e.read()


@pytest.fixture(scope="module")
def document(server):
    _, http_url = server
    status, content_type, body = call(f"{http_url}/openapi.json", "GET")
    assert status == 200 and content_type.startswith("application/json")
    return json.loads(body)


def test_the_generated_document_is_valid_openapi_and_lists_exactly_the_operations(document):
    validate(document)
    documented = sorted(
        (method.upper(), path)
        for path, item in document["paths"].items()
        for method in item
        if method in {"get", "post", "put", "delete", "patch"}
    )
    assert documented == sorted(OPERATIONS)


def path_examples(operation: dict) -> dict:
    return {p["name"]: p["example"] for p in operation.get("parameters", []) if p["in"] == "path" and "example" in p}


def test_each_documented_example_request_gets_an_answer_the_document_describes(server, document):
    _, http_url = server
    spec = OpenAPI.from_dict(document)
    exported = None
    for method, pattern in OPERATIONS:
        operation = document["paths"][pattern][method.lower()]
        values = path_examples(operation)
        path = pattern.format(**values)
        body, content_type = None, None
        content = operation.get("requestBody", {}).get("content", {})
        if "application/json" in content:
            example = content["application/json"].get("example")
            assert example is not None, f"{method} {pattern} documents no JSON example"
            body, content_type = json.dumps(example).encode(), "application/json"
        elif "application/octet-stream" in content:
            assert pattern.endswith("/import") and exported is not None
            body, content_type = exported, "application/octet-stream"
        request = MockRequest(
            http_url,
            method,
            path,
            path_pattern=pattern,
            view_args=values,
            # A binary body is documented as a string of format binary: its bytes as one.
            data=body if content_type != "application/octet-stream" else body.decode("latin-1"),
            content_type=content_type or "application/json",
        )
        if body is not None:
            spec.validate_request(request)
        status, got_type, data = call(http_url + path, method, body, content_type)
        assert status < 300, f"{method} {path}: {status} {data[:300]!r}"
        if pattern.endswith("/export"):
            exported = data
            assert exported.startswith(b"SCONEMAP")
        mime = got_type.split(";")[0]
        if mime.startswith("text/") or mime == "application/openmetrics-text":
            data = data.decode()
        elif mime != "application/json":
            # A binary body (a map file, a picture) is documented as a string of format binary: its bytes as one.
            data = data.decode("latin-1")
        response = MockResponse(data, status_code=status, content_type=mime)
        spec.validate_response(request, response)
    # The example map is gone (deleted last), the copy its import made is there.
    status, _, data = call(f"{http_url}/v1/maps", "GET")
    left = [m["map_id"] for m in json.loads(data)["maps"]]
    assert "office-copy" in left and "office" not in left, left


def test_an_error_answer_is_the_documented_envelope(server, document):
    _, http_url = server
    spec = OpenAPI.from_dict(document)
    status, content_type, data = call(f"{http_url}/v1/maps/no-such-map", "GET")
    assert status == 404
    request = MockRequest(http_url, "GET", "/v1/maps/no-such-map", path_pattern="/v1/maps/{map_id}",
                          view_args={"map_id": "no-such-map"})
    spec.validate_response(request, MockResponse(data, status_code=status, content_type=content_type))
    assert json.loads(data)["error"]["code"] == "NOT_FOUND"
