"""The checker of tests/test_openapi_truth.py: does a live answer carry exactly what the OpenAPI
document says, no field more?

The station's response models allow extra fields at runtime (web/schemas.py), so an undeclared
field reaches the client silently. Here the document is made strict instead: every object schema
that lists properties gets `additionalProperties: false`, then each live answer is validated
(jsonschema, Draft 2020-12 as OpenAPI 3.1 uses) against the response schema of its route, $refs
resolved inside the document. A field the route sends but the model lacks is reported with its
path in the answer. Pure functions: document and answers in, problems out.
"""

from __future__ import annotations

import copy
from typing import Any, Iterator

from jsonschema import Draft202012Validator
from referencing import Registry, Resource
from referencing.jsonschema import DRAFT202012

DOC_URI = "urn:station:openapi"
FREE_FORM = "x-free-form"  # a documented free-form map (web/schemas.py FREE_FORM): its keys are data


def strict(doc: dict) -> dict:
    """A copy of the document in which no object schema with properties admits another key."""
    out = copy.deepcopy(doc)
    for node, _path in walk(out):
        if isinstance(node.get("properties"), dict):
            node["additionalProperties"] = False
    return out


def walk(node: Any, path: str = "") -> Iterator[tuple[dict, str]]:
    """Every schema-like dict in the document with its JSON pointer-ish path."""
    if isinstance(node, dict):
        yield node, path
        for k, v in node.items():
            yield from walk(v, f"{path}/{k}")
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from walk(v, f"{path}/{i}")


def _pointer(*parts: str) -> str:
    return "/".join(p.replace("~", "~0").replace("/", "~1") for p in parts)


class Checker:
    """Validates answers against a strict copy of one OpenAPI document."""

    def __init__(self, doc: dict) -> None:
        self.doc = strict(doc)
        resource = Resource.from_contents(self.doc, default_specification=DRAFT202012)
        self.registry = Registry().with_resource(DOC_URI, resource)

    def schema_ref(self, method: str, template: str, status: int = 200, media: str = "application/json") -> str | None:
        op = self.doc["paths"].get(template, {}).get(method.lower())
        if op is None:
            raise KeyError(f"{method} {template} is not in the document")
        content = (op.get("responses", {}).get(str(status)) or {}).get("content") or {}
        if media not in content or not content[media].get("schema"):
            return None
        return f"{DOC_URI}#/" + _pointer("paths", template, method.lower(), "responses", str(status), "content",
                                         media, "schema")

    def problems(self, method: str, template: str, body: Any, status: int = 200) -> list[str]:
        """What in `body` the document does not declare (or declares otherwise); [] when it agrees."""
        ref = self.schema_ref(method, template, status)
        if ref is None:
            return [f"{method} {template} {status}: no JSON schema documented"]
        return self.validate(ref, body, f"{method} {template}")

    def validate(self, ref: str, body: Any, label: str) -> list[str]:
        """Problems of `body` against the schema at `ref` (a URI into the document), each with where."""
        validator = Draft202012Validator({"$ref": ref}, registry=self.registry)
        out = []
        for err in validator.iter_errors(body):
            for leaf in _leaves(err):
                where = "/".join(str(p) for p in leaf.absolute_path) or "(root)"
                out.append(f"{label}: at {where}: {leaf.message[:300]}")
        return sorted(set(out))

    def webhook_ref(self, name: str, media: str = "application/json") -> str:
        return f"{DOC_URI}#/" + _pointer("webhooks", name, "post", "requestBody", "content", media, "schema")


def _leaves(err: Any) -> list[Any]:
    """The errors that say what is wrong: inside an anyOf (a nullable field, a union of models),
    those of the branch the value nearly matches (not a mere type mismatch, fewest errors), not
    'is not valid under any of the given schemas' with the whole value."""
    if not err.context:
        return [err]
    branches: dict[Any, list[Any]] = {}
    for e in err.context:
        branches.setdefault(e.relative_schema_path[0], []).append(e)
    best = min(branches.values(), key=lambda es: (all(e.validator == "type" for e in es), len(es),
                                                   -max(len(e.absolute_path) for e in es)))
    return [leaf for e in best for leaf in _leaves(e)]


def response_refs(doc: dict) -> set[str]:
    """Names of the component schemas any response or webhook body reaches (transitively)."""
    seeds: list[Any] = []
    for item in list(doc.get("paths", {}).values()) + list((doc.get("webhooks") or {}).values()):
        for op in item.values():
            if not isinstance(op, dict):
                continue
            seeds.append(op.get("responses", {}))
    for item in (doc.get("webhooks") or {}).values():  # a webhook body is what the station sends
        for op in item.values():
            if isinstance(op, dict):
                seeds.append(op.get("requestBody", {}))
    names: set[str] = set()
    todo = seeds
    comps = doc.get("components", {}).get("schemas", {})
    while todo:
        node = todo.pop()
        for sub, _ in walk(node):
            ref = sub.get("$ref")
            if isinstance(ref, str) and ref.startswith("#/components/schemas/"):
                name = ref.rsplit("/", 1)[1]
                if name not in names:
                    names.add(name)
                    todo.append(comps.get(name, {}))
    return names


def _is_bare_object(node: dict) -> bool:
    types = node.get("type")
    is_object = types == "object" or (isinstance(types, list) and "object" in types)
    return is_object and not node.get("properties") and node.get("additionalProperties") in (None, True, {})


def bare_objects(doc: dict) -> list[str]:
    """Object schemas a response reaches that say nothing of their keys (no properties, no typed
    values), outside a documented free-form map (FREE_FORM on the node or one of its parents)."""
    comps = doc.get("components", {}).get("schemas", {})
    found = []
    roots = [(f"components/schemas/{n}", comps[n]) for n in sorted(response_refs(doc)) if n in comps]
    for item_path, item in doc.get("paths", {}).items():
        for method, op in item.items():
            for code, resp in (op.get("responses") or {}).items() if isinstance(op, dict) else ():
                for media, c in (resp.get("content") or {}).items():
                    roots.append((f"paths/{item_path}/{method}/{code}/{media}", c.get("schema") or {}))
    for root_path, root in roots:
        found += _bare_in(root, root_path)
    return sorted(set(found))


def _bare_in(node: Any, path: str) -> list[str]:
    if isinstance(node, list):
        return [p for i, v in enumerate(node) for p in _bare_in(v, f"{path}/{i}")]
    if not isinstance(node, dict) or FREE_FORM in node:
        return []
    out = [path] if _is_bare_object(node) else []
    for k, v in node.items():
        out += _bare_in(v, f"{path}/{k}")
    return out


def undescribed(doc: dict) -> list[str]:
    """Properties of response component schemas without a description (on the property or, for a
    $ref, on the referenced schema)."""
    comps = doc.get("components", {}).get("schemas", {})
    out = []
    for name in sorted(response_refs(doc)):
        for prop, sch in (comps.get(name, {}).get("properties") or {}).items():
            if sch.get("description"):
                continue
            refs = [s.get("$ref") for s in [sch, *sch.get("anyOf", []), *sch.get("allOf", [])] if s.get("$ref")]
            if refs and all(comps.get(r.rsplit("/", 1)[1], {}).get("description") for r in refs):
                continue
            out.append(f"{name}.{prop}")
    return out


def dangling_refs(doc: dict) -> list[str]:
    """$refs that name no component schema (a model documented by hand, web/schemas.py DOCUMENTED_ONLY)."""
    comps = doc.get("components", {}).get("schemas", {})
    refs = {n["$ref"] for n, _ in walk(doc) if isinstance(n.get("$ref"), str)}
    return sorted(r for r in refs if r.startswith("#/components/schemas/") and r.rsplit("/", 1)[1] not in comps)
