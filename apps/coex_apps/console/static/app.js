// CoEx topside console: live state over server-sent events, actions as POST /api/action.
// Plain browser JavaScript, no build step, no external resources.
"use strict";

const S = { now: 0, vehicle: null, map: null, surveys: null, images: null, series: null, other: null, link: null,
  queues: null, commands: [], log: [], versions: {} };
const $ = (sel) => document.querySelector(sel);
// A fleet console (several vehicles): the page shows the vehicle named by ?vehicle= (none:
// the first); every request and picture names it, and every action carries it.
const VEHICLE = new URLSearchParams(location.search).get("vehicle");
const withVehicle = (url) => (VEHICLE === null || !url ? url
  : `${url}${url.includes("?") ? "&" : "?"}vehicle=${encodeURIComponent(VEHICLE)}`);
const el = (tag, attrs = {}, ...kids) => {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") e.className = v;
    else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else if (k === "style") e.style.cssText = v;  // CSSOM: allowed by the page's CSP (no inline styles)
    else e.setAttribute(k, v);
  }
  for (const k of kids) e.append(k instanceof Node ? k : document.createTextNode(String(k)));
  return e;
};

// ------------------------------------------------------------------ formatting
const pad = (n) => String(n).padStart(2, "0");
function fmtT(t) {
  if (t === null || t === undefined) return "–";
  const s = ((Math.floor(t) % 86400) + 86400) % 86400;
  return `${pad(Math.floor(s / 3600))}:${pad(Math.floor(s / 60) % 60)}:${pad(s % 60)}`;
}
function fmtAge(a) {
  if (a === null || a === undefined || !isFinite(a)) return "–";
  a = Math.max(0, a);
  if (a < 90) return `${a.toFixed(0)} s`;
  if (a < 5400) return `${(a / 60).toFixed(0)} min`;
  return `${(a / 3600).toFixed(1)} h`;
}
function fmtBytes(b) {
  if (b === null || b === undefined) return "?";
  return b < 2048 ? `${b} B` : `${(b / 1024).toFixed(1)} kB`;
}
function parseTime(text) {
  // "hh:mm:ss" or "mm:ss" (time of day, nearest to now) or plain seconds
  text = text.trim();
  if (!text) return S.now;
  if (text.includes(":")) {
    const parts = text.split(":").map(Number);
    if (parts.some((p) => !isFinite(p))) throw new Error(`bad time ${text}`);
    while (parts.length < 3) parts.unshift(0);
    const tod = parts[0] * 3600 + parts[1] * 60 + parts[2];
    const base = S.now - (((S.now % 86400) + 86400) % 86400);
    let t = base + tod;
    if (t > S.now + 43200) t -= 86400;
    if (t < S.now - 43200) t += 86400;
    return t;
  }
  const v = Number(text);
  if (!isFinite(v)) throw new Error(`bad time ${text}`);
  return v;
}

// ------------------------------------------------------------------ actions
function toast(text, error = false) {
  const t = $("#toast");
  t.textContent = text;
  t.className = "toast" + (error ? " error" : "");
  clearTimeout(toast.timer);
  toast.timer = setTimeout(() => t.classList.add("hidden"), error ? 6000 : 2500);
}
// Actions go to the server one at a time, in the order the operator gave them: two quick
// clicks (flush a queue, then disable the link) must become commands in that order, and
// concurrent requests may be served in any order.
let actionChain = Promise.resolve();
function act(action, args) {
  const result = actionChain.then(() => sendAction(action, args));
  actionChain = result;
  return result;
}
async function sendAction(action, args) {
  try {
    const r = await fetch("/api/action", { method: "POST",
      headers: { "Content-Type": "application/json", "X-CSRF-Token": ME.csrf || "" },
      body: JSON.stringify({ action, args: S.fleet ? { ...args, vehicle: S.fleet.vehicle } : args }) });
    if (r.status === 401) { location.href = "/login"; return null; }
    const body = await r.json();
    if (!body.ok) { act.lastError = body.error || "failed"; toast(act.lastError, true); return null; }
    act.lastError = "";
    toast(`sent ${body.sent.map((m) => m.type).join(", ")}`);
    return body;
  } catch (err) {
    act.lastError = String(err);
    toast(act.lastError, true);
    return null;
  }
}

// ------------------------------------------------------------------ the map
const canvas = $("#map-canvas");
const ctx = canvas.getContext("2d");
const view = { cx: 0, cy: 0, scale: 1, auto: true };
const hiddenLevels = new Set();
const imgCache = new Map();
let drawMode = false, drag = null, roi = null;
let surveyMode = false, draft = null, hotSurvey = null;  // a survey being drawn; one hovered in the list
const openSurveys = new Set();  // surveys whose history the list shows (a click on the row)

function w2s(x, y) {
  return [canvas.width / 2 + (x - view.cx) * view.scale, canvas.height / 2 - (y - view.cy) * view.scale];
}
function s2w(px, py) {
  return [view.cx + (px - canvas.width / 2) / view.scale, view.cy - (py - canvas.height / 2) / view.scale];
}
function evPos(ev) {
  const r = canvas.getBoundingClientRect();
  return [(ev.clientX - r.left) * canvas.width / r.width, (ev.clientY - r.top) * canvas.height / r.height];
}
function resizeCanvas() {
  const r = canvas.getBoundingClientRect();
  const w = Math.max(200, Math.round(r.width)), h = Math.max(200, Math.round(r.height));
  if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
}
function bounds() {
  let b = null;
  const add = (x, y) => {
    if (x === null || y === null || x === undefined) return;
    if (!b) b = [x, y, x, y];
    else b = [Math.min(b[0], x), Math.min(b[1], y), Math.max(b[2], x), Math.max(b[3], y)];
  };
  if (S.map) {
    for (const lv of S.map.levels) { add(lv.x0, lv.y0); add(lv.x1, lv.y1); }
    for (const t of S.map.targets) add(t.x, t.y);
    for (const d of S.map.detections || []) add(d.x, d.y);
    for (const r of S.map.requests) { add(r.rect[0], r.rect[1]); add(r.rect[2], r.rect[3]); }
  }
  if (S.surveys) for (const sv of S.surveys.items) for (const p of sv.waypoints) add(p[0], p[1]);
  if (S.vehicle) for (const p of S.vehicle.track) add(p[1], p[2]);
  if (S.fleet) for (const v of S.fleet.vehicles) for (const p of v.track || []) add(p[0], p[1]);
  return b;
}
function fit() {
  resizeCanvas();
  const b = bounds();
  if (!b) return;
  const w = Math.max(b[2] - b[0], 20), h = Math.max(b[3] - b[1], 20);
  view.cx = (b[0] + b[2]) / 2; view.cy = (b[1] + b[3]) / 2;
  view.scale = 0.9 * Math.min(canvas.width / w, canvas.height / h);
}
function levelImage(lv) {
  let img = imgCache.get(lv.level);
  if (!img || img.dataset.src !== lv.png) {
    const fresh = new Image();
    fresh.dataset.src = lv.png;
    fresh.onload = () => { imgCache.set(lv.level, fresh); drawMap(); };
    fresh.src = withVehicle(lv.png);
    if (!img) return null;  // keep drawing the previous picture until the new one loads
  }
  return img && img.complete ? img : null;
}
const winCache = new Map();  // level -> {key, img, box}: what is on screen of a big level
function levelWindow(lv) {
  // A big level's picture is a decimated overview (lv.step level cells a pixel): zoomed in
  // further, ask the server for the part on screen, read from the receiver's tiles.
  if (!lv.step || lv.step <= 1) return null;
  let s = 1;
  while (s * 2 * lv.cell <= 1 / view.scale) s *= 2;  // a screen pixel holds s x s cells
  if (s >= lv.step) return null;
  const [vx0, vy1] = s2w(0, 0), [vx1, vy0] = s2w(canvas.width, canvas.height);
  const g = s * lv.cell * 256;  // snapped: small pans keep the picture
  const x0 = Math.floor(Math.max(vx0, lv.x0) / g) * g, y0 = Math.floor(Math.max(vy0, lv.y0) / g) * g;
  const x1 = Math.ceil(Math.min(vx1, lv.x1) / g) * g, y1 = Math.ceil(Math.min(vy1, lv.y1) / g) * g;
  if (x1 <= x0 || y1 <= y0) return null;
  const key = `/map/${lv.level}/window.png?x0=${x0}&y0=${y0}&x1=${x1}&y1=${y1}&step=${s}&v=${lv.version}`;
  let c = winCache.get(lv.level);
  if (!c) { c = { key: null, img: null, box: null, pending: null }; winCache.set(lv.level, c); }
  if (c.key !== key && c.pending !== key) {
    c.pending = key;
    const fresh = new Image(), entry = c;
    fresh.onload = () => {
      entry.key = key; entry.img = fresh; entry.box = [x0, y0, x1, y1];
      if (entry.pending === key) entry.pending = null;
      drawMap();
    };
    fresh.src = withVehicle(key);
  }
  return c.img && c.img.complete ? c : null;  // the previous one until the new one loads
}
function ageColor(age, alpha) {
  const f = Math.min(1, Math.max(0, age / 1800));
  const r = Math.round(80 + 175 * f), g = Math.round(220 - 150 * f);
  return `rgba(${r},${g},90,${alpha})`;
}
function drawMap() {
  placed.length = 0;
  regionLabels.length = 0;
  resizeCanvas();
  if (view.auto) fit();
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.fillStyle = "#0a1016";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  ctx.imageSmoothingEnabled = false;
  const m = S.map;
  const has = m && m.levels.length;
  $("#map-hint").classList.toggle("hidden", !!(has || (S.vehicle && S.vehicle.track.length)));
  drawGrid();
  if (m) {
    const visible = m.levels.filter((lv) => !hiddenLevels.has(lv.level));
    for (const lv of visible) {  // coarse first, finer on top
      const img = levelImage(lv);
      if (!img) continue;
      const box = lv.image || [lv.x0, lv.y0, lv.x1, lv.y1];  // the drawn array's extent
      const [ax, ay] = w2s(box[0], box[3]), [bx, by] = w2s(box[2], box[1]);
      ctx.drawImage(img, ax, ay, bx - ax, by - ay);
      const win = levelWindow(lv);
      if (win) {
        const [wa, wb] = w2s(win.box[0], win.box[3]), [wc, wd] = w2s(win.box[2], win.box[1]);
        ctx.drawImage(win.img, wa, wb, wc - wa, wd - wb);
      }
    }
    if ($("#show-gaps").checked && visible.length) drawGaps(visible[visible.length - 1]);
    if ($("#show-age").checked && visible.length) {
      const lv = visible[visible.length - 1];
      const span = lv.side * lv.cell * (lv.tile_span || 1);  // blocks of tile_span subgrids
      for (const [ix, iy, t] of lv.tiles) {
        const [ax, ay] = w2s(ix * span, (iy + 1) * span);
        const sz = span * view.scale;
        ctx.fillStyle = ageColor(S.now - t, 0.3);
        ctx.fillRect(ax, ay, sz, sz);
      }
    }
    for (const r of m.requests) {
      const [ax, ay] = w2s(r.rect[0], r.rect[3]), [bx, by] = w2s(r.rect[2], r.rect[1]);
      const style = ROI_STYLE[r.state] || ROI_STYLE.requested;
      ctx.strokeStyle = style[0]; ctx.setLineDash(style[1]); ctx.lineWidth = 2;
      if (style[2]) { ctx.fillStyle = style[2]; ctx.fillRect(ax, ay, bx - ax, by - ay); }
      ctx.strokeRect(ax, ay, bx - ax, by - ay);
      ctx.setLineDash([]);
      regionLabels.push([`L${r.level} ${r.text}`, ax + 3, ay + 12, style[0]]);
    }
  }
  if (S.fleet && $("#show-track").checked) drawFleet();
  if (S.vehicle && $("#show-track").checked) drawTrack();
  if (S.navigation && S.navigation.enabled && $("#show-usbl").checked) drawNavigation();
  if ($("#show-images").checked) drawImages();
  drawSurveys();
  if (m) {
    for (const t of m.targets) {
      const [x, y] = w2s(t.x, t.y);
      ctx.strokeStyle = "#ef5f5f"; ctx.lineWidth = 2;
      ctx.beginPath(); ctx.arc(x, y, 9, 0, 2 * Math.PI); ctx.stroke();
      const h = t.height !== undefined && t.height !== null ? ` ${Number(t.height).toFixed(1)} m high` : "";
      const size = t.cells && t.level !== undefined && S.map.meta ? `, ~${Math.round(t.cells * (S.map.meta.resolution * 2 ** t.level) ** 2)} m²` : "";
      placeLabel(`target${h}${size}`, x + 11, y - 6, "#ffb0b0");
    }
    drawDetections(m.detections || []);
  }
  // region labels last: where targets and surveys leave no room they are left out (the box's
  // style and the commands list say the same)
  for (const [text, x, y, color] of regionLabels) placeLabel(text, x, y, color, true);
  regionLabels.length = 0;
  if (roi) {
    const [ax, ay] = w2s(Math.min(roi[0], roi[2]), Math.max(roi[1], roi[3]));
    const [bx, by] = w2s(Math.max(roi[0], roi[2]), Math.min(roi[1], roi[3]));
    ctx.fillStyle = "rgba(79,179,255,0.15)"; ctx.fillRect(ax, ay, bx - ax, by - ay);
    ctx.strokeStyle = "#4fb3ff"; ctx.lineWidth = 2; ctx.strokeRect(ax, ay, bx - ax, by - ay);
    const sn = !$("#roi-bar").classList.contains("hidden") && roiSnapped();
    if (sn) {
      const [cx, cy] = w2s(sn.x0, sn.y1), [dx, dy] = w2s(sn.x1, sn.y0);
      ctx.setLineDash([3, 3]); ctx.strokeStyle = "#ffffff"; ctx.lineWidth = 1;
      ctx.strokeRect(cx, cy, dx - cx, dy - cy); ctx.setLineDash([]);
    }
  }
  drawDraft();
  drawScale();
  drawAxes();
}
// Axis ticks in metres east (bottom) and north (left) of the site origin, and a north arrow:
// the labels drawn are kept in window.coex.axes (for tests and the curious).
function drawAxes() {
  const stepM = niceStep(90 / view.scale);
  const [x0, y1] = s2w(0, 0), [x1, y0] = s2w(canvas.width, canvas.height);
  const W = canvas.width, H = canvas.height, axes = { x: [], y: [] };
  ctx.save();
  ctx.fillStyle = "rgba(10,16,22,0.72)";
  ctx.fillRect(0, H - 16, W, 16); ctx.fillRect(0, 0, 44, H - 16);
  ctx.font = "10px system-ui"; ctx.fillStyle = "#b8c8d6"; ctx.strokeStyle = "#b8c8d6"; ctx.lineWidth = 1;
  ctx.beginPath();
  for (let x = Math.ceil(x0 / stepM) * stepM; x < x1; x += stepM) {
    const [sx] = w2s(x, 0);
    if (sx < 50 || sx > W - 20) continue;
    ctx.moveTo(sx, H - 16); ctx.lineTo(sx, H - 12);
    const t = `${+x.toFixed(1)}`;
    ctx.fillText(t, sx - ctx.measureText(t).width / 2, H - 3);
    axes.x.push(t);
  }
  for (let y = Math.ceil(y0 / stepM) * stepM; y < y1; y += stepM) {
    const [, sy] = w2s(0, y);
    if (sy < 10 || sy > H - 24) continue;
    ctx.moveTo(44, sy); ctx.lineTo(40, sy);
    const t = `${+y.toFixed(1)}`;
    ctx.fillText(t, 38 - ctx.measureText(t).width, sy + 3);
    axes.y.push(t);
  }
  ctx.stroke();
  ctx.fillStyle = "#dce6ee";
  ctx.fillText("east (m)", W - 52, H - 19);
  ctx.save(); ctx.translate(10, 64); ctx.rotate(-Math.PI / 2); ctx.fillText("north (m)", -40, 0); ctx.restore();
  // north arrow (north is always up)
  const ax = W - 24, ay = 16;
  ctx.fillStyle = "rgba(10,16,22,0.72)"; ctx.beginPath(); ctx.arc(ax, ay + 12, 15, 0, 2 * Math.PI); ctx.fill();
  ctx.fillStyle = "#dce6ee"; ctx.beginPath();
  ctx.moveTo(ax, ay); ctx.lineTo(ax + 6, ay + 16); ctx.lineTo(ax, ay + 12); ctx.lineTo(ax - 6, ay + 16); ctx.closePath(); ctx.fill();
  ctx.font = "bold 10px system-ui"; ctx.fillText("N", ax - 3.5, ay + 25);
  ctx.restore();
  window.coex.axes = axes;
}
// Where the finest level shown has nothing, inside its extent: hatched, so that a coarser level
// drawn underneath does not hide that the fine data is missing there.
function drawGaps(lv) {
  const span = lv.side * lv.cell * (lv.tile_span || 1);
  const held = new Set(lv.tiles.map((t) => `${t[0]},${t[1]}`));
  const ix0 = Math.floor(lv.x0 / span), iy0 = Math.floor(lv.y0 / span);
  const ix1 = Math.ceil(lv.x1 / span), iy1 = Math.ceil(lv.y1 / span);
  if ((ix1 - ix0) * (iy1 - iy0) > 40000) return;
  ctx.save();
  ctx.strokeStyle = "rgba(255,255,255,0.55)"; ctx.lineWidth = 1;
  ctx.fillStyle = "rgba(10,16,22,0.55)";
  let n = 0;
  for (let ix = ix0; ix < ix1; ix++) for (let iy = iy0; iy < iy1; iy++) {
    if (held.has(`${ix},${iy}`)) continue;
    n++;
    const [ax, ay] = w2s(ix * span, (iy + 1) * span), sz = span * view.scale;
    ctx.fillRect(ax, ay, sz, sz);
    ctx.beginPath();
    for (let k = -sz; k < sz; k += 6) { ctx.moveTo(ax + Math.max(0, k), ay + Math.max(0, -k)); ctx.lineTo(ax + Math.min(sz, sz + k), ay + Math.min(sz, sz - k)); }
    ctx.stroke();
  }
  ctx.restore();
  window.coex.gaps = n;
}
// region requests: one look per state (the legend under the map says which)
const ROI_STYLE = { requested: ["#f0b443", [6, 4]], "in flight": ["#e8e05a", [], "rgba(232,224,90,0.10)"],
  "waiting for data": ["#6fb7ff", [2, 3], "rgba(111,183,255,0.10)"], filled: ["#58c47c", []],
  "nothing to send": ["#9aa6b2", [1, 4]] };
// labels placed so that they do not cover one another (tried below, above, then further down);
// an optional label with no free spot is left out, a needed one goes where it was asked
const placed = [];
const regionLabels = [];
function placeLabel(text, x, y, color, optional = false) {
  ctx.font = "bold 11px system-ui";
  const w = ctx.measureText(text).width + 6;
  x = Math.max(48, Math.min(x, canvas.width - w - 4));  // inside the map, clear of the axis
  for (const dy of [0, 15, -15, 30, -30, 45, 60, 75]) {
    const r = [x - 3, y + dy - 11, w, 15];
    if (!placed.some((q) => r[0] < q[0] + q[2] && q[0] < r[0] + r[2] && r[1] < q[1] + q[3] && q[1] < r[1] + r[3])) {
      placed.push(r); label(text, x, y + dy, color); return;
    }
  }
  if (optional) return;
  placed.push([x - 3, y - 11, w, 15]); label(text, x, y, color);
}
function drawGrid() {
  const stepM = niceStep(100 / view.scale);
  const [x0, y1] = s2w(0, 0), [x1, y0] = s2w(canvas.width, canvas.height);
  ctx.strokeStyle = "rgba(255,255,255,0.05)"; ctx.lineWidth = 1;
  ctx.beginPath();
  for (let x = Math.ceil(x0 / stepM) * stepM; x < x1; x += stepM) {
    const [sx] = w2s(x, 0); ctx.moveTo(sx, 0); ctx.lineTo(sx, canvas.height);
  }
  for (let y = Math.ceil(y0 / stepM) * stepM; y < y1; y += stepM) {
    const [, sy] = w2s(0, y); ctx.moveTo(0, sy); ctx.lineTo(canvas.width, sy);
  }
  ctx.stroke();
}
function niceStep(v) {
  const p = Math.pow(10, Math.floor(Math.log10(Math.max(v, 1e-6))));
  for (const k of [1, 2, 5, 10]) if (k * p >= v) return k * p;
  return 10 * p;
}
function drawScale() {
  const m = niceStep(120 / view.scale), px = m * view.scale;
  const x = 54, y = canvas.height - 26;
  ctx.strokeStyle = "#dce6ee"; ctx.lineWidth = 2;
  ctx.beginPath(); ctx.moveTo(x, y); ctx.lineTo(x + px, y); ctx.stroke();
  ctx.fillStyle = "#dce6ee"; ctx.font = "11px system-ui";
  ctx.fillText(`${m} m`, x + px + 6, y + 4);
}
// a fleet console: the other vehicles, dashed, with their names (this page's vehicle is drawn
// by drawTrack)
function drawFleet() {
  ctx.save();
  for (const v of S.fleet.vehicles) {
    if (v.id === S.fleet.vehicle || !v.track || !v.track.length) continue;
    ctx.strokeStyle = "rgba(180,200,215,0.6)"; ctx.lineWidth = 1.2; ctx.setLineDash([5, 4]);
    ctx.beginPath();
    v.track.forEach((p, i) => { const [x, y] = w2s(p[0], p[1]); if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y); });
    ctx.stroke(); ctx.setLineDash([]);
    const last = v.track[v.track.length - 1], [x, y] = w2s(last[0], last[1]);
    ctx.fillStyle = "#b4c8d7"; ctx.beginPath(); ctx.arc(x, y, 5, 0, 2 * Math.PI); ctx.fill();
    ctx.font = "bold 11px system-ui";  // label's: left of the dot near the right edge
    const wide = ctx.measureText(v.name).width;
    label(v.name, x + 8 + wide > canvas.width - 4 ? x - 8 - wide : x + 8, y - 6, "#b4c8d7");
  }
  ctx.restore();
}
function drawTrack() {
  const tr = S.vehicle.track;
  // with topside's drift correction applied the corrected track is drawn (drawNavigation) and the
  // vehicle's arrow stands at its newest corrected point
  const N = S.navigation, ct = N && N.enabled && N.applied && N.corrected_track && N.corrected_track.length
    && $("#show-usbl").checked ? N.corrected_track : null;
  if (tr.length > 1 && !ct) {
    ctx.strokeStyle = "rgba(255,255,255,0.75)"; ctx.lineWidth = 1.5;
    ctx.beginPath();
    tr.forEach((p, i) => { const [x, y] = w2s(p[1], p[2]); if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y); });
    ctx.stroke();
  }
  const st = S.vehicle.status;
  if (st) {
    const last = ct ? ct[ct.length - 1] : null;
    const [x, y] = last ? w2s(last[1], last[2]) : w2s(st.x, st.y), a = (st.heading * Math.PI) / 180;
    ctx.save(); ctx.translate(x, y); ctx.rotate(a);
    ctx.fillStyle = "#f28f3b"; ctx.strokeStyle = "#000";
    ctx.beginPath(); ctx.moveTo(0, -11); ctx.lineTo(7, 8); ctx.lineTo(-7, 8); ctx.closePath();
    ctx.fill(); ctx.stroke(); ctx.restore();
  }
}
// Navigation (issue 56): the ship's USBL fixes (dots, wild ones crossed), the vehicle's own
// dead-reckoned track (dashed) and the track corrected by topside's drift estimate (solid).
function drawNavigation() {
  const N = S.navigation;
  const line = (pts, style, dash) => {
    if (pts.length < 2) return;
    ctx.strokeStyle = style; ctx.lineWidth = 1.5; ctx.setLineDash(dash);
    ctx.beginPath();
    pts.forEach((p, i) => { const [x, y] = w2s(p[1], p[2]); if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y); });
    ctx.stroke(); ctx.setLineDash([]);
  };
  line(N.raw_track || [], "rgba(200,200,200,0.7)", [5, 4]);
  line(N.corrected_track || [], "#5fd3a6", []);
  for (const f of N.fixes || []) {
    const [x, y] = w2s(f[1], f[2]);
    if (f[4]) {
      ctx.strokeStyle = "#ef5f5f"; ctx.lineWidth = 1.5;
      ctx.beginPath(); ctx.moveTo(x - 4, y - 4); ctx.lineTo(x + 4, y + 4); ctx.moveTo(x + 4, y - 4); ctx.lineTo(x - 4, y + 4); ctx.stroke();
    } else {
      ctx.fillStyle = f[3] ? "rgba(120,190,255,0.8)" : "rgba(120,190,255,0.3)";
      ctx.beginPath(); ctx.arc(x, y, 2.5, 0, 2 * Math.PI); ctx.fill();
    }
  }
}
function renderNavigation() {
  const N = S.navigation, box = $("#nav-status");
  if (!N || !N.enabled) { box.classList.add("hidden"); return; }
  box.classList.remove("hidden");
  const c = N.correction;
  const fixes = `${N.fix_count} USBL fixes, ${N.outliers} rejected as wild`;
  if (!c) { box.textContent = `Navigation: ${fixes}; no correction yet (waiting for the vehicle's track)`; return; }
  const age = c.age === null || c.age === undefined ? "no fix used yet" : `newest fix used ${Math.round(c.age)} s ago`;
  box.textContent = `Navigation ${N.applied ? "corrected" : "NOT applied (shown in the vehicle's frame)"}: `
    + `correction ${c.size.toFixed(1)} m (east ${c.dx.toFixed(1)}, north ${c.dy.toFixed(1)}) ± ${c.sigma.toFixed(1)} m; `
    + `${age}; ${fixes}; fixes scatter ${c.fix_sigma.toFixed(1)} m`;
}
// Where the images were taken: their footprint (camera field of view at the vehicle's altitude)
// and a dot; the one open in the viewer, and images answering a request, stand out.
function drawImages() {
  if (!S.images) return;
  const ans = answeredBy();
  ctx.save();
  for (const it of S.images.items) {
    if (it.x === null || it.x === undefined) continue;
    const [x, y] = w2s(it.x, it.y);
    const hot = it.image_id === viewer.id || ans.has(it.image_id);
    if (it.footprint) {
      const w = it.footprint[0] * view.scale, h = it.footprint[1] * view.scale;
      ctx.strokeStyle = hot ? "#ffffff" : "rgba(120,230,255,0.8)"; ctx.lineWidth = hot ? 2 : 1;
      ctx.fillStyle = "rgba(120,230,255,0.10)";
      ctx.fillRect(x - w / 2, y - h / 2, w, h); ctx.strokeRect(x - w / 2, y - h / 2, w, h);
    }
    ctx.fillStyle = hot ? "#ffffff" : "#78e6ff";
    ctx.beginPath(); ctx.arc(x, y, hot ? 4 : 3, 0, 2 * Math.PI); ctx.fill();
    if (hot || view.scale > 4) label(`#${it.image_id}`, x + 6, y - 5, "#78e6ff");
  }
  ctx.restore();
}
function pickImage(p) {
  if (!S.images || !$("#show-images").checked) return false;
  for (const it of S.images.items) {
    if (it.x === null || it.x === undefined) continue;
    const [x, y] = w2s(it.x, it.y);
    if (Math.hypot(x - p[0], y - p[1]) < 7) { openViewer(it.image_id); return true; }
  }
  return false;
}
function renderLevels() {
  const tb = $("#levels-table tbody");
  tb.replaceChildren();
  const m = S.map;
  if (!m) return;
  for (const lv of m.levels.slice().sort((a, b) => a.level - b.level)) {
    const cb = el("input", { type: "checkbox" });
    cb.checked = !hiddenLevels.has(lv.level);
    cb.addEventListener("change", () => { if (cb.checked) hiddenLevels.delete(lv.level); else hiddenLevels.add(lv.level); drawMap(); });
    tb.append(el("tr", { "data-level": lv.level }, el("td", {}, cb), el("td", {}, lv.level),
      el("td", { title: lv.step > 1 ? `drawn at one pixel per ${lv.step} x ${lv.step} cells until you zoom in` : "" },
        `${lv.cell} m${lv.step > 1 ? ` (drawn ${lv.cell * lv.step} m)` : ""}`), el("td", { class: "n-subgrids" }, lv.subgrids),
      el("td", { title: "area held, and its share of the level's extent" },
        `${Math.round(lv.coverage_m2).toLocaleString()} m² (${lv.fill_pct ?? "?"} %)`),
      el("td", { class: "gaps", title: "blocks of the level's extent with no data (hatched with 'gaps')" }, lv.gap_note || "–"),
      el("td", {}, fmtAge(S.now - lv.newest)), el("td", {}, fmtAge(S.now - lv.oldest))));
  }
  const sel = $("#roi-level"), keep = sel.value;
  const n = m.meta ? m.meta.levels : Math.max(1, ...m.levels.map((l) => l.level + 1));
  sel.replaceChildren();
  for (let k = 0; k < Math.max(n, 1); k++) {
    const cell = m.meta ? m.meta.resolution * 2 ** k : null;
    sel.append(el("option", { value: k }, cell ? `${k} (${cell} m)` : `${k}`));
  }
  if (keep !== "") sel.value = keep;
  renderColorbar();
}
// The colour ramp with its numbers: seafloor elevation in metres (negative = below the surface
// datum), the same scale for every level.
function renderColorbar() {
  const m = S.map, box = $("#colorbar");
  if (!m || !m.zrange) { box.replaceChildren(); return; }
  const [lo, hi] = m.zrange, n = 5, ticks = [];
  const digits = hi - lo < 5 ? 1 : 0;
  for (let k = 0; k < n; k++) {
    const v = lo + ((hi - lo) * k) / (n - 1);
    ticks.push(el("span", { class: "tick", style: `left:${(100 * k) / (n - 1)}%` }, `${v.toFixed(digits)}`));
  }
  box.replaceChildren(el("span", { class: "cb-title" }, "seafloor elevation (m)"),
    el("div", { class: "cb-wrap" }, el("div", { class: "cb-ramp" }), el("div", { class: "cb-ticks" }, ...ticks)));
  const age = $("#show-age").checked;
  $("#age-legend").classList.toggle("hidden", !age);
}

canvas.addEventListener("mousedown", (ev) => {
  const p = evPos(ev);
  if (surveyMode) {
    const w = s2w(...p);
    draft = { kind: $("#survey-kind").value, a: w, b: w.slice() };
    drag = { kind: "survey" };
    showSurveyBar(); drawMap();
  } else if (drawMode) {
    const w = s2w(...p);
    roi = [w[0], w[1], w[0], w[1]];
    drag = { kind: "draw" };
  } else {
    drag = { kind: "pan", p, cx: view.cx, cy: view.cy };
  }
});
window.addEventListener("mousemove", (ev) => {
  const p = evPos(ev);
  const w = s2w(...p);
  $("#map-cursor").textContent = `x ${w[0].toFixed(1)} m, y ${w[1].toFixed(1)} m`;
  if (!drag) return;
  if (drag.kind === "draw") { roi[2] = w[0]; roi[3] = w[1]; drawMap(); }
  else if (drag.kind === "survey") { if (draft.kind !== "goto") draft.b = w; showSurveyBar(); drawMap(); }
  else {
    view.auto = false;
    view.cx = drag.cx - (p[0] - drag.p[0]) / view.scale;
    view.cy = drag.cy + (p[1] - drag.p[1]) / view.scale;
    drawMap();
  }
});
function pickTrackTime(p) {
  // a click (no drag) near the vehicle track sets the image time to when the vehicle was there
  if (!S.vehicle || !S.vehicle.track.length) return;
  let best = null, bestD = 10;
  for (const q of S.vehicle.track) {
    const [x, y] = w2s(q[1], q[2]);
    const d = Math.hypot(x - p[0], y - p[1]);
    if (d < bestD) { bestD = d; best = q; }
  }
  if (best) {
    $("#img-time").value = fmtT(best[0]);
    toast(`image time set to ${fmtT(best[0])} (vehicle at ${best[1].toFixed(0)}, ${best[2].toFixed(0)})`);
  }
}
window.addEventListener("keydown", (ev) => {
  if (ev.key === "Escape") {
    roi = null; $("#roi-bar").classList.add("hidden"); setDraw(false);
    endSurvey(); drawMap();
  }
});
window.addEventListener("mouseup", (ev) => {
  if (drag && drag.kind === "pan") {
    const p = evPos(ev);
    if (Math.hypot(p[0] - drag.p[0], p[1] - drag.p[1]) < 3 && !pickImage(p)) pickTrackTime(p);
  }
  if (drag && drag.kind === "survey") {
    const [ax, ay] = w2s(...draft.a), [bx, by] = w2s(...draft.b);
    const small = Math.hypot(bx - ax, by - ay) < 4;
    if (draft.kind !== "goto" && (small || (draft.kind === "lawnmower"
        && (Math.abs(bx - ax) < 4 || Math.abs(by - ay) < 4)))) {
      draft = null;  // a click where a drag was needed
      toast(`drag on the map to draw the ${$("#survey-kind").value === "line" ? "line" : "box"}`);
    }
    showSurveyBar(); drawMap();
  }
  if (drag && drag.kind === "draw") {
    if (Math.abs(roi[2] - roi[0]) * view.scale < 3 && Math.abs(roi[3] - roi[1]) * view.scale < 3) {
      roi = null;
    } else {
      showRoiBar();
    }
    drawMap();
  }
  drag = null;
});
canvas.addEventListener("wheel", (ev) => {
  ev.preventDefault();
  view.auto = false;
  const p = evPos(ev), before = s2w(...p);
  view.scale *= Math.exp(-ev.deltaY * 0.0015);
  const after = s2w(...p);
  view.cx += before[0] - after[0]; view.cy += before[1] - after[1];
  drawMap();
}, { passive: false });
canvas.addEventListener("dblclick", (ev) => {
  // double-click a target: select a 16 m box around it
  if (!S.map) return;
  const p = evPos(ev);
  for (const t of [...S.map.targets, ...(S.map.detections || [])]) {
    const [x, y] = w2s(t.x, t.y);
    if (Math.hypot(x - p[0], y - p[1]) < 12) {
      roi = [t.x - 8, t.y - 8, t.x + 8, t.y + 8];
      showRoiBar(); drawMap(); return;
    }
  }
});
// The vehicle's detections: suggestions (a dashed magenta diamond, oriented along the object's
// long axis when known), never drawn like the candidates the operator or the console flagged.
const DETECTION_COLOR = "#e36bff";
function drawDetections(items) {
  window.coex.detections = [];
  for (const d of items) {
    const [x, y] = w2s(d.x, d.y);
    const r = Math.max(13, Math.min(30, ((d.length || 4) / 2 + 1.5) * view.scale));
    const a = ((d.orientation === null || d.orientation === undefined) ? 45 : d.orientation) * Math.PI / 180;
    ctx.save();
    ctx.translate(x, y); ctx.rotate(a);  // the long axis, clockwise from north
    const w = Math.max(7, r * Math.min(1, (d.width || 2) / Math.max(d.length || 4, 0.1)));
    ctx.beginPath(); ctx.moveTo(0, -r); ctx.lineTo(w, 0); ctx.lineTo(0, r); ctx.lineTo(-w, 0); ctx.closePath();
    ctx.fillStyle = "rgba(227,107,255,0.18)"; ctx.fill();
    ctx.lineWidth = 4; ctx.strokeStyle = "rgba(0,0,0,0.55)"; ctx.stroke();  // a halo: readable on any colour
    ctx.setLineDash([5, 3]); ctx.lineWidth = 2.2; ctx.strokeStyle = DETECTION_COLOR; ctx.stroke();
    ctx.restore(); ctx.setLineDash([]);
    const dims = d.length !== null && d.length !== undefined ? ` ${Number(d.length).toFixed(1)}×${Number(d.width).toFixed(1)} m` : "";
    const high = d.height !== null && d.height !== undefined ? ` ${Number(d.height).toFixed(1)} m high` : "";
    const text = `suggested D${d.id}: score ${Number(d.score).toFixed(2)}${high}${dims}`;
    placeLabel(text, x + r + 4, y + 12, "#f2b8ff");
    window.coex.detections.push({ id: d.id, x, y, text });
  }
}
function setDraw(on) {
  if (on) endSurvey();
  drawMode = on;
  $("#draw-btn").classList.toggle("active", on);
  canvas.classList.toggle("drawing", on);
}
// The region the vehicle is asked for: whole subgrids of the level, so the box drawn grows to
// the subgrid edges; the bar says the size drawn and the size sent, and the map shows it dashed.
function roiSnapped() {
  if (!roi || !S.map || !S.map.meta) return null;
  const k = Number($("#roi-level").value || 0), side = S.map.meta.resolution * 2 ** k * S.map.meta.subgrid_side;
  const x0 = Math.floor(Math.min(roi[0], roi[2]) / side) * side, y0 = Math.floor(Math.min(roi[1], roi[3]) / side) * side;
  const x1 = (Math.floor(Math.max(roi[0], roi[2]) / side) + 1) * side, y1 = (Math.floor(Math.max(roi[1], roi[3]) / side) + 1) * side;
  return { x0, y0, x1, y1, side, nx: Math.round((x1 - x0) / side), ny: Math.round((y1 - y0) / side) };
}
function showRoiBar() {
  const w = Math.abs(roi[2] - roi[0]), h = Math.abs(roi[3] - roi[1]);
  const sn = roiSnapped();
  let text = `drawn ${w.toFixed(0)} × ${h.toFixed(0)} m at (${Math.min(roi[0], roi[2]).toFixed(0)}, ${Math.min(roi[1], roi[3]).toFixed(0)})`;
  if (sn) text += ` → asks ${sn.x1 - sn.x0} × ${sn.y1 - sn.y0} m (${sn.nx} × ${sn.ny} subgrids of ${sn.side} m)`;
  $("#roi-desc").textContent = text;
  $("#roi-bar").classList.remove("hidden");
  drawMap();
}
$("#roi-level").addEventListener("change", () => { if (roi) showRoiBar(); });
$("#draw-btn").addEventListener("click", () => setDraw(!drawMode));
$("#survey-btn").addEventListener("click", () => { if (surveyMode) endSurvey(); else startSurvey(); drawMap(); });
$("#fit-btn").addEventListener("click", () => { view.auto = true; drawMap(); });
$("#show-age").addEventListener("change", () => { $("#age-legend").classList.toggle("hidden", !$("#show-age").checked); drawMap(); });
$("#show-gaps").addEventListener("change", drawMap);
$("#show-track").addEventListener("change", drawMap);
$("#show-usbl").addEventListener("change", drawMap);
$("#show-images").addEventListener("change", drawMap);
$("#roi-cancel").addEventListener("click", () => { roi = null; $("#roi-bar").classList.add("hidden"); drawMap(); });
$("#roi-send").addEventListener("click", async () => {
  if (!roi) return;
  const r = await act("request_region", { level: Number($("#roi-level").value || 0),
    x_min: roi[0], y_min: roi[1], x_max: roi[2], y_max: roi[3], fill_gaps: $("#roi-gaps").checked });
  if (r) { roi = null; $("#roi-bar").classList.add("hidden"); setDraw(false); drawMap(); }
});

// ------------------------------------------------------------------ surveys
// The operator draws a survey (click a point, drag a line, drag a box for a lawnmower) and sends
// it; the survey receiver sends the SurveyCommand and follows it. Each survey is drawn as the
// path the vehicle will fly (S.surveys: the receiver's records), coloured by its state.
const SURVEY_COLOR = { requested: "#f0b443", accepted: "#6fb7ff", started: "#d08cff",
  completed: "#58c47c", rejected: "#ff5c5c", aborted: "#a3adb8", "given up": "#a3adb8",
  unknown: "#a3adb8" };
const SURVEY_DASH = { requested: [7, 4], rejected: [4, 4], aborted: [2, 4], "given up": [6, 3, 2, 3] };
const KIND_NAME = { goto: "go to", line: "line", lawnmower: "lawnmower", waypoints: "waypoints" };
// How a survey is drawn: by its state, except that an autonomy that never answered refused
// nothing: drawn like a survey given up, not like a refusal.
function surveyLook(sv) { return sv.reason === "AUTONOMY_NO_ANSWER" ? "given up" : sv.state; }
// What the list and the map call it: the console's outcome ("refused by autonomy", "no answer
// from autonomy", "taken over" ...), else its state.
function surveyWord(sv) { return sv.outcome || sv.state; }
const DEG = Math.PI / 180;
const round = (v, q) => Math.round(v / q) * q;

function numField(sel) {
  const t = $(sel).value.trim();
  if (t === "") return null;
  const v = Number(t);
  if (!isFinite(v)) throw new Error(`${$(sel).id.replace("survey-", "")}: not a number`);
  return v;
}
// What the drawn survey asks for (the action's arguments).
function surveyArgs() {
  if (!draft) return null;
  const args = { kind: draft.kind };
  const [ax, ay] = draft.a, [bx, by] = draft.b;
  if (draft.kind === "goto") {
    Object.assign(args, { x: round(ax, 0.1), y: round(ay, 0.1) });
  } else if (draft.kind === "line") {
    // drawn with a mouse: whole degrees and metres
    const heading = round(((Math.atan2(bx - ax, by - ay) / DEG) + 360) % 360, 1) % 360;
    Object.assign(args, { x: round(ax, 0.1), y: round(ay, 0.1), heading,
      length: round(Math.hypot(bx - ax, by - ay), 1) });
  } else {
    // a box: rows along the heading (default: the box's long side), covering the whole box
    const W = Math.abs(bx - ax), H = Math.abs(by - ay);
    let heading = numField("#survey-heading");
    if (heading === null) heading = W >= H ? 90 : 0;
    heading = round(((heading % 360) + 360) % 360, 0.1);
    const sn = Math.abs(Math.sin(heading * DEG)), cs = Math.abs(Math.cos(heading * DEG));
    Object.assign(args, { x: round((ax + bx) / 2, 0.1), y: round((ay + by) / 2, 0.1), heading,
      length: round(W * sn + H * cs, 1), width: round(W * cs + H * sn, 1),
      spacing: numField("#survey-spacing") });
  }
  const z = numField("#survey-z");
  if (z !== null) args[$("#survey-zmode").value] = z;
  const speed = numField("#survey-speed");
  if (speed !== null) args.speed = speed;
  args.append = $("#survey-append").checked;
  return args;
}
// The path a survey asks for: the same waypoints as the vehicle's plan (coex_plugins.survey.plan).
function surveyPath(a) {
  if (a.kind === "goto") return [[a.x, a.y]];
  const ex = Math.sin(a.heading * DEG), ey = Math.cos(a.heading * DEG);
  if (a.kind === "line") return [[a.x, a.y], [a.x + a.length * ex, a.y + a.length * ey]];
  if (!(a.spacing > 0) || !(a.length > 0)) return [];
  const rows = Math.floor(a.width / a.spacing + 1e-9) + 1;
  if (rows > 200) return [];
  const px = -ey, py = ex, across = (rows - 1) * a.spacing, out = [];
  for (let r = 0; r < rows; r++) {
    const off = across / 2 - r * a.spacing, cx = a.x + off * px, cy = a.y + off * py;
    const p = [cx - (a.length / 2) * ex, cy - (a.length / 2) * ey];
    const q = [cx + (a.length / 2) * ex, cy + (a.length / 2) * ey];
    if (r % 2 === 0) out.push(p, q); else out.push(q, p);
  }
  return out;
}
function pathLength(w) {
  let n = 0;
  for (let i = 1; i < w.length; i++) n += Math.hypot(w[i][0] - w[i - 1][0], w[i][1] - w[i - 1][1]);
  return n;
}
function startSurvey() {
  setDraw(false);
  surveyMode = true; draft = null;
  $("#survey-btn").classList.add("active");
  canvas.classList.add("drawing");
  $("#roi-bar").classList.add("hidden"); roi = null;
  showSurveyBar();
}
function endSurvey() {
  surveyMode = false; draft = null;
  $("#survey-btn").classList.remove("active");
  if (!drawMode) canvas.classList.remove("drawing");
  $("#survey-bar").classList.add("hidden");
}
function showSurveyBar() {
  const bar = $("#survey-bar"), kind = $("#survey-kind").value;
  bar.classList.remove("hidden", "goto", "line", "lawnmower");
  bar.classList.add(kind);
  $("#survey-error").classList.add("hidden");
  const desc = $("#survey-desc");
  let args = null, err = "";
  try { args = surveyArgs(); } catch (e) { err = e.message; }
  if (args && args.kind === "lawnmower") {
    const [ax, ay] = draft.a, [bx, by] = draft.b;
    $("#survey-heading").placeholder = `auto (${Math.abs(bx - ax) >= Math.abs(by - ay) ? 90 : 0})`;
  } else {
    $("#survey-heading").placeholder = "auto";
  }
  let text = { goto: "click the point to go to", line: "drag the line to fly (from its start)",
    lawnmower: "drag a box to cover with a lawnmower" }[kind];
  if (err) text = err;
  else if (args) {
    const path = surveyPath(args);
    if (args.kind === "goto") text = `go to (${args.x.toFixed(0)}, ${args.y.toFixed(0)})`;
    else if (args.kind === "line") text = `line ${args.length} m, heading ${args.heading}°, from (${args.x.toFixed(0)}, ${args.y.toFixed(0)})`;
    else if (!path.length) text = `lawnmower ${args.length} × ${args.width} m: give a spacing above 0 (at most 200 rows)`;
    else text = `lawnmower ${args.length} × ${args.width} m, heading ${args.heading}°, ${path.length / 2} rows, path ${pathLength(path).toFixed(0)} m`;
  }
  desc.textContent = text;
  desc.classList.toggle("dim", !args);
  $("#survey-send").disabled = !args || !!err || !surveyPath(args).length || !ME.may_command;
}
function drawDraft() {
  if (!surveyMode || !draft) return;
  let args;
  try { args = surveyArgs(); } catch (e) { return; }
  ctx.save();
  if (args.kind === "lawnmower") {  // the box drawn
    const [ax, ay] = w2s(...draft.a), [bx, by] = w2s(...draft.b);
    ctx.fillStyle = "rgba(79,179,255,0.10)"; ctx.fillRect(ax, ay, bx - ax, by - ay);
    ctx.strokeStyle = "rgba(79,179,255,0.8)"; ctx.lineWidth = 1; ctx.setLineDash([4, 3]);
    ctx.strokeRect(ax, ay, bx - ax, by - ay);
  }
  const path = surveyPath(args);
  ctx.setLineDash([]);
  strokePath(path, "#ffffff", 2, [], 1);
  if (path.length) {
    ctx.fillStyle = "#ffffff"; ctx.font = "bold 11px system-ui";
    const [x, y] = w2s(...path[0]);
    label(`preview: ${KIND_NAME[args.kind]}`, x + 8, y - 8, "#ffffff");
  }
  ctx.restore();
}
function strokePath(path, color, width, dash, alpha) {
  if (!path.length) return;
  ctx.globalAlpha = alpha;
  ctx.strokeStyle = color; ctx.fillStyle = color; ctx.lineWidth = width; ctx.setLineDash(dash);
  if (path.length > 1) {
    ctx.beginPath();
    path.forEach((p, i) => { const [x, y] = w2s(p[0], p[1]); if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y); });
    ctx.stroke();
    ctx.setLineDash([]);
    // an arrow head on the last leg: the way it is flown
    const [x0, y0] = w2s(...path[path.length - 2]), [x1, y1] = w2s(...path[path.length - 1]);
    const a = Math.atan2(y1 - y0, x1 - x0), L = 9;
    ctx.beginPath(); ctx.moveTo(x1, y1);
    ctx.lineTo(x1 - L * Math.cos(a - 0.45), y1 - L * Math.sin(a - 0.45));
    ctx.lineTo(x1 - L * Math.cos(a + 0.45), y1 - L * Math.sin(a + 0.45));
    ctx.closePath(); ctx.fill();
  }
  ctx.setLineDash([]);
  const [sx, sy] = w2s(...path[0]);  // the start (a go-to: the point, as a diamond)
  ctx.beginPath();
  if (path.length === 1) { ctx.moveTo(sx, sy - 7); ctx.lineTo(sx + 7, sy); ctx.lineTo(sx, sy + 7); ctx.lineTo(sx - 7, sy); ctx.closePath(); ctx.lineWidth = 2; ctx.stroke(); }
  else { ctx.arc(sx, sy, 4, 0, 2 * Math.PI); ctx.fill(); }
  ctx.globalAlpha = 1;
}
function label(text, x, y, color) {
  ctx.font = "bold 11px system-ui";
  const w = ctx.measureText(text).width;
  ctx.fillStyle = "rgba(10,16,22,0.78)"; ctx.fillRect(x - 3, y - 11, w + 6, 15);
  ctx.fillStyle = color; ctx.fillText(text, x, y);
}
function drawSurveys() {
  if (!S.surveys) return;
  ctx.save();
  const items = S.surveys.items;
  // finished ones first, the live ones on top; the hovered one last
  const order = items.slice().sort((a, b) => (a.survey_id === hotSurvey) - (b.survey_id === hotSurvey)
    || ["requested", "accepted", "started"].includes(a.state) - ["requested", "accepted", "started"].includes(b.state));
  for (const sv of order) {
    const look = surveyLook(sv);
    const color = SURVEY_COLOR[look] || SURVEY_COLOR.unknown, w = sv.waypoints;
    if (!w.length) continue;
    const hot = sv.survey_id === hotSurvey;
    const dim = ["completed", "aborted", "given up"].includes(look) && !hot ? 0.55 : 1;
    const lw = hot ? 4 : sv.state === "started" ? 3 : 2;
    if (sv.state === "started" && sv.index !== null && sv.index !== undefined && sv.index < w.length) {
      const i = Math.max(0, sv.index);
      strokePath(w.slice(0, i + 1), color, lw, [], 0.4);     // flown
      strokePath(w.slice(Math.max(0, i - 1)), color, lw, [], 1);  // to fly (from the leg it is on)
      const [x, y] = w2s(...w[i]);  // the waypoint it heads for
      ctx.strokeStyle = color; ctx.lineWidth = 2;
      ctx.beginPath(); ctx.arc(x, y, 8, 0, 2 * Math.PI); ctx.stroke();
      ctx.beginPath(); ctx.arc(x, y, 3, 0, 2 * Math.PI); ctx.fillStyle = color; ctx.fill();
      placeLabel(`→ waypoint ${sv.index}`, x + 11, y + 4, color);
    } else {
      strokePath(w, color, lw, SURVEY_DASH[look] || [], dim);
    }
    const [x, y] = w2s(...w[0]);
    ctx.globalAlpha = dim;
    placeLabel(`S${sv.survey_id} ${surveyWord(sv)}`, x + 7, y - 7, color);
    ctx.globalAlpha = 1;
  }
  ctx.restore();
}
function surveyDetails(sv) {
  if (sv.text) return sv.text;
  if (sv.reason) return sv.reason.toLowerCase().replace(/_/g, " ");
  const what = [];
  if (sv.kind === "lawnmower") what.push(`${sv.length} × ${sv.width} m, rows ${sv.spacing} m apart, heading ${sv.heading}°`);
  else if (sv.kind === "line") what.push(`${sv.length} m, heading ${sv.heading}°`);
  else if (sv.waypoints.length) what.push(`(${sv.waypoints[0][0].toFixed(0)}, ${sv.waypoints[0][1].toFixed(0)})`);
  if (sv.altitude !== null && sv.altitude !== undefined) what.push(`altitude ${sv.altitude} m`);
  if (sv.depth !== null && sv.depth !== undefined) what.push(`depth ${sv.depth} m`);
  if (sv.speed !== null && sv.speed !== undefined) what.push(`${sv.speed} m/s`);
  return what.join(", ");
}
function renderSurveys() {
  const tb = $("#surveys-table tbody");
  const items = (S.surveys && S.surveys.items) || [];
  const btn = $("#survey-btn");
  if (S.surveys && !S.surveys.available) {  // no survey receiver on this console's node
    btn.disabled = true; btn.title = "this console cannot ask for surveys (no survey receiver)";
    if (surveyMode) endSurvey();
  } else if (ME.may_command) {
    btn.disabled = false; btn.title = "draw a survey for the vehicle: a point, a line or a lawnmower box";
  }
  if (!items.length) {
    tb.replaceChildren(el("tr", { class: "empty-row" }, el("td", { colspan: 5, class: "empty" },
      S.surveys && !S.surveys.available ? "This console cannot ask for surveys (its node has no survey receiver)."
        : "No survey requested yet.")));
    return;
  }
  tb.replaceChildren(...items.slice().reverse().flatMap((sv) => {
    const why = ["rejected", "aborted", "given up"].includes(sv.state);
    // the survey receiver's history, in the vehicle's time order: shown as it comes, never re-sorted
    const lines = (sv.history || []).map((h) => `${fmtT(h[0])} ${h[1]}${h[2] ? ": " + h[2] : ""}`);
    const changed = sv.time !== null && fmtT(sv.time) !== fmtT(sv.requested) ? ` → ${fmtT(sv.time)}` : "";
    const open = openSurveys.has(sv.survey_id);
    const look = String(surveyLook(sv)).replace(" ", "_");
    const tr = el("tr", { "data-survey": sv.survey_id, "data-state": sv.state, "data-outcome": surveyWord(sv),
                          title: lines.join("\n") + "\n(click: the history under the row)" },
      el("td", {}, `${open ? "▾" : "▸"} S${sv.survey_id}`), el("td", {}, KIND_NAME[sv.kind] || sv.kind || "?"),
      el("td", {}, el("span", { class: `sbadge st-${look}` }, surveyWord(sv))),
      el("td", {}, `${fmtT(sv.requested)}${changed}`),
      el("td", { class: "details" + (why ? " why" : "") }, surveyDetails(sv)));
    tr.classList.toggle("hot", sv.survey_id === hotSurvey);
    tr.addEventListener("mouseenter", () => { hotSurvey = sv.survey_id; tr.classList.add("hot"); drawMap(); });
    tr.addEventListener("mouseleave", () => { hotSurvey = null; tr.classList.remove("hot"); drawMap(); });
    tr.addEventListener("click", () => {
      if (openSurveys.has(sv.survey_id)) openSurveys.delete(sv.survey_id); else openSurveys.add(sv.survey_id);
      renderSurveys();
    });
    if (!open) return [tr];
    const hist = el("tr", { class: "survey-history", "data-history": sv.survey_id },
      el("td", { colspan: 5 }, el("ol", {}, ...lines.map((l) => el("li", {}, l)))));
    return [tr, hist];
  }));
}
for (const sel of ["#survey-kind", "#survey-heading", "#survey-spacing", "#survey-z", "#survey-zmode", "#survey-speed"]) {
  $(sel).addEventListener("input", () => {
    if (sel === "#survey-kind" && draft) draft = null;  // another kind: draw it again
    showSurveyBar(); drawMap();
  });
}
$("#survey-cancel").addEventListener("click", () => { endSurvey(); drawMap(); });
$("#survey-send").addEventListener("click", async () => {
  let args;
  try { args = surveyArgs(); } catch (e) { toast(e.message, true); return; }
  if (!args) return;
  const r = await act("survey", args);
  if (r) { endSurvey(); drawMap(); return; }
  const box = $("#survey-error");  // refused before it was sent: say why, keep the drawing
  box.textContent = `not sent: ${act.lastError}`;
  box.classList.remove("hidden");
});

// ------------------------------------------------------------------ images
const cards = new Map();
function renderImages() {
  const g = $("#gallery");
  const im = S.images;
  if (!im) return;
  const p = im.progress;
  $("#img-progress").textContent = p ? `vehicle: ${p.pending ?? 0} pending, sending ${p.current ?? "–"}, next ${(p.next || []).join(", ") || "–"}, ${p.unacked_fragments ?? 0} fragments unacked` : "";
  if (im.items.length && g.querySelector(".empty")) g.replaceChildren();
  for (const it of im.items) {
    let c = cards.get(it.image_id);
    if (!c) { c = makeCard(it); cards.set(it.image_id, c); g.prepend(c.root); }
    updateCard(c, it);
  }
}
function makeCard(it) {
  const root = el("div", { class: "card", "data-image": it.image_id });
  const pic = el("div", { class: "nothumb" }, "waiting for data");
  const meta = el("div", { class: "meta" });
  const bar = el("div", { class: "bar" }, el("div", { style: "width:0%" }));
  const bytes = el("div", { class: "meta" });
  const kind = el("select", { title: "how much of this image to transfer" },
    ...[["fraction", "% of bytes"], ["layer", "up to layer"], ["full", "all of it"], ["skip", "skip it"]]
      .map(([k, t]) => el("option", { value: k }, t)));
  const val = el("input", { value: "50", title: "% of the bytes, or the quality layer" });
  kind.addEventListener("change", () => { val.disabled = kind.value === "full" || kind.value === "skip"; });
  root.addEventListener("click", (ev) => { if (!ev.target.closest(".goal")) openViewer(it.image_id); });
  const set = el("button", { title: "transfer this image up to the goal" }, "Goal");
  set.addEventListener("click", () => act("set_image_goal", { image_id: it.image_id, kind: kind.value, value: Number(val.value || 0) }));
  const wrap = el("div", { class: "thumbwrap" }, pic);
  const regions = document.createElementNS(SVG_NS, "svg");
  regions.setAttribute("class", "thumb-regions");
  regions.setAttribute("preserveAspectRatio", "xMidYMid meet");  // as the thumb's object-fit
  wrap.append(regions);
  root.append(wrap, meta, bar, bytes, el("div", { class: "goal" }, kind, val, set));
  return { root, pic, meta, bar, bytes, regions, thumb: null, regionSig: "" };
}
const SVG_NS = "http://www.w3.org/2000/svg";
const REGION_COLOUR = { requested: "#f0b443", waiting: "#4fb3ff", accepted: "#58c47c", rejected: "#ef5f5f" };
// the regions asked of an image, outlined on its card's thumbnail (in image pixels)
function drawThumbRegions(c, it) {
  const regs = it.regions || [];
  const sig = JSON.stringify([it.width, it.height, regs.map((r) => [r.box, r.state])]);
  if (sig === c.regionSig) return;
  c.regionSig = sig;
  c.regions.replaceChildren();
  if (!it.width || !it.height) return;
  c.regions.setAttribute("viewBox", `0 0 ${it.width} ${it.height}`);
  for (const r of regs) {
    const [x0, y0, x1, y1] = r.box;
    const rect = document.createElementNS(SVG_NS, "rect");
    for (const [k, v] of [["x", x0], ["y", y0], ["width", x1 - x0], ["height", y1 - y0],
      ["fill", "none"], ["stroke", REGION_COLOUR[r.state] || "#f0b443"], ["stroke-width", 1.5],
      ["vector-effect", "non-scaling-stroke"], ["stroke-dasharray", r.state === "accepted" ? "" : "4 2"]]) rect.setAttribute(k, v);
    const title = document.createElementNS(SVG_NS, "title");
    title.textContent = `region ${x0}..${x1} × ${y0}..${y1}: ${regionState(r)}`;
    rect.append(title);
    c.regions.append(rect);
  }
}
function updateCard(c, it) {
  if (it.thumb && it.thumb !== c.thumb) {
    const img = el("img", { class: "thumb", src: withVehicle(it.thumb), alt: `image ${it.image_id}` });
    c.pic.replaceWith(img); c.pic = img; c.thumb = it.thumb;
  }
  const pos = it.x !== null && it.x !== undefined ? ` · (${Number(it.x).toFixed(0)}, ${Number(it.y).toFixed(0)})` : "";
  c.meta.textContent = `#${it.image_id} · ${fmtT(it.t)}${pos}${it.width ? ` · ${it.width}×${it.height}` : ""}`;
  const f = it.fraction ?? 0;
  c.bar.firstChild.style.width = `${Math.min(100, 100 * f).toFixed(1)}%`;
  const goal = it.goal ? ` · goal ${it.goal.kind.toLowerCase()}${it.goal.value ? " " + it.goal.value : ""}` : "";
  c.bytes.textContent = `${fmtBytes(it.bytes_received)} / ${fmtBytes(it.total_bytes)}${goal}`;
  c.root.classList.toggle("current", S.images.progress && S.images.progress.current === it.image_id);
  const answered = answeredBy().get(it.image_id);
  c.root.classList.toggle("answer", !!answered);
  c.root.title = answered ? `answers: ${answered}` : "click to open full size";
  drawThumbRegions(c, it);
  if (viewer.id === it.image_id) showViewer();
}
// image id -> the by-time request it answered (the newest)
function answeredBy() {
  const out = new Map();
  for (const c of S.commands || []) if (c.image_id !== null && c.image_id !== undefined && !out.has(c.image_id)) out.set(c.image_id, c.summary);
  return out;
}

// ------------------------------------------------------------------ full-size viewer
const viewer = { id: null, fit: true };
function openViewer(id) {
  if (viewer.id !== id) endRegion();
  viewer.id = id; showViewer();
}
function closeViewer() { viewer.id = null; endRegion(); $("#viewer").classList.add("hidden"); }
function showViewer() {
  const it = S.images && S.images.items.find((i) => i.image_id === viewer.id);
  if (!it) return;
  $("#viewer").classList.remove("hidden");
  const img = $("#viewer-img");
  if (it.full && img.dataset.src !== it.full) { img.src = withVehicle(it.full); img.dataset.src = it.full; }
  img.classList.toggle("hidden", !it.full);
  $("#viewer-none").classList.toggle("hidden", !!it.full);
  img.classList.toggle("fit", viewer.fit);
  $("#viewer-zoom").textContent = viewer.fit ? "100 %" : "fit";
  const pos = it.x !== null && it.x !== undefined ? `(${Number(it.x).toFixed(1)}, ${Number(it.y).toFixed(1)}) m` : "–";
  const fp = it.footprint ? `about ${it.footprint[0].toFixed(1)} × ${it.footprint[1].toFixed(1)} m of seafloor` : "–";
  const layers = it.layers ? `${it.layers_complete ?? 0} of ${it.layers} complete` : "–";
  const goal = it.goal ? `${it.goal.kind.toLowerCase()}${it.goal.value ? " " + it.goal.value : ""}` : "default";
  const rows = [["image", `#${it.image_id}`], ["taken", fmtT(it.t)], ["position", pos],
    ["footprint", fp], ["size", it.width ? `${it.width} × ${it.height} px` : "–"],
    ["bytes", `${fmtBytes(it.bytes_received)} of ${fmtBytes(it.total_bytes)}${it.fraction !== null && it.fraction !== undefined ? ` (${(100 * it.fraction).toFixed(1)} %)` : ""}`],
    ["decoded from", it.bytes_used !== undefined && it.bytes_used !== null ? `${fmtBytes(it.bytes_used)} in ${it.packets_used} of ${it.packets} packets` : "–"],
    ["quality layers", layers], ["goal", goal]];
  const ans = answeredBy().get(it.image_id);
  if (ans) rows.push(["answers", ans]);
  $("#viewer-meta").replaceChildren(...rows.map(([k, v]) => el("tr", {}, el("th", {}, k), el("td", {}, v))));
  $("#viewer-title").textContent = `Image #${it.image_id} · ${fmtT(it.t)}${it.complete ? " · complete" : ""}`;
  showRegionTool(it);
  placeOverlay();
}
$("#viewer-close").addEventListener("click", closeViewer);
$("#viewer").addEventListener("click", (ev) => {
  // a drag that ends outside the box is not a click on the backdrop
  if (ev.target.id === "viewer" && performance.now() - region.dragEnd > 400) closeViewer();
});
$("#viewer-zoom").addEventListener("click", () => { viewer.fit = !viewer.fit; showViewer(); });
$("#viewer-img").addEventListener("load", placeOverlay);
window.addEventListener("resize", () => { if (viewer.id !== null) placeOverlay(); });

// ------------------------------------------------------------------ image regions
// The Region tool of the viewer: drag a rectangle on the picture (screen pixels mapped to
// image pixels whatever the zoom), choose a goal and ask for it (action image_region). The
// regions asked are outlined on the picture with their state, and listed with the reason of a
// refusal and the quality layers reached inside them.
const region = { drawing: false, draft: null, start: null, dragEnd: -1e9 };
const REGION_UNIT = { quality: "dB", bytes: "bytes", layer: "layers" };
function viewerItem() { return S.images && S.images.items.find((i) => i.image_id === viewer.id); }
function regionState(r) {
  let s = r.state;
  // served as a crop: the parent's layers say little about the region (the crop is coded to the goal)
  if (r.served === "crop" && r.crop && r.state !== "rejected")
    return s + (r.crop.complete ? " · crop" : " · crop arriving");
  if (r.layers_complete !== null && r.layers_complete !== undefined && r.state !== "rejected")
    s += ` · ${r.layers_complete} of ${r.layers ?? "?"} layers`;
  return s;
}
function regionGoal(r) {
  return r.kind === "quality" ? `${r.value} dB` : r.kind === "bytes" ? `${r.value} bytes` : `${r.value} layers`;
}
function endRegion() {
  region.drawing = false; region.draft = null; region.start = null;
  $("#region-draw").classList.remove("on");
  $("#viewer-stage").classList.remove("drawing");
  $("#region-error").classList.add("hidden");
}
// where the picture is drawn inside its <img> box (object-fit: contain leaves bars around it)
function pictureRect() {
  const img = $("#viewer-img");
  const nw = img.naturalWidth, nh = img.naturalHeight;
  if (!nw || !nh || img.classList.contains("hidden")) return null;
  const bw = img.clientWidth, bh = img.clientHeight;
  const k = viewer.fit ? Math.min(bw / nw, bh / nh) : 1;
  return { left: img.offsetLeft + (bw - nw * k) / 2, top: img.offsetTop + (bh - nh * k) / 2,
    width: nw * k, height: nh * k };
}
function placeOverlay() {
  const ov = $("#viewer-overlay");
  const r = pictureRect();
  const it = viewerItem();
  if (!r || !it || !it.width) { ov.classList.add("hidden"); return; }
  ov.classList.remove("hidden");
  Object.assign(ov.style, { left: `${r.left}px`, top: `${r.top}px`, width: `${r.width}px`, height: `${r.height}px` });
  drawViewerRegions(it);
}
// an event's position in image pixels (clamped to the image)
function imagePixel(ev) {
  const it = viewerItem();
  const b = $("#viewer-overlay").getBoundingClientRect();
  const cl = (v, hi) => Math.max(0, Math.min(hi, v));
  return [cl(Math.round((ev.clientX - b.left) / b.width * it.width), it.width),
    cl(Math.round((ev.clientY - b.top) / b.height * it.height), it.height)];
}
function pct(v, of) { return `${(100 * v / of).toFixed(3)}%`; }
function drawViewerRegions(it) {
  const ov = $("#viewer-overlay");
  const W = it.width, H = it.height;
  const boxes = [], labels = [];
  (it.regions || []).forEach((r, k) => {
    const [x0, y0, x1, y1] = r.box;
    const d = el("div", { class: `iregion st-${r.state}`, "data-region": k + 1, "data-state": r.state,
      title: `${x0}..${x1} × ${y0}..${y1} px to ${regionGoal(r)}: ${regionState(r)}${r.reason ? ` (${r.reason})` : ""}` });
    Object.assign(d.style, { left: pct(x0, W), top: pct(y0, H), width: pct(x1 - x0, W), height: pct(y1 - y0, H) });
    boxes.push(d);
    labels.push([el("span", { class: `iregion-label st-${r.state}` }, `${k + 1} · ${regionState(r)}`), r.box]);
  });
  if (region.draft) {
    const [x0, y0, x1, y1] = region.draft;
    const d = el("div", { class: "iregion draft" });
    Object.assign(d.style, { left: pct(x0, W), top: pct(y0, H), width: pct(x1 - x0, W), height: pct(y1 - y0, H) });
    boxes.push(d);
    labels.push([el("span", { class: "iregion-label" }, `${x1 - x0} × ${y1 - y0} px`), region.draft]);
  }
  ov.replaceChildren(...boxes);
  // labels clear of one another: above the box, inside its top, under it, inside its bottom;
  // a label with no free spot keeps only its number (the list beside says the rest)
  const sx = ov.clientWidth / W, sy = ov.clientHeight / H;
  const placed = [];
  const free = (a) => a.x >= 0 && a.y >= 0 && a.x + a.w <= ov.clientWidth + 1 && a.y + a.h <= ov.clientHeight + 1
    && placed.every((b) => a.x + a.w <= b.x || b.x + b.w <= a.x || a.y + a.h <= b.y || b.y + b.h <= a.y);
  for (const [lab, [x0, y0, x1, y1]] of labels.reverse()) {  // the newest first
    ov.append(lab);
    const tryAt = () => {
      const w = lab.offsetWidth, h = lab.offsetHeight;
      const left = Math.min(x0 * sx, ov.clientWidth - w);
      for (const y of [y0 * sy - h - 1, y0 * sy + 2, y1 * sy + 1, y1 * sy - h - 2]) {
        const a = { x: Math.max(0, left), y, w, h };
        if (free(a)) return a;
      }
      return null;
    };
    let at = tryAt();
    if (!at && lab.textContent.includes(" · ")) {
      lab.textContent = lab.textContent.split(" · ")[0];
      at = tryAt();
    }
    if (!at) { lab.remove(); continue; }
    placed.push(at);
    Object.assign(lab.style, { left: `${at.x}px`, top: `${at.y}px` });
  }
}
function showRegionTool(it) {
  const off = it.precincts === 0;
  const viewerOnly = !ME.may_command;
  $("#region-off").classList.toggle("hidden", !off && !viewerOnly);
  $("#region-off").textContent = off
    ? "This image was coded without precincts: a region of it cannot be sent on its own. Ask for more of the whole image instead (Get all of it, or a goal on its card)."
    : viewerOnly ? "Viewers cannot ask for regions." : "";
  $("#region-form").classList.toggle("hidden", off || viewerOnly);
  if (off || viewerOnly) endRegion();
  const d = region.draft;
  $("#region-box").textContent = d ? `x ${d[0]}..${d[2]}, y ${d[1]}..${d[3]} (${d[2] - d[0]} × ${d[3] - d[1]} px)`
    : region.drawing ? "drag a rectangle on the picture" : "no rectangle yet";
  $("#region-send").disabled = !d || off || viewerOnly;
  const regs = it.regions || [];
  $("#region-list").replaceChildren(...regs.map((r, k) => {
    const [x0, y0, x1, y1] = r.box;
    const li = el("li", { "data-state": r.state, value: k + 1, "data-served": r.served || "" },
      `${x0}..${x1} × ${y0}..${y1} px to ${regionGoal(r)}: `, el("b", { class: `st-${r.state}` }, regionState(r)));
    if (r.reason) li.append(el("span", { class: "why" }, r.reason));
    const c = r.crop;
    if (r.served === "crop" && c) {
      // served as a crop: the region coded on its own, pasted over the picture; shown here too
      const bytes = `${fmtBytes(c.held_bytes)} of ${fmtBytes(c.total_bytes)}`;
      li.append(el("span", { class: "served" }, `crop ${c.width} × ${c.height} px · ${bytes}`
        + (c.complete ? "" : " so far") + (c.shown ? " · shown over the picture" : " · the picture is as good there")));
      if (c.png) li.append(el("img", { class: "region-crop", src: withVehicle(c.png), alt: `crop of region ${k + 1}`,
        title: `what the crop shows of ${x0}..${x1} × ${y0}..${y1} px (${bytes})` }));
    } else if (r.served === "packets") {
      li.append(el("span", { class: "served" }, `the picture's own packets · ${fmtBytes(r.bytes ?? 0)}`));
    }
    return li;
  }));
}
$("#region-draw").addEventListener("click", () => {
  region.drawing = !region.drawing;
  $("#region-draw").classList.toggle("on", region.drawing);
  $("#viewer-stage").classList.toggle("drawing", region.drawing);
  const it = viewerItem();
  if (it) showRegionTool(it);
});
$("#region-cancel").addEventListener("click", () => { endRegion(); const it = viewerItem(); if (it) { showRegionTool(it); placeOverlay(); } });
$("#region-kind").addEventListener("change", () => {
  const k = $("#region-kind").value, it = viewerItem();
  $("#region-unit").textContent = REGION_UNIT[k];
  $("#region-value").value = k === "quality" ? "30" : k === "bytes" ? "2000"
    : String(Math.min(it && it.layers ? it.layers : 1, ((it && it.layers_complete) || 0) + 3));
});
{
  // on the whole stage: a drag may start in the bars beside the picture (clamped to its edge)
  const ov = $("#viewer-stage");
  ov.addEventListener("pointerdown", (ev) => {
    if (!region.drawing || ev.button !== 0) return;
    ev.preventDefault();
    ov.setPointerCapture(ev.pointerId);
    region.start = imagePixel(ev);
    region.draft = null;
  });
  ov.addEventListener("pointermove", (ev) => {
    if (!region.start) return;
    const [a, b] = region.start, [c, d] = imagePixel(ev);
    region.draft = [Math.min(a, c), Math.min(b, d), Math.max(a, c), Math.max(b, d)];
    const it = viewerItem();
    if (it) drawViewerRegions(it);
  });
  ov.addEventListener("pointerup", (ev) => {
    if (!region.start) return;
    region.start = null;
    region.dragEnd = performance.now();
    const d = region.draft;
    if (d && (d[2] - d[0] < 1 || d[3] - d[1] < 1)) region.draft = null;  // a click, not a drag
    const it = viewerItem();
    if (it) { showRegionTool(it); drawViewerRegions(it); }
  });
}
$("#region-send").addEventListener("click", async () => {
  const it = viewerItem(), d = region.draft;
  if (!it || !d) return;
  const value = Number($("#region-value").value);
  const r = await act("image_region", { image_id: it.image_id, x0: d[0], y0: d[1], x1: d[2], y1: d[3],
    kind: $("#region-kind").value, value });
  if (r) { endRegion(); showRegionTool(it); placeOverlay(); return; }
  const box = $("#region-error");  // refused before it was sent: say why, keep the rectangle
  box.textContent = `not sent: ${act.lastError}`;
  box.classList.remove("hidden");
});
$("#viewer-full").addEventListener("click", () => { if (viewer.id !== null) act("set_image_goal", { image_id: viewer.id, kind: "full", value: 0 }); });
window.addEventListener("keydown", (ev) => { if (ev.key === "Escape" && viewer.id !== null) closeViewer(); });
for (const b of document.querySelectorAll(".img-time-btn")) {
  b.addEventListener("click", () => {
    let t;
    try { t = parseTime($("#img-time").value); } catch (e) { toast(String(e.message), true); return; }
    act("image_by_time", { t, direction: b.dataset.dir });
  });
}

// ------------------------------------------------------------------ time series
const plots = new Map();
let seriesSel = null;  // {channel, t0, t1}
function renderSeries() {
  const box = $("#series");
  const sr = S.series;
  if (!sr) return;
  if (sr.channels.length && box.querySelector(".empty")) box.replaceChildren();
  for (const ch of sr.channels) {
    let p = plots.get(ch.channel);
    if (!p) { p = makePlot(ch.channel); plots.set(ch.channel, p); box.append(p.root); }
    p.data = ch;
    drawPlot(p);
  }
}
function makePlot(channel) {
  const title = el("div", { class: "title" });
  const cv = el("canvas", { width: 600, height: 140, "data-channel": channel });
  const root = el("div", { class: "plot" }, title, cv);
  const p = { root, title, cv, data: null, range: null };
  let down = null;
  cv.addEventListener("mousedown", (ev) => { const t = plotT(p, ev); if (t !== null) { down = t; seriesSel = { channel, t0: t, t1: t }; drawAllPlots(); } });
  cv.addEventListener("mousemove", (ev) => { if (down === null) return; const t = plotT(p, ev); if (t !== null) { seriesSel.t1 = t; drawAllPlots(); } });
  window.addEventListener("mouseup", () => {
    if (down === null) return;
    down = null;
    if (seriesSel && Math.abs(seriesSel.t1 - seriesSel.t0) < 1e-6) seriesSel = null;
    $("#series-refine").disabled = !seriesSel;
    drawAllPlots();
  });
  return p;
}
function plotT(p, ev) {
  if (!p.range) return null;
  const r = p.cv.getBoundingClientRect();
  const px = ((ev.clientX - r.left) / r.width) * p.cv.width;
  const f = Math.min(1, Math.max(0, (px - SERIES_L) / (p.cv.width - SERIES_L - 6)));
  return p.range[0] + f * (p.range[1] - p.range[0]);
}
const SERIES_L = 48;
// A channel is stale when its newest sample is older than a few TDMA cycles.
function staleAfter() {
  const sch = S.link && S.link.schedules && S.link.schedules[0];
  return Math.max(120, 3 * (sch && sch.cycle > 0 ? sch.cycle : 60));
}
function drawAllPlots() { for (const p of plots.values()) drawPlot(p); }
function drawPlot(p) {
  const cv = p.cv, c = cv.getContext("2d"), ch = p.data;
  const rect = cv.getBoundingClientRect();
  if (rect.width > 50 && cv.width !== Math.round(rect.width)) cv.width = Math.round(rect.width);
  const W = cv.width, H = cv.height;
  c.fillStyle = "#0a1016"; c.fillRect(0, 0, W, H);
  const unit = ch.unit ? ` [${ch.unit}]` : "";
  const err = ch.max_error !== null && ch.max_error !== undefined ? ` · max error ±${Number(ch.max_error).toPrecision(3)}` : "";
  p.title.innerHTML = "";
  p.title.append(el("b", {}, ch.name || `channel ${ch.channel}`), `${unit} · ${ch.samples || 0} samples${err}`);
  p.root.removeAttribute("data-stale");
  if (!ch.t || !ch.t.length) { p.range = null; return; }
  const t = ch.t, v = ch.v, e = ch.err;
  let t0 = t[0], t1 = t[t.length - 1];
  const age = S.now - t1;
  if (age > staleAfter()) {
    const words = `no new samples for ${fmtAge(age)} (newest ${fmtT(t1)})`;
    p.title.append(" ", el("span", { class: "stale" }, words));
    p.root.dataset.stale = words;
  }
  if (t1 <= t0) t1 = t0 + 1;
  let lo = Infinity, hi = -Infinity;
  for (let i = 0; i < v.length; i++) {
    const ei = e[i] > 0 ? e[i] : 0;
    lo = Math.min(lo, v[i] - ei); hi = Math.max(hi, v[i] + ei);
  }
  if (hi <= lo) { hi = lo + 1; }
  const padY = (hi - lo) * 0.08; lo -= padY; hi += padY;
  p.range = [t0, t1];
  const [X, Y] = plotAxes(c, W, H, t0, t1, lo, hi, { left: SERIES_L, ylabel: ch.unit || "" });
  const top = 14, bot = H - 26;
  // pending refinement requests
  for (const r of (S.series.requests || []).filter((q) => q.channel === ch.channel)) {
    c.fillStyle = "rgba(240,180,67,0.12)";
    c.fillRect(X(r.start), top, Math.max(2, X(r.end) - X(r.start)), bot - top);
  }
  // error band
  c.fillStyle = "rgba(79,179,255,0.25)";
  c.beginPath();
  const flush = (from, to) => {
    if (to <= from) return;
    c.moveTo(X(t[from]), Y(v[from] + e[from]));
    for (let i = from; i < to; i++) c.lineTo(X(t[i]), Y(v[i] + e[i]));
    for (let i = to - 1; i >= from; i--) c.lineTo(X(t[i]), Y(v[i] - e[i]));
    c.closePath();
  };
  let start = 0;
  for (let i = 0; i <= t.length; i++) {
    const ok = i < t.length && e[i] >= 0 && (i === start || t[i] - t[i - 1] < (t1 - t0) / 50);
    if (!ok) { flush(start, i); start = i + (i < t.length && e[i] < 0 ? 1 : 0); }
  }
  c.fill();
  c.strokeStyle = "#dce6ee"; c.lineWidth = 1;
  c.beginPath();
  for (let i = 0; i < t.length; i++) {
    const gap = i > 0 && t[i] - t[i - 1] > (t1 - t0) / 50;
    if (i === 0 || gap) c.moveTo(X(t[i]), Y(v[i])); else c.lineTo(X(t[i]), Y(v[i]));
  }
  c.stroke();
  if (seriesSel && seriesSel.channel === ch.channel) {
    const a = X(Math.min(seriesSel.t0, seriesSel.t1)), b = X(Math.max(seriesSel.t0, seriesSel.t1));
    c.fillStyle = "rgba(79,179,255,0.2)"; c.fillRect(a, top, b - a, bot - top);
    c.strokeStyle = "#4fb3ff"; c.strokeRect(a, top, b - a, bot - top);
  }
}
$("#series-refine").addEventListener("click", async () => {
  if (!seriesSel) return;
  const txt = $("#series-err").value.trim();
  const args = { channel: seriesSel.channel, start: Math.min(seriesSel.t0, seriesSel.t1),
    end: Math.max(seriesSel.t0, seriesSel.t1) };
  if (txt) args.max_error = Number(txt);
  const r = await act("refine_series", args);
  if (r) { seriesSel = null; $("#series-refine").disabled = true; drawAllPlots(); }
});

// ------------------------------------------------------------------ link & queues
function renderLink() {
  const L = S.link;
  if (!L) return;
  const box = $("#tdma");
  box.replaceChildren();
  for (const sch of L.schedules) {
    const h = sch.proposed ? 46 : 28;
    const cv = el("canvas", { width: 560, height: h, "data-link": sch.link });
    cv.style.height = `${h}px`;  // drawn at its natural aspect: one canvas pixel a CSS pixel
    box.append(cv);
  }
  drawTdma();
  const tb = $("#links-table tbody");
  tb.replaceChildren();
  for (const lk of L.links) {
    const state = lk.enabled ? (lk.muted ? "muted" : "enabled") : "disabled";
    const btn = el("button", {}, lk.enabled ? "Disable" : "Enable");
    btn.addEventListener("click", () => act("link_control", { link: lk.link, enabled: !lk.enabled }));
    // spare traffic (re-sends, refinements, redundant copies): the operator's energy lever
    const spare = el("select", { title: "spare traffic: share of each packet (0 = off)", "data-spare-link": lk.link },
      ...[["", "spare…"], ["100", "spare 100 %"], ["50", "spare 50 %"], ["25", "spare 25 %"], ["0", "spare off"]]
        .map(([v, t]) => el("option", { value: v }, t)));
    spare.addEventListener("change", () => {
      if (spare.value !== "") act("spare_config", { link: lk.link, percent: Number(spare.value) });
    });
    // every counter in words: a non-expert reads the row, no tooltip needed
    const heard = lk.packets ? `${lk.packets} packets heard (${lk.frames} frames)` : "no modem report yet";
    const ours = [];
    if (lk.sent_packets !== undefined) ours.push(`topside sent ${lk.sent_packets} packets`);
    if (lk.frames_rx !== undefined) ours.push(`decoded ${lk.frames_rx} frames`);
    const bad = lk.bad_frames + (lk.local_bad || 0);
    const pct = lk.frames ? ` (${((100 * lk.bad_frames) / lk.frames).toFixed(0)} % of frames heard)` : "";
    const badWords = bad ? `${lk.bad_frames} frames garbled${pct}` + (lk.local_bad ? `, ${lk.local_bad} topside could not decode` : "")
      : "none garbled";
    const rate = lastRate(lk);
    tb.append(el("tr", { "data-link": lk.link }, el("td", {}, lk.link),
      el("td", { class: lk.enabled ? "on" : "off" }, state, ...modemWords(lk)),
      el("td", { class: "words" }, lk.snr === null || lk.snr === undefined ? "–" : `${Number(lk.snr).toFixed(1)} dB`,
        el("div", { class: "expl" }, snrWords(lk.snr))),
      el("td", { class: "words", "data-col": "frames" }, heard, ours.length ? el("div", { class: "expl" }, ours.join(", ")) : "",
        rate ? el("div", { class: "expl" }, rate) : ""),
      el("td", { class: "words", "data-col": "bad" }, badWords),
      el("td", {}, fmtAge(lk.last_heard !== null && lk.last_heard !== undefined ? S.now - lk.last_heard : lk.age)),
      el("td", {}, btn, " ", spare)));
  }
  renderLinkPlots();
  const sl = $("#sched-slots");
  if (!sl.value && L.schedules.length) {
    sl.value = L.schedules[0].slots.map((s) => `${s.owner}:${s.duration}:${s.guard}`).join(", ");
    $("#sched-link").value = L.schedules[0].link;
  }
}
// the modems' outages: topside's own (being reopened, or back) and the vehicle's (its LinkHealth)
function modemWords(lk) {
  const out = [];
  const own = lk.topside_modem;
  if (own && !own.up) out.push(el("div", { class: "expl bad", "data-modem": "topside", title: own.last_error || "" },
    `topside modem DOWN for ${fmtSecs(own.last_down)}: reopening it`),
    el("div", { class: "expl clip", title: own.last_error || "" }, own.last_error || "no answer"));
  else if (own && own.outages) out.push(el("div", { class: "expl", "data-modem": "topside" },
    `topside modem: ${own.outages} outage${own.outages === 1 ? "" : "s"}, ${fmtSecs(own.down_total)} down in all`));
  const veh = lk.vehicle_modem;
  if (veh && !veh.up) out.push(el("div", { class: "expl bad", "data-modem": "vehicle" },
    `vehicle modem DOWN (outage ${veh.outages}, reported over another link)`));
  else if (veh && veh.outages) out.push(el("div", { class: "expl", "data-modem": "vehicle" },
    `vehicle modem: ${veh.outages} outage${veh.outages === 1 ? "" : "s"}, last ${fmtSecs(veh.last_down)}, ${fmtSecs(veh.down_total)} down in all`));
  return out;
}
function fmtSecs(s) {
  s = Math.max(0, Math.round(Number(s) || 0));
  if (s < 60) return `${s} s`;
  if (s < 3600) return s % 60 ? `${Math.floor(s / 60)} min ${s % 60} s` : `${Math.floor(s / 60)} min`;
  return `${Math.floor(s / 3600)} h ${Math.floor((s % 3600) / 60)} min`;
}
function snrWords(snr) {
  if (snr === null || snr === undefined) return "signal strength: not reported";
  if (snr >= 15) return "strong signal";
  if (snr >= 8) return "good signal";
  if (snr >= 3) return "weak signal: expect lost frames";
  return "very weak: most frames will be lost";
}
// bytes received in the last complete cycle, in words
function lastRate(lk) {
  const th = lk.throughput || [];
  const done = th.filter((b) => b[0] + b[2] <= S.now);
  if (!done.length) return "";
  const b = done[done.length - 1];
  return `last cycle: ${fmtBytes(b[1])} received in ${b[2]} s (${(b[1] / b[2]).toFixed(0)} B/s)`;
}
// ---- small plots against dive time (canvas, no library)
function fmtDive(s, step) {
  s = Math.round(s);
  const sign = s < 0 ? "-" : ""; s = Math.abs(s);
  if (step >= 60 && s % 60 === 0) {
    const mins = s / 60;
    return mins >= 60 ? `${sign}${Math.floor(mins / 60)} h ${pad(mins % 60)}` : `${sign}${mins} min`;
  }
  return `${sign}${Math.floor(s / 60)}:${pad(s % 60)}`;
}
function timeStep(span, n) {
  const steps = [5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600, 7200, 14400];
  for (const st of steps) if (span / st <= n) return st;
  return steps[steps.length - 1];
}
// Axes for a plot of [t0, t1] (absolute seconds, labelled in dive time) by [lo, hi]; returns X, Y.
function plotAxes(c, W, H, t0, t1, lo, hi, opts = {}) {
  const L = opts.left || 40, R = 6, T = 14, B = 26;
  const X = (t) => L + ((t - t0) / (t1 - t0 || 1)) * (W - L - R);
  const Y = (y) => H - B - ((y - lo) / (hi - lo || 1)) * (H - B - T);
  const d0 = diveStart() ?? t0;
  c.strokeStyle = "#2a3a48"; c.lineWidth = 1; c.fillStyle = "#8aa0b2"; c.font = "10px system-ui";
  c.beginPath(); c.moveTo(L, T); c.lineTo(L, H - B); c.lineTo(W - R, H - B); c.stroke();
  const st = timeStep(t1 - t0, Math.max(2, Math.floor((W - L) / 70)));
  c.textAlign = "center";
  const xt = [];
  for (let k = Math.ceil((t0 - d0) / st) * st; d0 + k <= t1 + 1e-6; k += st) {
    const x = X(d0 + k);
    c.beginPath(); c.moveTo(x, H - B); c.lineTo(x, H - B + 3); c.stroke();
    c.textAlign = x > W - 24 ? "right" : "center";
    c.fillText(fmtDive(k, st), x > W - 24 ? W - 2 : x, H - B + 12);
    xt.push(fmtDive(k, st));
  }
  // what was drawn, for tests and the curious
  c.canvas.dataset.xticks = JSON.stringify(xt);
  c.canvas.dataset.xlabel = opts.xlabel || "dive time";
  c.canvas.dataset.ylabel = opts.ylabel || "";
  c.textAlign = "center";
  c.fillText(opts.xlabel || "dive time", L + (W - L - R) / 2, H - 2);
  let ys = niceStep((hi - lo) / 4);
  if (Math.floor(hi / ys) - Math.ceil(lo / ys) < 2) ys = niceStep((hi - lo) / 8);
  c.textAlign = "right";
  for (let y = Math.ceil(lo / ys) * ys; y <= hi + 1e-9; y += ys) {
    c.beginPath(); c.moveTo(L - 3, Y(y)); c.lineTo(L, Y(y)); c.stroke();
    c.fillText(Number(y.toPrecision(4)).toString(), L - 4, Y(y) + 3);
  }
  c.textAlign = "left";
  c.fillText(opts.ylabel || "", 2, 10);
  return [X, Y];
}
function renderLinkPlots() {
  const box = $("#link-plots");
  const links = (S.link && S.link.links) || [];
  const have = links.filter((lk) => (lk.history && lk.history.length) || (lk.throughput && lk.throughput.length));
  box.classList.toggle("hidden", !have.length);
  for (const lk of have) {
    let p = box.querySelector(`[data-plots-link="${lk.link}"]`);
    if (!p) {
      p = el("div", { class: "link-plots", "data-plots-link": lk.link },
        el("div", { class: "ptitle" }, `link ${lk.link}: bytes received from the vehicle per TDMA cycle`),
        el("canvas", { class: "tput", width: 560, height: 110, "data-plot": "throughput" }),
        el("div", { class: "ptitle" }, `link ${lk.link}: signal-to-noise ratio of each packet heard (higher is better; red ticks: garbled frames)`),
        el("canvas", { class: "snr", width: 560, height: 110, "data-plot": "snr" }));
      box.append(p);
    }
    p.lk = lk;
  }
  drawLinkPlots();
}
function drawLinkPlots() {
  for (const p of document.querySelectorAll("#link-plots .link-plots")) {
    const lk = p.lk; if (!lk) continue;
    const hist = (lk.history || []).slice().sort((a, b) => a[0] - b[0]), th = lk.throughput || [];
    const d0 = diveStart();
    let t0 = Infinity, t1 = -Infinity;
    for (const h of hist) { t0 = Math.min(t0, h[0]); t1 = Math.max(t1, h[0]); }
    for (const b of th) { t0 = Math.min(t0, b[0]); t1 = Math.max(t1, b[0] + b[2]); }
    if (d0 !== null) t0 = Math.min(t0, d0);
    t1 = Math.max(t1, S.now);
    if (!isFinite(t0)) continue;
    if (t1 - t0 < 60) t0 = t1 - 60;
    for (const cv of p.querySelectorAll("canvas")) {
      const rect = cv.getBoundingClientRect();
      if (rect.width > 50 && cv.width !== Math.round(rect.width)) cv.width = Math.round(rect.width);
      const c = cv.getContext("2d"), W = cv.width, H = cv.height;
      c.fillStyle = "#0a1016"; c.fillRect(0, 0, W, H);
      if (cv.dataset.plot === "throughput") {
        const hi = Math.max(10, ...th.map((b) => b[1])) * 1.1;
        const [X, Y] = plotAxes(c, W, H, t0, t1, 0, hi, { ylabel: "bytes / cycle" });
        for (const b of th) {
          const open = b[0] + b[2] > S.now;
          c.fillStyle = open ? "rgba(79,179,255,0.4)" : "#4fb3ff";
          c.fillRect(X(b[0]) + 0.5, Y(b[1]), Math.max(1, X(b[0] + b[2]) - X(b[0]) - 1), Y(0) - Y(b[1]));
        }
        if (!th.length) { c.fillStyle = "#8aa0b2"; c.fillText("nothing received yet", 50, H / 2); }
      } else {
        const vals = hist.map((h) => h[1]).filter((v) => v !== null);
        const lo = Math.min(0, ...vals), hi = Math.max(20, ...vals) + 2;
        const [X, Y] = plotAxes(c, W, H, t0, t1, lo, hi, { ylabel: "SNR (dB)" });
        c.strokeStyle = "#58c47c"; c.fillStyle = "#58c47c"; c.lineWidth = 1.2; c.beginPath();
        let first = true;
        for (const h of hist) {
          if (h[1] === null) { first = true; continue; }
          if (first) c.moveTo(X(h[0]), Y(h[1])); else c.lineTo(X(h[0]), Y(h[1]));
          first = false;
        }
        c.stroke();
        for (const h of hist) {
          if (h[1] !== null) c.fillRect(X(h[0]) - 1.5, Y(h[1]) - 1.5, 3, 3);
          if (h[3] > 0) { c.fillStyle = "#ef5f5f"; c.fillRect(X(h[0]) - 1, Y(lo) - 8, 2, 8); c.fillStyle = "#58c47c"; }
        }
      }
    }
  }
}
// a TDMA slot's owner: "top" for topside, the vehicle's name in a fleet console, else "veh"
function slotOwner(owner, L) {
  if (owner === L.node_id) return "top";
  const v = S.fleet && S.fleet.vehicles.find((x) => x.id === owner);
  return v ? v.name : "veh";
}
function drawTdma() {
  const L = S.link;
  if (!L) return;
  for (const cv of document.querySelectorAll("#tdma canvas")) {
    const sch = L.schedules.find((s) => String(s.link) === cv.dataset.link);
    if (!sch) continue;
    const rect = cv.getBoundingClientRect();
    if (rect.width > 50 && cv.width !== Math.round(rect.width)) cv.width = Math.round(rect.width);
    const c = cv.getContext("2d"), W = cv.width, LW = 96;
    c.fillStyle = "#0a1016"; c.fillRect(0, 0, W, cv.height);
    const row = (slots, y, h, label) => {
      const total = slots.reduce((a, s) => a + s.duration, 0) || 1;
      let x = LW;
      c.fillStyle = "#8aa0b2"; c.font = "10px system-ui"; c.fillText(label, 2, y + h);
      slots.forEach((s, i) => {
        const w = ((W - LW - 2) * s.duration) / total;
        const col = s.owner === L.node_id ? "#4fb3ff" : s.owner === L.vehicle_id ? "#f28f3b" : "#889";
        c.fillStyle = col; c.globalAlpha = 0.75; c.fillRect(x + 1, y, w - 2, h);
        c.globalAlpha = 1; c.fillStyle = "rgba(0,0,0,0.45)";
        const gw = ((W - LW - 2) * s.guard) / total; c.fillRect(x + w - 1 - gw, y, gw, h);
        c.fillStyle = "#05090d"; c.fillText(`${i}:${slotOwner(s.owner, L)}`, x + 4, y + h - 5);
        x += w;
      });
      return total;
    };
    const total = row(sch.slots, 2, 22, `link ${sch.link} v${sch.active_version}`);
    if (sch.cycle > 0) {
      const since = S.now - sch.epoch;
      const pos = ((since % sch.cycle) + sch.cycle) % sch.cycle;
      const x = LW + ((W - LW - 2) * pos) / total;
      c.strokeStyle = "#fff"; c.lineWidth = 2; c.beginPath(); c.moveTo(x, 0); c.lineTo(x, 26); c.stroke();
      c.fillStyle = "#dce6ee";
      c.fillText(`cycle ${(sch.first_cycle + Math.floor(since / sch.cycle)) % 65536}`, 2, 10);
    }
    if (sch.proposed) {
      row(sch.proposed.slots, 28, 16, `v${sch.proposed.version} ${sch.proposed.status}`);
    }
  }
}
$("#sched-send").addEventListener("click", () => {
  const slots = [];
  for (const part of $("#sched-slots").value.split(",")) {
    const f = part.trim().split(":").map(Number);
    if (!part.trim()) continue;
    if (f.length < 2 || f.some((x) => !isFinite(x))) { toast(`bad slot "${part.trim()}" (owner:seconds:guard)`, true); return; }
    slots.push({ owner: f[0], duration: f[1], guard: f[2] || 0 });
  }
  act("propose_schedule", { link: Number($("#sched-link").value || 0), slots });
});
const qrows = new Map();
function renderQueues() {
  const Q = S.queues;
  if (!Q) return;
  $("#queues-age").textContent = Q.t !== null && Q.t !== undefined ? `queue status from the vehicle at ${fmtT(Q.t)}` : "no queue status from the vehicle yet";
  const tb = $("#queues-table tbody");
  for (const s of Q.streams) {
    let r = qrows.get(s.stream);
    if (!r) {
      const prio = el("input", { type: "number", min: 0, max: 127 });
      const setP = el("button", { title: "set priority" }, "Set");
      const tog = el("button", {});
      const flush = el("button", { title: "discard everything queued" }, "Flush");
      setP.addEventListener("click", () => act("queue_config", { stream: s.stream, priority: Number(prio.value) }));
      tog.addEventListener("click", () => act("queue_config", { stream: s.stream, enabled: !r.enabled }));
      flush.addEventListener("click", () => act("queue_config", { stream: s.stream, flush: true }));
      const cells = [0, 1, 2, 3, 4, 5, 6].map(() => el("td"));
      cells[6].className = "words";
      cells[2].append(prio, setP);
      const tr = el("tr", { "data-stream": s.stream }, ...cells, el("td", {}, tog, flush));
      r = { tr, cells, prio, tog, enabled: s.enabled };
      qrows.set(s.stream, r);
      tb.append(tr);
    }
    r.enabled = s.enabled;
    r.cells[0].textContent = `${s.stream} ${s.name}`;
    r.cells[0].className = s.enabled ? "" : "off";
    r.cells[1].textContent = s.tier;
    if (document.activeElement !== r.prio) r.prio.value = s.priority;
    r.cells[3].textContent = s.depth;
    r.cells[4].textContent = fmtBytes(s.queued_bytes);
    r.cells[5].textContent = fmtAge(s.oldest_age);
    r.cells[6].textContent = s.drops_total ? `${s.drops} dropped in the last report, ${s.drops_total} in all` : "none dropped";
    r.tog.textContent = s.enabled ? "Disable" : "Enable";
  }
}

// ------------------------------------------------------------------ header, commands, log
// Dive time: since the first vehicle status the console holds.
function diveStart() {
  const tr = S.vehicle && S.vehicle.track;
  return tr && tr.length ? tr[0][0] : null;
}
function fmtDur(s) {
  s = Math.max(0, Math.floor(s));
  return `${Math.floor(s / 3600)}:${pad(Math.floor(s / 60) % 60)}:${pad(s % 60)}`;
}
function showClock() {
  const t0 = diveStart();
  $("#clock").textContent = fmtT(S.now) + (t0 !== null ? ` · dive ${fmtDur(S.now - t0)}` : "");
  $("#clock").title = "time of day (UTC) of the dive, and time since the first vehicle status";
}
// What the vehicle is doing, in words: its vertical motion from the track's depths, and the
// survey it flies (from the survey receiver's state) when one is started.
function vehicleDoing() {
  const out = [];
  const V = S.vehicle || {};
  // only while in contact: a dive that ended, or a silent vehicle, is not "ascending" now
  if (V.ended || !V.status || S.now - V.status.t > staleAfter()) return "";
  const tr = V.track || [];
  if (tr.length >= 2) {
    const last = tr[tr.length - 1];
    let k = tr.length - 2;
    while (k > 0 && last[0] - tr[k][0] < 20) k--;
    const dt = last[0] - tr[k][0];
    const rate = dt > 0 ? (last[3] - tr[k][3]) / dt : 0;
    if (dt > 0 && dt < 600 && rate > 0.05) out.push("descending");
    else if (dt > 0 && dt < 600 && rate < -0.05) out.push("ascending");
  }
  const items = (S.surveys && S.surveys.items) || [];
  const flying = items.filter((sv) => sv.state === "started");
  if (flying.length) {
    const sv = flying[flying.length - 1];
    // the waypoint as the map labels it ("→ waypoint 3")
    out.push(`flying survey S${sv.survey_id}` + (sv.index !== null && sv.index !== undefined ? ` → waypoint ${sv.index}` : ""));
  }
  return out.join(", ");
}
// Contact: "live" only while the page is connected and the vehicle was heard lately.
let pageConnected = false;
function showConn() {
  const conn = $("#conn");
  const V = S.vehicle || {};
  const v = V.status;
  let text = "live", cls = "conn on";
  if (!pageConnected) { text = "reconnecting…"; cls = "conn off"; }
  else if (V.ended) { text = `ended: ${V.ended}`; cls = "conn ended"; }
  else if (!v) { text = "live · no vehicle status yet"; cls = "conn wait"; }
  else if (S.now - v.t > staleAfter()) { text = `no contact for ${fmtAge(S.now - v.t)}`; cls = "conn wait"; }
  conn.textContent = text; conn.className = cls;
  conn.title = "live: the page is connected and the vehicle was heard in the last few TDMA cycles";
}
function renderVehicle() {
  const v = S.vehicle && S.vehicle.status;
  const box = $("#vehicle-status");
  showConn();
  if (!v) { box.textContent = "no vehicle status yet"; return; }
  box.innerHTML = "";
  const f = (label, value) => [el("span", {}, ` ${label} `), el("b", {}, value)];
  const doing = vehicleDoing();
  box.append(...f("reports", v.mode), ...(doing ? [el("b", { class: "doing" }, ` · ${doing}`)] : []),
    ...f("depth", `${v.depth.toFixed(1)} m`),
    ...f("alt", v.altitude === null ? "–" : `${v.altitude.toFixed(1)} m`),
    ...f("hdg", `${v.heading.toFixed(0)}°`), ...f("speed", `${v.speed.toFixed(2)} m/s`),
    ...f("battery", `${v.battery}%`), ...f("pos", `${v.x.toFixed(0)}, ${v.y.toFixed(0)}`),
    ...f("heard", `${fmtAge(S.now - v.t)} ago`));
  box.title = `vehicle status of ${fmtT(v.t)}: the mode is what the vehicle reports`;
  if (v.faults) box.append(el("b", { class: "off" }, ` faults 0x${v.faults.toString(16)}`));
  const it = $("#img-time");
  if (!it.value && document.activeElement !== it) it.placeholder = fmtT(v.t);
}
function renderCommands() {
  const ul = $("#commands");
  ul.replaceChildren(...S.commands.map((c) => el("li", { "data-status": c.status, "data-command": c.command_id },
    el("span", { class: "t" }, fmtT(c.sent)), c.summary,
    c.by ? el("span", { class: "by", title: "sent by" }, ` · ${c.by}`) : "",
    el("span", { class: `badge ${c.status.replace(/ /g, "_")}` }, c.status),
    c.reason ? el("div", { class: `reason ${c.status.replace(/ /g, "_")}` }, c.reason) : "",
    c.answer ? el("div", { class: "answer" }, c.answer) : "")));
  if (!S.commands.length) ul.append(el("li", { class: "empty" }, "No command sent yet."));
}
function renderLog() {
  const ul = $("#log");
  // an entry counting repeated events (l.n of them) spans its first to its last time
  ul.replaceChildren(...S.log.slice().reverse().map((l) => el("li", { class: l.level + (l.n > 1 ? " counted" : "") },
    el("span", { class: "t" }, l.n > 1 ? `${fmtT(l.t)}–${fmtT(l.last)}` : fmtT(l.t)), l.text)));
}

// products of modalities the page has no panel for (a third-party plugin): a generic table
function renderOther() {
  const mods = (S.other && S.other.modalities) || [];
  $("#other-panel").classList.toggle("hidden", !mods.length);
  $("#other").replaceChildren(...mods.map((mod) => el("div", { class: "other-mod" },
    el("h3", {}, mod.name),
    el("table", { class: "grid" },
      el("thead", {}, el("tr", {}, el("th", {}, "product"), el("th", {}, "kind"),
        el("th", {}, "version"), el("th", {}, "details"))),
      el("tbody", {}, ...mod.products.map((p) => el("tr", {},
        el("td", {}, p.key), el("td", {}, p.kind), el("td", {}, p.version),
        el("td", { class: "fields" }, Object.entries(p.fields).map(([k, v]) => `${k}: ${v}`).join(", ")))))))));
}

const RENDER = { vehicle: () => { renderVehicle(); drawMap(); }, map: () => { renderLevels(); drawMap(); },
  images: () => { renderImages(); drawMap(); },
  surveys: () => { renderSurveys(); renderVehicle(); drawMap(); },
  series: renderSeries, other: renderOther, link: renderLink, queues: renderQueues,
  commands: () => { renderCommands(); if (S.images) renderImages(); }, log: renderLog,
  navigation: () => { renderNavigation(); drawMap(); } };

// A map update is a delta (the server sends a level's blocks only when they changed): merge it
// into the map the page holds.
function mergeMap(old, upd) {
  if (!upd.delta || !old) return upd;
  const had = new Map((old.levels || []).map((lv) => [lv.level, lv]));
  upd.levels = upd.levels.map((lv) => {
    const prev = had.get(lv.level);
    if (lv.same) return prev;
    if (!lv.tiles_changed) return lv;
    const tiles = new Map(((prev && prev.tiles) || []).map((t) => [`${t[0]},${t[1]}`, t]));
    for (const t of lv.tiles_changed) tiles.set(`${t[0]},${t[1]}`, t);
    for (const t of lv.tiles_removed || []) tiles.delete(`${t[0]},${t[1]}`);
    const out = Object.assign({}, lv, { tiles: [...tiles.values()] });
    delete out.tiles_changed; delete out.tiles_removed;
    return out;
  }).filter((lv) => lv);
  delete upd.delta;
  return upd;
}
// the fleet strip: every vehicle of a fleet console (position, mode, status age, link loss and
// last heard, queued bytes, open commands), each a link to its own page
function renderFleet() {
  const f = S.fleet, strip = $("#fleet");
  if (!f || !strip) return;
  drawMap();
  strip.classList.remove("hidden");
  strip.replaceChildren(...f.vehicles.map((v) => {
    const lk = Object.values(v.links || {})[0] || {};
    const age = v.status_t == null ? "no status" : `status ${Math.max(0, S.now - v.status_t).toFixed(0)} s ago`;
    const pos = v.x == null ? "" : ` at ${v.x.toFixed(0)}, ${v.y.toFixed(0)} m, ${v.depth.toFixed(0)} m deep, ${v.mode}`;
    const loss = lk.loss == null ? "loss ?" : `loss ${(100 * lk.loss).toFixed(0)} %`;
    const a = el("a", { class: "fleet-vehicle" + (v.id === f.vehicle ? " current" : ""),
      href: `/?vehicle=${encodeURIComponent(v.name)}`, "data-vehicle": v.name },
      el("b", {}, `${v.name} (${v.id})`), ` ${age}${pos}; ${loss}; ${v.queued_bytes || 0} B queued; `
      + `${v.open_commands || 0} open command${v.open_commands === 1 ? "" : "s"}; ${v.images || 0} images`);
    if (v.id === f.vehicle) a.setAttribute("aria-current", "page");
    return a;
  }));
}
function apply(data, full) {
  if (data.now !== undefined) S.now = data.now;
  if (data.fleet) { S.fleet = data.fleet; renderFleet(); }
  if (data.map) data.map = mergeMap(full ? null : S.map, data.map);
  if (data.versions) S.versions = data.versions;
  for (const k of Object.keys(RENDER)) {
    if (k in data) { S[k] = data[k]; RENDER[k](); S.versions[k] = (S.versions[k] || 0) + (full ? 0 : 1); }
  }
  showClock();
  applyRole();
  window.coex.updates += 1;
}

// ------------------------------------------------------------------ who is signed in
// Viewers see everything live; only operators command: for a viewer every command button is
// disabled (the server refuses their actions anyway, 403).
const ME = { auth: false, name: "", role: "operator", may_command: true, csrf: "" };
const VIEW_ONLY = new Set(["fit-btn", "draw-btn", "roi-cancel", "logout-btn"]);
function applyRole() {
  document.body.classList.toggle("role-viewer", !ME.may_command);  // not "viewer": the image viewer's class
  if (ME.may_command) return;
  for (const b of document.querySelectorAll("main button, main select, #roi-form input, #sched-form input")) {
    if (!VIEW_ONLY.has(b.id)) { b.disabled = true; b.title = "viewers cannot command"; }
  }
}
async function whoami() {
  try {
    const r = await fetch("/api/whoami");
    if (r.status === 401) { location.href = "/login"; return; }
    Object.assign(ME, await r.json());
  } catch (err) { return; }
  const who = $("#who");
  if (ME.auth) {
    who.replaceChildren(`${ME.name} (${ME.role}) `,
      el("button", { id: "logout-btn", type: "button", title: "sign out" }, "Sign out"));
    $("#logout-btn").addEventListener("click", async () => {
      await fetch("/logout", { method: "POST", headers: { "X-CSRF-Token": ME.csrf } });
      location.href = "/login";
    });
  }
  applyRole();
  window.coex.me = ME;
}

// ------------------------------------------------------------------ live connection
// for tests and the curious: state, view, and world -> page coordinates of the map
window.coex = { S, view, updates: 0, connected: false, region,
  pagePoint(x, y) {
    const r = canvas.getBoundingClientRect(), [sx, sy] = w2s(x, y);
    return [r.left + (sx * r.width) / canvas.width, r.top + (sy * r.height) / canvas.height];
  } };
function connect() {
  const es = new EventSource(withVehicle("/api/events"));
  es.addEventListener("snapshot", (ev) => { apply(JSON.parse(ev.data), true); });
  es.addEventListener("update", (ev) => { apply(JSON.parse(ev.data), false); });
  es.addEventListener("clock", (ev) => {
    S.now = JSON.parse(ev.data).now;
    showClock();
    renderVehicle(); drawTdma(); drawAllPlots();
  });
  // the server ends the stream when the session ends (signed out, expired, removed from the
  // operators file, new password) and says when the person's role changed (made a viewer)
  es.addEventListener("session", (ev) => {
    const s = JSON.parse(ev.data);
    if (s.ended) { es.close(); location.href = "/login"; return; }
    whoami();
  });
  es.onopen = () => { pageConnected = true; showConn(); window.coex.connected = true; };
  es.onerror = () => { pageConnected = false; showConn(); window.coex.connected = false; };
}
window.addEventListener("resize", () => { drawMap(); drawAllPlots(); drawTdma(); drawLinkPlots(); });
whoami().then(connect);
