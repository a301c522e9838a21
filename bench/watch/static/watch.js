// bench watch: the page. Polls the server for the bins it lacks, draws one uPlot per stream and unit, marks steps,
// events and limits, and offers the only two actions: pause and stop. Plain browser JavaScript, no build step.
"use strict";

const POLL_MS = 500;  // the server looks at the file at most every 0.2 s; the page follows within a second
const ORDER = ["amplifier", "laser", "load_cell", "motor", "setpoints"];  // voltage, current, displacement, force, motor
const COLOURS = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#17becf"];
const MARK = {start: "#888", pause: "#d99a00", resume: "#3a9d3a", restart: "#3a9d3a", specimen: "#6a3d9a",
              request: "#b3261e", stop: "#b3261e", interrupted: "#b3261e", tripped: "#b3261e", error: "#b3261e",
              interlock: "#b3261e", fault: "#b3261e", watchdog: "#b3261e", safe: "#14612a"};
const PREFIX = [[1e9, "G"], [1e6, "M"], [1e3, "k"], [1, ""], [1e-3, "m"], [1e-6, "µ"], [1e-9, "n"], [1e-12, "p"]];

const params = new URLSearchParams(location.search);
const token = params.get("token");
const headers = token ? {"X-Bench-Token": token} : {};
const store = {};   // stream → {generation, t_lo, t_hi, lo: {col: []}, hi: {col: []}, units, records}
const panels = {};  // "stream|unit" → {plot, stream, unit, cols, el}
let run = params.get("run");
let latest = null;  // the last answer
let zoomed = false;
const state = window.benchWatch = {polls: 0, records: {}, points: 0, state: "", panels: 0, error: ""};

// a value with an SI prefix on its unit: 0.005 "m" → "5 mm"
function si(v, unit) {
  unit = unit || "";
  if (v === 0 || !isFinite(v)) return `${v} ${unit}`.trim();
  const a = Math.abs(v);
  for (const [f, p] of PREFIX) if (a >= f * 0.9999) return `${+(v / f).toPrecision(4)} ${p}${unit}`.trim();
  return `${v.toExponential(2)} ${unit}`.trim();
}

function el(tag, attrs, text) {
  const e = document.createElement(tag);
  Object.assign(e, attrs || {});
  if (text !== undefined) e.textContent = text;
  return e;
}

function merge(name, s) {
  const old = store[name];
  if (!old || old.generation !== s.generation) {
    store[name] = {generation: s.generation, t_lo: s.t_lo, t_hi: s.t_hi, lo: s.lo, hi: s.hi};
  } else {
    const cut = (a, b) => { a.length = s.from; for (const v of b) a.push(v); };
    cut(old.t_lo, s.t_lo); cut(old.t_hi, s.t_hi);
    for (const c of Object.keys(s.lo)) { cut(old.lo[c], s.lo[c]); cut(old.hi[c], s.hi[c]); }
  }
  Object.assign(store[name], {units: s.units, records: s.records});
}

function have() {
  return Object.entries(store).map(([n, s]) => `${n}:${s.generation}:${s.t_lo.length}`).join(",");
}

function tmax() {
  let m = 0;
  for (const s of Object.values(store)) if (s.t_hi.length) m = Math.max(m, s.t_hi[s.t_hi.length - 1]);
  return m;
}

// every event on the time axis; the step names on each panel's top edge
function drawMarks(u) {
  if (!latest) return;
  const ctx = u.ctx, {left, top, width, height} = u.bbox, dpr = devicePixelRatio || 1;
  ctx.save();
  ctx.beginPath(); ctx.rect(left, top, width, height); ctx.clip();
  ctx.font = `${10 * dpr}px system-ui, sans-serif`;
  for (const e of latest.events || []) {
    const x = Math.round(u.valToPos(e.t, "x", true));
    if (x < left || x > left + width) continue;
    ctx.strokeStyle = MARK[e.kind] || "#888";
    ctx.lineWidth = (e.kind === "start" ? 1 : 2) * dpr;
    ctx.setLineDash(e.kind === "start" ? [3 * dpr, 3 * dpr] : []);
    ctx.beginPath(); ctx.moveTo(x, top); ctx.lineTo(x, top + height); ctx.stroke();
    ctx.fillStyle = ctx.strokeStyle;
    const label = e.kind === "start" ? e.text.split(" | ")[0] : e.kind;
    ctx.fillText(label, x + 3 * dpr, top + 11 * dpr);
  }
  const p = u._bench, limit = latest.limits ? latest.limits[p.unit] : undefined;
  if (limit !== undefined) {
    ctx.strokeStyle = "#b3261e"; ctx.lineWidth = dpr; ctx.setLineDash([6 * dpr, 4 * dpr]);
    for (const v of [limit, -limit]) {
      const y = Math.round(u.valToPos(v, "y", true));
      if (y < top || y > top + height) continue;
      ctx.beginPath(); ctx.moveTo(left, y); ctx.lineTo(left + width, y); ctx.stroke();
    }
  }
  ctx.restore();
}

function panel(stream, unit, cols) {
  const key = `${stream}|${unit}`;
  if (panels[key]) return panels[key];
  const box = el("div", {className: "panel"});
  const title = el("h2", {}, `${stream} [${unit || "1"}]`);
  const limit = latest.limits ? latest.limits[unit] : undefined;
  if (limit !== undefined) title.appendChild(el("span", {className: "limit"}, `limit ±${si(limit, unit)}`));
  box.appendChild(title);
  document.getElementById("panels").appendChild(box);
  const opts = {
    width: Math.max(400, document.getElementById("panels").clientWidth - 10), height: 170,
    scales: {x: {time: false}},
    series: [{label: "t [s]"}, ...cols.map((c, i) => ({label: `${c} [${unit || "1"}]`, stroke: COLOURS[i % COLOURS.length],
                                                         width: 1, spanGaps: true}))],
    axes: [{label: "t [s] (run clock)", size: 36}, {label: unit || "1", size: 70, values: (u, v) => v.map(x => si(x, unit))}],
    cursor: {sync: {key: "bench-watch"}},
    hooks: {draw: [drawMarks], setSelect: [u => { if (u.select.width > 0) zoomed = true; }]},
  };
  const plot = new uPlot(opts, [[], ...cols.map(() => [])], box);
  plot._bench = {unit};
  plot.over.addEventListener("dblclick", () => { zoomed = false; redraw(); });
  panels[key] = {plot, stream, unit, cols, box};
  state.panels = Object.keys(panels).length;
  return panels[key];
}

// a stream's bins as a zigzag: each bin's minimum at its first time, its maximum at its last
function zigzag(s, cols) {
  const n = s.t_lo.length, x = new Array(2 * n), ys = cols.map(() => new Array(2 * n));
  for (let k = 0; k < n; k++) {
    x[2 * k] = s.t_lo[k]; x[2 * k + 1] = s.t_hi[k];
    cols.forEach((c, j) => { ys[j][2 * k] = s.lo[c][k]; ys[j][2 * k + 1] = s.hi[c][k]; });
  }
  return [x, ...ys];
}

function redraw() {
  const names = Object.keys(store).sort((a, b) => (ORDER.indexOf(a) + 99 * (ORDER.indexOf(a) < 0)) -
                                                   (ORDER.indexOf(b) + 99 * (ORDER.indexOf(b) < 0)));
  const end = tmax();
  let points = 0;
  for (const name of names) {
    const s = store[name], byUnit = {};
    for (const c of Object.keys(s.lo)) (byUnit[s.units[c] || ""] = byUnit[s.units[c] || ""] || []).push(c);
    for (const [unit, cols] of Object.entries(byUnit)) {
      const p = panel(name, unit, cols);
      const data = zigzag(s, p.cols);
      points += data[0].length * p.cols.length;
      if (zoomed) { p.plot.setData(data, false); continue; }
      p.plot.setData(data);
      if (end > 0) p.plot.setScale("x", {min: 0, max: end});
    }
    state.records[name] = s.records;
  }
  state.points = points;
}

function show(d) {
  const st = document.getElementById("state");
  st.textContent = d.state;
  st.className = "state " + d.state;
  document.getElementById("reason").textContent =
    `${d.name} — protocol ${d.protocol || "?"} on rig ${d.rig || "?"}: ${d.reason}` +
    (d.updated !== undefined ? ` (file updated at ${d.updated.toFixed(1)} s)` : "");
  document.getElementById("records").textContent = Object.entries(d.streams)
    .map(([n, s]) => `${n}: ${s.records.toLocaleString()} records${d.behind && d.behind[n] ? ` (${d.behind[n].toLocaleString()} still to read)` : ""}`)
    .join(" · ");
  const faults = (d.faults || []).map(f => `${f.kind} at ${f.t.toFixed(3)} s: ${f.text}`);
  if (d.latched) faults.push(`interlock latched: ${d.latched}`);
  document.getElementById("faults").textContent = faults.join(" · ");
  const live = d.state === "running" || d.state === "paused";
  document.getElementById("pause").disabled = !live || d.state === "paused";
  document.getElementById("stop").disabled = !live;
}

async function poll() {
  try {
    if (!run) {
      const r = await fetch("api/runs", {headers, cache: "no-store"});
      if (!r.ok) throw new Error((await r.json()).error || r.statusText);
      const runs = (await r.json()).runs;
      const sel = document.getElementById("run");
      sel.replaceChildren(...runs.map(n => el("option", {value: n}, n)));
      run = runs[0] || null;
      sel.onchange = () => { location.search = new URLSearchParams({...(token ? {token} : {}), run: sel.value}); };
      if (!run) throw new Error("no run file served yet");
    }
    const r = await fetch(`api/runs/${encodeURIComponent(run)}?have=${encodeURIComponent(have())}`,
                          {headers, cache: "no-store"});
    if (!r.ok) throw new Error((await r.json()).error || r.statusText);
    const d = await r.json();
    latest = d;
    for (const [name, s] of Object.entries(d.streams)) merge(name, s);
    const sel = document.getElementById("run");
    if (!sel.options.length) sel.appendChild(el("option", {value: run}, run));
    show(d);
    redraw();
    state.polls += 1;
    state.state = d.state;
    state.error = "";
  } catch (err) {
    state.error = String(err.message || err);
    document.getElementById("state").textContent = `no answer: ${state.error}`;
    document.getElementById("state").className = "state";
  }
  setTimeout(poll, POLL_MS);
}

async function act(what) {
  const msg = document.getElementById("message");
  try {
    const r = await fetch(`api/runs/${encodeURIComponent(run)}/${what}`,
                          {method: "POST", headers: {...headers, "X-Bench": "1"}});
    const d = await r.json();
    msg.textContent = r.ok ? `${what} asked (recorded as ${d.by})` : `refused: ${d.error}`;
  } catch (err) {
    msg.textContent = `refused: ${err}`;
  }
}

document.getElementById("pause").onclick = () => act("pause");
document.getElementById("stop").onclick = () => act("stop");
window.addEventListener("resize", () => {
  const w = Math.max(400, document.getElementById("panels").clientWidth - 10);
  for (const p of Object.values(panels)) p.plot.setSize({width: w, height: 170});
});
poll();
