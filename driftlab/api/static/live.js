// driftlab live page: follows /live/events (server-sent events) and draws every campaign on show.
// No library: SVG strip charts drawn here. Units on the page: degC, um (lengths), urad (angles),
// mm (positions; deg for the rotary axes A and B), campaign time in h:mm:ss since the start.
"use strict";

const state = { campaigns: new Map(), serverSkewMs: 0, updates: 0, lastLagMs: null };
const PALETTE = ["#2456a6", "#c0392b", "#1f7a3a", "#8e44ad", "#d35400", "#16a085", "#7f8c8d", "#b8860b",
  "#2c3e50", "#e84393", "#0984e3", "#6ab04c"];
const TERM_NAMES = { dx: "translation along X", dy: "translation along Y", dz: "translation along Z",
  alpha: "rotation about X", beta: "rotation about Y", gamma: "rotation about Z" };
const ANGLES = new Set(["alpha", "beta", "gamma"]);

function el(tag, attrs, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === null || v === undefined) continue;
    if (k === "class") node.className = v; else if (k === "text") node.textContent = v; else node.setAttribute(k, v);
  }
  for (const c of children) if (c !== null && c !== undefined) node.append(c);
  return node;
}

function svg(tag, attrs) {
  const node = document.createElementNS("http://www.w3.org/2000/svg", tag);
  for (const [k, v] of Object.entries(attrs || {})) node.setAttribute(k, v);
  return node;
}

function clock(s) {
  if (s === null || s === undefined || !isFinite(s)) return "-";
  const neg = s < 0; s = Math.abs(Math.round(s));
  const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), sec = s % 60;
  return (neg ? "-" : "") + `${h}:${String(m).padStart(2, "0")}:${String(sec).padStart(2, "0")}`;
}

function span(s) {  // a duration in words
  if (s === null || s === undefined || !isFinite(s)) return "-";
  if (s < 90) return `${s.toFixed(s < 10 ? 1 : 0)} s`;
  if (s < 5400) return `${Math.round(s / 60)} min`;
  return `${(s / 3600).toFixed(1)} h`;
}

function fmt(v, digits) { return v === null || v === undefined || !isFinite(v) ? "-" : v.toFixed(digits); }

function natural(a, b) { return a.localeCompare(b, undefined, { numeric: true }); }

// ---------------------------------------------------------------- merging what the server sends

function setCampaign(c) {
  state.campaigns.set(c.campaign_id, {
    head: c, channels: c.channels, window_s: c.window_s,
    temps: { b: c.temperatures.b.slice(), t: c.temperatures.t.slice(),
             values: Object.fromEntries(Object.entries(c.temperatures.values).map(([k, v]) => [k, v.slice()])) },
    errors: c.errors,
  });
}

function mergeUpdate(u) {
  const cur = state.campaigns.get(u.campaign_id);
  if (!cur) return false;  // a snapshot of it is on its way
  cur.head = Object.assign({}, cur.head, u, { channels: cur.channels });
  const T = cur.temps, nb = u.temperatures.b;
  if (nb.length) {
    // buckets are in time order; the first new one may repeat (with more scans) the last we hold
    while (T.b.length && T.b[T.b.length - 1] >= nb[0]) {
      T.b.pop(); T.t.pop(); for (const k in T.values) T.values[k].pop();
    }
    T.b.push(...nb); T.t.push(...u.temperatures.t);
    for (const k in T.values) T.values[k].push(...(u.temperatures.values[k] || nb.map(() => null)));
    const since = T.t[T.t.length - 1] - cur.window_s;
    let cut = 0; while (cut < T.t.length && T.t[cut] < since) cut++;
    if (cut) { T.b.splice(0, cut); T.t.splice(0, cut); for (const k in T.values) T.values[k].splice(0, cut); }
  }
  const E = cur.errors, ne = u.errors;
  const last = E.seq.length ? E.seq[E.seq.length - 1] : -Infinity;
  for (let i = 0; i < ne.seq.length; i++) {
    if (ne.seq[i] <= last) continue;
    for (const k in E) E[k].push(ne[k][i]);
  }
  const tmax = cur.head.progress.time_s;
  if (tmax !== null && E.t.length) {
    let cut = 0; while (cut < E.t.length && (E.t[cut] < tmax - cur.window_s || E.t.length - cut > 4000)) cut++;
    if (cut) for (const k in E) E[k].splice(0, cut);
  }
  return true;
}

// ---------------------------------------------------------------- charts

function lineChart(series, opts) {
  // series: [{name, color, x: [], y: [], width?, opacity?, dots?}]; returns an <svg>
  const W = 560, H = 170, L = 46, R = 8, Tp = 8, B = 24;
  const root = svg("svg", { class: "chart", viewBox: `0 0 ${W} ${H}`, role: "img",
                           "aria-label": opts.label });
  let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
  for (const s of series) for (let i = 0; i < s.x.length; i++) {
    const y = s.y[i]; if (y === null || !isFinite(y)) continue;
    x0 = Math.min(x0, s.x[i]); x1 = Math.max(x1, s.x[i]); y0 = Math.min(y0, y); y1 = Math.max(y1, y);
  }
  if (opts.xRange) { x0 = opts.xRange[0]; x1 = opts.xRange[1]; }
  if (!isFinite(x0)) { root.append(svgText(W / 2, H / 2, "no readings yet", "middle")); return root; }
  if (x1 - x0 < 1e-9) { x0 -= 1; x1 += 1; }
  const pad = Math.max((y1 - y0) * 0.08, opts.minSpan || 0.05);
  y0 -= pad; y1 += pad;
  const sx = (x) => L + (x - x0) / (x1 - x0) * (W - L - R), sy = (y) => Tp + (y1 - y) / (y1 - y0) * (H - Tp - B);
  for (const f of [0, 0.5, 1]) {
    const yv = y0 + f * (y1 - y0), xv = x0 + f * (x1 - x0);
    root.append(svg("line", { class: "grid", x1: L, x2: W - R, y1: sy(yv), y2: sy(yv) }));
    root.append(svgText(L - 4, sy(yv) + 3, yv.toFixed(opts.yDigits ?? 1), "end"));
    root.append(svgText(sx(xv), H - B + 13, opts.xFmt ? opts.xFmt(xv) : xv.toFixed(0), f === 0 ? "start" : f === 1 ? "end" : "middle"));
  }
  root.append(svg("line", { class: "axis", x1: L, x2: L, y1: Tp, y2: H - B }));
  root.append(svg("line", { class: "axis", x1: L, x2: W - R, y1: H - B, y2: H - B }));
  root.append(svgText(W - R, H - 2, opts.xLabel, "end"));
  for (const s of series) {
    let d = "", pen = false;
    for (let i = 0; i < s.x.length; i++) {
      const y = s.y[i];
      if (y === null || !isFinite(y)) { pen = false; continue; }
      d += `${pen ? "L" : "M"}${sx(s.x[i]).toFixed(1)},${sy(y).toFixed(1)}`; pen = true;
      if (s.dots) d += `m-1.5,0a1.5,1.5 0 1,0 3,0a1.5,1.5 0 1,0 -3,0m-1.5,0`;
    }
    if (d) root.append(svg("path", { d, stroke: s.color, "stroke-width": s.width || 1.4, "stroke-opacity": s.opacity ?? 1 }));
  }
  return root;
}

function svgText(x, y, text, anchor) {
  const t = svg("text", { x, y, "text-anchor": anchor }); t.textContent = text; return t;
}

// ---------------------------------------------------------------- drawing one campaign

function stageBlock(h) {
  const st = h.stage, p = h.progress, n = h.stages.length;
  const box = el("div", { class: "box" }, el("h3", { text: "Stage" }));
  const name = st ? st.name : "-";
  box.append(el("div", { class: "big" }, el("span", { "data-live": "stage", text: name })));
  if (st) {
    const heat = st.heat_source && st.heat_source !== "none" ? st.heat_source : "no heat source";
    const bits = [`${st.ordinal + 1} of ${n}`, `axis ${st.axis || "-"}`, heat];
    if (st.spindle_rpm) bits.push(`spindle ${Math.round(st.spindle_rpm)} rpm`);
    if (st.feed_mm_min) bits.push(`feed ${Math.round(st.feed_mm_min)} mm/min`);
    box.append(el("p", { class: "sub", text: bits.join(" \u00b7 ") }));
    box.append(el("p", { class: "sub", "data-live": "setup", text: "setup: " + setupText(st.setup, h) }));
    const f = p.stage_fraction ?? 0;
    box.append(el("div", { class: "bar", title: `${(100 * f).toFixed(0)} % of the stage` },
      el("span", { style: `width:${(100 * f).toFixed(1)}%` })));
    const wall = p.stage_left_wall_s !== null && h.speed && h.speed !== 1 ? ` (about ${span(p.stage_left_wall_s)} of wall-clock time at \u00d7${h.speed})` : "";
    // a finished campaign is done; one nobody runs (stale, stopped) has no time "left"
    const left = h.status === "done" ? "campaign done"
      : h.stale_since ? `stale since ${h.stale_since}: the daemon stopped beating`
      : p.stage_left_s === null ? `${h.status}` : `${span(p.stage_left_s)} of campaign time left${wall}`;
    box.append(el("p", { class: "sub num", "data-live": "stage-left", text: `${(100 * f).toFixed(0)} % done, ${left}` }));
  }
  const tl = el("div", { class: "timeline", "aria-label": "stages" });
  const total = p.total_s || 1;
  for (const s of h.stages) {
    const w = Math.max(((s.end_s ?? total) - s.start_s) / total * 100, 0.5);
    tl.append(el("span", { class: s.status, style: `width:${w}%`, title: `${s.name}: ${s.status}`, text: s.name }));
  }
  box.append(tl);
  return box;
}

function setupText(setup, h) {
  if (setup) {
    const parts = [setup.id, setup.instrument, setup.optics || setup.fixture,
      Array.isArray(setup.terms) ? "terms " + setup.terms.join(", ") : null].filter(Boolean);
    return parts.join(", ");
  }
  const st = h.stage; if (!st) return "-";
  const cur = state.campaigns.get(h.campaign_id), E = cur ? cur.errors : null;
  const terms = new Set();
  if (E) for (let i = 0; i < E.t.length; i++) if (E.t[i] >= st.start_s && E.axis[i] === st.axis) terms.add(E.term[i]);
  return terms.size ? `${st.axis} axis, measuring ${[...terms].join(", ")}` : `${st.axis} axis (no sweep readings yet in this stage)`;
}

function progressBlock(h) {
  const p = h.progress;
  const box = el("div", { class: "box" }, el("h3", { text: "Progress" }));
  box.append(el("div", { class: "bar", title: `${(100 * p.fraction).toFixed(1)} %` },
    el("span", { style: `width:${(100 * p.fraction).toFixed(1)}%` })));
  const latest = h.latest;
  const dl = el("dl", { class: "kv" });
  const add = (k, v) => dl.append(el("dt", { text: k }), el("dd", {}, v));
  add("scans stored", el("span", {}, el("span", { "data-live": "scans", text: String(p.scans) }), ` of ${p.n_scans}`));
  add("sweep points", `${p.points} of ${p.n_points}`);
  add("latest scan", el("time", { "data-live": "latest-time", datetime: latest ? latest.at : null,
    "data-seconds": latest ? String(latest.time_s) : null,
    text: latest ? `${clock(latest.time_s)} into the campaign` : "none yet" }));
  add("campaign left", `${span(p.total_left_s)}` + (p.total_left_wall_s !== null && h.speed && h.speed !== 1 ? ` (\u2248 ${span(p.total_left_wall_s)} wall-clock)` : ""));
  const age = h.updated_at ? (Date.now() - state.serverSkewMs - Date.parse(h.updated_at)) / 1000 : null;
  add("last commit", el("span", { "data-live": "commit-age", class: age > 120 && h.status === "running" ? "warn" : null,
    text: age === null ? "-" : `${span(Math.max(age, 0))} ago` }));
  box.append(dl);
  return box;
}

function healthBlock(h) {
  const x = h.health;
  const box = el("div", { class: "box" }, el("h3", { text: "Instrument health" }));
  const dl = el("dl", { class: "kv" });
  const add = (k, v, cls) => dl.append(el("dt", { text: k }), el("dd", { class: cls, "data-live": "health-" + k.split(" ")[0] }, v));
  add("faults", String(x.faults), x.faults ? "warn" : "ok");
  add("timeouts", `${x.timeouts}` + (x.counted_over < x.faults ? ` in the last ${x.counted_over} faults` : ""), x.timeouts ? "warn" : "ok");
  if (x.retries) add("retries", Object.entries(x.retries).map(([k, v]) => `${k} ${v}`).join(", "));
  add("open thermocouples", x.open.length ? x.open.join(", ") : "none", x.open.length ? "bad" : "ok");
  const by = Object.entries(x.by_instrument);
  if (by.length) add("by instrument", by.map(([k, v]) => `${k} ${v}`).join(", "));
  box.append(dl);
  if (x.recent.length) {
    const ul = el("ul", { class: "faults" });
    for (const f of x.recent.slice().reverse())
      ul.append(el("li", { text: `${clock(f.t_s)} ${f.instrument} (${f.step}): ${f.message}` }));
    box.append(ul);
  }
  return box;
}

function temperatureCharts(cur) {
  const h = cur.head, T = cur.temps, latest = (h.latest && h.latest.values) || {};
  const groups = new Map();
  for (const c of cur.channels) {
    const g = c.room ? "room" : c.structure;
    if (!groups.has(g)) groups.set(g, []);
    groups.get(g).push(c);
  }
  const wrap = el("div", { class: "structures" });
  const hours = T.t.map((t) => t / 3600);
  const tEnd = h.progress.time_s !== null ? h.progress.time_s / 3600 : null;
  const xRange = tEnd !== null ? [Math.max(tEnd - cur.window_s / 3600, 0), Math.max(tEnd, 1 / 60)] : null;
  for (const [g, chans] of [...groups.entries()].sort((a, b) => natural(a[0], b[0]))) {
    chans.sort((a, b) => natural(a.name, b.name));
    const series = chans.map((c, i) => ({ name: c.name, color: PALETTE[i % PALETTE.length], x: hours, y: T.values[c.name] || [] }));
    const box = el("div", { class: "box", "data-structure": g });
    box.append(el("h3", { text: `${g.replace(/_/g, " ")}: ${chans.length} thermocouple${chans.length > 1 ? "s" : ""}, \u00b0C` }));
    box.append(lineChart(series, { label: `temperatures of the ${g}`, xLabel: "campaign time (h)", yLabel: "\u00b0C",
      yDigits: 1, minSpan: 0.2, xRange, xFmt: (v) => v.toFixed(1) }));
    const leg = el("div", { class: "legend" });
    chans.forEach((c, i) => {
      const v = latest[c.name];
      const open = c.name in latest && v === null;
      leg.append(el("span", { class: open ? "open" : null, title: c.location || c.name, "data-channel": c.name },
        el("i", { style: `background:${PALETTE[i % PALETTE.length]}` }),
        `${c.name} ${open ? "open" : fmt(v, 2) + " \u00b0C"}`));
    });
    box.append(leg);
    wrap.append(box);
  }
  return wrap;
}

function errorCharts(cur) {
  const E = cur.errors, wrap = el("div", { class: "errors" });
  const keys = new Map();
  for (let i = 0; i < E.seq.length; i++) {
    const k = `${E.axis[i]}/${E.term[i]}`;
    if (!keys.has(k)) keys.set(k, []);
    keys.get(k).push(i);
  }
  if (!keys.size) { wrap.append(el("p", { class: "sub", text: "No error readings in the window yet." })); return wrap; }
  for (const [k, idx] of [...keys.entries()].sort()) {
    const [axis, term] = k.split("/");
    const angle = ANGLES.has(term), scale = angle ? 1e6 : 1e3, unit = angle ? "\u00b5rad" : "\u00b5m";
    const posUnit = axis === "A" || axis === "B" ? "deg" : "mm";
    const sweeps = new Map();
    for (const i of idx) {
      const s = `${E.sweep[i]}:${E.direction[i]}`;
      if (!sweeps.has(s)) sweeps.set(s, { dir: E.direction[i], pts: [] });
      sweeps.get(s).pts.push([E.position[i], E.value[i] * scale, E.t[i]]);
    }
    const list = [...sweeps.values()].slice(-8);
    const series = list.map((s, j) => {
      s.pts.sort((a, b) => a[0] - b[0]);
      const newest = j >= list.length - 2;
      return { name: "", color: s.dir > 0 ? "#2456a6" : "#c0392b", x: s.pts.map((p) => p[0]), y: s.pts.map((p) => p[1]),
               dots: true, width: newest ? 2 : 1, opacity: newest ? 1 : 0.25 + 0.5 * j / list.length };
    });
    const lastI = idx[idx.length - 1];
    const box = el("div", { class: "box", "data-term": k });
    box.append(el("h3", { text: `${axis} axis \u00b7 ${term} (${TERM_NAMES[term] || term}), ${unit}` }));
    box.append(lineChart(series, { label: `${term} error against ${axis} position`, xLabel: `${axis} position (${posUnit})`,
      yLabel: unit, yDigits: 1, minSpan: 0.5 }));
    box.append(el("div", { class: "legend" },
      el("span", {}, el("i", { style: "background:#2456a6" }), "approach +"),
      el("span", {}, el("i", { style: "background:#c0392b" }), "approach \u2212"),
      el("span", { class: "num", text: `latest ${fmt(E.value[lastI] * scale, 1)} ${unit} at ${E.position[lastI]} ${posUnit} (${clock(E.t[lastI])}); last ${list.length} sweeps, newest darkest` })));
    wrap.append(box);
  }
  return wrap;
}

function campaignSection(cur) {
  const h = cur.head;
  const sec = el("section", { class: "campaign", "data-campaign-id": String(h.campaign_id), "aria-label": `campaign ${h.name}` });
  const mode = h.mode === "sim" ? `virtual machine${h.speed ? ` at \u00d7${h.speed}` : ""}` : "instruments";
  const shown = h.stale_since ? `stale since ${h.stale_since}` : h.status;
  sec.append(el("h2", {}, `${h.name} `, el("span", { class: `badge ${h.stale_since ? "stale" : h.status}`, "data-live": "status", text: shown })));
  sec.append(el("p", { class: "sub", text: `campaign ${h.campaign_id} \u00b7 machine ${h.machine} \u00b7 ${mode} \u00b7 started ${h.started_at ? new Date(h.started_at).toLocaleString() : "-"}` }));
  sec.append(el("div", { class: "grid" }, stageBlock(h), progressBlock(h), healthBlock(h)));
  sec.append(el("h4", { text: `Thermocouples, last ${span(cur.window_s)} by structure (latest scan in the legend)` }));
  sec.append(temperatureCharts(cur));
  sec.append(el("h4", { text: "Error readings as they arrive (value against position, per term)" }));
  sec.append(errorCharts(cur));
  return sec;
}

let pending = false;
function render() {
  if (pending) return;
  pending = true;
  requestAnimationFrame(() => {
    pending = false;
    const main = document.getElementById("campaigns");
    const sections = [...state.campaigns.values()].sort((a, b) =>
      (a.head.status === "running" ? 0 : 1) - (b.head.status === "running" ? 0 : 1) || b.head.campaign_id - a.head.campaign_id);
    main.replaceChildren();
    if (!sections.length) {
      main.append(el("p", { class: "empty", id: "empty", text: "No campaign is running. Start one with " +
        "driftlab daemon --plan PLAN.yaml (add --sim SCENARIO.yaml for the virtual machine); it appears here at its first commit." }));
    }
    for (const cur of sections) main.append(campaignSection(cur));
    document.body.dataset.updates = String(state.updates);
    if (state.lastLagMs !== null) document.body.dataset.lagMs = String(Math.round(state.lastLagMs));
  });
}

// ---------------------------------------------------------------- the stream

function connect() {
  const conn = document.getElementById("conn");
  const es = new EventSource("/live/events");
  const skew = (serverTime) => { if (serverTime) state.serverSkewMs = Date.now() - Date.parse(serverTime); };
  es.addEventListener("open", () => { conn.dataset.state = "open"; conn.textContent = "live"; });
  es.addEventListener("error", () => { conn.dataset.state = "retry"; conn.textContent = "connection lost, reconnecting\u2026"; });
  es.addEventListener("snapshot", (ev) => {
    const doc = JSON.parse(ev.data);
    skew(doc.server_time);
    state.campaigns.clear();
    for (const c of doc.campaigns) setCampaign(c);
    conn.dataset.state = "open"; conn.textContent = "live";
    render();
  });
  es.addEventListener("campaign", (ev) => {
    const doc = JSON.parse(ev.data);
    setCampaign(doc.campaign);
    render();
  });
  es.addEventListener("update", (ev) => {
    const doc = JSON.parse(ev.data);
    if (mergeUpdate(doc.campaign)) {
      state.updates += 1;
      // commit (stored by the daemon) to page: measured on this page's clock, corrected by the server's
      if (doc.campaign.updated_at) state.lastLagMs = Date.now() - state.serverSkewMs - Date.parse(doc.campaign.updated_at);
      render();
    }
  });
  es.addEventListener("gone", (ev) => { state.campaigns.delete(JSON.parse(ev.data).campaign_id); render(); });
}

connect();
setInterval(render, 5000);  // keeps "last commit ... ago" current when nothing arrives
