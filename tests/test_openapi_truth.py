"""The OpenAPI document tells the whole truth: every GET route of a live station answers with
exactly the fields its response schema in /openapi.json declares, no field more.

The runtime models allow extra fields (web/schemas.py: forward compatible), so an undeclared field
would reach clients silently and a client generated from the document would never see it. This
test is what forbids it. The station is real (tests/openapi_truth_world.py: simulated boards, the
daemon, SQLite, the web app on 127.0.0.1) and holds data behind every route; every GET route the
document lists is called, the running batch's status many times while it runs, and each JSON answer
is validated against a strict copy of the document (tests/openapi_truth_support.py: undeclared
fields forbidden). The webhook bodies the MES capture server received are validated too; the
document may not hold an object schema that says nothing of its keys (outside documented free-form
maps) nor an undescribed field; and the models must neither drop an undeclared field before the
wire nor change a value the producers send. The checker itself is shown to catch a missing field.
"""

from __future__ import annotations

import json

import pytest
from pydantic import BaseModel

from openapi_truth_support import Checker, bare_objects, dangling_refs, undescribed
from openapi_truth_world import NOT_JSON, MesCapture, collect


# --- the tests ------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def world(tmp_path_factory):
    mes = MesCapture()
    a, info, ls = collect(tmp_path_factory.mktemp("openapi_truth"), mes)
    try:
        doc = a.client.get("/openapi.json").json()
        yield {"answers": a.rows, "info": info, "mes": list(mes.bodies), "doc": doc, "app": ls.app, "raw": a.raw,
               "live": ls}
    finally:
        a.client.close()
        ls.__exit__(None, None, None)
        mes.close()


def _media_types(doc: dict, template: str) -> set[str]:
    return set((doc["paths"][template]["get"]["responses"]["200"].get("content") or {}))


def test_every_get_route_answers_only_what_its_schema_declares(world):
    """Every GET route of the document was called with real data, answered 200 with a documented
    media type, and every JSON answer validates against its strict response schema."""
    doc, rows = world["doc"], world["answers"]
    get_routes = {p for p, item in doc["paths"].items() if "get" in item}
    called = {t for t, _u, status, _c, _b in rows if status == 200}
    assert get_routes - called == set(), f"GET routes not exercised with a 200 answer: {sorted(get_routes - called)}"
    assert [(u, s) for _t, u, s, _c, _b in rows if s != 200] == []
    checker = Checker(doc)
    problems: dict[str, int] = {}
    n_json = 0
    for template, _url, _status, ctype, body in rows:
        documented = _media_types(doc, template)
        assert ctype in documented, f"{template} answered {ctype}, documents {documented}"
        if ctype != "application/json":
            assert ctype in NOT_JSON, (template, ctype)
            continue
        n_json += 1
        for p in checker.problems("GET", template, body):
            problems[p] = problems.get(p, 0) + 1
    print(f"\n{n_json} JSON answers of {len(get_routes)} GET routes validated "
          f"(batch ran {world['info']['batch_s']:.1f} s)")
    assert not problems, "answers the document does not declare:\n" + "\n".join(
        f"{n} x {p}" for p, n in sorted(problems.items())[:60])


def test_the_webhook_bodies_match_the_documented_payload(world):
    bodies = world["mes"]
    assert len(bodies) >= 2
    checker = Checker(world["doc"])
    problems = sorted({p for b in bodies for p in checker.validate(checker.webhook_ref("mes-result"), b, "mes-result")})
    assert problems == []


def _passes_through(sent, answered, where: str = "") -> list[str]:
    """Where `answered` (a model's output) differs from what the producer `sent`: a value changed,
    a key dropped or renamed. Keys the model adds (declared defaults) are fine."""
    if isinstance(sent, dict):
        if not isinstance(answered, dict):
            return [f"{where}: object became {answered!r:.60}"]
        return [p for k, v in sent.items() for p in (
            _passes_through(v, answered[k], f"{where}/{k}") if k in answered else [f"{where}/{k}: dropped"])]
    if isinstance(sent, list):
        if not isinstance(answered, list) or len(answered) != len(sent):
            return [f"{where}: list changed"]
        return [p for i, (x, y) in enumerate(zip(sent, answered)) for p in _passes_through(x, y, f"{where}/{i}")]
    same = (sent == answered and type(sent) is type(answered)) or (
        isinstance(sent, (int, float)) and not isinstance(sent, bool) and isinstance(answered, float) and sent == answered)
    return [] if same else [f"{where}: {sent!r:.60} became {answered!r:.60}"]


def test_the_models_pass_every_value_the_producers_send_unchanged(world):
    """The runtime side of the same truth: validating through the response models (the routes do)
    changes no value, drops or renames no key of what the daemon and the diagnosis produce (a union
    resolved to the wrong model, an alias, a coercion would)."""
    from web.diag_plots import report_json
    from web.schemas import BatchStatus, DiagnosisOut
    from web.views import clean

    ls = world["live"]
    problems = []
    assert len(world["raw"]) > 20
    for raw in world["raw"]:
        sent = json.loads(json.dumps(clean(raw)))
        problems += _passes_through(sent, BatchStatus.model_validate(raw).model_dump(mode="json"), "status")
    run_id = world["info"]["diagnosed"]
    rep = ls.app.state.diagnosis_cache.get(run_id, ("thermal_lag", "bias_t2"), lambda: None)
    assert rep is not None  # computed by the sweep's request
    sent = json.loads(json.dumps(clean(report_json(rep))))
    problems += _passes_through(sent, DiagnosisOut.model_validate(sent).model_dump(mode="json"), "diagnosis")
    assert sorted(set(problems))[:40] == []


def test_no_response_schema_is_an_object_that_says_nothing_of_its_keys(world):
    assert dangling_refs(world["doc"]) == []
    assert bare_objects(world["doc"]) == []


def test_every_field_of_a_response_schema_is_described(world):
    assert undescribed(world["doc"]) == []


def test_every_response_model_lets_undeclared_fields_reach_the_wire(world):
    """A model that dropped undeclared fields (pydantic's default, extra="ignore") would hide them
    from the live check above; every model a route answers with must pass them through."""
    from fastapi.routing import APIRoute

    seen, dropping = set(), []

    def visit(tp) -> None:
        for sub in getattr(tp, "__args__", ()) or ():
            visit(sub)
        if isinstance(tp, type) and issubclass(tp, BaseModel) and tp not in seen:
            seen.add(tp)
            if tp.model_config.get("extra") != "allow":
                dropping.append(tp.__name__)
            for f in tp.model_fields.values():
                visit(f.annotation)

    def routes(items):  # FastAPI keeps an included router's routes behind a wrapper
        for r in items:
            if isinstance(r, APIRoute):
                yield r
            elif hasattr(r, "original_router"):
                yield from routes(r.original_router.routes)

    for route in routes(world["app"].routes):
        if route.response_model is not None:
            visit(route.response_model)
    from web.schemas import MesResultPayload

    visit(MesResultPayload)  # the webhook's body
    assert len(seen) > 30 and dropping == [], (len(seen), dropping)


# --- the checker itself -------------------------------------------------------------------------

def test_the_checker_reports_a_field_a_model_lacks():
    """One deliberately incomplete model (the route sends `extra_mg`, nested in a list too): the
    checker names the field and where it is, and is silent once the model declares it."""
    from fastapi import FastAPI
    from fastapi.testclient import TestClient

    from web.schemas import _Out

    class Inner(_Out):
        a: int

    class Thin(_Out):
        id: int
        items: list[Inner]

    class Full(Thin):
        extra_mg: float

    answer = {"id": 1, "extra_mg": 2.5, "items": [{"a": 1}, {"a": 2, "b": "x"}]}
    app = FastAPI()
    app.get("/thin", response_model=Thin)(lambda: answer)
    app.get("/full", response_model=Full)(lambda: {**answer, "items": [{"a": 1}]})
    with TestClient(app) as c:
        doc = c.get("/openapi.json").json()
        thin, full = c.get("/thin").json(), c.get("/full").json()
    assert thin == answer  # extra="allow": the undeclared fields reach the client
    problems = Checker(doc).problems("GET", "/thin", thin)
    assert any("at (root)" in p and "'extra_mg' was unexpected" in p for p in problems), problems
    assert any("at items/1" in p and "'b' was unexpected" in p for p in problems), problems
    assert Checker(doc).problems("GET", "/full", full) == []
    assert bare_objects(doc) == []


def test_the_checker_reports_a_field_removed_from_the_live_document(world):
    """The same on the station's own document and answers: without `label_serial` in SlotStatus,
    every batch status answer is reported."""
    import copy

    doc = copy.deepcopy(world["doc"])
    del doc["components"]["schemas"]["SlotStatus"]["properties"]["label_serial"]
    body = next(b for t, _u, _s, _c, b in world["answers"] if t == "/api/batches/{batch_id}")
    problems = Checker(doc).problems("GET", "/api/batches/{batch_id}", body)
    assert problems and all("'label_serial' was unexpected" in p for p in problems), problems


def test_bare_objects_finds_an_undocumented_map_and_spares_a_documented_one():
    from pydantic import Field

    from web.schemas import _Out
    from web.schemas_common import free_form

    class M(_Out):
        loose: dict = Field(description="x")
        typed: dict[str, int] = Field(description="x")
        documented: dict | None = free_form("x", default=None)

    doc = {"paths": {"/m": {"get": {"responses": {"200": {"content": {"application/json": {
        "schema": {"$ref": "#/components/schemas/M"}}}}}}}},
        "components": {"schemas": {"M": M.model_json_schema()}}}
    assert bare_objects(doc) == ["components/schemas/M/properties/loose"]
