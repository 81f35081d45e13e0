/* ra2vipas dashboard: the token for state-changing requests, the new-campaign form, the live
 * campaign page (DR curves, POD, reliability), the live study page (metric against the varied
 * parameter), the episode player. Plain ES2017, no build step; plots with
 * uPlot, partial page updates with htmx (both served by the orchestrator). */
(function () {
  "use strict";

  const TOKEN_KEY = "ra2vipas.apiToken";   // sessionStorage: this tab only, never a URL
  // each policy's colour comes with the data (the server's names.web_colours: a built-in's
  // own, any other policy's from its name); this is only for data that carries none
  const FALLBACK = ["#1f6fb4", "#d0402b", "#2b8f3a", "#8a5ac2", "#b8860b"];
  const FINISHED = ["done", "failed", "cancelled"];

  const $ = (sel, root) => (root || document).querySelector(sel);
  const $$ = (sel, root) => Array.from((root || document).querySelectorAll(sel));
  const color = (given, i) => given || FALLBACK[i % FALLBACK.length];
  const alpha = (hex, a) => hex + Math.round(a * 255).toString(16).padStart(2, "0");
  const fixed = (v, d) => (v === null || v === undefined || Number.isNaN(v) ? "—" : Number(v).toFixed(d));

  function toast(text, kind) {
    const el = $("#toast");
    if (!el) return;
    el.textContent = text;
    el.className = "show " + (kind || "");
    clearTimeout(toast.timer);
    toast.timer = setTimeout(() => { el.className = ""; }, 6000);
  }

  // -- the API token -------------------------------------------------------------------------
  const authRequired = () => ($('meta[name="ra2vipas-auth"]') || {}).content === "required";

  function askToken(message) {
    const dialog = $("#token-dialog"), input = $("#token-input"), error = $("#token-error");
    return new Promise((resolve) => {
      error.hidden = !message;
      error.textContent = message || "";
      input.value = "";
      const done = (value) => {
        form.removeEventListener("submit", onSubmit);
        cancel.removeEventListener("click", onCancel);
        dialog.removeEventListener("cancel", onCancel);
        if (dialog.open) dialog.close();
        resolve(value);
      };
      const form = $("#token-form"), cancel = $("#token-cancel");
      const onSubmit = (e) => { e.preventDefault(); const v = input.value.trim(); if (v) done(v); };
      const onCancel = (e) => { e.preventDefault(); done(null); };
      form.addEventListener("submit", onSubmit);
      cancel.addEventListener("click", onCancel);
      dialog.addEventListener("cancel", onCancel);
      dialog.showModal();
      input.focus();
    });
  }

  /* A state-changing request to the REST API. With a token configured, the token the user
   * typed once is sent as Authorization: Bearer; a 401 asks again. Resolves to the Response,
   * or null if the user cancelled. */
  async function api(method, url, body) {
    let token = sessionStorage.getItem(TOKEN_KEY);
    if (authRequired() && !token) {
      token = await askToken();
      if (!token) return null;
    }
    for (let attempt = 0; attempt < 3; attempt++) {
      const headers = { Accept: "application/json" };
      if (body !== undefined) headers["Content-Type"] = "application/json";
      if (token) headers.Authorization = "Bearer " + token;
      const response = await fetch(url, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
      if (response.status !== 401) {
        if (token) sessionStorage.setItem(TOKEN_KEY, token);
        return response;
      }
      sessionStorage.removeItem(TOKEN_KEY);
      token = await askToken("That token was refused; try again.");
      if (!token) return null;
    }
    return null;
  }

  async function detail(response) {
    try { const b = await response.json(); return b.detail || response.statusText; } catch (e) { return response.statusText; }
  }

  // -- charts --------------------------------------------------------------------------------
  function chartWidth(el) { return Math.max(280, Math.floor(el.getBoundingClientRect().width || el.parentElement.clientWidth || 600)); }

  function resizeWith(el, plot, height) {
    const ro = new ResizeObserver(() => plot.setSize({ width: chartWidth(el), height: height }));
    ro.observe(el);
    return ro;
  }

  /* DR curves: one line per algorithm with its Wilson band; a legend of checkboxes (toggle),
   * the values under the cursor, drag to zoom. */
  function drChart(el, legend, data) {
    const names = Object.keys(data.algorithms);
    const series = [{ label: "t [s]" }], bands = [], columns = [data.t];
    names.forEach((name, i) => {
      const a = data.algorithms[name], c = color(a.color, i), base = series.length;
      series.push({ label: a.label, stroke: c, width: 2, points: { show: false }, spanGaps: false });
      series.push({ label: a.label + " low", stroke: "transparent", points: { show: false } });
      series.push({ label: a.label + " high", stroke: "transparent", points: { show: false } });
      bands.push({ series: [base + 2, base + 1], fill: alpha(c, 0.16) });
      columns.push(a.dr.length ? a.dr : data.t.map(() => null), a.lo.length ? a.lo : data.t.map(() => null),
                   a.hi.length ? a.hi : data.t.map(() => null));
    });
    const height = Math.min(360, Math.max(220, Math.round(chartWidth(el) * 0.45)));
    const opts = {
      width: chartWidth(el), height: height, series: series, bands: bands, legend: { show: false },
      scales: { x: { time: false }, y: { range: [0, 1.02] } },
      axes: [{ label: "time [s]" }, { label: "DR_t", values: (u, v) => v.map((x) => x.toFixed(1)) }],
      cursor: { drag: { x: true, y: false } },
      hooks: { setCursor: [(u) => showValues(u)] },
    };
    const plot = new uPlot(opts, columns, el);
    // legend: one checkbox per algorithm, with the value under the cursor (else the last)
    legend.innerHTML = "";
    names.forEach((name, i) => {
      const a = data.algorithms[name];
      const id = "show-" + el.id + "-" + name;
      const item = document.createElement("label");
      item.className = "legend-item";
      item.innerHTML = '<input type="checkbox" checked id="' + id + '"> <span class="sw"></span> ' +
        a.label + ' <span class="num value" data-alg="' + name + '"></span>';
      item.querySelector(".sw").style.background = color(a.color, i);  // CSSOM: the page's CSP allows no style attributes
      item.querySelector("input").addEventListener("change", (e) => {
        const base = 1 + 3 * i;
        [base, base + 1, base + 2].forEach((s) => plot.setSeries(s, { show: e.target.checked }));
      });
      legend.appendChild(item);
    });
    function showValues(u) {
      const idx = u.cursor.idx;
      names.forEach((name, i) => {
        const cell = legend.querySelector('[data-alg="' + name + '"]');
        if (!cell) return;
        const col = u.data[1 + 3 * i], lo = u.data[2 + 3 * i], hi = u.data[3 + 3 * i];
        const k = idx === null || idx === undefined ? col.length - 1 : idx;
        const n = (u.__algorithms || data.algorithms)[name].n;
        cell.textContent = col[k] === null || col[k] === undefined ? "(no test yet)" :
          "DR " + fixed(col[k], 3) + " [" + fixed(lo[k], 3) + ", " + fixed(hi[k], 3) + "] at " + fixed(u.data[0][k], 1) + " s, n=" + n;
      });
    }
    plot.__algorithms = data.algorithms;
    plot.__update = (next) => {
      const cols = [next.t];
      names.forEach((name) => {
        const a = next.algorithms[name] || { dr: [], lo: [], hi: [] };
        cols.push(a.dr.length ? a.dr : next.t.map(() => null), a.lo.length ? a.lo : next.t.map(() => null),
                  a.hi.length ? a.hi : next.t.map(() => null));
      });
      plot.__algorithms = next.algorithms;
      plot.setData(cols, false);
      plot.redraw(true, false);
      showValues(plot);
    };
    showValues(plot);
    resizeWith(el, plot, height);
    return plot;
  }

  function podChart(el, legend, d) {
    const tables = [[d.dense, d.true], [d.grid, d.mean, d.lo, d.hi]];
    if (d.samples) {
      const order = d.samples.r.map((_, i) => i).sort((a, b) => d.samples.r[a] - d.samples.r[b]);
      const r = [], p = [];
      let last = null;
      order.forEach((i) => { if (d.samples.r[i] !== last) { r.push(d.samples.r[i]); p.push(d.samples.p[i]); last = d.samples.r[i]; } });
      tables.push([r, p]);
    }
    const joined = uPlot.join(tables);
    const series = [{ label: "r [dBm]" },
      { label: "true p_D(r)", stroke: "#111", width: 1.5, spanGaps: true, points: { show: false } },
      { label: "learned mean", stroke: "#1f6fb4", width: 2, spanGaps: true, points: { show: false } },
      { label: "−2 std", stroke: "transparent", spanGaps: true, points: { show: false } },
      { label: "+2 std", stroke: "transparent", spanGaps: true, points: { show: false } }];
    if (d.samples) series.push({ label: "training samples (truth)", stroke: "#e08a1e", paths: () => null,
                                 points: { show: true, size: 3, fill: "#e08a1e", stroke: "#e08a1e" } });
    const height = Math.min(320, Math.max(200, Math.round(chartWidth(el) * 0.4)));
    const plot = new uPlot({ width: chartWidth(el), height: height, series: series, legend: { show: true, live: true },
      bands: [{ series: [4, 3], fill: "rgba(31,111,180,0.18)" }],
      scales: { x: { time: false }, y: { range: [-0.03, 1.02] } },
      axes: [{ label: "iso RSSI r [dBm]" }, { label: "probability of detection" }] }, joined, el);
    legend.textContent = d.r2 === null || d.r2 === undefined ? "" : "R² " + fixed(d.r2, 3) + (d.samples ? " · " + d.samples.n + " training samples" : "");
    resizeWith(el, plot, height);
    return plot;
  }

  /* Reliability diagram of the final confidences: per algorithm, the share of final answers
   * that are the Tx against the bins' mean confidence; the diagonal is perfect calibration. */
  function reliabilityChart(el, legend, d) {
    const names = Object.keys(d.algorithms);
    const tables = [[[0, 1], [0, 1]]].concat(names.map((name) => [d.algorithms[name].confidence, d.algorithms[name].accuracy]));
    const series = [{ label: "confidence" }, { label: "perfectly calibrated", stroke: "#888", width: 1, dash: [4, 4], points: { show: false } }];
    names.forEach((name, i) => {
      const c = color(d.algorithms[name].color, i);
      series.push({ label: d.algorithms[name].label, stroke: c, width: 2, spanGaps: true, points: { show: true, size: 7, fill: c, stroke: c } });
    });
    const height = Math.min(340, Math.max(240, Math.round(chartWidth(el) * 0.85)));
    const plot = new uPlot({ width: chartWidth(el), height: height, series: series, legend: { show: false },
      scales: { x: { time: false, range: [0, 1] }, y: { range: [0, 1.02] } },
      axes: [{ label: "mean final confidence" }, { label: "share that is the Tx", values: (u, v) => v.map((x) => x.toFixed(1)) }] },
      uPlot.join(tables), el);
    legend.innerHTML = "";
    names.forEach((name, i) => {
      const a = d.algorithms[name], item = document.createElement("span");
      item.className = "legend-item";
      item.innerHTML = '<span class="sw"></span> ' + a.label +
        (a.ece === null || a.ece === undefined ? "" : ' <span class="num">ECE ' + fixed(a.ece, 3) + "</span>");
      item.querySelector(".sw").style.background = color(a.color, i);
      legend.appendChild(item);
    });
    resizeWith(el, plot, height);
    return plot;
  }

  // -- campaign page -------------------------------------------------------------------------
  let campaignState = null;

  function initCampaign(root) {
    const page = root.id === "campaign" ? root : $("#campaign", root);
    if (!page) return;
    if (campaignState && campaignState.source) campaignState.source.close();
    const id = page.dataset.campaignId;
    const state = campaignState = { id: id, dr: null, pod: null, source: null };
    const drData = JSON.parse($("#dr-data", page).textContent);
    if (drData) state.dr = drChart($("#dr-chart", page), $("#dr-legend", page), drData);
    $("#dr-reset", page).addEventListener("click", () => {
      if (state.dr) state.dr.setScale("x", { min: state.dr.data[0][0], max: state.dr.data[0][state.dr.data[0].length - 1] });
    });
    loadPod(state, page);
    const rel = $("#reliability-data", page);
    if (rel) reliabilityChart($("#reliability-chart", page), $("#reliability-legend", page), JSON.parse(rel.textContent));
    const cancel = $("#cancel-button", page), del = $("#delete-button", page);
    if (cancel) cancel.addEventListener("click", async () => {
      if (!window.confirm("Cancel campaign " + id + "? Tests recorded so far are kept.")) return;
      const r = await api("POST", "/campaigns/" + id + "/cancel");
      if (r === null) return;
      if (r.ok) toast("Campaign " + id + " cancelled.", "ok"); else toast("Cancel failed: " + (await detail(r)), "bad");
      if (r.ok && !state.source) refreshCampaign();
    });
    if (del) del.addEventListener("click", async () => {
      if (!window.confirm("Delete campaign " + id + " and every test it recorded?")) return;
      const r = await api("DELETE", "/campaigns/" + id);
      if (r === null) return;
      if (r.status === 204) window.location.assign("/"); else toast("Delete failed: " + (await detail(r)), "bad");
    });
    if (page.dataset.active === "true") follow(state, page);
  }

  function loadPod(state, page) {
    const el = $("#pod-chart", page);
    if (!el || state.pod || state.podLoading) return;
    state.podLoading = true;
    fetch(el.dataset.url, { headers: { Accept: "application/json" } }).then(async (r) => {
      state.podLoading = false;
      if (!r.ok) return;
      const d = await r.json();
      if (!d.ready || !document.body.contains(el) || state.pod) return;
      state.pod = podChart(el, $("#pod-legend", page), d);
      $("#pod-pending", page).textContent = "";
    }).catch(() => { state.podLoading = false; });
  }

  function follow(state, page) {
    const source = state.source = new EventSource("/ui/campaigns/" + state.id + "/live");
    source.addEventListener("progress", (e) => {
      const p = JSON.parse(e.data);
      const badge = $("#status", page);
      badge.textContent = p.status;
      badge.className = "status status-" + p.status;
      page.dataset.status = p.status;
      const bar = $("#progress-bar", page);
      bar.max = p.progress.total || 1;
      bar.value = p.progress.done;
      $("#progress-text", page).textContent = p.progress.done + "/" + p.progress.total + " episodes done, " + p.progress.running + " running";
      $("#pod-r2", page).textContent = fixed(p.pod.r2, 3);
      const err = $("#campaign-error", page);
      err.hidden = !p.error;
      err.textContent = p.error || "";
      if (p.status !== state.lastStatus || p.pod.r2 !== state.lastR2) loadPod(state, page);  // the model is stored as training ends
      state.lastStatus = p.status;
      state.lastR2 = p.pod.r2;
      refreshTests(state, page);
      if (FINISHED.includes(p.status)) {
        source.close();
        state.source = null;
        refreshCampaign();
      }
    });
    source.addEventListener("curves", (e) => {
      const d = JSON.parse(e.data);
      const any = Object.values(d.algorithms).some((a) => a.n > 0);
      if (!any) return;
      if (state.dr) state.dr.__update(d);
      else state.dr = drChart($("#dr-chart", page), $("#dr-legend", page), d);
    });
    source.addEventListener("deleted", () => { source.close(); toast("This campaign was deleted.", "bad"); });
  }

  function refreshTests(state, page) {
    // the per-test table follows the run (every 5 s at most, the same filter and page), unless the user is in it
    const holder = $("#tests", page), current = $("#tests-state", page);
    if (!holder || !current || holder.contains(document.activeElement) || Date.now() - (state.testsAt || 0) < 5000) return;
    state.testsAt = Date.now();
    htmx.ajax("GET", current.dataset.url, { target: holder, swap: "innerHTML" });
  }

  function refreshCampaign() {
    // the finished campaign's page (summary, exports, final curves), swapped in without a reload
    htmx.ajax("GET", window.location.pathname + window.location.search, { target: "#campaign", select: "#campaign", swap: "outerHTML" });
  }

  // -- study page ----------------------------------------------------------------------------
  const BOUNDED = /^(dr_final|in_fov_final|calibration_|decision_accuracy|decision_undecided)/;  // metrics in [0, 1]
  const key = (v) => JSON.stringify(v);
  let studyState = null;

  function bandOf(metric) { return metric === "dr_final" ? ["ci95_lo", "ci95_hi"] : [metric + "_ci95_lo", metric + "_ci95_hi"]; }

  /* The metric against the varied parameter: one line per algorithm (points at the grid's
   * values; categories for a non-numeric parameter) with its 95 % band where the rows have one;
   * a legend of checkboxes (toggle) with the values under the cursor. */
  function studyChart(el, legend, chart, metric, hidden) {
    const name = chart.parameters[0], values = chart.vary[name];
    const numeric = values.every((v) => typeof v === "number");
    const xs = numeric ? values.slice().sort((a, b) => a - b) : values.slice();
    const pos = numeric ? xs : xs.map((_, i) => i);
    const [loKey, hiKey] = bandOf(metric);
    const names = Object.keys(chart.algorithms).filter((a) => chart.rows.some((r) => r.algorithm === a));
    const series = [{ label: name }], bands = [], columns = [pos];
    names.forEach((a, i) => {
      const c = color((chart.colors || {})[a], i), base = series.length;
      const mine = new Map(chart.rows.filter((r) => r.algorithm === a).map((r) => [key(r[name]), r]));
      const at = (f) => xs.map((x) => { const r = mine.get(key(x)); return r && typeof r[f] === "number" ? r[f] : null; });
      series.push({ label: chart.algorithms[a], stroke: c, width: 2, spanGaps: true, show: !hidden.has(a),
                    points: { show: true, size: 7, fill: c, stroke: c } });
      series.push({ label: "low", stroke: "transparent", spanGaps: true, points: { show: false }, show: !hidden.has(a) });
      series.push({ label: "high", stroke: "transparent", spanGaps: true, points: { show: false }, show: !hidden.has(a) });
      bands.push({ series: [base + 2, base + 1], fill: alpha(c, 0.16) });
      columns.push(at(metric), at(loKey), at(hiKey), xs.map((x) => { const r = mine.get(key(x)); return r ? r.tests : null; }));
    });
    const data = [pos];
    names.forEach((_, i) => data.push(columns[1 + 4 * i], columns[2 + 4 * i], columns[3 + 4 * i]));
    const tests = names.map((_, i) => columns[4 + 4 * i]);
    const lo = Math.min.apply(null, pos), hi = Math.max.apply(null, pos), pad = (hi - lo) * 0.05 || 0.5;
    const height = Math.min(360, Math.max(220, Math.round(chartWidth(el) * 0.45)));
    const label = (chart.metrics.find((m) => m.key === metric) || { label: metric }).label;
    const plot = new uPlot({
      width: chartWidth(el), height: height, series: series, bands: bands, legend: { show: false },
      scales: { x: { time: false, range: [lo - pad, hi + pad] },
                y: { range: BOUNDED.test(metric) ? [0, 1.02] : (u, mn, mx) => (mn === null ? [0, 1] : [Math.min(0, mn), mx > 0 ? mx * 1.08 : 1]) } },
      axes: [{ label: name, splits: xs.length <= 16 ? () => pos : undefined,
               values: numeric ? undefined : (u, v) => v.map((p) => (Number.isInteger(p) && xs[p] !== undefined ? String(xs[p]) : "")) },
             { label: label, size: 60 }],
      hooks: { setCursor: [(u) => showValues(u)] },
    }, data, el);
    legend.innerHTML = "";
    names.forEach((a, i) => {
      const item = document.createElement("label");
      item.className = "legend-item";
      item.innerHTML = '<input type="checkbox"' + (hidden.has(a) ? "" : " checked") + '> <span class="sw"></span> ' +
        chart.algorithms[a] + ' <span class="num value" data-alg="' + a + '"></span>';
      item.querySelector(".sw").style.background = color((chart.colors || {})[a], i);
      item.querySelector("input").addEventListener("change", (e) => {
        if (e.target.checked) hidden.delete(a); else hidden.add(a);
        [1, 2, 3].forEach((k) => plot.setSeries(3 * i + k, { show: e.target.checked }));
      });
      legend.appendChild(item);
    });
    function showValues(u) {
      const idx = u.cursor.idx;
      names.forEach((a, i) => {
        const cell = legend.querySelector('[data-alg="' + a + '"]');
        const y = u.data[1 + 3 * i], l = u.data[2 + 3 * i], h = u.data[3 + 3 * i];
        let k = idx;
        if (k === null || k === undefined) { k = y.length - 1; while (k > 0 && y[k] === null) k--; }
        if (y[k] === null || y[k] === undefined) { cell.textContent = "(no test yet)"; return; }
        cell.textContent = fixed(y[k], 3) + (l[k] !== null && h[k] !== null ? " [" + fixed(l[k], 3) + ", " + fixed(h[k], 3) + "]" : "") +
          " at " + name + "=" + xs[k] + ", n=" + tests[i][k];
      });
    }
    showValues(plot);
    resizeWith(el, plot, height);
    return plot;
  }

  function drawStudy(state, page) {
    const chart = state.chart, metric = state.metric;
    const hasRows = chart.rows.some((r) => typeof r[metric] === "number");
    const el = $("#study-chart", page), img = $("#study-heatmap", page), exports = $("#plot-exports", page);
    if (exports) {
      exports.hidden = !hasRows;
      ["png", "svg"].forEach((f) => { const a = $("#export-" + f, page); if (a) a.href = "/studies/" + state.id + "/plots/" + metric + "?format=" + f; });
    }
    if (el) {
      if (state.plot) { state.plot.destroy(); state.plot = null; }
      if (hasRows) state.plot = studyChart(el, $("#study-legend", page), chart, metric, state.hidden);
      else $("#study-legend", page).textContent = "";
    }
    if (img && hasRows) {
      // the server's heat map; while the study runs, a new picture at each update of the rows
      const done = chart.rows.reduce((n, r) => n + (r.tests || 0), 0);
      img.src = img.dataset.base + encodeURIComponent(metric) + "?format=svg" + (chart.partial ? "&rows=" + done : "");
    }
  }

  function initStudy(root) {
    const page = root.id === "study" ? root : $("#study", root);
    if (!page) return;
    if (studyState && studyState.source) studyState.source.close();
    const id = page.dataset.studyId;
    const state = studyState = { id: id, chart: JSON.parse($("#study-data", page).textContent), plot: null, source: null,
                                 hidden: (studyState && studyState.id === id && studyState.hidden) || new Set(),
                                 metric: studyState && studyState.id === id ? studyState.metric : null };
    const select = $("#metric", page);
    $("#metric-form", page).addEventListener("submit", (e) => e.preventDefault());  // no inline handler: the CSP allows none
    if (state.metric && Array.from(select.options).some((o) => o.value === state.metric)) select.value = state.metric;
    state.metric = select.value || "dr_final";
    select.addEventListener("change", () => { state.metric = select.value; drawStudy(state, page); });
    drawStudy(state, page);
    const cancel = $("#cancel-button", page), del = $("#delete-button", page);
    if (cancel) cancel.addEventListener("click", async () => {
      if (!window.confirm("Cancel study " + id + "? Every unfinished point stops; tests recorded so far are kept.")) return;
      const r = await api("POST", "/studies/" + id + "/cancel");
      if (r === null) return;
      if (r.ok) toast("Study " + id + " cancelled.", "ok"); else toast("Cancel failed: " + (await detail(r)), "bad");
      if (r.ok && !state.source) refreshStudy();
    });
    if (del) del.addEventListener("click", async () => {
      if (!window.confirm("Delete study " + id + ", its points' campaigns and every test they recorded?")) return;
      const r = await api("DELETE", "/studies/" + id);
      if (r === null) return;
      if (r.status === 204) window.location.assign("/ui/studies"); else toast("Delete failed: " + (await detail(r)), "bad");
    });
    if (page.dataset.active === "true") followStudy(state, page);
  }

  function followStudy(state, page) {
    const source = state.source = new EventSource("/ui/studies/" + state.id + "/live");
    source.addEventListener("progress", (e) => {
      const s = JSON.parse(e.data);
      const badge = $("#status", page);
      badge.textContent = s.status;
      badge.className = "status status-" + s.status;
      page.dataset.status = s.status;
      const bar = $("#progress-bar", page);
      bar.max = s.progress.total || 1;
      bar.value = s.progress.done;
      $("#progress-text", page).textContent = s.progress.done + "/" + s.progress.total + " episodes done, " + s.progress.running + " running";
      const err = $("#study-error", page);
      err.hidden = !s.error;
      err.textContent = s.error || "";
      (s.points || []).forEach((p) => {
        const st = $('[data-point-status="' + p.point + '"]', page), pr = $('[data-point-progress="' + p.point + '"]', page);
        if (st) { st.textContent = p.status; st.className = "status status-" + p.status; }
        if (pr) pr.textContent = p.progress.done + "/" + p.progress.total;
      });
      if (FINISHED.includes(s.status)) {
        source.close();
        state.source = null;
        refreshStudy();
      }
    });
    source.addEventListener("results", (e) => {
      const d = JSON.parse(e.data);
      state.chart = d.chart;
      const select = $("#metric", page);
      const keys = d.chart.metrics.map((m) => m.key);
      if (keys.join() !== Array.from(select.options).map((o) => o.value).join()) {
        select.innerHTML = "";
        d.chart.metrics.forEach((m) => { const o = document.createElement("option"); o.value = m.key; o.textContent = m.label; select.appendChild(o); });
        if (keys.includes(state.metric)) select.value = state.metric; else state.metric = select.value;
      }
      if (d.chart.rows.length) $("#plot-note", page).textContent = "Over the tests recorded so far; grows while the study runs.";
      drawStudy(state, page);
      const holder = $("#study-table", page);
      if (!holder.contains(document.activeElement)) holder.innerHTML = d.table;
    });
    source.addEventListener("deleted", () => { source.close(); state.source = null; toast("This study was deleted.", "bad"); });
  }

  function refreshStudy() {
    htmx.ajax("GET", window.location.pathname, { target: "#study", select: "#study", swap: "outerHTML" });
  }

  // -- new campaign --------------------------------------------------------------------------
  const FIXED_FIELDS = ["preset", "tests", "seed", "mode", "name", "stop_confidence", "algorithms"];

  function fieldError(form, name, message) {
    const slot = $("#error-" + CSS.escape(name), form);
    const input = form.elements[name];
    if (slot) { slot.textContent = message; slot.hidden = !message; slot.setAttribute("role", message ? "alert" : ""); }
    const inputs = input instanceof RadioNodeList ? Array.from(input) : input ? [input] : [];
    inputs.forEach((el) => { if (message) el.setAttribute("aria-invalid", "true"); else el.removeAttribute("aria-invalid"); });
    return slot;
  }

  function checkInput(el) {
    if (!el.checkValidity()) return el.validationMessage;
    if (el.type === "number" && el.value !== "") {
      const v = Number(el.value);
      if (el.dataset.minOpen && v <= Number(el.min)) return "must be greater than " + el.min;
      if (el.dataset.maxOpen && v >= Number(el.max)) return "must be less than " + el.max;
    }
    return "";
  }

  function numberOf(el) { return el.dataset.kind === "int" || el.step === "1" ? parseInt(el.value, 10) : parseFloat(el.value); }

  function initNewCampaign(root) {
    const form = root.id === "new-campaign" ? root : $("#new-campaign", root);
    if (!form || form.dataset.ready) return;
    form.dataset.ready = "1";
    form.addEventListener("input", (e) => { if (e.target.name) fieldError(form, e.target.name, ""); });
    form.addEventListener("submit", async (e) => {
      e.preventDefault();
      const banner = $("#form-error", form);
      banner.hidden = true;
      $$("[aria-invalid]", form).forEach((el) => fieldError(form, el.name, ""));
      let first = null;
      const flag = (name, message) => { const slot = fieldError(form, name, message); if (!first) first = form.elements[name] || slot; };
      const inputs = $$("input[name], select[name]", form).filter((el) => el.type !== "checkbox");
      inputs.forEach((el) => { const m = checkInput(el); if (m) flag(el.name, m); });
      const algorithms = $$('input[name="algorithms"]:checked', form).map((el) => el.value);
      if (!algorithms.length) flag("algorithms", "choose at least one algorithm");
      if (first) { (first.focus ? first : form).focus(); return; }
      const body = { preset: form.elements.preset.value, tests: parseInt(form.elements.tests.value, 10),
                     seed: parseInt(form.elements.seed.value, 10), mode: form.elements.mode.value, algorithms: algorithms, overrides: {} };
      const name = form.elements.name.value.trim();
      if (name) body.name = name;
      const stop = parseFloat(form.elements.stop_confidence.value);
      if (stop > 0) body.stop_confidence = stop;
      $$("[data-param]", form).forEach((el) => {
        const kind = el.dataset.kind;
        const asText = el.tagName === "SELECT" || kind === "text";
        const value = kind === "bool" ? el.value === "true" : asText ? el.value : numberOf(el);
        const original = kind === "bool" ? el.dataset.default === "true" : asText ? el.dataset.default : Number(el.dataset.default);
        if (value !== original) body.overrides[el.name] = value;
      });
      const button = $("#submit-campaign", form);
      button.disabled = true;
      try {
        const r = await api("POST", "/campaigns", body);
        if (r === null) return;
        if (r.status === 201) {
          const c = await r.json();
          window.location.assign("/ui/campaigns/" + c.id);
          return;
        }
        let payload = {};
        try { payload = await r.json(); } catch (err) { payload = { detail: r.statusText }; }
        banner.textContent = "Not started: " + (payload.detail || r.statusText);
        banner.hidden = false;
        if (r.status === 422) showApiErrors(form, payload.errors || []);
        if (!first) banner.focus();
      } finally {
        button.disabled = false;
      }

      function showApiErrors(form, errors) {
        const params = new Set($$("[data-param]", form).map((el) => el.name));
        errors.forEach((err) => {
          const loc = (err.loc || []).filter((p) => p !== "body");
          let field = loc.length ? String(loc[0]) : "";
          let message = err.msg || "";
          if (field === "overrides") {
            const named = (message.match(/[a-z][a-z0-9_]*/g) || []).find((w) => params.has(w)) || (loc[1] && params.has(loc[1]) ? loc[1] : null);
            if (named) field = named;
          }
          if (params.has(field) || FIXED_FIELDS.includes(field)) flag(field, message);
        });
        if (first && first.focus) first.focus();
      }
    });
  }

  // -- episode player ------------------------------------------------------------------------
  const SVGNS = "http://www.w3.org/2000/svg";

  function svg(tag, attrs, parent) {
    const el = document.createElementNS(SVGNS, tag);
    Object.entries(attrs).forEach(([k, v]) => el.setAttribute(k, v));
    if (parent) parent.appendChild(el);
    return el;
  }

  function initEpisode(root) {
    const holder = root.id === "episode" ? root : $("#episode", root);
    if (!holder || holder.dataset.ready) return;
    holder.dataset.ready = "1";
    const ep = JSON.parse($("#episode-data").textContent);
    const n = ep.t.length, polar = $("#polar", holder), slider = $("#step-slider", holder), readout = $("#step-readout", holder);
    const play = $("#play", holder);
    const rangeAt = (tg, k) => (tg.ranges ? tg.ranges[Math.min(k, tg.ranges.length - 1)] : tg.range);
    const bearingAt = (tg, k) => (tg.bearings ? tg.bearings[Math.min(k, tg.bearings.length - 1)] : tg.bearing);
    let rmax = 0;
    ep.targets.forEach((tg) => { (tg.ranges || [tg.range]).forEach((r) => { rmax = Math.max(rmax, r); }); });
    rmax = Math.max(rmax, 1e-6);
    const R_TARGETS = 0.7, R_IN = 0.78, R_OUT = 1.08;  // targets inside, the pan spiral outside
    const xy = (r, a) => [r * Math.cos(a), -r * Math.sin(a)];
    // static layer: range rings and compass
    const grid = svg("g", { class: "grid" }, polar);
    [0.25, 0.5, 0.75, 1].forEach((f) => {
      svg("circle", { cx: 0, cy: 0, r: R_TARGETS * f }, grid);
      const t = svg("text", { x: 0.01, y: -R_TARGETS * f - 0.01, class: "ring-label" }, grid);
      t.textContent = (rmax * f).toFixed(1) + " m";
    });
    svg("circle", { cx: 0, cy: 0, r: R_IN, class: "spiral-edge" }, grid);
    for (let k = 0; k < 8; k++) {
      const [x, y] = xy(R_OUT, (k * Math.PI) / 4);
      svg("line", { x1: 0, y1: 0, x2: x, y2: y }, grid);
    }
    [["0°", 0], ["90°", Math.PI / 2], ["180°", Math.PI], ["−90°", -Math.PI / 2]].forEach(([txt, a]) => {
      const [x, y] = xy(R_OUT + 0.02, a);
      const t = svg("text", { x: x, y: y, class: "compass", "text-anchor": "middle", "dominant-baseline": "middle" }, grid);
      t.textContent = txt;
    });
    const fov = svg("path", { class: "fov" }, polar);
    const spiral = svg("polyline", { class: "pan-trail", fill: "none" }, polar);
    const estimate = svg("line", { class: "estimate", x1: 0, y1: 0 }, polar);
    const panMark = svg("circle", { class: "pan-mark", r: 0.025 }, polar);
    const dots = ep.targets.map((tg) => {
      const g = svg("g", { class: tg.is_tx ? "target tx" : "target" }, polar);
      svg("circle", { r: tg.is_tx ? 0.035 : 0.025 }, g);
      if (tg.is_tx) { const t = svg("text", { x: 0.05, y: -0.04, class: "tx-label" }, g); t.textContent = "Tx"; }
      const title = svg("title", {}, g);
      title.textContent = "target " + tg.index + (tg.is_tx ? " (Tx)" : "");
      return g;
    });
    const spiralPoint = (k) => xy(R_IN + ((R_OUT - R_IN) * k) / Math.max(1, n - 1), ep.pan[k]);
    // the pan trajectory as a spiral: each move follows the shorter way round, radius growing with time
    const wrap = (a) => Math.atan2(Math.sin(a), Math.cos(a));
    const trail = [spiralPoint(0)].map((p) => p.map((v) => v.toFixed(4)).join(",")), ends = [0];
    for (let k = 1; k < n; k++) {
      const d = wrap(ep.pan[k] - ep.pan[k - 1]), parts = Math.max(1, Math.ceil(Math.abs(d) / 0.1));
      for (let j = 1; j <= parts; j++) {
        const f = (k - 1 + j / parts) / Math.max(1, n - 1);
        trail.push(xy(R_IN + (R_OUT - R_IN) * f, ep.pan[k - 1] + (d * j) / parts).map((v) => v.toFixed(4)).join(","));
      }
      ends.push(trail.length - 1);  // step k's point
    }
    const charts = [];
    function render(k) {
      const s = ep.pan[k], h = ep.fov_half_rad;
      const [ax, ay] = xy(R_TARGETS * 1.06, s - h), [bx, by] = xy(R_TARGETS * 1.06, s + h);
      fov.setAttribute("d", "M0,0 L" + ax + "," + ay + " A" + R_TARGETS * 1.06 + "," + R_TARGETS * 1.06 + " 0 " + (2 * h > Math.PI ? 1 : 0) + " 0 " + bx + "," + by + " Z");
      const [ex, ey] = xy(R_OUT, ep.est[k]);
      estimate.setAttribute("x2", ex);
      estimate.setAttribute("y2", ey);
      spiral.setAttribute("points", trail.slice(0, ends[k] + 1).join(" "));
      const [px, py] = spiralPoint(k);
      panMark.setAttribute("cx", px);
      panMark.setAttribute("cy", py);
      ep.targets.forEach((tg, i) => {
        const [x, y] = xy((R_TARGETS * rangeAt(tg, k)) / rmax, bearingAt(tg, k));
        dots[i].setAttribute("transform", "translate(" + x.toFixed(4) + "," + y.toFixed(4) + ")");
        dots[i].classList.toggle("chosen", tg.index === ep.i_hat[k]);
      });
      const conf = ep.confidence ? " · confidence " + fixed(ep.confidence[k], 2) : "";
      readout.textContent = "t = " + fixed(ep.t[k], 1) + " s (step " + k + ") · î = " + ep.i_hat[k] + (ep.hit[k] ? " ✓ the Tx" : " ✗") +
        " · error " + fixed(ep.error_deg[k], 1) + "°" + conf + (ep.decided_step !== null && k >= ep.decided_step ? " · decided" : "");
      slider.setAttribute("aria-valuetext", readout.textContent);
      charts.forEach((c) => c.redraw(false, false));
    }
    function marker(u) {
      const k = Number(slider.value), x = u.valToPos(ep.t[k], "x", true), ctx = u.ctx;
      ctx.save();
      ctx.strokeStyle = "#c0392b";
      ctx.lineWidth = 1.5 * devicePixelRatio;
      ctx.beginPath();
      ctx.moveTo(x, u.bbox.top);
      ctx.lineTo(x, u.bbox.top + u.bbox.height);
      ctx.stroke();
      ctx.restore();
    }
    function series(id, label, values, stroke, range) {
      const el = $("#" + id, holder);
      if (!el) return;
      const height = 150;
      const plot = new uPlot({ width: chartWidth(el), height: height, legend: { show: false },
        series: [{ label: "t" }, { label: label, stroke: stroke, width: 1.5, points: { show: false } }],
        scales: { x: { time: false }, y: range ? { range: range } : {} }, axes: [{}, { size: 50 }],
        hooks: { draw: [marker] }, cursor: { drag: { x: true, y: false } } }, [ep.t, values], el);
      resizeWith(el, plot, height);
      charts.push(plot);
    }
    series("error-chart", "error [deg]", ep.error_deg, "#c0392b");
    series("reward-chart", "reward", ep.reward, "#1f6fb4");
    if (ep.confidence) series("confidence-chart", "confidence", ep.confidence, "#2b8f3a", [0, 1]);
    slider.addEventListener("input", () => render(Number(slider.value)));
    let timer = null;
    const stop = () => { clearInterval(timer); timer = null; play.textContent = "▶"; play.setAttribute("aria-label", "play"); };
    play.addEventListener("click", () => {
      if (timer) { stop(); return; }
      if (Number(slider.value) >= n - 1) slider.value = 0;
      play.textContent = "❚❚";
      play.setAttribute("aria-label", "pause");
      const period = Math.max(16, (ep.rf_period_s * 1000) / 2);  // twice real time
      timer = setInterval(() => {
        const k = Number(slider.value) + 1;
        if (k >= n) { stop(); return; }
        slider.value = k;
        render(k);
      }, period);
    });
    render(Number(slider.value));
  }

  function init(root) {
    initCampaign(root);
    initStudy(root);
    initNewCampaign(root);
    initEpisode(root);
  }

  if (window.htmx) htmx.onLoad(init); else document.addEventListener("DOMContentLoaded", () => init(document.body));
  window.ra2vipas = { api: api };
})();
