// A self-hosted API reference rendered from /openapi.json (no CDN: Swagger UI would load from one).
"use strict";

function el(tag, cls, ...kids) {
  const e = document.createElement(tag);
  if (cls) e.className = cls;
  for (const k of kids) if (k !== null && k !== undefined) e.append(k instanceof Node ? k : document.createTextNode(String(k)));
  return e;
}

function refName(schema) {
  if (!schema) return "";
  if (schema.$ref) return schema.$ref.split("/").pop();
  if (schema.type === "array") return refName(schema.items) + "[]";
  if (schema.anyOf) return schema.anyOf.map(refName).join(" | ");
  return schema.type || "";
}

function fields(spec, name) {
  const s = (spec.components && spec.components.schemas && spec.components.schemas[name]) || null;
  if (!s || !s.properties) return null;
  const req = new Set(s.required || []);
  const ul = el("ul", "api-fields");
  for (const [k, v] of Object.entries(s.properties)) {
    ul.append(el("li", "", el("code", "", k), ` ${refName(v)}${req.has(k) ? " (required)" : ""}`,
      v.description ? el("span", "muted", " — " + v.description) : null));
  }
  return ul;
}

async function main() {
  const spec = await (await fetch("/openapi.json")).json();
  document.getElementById("api-info").textContent = `${spec.info.title} ${spec.info.version}`;
  const box = document.getElementById("api-paths");
  // REST paths, then the webhooks the station itself POSTs (the MES result payload)
  const entries = [...Object.entries(spec.paths).map(([p, ops]) => [p, ops, false]),
    ...Object.entries(spec.webhooks || {}).map(([name, ops]) => [name, ops, true])];
  for (const [path, ops, hook] of entries) {
    for (const [method, op] of Object.entries(ops)) {
      const card = el("article", "run-card api-op" + (hook ? " api-webhook" : ""));
      const left = el("div", "");
      left.append(el("h3", "", el("span", "api-method api-" + method, method.toUpperCase()), " ",
        hook ? el("span", "muted", "webhook, station → your URL: ") : null, el("code", "", path)));
      if (op.summary) left.append(el("div", "", op.summary));
      if (op.description) left.append(el("p", "muted", op.description));
      const params = (op.parameters || []).map((p) => el("li", "", el("code", "", p.name), ` (${p.in}) ${refName(p.schema)}`,
        p.description ? el("span", "muted", " — " + p.description) : null));
      if (params.length) left.append(el("div", "label", "Parameters"), el("ul", "api-fields", ...params));
      const body = op.requestBody && op.requestBody.content && op.requestBody.content["application/json"];
      if (body) {
        const name = refName(body.schema);
        left.append(el("div", "label", "Body: " + name));
        const f = fields(spec, name);
        if (f) left.append(f);
      }
      const right = el("div", "");
      for (const [code, r] of Object.entries(op.responses || {})) {
        const content = r.content || {};
        const kinds = Object.keys(content);
        const schema = content["application/json"] ? refName(content["application/json"].schema) : kinds.join(", ");
        right.append(el("div", "", el("b", "", code), " ", r.description || "", schema ? el("code", "", " " + schema) : null));
      }
      card.append(left, right);
      box.append(card);
    }
  }
}

document.addEventListener("DOMContentLoaded", () => { main().catch((e) => { document.getElementById("api-info").textContent = "cannot load /openapi.json: " + e; }); });
