// HiveMap viewer: everything comes from the WebSocket /ws/viewer (services/api/routes/live.py).
// Plain Canvas 2D, no library: the page must work offline and be served by the API as is.
"use strict";

const PALETTE = ["#4cc9f0", "#f72585", "#b5e48c", "#ff9f1c", "#9d4edd", "#ffd60a", "#00f5d4",
  "#ef476f", "#90be6d", "#f3722c", "#4361ee", "#e9c46a", "#06d6a0", "#ff70a6", "#80ed99",
  "#c77dff", "#f9844a", "#48cae4", "#d00000", "#a7c957"];
const STATUS_COLOUR = { tracking: null, initializing: "#3a86ff", lost: "#ff9f1c", disconnected: "#6c757d" };
const DISCONNECTED_MS = 3000;

const S = {
  maps: [], agents: {}, order: [], trajs: {}, loops: {}, points: {}, merges: [], events: [],
  sel: null, pinned: false, connected: false, lastMsg: 0, basis: {},
};
// What the browser test reads: frames drawn (and how many of them redrew the top view's
// still layer), the measured rate, what is on screen.
const stats = window.hivemapViewer = { frames: 0, layers: 0, fps: 0, messages: 0, drawn: { agents: 0, points: 0, poses: {} } };

// An agent named after a colour ("red", "Blue") is drawn in it, lightened so that it
// shows on the dark background; any other name takes the next palette colour. Resolved
// once per agent and kept, so a colour never changes while the page is open.
const COLOURS = stats.colours = {};  // agent -> CSS colour (the browser test reads it)
const probe = document.createElement("canvas").getContext("2d");
function namedColour(a) {
  const name = String(a).toLowerCase();
  if (!/^[a-z]+$/.test(name) || !CSS.supports("color", name)) return null;
  probe.fillStyle = "#000"; probe.fillStyle = name;
  const hex = probe.fillStyle;  // normalized to #rrggbb
  if (!/^#[0-9a-f]{6}$/.test(hex)) return null;
  const mix = (i) => Math.round(0.7 * parseInt(hex.slice(i, i + 2), 16) + 0.3 * 255);
  return `rgb(${mix(1)}, ${mix(3)}, ${mix(5)})`;
}
function colour(a) {
  if (!(a in COLOURS)) {
    let c = namedColour(a);
    if (c === null) { S.order.push(a); c = PALETTE[(S.order.length - 1) % PALETTE.length]; }
    COLOURS[a] = c;
  }
  return COLOURS[a];
}

// --- connection ------------------------------------------------------------------------------
let backoff = 500;
function connect() {
  const base = location.pathname.replace(/[^/]*$/, "");
  // The API token comes in the page's URL (?token=, as `hivemap up` prints it); a
  // WebSocket takes no header, so it goes on as a query parameter.
  const token = new URLSearchParams(location.search).get("token");
  const auth = token ? "?token=" + encodeURIComponent(token) : "";
  const ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + base + "ws/viewer" + auth);
  ws.onopen = () => { S.connected = true; backoff = 500; setConn("live", "live"); };
  ws.onmessage = (e) => { S.lastMsg = performance.now(); stats.messages++; onMessage(JSON.parse(e.data)); };
  ws.onclose = () => {
    S.connected = false; setConn("down", "reconnecting…");
    setTimeout(connect, backoff); backoff = Math.min(backoff * 2, 8000);
  };
}
function setConn(cls, text) { const c = document.getElementById("conn"); c.className = "badge " + cls; c.textContent = text; }

function onMessage(m) {
  if (m.type === "state") onState(m);
  else if (m.type === "poses") for (const p of m.poses) onPose(p);
  else if (m.type === "points") S.points[m.map_id] = { xyz: Float32Array.from(m.xyz), n: m.n, total: m.n_total, up: m.up };
  else if (m.type === "event") onEvent(m);
}

function onState(m) {
  S.maps = m.maps;
  S.trajs = m.trajectories;
  S.loops = m.loops;
  const now = performance.now();
  for (const a of m.agents) {
    colour(a.agent);
    const g = S.agents[a.agent] || (S.agents[a.agent] = { lastSeen: 0 });
    Object.assign(g, { agent: a.agent, map_id: a.map_id, n_kf: a.n_kf, n_mp: a.n_mp });
    if (a.position) {
      if (!g.position || a.age_s < (now - g.lastSeen) / 1000) {
        Object.assign(g, { position: a.position, q: a.quaternion_xyzw, fps: a.fps });
      }
      g.lastSeen = Math.max(g.lastSeen, now - a.age_s * 1000);
    }
    g.serverStatus = a.status;
  }
  for (const mp of S.maps) if (mp.merged_into) delete S.points[mp.map_id];
  // Follow the shown map through merges; unless one was chosen, show the biggest live
  // map (switching only for a clearly bigger one, so the view does not flip).
  const byId = Object.fromEntries(S.maps.map((x) => [x.map_id, x]));
  for (let i = 0; S.sel && byId[S.sel] && byId[S.sel].merged_into && i < 64; i++) S.sel = byId[S.sel].merged_into;
  const best = S.maps.filter((x) => !x.merged_into).sort((a, b) => b.n_kf - a.n_kf)[0];
  const cur = byId[S.sel];
  if (best && (!cur || cur.merged_into || (!S.pinned && best.n_kf > 1.2 * cur.n_kf + 2))) {
    if (S.sel !== best.map_id) top2d.fitNext = true;
    S.sel = best.map_id;
  }
  renderSide();
}

function onPose(p) {
  colour(p.agent);
  const g = S.agents[p.agent] || (S.agents[p.agent] = { agent: p.agent, n_kf: 0 });
  Object.assign(g, { map_id: p.map_id, position: p.position, q: p.quaternion_xyzw, fps: p.fps,
    serverStatus: p.status, lastSeen: performance.now() });
}

function onEvent(e) {
  e.seen = performance.now();
  S.events.unshift(e);
  if (e.kind === "merge" && e.at) S.merges.push(e);
  const li = document.createElement("li");
  const t = new Date(e.t * 1000).toLocaleTimeString();
  li.innerHTML = e.kind === "merge"
    ? `<span class="t">${t}</span><span class="merge">◆ merge</span> ${esc(e.source)} → ${esc(e.target)}`
    : `<span class="t">${t}</span><span class="loop">⟲ loop closed</span> in ${esc(e.map_id)}`;
  const ol = document.getElementById("events");
  ol.prepend(li);
  while (ol.children.length > 50) ol.lastChild.remove();
}

function esc(s) { return String(s).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" }[c])); }

function status(g) {
  if (!g.lastSeen || performance.now() - g.lastSeen > DISCONNECTED_MS) return "disconnected";
  return g.serverStatus || "tracking";
}

// --- side panel --------------------------------------------------------------------------------
function renderSide() {
  const tb = document.querySelector("#agents tbody");
  const rows = Object.values(S.agents).sort((a, b) => a.agent.localeCompare(b.agent, undefined, { numeric: true }));
  // Rewritten only when it reads differently: a new table is a layout of the page.
  const html = rows.map((g) => {
    const st = status(g);
    return `<tr><td><span class="sw" style="background:${colour(g.agent)}"></span></td><td>${esc(g.agent)}</td>` +
      `<td><span class="st ${st}">${st}</span></td><td>${esc(g.map_id || "")}</td>` +
      `<td class="num">${g.n_kf ?? ""}</td><td class="num">${g.fps != null ? g.fps.toFixed(0) : ""}</td></tr>`;
  }).join("");
  if (html !== renderSide.html) { tb.innerHTML = html; renderSide.html = html; }
  const live = S.maps.filter((m) => !m.merged_into);
  const bar = document.getElementById("maps");
  const want = live.map((m) => m.map_id + (m.map_id === S.sel ? "*" : "") + m.n_kf).join();
  if (bar.dataset.key !== want) {
    bar.dataset.key = want;
    bar.innerHTML = "";
    for (const m of live) {
      const b = document.createElement("button");
      b.textContent = `${m.map_id} (${m.n_kf} KFs)`;
      if (m.map_id === S.sel) b.className = "sel";
      b.onclick = () => { S.sel = m.map_id; S.pinned = true; top2d.fitNext = true; renderSide(); };
      bar.append(b);
    }
  }
  const nkf = live.reduce((s, m) => s + m.n_kf, 0);
  const pts = S.points[S.sel];
  const totals = document.getElementById("totals");
  const text =
    `${rows.length} agents · ${live.length} map${live.length === 1 ? "" : "s"} · ${nkf} keyframes` +
    (pts ? ` · ${pts.total} points (${pts.n} shown)` : "");
  if (totals.textContent !== text) totals.textContent = text;
}
setInterval(renderSide, 1000);

// --- geometry --------------------------------------------------------------------------------
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => { const n = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / n, a[1] / n, a[2] / n]; };

// Each map's "up" comes from the server (feed.up_direction; the one sent with the points
// also knows where the floor is); x is the map's x axis made level, so the view keeps its
// orientation as the map grows.
function basis(mapId) {
  const m = S.maps.find((x) => x.map_id === mapId), P = S.points[mapId];
  const up = norm(P && P.up ? P.up : m && m.up ? m.up : [0, -1, 0]);
  const b = S.basis[mapId];
  if (b && dot(b.up, up) > 0.995) return b;
  let e1 = Math.abs(up[0]) < 0.9 ? [1, 0, 0] : [0, 0, 1];
  e1 = norm([e1[0] - up[0] * dot(e1, up), e1[1] - up[1] * dot(e1, up), e1[2] - up[2] * dot(e1, up)]);
  const e2 = cross(up, e1);
  return (S.basis[mapId] = { e1, e2, up });
}
const toLocal = (B, p) => [dot(p, B.e1), dot(p, B.e2), dot(p, B.up)];

function heading(q) { // camera z axis (forward) in the map frame
  const [x, y, z, w] = q;
  return [2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)];
}

function niceStep(raw) {
  const e = Math.pow(10, Math.floor(Math.log10(raw)));
  const f = raw / e;
  return (f < 1.5 ? 1 : f < 3.5 ? 2 : f < 7.5 ? 5 : 10) * e;
}
function fmtLen(m) { return m >= 1000 ? (m / 1000) + " km" : m >= 1 ? m + " m" : m >= 0.01 ? Math.round(m * 100) + " cm" : (m * 1000).toFixed(0) + " mm"; }

// Height colour (viridis stops) as packed ABGR for the pixel buffer.
const VIRIDIS = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]];
function heightRGBA(t, alpha) {
  t = Math.min(1, Math.max(0, t)) * (VIRIDIS.length - 1);
  const i = Math.min(VIRIDIS.length - 2, Math.floor(t)), f = t - i;
  const c = VIRIDIS[i].map((v, k) => Math.round(v + (VIRIDIS[i + 1][k] - v) * f));
  return (alpha << 24) | (c[2] << 16) | (c[1] << 8) | c[0];
}

// What one frame draws for the selected map, in its local (e1, e2, up) coordinates.
function scene() {
  const mapId = S.sel;
  const trajs = {};
  for (const a in S.trajs) {
    const g = S.agents[a];
    if (g && g.map_id === mapId && S.trajs[a].length) trajs[a] = S.trajs[a];
  }
  const B = basis(mapId);
  const out = { mapId, B, trajs: {}, poses: [], loops: [], merges: [], pts: null };
  // Keyframe trajectories change with a state message (every 1.5 s), not per frame.
  const tc = S.trajCache;
  if (tc && tc.src === S.trajs && tc.B === B && tc.mapId === mapId) out.trajs = tc.out;
  else {
    for (const a in trajs) out.trajs[a] = trajs[a].map((p) => toLocal(B, p));
    S.trajCache = { src: S.trajs, B, mapId, out: out.trajs };
  }
  for (const a in S.agents) {
    const g = S.agents[a];
    if (g.map_id !== mapId || !g.position) continue;
    const h = g.q ? toLocal(B, heading(g.q)) : [1, 0, 0];
    out.poses.push({ agent: a, p: toLocal(B, g.position), h, st: status(g) });
  }
  for (const e of S.loops[mapId] || []) out.loops.push([toLocal(B, e.a), toLocal(B, e.b)]);
  for (const e of S.merges) if (e.target === mapId) out.merges.push({ p: toLocal(B, e.at), e });
  const P = S.points[mapId];
  if (P) {
    if (!P.local || P.B !== B) {
      const n = P.xyz.length / 3, L = new Float32Array(n * 3);
      let zlo = Infinity, zhi = -Infinity;
      for (let i = 0; i < n; i++) {
        const p = [P.xyz[3 * i], P.xyz[3 * i + 1], P.xyz[3 * i + 2]];
        L[3 * i] = dot(p, B.e1); L[3 * i + 1] = dot(p, B.e2); const z = L[3 * i + 2] = dot(p, B.up);
        zlo = Math.min(zlo, z); zhi = Math.max(zhi, z);
      }
      // Colour between the 5th and 95th height percentiles: a few outliers do not wash it out.
      const zs = Array.from({ length: Math.min(n, 2000) }, (_, k) => L[3 * Math.floor(k * n / Math.min(n, 2000)) + 2]).sort((a, b) => a - b);
      P.zlo = zs.length ? zs[Math.floor(zs.length * 0.05)] : zlo; P.zhi = zs.length ? zs[Math.floor(zs.length * 0.95)] : zhi;
      // Each point's colour once per points message, not per point and frame.
      const span = (P.zhi - P.zlo) || 1, rgba = new Uint32Array(n);
      for (let i = 0; i < n; i++) rgba[i] = heightRGBA((L[3 * i + 2] - P.zlo) / span, 230);
      P.local = L; P.B = B; P.rgba = rgba;
    }
    out.pts = P;
  }
  return out;
}

function bounds(sc) {
  let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity, z0 = Infinity, z1 = -Infinity;
  const add = (p) => { x0 = Math.min(x0, p[0]); x1 = Math.max(x1, p[0]); y0 = Math.min(y0, p[1]); y1 = Math.max(y1, p[1]); z0 = Math.min(z0, p[2]); z1 = Math.max(z1, p[2]); };
  for (const a in sc.trajs) for (const p of sc.trajs[a]) add(p);
  for (const q of sc.poses) add(q.p);
  if (!isFinite(x0)) return null;
  // Points widen the frame a little (walls beyond the path), by robust percentiles.
  if (sc.pts && sc.pts.local.length) {
    const L = sc.pts.local, n = L.length / 3, k = Math.min(n, 1000), xs = [], ys = [];
    for (let i = 0; i < k; i++) { const j = Math.floor(i * n / k); xs.push(L[3 * j]); ys.push(L[3 * j + 1]); }
    xs.sort((a, b) => a - b); ys.sort((a, b) => a - b);
    x0 = Math.min(x0, xs[Math.floor(k * 0.03)]); x1 = Math.max(x1, xs[Math.floor(k * 0.97)]);
    y0 = Math.min(y0, ys[Math.floor(k * 0.03)]); y1 = Math.max(y1, ys[Math.floor(k * 0.97)]);
  }
  return { x0, x1, y0, y1, z0, z1 };
}

// --- canvases ---------------------------------------------------------------------------------
function Surface(id) {
  const cv = document.getElementById(id);
  const s = { cv, cx: cv.getContext("2d", { alpha: false }), w: 0, h: 0, dpr: 1,
    off: document.createElement("canvas"), layer: document.createElement("canvas") };
  s.lcx = s.layer.getContext("2d", { alpha: false });
  s.resize = () => {
    const r = cv.getBoundingClientRect();
    s.dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(r.width * s.dpr)), h = Math.max(1, Math.round(r.height * s.dpr));
    if (w !== cv.width || h !== cv.height) {
      cv.width = w; cv.height = h; s.off.width = w; s.off.height = h; s.layer.width = w; s.layer.height = h;
      s.layerKey = null;
      s.img = s.off.getContext("2d").createImageData(w, h);
      s.buf = new Uint32Array(s.img.data.buffer);
    }
    s.w = w; s.h = h;
  };
  // Map points as 2x2 pixels through a buffer: tens of thousands cost a millisecond. The
  // projections are written out (no closure, no array per point): the orbit view turns,
  // so its points are projected every frame.
  s.plot = (P, proj) => {
    s.buf.fill(0);
    const L = P.local, C = P.rgba, n = L.length / 3, W = s.w, H = s.h, buf = s.buf;
    let drawn = 0;
    if (proj.affine) {
      const { ox, sx, oy, sy } = proj;
      for (let i = 0; i < n; i++) {
        const x = (ox + L[3 * i] * sx) | 0, y = (oy + L[3 * i + 1] * sy) | 0;
        if (x < 0 || y < 0 || x >= W - 1 || y >= H - 1) continue;
        const c = C[i], o = y * W + x;
        buf[o] = c; buf[o + 1] = c; buf[o + W] = c; buf[o + W + 1] = c;
        drawn++;
      }
    } else {
      const { eye, r, u, f, F } = proj, cxp = W / 2, cyp = H / 2;
      for (let i = 0; i < n; i++) {
        const dx = L[3 * i] - eye[0], dy = L[3 * i + 1] - eye[1], dz = L[3 * i + 2] - eye[2];
        const zc = dx * f[0] + dy * f[1] + dz * f[2];
        if (zc < 0.05) continue;
        const x = (cxp + F * (dx * r[0] + dy * r[1] + dz * r[2]) / zc) | 0;
        const y = (cyp - F * (dx * u[0] + dy * u[1] + dz * u[2]) / zc) | 0;
        if (x < 0 || y < 0 || x >= W - 1 || y >= H - 1) continue;
        const c = C[i], o = y * W + x;
        buf[o] = c; buf[o + 1] = c; buf[o + W] = c; buf[o + W + 1] = c;
        drawn++;
      }
    }
    s.off.getContext("2d").putImageData(s.img, 0, 0);
    return drawn;
  };
  s.points = (P, proj, cx = s.cx) => {
    const n = s.plot(P, proj);
    cx.drawImage(s.off, 0, 0);
    return n;
  };
  return s;
}

const top2d = Surface("top");
const orbit = Surface("orbit");
Object.assign(top2d, { view: null, target: null, user: false, fitNext: true });
Object.assign(orbit, { az: 0.6, el: 0.5, dragUntil: 0, last: performance.now() });

// Top-down: pan and zoom by hand; a double-click goes back to following the map.
(() => {
  let drag = null;
  top2d.cv.addEventListener("wheel", (e) => {
    if (!top2d.view) return;
    e.preventDefault(); top2d.user = true;
    const f = Math.exp(-e.deltaY * 0.0015), v = top2d.view, r = top2d.cv.getBoundingClientRect();
    const mx = (e.clientX - r.left) * top2d.dpr, my = (e.clientY - r.top) * top2d.dpr;
    const wx = v.cx + (mx - top2d.w / 2) / v.s, wy = v.cy - (my - top2d.h / 2) / v.s;
    v.s *= f; v.cx = wx - (mx - top2d.w / 2) / v.s; v.cy = wy + (my - top2d.h / 2) / v.s;
  }, { passive: false });
  top2d.cv.addEventListener("mousedown", (e) => { drag = [e.clientX, e.clientY]; });
  addEventListener("mouseup", () => { drag = null; });
  addEventListener("mousemove", (e) => {
    if (!drag || !top2d.view) return;
    top2d.user = true;
    top2d.view.cx -= (e.clientX - drag[0]) * top2d.dpr / top2d.view.s;
    top2d.view.cy += (e.clientY - drag[1]) * top2d.dpr / top2d.view.s;
    drag = [e.clientX, e.clientY];
  });
  top2d.cv.addEventListener("dblclick", () => { top2d.user = false; top2d.fitNext = true; });
  let od = null;
  orbit.cv.addEventListener("mousedown", (e) => { od = [e.clientX, e.clientY]; });
  addEventListener("mouseup", () => { od = null; });
  addEventListener("mousemove", (e) => {
    if (!od) return;
    orbit.az -= (e.clientX - od[0]) * 0.01;
    orbit.el = Math.min(1.45, Math.max(0.05, orbit.el + (e.clientY - od[1]) * 0.01));
    od = [e.clientX, e.clientY]; orbit.dragUntil = performance.now() + 3000;
  });
})();

function drawTop(sc, bb, now) {
  const s = top2d, cx = s.cx, W = s.w, H = s.h, d = s.dpr;
  if (!bb) { cx.fillStyle = "#0e1116"; cx.fillRect(0, 0, W, H); emptyNote(s, "waiting for keyframes…"); return; }
  const pad = 60 * d;
  const tgt = {
    cx: (bb.x0 + bb.x1) / 2, cy: (bb.y0 + bb.y1) / 2,
    s: Math.min((W - 2 * pad) / Math.max(bb.x1 - bb.x0, 0.5), (H - 2 * pad) / Math.max(bb.y1 - bb.y0, 0.5)),
  };
  if (!s.view || s.fitNext) { s.view = { ...tgt }; s.goal = { ...tgt }; s.fitNext = false; }
  else if (!s.user) {
    // A new fit only when the map leaves the view's margin or has become much smaller
    // than it, then eased towards: the view follows a growing map without jumping, and
    // holds still in between, so the points layer is not redrawn every frame.
    const g = s.goal, hw = (W / 2 - pad / 2) / g.s, hh = (H / 2 - pad / 2) / g.s;
    if (bb.x0 < g.cx - hw || bb.x1 > g.cx + hw || bb.y0 < g.cy - hh || bb.y1 > g.cy + hh || tgt.s > 1.3 * g.s) {
      s.goal = { ...tgt };
    }
    const v = s.view, G = s.goal, k = 0.08;
    if (Math.abs(G.cx - v.cx) * v.s < 0.5 && Math.abs(G.cy - v.cy) * v.s < 0.5 && Math.abs(Math.log(G.s / v.s)) < 0.002) {
      s.view = { ...G };
    } else {
      v.cx += (G.cx - v.cx) * k; v.cy += (G.cy - v.cy) * k;
      v.s *= Math.pow(G.s / v.s, k);
    }
  }
  const v = s.view;
  const X = (x) => W / 2 + (x - v.cx) * v.s, Y = (y) => H / 2 - (y - v.cy) * v.s;

  // What changes only with the view or with a message from the server (grid, points,
  // keyframe trajectories, loops, merges, scale bar) is drawn into a layer kept between
  // frames; a frame copies it and draws what moves on top. In software (no GPU, a
  // small server's cores) drawing all of it every frame cost more than the rest of the
  // page together.
  const key = `${v.cx},${v.cy},${v.s},${W},${H},${sc.mapId},${S.merges.length}`;
  if (key !== s.layerKey || sc.trajs !== s.layerTrajs || (sc.pts && sc.pts.local) !== s.layerPts || sc.loops.length !== s.layerLoops) {
    drawTopLayer(s, sc, v, X, Y);
    stats.layers++;
    Object.assign(s, { layerKey: key, layerTrajs: sc.trajs, layerPts: sc.pts && sc.pts.local, layerLoops: sc.loops.length });
  }
  cx.drawImage(s.layer, 0, 0);

  // From each agent's newest keyframe to where it is now.
  for (const q of sc.poses) {
    const t = sc.trajs[q.agent];
    if (!t || !t.length) continue;
    const p = t[t.length - 1];
    cx.strokeStyle = colour(q.agent); cx.lineWidth = 2 * d; cx.beginPath();
    cx.moveTo(X(p[0]), Y(p[1])); cx.lineTo(X(q.p[0]), Y(q.p[1])); cx.stroke();
  }

  // A ring spreading out for 4 s after a merge or a loop.
  for (const m of sc.merges) {
    const age = (now - m.e.seen) / 4000;
    if (age < 1) { cx.strokeStyle = `rgba(255,176,0,${1 - age})`; cx.lineWidth = 2 * d; cx.beginPath(); cx.arc(X(m.p[0]), Y(m.p[1]), 8 * d + age * 60 * d, 0, 7); cx.stroke(); }
  }
  for (const e of S.events) {
    if (e.kind !== "loop" || e.map_id !== sc.mapId || now - e.seen > 4000 || !e.at) continue;
    const p = toLocal(sc.B, e.at), age = (now - e.seen) / 4000;
    cx.strokeStyle = `rgba(255,79,216,${1 - age})`; cx.lineWidth = 2 * d;
    cx.beginPath(); cx.arc(X(p[0]), Y(p[1]), 6 * d + age * 50 * d, 0, 7); cx.stroke();
  }

  // Current poses: a triangle along the heading, ringed by the status when not tracking.
  stats.drawn.poses = {};
  for (const q of sc.poses) {
    const x = X(q.p[0]), y = Y(q.p[1]), c = colour(q.agent);
    const hx = q.h[0], hy = q.h[1], hn = Math.hypot(hx, hy) || 1, ux = hx / hn, uy = -hy / hn;
    const r = 11 * d;
    cx.fillStyle = q.st === "disconnected" ? "#6c757d" : c;
    cx.strokeStyle = "#fff"; cx.lineWidth = 1.2 * d;
    cx.beginPath();
    cx.moveTo(x + ux * r, y + uy * r);
    cx.lineTo(x - ux * r * 0.6 - uy * r * 0.55, y - uy * r * 0.6 + ux * r * 0.55);
    cx.lineTo(x - ux * r * 0.3, y - uy * r * 0.3);
    cx.lineTo(x - ux * r * 0.6 + uy * r * 0.55, y - uy * r * 0.6 - ux * r * 0.55);
    cx.closePath(); cx.fill(); cx.stroke();
    const sc2 = STATUS_COLOUR[q.st];
    if (sc2) {
      cx.strokeStyle = sc2; cx.lineWidth = 2.5 * d;
      if (q.st === "disconnected") cx.setLineDash([3 * d, 3 * d]);
      cx.beginPath(); cx.arc(x, y, r + 5 * d + (q.st === "lost" ? 3 * d * Math.sin(now / 150) : 0), 0, 7); cx.stroke();
      cx.setLineDash([]);
    }
    cx.fillStyle = c; cx.font = `${12 * d}px system-ui, sans-serif`;
    cx.fillText(q.agent + (q.st !== "tracking" ? ` (${q.st})` : ""), x + r + 6 * d, y - 6 * d);
    stats.drawn.poses[q.agent] = { x: x / d, y: y / d, world: q.p.slice(), status: q.st };
  }
  stats.drawn.agents = sc.poses.length;
}

// The top view's layer: everything drawTop does not animate, for view ``v``.
function drawTopLayer(s, sc, v, X, Y) {
  const cx = s.lcx, W = s.w, H = s.h, d = s.dpr;
  cx.fillStyle = "#0e1116"; cx.fillRect(0, 0, W, H);
  // Grid: 1-2-5 steps about 90 px apart, labelled in metres along the edges.
  const step = niceStep(90 * d / v.s);
  const gx0 = Math.floor((v.cx - W / 2 / v.s) / step), gx1 = Math.ceil((v.cx + W / 2 / v.s) / step);
  const gy0 = Math.floor((v.cy - H / 2 / v.s) / step), gy1 = Math.ceil((v.cy + H / 2 / v.s) / step);
  cx.lineWidth = 1;
  cx.font = `${11 * d}px system-ui, sans-serif`;
  for (let i = gx0; i <= gx1; i++) {
    cx.strokeStyle = i === 0 ? "#3b4756" : "#1d242d";
    cx.beginPath(); cx.moveTo(Math.round(X(i * step)) + 0.5, 0); cx.lineTo(Math.round(X(i * step)) + 0.5, H); cx.stroke();
  }
  for (let j = gy0; j <= gy1; j++) {
    cx.strokeStyle = j === 0 ? "#3b4756" : "#1d242d";
    cx.beginPath(); cx.moveTo(0, Math.round(Y(j * step)) + 0.5); cx.lineTo(W, Math.round(Y(j * step)) + 0.5); cx.stroke();
  }
  cx.fillStyle = "#5d6875";
  const dec = Math.max(0, -Math.floor(Math.log10(step)));
  for (let i = gx0; i <= gx1; i++) cx.fillText((i * step).toFixed(dec), X(i * step) + 3 * d, H - 6 * d);
  for (let j = gy0; j <= gy1; j++) cx.fillText((j * step).toFixed(dec), 4 * d, Y(j * step) - 3 * d);

  const proj = { affine: true, ox: W / 2 - v.cx * v.s, sx: v.s, oy: H / 2 + v.cy * v.s, sy: -v.s };
  stats.drawn.points = sc.pts ? s.points(sc.pts, proj, cx) : 0;

  // Loops: dashed magenta between the two keyframes.
  cx.setLineDash([6 * d, 4 * d]); cx.strokeStyle = "#ff4fd8"; cx.lineWidth = 1.5 * d;
  for (const [a, b] of sc.loops) { cx.beginPath(); cx.moveTo(X(a[0]), Y(a[1])); cx.lineTo(X(b[0]), Y(b[1])); cx.stroke(); }
  cx.setLineDash([]);

  // Keyframe trajectories.
  for (const a in sc.trajs) {
    const t = sc.trajs[a], c = colour(a);
    cx.strokeStyle = c; cx.lineWidth = 2 * d; cx.beginPath();
    t.forEach((p, i) => (i ? cx.lineTo(X(p[0]), Y(p[1])) : cx.moveTo(X(p[0]), Y(p[1]))));
    cx.stroke();
    cx.fillStyle = c;
    const k = 3 * d;
    for (const p of t) cx.fillRect(X(p[0]) - k / 2, Y(p[1]) - k / 2, k, k);
  }

  // Merges: an amber diamond where it happened.
  for (const m of sc.merges) {
    const x = X(m.p[0]), y = Y(m.p[1]), r = 8 * d;
    cx.fillStyle = "#ffb000"; cx.beginPath();
    cx.moveTo(x, y - r); cx.lineTo(x + r, y); cx.lineTo(x, y + r); cx.lineTo(x - r, y); cx.closePath(); cx.fill();
  }

  // Scale bar, bottom left, and the axes, bottom right.
  const L = niceStep(140 * d / v.s), px = L * v.s, bx = 20 * d, by = H - 28 * d;
  cx.fillStyle = "rgba(14,17,22,0.75)"; cx.fillRect(bx - 8 * d, by - 20 * d, px + 16 * d, 34 * d);
  cx.strokeStyle = "#e6edf3"; cx.lineWidth = 2 * d;
  cx.beginPath(); cx.moveTo(bx, by - 5 * d); cx.lineTo(bx, by); cx.lineTo(bx + px, by); cx.lineTo(bx + px, by - 5 * d); cx.stroke();
  cx.fillStyle = "#e6edf3"; cx.font = `${12 * d}px system-ui, sans-serif`;
  const scaleText = fmtLen(+L.toPrecision(3));
  cx.fillText(scaleText, bx + px / 2 - 14 * d, by - 8 * d);
  stats.drawn.scaleBar = { text: scaleText, px: px / d };
  stats.drawn.grid_m = step;
  const ax = W - 60 * d, ay = H - 24 * d, al = 34 * d;
  cx.lineWidth = 2 * d;
  cx.strokeStyle = "#ff5d5d"; cx.beginPath(); cx.moveTo(ax, ay); cx.lineTo(ax + al, ay); cx.stroke();
  cx.strokeStyle = "#5dff8a"; cx.beginPath(); cx.moveTo(ax, ay); cx.lineTo(ax, ay - al); cx.stroke();
  cx.fillStyle = "#ff5d5d"; cx.fillText("x", ax + al + 3 * d, ay + 4 * d);
  cx.fillStyle = "#5dff8a"; cx.fillText("y", ax - 4 * d, ay - al - 4 * d);
  cx.fillStyle = "#8b96a5"; cx.fillText(`map ${sc.mapId} · grid ${fmtLen(+step.toPrecision(3))}`, 10 * d, 36 * d);
}

function drawOrbit(sc, bb, now) {
  const s = orbit, cx = s.cx, W = s.w, H = s.h, d = s.dpr;
  const dt = Math.min(0.1, (now - s.last) / 1000); s.last = now;
  if (now > s.dragUntil) s.az += dt * 0.35;
  cx.fillStyle = "#0b0e13"; cx.fillRect(0, 0, W, H);
  if (!bb) { emptyNote(s, "waiting for keyframes…"); return; }
  const c = [(bb.x0 + bb.x1) / 2, (bb.y0 + bb.y1) / 2, (bb.z0 + bb.z1) / 2];
  const R = Math.max(1, 0.5 * Math.hypot(bb.x1 - bb.x0, bb.y1 - bb.y0, bb.z1 - bb.z0));
  const fov = 0.9, dist = 1.15 * R / Math.tan(fov / 2);
  const ce = Math.cos(s.el);
  const eye = [c[0] + dist * ce * Math.cos(s.az), c[1] + dist * ce * Math.sin(s.az), c[2] + dist * Math.sin(s.el)];
  const f = norm([c[0] - eye[0], c[1] - eye[1], c[2] - eye[2]]);
  const r = norm(cross(f, [0, 0, 1])), u = cross(r, f);
  const F = 0.5 * Math.min(W, H) / Math.tan(fov / 2);
  const P = (x, y, z) => {
    const dx = x - eye[0], dy = y - eye[1], dz = z - eye[2];
    const zc = dx * f[0] + dy * f[1] + dz * f[2];
    if (zc < 0.05) return null;
    return [W / 2 + F * (dx * r[0] + dy * r[1] + dz * r[2]) / zc, H / 2 - F * (dx * u[0] + dy * u[1] + dz * u[2]) / zc, zc];
  };
  // Ground grid under the lowest keyframe.
  const step = niceStep(R / 4), g0 = bb.z0 - 0.2 * R;
  cx.strokeStyle = "#1f2731"; cx.lineWidth = 1;
  const n = 6;
  for (let i = -n; i <= n; i++) {
    for (const [a, b] of [[[c[0] + i * step, c[1] - n * step], [c[0] + i * step, c[1] + n * step]],
      [[c[0] - n * step, c[1] + i * step], [c[0] + n * step, c[1] + i * step]]]) {
      const p = P(a[0], a[1], g0), q = P(b[0], b[1], g0);
      if (p && q) { cx.beginPath(); cx.moveTo(p[0], p[1]); cx.lineTo(q[0], q[1]); cx.stroke(); }
    }
  }
  if (sc.pts) s.points(sc.pts, { eye, r, u, f, F });
  cx.setLineDash([5 * d, 4 * d]); cx.strokeStyle = "#ff4fd8"; cx.lineWidth = 1.5 * d;
  for (const [a, b] of sc.loops) {
    const p = P(...a), q = P(...b);
    if (p && q) { cx.beginPath(); cx.moveTo(p[0], p[1]); cx.lineTo(q[0], q[1]); cx.stroke(); }
  }
  cx.setLineDash([]);
  for (const a in sc.trajs) {
    cx.strokeStyle = colour(a); cx.lineWidth = 2 * d; cx.beginPath();
    let started = false;
    for (const p of sc.trajs[a]) {
      const q = P(p[0], p[1], p[2]);
      if (!q) { started = false; continue; }
      if (started) cx.lineTo(q[0], q[1]); else { cx.moveTo(q[0], q[1]); started = true; }
    }
    cx.stroke();
  }
  for (const m of sc.merges) {
    const q = P(...m.p);
    if (q) { cx.fillStyle = "#ffb000"; cx.beginPath(); cx.arc(q[0], q[1], 6 * d, 0, 7); cx.fill(); }
  }
  for (const g of sc.poses) {
    const q = P(...g.p);
    if (!q) continue;
    const rad = Math.max(3 * d, Math.min(12 * d, 0.25 * F / q[2]));
    cx.fillStyle = g.st === "disconnected" ? "#6c757d" : colour(g.agent);
    cx.beginPath(); cx.arc(q[0], q[1], rad, 0, 7); cx.fill();
    if (STATUS_COLOUR[g.st]) { cx.strokeStyle = STATUS_COLOUR[g.st]; cx.lineWidth = 2 * d; cx.beginPath(); cx.arc(q[0], q[1], rad + 4 * d, 0, 7); cx.stroke(); }
  }
}

function emptyNote(s, text) {
  s.cx.fillStyle = "#5d6875"; s.cx.font = `${14 * s.dpr}px system-ui, sans-serif`;
  s.cx.fillText(S.connected ? text : "connecting to the server…", 20 * s.dpr, s.h / 2);
}

// --- frame loop --------------------------------------------------------------------------------
// At most 30 frames a second: smooth for a map, and half the CPU of the display's 60 (the
// browser may share a small server's cores). stats.drawMs says how much of a frame's
// 33 ms the drawing takes: the headroom left.
const FRAME_MS = 1000 / 30;
let fpsT0 = performance.now(), fpsN = 0, lastDraw = 0;
const drawTimes = [];
function frame(now) {
  requestAnimationFrame(frame);
  if (now - lastDraw < FRAME_MS - 2) return;
  lastDraw = now;
  const t0 = performance.now();
  top2d.resize(); orbit.resize();
  const sc = scene(), bb = bounds(sc);
  drawTop(sc, bb, now);
  drawOrbit(sc, bb, now);
  drawTimes.push(performance.now() - t0);
  if (drawTimes.length > 60) drawTimes.shift();
  stats.drawMs = drawTimes.slice().sort((a, b) => a - b)[Math.floor(drawTimes.length / 2)];
  stats.frames++; fpsN++;
  if (now - fpsT0 >= 1000) {
    stats.fps = fpsN * 1000 / (now - fpsT0); fpsT0 = now; fpsN = 0;
    document.getElementById("fps").textContent = `${stats.fps.toFixed(0)} fps · draw ${stats.drawMs.toFixed(1)} ms`;
    if (S.connected && now - S.lastMsg > 5000) setConn("wait", "no data");
    else if (S.connected) setConn("live", "live");
  }
}
connect();
requestAnimationFrame(frame);
