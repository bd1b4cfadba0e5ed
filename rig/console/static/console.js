// The rig console page: live state and traces from the websocket, commands back over it.
// Figures for tests and benchmarks are kept in window.rigStats (updates, renders, click-to-shown latencies, and
// each plot's axis labels and tick texts as last drawn).
"use strict";
(() => {
  const $ = (id) => document.getElementById(id);
  const TRACE_S = 10;
  const stats = window.rigStats = {deltas: 0, renders: 0, renderTimes: [], renderMs: [], isoLatencyMs: [],
                                   replies: [], attached: 0, seq: 0, lastNow: null, axes: {}};
  const QUANT = [  // per mount: what, unit shown, scale from SI, the limit's key in layout.limits
    {name: "acceleration", unit: "m/s²", k: 1, lim: "accel_range_mps2"},
    {name: "stroke", unit: "µm", k: 1e6, lim: "stroke_limit_m"},
    {name: "valve command", unit: "V", k: 1, lim: "valve_limit_V"},
  ];
  let layout = null, readOnly = true, ended = null, hello = {};
  let lastEvent = 0;     // the newest event shown (events are numbered by the server; a full state repeats some)
  let tr = {t: [], v: []};
  let charts = [];
  let specChart = null, vcChart = null;
  let dirty = false, pendingIso = null, frame = 0;
  let now = {}, status = {};
  let ws = null;

  // ---- connection ------------------------------------------------------------------------------------------
  function connect() {
    ws = new WebSocket(`ws://${location.host}/ws`);
    ws.onopen = () => setConn("live", "connected");
    ws.onclose = () => {
      setConn("lost", ended ? "run ended" : "disconnected");
      if (!ended) setTimeout(connect, 1000);
    };
    ws.onmessage = (ev) => handle(JSON.parse(ev.data));
  }
  function setConn(cls, text) { const c = $("conn"); c.className = "conn " + cls; c.textContent = text; }

  let nextId = 0;
  function command(cmd, args) {
    if (readOnly || !ws || ws.readyState !== 1) return;
    nextId += 1;
    ws.send(JSON.stringify({id: nextId, cmd, args: args || {}}));
  }

  // ---- messages ----------------------------------------------------------------------------------------------
  function handle(msg) {
    if (msg.type === "full") return full(msg);
    if (msg.type === "delta") return delta(msg);
    if (msg.type === "reply") {
      stats.replies.push(msg);
      const r = $("reply");
      r.textContent = msg.text;
      r.className = "reply" + (msg.ok ? "" : " refused");
      return;
    }
    if (msg.type === "ended") {
      ended = msg.reason;
      $("ended").hidden = false;
      $("ended").textContent = `The run has ended: ${msg.reason}`;
      setControls();
    }
  }

  function full(msg) {
    readOnly = msg.read_only;
    hello = msg.hello || {};
    $("readonly").hidden = !readOnly;
    $("backend").textContent = hello.backend || "";
    stats.attached = msg.attached;
    if (msg.layout) {
      layout = msg.layout;
      buildMounts(msg.trace_names.length / 3);
      tr = {t: msg.traces.t.slice(), v: msg.traces.v.map((a) => a.slice())};
      scaleTraces(tr.v);
    }
    $("events").innerHTML = "";
    lastEvent = 0;
    (msg.events || []).forEach(addEvent);
    if (msg.ended) handle({type: "ended", reason: msg.ended});
    apply(msg);
    if (msg.result) showResult(msg.result);
    setControls();
  }

  function delta(msg) {
    stats.deltas += 1;
    stats.seq = msg.seq;
    if (msg.traces && layout) {
      const v = msg.traces.v;
      scaleTraces(v);
      for (const x of msg.traces.t) tr.t.push(x);
      v.forEach((a, k) => { for (const x of a) tr.v[k].push(x); });
      const tEnd = tr.t[tr.t.length - 1];
      let cut = 0;
      while (cut < tr.t.length && tr.t[cut] < tEnd - TRACE_S) cut++;
      if (cut) { tr.t.splice(0, cut); tr.v.forEach((a) => a.splice(0, cut)); }
    }
    (msg.events || []).forEach(addEvent);
    apply(msg);
    if (msg.result) showResult(msg.result);
  }

  function scaleTraces(v) {
    const n = v.length / 3;
    for (let q = 0; q < 3; q++) {
      const k = QUANT[q].k;
      if (k !== 1) for (let m = 0; m < n; m++) { const a = v[q * n + m]; for (let i = 0; i < a.length; i++) if (a[i] !== null) a[i] *= k; }
    }
  }

  // ---- what the page shows -----------------------------------------------------------------------------------
  function apply(msg) {
    if (msg.status) status = msg.status;
    if (msg.now && Object.keys(msg.now).length) now = msg.now;
    const run = status.run || {};
    // the rows' flags while a run is shown (they lead the status by up to 0.1 s), else the status
    const fromRows = run.phase === undefined || run.phase === "run";
    const state = (fromRows ? now.state || run.state : run.state) || "-";
    const iso = fromRows && now.isolation !== undefined ? now.isolation : run.isolation;
    const st = $("state");
    st.textContent = run.phase === "chirp" ? `${state} (chirp)` : state;
    st.className = "badge " + state;
    const isoEl = $("isolation");
    const held = iso && state !== "ACTIVE";        // chosen on, but the loop is not isolating (FAULT, INACTIVE)
    isoEl.textContent = iso === undefined ? "-" : (held ? `on (held: ${state})` : (iso ? "on" : "off"));
    isoEl.className = "badge " + (held ? "held" : (iso ? "on" : "off"));
    const faulted = state === "FAULT";
    $("fault").hidden = !faulted;
    if (faulted) $("fault").textContent = "FAULT: " + (run.fault_reason || "(reason follows)");
    $("harm").hidden = !run.harm;          // the do-no-harm supervisor switched isolation off
    if (run.harm) $("harm").textContent = run.harm;
    $("clock").textContent = now.t_s !== undefined ? `t = ${now.t_s.toFixed(2)} s` : "t = -";
    if (msg.timing) {
      const tm = msg.timing;
      $("timing-window").textContent = `last ${tm.window_s.toFixed(1)} s`;
      $("compute-p99").textContent = us(tm.compute_us.p99);
      $("compute-p50").textContent = us(tm.compute_us.p50);
      $("wake-p99").textContent = us(tm.wake_latency_us.p99);
      $("wake-p50").textContent = us(tm.wake_latency_us.p50);
    }
    if (run.iterations !== undefined) {
      $("iterations").textContent = run.iterations;
      $("loop-rate").textContent = `${run.rate_hz} Hz`;
      $("missed").textContent = `${run.overruns + run.skipped_periods} (${(100 * run.missed_deadline_fraction).toFixed(3)} %)`;
      $("overruns").textContent = run.overruns;
      $("stop-reason").textContent = run.stop_reason || "-";
    }
    if (now.cmd_limited !== undefined) $("limited").textContent = now.cmd_limited ? "yes" : "no";
    const rec = status.recording;
    $("rec-file").textContent = rec ? rec.path + (rec.running ? "" : " (closed)") : "not recording";
    $("rec-rows").textContent = rec ? rec.rows_written : "-";
    $("rec-dropped").textContent = rec ? rec.dropped_rows : "-";
    const job = status.job;
    if (job) {
      $("chirp-progress").value = job.progress;
      $("chirp-text").textContent = `${job.phase}: ${job.text}`;
    }
    if (msg.spectrum) drawSpectrum(msg.spectrum);
    if (msg.vc) drawVC(msg.vc);
    if (pendingIso && iso === pendingIso.want) pendingIso.seen = true;
    setControls();
    schedule();
  }

  function us(x) { return x === null || x === undefined ? "-" : `${x.toFixed(1)} µs`; }

  function setControls() {
    const phase = (status.run || {}).phase;
    const running = phase === "run" && !ended;
    const can = !readOnly && !ended;
    document.querySelectorAll("button, input, select").forEach((el) => {
      if (el.id !== "full-scale") el.disabled = !(can && running);
    });
    $("safe-stop").disabled = !(can && (running || phase === "chirp"));
    const rec = status.recording;
    if (can && running) {
      $("rec-start").disabled = !!(rec && rec.running);
      $("rec-stop").disabled = !(rec && rec.running);
    }
    $("chirp-mount-label").hidden = hello.backend === "sim";
    $("mode-group").hidden = !(layout && layout.modes);      // operating modes: the stand layout only
  }

  // one clock for every event: the wall-clock time of day (a run's loop time restarts with each session)
  function clock(wall) {
    const d = new Date(wall * 1000), z = (x, n) => String(x).padStart(n || 2, "0");
    return `${z(d.getHours())}:${z(d.getMinutes())}:${z(d.getSeconds())}.${z(d.getMilliseconds(), 3)}`;
  }

  function addEvent(e) {
    if (e.seq !== undefined) {
      if (e.seq <= lastEvent) return;          // shown already (it came in a full state, then in a delta)
      lastEvent = e.seq;
    }
    const li = document.createElement("li");
    li.className = e.level || "INFO";
    const t = document.createElement("time");
    t.textContent = clock(e.wall);
    t.dateTime = new Date(e.wall * 1000).toISOString();
    li.appendChild(t);
    li.appendChild(document.createTextNode(e.text));
    const list = $("events");
    list.insertBefore(li, list.firstChild);
    while (list.children.length > 150) list.removeChild(list.lastChild);
  }

  // ---- plots ----------------------------------------------------------------------------------------------
  function limitLines(lim) {
    return {hooks: {draw: [(u) => {
      const ctx = u.ctx, b = u.bbox;
      ctx.save();
      ctx.strokeStyle = "#c62828";
      ctx.lineWidth = devicePixelRatio;
      ctx.setLineDash([6 * devicePixelRatio, 4 * devicePixelRatio]);
      for (const y of [lim, -lim]) {
        const py = u.valToPos(y, "y", true);
        if (py >= b.top && py <= b.top + b.height) {
          ctx.beginPath(); ctx.moveTo(b.left, py); ctx.lineTo(b.left + b.width, py); ctx.stroke();
        }
      }
      ctx.restore();
    }]}};
  }

  // ---- axes: ticks at round steps, at least three on any range, each plot's axes named with their units -------
  const AXIS_FONT = "10px system-ui";

  function linearSplits(u, i, lo, hi) {
    if (!isFinite(lo) || !isFinite(hi) || !(hi > lo)) return [];
    for (let e = Math.floor(Math.log10(hi - lo)); e > -300; e--) {
      for (const m of [5, 2.5, 2, 1]) {                      // the largest round step giving three ticks
        const step = m * Math.pow(10, e), a = Math.ceil(lo / step - 1e-9), b = Math.floor(hi / step + 1e-9);
        if (b - a >= 2) {
          const out = [];
          for (let k = a; k <= b; k++) out.push(+(k * step).toPrecision(12));
          return out;
        }
      }
    }
    return [lo, hi];
  }

  function decimals(step) {           // the decimals a round step needs (0.025 -> 3, 0.5 -> 1, 20 -> 0)
    for (let d = 0; d < 12; d++) if (Math.abs(step * Math.pow(10, d) - Math.round(step * Math.pow(10, d))) < 1e-6) return d;
    return 12;
  }

  function linearTicks(vals) {
    const step = vals.length > 1 ? Math.abs(vals[1] - vals[0]) : 0;
    const big = Math.max(...vals.map((v) => Math.abs(v || 0)));
    if (big >= 1e5 || (step > 0 && step < 1e-4)) return vals.map((v) => (v === 0 ? "0" : v.toExponential(decimals(step / Math.pow(10, Math.floor(Math.log10(step)))))));
    const d = step > 0 ? decimals(step) : 3;
    return vals.map((v) => (v === null ? "" : v.toFixed(d)));
  }

  // the tick texts of axis `which` of plot `id`, kept in rigStats.axes for the tests
  function recorded(id, which, label, fmt) {
    const rec = (stats.axes[id] = stats.axes[id] || {});
    rec[which] = {label, ticks: []};
    return (u, vals) => { const out = fmt(vals); rec[which].ticks = out.filter((x) => x !== ""); return out; };
  }

  function linearAxes(id, xLabel, yLabel) {
    return [
      {size: 24, font: AXIS_FONT, label: xLabel, labelSize: 12, labelFont: AXIS_FONT, ticks: {size: 4},
       splits: linearSplits, values: recorded(id, "x", xLabel, linearTicks)},
      {size: 44, font: AXIS_FONT, label: yLabel, labelSize: 14, labelFont: AXIS_FONT, ticks: {size: 4},
       splits: linearSplits,
       values: recorded(id, "y", yLabel, linearTicks)},
    ];
  }

  function buildMounts(n) {
    const box = $("mounts");
    charts.forEach((c) => c.u.destroy());
    charts = [];
    box.innerHTML = "";
    const head = document.createElement("div");
    box.appendChild(head);
    QUANT.forEach((q) => { const h = document.createElement("div"); h.className = "note"; h.textContent = `${q.name} [${q.unit}]`; box.appendChild(h); });
    const w = Math.max(220, Math.floor((box.clientWidth - 110 - 24) / 3));
    for (let m = 0; m < n; m++) {
      const name = document.createElement("div");
      name.className = "mount-name";
      name.textContent = layout.mounts[m];
      box.appendChild(name);
      QUANT.forEach((q, qi) => {
        const el = document.createElement("div");
        el.className = "chart";
        el.id = `chart-${layout.mounts[m]}-${qi}`;
        box.appendChild(el);
        const lim = layout.limits[q.lim] * q.k;
        const u = new uPlot({
          width: w, height: 136, legend: {show: false}, cursor: {show: false},
          scales: {x: {time: false}, y: {range: (u, lo, hi) => yRange(lo, hi, lim)}},
          axes: linearAxes(el.id, "loop time [s]", `${q.name} [${q.unit}]`),
          series: [{}, {stroke: ["#1565c0", "#2e7d32", "#6a1b9a"][qi], width: 1}],
          plugins: [limitLines(lim)],
        }, [[], []], el);
        charts.push({u, idx: qi * n + m});
      });
    }
  }

  function yRange(lo, hi, lim) {
    if ($("full-scale").checked) return [-1.1 * lim, 1.1 * lim];
    if (lo === null || hi === null || !isFinite(lo) || !isFinite(hi)) return [-1, 1];
    if (hi - lo < 1e-12) { const d = Math.abs(hi) * 0.1 + 1e-9; return [lo - d, hi + d]; }
    const pad = 0.08 * (hi - lo);
    return [lo - pad, hi + pad];
  }

  function num(v) {
    if (v === null || v === 0) return v === 0 ? "0" : "";
    const a = Math.abs(v);
    return a >= 1e4 || a < 1e-2 ? v.toExponential(0) : String(+v.toPrecision(3));
  }

  function logChart(el, series, x, ys, w, h, plugins, yLabel) {
    const logTicks = (vals) => vals.map(num);
    return new uPlot({
      width: w, height: h, legend: {show: true, live: false}, cursor: {show: false}, plugins: plugins || [],
      scales: {x: {time: false, distr: 3, log: 10, range: (u, lo, hi) => [lo, hi]}, y: {distr: 3, log: 10}},
      axes: [{size: 26, font: AXIS_FONT, label: "frequency [Hz]", labelSize: 12, labelFont: AXIS_FONT, ticks: {size: 4},
              values: recorded(el.id, "x", "frequency [Hz]", logTicks)},
             {size: 56, font: AXIS_FONT, label: yLabel, labelSize: 14, labelFont: AXIS_FONT, ticks: {size: 4},
              values: recorded(el.id, "y", yLabel, logTicks)}],
      series: [{label: "Hz"}, ...series],
    }, [x, ...ys], el);
  }

  function positive(a) { return a ? a.map((v) => (v !== null && v > 0 ? v : null)) : null; }

  function drawSpectrum(sp) {
    const el = $("spectrum");
    const cls = sp.classes;
    const f = sp.f_hz || [];
    const ys = ["off", "on"].map((k) => positive(cls[k] && cls[k].asd) || f.map(() => null));
    const rms = sp.rms_mps2 || {};
    $("spec-note").textContent = "heave acceleration ASD [m/s²/√Hz], isolation off against on" +
      ["off", "on"].map((k) => (rms[k] ? `; ${k} ${rms[k].toExponential(2)} m/s² rms` : "")).join("");
    if (!specChart) {
      el.innerHTML = "";
      specChart = logChart(el, [{label: "isolation off", stroke: "#7b8794", width: 1.2},
                                {label: "isolation on", stroke: "#1565c0", width: 1.2}], f, ys,
                           Math.max(300, el.clientWidth), 240, [], "ASD [m/s²/√Hz]");
    } else {
      specChart.setData([f, ...ys]);
    }
  }

  let vcCriteria = {};
  const criterionLines = {hooks: {draw: [(u) => {      // the criteria as labelled dashed lines, not as series
    const ctx = u.ctx, bx = u.bbox, f = u.data[0];
    ctx.save();
    ctx.beginPath(); ctx.rect(bx.left, bx.top, bx.width, bx.height); ctx.clip();
    ctx.strokeStyle = "#9aa5b1"; ctx.fillStyle = "#52606d";
    ctx.lineWidth = devicePixelRatio; ctx.setLineDash([5 * devicePixelRatio, 4 * devicePixelRatio]);
    ctx.font = `${10 * devicePixelRatio}px system-ui`;
    for (const [name, ys] of Object.entries(vcCriteria)) {
      ctx.beginPath();
      ys.forEach((y, i) => { const px = u.valToPos(f[i], "x", true), py = u.valToPos(y, "y", true);
                             if (i) ctx.lineTo(px, py); else ctx.moveTo(px, py); });
      ctx.stroke();
      const py = u.valToPos(ys[ys.length - 1], "y", true);
      if (py > bx.top + 8 && py < bx.top + bx.height) ctx.fillText(name, bx.left + bx.width - 120 * devicePixelRatio, py - 3);
    }
    ctx.restore();
  }]}};

  function drawVC(vc) {
    const el = $("vc");
    if (!vc.available) {
      el.innerHTML = "";
      const p = document.createElement("p");
      p.className = "note";
      p.textContent = vc.why;
      el.appendChild(p);
      return;
    }
    const f = vc.band_hz;
    vcCriteria = vc.criteria;
    const cls = vc.vc_class || {};
    $("vc-note").textContent = "one-third-octave rms velocity [µm/s], dashed: the criteria" +
      ["off", "on"].map((k) => (cls[k] ? `; ${k}: ${cls[k]}` : "")).join("");
    const ys = ["off", "on"].map((k) => positive(vc.velocity_um_s[k]) || f.map(() => null));
    if (!vcChart) {
      el.innerHTML = "";
      vcChart = logChart(el, [{label: "isolation off", stroke: "#7b8794", width: 1.5, points: {show: true}},
                              {label: "isolation on", stroke: "#1565c0", width: 1.5, points: {show: true}}],
                         f, ys, Math.max(300, el.clientWidth), 240, [criterionLines], "rms velocity [µm/s]");
    } else {
      vcChart.setData([f, ...ys]);
    }
  }

  function schedule() {
    if (dirty) return;
    dirty = true;
    requestAnimationFrame(render);
  }

  function render() {
    dirty = false;
    const t0 = performance.now();
    if (layout && tr.t.length) {
      for (const c of charts) c.u.setData([tr.t, tr.v[c.idx]]);
    }
    const t = performance.now();
    stats.renderMs.push(t - t0);
    if (stats.renderMs.length > 1200) stats.renderMs.splice(0, 600);
    stats.renders += 1;
    stats.renderTimes.push(t);
    if (stats.renderTimes.length > 1200) stats.renderTimes.splice(0, 600);
    stats.lastNow = now;
    if (pendingIso && pendingIso.seen) {
      stats.isoLatencyMs.push(t - pendingIso.t0);
      pendingIso = null;
    }
    frame += 1;
    if (frame % 10 === 0) {
      const rt = stats.renderTimes, k = Math.min(rt.length - 1, 20);
      if (k > 0) $("rate").textContent = `${(1000 * k / (rt[rt.length - 1] - rt[rt.length - 1 - k])).toFixed(1)} updates/s`;
    }
  }

  // ---- controls ---------------------------------------------------------------------------------------------
  document.querySelectorAll("button[data-cmd]").forEach((b) => b.addEventListener("click", () => {
    const cmd = b.dataset.cmd;
    if (cmd === "isolation") {
      const want = b.dataset.on === "true";
      pendingIso = {want, t0: performance.now(), seen: false};
      command(cmd, {on: want});
    } else if (cmd === "safe_stop") {
      command(cmd);
    } else {
      command(cmd);
    }
  }));
  $("rec-start").addEventListener("click", () => {
    let p = $("rec-path").value.trim();
    if (!p) {
      const d = new Date(), z = (x) => String(x).padStart(2, "0");
      p = `rig_run_${d.getFullYear()}${z(d.getMonth() + 1)}${z(d.getDate())}_${z(d.getHours())}${z(d.getMinutes())}${z(d.getSeconds())}.h5`;
      $("rec-path").value = p;
    }
    command("record_start", {path: p});
  });
  $("rec-stop").addEventListener("click", () => command("record_stop"));
  $("mode-set").addEventListener("click", () => command("mode", {request: $("mode-text").value.trim()}));
  $("chirp-run").addEventListener("click", () => command("chirp", {
    amplitude_V: +$("chirp-amp").value, f0_hz: +$("chirp-f0").value, f1_hz: +$("chirp-f1").value,
    duration_s: +$("chirp-dur").value, mount: $("chirp-mount").value || "front_left"}));
  $("full-scale").addEventListener("change", () => { charts.forEach((c) => c.u.redraw(true, true)); schedule(); });
  ["front_left", "front_right", "rear_left", "rear_right"].forEach((m) => {
    const o = document.createElement("option"); o.value = m; o.textContent = m; $("chirp-mount").appendChild(o);
  });

  function showResult(r) {
    const box = $("ident");
    box.innerHTML = "";
    if (!r.ok) {
      const p = document.createElement("p"); p.className = "reply refused"; p.textContent = r.text; box.appendChild(p);
      return;
    }
    const t = document.createElement("table");
    t.className = "ident";
    t.id = "ident-table";
    const head = ["parameter", "unit", "Table 1", "identified", "1σ", "change", "note"];
    t.insertRow().append(...head.map((h) => { const th = document.createElement("th"); th.textContent = h; return th; }));
    for (const k of ["K_L", "C", "w_nv", "zeta", "K_Q", "K_C"]) {
      const v0 = r.design[k], v = r.parameters[k];
      const row = t.insertRow();
      [k, r.units[k], v0.toPrecision(4), v.toPrecision(4), r.std[k].toPrecision(2),
       `${(100 * (v / v0 - 1)).toFixed(1)} %`, k in (r.weakly_identified || {}) ? "weak (prior-held)" : ""]
        .forEach((x) => { row.insertCell().textContent = x; });
    }
    box.appendChild(t);
    const f = r.fit, p = document.createElement("p");
    p.className = "note";
    p.textContent = `from ${r.recording}: time-domain NRMSE ${f.nrmse.toFixed(4)}, FRF error ` +
      `${f.frf_err_db.toFixed(2)} dB / ${f.frf_err_deg.toFixed(2)}°`;
    box.appendChild(p);
  }

  connect();
})();
