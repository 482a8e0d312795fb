"""openapi.yaml is the contract: it must be valid OpenAPI 3.1 and agree with the app on
paths, methods, parameters, request bodies (fields) and response status codes."""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from openapi_spec_validator import validate

SPEC_PATH = Path(__file__).resolve().parents[2] / "openapi.yaml"
METHODS = {"get", "post", "put", "patch", "delete"}


@pytest.fixture(scope="module")
def spec() -> dict:
    return yaml.safe_load(SPEC_PATH.read_text())


@pytest.fixture
def app_spec(client) -> dict:
    return client.app.openapi()


def resolve(doc: dict, node: dict) -> dict:
    while isinstance(node, dict) and "$ref" in node:
        target = doc
        for part in node["$ref"].removeprefix("#/").split("/"):
            target = target[part]
        node = target
    return node


def operations(doc: dict) -> dict[tuple[str, str], dict]:
    ops = {}
    for path, item in doc["paths"].items():
        shared = item.get("parameters", [])
        for method, op in item.items():
            if method in METHODS:
                ops[(path, method)] = {**op, "parameters": shared + op.get("parameters", [])}
    return ops


def params(doc: dict, op: dict) -> set[tuple[str, str, bool]]:
    out = set()
    for p in op["parameters"]:
        p = resolve(doc, p)
        name = p["name"].lower() if p["in"] == "header" else p["name"]
        out.add((name, p["in"], bool(p.get("required", False))))
    return out


def body(doc: dict, op: dict) -> tuple[bool, dict[str, set[str]]] | None:
    if "requestBody" not in op:
        return None
    req = resolve(doc, op["requestBody"])
    fields = {}
    for media, content in req["content"].items():
        schema = resolve(doc, content.get("schema", {}))
        if "anyOf" in schema:  # FastAPI spells optional bodies as anyOf [X, null]
            schema = resolve(doc, next(s for s in schema["anyOf"] if s.get("type") != "null"))
        fields[media] = set(schema.get("properties", {}))
    return bool(req.get("required", False)), fields


def test_spec_is_valid_openapi_31(spec) -> None:
    assert spec["openapi"].startswith("3.1")
    validate(spec)


def test_same_operations(spec, app_spec) -> None:
    assert set(operations(spec)) == set(operations(app_spec))


def test_same_parameters_bodies_and_status_codes(spec, app_spec) -> None:
    ours, theirs = operations(spec), operations(app_spec)
    problems = []
    for key in sorted(ours.keys() & theirs.keys()):
        a, b = ours[key], theirs[key]
        if params(spec, a) != params(app_spec, b):
            problems.append(f"{key}: parameters {sorted(params(spec, a))} != app {sorted(params(app_spec, b))}")
        if set(a["responses"]) != set(b["responses"]):
            problems.append(f"{key}: responses {sorted(a['responses'])} != app {sorted(b['responses'])}")
        if body(spec, a) != body(app_spec, b):
            problems.append(f"{key}: body {body(spec, a)} != app {body(app_spec, b)}")
    assert not problems, "\n".join(problems)


def test_error_responses_are_problem_json(spec, app_spec) -> None:
    for doc in (spec, app_spec):
        for key, op in operations(doc).items():
            for code, response in op["responses"].items():
                response = resolve(doc, response)
                if code[0] in "45" and code != "503" or (code == "503" and "Health" not in str(response)):
                    assert "application/problem+json" in response.get("content", {}), (key, code)


def test_enums_match(spec, app_spec) -> None:
    """Formats and planes the app accepts are the ones the contract documents."""
    def enum_of(doc: dict, schema_name: str, field: str) -> set:
        schemas = doc["components"]["schemas"]
        schema = resolve(doc, schemas[schema_name]["properties"][field])
        return set(schema.get("enum") or next(s["enum"] for s in schema.get("anyOf", []) if "enum" in s))

    assert enum_of(spec, "VolumeRequest", "format") == enum_of(app_spec, "VolumeIn", "format")
    assert enum_of(spec, "RegionRequest", "format") == enum_of(app_spec, "RegionIn", "format")
    assert enum_of(spec, "RegionRequest", "dds_compression") == enum_of(app_spec, "RegionIn", "dds_compression")
    bake_form = [resolve(doc, operations(doc)[("/v1/textures/{texture_id}/bakes", "post")]["requestBody"])
                 ["content"]["multipart/form-data"]["schema"] for doc in (spec, app_spec)]
    bake_form[1] = resolve(app_spec, bake_form[1])
    for field in ("format", "dds_compression"):
        spec_field, app_field = (resolve(doc, form["properties"][field])
                                 for doc, form in zip((spec, app_spec), bake_form))
        assert set(spec_field["enum"]) == set(app_field["enum"]), field
    tile_op = operations(app_spec)[("/v1/textures/{texture_id}/tiles/{z}/{x}/{y}.{fmt}", "get")]
    fmt = next(resolve(app_spec, p) for p in tile_op["parameters"] if resolve(app_spec, p)["name"] == "fmt")
    spec_op = operations(spec)[("/v1/textures/{texture_id}/tiles/{z}/{x}/{y}.{fmt}", "get")]
    spec_fmt = next(resolve(spec, p) for p in spec_op["parameters"] if resolve(spec, p)["name"] == "fmt")
    assert set(resolve(app_spec, fmt["schema"])["enum"]) == set(spec_fmt["schema"]["enum"])


BOUNDS = ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum", "default")


def bounds(doc: dict, schema: dict) -> dict:
    """A schema's bounds and numeric default; an optional one's (anyOf [X, null]) from X."""
    schema = resolve(doc, schema)
    if "anyOf" in schema:
        inner = next((resolve(doc, s) for s in schema["anyOf"] if s.get("type") != "null"), {})
        schema = {**inner, **schema}
    return {key: schema[key] for key in BOUNDS if key in schema
            and (key != "default" or type(schema[key]) in (int, float))}  # numbers only: FastAPI drops [] / null


def field_bounds(doc: dict, op: dict) -> dict[tuple[str, str], dict]:
    """(where, name) -> bounds, for an operation's parameters and its body's fields."""
    found = {(p["in"], p["name"]): bounds(doc, p.get("schema", {})) for p in map(lambda p: resolve(doc, p),
                                                                                 op["parameters"])}
    if "requestBody" in op:
        for content in resolve(doc, op["requestBody"])["content"].values():
            schema = resolve(doc, content.get("schema", {}))
            if "anyOf" in schema:
                schema = resolve(doc, next(s for s in schema["anyOf"] if s.get("type") != "null"))
            found |= {("body", name): bounds(doc, prop) for name, prop in schema.get("properties", {}).items()}
    return found


def test_same_bounds_and_defaults(spec, app_spec) -> None:
    """A number's bounds and default are the app's (settings.FIT_SECONDS, worker/contract.py),
    which the contract repeats for its readers: a change there must change it here."""
    ours, theirs = operations(spec), operations(app_spec)
    problems = []
    for key in sorted(ours.keys() & theirs.keys()):
        a, b = field_bounds(spec, ours[key]), field_bounds(app_spec, theirs[key])
        for name in sorted(a.keys() & b.keys()):
            if a[name] != b[name]:
                problems.append(f"{key} {name}: {a[name]} != app {b[name]}")
    assert not problems, "\n".join(problems)


def test_limits_are_the_settings(spec, app_spec, client, settings) -> None:
    """GET /v1/limits answers the settings in force and the bounds no setting raises, with
    the fields openapi.yaml documents."""
    from service.schemas import FitIn
    from worker import contract

    limits = client.get("/v1/limits").json()
    for doc in (spec, app_spec):
        schema = doc["components"]["schemas"]["Limits"]
        assert set(limits) == set(schema["properties"]) == set(schema["required"])
    assert limits["max_volume_resolution"] == settings.max_volume_resolution == 32  # the tests' setting
    assert (limits["max_tile_size"], limits["max_bake_resolution"], limits["max_upload_bytes"]) == (
        settings.max_tile_size, settings.max_bake_resolution, settings.max_upload_bytes)
    assert (limits["min_tile_size"], limits["min_bake_resolution"], limits["planes"]) == (
        contract.MIN_TILE_SIZE, contract.MIN_BAKE_RESOLUTION, list(contract.PLANES))
    assert limits["fit_seconds"] == FitIn().seconds and limits["max_fit_seconds"] == settings.max_fit_seconds
