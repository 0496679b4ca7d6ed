// The picture of a "turn the plate" prompt: the plate drawn as it must sit, in an isometric view of
// the room (table below, gravity down), computed from the position's direction in the board's frame,
// so that every position (P, N, ±x, ±y, ±z, the sfem-24 ring) gets a correct picture and the
// operator does not have to know what "P" means.
//
// Convention (contracts/positions.py): `direction` is the nominal 1 g reading of the board at rest
// in that position. An accelerometer at rest reads +1 g along the axis that points UP (a board lying
// flat, component side up, reads z = +1 g: position "+z"), so the picture turns the board until
// `direction` points up; gravity pulls along -direction ("this side down").
// Pure: numbers in, SVG markup out (no DOM, no state); its few words from i18n.js (t).
"use strict";

const ORIENT_S = 1 / Math.sqrt(3);

// Index -> name as the fixture and the logs number them (contracts/positions.py), with directions.
const POSITION_TABLE = (() => {
  const t = [["P", [ORIENT_S, ORIENT_S, ORIENT_S]], ["N", [-ORIENT_S, -ORIENT_S, -ORIENT_S]],
    ["+x", [1, 0, 0]], ["-x", [-1, 0, 0]], ["+y", [0, 1, 0]], ["-y", [0, -1, 0]], ["+z", [0, 0, 1]], ["-z", [0, 0, -1]]];
  for (const [axis, label] of [[2, "z"], [1, "y"], [0, "x"]]) {
    const [a, b] = [0, 1, 2].filter((k) => k !== axis);
    for (let k = 0; k < 8; k++) {
      const v = [0, 0, 0], ang = (k * 45 * Math.PI) / 180;
      v[a] = Math.round(Math.cos(ang) * 1e12) / 1e12;
      v[b] = Math.round(Math.sin(ang) * 1e12) / 1e12;
      t.push([`sfem-${label}${k * 45}`, v]);
    }
  }
  return t;
})();

// The prompt's direction, or (an older daemon, a live event without it) the table's by name or index.
function promptDirection(p) {
  const d = p && p.direction;
  if (Array.isArray(d) && d.length === 3 && d.every((v) => Number.isFinite(Number(v)))) {
    const n = Math.hypot(...d.map(Number));
    if (n > 1e-9) return d.map((v) => Number(v) / n);
  }
  let name = p && p.position_name;
  if (!name && p && typeof p.text === "string") {
    const m = /turn the plate to (\S+)/.exec(p.text);
    if (m) name = m[1];
  }
  const byName = POSITION_TABLE.find(([n]) => n === name);
  if (byName) return byName[1];
  const idx = p && Number.isInteger(p.position) ? p.position : -1;
  return idx >= 0 && idx < POSITION_TABLE.length ? POSITION_TABLE[idx][1] : null;
}

function positionNameOf(p) {
  if (p && p.position_name) return p.position_name;
  const idx = p && Number.isInteger(p.position) ? p.position : -1;
  return idx >= 0 && idx < POSITION_TABLE.length ? POSITION_TABLE[idx][0] : "";
}

const v3 = {
  dot: (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2],
  cross: (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]],
  scale: (a, k) => a.map((v) => v * k),
  sub: (a, b) => a.map((v, i) => v - b[i]),
  unit: (a) => { const n = Math.hypot(...a); return a.map((v) => v / n); },
};
const DEG = Math.PI / 180;
const hor = (azDeg) => [Math.cos(azDeg * DEG), Math.sin(azDeg * DEG), 0];

// The camera: from the front right, a little above, so that "up" stays up on the screen.
const CAM_AZ_DEG = 30, CAM_EL_DEG = 22;
const CAM_V = [Math.cos(CAM_EL_DEG * DEG) * Math.cos(CAM_AZ_DEG * DEG), Math.cos(CAM_EL_DEG * DEG) * Math.sin(CAM_AZ_DEG * DEG),
  Math.sin(CAM_EL_DEG * DEG)];  // towards the viewer
const CAM_R = v3.unit(v3.cross([0, 0, 1], CAM_V));  // screen right
const CAM_U = v3.cross(CAM_V, CAM_R);  // screen up

// The pose of the plate (rows: world images of board x, y, z) with d (board frame) pointing up.
// Gravity fixes the pose only up to a turn about the vertical; that turn is chosen for the clearest
// picture: the plate's upward face (the component side, or its back when that side must face down)
// turned towards the viewer, a bit to the side so that its thickness shows; a plate lying flat has
// its x to the right.
function plateAxes(d) {
  const ez = [0, 0, 1];
  let w = v3.sub(ez, v3.scale(d, v3.dot(ez, d)));  // the plate's normal, without its vertical part
  let target;
  if (Math.hypot(...w) < 1e-6) {
    w = v3.sub([1, 0, 0], v3.scale(d, d[0]));
    target = hor(CAM_AZ_DEG + 90 - 25);  // flat: x to the right, seen a little from its side
  } else {
    target = v3.scale(hor(CAM_AZ_DEG - 25), v3.dot(ez, d) < -1e-6 ? -1 : 1);
  }
  const b1 = v3.unit(w), b2 = v3.cross(d, b1);  // board-frame basis (d, b1, b2) -> world (up, target, up x target)
  const up = [0, 0, 1], t2 = v3.cross(up, target);
  // world image of a board vector p: (p.d) up + (p.b1) target + (p.b2) t2
  return [0, 1, 2].map((i) => [0, 1, 2].map((k) => d[i] * up[k] + b1[i] * target[k] + b2[i] * t2[k]));
}

const toWorld = (A, p) => [0, 1, 2].map((k) => p[0] * A[0][k] + p[1] * A[1][k] + p[2] * A[2][k]);

// "x up · y up · z level": each board axis against the vertical, in words (the reading's sign).
function axisWords(d) {
  return ["x", "y", "z"].map((ax, i) => {
    const c = d[i];
    return t(c > 0.2 ? "orient.axis_up" : c < -0.2 ? "orient.axis_down" : "orient.axis_level", { axis: ax });
  }).join(" · ");
}

// SVG markup of the plate in the position whose board-frame up direction is d (unit vector): the
// plate resting on the table, its x/y/z axes, and gravity.
function orientationSvg(d, rawName) {
  const name = String(rawName || "").replace(/[<>&"']/g, (c) => `&#${c.charCodeAt(0)};`);
  const W = 220, H = 190, cx = 98, cy = 92, k = 40;
  const A = plateAxes(d);
  const half = [1.0, 0.7, 0.12];  // the plate: long along x, thin along z
  const at = (p) => toWorld(A, p);
  const corners = [];
  for (const sx of [-1, 1]) for (const sy of [-1, 1]) for (const sz of [-1, 1]) corners.push(at([sx * half[0], sy * half[1], sz * half[2]]));
  const zTable = Math.min(...corners.map((c) => c[2]));  // the plate rests on its lowest corner or edge
  const proj = (p) => [cx + k * v3.dot(p, CAM_R), cy - k * v3.dot(p, CAM_U)];
  const pts = (list) => list.map((p) => proj(p).map((v) => v.toFixed(1)).join(",")).join(" ");
  const faces = [];
  for (let axis = 0; axis < 3; axis++) {
    for (const sign of [1, -1]) {
      const n = [0, 0, 0]; n[axis] = sign;
      const wn = at(n);
      if (v3.dot(wn, CAM_V) <= 1e-6) continue;  // faces away: hidden by the plate itself
      const [a, b] = [0, 1, 2].filter((q) => q !== axis);
      const quad = [[-1, -1], [1, -1], [1, 1], [-1, 1]].map(([u, w]) => {
        const s = [0, 0, 0]; s[axis] = sign * half[axis]; s[a] = u * half[a]; s[b] = w * half[b];
        return at(s);
      });
      const top = axis === 2 && sign === 1;  // the component side (the sensors' +z)
      const light = (0.6 + 0.4 * Math.max(0, wn[2])).toFixed(2);
      faces.push(`<polygon class="face${top ? " top" : ""}" points="${pts(quad)}" fill-opacity="${light}"/>`);
      if (top) {  // the sensor on the component side
        const chip = [[-0.22, -0.22], [0.22, -0.22], [0.22, 0.22], [-0.22, 0.22]].map(([u, w]) => at([u, w, half[2]]));
        faces.push(`<polygon class="chip" points="${pts(chip)}"/>`);
      }
    }
  }
  const colours = { x: "#ff5a5a", y: "#3ddc84", z: "#4aa8ff" };
  const back = [], front = [];
  ["x", "y", "z"].forEach((ax, i) => {
    const e = [0, 0, 0]; e[i] = 1;
    const dir = at(e);
    const from = v3.scale(dir, i === 2 ? half[2] : 0.15), tip = v3.scale(dir, i === 2 ? 1.25 : 1.45);
    const [x0, y0] = proj(from), [x1, y1] = proj(tip);
    const lab = proj(v3.scale(dir, i === 2 ? 1.5 : 1.7));
    const svg = `<g class="axis axis-${ax}" data-axis="${ax}"><line x1="${x0.toFixed(1)}" y1="${y0.toFixed(1)}" x2="${x1.toFixed(1)}" `
      + `y2="${y1.toFixed(1)}" stroke="${colours[ax]}" marker-end="url(#orient-head-${ax})"/>`
      + `<text x="${lab[0].toFixed(1)}" y="${(lab[1] + 6).toFixed(1)}" fill="${colours[ax]}" text-anchor="middle">${ax}</text></g>`;
    (v3.dot(dir, CAM_V) < -0.05 ? back : front).push(svg);
  });
  const R = 1.9;
  const table = pts([[-R, -R, zTable], [R, -R, zTable], [R, R, zTable], [-R, R, zTable]]);
  const heads = Object.entries(colours).map(([ax, c]) => `<marker id="orient-head-${ax}" viewBox="0 0 10 10" refX="8" refY="5" `
    + `markerWidth="4" markerHeight="4" orient="auto-start-reverse"><path d="M0,0 L10,5 L0,10 z" fill="${c}"/></marker>`).join("");
  const dirText = d.map((v) => (Math.abs(v) < 5e-4 ? 0 : v).toFixed(2)).join(", ");
  const esc = (x) => String(x).replace(/[<>&"']/g, (c) => `&#${c.charCodeAt(0)};`);
  const label = esc(t("orient.label", { position: rawName || "?", axes: axisWords(d), reading: dirText }));
  return `<svg class="orientation" viewBox="0 0 ${W} ${H}" role="img" aria-label="${label}" data-position="${name || ""}" `
    + `data-direction="${dirText}"><title>${label}</title><defs>${heads}`
    + `<marker id="orient-head-g" viewBox="0 0 10 10" refX="8" refY="5" markerWidth="4" markerHeight="4" orient="auto">`
    + `<path d="M0,0 L10,5 L0,10 z" fill="#ffc61a"/></marker></defs>`
    + `<polygon class="floor" points="${table}"/>`
    + back.join("") + faces.join("") + front.join("")
    + `<g class="gravity"><line x1="${W - 20}" y1="26" x2="${W - 20}" y2="${H - 30}" marker-end="url(#orient-head-g)"/>`
    + `<text x="${W - 20}" y="16" text-anchor="middle">${esc(t("orient.down"))}</text></g>`
    + `<text class="pos-name" x="8" y="22">${name || ""}</text></svg>`;
}

// The picture and the words for a prompt, or null when its position is unknown.
function promptPicture(p) {
  const d = promptDirection(p);
  if (!d) return null;
  const name = positionNameOf(p);
  return { svg: orientationSvg(d, name), words: axisWords(d), name };
}
