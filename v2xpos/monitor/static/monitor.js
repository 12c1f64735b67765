// v2xpos monitor page: polls /api/state and draws the bird's-eye view (canvas) and the table.
"use strict";
const POLL_MS = 200;
const COLORS = {
  valid: "#1a9c3a", fix_invalid: "#f08c00", timeout: "#d62728", no_data: "#8c8c8c", future: "#8e44ad",
  attitude_uncertain: "#c9a100", sigma_exceeded: "#e35d9c", clock_unsynced: "#2a7ab0", inconsistent: "#7f3f00",
  unverified: "#b07f3f", stale: "#444444",
};
const FROZEN_S = 1.0;          // no new snapshot for this long: the monitor itself is gone or stuck
const FIT_MAX_M = 150;         // auto-zoom fits the targets within this range (others: arrows at the edge)
const DEFAULT_OUTLINE = { vehicle: { kind: "polygon", points_m: [[3.5, -0.9], [3.5, 0.9], [-1.0, 0.9], [-1.0, -0.9]], radius_m: 0 },
                          pedestrian: { kind: "circle", points_m: [], radius_m: 0.4 } };
const canvas = document.getElementById("view");
const ctx = canvas.getContext("2d");
let halfRangeM = 30;           // metres from the master to the view's edge (changes with hysteresis)
window.v2xposRendered = [];    // what the last draw put on the canvas (read by the browser test)
window.v2xposVersion = -1;

function colorOf(status) { return COLORS[status] || "#000000"; }

function fmt(x, d) {
  if (x === null || x === undefined || !isFinite(x)) return "-";
  for (let k = d; k >= 0; k--) { const s = x.toFixed(k); if (s.length <= 7) return s; }
  if (Math.abs(x) < 1e6) return (x / 1e3).toFixed(0) + "k";
  return (x / 1e6).toFixed(0) + "M";
}

function legend() {
  const el = document.getElementById("legend");
  el.innerHTML = Object.entries(COLORS).map(([k, c]) => `<span><i style="background:${c}"></i>${k}</span>`).join("");
}

let manualHalfRangeM = null;  // set by the zoom buttons; null = fit every target
const STEPS = [15, 30, 60, 120, 250, 500, 1000];

function posOf(r) {
  if (r.x_m !== null && r.y_m !== null) return [r.x_m, r.y_m];
  if (r.last_x_m !== null && r.last_y_m !== null) return [r.last_x_m, r.last_y_m];
  return null;
}

function chooseScale(rows) {
  // fit the targets within FIT_MAX_M of the master (or the nearest one when none is): a far
  // pedestrian must not pile the nearby cars onto the master; far targets are arrows at the edge
  if (manualHalfRangeM !== null) { halfRangeM = manualHalfRangeM; return; }
  const pos = rows.map(posOf).filter(p => p !== null);
  const dist = p => Math.max(Math.abs(p[0]), Math.abs(p[1]));
  let fit = pos.filter(p => dist(p) <= FIT_MAX_M);
  if (!fit.length && pos.length) fit = [pos.reduce((a, b) => (dist(a) <= dist(b) ? a : b))];
  let need = 10;
  for (const [x, y] of fit) need = Math.max(need, Math.abs(x) * 1.15 + 5, Math.abs(y) * 1.15 + 5);
  let want = STEPS.find(s => s >= need) || STEPS[STEPS.length - 1];
  // grow at once, shrink only when everything fits in half of the view (no jumping back and forth)
  if (want > halfRangeM || want * 2 <= halfRangeM) halfRangeM = want;
}

function toScreen(x, y) {
  // master at the centre, x forward = up, y right = right
  const s = Math.min(canvas.width, canvas.height) / (2 * halfRangeM);
  return [canvas.width / 2 + y * s, canvas.height / 2 - x * s, s];
}

function drawGrid() {
  ctx.fillStyle = "#ffffff"; ctx.fillRect(0, 0, canvas.width, canvas.height);
  const step = halfRangeM <= 15 ? 5 : halfRangeM <= 60 ? 10 : halfRangeM <= 250 ? 50 : 100;
  ctx.strokeStyle = "#e6e6e6"; ctx.lineWidth = 1; ctx.font = "10px sans-serif"; ctx.fillStyle = "#888";
  for (let m = -Math.ceil(halfRangeM * 1.5 / step) * step; m <= halfRangeM * 1.5; m += step) {
    let [sx] = toScreen(0, m); ctx.beginPath(); ctx.moveTo(sx, 0); ctx.lineTo(sx, canvas.height); ctx.stroke();
    let [, sy] = toScreen(m, 0); ctx.beginPath(); ctx.moveTo(0, sy); ctx.lineTo(canvas.width, sy); ctx.stroke();
    if (m !== 0) { ctx.fillText(`x ${m} m`, 4, sy - 2); ctx.fillText(`y ${m} m`, sx + 2, canvas.height - 18); }
  }
  ctx.fillText(`grid ${step} m`, 6, canvas.height - 6);
}

function drawLanes(lanes) {
  ctx.save(); ctx.setLineDash([10, 8]); ctx.strokeStyle = "#5577aa"; ctx.lineWidth = 2;
  lanes.forEach((l, i) => {
    if (l.lateral_m === null) return;
    const [sx] = toScreen(0, l.lateral_m);
    ctx.beginPath(); ctx.moveTo(sx, 0); ctx.lineTo(sx, canvas.height); ctx.stroke();
    ctx.fillStyle = "#5577aa"; ctx.fillText(`lane ${l.id}`, sx + 3, 12 + 12 * i);
  });
  ctx.restore();
}

function drawMaster(id) {
  const [sx, sy, s] = toScreen(0, 0);
  ctx.fillStyle = "#1f3b73"; ctx.beginPath();
  ctx.moveTo(sx, sy - Math.max(10, 2.5 * s)); ctx.lineTo(sx - 7, sy + 7); ctx.lineTo(sx + 7, sy + 7); ctx.closePath(); ctx.fill();
  ctx.fillText(id || "master", sx + 9, sy + 4);
}

function drawTrail(points, color) {
  if (!points || points.length < 2) return;
  ctx.save(); ctx.globalAlpha = 0.45; ctx.strokeStyle = color; ctx.lineWidth = 1.5; ctx.beginPath();
  points.forEach(([x, y], i) => { const [sx, sy] = toScreen(x, y); if (i) ctx.lineTo(sx, sy); else ctx.moveTo(sx, sy); });
  ctx.stroke(); ctx.restore();
}

function inView(x, y) { return Math.abs(x) <= halfRangeM * 1.05 && Math.abs(y) <= halfRangeM * 1.05; }

function drawEdgeMarker(r, x, y) {
  // a target outside the view: an arrow on the edge in its direction, with its id and distance
  const color = colorOf(r.status);
  const k = halfRangeM * 0.92 / Math.max(Math.abs(x), Math.abs(y));
  const [ex, ey] = toScreen(x * k, y * k);
  const a = Math.atan2(-x, y);       // screen angle of the direction (x up, y right)
  ctx.save(); ctx.translate(ex, ey); ctx.rotate(a); ctx.fillStyle = color;
  ctx.beginPath(); ctx.moveTo(10, 0); ctx.lineTo(-6, -6); ctx.lineTo(-6, 6); ctx.closePath(); ctx.fill(); ctx.restore();
  ctx.fillStyle = "#000"; ctx.font = "11px sans-serif";
  const d = Math.hypot(x, y);
  ctx.fillText(`${r.id} ${r.status} ${d.toFixed(0)} m`, Math.min(ex + 8, canvas.width - 120), Math.max(ey - 8, 12));
  return { id: r.id, status: r.status, color: color, px: ex, py: ey, edge: true, range_m: r.range_m, x_m: r.x_m };
}

function drawTarget(r, lastSeen) {
  // lastSeen: the status carries no position; drawn hollow and dashed where it was last seen
  const color = colorOf(r.status);
  const g = r.geometry || DEFAULT_OUTLINE[r.kind] || DEFAULT_OUTLINE.vehicle;
  const x = lastSeen ? r.last_x_m : r.x_m, y = lastSeen ? r.last_y_m : r.y_m;
  const yawDeg = lastSeen ? r.last_rel_yaw_deg : r.rel_yaw_deg;
  const yaw = (yawDeg === null ? 0 : yawDeg) * Math.PI / 180;
  const c = Math.cos(yaw), s = Math.sin(yaw);
  const [cx, cy, scale] = toScreen(x, y);
  ctx.save(); ctx.fillStyle = color; ctx.strokeStyle = color; ctx.lineWidth = 2;
  if (lastSeen) {
    ctx.setLineDash([4, 3]); ctx.beginPath();
    if (g.kind === "circle" || !g.points_m.length) ctx.arc(cx, cy, Math.max(5, (g.radius_m || 0.4) * scale), 0, 2 * Math.PI);
    else g.points_m.forEach(([px, py], i) => {
      const [sx, sy] = toScreen(x + c * px - s * py, y + s * px + c * py);
      if (i) ctx.lineTo(sx, sy); else ctx.moveTo(sx, sy);
    });
    ctx.closePath(); ctx.stroke(); ctx.setLineDash([]);
    ctx.fillStyle = "#000"; ctx.font = "11px sans-serif";
    ctx.fillText(`${r.id} ${r.status} (last seen)`, cx + 8, cy - 8);
    ctx.restore();
    return { id: r.id, status: r.status, color: color, px: cx, py: cy, last_seen: true };
  }
  if (g.kind === "circle" || !g.points_m.length) {
    ctx.beginPath(); ctx.arc(cx, cy, Math.max(4, (g.radius_m || 0.4) * scale), 0, 2 * Math.PI); ctx.fill();
  } else {
    ctx.globalAlpha = 0.85; ctx.beginPath();
    g.points_m.forEach(([px, py], i) => {
      const [sx, sy] = toScreen(r.x_m + c * px - s * py, r.y_m + s * px + c * py);
      if (i) ctx.lineTo(sx, sy); else ctx.moveTo(sx, sy);
    });
    ctx.closePath(); ctx.fill(); ctx.globalAlpha = 1; ctx.stroke();
    ctx.beginPath(); ctx.arc(cx, cy, 4, 0, 2 * Math.PI); ctx.fill();   // reference point
  }
  ctx.fillStyle = "#000"; ctx.font = "11px sans-serif";
  ctx.fillText(`${r.id} ${r.status}${r.range_m !== null ? " " + r.range_m.toFixed(1) + " m" : ""}`, cx + 8, cy - 8);
  ctx.restore();
  return { id: r.id, status: r.status, color: color, px: cx, py: cy, range_m: r.range_m, x_m: r.x_m };
}

let lastSnap = null;
function zoom(step) {
  const i = STEPS.indexOf(halfRangeM);
  const k = Math.min(STEPS.length - 1, Math.max(0, (i < 0 ? 2 : i) + step));
  manualHalfRangeM = STEPS[k];
  if (lastSnap) drawView(lastSnap);
}
document.getElementById("zin").onclick = () => zoom(-1);
document.getElementById("zout").onclick = () => zoom(1);
document.getElementById("zauto").onclick = () => { manualHalfRangeM = null; if (lastSnap) drawView(lastSnap); };

function drawView(snap) {
  lastSnap = snap;
  chooseScale(snap.rows);
  document.getElementById("zlabel").textContent =
    `±${halfRangeM} m around the master (${manualHalfRangeM === null ? "auto" : "fixed"})`;
  drawGrid();
  drawLanes(snap.lanes || []);
  for (const r of snap.rows) drawTrail(snap.trails[r.id], colorOf(r.status));
  drawMaster(snap.master.id);
  const drawn = [];
  for (const r of snap.rows.slice().reverse()) {   // worst drawn last, on top
    const p = posOf(r);
    if (p === null) continue;
    if (!inView(p[0], p[1])) drawn.push(drawEdgeMarker(r, p[0], p[1]));
    else if (r.x_m !== null && r.y_m !== null) drawn.push(drawTarget(r, false));
    else drawn.push(drawTarget(r, true));
  }
  window.v2xposRendered = drawn;
  window.v2xposHalfRangeM = halfRangeM;
}

function cell(text, cls, style) { return `<td${cls ? ` class="${cls}"` : ""}${style ? ` style="${style}"` : ""}>${text}</td>`; }
function esc(t) { return String(t === null || t === undefined || t === "" ? "-" : t).replace(/[&<>"]/g, ch => ({"&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;"})[ch]); }

function drawTable(snap) {
  const html = snap.rows.map(r => `<tr data-target="${esc(r.id)}" data-status="${esc(r.status)}">` +
    cell(esc(r.id), "l") + cell(esc(r.kind), "l") +
    cell(esc(r.status.toUpperCase() + (r.degraded ? " DEGRADED" : "")), "l", `color:${colorOf(r.status)};font-weight:bold`) +
    cell(esc(r.reason), "l") + cell(`${esc(r.master_fix)}/${esc(r.target_fix)}`, "l") +
    cell(fmt(r.range_m, 2)) + cell(fmt(r.x_m, 2)) + cell(fmt(r.y_m, 2)) + cell(fmt(r.rel_yaw_deg, 1)) +
    cell(fmt(r.sigma_h_m, 3)) + cell(fmt(r.age_ms, 1)) + cell(fmt(r.ttc_s, 1)) + cell(esc(r.imu), "l") +
    cell(esc(r.instruction), "l") + "</tr>").join("");
  document.getElementById("rows").innerHTML = html;
  const m = snap.master;
  const el = document.getElementById("master");
  const age = m.status_age_s === null || m.status_age_s === undefined ? "-" : m.status_age_s.toFixed(1);
  let text, cls;
  if (m.state === "gone") {
    text = `MASTER ${m.id || "?"} GONE: no status for ${age} s. Every row is STALE: nothing shown is live.`;
    cls = "alarm";
  } else if (m.state === "not_heard") {
    text = `waiting for the master: nothing heard for ${fmt(snap.monitor.waited_s, 0)} s (check the monitor's --connect, --fleet, --master)`;
    cls = "warn";
  } else {
    const clock = m.clock_synchronised === null || m.clock_synchronised === undefined ? "-" : (m.clock_synchronised ? "ok" : "UNSYNCED");
    const phase = m.state === "starting" ? ` STARTING (phase ${m.phase}${m.waiting_for && m.waiting_for.length ? ", waiting for " + m.waiting_for.join(", ") : ""})` : " live";
    text = `master ${m.id || "?"}${phase}  status ${age} s old  fix ${m.fix || "-"}  clock ${clock}  t ${fmt(m.t_rel_s, 1)} s  ` +
      `processed ${m.processed || 0}  pipeline p99 ${fmt(m.pipeline_ms_p99, 2)} ms  e2e p99 ${fmt(m.e2e_ms_p99, 2)} ms  targets ${snap.rows.length}`;
    cls = m.state === "starting" ? "warn" : "";
  }
  el.textContent = text; el.className = cls; el.dataset.state = m.state;
  const alarms = (m.clock_alarms || []).map(id => {
    const r = snap.rows.find(x => x.id === id);
    return `CLOCK ALARM ${esc(id)}: ${esc(r ? r.reason : "")}`;
  });
  document.getElementById("alarms").innerHTML = alarms.join("<br>");
  drawVehicles(snap.vehicles || []);
}

function drawVehicles(vs) {
  document.getElementById("vehicles").innerHTML = vs.map(v => {
    const age = v.state === "live" ? "" : ` (${fmt(v.status_age_s, 0)} s ago)`;
    const cls = v.state === "live" ? "" : "alarm";
    return `<div class="veh ${cls}" data-vehicle="${esc(v.id)}" data-state="${esc(v.state)}"><b>[${esc(v.state.toUpperCase())}${age}]</b> ` +
      `${esc(v.line)}</div>`;
  }).join("");
}

function markAllStale(why) {
  // the page has no fresh snapshot: nothing it shows may look live
  const el = document.getElementById("master");
  el.textContent = why; el.className = "alarm"; el.dataset.state = "frozen";
  for (const tr of document.querySelectorAll("#rows tr")) {
    tr.dataset.status = "stale";
    tr.children[2].textContent = "STALE"; tr.children[2].style.color = COLORS.stale;
  }
  if (lastSnap) {
    const rows = lastSnap.rows.map(r => Object.assign({}, r, { status: "stale", x_m: null, y_m: null,
      last_x_m: r.x_m !== null ? r.x_m : r.last_x_m, last_y_m: r.y_m !== null ? r.y_m : r.last_y_m }));
    drawView(Object.assign({}, lastSnap, { rows: rows }));
  }
}

let lastNewAt = Date.now();
async function poll() {
  try {
    const r = await fetch("/api/state", { cache: "no-store" });
    const snap = await r.json();
    if (snap && snap.version !== window.v2xposVersion) {
      drawView(snap); drawTable(snap);
      window.v2xposVersion = snap.version;
      lastNewAt = Date.now();
    } else if (snap === null) {
      document.getElementById("master").textContent = "waiting for the monitor's first snapshot ...";
      lastNewAt = Date.now();
    }
  } catch (e) {
    markAllStale(`monitor not reachable (${e}): nothing shown is live`);
  }
  if (Date.now() - lastNewAt > FROZEN_S * 1000 && lastSnap) {
    markAllStale(`no new data from the monitor for ${((Date.now() - lastNewAt) / 1000).toFixed(1)} s: nothing shown is live`);
  }
  setTimeout(poll, POLL_MS);
}
legend();
drawGrid();
poll();
