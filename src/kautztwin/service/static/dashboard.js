// kautztwin live dashboard: polls the twin's HTTP API and draws on <canvas>.
// No third-party code, no network beyond this server.  MIT, see LICENSE.txt.
"use strict";
(function () {
  const MAX = 3000;            // samples kept (bounded: the page stays responsive for hours)
  const MAX_EVENTS = 200;
  const COLORS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#d62728"];
  const buf = { t: [], y: [], yp: [], sp: [], u: [], fit: [], mpc: [] };
  let seq = 0, lastEvent = 0, events = [], whatif = null, info = {}, models = [];
  const $ = (id) => document.getElementById(id);
  const tokenBox = $("token");
  tokenBox.value = sessionStorage.getItem("kautztwin-token") || "";
  tokenBox.addEventListener("change", () => sessionStorage.setItem("kautztwin-token", tokenBox.value));

  function headers(json) {
    const h = {};
    if (json) h["Content-Type"] = "application/json";
    if (tokenBox.value) h["Authorization"] = "Bearer " + tokenBox.value;
    return h;
  }
  async function getJSON(path) {
    const r = await fetch(path, { headers: headers(false) });
    if (!r.ok) throw new Error(path + ": " + r.status);
    return r.json();
  }
  async function post(path, body) {
    const r = await fetch(path, { method: "POST", headers: headers(true), body: JSON.stringify(body) });
    let data = null;
    try { data = await r.json(); } catch (e) { data = {}; }
    if (!r.ok) throw new Error(r.status + ": " + (data.message || data.detail || r.statusText));
    return data;
  }
  function push(arr, v) { arr.push(v === null || v === undefined ? NaN : v); if (arr.length > MAX) arr.shift(); }

  // ------------------------------------------------------------------ plotting
  function niceTicks(lo, hi, n) {
    const span = hi - lo || 1, step0 = span / n, mag = Math.pow(10, Math.floor(Math.log10(step0)));
    let step = mag;   // the round step whose tick count is closest to n
    for (const m of [1, 2, 2.5, 5, 10]) if (Math.abs(span / (m * mag) - n) < Math.abs(span / step - n)) step = m * mag;
    const out = [];
    for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-9 * span; v += step) out.push(v);
    return out;
  }
  function fmt(v) { const a = Math.abs(v); return a >= 1000 || (a < 0.01 && a > 0) ? v.toExponential(1) : +v.toPrecision(4) + ""; }
  function range(arrays) {
    let lo = Infinity, hi = -Infinity;
    for (const a of arrays) for (const v of a) if (isFinite(v)) { if (v < lo) lo = v; if (v > hi) hi = v; }
    if (!isFinite(lo)) return [0, 1];
    if (hi - lo < 1e-9) { lo -= 0.5; hi += 0.5; }
    const pad = 0.05 * (hi - lo);
    return [lo - pad, hi + pad];
  }
  // series: [{x, y, color, dash, width}], bands: [{x, lo, hi, color}], marks: [{x, color}]
  function plot(canvas, series, opts) {
    opts = opts || {};
    const dpr = window.devicePixelRatio || 1, w = canvas.clientWidth || 600, h = canvas.height / (canvas._dpr || 1);
    canvas._dpr = dpr; canvas.width = w * dpr; canvas.height = h * dpr;
    const g = canvas.getContext("2d");
    g.setTransform(dpr, 0, 0, dpr, 0, 0);
    g.clearRect(0, 0, w, h);
    const L = 52, R = 8, T = 6, B = 20, pw = w - L - R, ph = h - T - B;
    const xs = series.map((s) => s.x).concat((opts.bands || []).map((b) => b.x));
    const ys = series.map((s) => s.y).concat((opts.bands || []).flatMap((b) => [b.lo, b.hi]));
    const [x0, x1] = opts.xrange || range(xs);
    const [y0, y1] = opts.yrange || range(ys);
    const X = (v) => L + (v - x0) / (x1 - x0) * pw, Y = (v) => T + ph - (v - y0) / (y1 - y0) * ph;
    g.strokeStyle = "#e4e4e4"; g.fillStyle = "#666"; g.font = "11px sans-serif"; g.lineWidth = 1;
    for (const v of niceTicks(y0, y1, 4)) { g.beginPath(); g.moveTo(L, Y(v)); g.lineTo(L + pw, Y(v)); g.stroke(); g.fillText(fmt(v), 2, Y(v) + 4); }
    for (const v of niceTicks(x0, x1, 8)) { g.beginPath(); g.moveTo(X(v), T); g.lineTo(X(v), T + ph); g.stroke(); g.fillText(fmt(v), X(v) - 10, h - 5); }
    g.save(); g.beginPath(); g.rect(L, T, pw, ph); g.clip();
    for (const m of opts.marks || []) {
      if (m.x < x0 || m.x > x1) continue;
      g.strokeStyle = m.color; g.setLineDash([3, 3]); g.beginPath(); g.moveTo(X(m.x), T); g.lineTo(X(m.x), T + ph); g.stroke();
    }
    g.setLineDash([]);
    for (const b of opts.bands || []) {
      g.fillStyle = b.color; g.beginPath();
      b.x.forEach((v, i) => (i ? g.lineTo(X(v), Y(b.hi[i])) : g.moveTo(X(v), Y(b.hi[i]))));
      for (let i = b.x.length - 1; i >= 0; i--) g.lineTo(X(b.x[i]), Y(b.lo[i]));
      g.closePath(); g.fill();
    }
    for (const s of series) {
      g.strokeStyle = s.color; g.lineWidth = s.width || 1.3; g.setLineDash(s.dash || []);
      g.beginPath(); let pen = false;
      const step = Math.max(1, Math.floor(s.x.length / (2 * pw)));   // at most ~2 points a pixel
      for (let i = 0; i < s.x.length; i += step) {
        const a = s.x[i], b = s.y[i];
        if (!isFinite(a) || !isFinite(b)) { pen = false; continue; }
        if (pen) g.lineTo(X(a), Y(b)); else { g.moveTo(X(a), Y(b)); pen = true; }
      }
      g.stroke();
    }
    g.restore(); g.setLineDash([]);
    g.strokeStyle = "#999"; g.strokeRect(L, T, pw, ph);
    canvas.dataset.points = String(series.reduce((n, s) => n + s.x.length, 0));
  }
  function eventColor(kind) {
    if (kind.startsWith("api-")) return COLORS[2];
    if (kind === "model-version") return COLORS[1];
    if (kind === "drift" || kind === "desync") return COLORS[4];
    return null;
  }
  function draw() {
    const t = buf.t;
    let xr = range([t]);
    if (whatif) xr = [xr[0], Math.max(xr[1], whatif.t[whatif.t.length - 1])];
    const marks = events.filter((e) => e.t !== null && eventColor(e.kind)).map((e) => ({ x: e.t, color: eventColor(e.kind) }));
    const ys = [{ x: t, y: buf.yp, color: COLORS[1], width: 2.2 }, { x: t, y: buf.y, color: COLORS[0], width: 1 },
                { x: t, y: buf.sp, color: COLORS[2], dash: [6, 3] }];
    const bands = [];
    if (whatif) {
      ys.push({ x: whatif.t, y: whatif.y, color: COLORS[3], width: 2 });
      if (whatif.lower) bands.push({ x: whatif.t, lo: whatif.lower, hi: whatif.upper, color: "rgba(148,103,189,0.18)" });
    }
    plot($("plot-y"), ys, { xrange: xr, bands: bands, marks: marks });
    const us = [{ x: t, y: buf.u, color: COLORS[0] }];
    if (whatif) us.push({ x: whatif.t, y: whatif.u, color: COLORS[3], dash: [4, 2] });
    plot($("plot-u"), us, { xrange: xr });
    plot($("plot-fit"), [{ x: t, y: buf.fit, color: COLORS[0] }], { xrange: xr, marks: marks });
    plot($("plot-mpc"), [{ x: t, y: buf.mpc, color: COLORS[0] }], { xrange: xr });
    drawTimeline();
  }
  function drawTimeline() {
    const c = $("timeline"), dpr = window.devicePixelRatio || 1, w = c.clientWidth || 300, h = 46;
    c.width = w * dpr; c.height = h * dpr;
    const g = c.getContext("2d"); g.setTransform(dpr, 0, 0, dpr, 0, 0); g.clearRect(0, 0, w, h);
    const tEnd = buf.t.length ? buf.t[buf.t.length - 1] : 1;
    const ts = models.map((m) => (m.t === null ? 0 : m.t));
    const t0 = 0, t1 = Math.max(tEnd, ...ts, 1e-9);
    const X = (v) => 6 + (v - t0) / (t1 - t0) * (w - 12);
    g.strokeStyle = "#999"; g.beginPath(); g.moveTo(6, 24); g.lineTo(w - 6, 24); g.stroke();
    g.font = "10px sans-serif";
    models.forEach((m, i) => {
      const x = X(ts[i]);
      g.fillStyle = m.active ? COLORS[1] : COLORS[0];
      g.beginPath(); g.arc(x, 24, m.active ? 5 : 3.5, 0, 2 * Math.PI); g.fill();
      g.fillText("v" + m.version, x - 6, i % 2 ? 42 : 14);
    });
  }

  // ------------------------------------------------------------------ data
  function add(samples) {
    for (const s of samples) {
      push(buf.t, s.t); push(buf.y, s.y); push(buf.yp, s.y_pred); push(buf.sp, s.setpoint);
      push(buf.u, s.u); push(buf.fit, s.fit); push(buf.mpc, s.mpc_ms);
      seq = s.seq;
    }
  }
  function status(s) {
    const f = (v, d) => (v === null || v === undefined ? "-" : (+v).toFixed(d));
    $("status").textContent = "k " + (s.k ?? "-") + "  t " + f(s.t, 2) + " s  " + (s.phase || "") +
      "  v" + (s.version ?? "-") + "  fit " + f(s.fit, 1) + " %  y " + f(s.y, 3) + "  u " + f(s.u, 3) +
      "  sp " + f(s.setpoint, 3) + "  link " + (s.link || "-") + (s.running ? "" : "  (stopped)");
    if (s.plant) $("plant").textContent = s.plant;
    if (s.setpoint_limits) {
      const [lo, hi] = s.setpoint_limits;
      $("sp-limits").textContent = "limits: " + (lo === null ? "-inf" : lo) + " ... " + (hi === null ? "inf" : hi);
    }
  }
  async function poll() {
    try {
      const r = await getJSON("/recent?since=" + seq);
      if (r.seq < seq) { for (const k in buf) buf[k].length = 0; seq = 0; }   // the service restarted
      add(r.samples);
      info = await getJSON("/state");
      status(info);
    } catch (e) { $("status").textContent = "no connection: " + e.message; }
    draw();
  }
  async function slowPoll() {
    try {
      const ev = await getJSON("/events?after=" + lastEvent + "&limit=500");
      for (const e of ev.events) {
        lastEvent = e.id; events.push(e);
        const li = document.createElement("li");
        li.textContent = (e.t === null ? "" : e.t.toFixed(2) + " s ") + e.kind + ": " + e.message;
        $("events").prepend(li);
        while ($("events").children.length > MAX_EVENTS) $("events").lastChild.remove();
      }
      if (events.length > MAX_EVENTS) events = events.slice(-MAX_EVENTS);
      models = await getJSON("/models");
      const body = $("models").querySelector("tbody"); body.textContent = "";
      for (const m of models.slice(-12)) {
        const tr = document.createElement("tr"); if (m.active) tr.className = "active";
        for (const v of [m.version, m.t === null ? "-" : m.t.toFixed(1), m.method, m.fit_percent === null ? "-" : m.fit_percent.toFixed(1)]) {
          const td = document.createElement("td"); td.textContent = v; tr.appendChild(td);
        }
        body.appendChild(tr);
      }
    } catch (e) { /* the store is not open yet */ }
  }
  function show(id, text, error) { const el = $(id); el.textContent = text; el.className = "result" + (error ? " error" : ""); }

  $("sp-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    try {
      const r = await post("/setpoint", { value: parseFloat($("sp-value").value) });
      show("sp-result", "set-point " + r.setpoint + " from sample " + r.k_from);
    } catch (e) { show("sp-result", e.message, true); }
  });
  $("wi-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const mode = document.querySelector("input[name=wi-mode]:checked").value;
    const steps = parseInt($("wi-steps").value, 10);
    const body = mode === "u" ? { u: $("wi-u").value.split(",").map(Number) }
                              : { setpoint: parseFloat($("wi-sp").value), steps: steps };
    try {
      whatif = await post("/whatif", body);
      show("wi-result", "predicted " + whatif.y.length + " samples from k " + whatif.k + " (model v" + whatif.version + ")");
      draw();
    } catch (e) { show("wi-result", e.message, true); }
  });
  $("reid").addEventListener("click", async () => {
    try { const r = await post("/reidentify", { reason: "dashboard" }); show("reid-result", "scheduled at sample " + r.k); }
    catch (e) { show("reid-result", e.message, true); }
  });
  window.addEventListener("resize", draw);
  window.kautztwinDashboard = { buf: buf, get whatif() { return whatif; } };
  poll(); slowPoll();
  setInterval(poll, 300);
  setInterval(slowPoll, 2000);
})();
