/* HRC operator console. Plain JavaScript, no build step, no external resources.
 *
 * Talks to the operator API under /api with the bearer token kept in sessionStorage, follows /api/live
 * (a WebSocket of runtime snapshots) and embeds the viser 3D view (its port comes from GET /api/info).
 * Every error the API returns is shown with its `detail`.
 */
"use strict";

(function () {
  const TOKEN_KEY = "hrc.operatorToken";
  const PLAN_HISTORY = 240; // planning times kept for the plot

  const $ = (id) => document.getElementById(id);
  const state = {
    token: sessionStorage.getItem(TOKEN_KEY),
    info: null,
    ws: null,
    wsRetry: 0,
    wsTimer: null,
    latest: null,
    latestText: null,
    received: 0,
    minT: -Infinity,
    connText: "",
    dirty: false,
    lastTrialId: null,
    runningTrialId: null,
    participants: [],
    sessions: [],
    planHistory: [],
    lastPlanKey: "",
    view: "live",
  };

  // ------------------------------------------------------------------ messages

  class ApiError extends Error {
    constructor(status, detail) {
      super(detail);
      this.status = status;
      this.detail = detail;
    }
  }

  function showError(message) {
    $("alert-text").textContent = message;
    $("alert").hidden = false;
  }

  function clearError() {
    $("alert").hidden = true;
    $("alert-text").textContent = "";
  }

  let toastTimer = null;
  function toast(message) {
    const el = $("toast");
    el.textContent = message;
    el.hidden = false;
    clearTimeout(toastTimer);
    toastTimer = setTimeout(() => { el.hidden = true; }, 3500);
  }

  function describe(err, what) {
    if (err instanceof ApiError) {
      return `${what} failed (HTTP ${err.status}): ${err.detail}`;
    }
    return `${what} failed: ${err && err.message ? err.message : err}`;
  }

  // ------------------------------------------------------------------ API client

  async function readDetail(res) {
    const text = await res.text();
    if (!text) return res.statusText || "no details";
    try {
      const body = JSON.parse(text);
      if (typeof body.detail === "string") return body.detail;
      if (Array.isArray(body.detail)) {
        return body.detail.map((e) => `${(e.loc || []).join(".")}: ${e.msg}`).join("; ");
      }
      return text;
    } catch (_e) {
      return text.slice(0, 300);
    }
  }

  async function api(path, { method = "GET", body = undefined, raw = false } = {}) {
    const headers = { Accept: raw ? "*/*" : "application/json" };
    if (state.token) headers.Authorization = `Bearer ${state.token}`;
    if (body !== undefined) headers["Content-Type"] = "application/json";
    let res;
    try {
      res = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
    } catch (e) {
      throw new ApiError(0, `the server cannot be reached (${e.message}); is hrc serve running?`);
    }
    if (!res.ok) {
      const detail = await readDetail(res);
      if (res.status === 401) signOut(`The server refused the token: ${detail}`);
      throw new ApiError(res.status, detail);
    }
    if (raw) return res;
    if (res.status === 204) return null;
    return res.json();
  }

  // ------------------------------------------------------------------ sign-in

  function showLogin(message) {
    $("app-view").hidden = true;
    $("login-view").hidden = false;
    $("logout-button").hidden = true;
    $("login-error").textContent = message || "";
    $("login-token").focus();
  }

  function signOut(message) {
    state.token = null;
    sessionStorage.removeItem(TOKEN_KEY);
    closeLive();
    showLogin(message);
  }

  async function signIn(token) {
    state.token = token;
    try {
      state.info = await api("/api/info");
    } catch (err) {
      state.token = null;
      if (err instanceof ApiError && err.status === 401) {
        sessionStorage.removeItem(TOKEN_KEY);
        showLogin(`Token rejected: ${err.detail}`);
      } else {
        showLogin(describe(err, "Sign-in"));
      }
      return false;
    }
    sessionStorage.setItem(TOKEN_KEY, token);
    $("login-view").hidden = true;
    $("app-view").hidden = false;
    $("logout-button").hidden = false;
    $("login-error").textContent = "";
    enterApp();
    return true;
  }

  function enterApp() {
    const info = state.info;
    $("version").textContent = info.version ? `v${info.version}` : "";
    $("robot-pill").textContent = `robot: ${info.robot} · person: ${info.human_source}`;
    setupViser(info.viser_port);
    connectLive();
    refreshStudy().catch((err) => showError(describe(err, "Loading the study records")));
  }

  // The 3D view renders continuously. Served from the same site (same host name) the browser would run it in
  // the page's own renderer process, where software WebGL can starve the live stream; on a loopback address
  // the other loopback name (127.0.0.1 <-> localhost) is a different site and gets its own process.
  function viserHost(host) {
    if (host === "127.0.0.1") return "localhost";
    if (host === "localhost") return "127.0.0.1";
    return host;
  }

  function setupViser(port) {
    const frame = $("viser-frame");
    if (!port) {
      frame.hidden = true;
      $("viser-empty").hidden = false;
      return;
    }
    // The 3D view's socket needs the operator token: viser's client connects to the URL in ?websocket=.
    const host = `${viserHost(location.hostname)}:${port}`;
    const socket = `${location.protocol === "https:" ? "wss:" : "ws:"}//${host}/?token=${encodeURIComponent(state.token || "")}`;
    const url = `${location.protocol}//${host}/?websocket=${encodeURIComponent(socket)}`;
    if (frame.getAttribute("src") !== url) frame.setAttribute("src", url);
    $("viser-link").href = url;
  }

  // ------------------------------------------------------------------ live snapshots

  function closeLive() {
    clearTimeout(state.wsTimer);
    if (state.ws) {
      state.ws.onclose = null;
      state.ws.close();
      state.ws = null;
    }
    setConn("offline", "");
  }

  function setConn(text, cls) {
    state.connText = text;
    $("conn-text").textContent = text;
    $("conn-pill").className = `pill ${cls}`;
  }

  function connectLive() {
    closeLive();
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    const ws = new WebSocket(`${proto}//${location.host}/api/live`);
    state.ws = ws;
    setConn("connecting…", "warn");
    ws.onopen = () => {
      ws.send(JSON.stringify({ token: state.token }));
    };
    // Keep message handling cheap: snapshots arrive at up to 30 Hz and can be large (skeleton, forecast,
    // plans), so only the newest text is kept here and parsed once per animation frame in render().
    ws.onmessage = (ev) => {
      const text = ev.data;
      if (typeof text !== "string") return;
      if (text.startsWith('{"type":"error"')) {
        try {
          const msg = JSON.parse(text);
          showError(`Live stream: ${msg.detail || msg.code}`);
        } catch (_e) {
          /* not JSON: ignore */
        }
        return;
      }
      state.latestText = text;
      state.received += 1;
    };
    ws.onclose = (ev) => {
      state.ws = null;
      if (ev.code === 1008) {
        setConn("refused", "danger");
        signOut(`The live stream refused the token: ${ev.reason || "invalid operator token"}`);
        return;
      }
      setConn("reconnecting…", "danger");
      const delay = Math.min(5000, 500 * 2 ** state.wsRetry);
      state.wsRetry += 1;
      state.wsTimer = setTimeout(connectLive, delay);
    };
  }

  function classify(snap) {
    const text = String(snap.state || "unknown").replace(/[_-]/g, " ").trim().toUpperCase();
    const low = text.toLowerCase();
    if (snap.estopped) return ["E-STOP", "danger"];
    if (snap.stale) return [`${text} · STREAM STALE`, "danger"];
    if (/stop|fault|error|emergency/.test(low)) return [text, "danger"];
    if (/avoid|replan|slow|hold|wait/.test(low)) return [text, "warn"];
    if (/nominal|run|exec|moving/.test(low)) return [text, "ok"];
    return [text, ""];
  }

  const fmt = (v, digits = 2, unit = "") =>
    v === null || v === undefined || !Number.isFinite(Number(v)) ? "–" : `${Number(v).toFixed(digits)}${unit}`;

  // every tracked body with its tracker id ("2 tracked: #3, #7"), nobody in view, or no frame yet
  function bodiesText(s) {
    if (!Array.isArray(s.skeleton)) return "not seen";
    const ids = Array.isArray(s.body_ids) ? s.body_ids : [];
    const n = ids.length || Math.round(s.skeleton.length / 19);
    if (n === 0) return s.stale ? "stale" : "nobody in view";
    const who = ids.length ? `: ${ids.map((i) => `#${i}`).join(", ")}` : "";
    return `${n} ${s.stale ? "stale" : "tracked"}${who}`;
  }

  function takeLatest() {
    const text = state.latestText;
    if (text === null) return;
    state.latestText = null;
    let msg;
    try {
      msg = JSON.parse(text);
    } catch (_e) {
      return;
    }
    if (msg.type !== "snapshot") return;
    // A snapshot older than a state the server already confirmed (E-stop, reset) is stale: skip it.
    if (Number.isFinite(msg.t) && msg.t < state.minT) return;
    if (state.connText !== "live") setConn("live", "ok");
    state.wsRetry = 0;
    state.latest = msg;
    state.dirty = true;
  }

  function render() {
    requestAnimationFrame(render);
    takeLatest();
    if (!state.dirty || !state.latest) return;
    state.dirty = false;
    const s = state.latest;
    const [text, cls] = classify(s);
    $("state-pill-text").textContent = text;
    $("state-pill").className = `pill pill-state ${cls}`;
    const big = $("live-state");
    big.textContent = text;
    big.className = `state-big ${cls}`;
    big.dataset.state = String(s.state || "");
    big.dataset.estopped = s.estopped ? "true" : "false";
    $("estop-button").classList.toggle("latched", !!s.estopped);
    $("live-method").textContent = s.method ? `method: ${s.method}` : "–";
    // the speed both screens print (held between shared refreshes: the 3D view shows the same number)
    const speed = Number(s.speed_shown ?? s.speed_scale);
    $("speed-meter").value = Number.isFinite(speed) ? speed : 0;
    $("speed-scale").textContent = Number.isFinite(speed) ? `${Math.floor(speed * 100 + 0.5)}%` : "–";
    big.dataset.t = Number.isFinite(Number(s.t)) ? Number(s.t).toFixed(3) : "";
    renderModes(s);
    const p = s.p_world_tcp;
    $("tcp").textContent = Array.isArray(p) ? p.map((v) => fmt(v, 3)).join(", ") : "–";
    $("skeleton-status").textContent = bodiesText(s);

    // trial
    const trialId = s.trial_id === undefined ? null : s.trial_id;
    state.runningTrialId = trialId;
    $("trial-stop").disabled = trialId === null;
    $("trial-stop-live").disabled = trialId === null;
    if (trialId !== null) {
      const el = Number(s.trial_elapsed_s) || 0;
      const du = Number(s.trial_duration_s) || 0;
      $("trial-pill").textContent = `trial #${trialId} · ${s.method || ""}`;
      $("trial-label").textContent = `trial #${trialId} running`;
      $("trial-progress").style.width = du > 0 ? `${Math.min(100, (100 * el) / du).toFixed(1)}%` : "0%";
      $("trial-time").textContent = du > 0 ? `${el.toFixed(0)} s of ${du.toFixed(0)} s` : `${el.toFixed(0)} s`;
    } else {
      $("trial-pill").textContent = "no trial";
      $("trial-label").textContent = "no trial running";
      $("trial-progress").style.width = "0%";
      $("trial-time").textContent = "–";
    }
    if (trialId !== state.lastTrialId) {
      const ended = state.lastTrialId !== null;
      state.lastTrialId = trialId;
      // a trial started or ended: refresh the table (an ended trial gets its metrics shortly after)
      refreshTrials().catch(() => {});
      if (ended) setTimeout(() => refreshTrials().catch(() => {}), 1500);
    }

    // counters and where the trial's time went
    renderCounters(s.counters || {});
    renderBudget(s.time_budget || {});
    renderBudgetByGoal(s.time_budget_by_goal || {});
    // planning times
    const plans = Array.isArray(s.planning_ms) ? s.planning_ms.filter((v) => Number.isFinite(v)) : [];
    const key = plans.join(",");
    if (key !== state.lastPlanKey) {
      state.lastPlanKey = key;
      state.planHistory = plans.slice(-PLAN_HISTORY);
      drawPlanning(s);
    }
  }

  // What limits the robot (one field of the snapshot, as the 3D view shows it): the limiting part's mode,
  // the separation it keeps and the one the speed governor holds it to, and every part's mode.
  const partName = (name) => String(name || "").replace(/_/g, " ");

  function renderModes(s) {
    const parts = Array.isArray(s.parts) ? s.parts : [];
    const limiting = parts.find((p) => p.name === s.limiting_part) || null;
    const chip = $("live-mode");
    chip.textContent = s.mode_text || "–";
    chip.dataset.mode = s.mode ? String(s.mode).split(":")[0] : "";
    chip.dataset.label = s.mode || "";
    $("live-limiting").textContent = limiting ? `limited by the ${partName(limiting.name)}` : "";
    const from = limiting && limiting.held_from_text ? ` from the ${limiting.held_from_text}` : "";
    $("separation").textContent = fmt(s.separation_m, 2, " m") + (fmt(s.separation_m) === "–" ? "" : from);
    const req = fmt(s.required_separation_m, 2, " m");
    $("required-separation").textContent =
      limiting && req !== "–" ? `${req} (${partName(limiting.name)}${limiting.mode === "stopped" ? ", to move" : ""})` : req;
    const list = $("part-modes");
    while (list.children.length > parts.length) list.lastElementChild.remove();
    while (list.children.length < parts.length) {
      const li = document.createElement("li");
      for (const cls of ["part-name", "mode-chip", "num"]) {
        const span = document.createElement("span");
        span.className = cls;
        li.append(span);
      }
      list.append(li);
    }
    parts.forEach((p, i) => {
      const li = list.children[i];
      li.className = p.name === s.limiting_part ? "limiting" : "";
      li.dataset.part = p.name;
      li.dataset.mode = p.label;
      const [name, mode, nums] = li.children;
      name.textContent = partName(p.name);
      mode.textContent = p.text;
      mode.dataset.mode = p.mode;
      nums.textContent = `${fmt(p.separation_m, 2)} / ${fmt(p.required_m, 2)} m`;
      nums.title = `separation${p.held_from_text ? " from the " + p.held_from_text : ""} / held to`;
    });
  }

  function renderCounters(counters) {
    const dl = $("counters");
    const keys = Object.keys(counters).sort();
    if (dl.dataset.keys !== keys.join(",")) {
      dl.textContent = "";
      for (const k of keys) {
        const dt = document.createElement("dt");
        dt.textContent = k.replace(/_/g, " ");
        const dd = document.createElement("dd");
        dd.dataset.counter = k;
        dd.dataset.testid = `counter-${k}`;
        dd.setAttribute("data-testid", `counter-${k}`);
        dl.append(dt, dd);
      }
      dl.dataset.keys = keys.join(",");
    }
    for (const dd of dl.querySelectorAll("dd")) {
      const v = counters[dd.dataset.counter];
      dd.textContent = typeof v === "number" && !Number.isInteger(v) ? v.toFixed(2) : String(v);
    }
  }

  // the parts of the time budget (app.control.supervisor_types.TIME_BUDGET), in the order they are shown
  const BUDGET_PARTS = [
    ["moving_full", "moving, full speed", "#2e7d32"],
    ["moving_scaled", "moving, slowed", "#66bb6a"],
    ["braking", "braking", "#ffa000"],
    ["stopped", "held still", "#d32f2f"],
    ["planned_wait", "planned wait", "#7e57c2"],
    ["gripper", "gripper", "#8d6e63"],
    ["waiting_for_person", "waiting for the person", "#00acc1"],
    ["waiting_for_plan", "waiting for a plan", "#1e88e5"],
    ["idle", "idle", "#b0bec5"],
  ];

  function renderBudget(budget) {
    const bar = $("budget-bar");
    const dl = $("time-budget");
    const total = budgetTotal(budget);
    if (!(total > 0)) {
      bar.textContent = "";
      dl.textContent = "";
      dl.dataset.built = "";
      $("budget-total").textContent = "no trial running";
      return;
    }
    if (dl.dataset.built !== "1") {
      bar.textContent = "";
      dl.textContent = "";
      for (const [k, label, color] of BUDGET_PARTS) {
        const seg = document.createElement("span");
        seg.dataset.part = k;
        seg.style.background = color;
        seg.title = label;
        bar.append(seg);
        const dt = document.createElement("dt");
        const sw = document.createElement("span");
        sw.className = "budget-swatch";
        sw.style.background = color;
        dt.append(sw, document.createTextNode(label));
        const dd = document.createElement("dd");
        dd.dataset.part = k;
        dd.setAttribute("data-testid", `budget-${k}`);
        dl.append(dt, dd);
      }
      dl.dataset.built = "1";
    }
    for (const seg of bar.querySelectorAll("span")) {
      seg.style.width = `${(100 * (Number(budget[seg.dataset.part]) || 0)) / total}%`;
    }
    for (const dd of dl.querySelectorAll("dd")) {
      const v = Number(budget[dd.dataset.part]) || 0;
      dd.textContent = `${v.toFixed(1)} s`;
    }
    const scaled = Number(budget.mean_scale_when_scaled);
    const slowed = Number.isFinite(scaled) && scaled > 0 ? ` · slowed to ${Math.round(scaled * 100)}% on average` : "";
    $("budget-total").textContent = `${total.toFixed(1)} s${slowed}`;
  }

  // the seconds of a time budget's parts (by part), summed
  function budgetTotal(parts) {
    return BUDGET_PARTS.reduce((acc, [k]) => acc + (Number(parts[k]) || 0), 0);
  }

  // one segment per part of a time budget (seconds by part) in ``bar``, as wide as its share of ``total``
  function fillBudgetBar(bar, parts, total) {
    for (const [k, label, color] of BUDGET_PARTS) {
      const v = Number(parts[k]) || 0;
      if (!(v > 0) || !(total > 0)) continue;
      const seg = document.createElement("span");
      seg.style.background = color;
      seg.style.width = `${(100 * v) / total}%`;
      seg.title = `${label}: ${v.toFixed(1)} s`;
      bar.append(seg);
    }
  }

  // the task poses that took the most time, each with its own budget bar: where the cell loses its time
  const BUDGET_GOALS_SHOWN = 5;

  function renderBudgetByGoal(byGoal) {
    const list = $("budget-goals");
    const rows = Object.entries(byGoal)
      .filter(([goal, parts]) => goal !== "none" && Number(parts.total) > 0)
      .sort((a, b) => Number(b[1].total) - Number(a[1].total))
      .slice(0, BUDGET_GOALS_SHOWN);
    const key = rows.map(([goal, parts]) => `${goal}:${Number(parts.total).toFixed(1)}`).join(",");
    if (key === list.dataset.key) return;
    list.dataset.key = key;
    list.textContent = "";
    for (const [goal, parts] of rows) {
      const total = Number(parts.total);
      const li = document.createElement("li");
      li.dataset.goal = goal;
      li.setAttribute("data-testid", `budget-goal-${goal}`);
      const name = document.createElement("span");
      name.className = "budget-goal-name";
      name.textContent = goal;
      const bar = document.createElement("span");
      bar.className = "budget-bar budget-bar-mini";
      const held = Number(parts.stopped) || 0;
      bar.title = `${goal}: ${total.toFixed(1)} s, ${held.toFixed(1)} s held still`;
      fillBudgetBar(bar, parts, total);
      const secs = document.createElement("span");
      secs.className = "budget-goal-total";
      secs.textContent = `${total.toFixed(1)} s`;
      li.append(name, bar, secs);
      list.append(li);
    }
    $("budget-goals-head").hidden = rows.length === 0;
  }

  function quantile(sorted, q) {
    if (!sorted.length) return NaN;
    const i = (sorted.length - 1) * q;
    const lo = Math.floor(i);
    const hi = Math.ceil(i);
    return sorted[lo] + (sorted[hi] - sorted[lo]) * (i - lo);
  }

  function drawPlanning(s) {
    const canvas = $("planning-plot");
    const dpr = window.devicePixelRatio || 1;
    const w = canvas.clientWidth || 380;
    const h = canvas.clientHeight || 140;
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr);
      canvas.height = Math.round(h * dpr);
    }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    const data = state.planHistory;
    let deadline = Number(s.deadline_ms);
    if (!Number.isFinite(deadline) && Number.isFinite(Number(s.deadline_s))) deadline = 1000 * Number(s.deadline_s);
    if (!Number.isFinite(deadline) && state.info && Number.isFinite(Number(state.info.deadline_s))) {
      deadline = 1000 * Number(state.info.deadline_s); // D from GET /api/info
    }
    const padL = 34, padB = 16, padT = 8, padR = 6;
    const pw = w - padL - padR, ph = h - padT - padB;
    const maxV = Math.max(1, ...data, Number.isFinite(deadline) ? deadline * 1.15 : 0) * 1.1;
    // axes and grid
    ctx.font = "10px system-ui, sans-serif";
    ctx.fillStyle = "#66758a";
    ctx.strokeStyle = "#e3e8ee";
    ctx.lineWidth = 1;
    for (let k = 0; k <= 4; k++) {
      const v = (maxV * k) / 4;
      const y = padT + ph - (v / maxV) * ph;
      ctx.beginPath();
      ctx.moveTo(padL, y + 0.5);
      ctx.lineTo(w - padR, y + 0.5);
      ctx.stroke();
      ctx.fillText(v >= 10 ? v.toFixed(0) : v.toFixed(1), 2, y + 3);
    }
    ctx.fillText("ms", 2, h - 3);
    if (Number.isFinite(deadline)) {
      const y = padT + ph - (deadline / maxV) * ph;
      ctx.strokeStyle = "#d63031";
      ctx.setLineDash([5, 4]);
      ctx.beginPath();
      ctx.moveTo(padL, y);
      ctx.lineTo(w - padR, y);
      ctx.stroke();
      ctx.setLineDash([]);
      ctx.fillStyle = "#d63031";
      ctx.fillText(`deadline ${deadline.toFixed(0)} ms`, w - padR - 90, y - 3);
    }
    if (!data.length) {
      ctx.fillStyle = "#66758a";
      ctx.fillText("no plans yet", padL + pw / 2 - 28, padT + ph / 2);
      $("plan-stats").textContent = "–";
      return;
    }
    const n = data.length;
    const bw = Math.max(1, pw / Math.max(n, 60));
    for (let i = 0; i < n; i++) {
      const v = data[i];
      const bh = (v / maxV) * ph;
      const x = padL + pw - (n - i) * bw;
      ctx.fillStyle = Number.isFinite(deadline) && v > deadline ? "#d63031" : "#2962ff";
      ctx.fillRect(x, padT + ph - bh, Math.max(1, bw - 1), bh);
    }
    const sorted = [...data].sort((a, b) => a - b);
    $("plan-stats").textContent =
      `median ${quantile(sorted, 0.5).toFixed(1)} ms · p95 ${quantile(sorted, 0.95).toFixed(1)} ms · n=${n}`;
  }

  // ------------------------------------------------------------------ robot

  // A REST answer (E-stop, reset) carries the runtime state after the command: show it at once, and ignore
  // live snapshots taken before it that may still be in flight.
  function applyStatus(status) {
    if (Number.isFinite(status.t)) state.minT = status.t;
    state.latest = Object.assign({}, state.latest || {}, status);
    state.latestText = null;
    state.dirty = true;
  }

  async function estop() {
    if (!state.token) {
      showError("Sign in first: the E-stop is sent to the server with the operator token.");
      return;
    }
    const btn = $("estop-button");
    btn.disabled = true;
    try {
      const status = await api("/api/robot/estop", { method: "POST" });
      toast("E-stop sent: the robot is stopped.");
      applyStatus(status);
    } catch (err) {
      showError(describe(err, "E-stop"));
    } finally {
      btn.disabled = false;
    }
  }

  async function reset() {
    try {
      const status = await api("/api/robot/reset", { method: "POST" });
      clearError();
      toast("Reset: the robot may run again.");
      applyStatus(status);
    } catch (err) {
      showError(describe(err, "Reset"));
    }
  }

  // ------------------------------------------------------------------ study records

  function option(value, text) {
    const o = document.createElement("option");
    o.value = String(value);
    o.textContent = text;
    return o;
  }

  function cell(text, cls) {
    const td = document.createElement("td");
    td.textContent = text === null || text === undefined ? "–" : String(text);
    if (cls) td.className = cls;
    return td;
  }

  function badge(text, cls) {
    const td = document.createElement("td");
    const b = document.createElement("span");
    b.className = `badge ${cls || text}`;
    b.textContent = text;
    td.append(b);
    return td;
  }

  const shortTime = (iso) => (iso ? new Date(iso).toLocaleString() : "–");

  async function refreshStudy() {
    await Promise.all([refreshParticipants(), refreshSessions(), refreshTrials()]);
  }

  async function refreshParticipants(selectId) {
    state.participants = await api("/api/participants");
    const body = $("participants-body");
    body.textContent = "";
    for (const p of state.participants) {
      const tr = document.createElement("tr");
      tr.dataset.code = p.code;
      tr.append(cell(p.id, "num"), cell(p.code), cell(p.age), cell(p.experience));
      body.append(tr);
    }
    $("participants-count").textContent = `${state.participants.length} in total`;
    const sel = $("trial-participant");
    const keep = selectId !== undefined ? String(selectId) : sel.value;
    sel.textContent = "";
    sel.append(option("", state.participants.length ? "choose a participant" : "add a participant first"));
    for (const p of state.participants) sel.append(option(p.id, `${p.code} (#${p.id})`));
    sel.value = state.participants.some((p) => String(p.id) === keep) ? keep : "";
    await suggestOrder();
  }

  async function refreshSessions(selectId) {
    state.sessions = await api("/api/sessions");
    const body = $("sessions-body");
    body.textContent = "";
    for (const s of state.sessions) {
      const tr = document.createElement("tr");
      tr.append(cell(s.id, "num"), cell(s.name), cell(shortTime(s.created)));
      body.append(tr);
    }
    for (const [id, none] of [["trial-session", "(none)"], ["results-session", "all sessions"]]) {
      const sel = $(id);
      const keep = id === "trial-session" && selectId !== undefined ? String(selectId) : sel.value;
      sel.textContent = "";
      sel.append(option("", none));
      for (const s of state.sessions) sel.append(option(s.id, `${s.name} (#${s.id})`));
      sel.value = state.sessions.some((s) => String(s.id) === keep) ? keep : "";
    }
  }

  async function refreshTrials() {
    const trials = await api("/api/trials?limit=1000");
    const body = $("trials-body");
    body.textContent = "";
    const sessions = new Map(state.sessions.map((s) => [s.id, s.name]));
    for (const t of trials.slice(-100).reverse()) {
      const m = t.metrics || {};
      const tr = document.createElement("tr");
      tr.dataset.trialId = String(t.id);
      tr.append(
        cell(t.id, "num"),
        cell(t.participant_code),
        cell(t.session_id ? sessions.get(t.session_id) || `#${t.session_id}` : "–"),
        badge(t.method),
        badge(t.status),
        cell(t.metrics ? m.completed_tasks : null, "num"),
        cell(t.metrics ? (1000 * m.avg_planning_time_s).toFixed(1) : null, "num"),
        cell(t.metrics ? m.stop_replans : null, "num"),
        cell(t.metrics ? m.online_replans : null, "num"),
        cell(t.metrics && m.min_separation_m !== null ? m.min_separation_m.toFixed(2) : null, "num"),
        cell(shortTime(t.started_at)),
      );
      if (t.abort_reason) tr.title = `aborted: ${t.abort_reason}`;
      body.append(tr);
    }
    return trials;
  }

  async function suggestOrder() {
    const pid = $("trial-participant").value;
    const hint = $("method-order");
    if (!pid) {
      hint.textContent = "Pick a participant to see the counterbalanced order.";
      return;
    }
    try {
      const [order, done] = await Promise.all([
        api(`/api/participants/${pid}/method-order`),
        api(`/api/trials?participant_id=${pid}&status=completed`),
      ]);
      const doneMethods = new Set(done.map((t) => t.method));
      const next = order.methods.find((m) => !doneMethods.has(m));
      hint.textContent = "";
      hint.append("Counterbalanced order: ");
      order.methods.forEach((m, i) => {
        if (i) hint.append(" → ");
        const el = document.createElement(m === next ? "strong" : "span");
        el.textContent = `${i + 1}. ${m}${doneMethods.has(m) ? " ✓" : ""}`;
        hint.append(el);
      });
      hint.append(next ? ` (next: ${next})` : " (both done)");
      hint.dataset.next = next || "";
      if (next) $("trial-method").value = next;
    } catch (err) {
      hint.textContent = describe(err, "Reading the method order");
    }
  }

  async function createParticipant(ev) {
    ev.preventDefault();
    const code = $("participant-code").value.trim();
    const age = $("participant-age").value;
    const experience = $("participant-experience").value.trim();
    const body = { code };
    if (age !== "") body.age = Number(age);
    if (experience) body.experience = experience;
    try {
      const p = await api("/api/participants", { method: "POST", body });
      toast(`Participant ${p.code} added.`);
      $("participant-form").reset();
      clearError();
      await refreshParticipants(p.id);
    } catch (err) {
      showError(describe(err, "Adding the participant"));
    }
  }

  async function createSession(ev) {
    ev.preventDefault();
    try {
      const s = await api("/api/sessions", { method: "POST", body: { name: $("session-name").value.trim() } });
      toast(`Session “${s.name}” added.`);
      $("session-form").reset();
      clearError();
      await refreshSessions(s.id);
    } catch (err) {
      showError(describe(err, "Adding the session"));
    }
  }

  async function startTrial(ev) {
    ev.preventDefault();
    const pid = $("trial-participant").value;
    if (!pid) {
      showError("Choose a participant before starting a trial (add one under Participants).");
      return;
    }
    const body = {
      participant_id: Number(pid),
      method: $("trial-method").value,
      duration_s: Number($("trial-duration").value),
    };
    const sid = $("trial-session").value;
    if (sid) body.session_id = Number(sid);
    const seed = $("trial-seed").value;
    if (seed !== "") body.seed = Number(seed);
    const btn = $("trial-start");
    btn.disabled = true;
    try {
      const t = await api("/api/trials", { method: "POST", body });
      clearError();
      toast(`Trial #${t.id} started: ${t.method}, ${body.duration_s} s.`);
      await refreshTrials();
      selectView("live");
    } catch (err) {
      showError(describe(err, "Starting the trial"));
    } finally {
      btn.disabled = false;
    }
  }

  async function stopTrial() {
    const id = state.runningTrialId;
    if (id === null || id === undefined) {
      showError("No trial is running.");
      return;
    }
    try {
      const t = await api(`/api/trials/${id}/stop`, { method: "POST" });
      toast(`Trial #${t.id} stopped (${t.status}).`);
      await refreshTrials();
      await suggestOrder();
    } catch (err) {
      showError(describe(err, "Stopping the trial"));
    }
  }

  // ------------------------------------------------------------------ results

  function fmtNum(v) {
    if (v === null || v === undefined || !Number.isFinite(v)) return "–";
    if (Number.isInteger(v)) return String(v);
    const a = Math.abs(v);
    return a !== 0 && a < 0.01 ? v.toExponential(2) : v.toFixed(3);
  }

  function sessionQuery() {
    const sid = $("results-session").value;
    return sid ? `?session_id=${sid}` : "";
  }

  async function refreshResults() {
    let summary;
    try {
      summary = await api(`/api/summary${sessionQuery()}`);
    } catch (err) {
      showError(describe(err, "Loading the results"));
      return;
    }
    const body = $("results-body");
    body.textContent = "";
    for (const metric of summary.metrics || []) {
      const tr = document.createElement("tr");
      tr.dataset.metric = metric;
      const a = (summary.proactive || {})[metric] || {};
      const b = (summary.reactive || {})[metric] || {};
      const t = (summary.tests || {})[metric] || {};
      const p = (summary.p_values || {})[metric];
      const ms = (x) => `${fmtNum(x.mean)} ± ${fmtNum(x.sd)} (n=${x.n ?? 0})`;
      tr.append(cell((summary.labels || {})[metric] || metric), cell(ms(a)), cell(ms(b)));
      const test = cell(t.test || "–");
      if (t.why) test.title = t.why;
      tr.append(test);
      const pc = cell(p === null || p === undefined ? "–" : p < 0.001 ? "< 0.001" : p.toFixed(3), "num");
      if (p !== null && p !== undefined && p < 0.05) pc.classList.add("sig");
      tr.append(pc);
      tr.append(cell(t.effect_size === null || t.effect_size === undefined ? "–" : `${t.effect_size_name}: ${fmtNum(t.effect_size)}`));
      body.append(tr);
    }
    const nt = summary.n_trials || {};
    $("results-note").textContent =
      `${summary.n_participants ?? 0} participants with both methods · completed trials: ` +
      `proactive ${nt.proactive ?? 0}, reactive ${nt.reactive ?? 0}. Hover a test for why it was chosen; ` +
      "p < 0.05 in green.";
    renderResultsBudget(summary);
    await refreshBoxplots(summary);
  }

  // per method: the mean time budget of its completed trials as one bar, and how well its plans said when
  // the robot would arrive
  function renderResultsBudget(summary) {
    const box = $("results-budget");
    box.textContent = "";
    const budgets = summary.time_budget_s || {};
    const arrivals = summary.arrival_error_s || {};
    for (const method of ["proactive", "reactive"]) {
      const b = budgets[method] || {};
      if (!(b.trials > 0)) continue;
      const total = budgetTotal(b);
      const row = document.createElement("div");
      row.className = "results-budget-row";
      row.setAttribute("data-testid", `results-budget-${method}`);
      const head = document.createElement("div");
      head.className = "results-budget-head";
      const name = document.createElement("strong");
      name.textContent = method;
      const facts = document.createElement("span");
      facts.className = "muted small";
      const a = arrivals[method] || {};
      const parts = [`${total.toFixed(1)} s over ${b.trials} trial${b.trials === 1 ? "" : "s"}`];
      for (const k of ["moving_scaled", "stopped", "waiting_for_person", "waiting_for_plan"]) {
        const label = (BUDGET_PARTS.find(([key]) => key === k) || [k, k])[1];
        parts.push(`${label} ${(Number(b[k]) || 0).toFixed(1)} s`);
      }
      if (a.trials > 0 && a.median_abs !== null && a.median_plan_s !== null) {
        const rel = a.relative === null ? "" : ` (${Math.round(a.relative * 100)}%)`;
        parts.push(`arrival error ${fmtNum(a.median_abs)} s of ${fmtNum(a.median_plan_s)} s plans${rel}`);
      }
      facts.textContent = parts.join(" · ");
      head.append(name, facts);
      const bar = document.createElement("div");
      bar.className = "budget-bar";
      bar.setAttribute("role", "img");
      bar.setAttribute("aria-label", `Where the ${method} trials' time went`);
      fillBudgetBar(bar, b, total);
      row.append(head, bar);
      box.append(row);
    }
    if (!box.childElementCount) {
      const p = document.createElement("p");
      p.className = "muted";
      p.textContent = "No completed trials with a time budget yet.";
      box.append(p);
    }
  }

  async function refreshBoxplots(summary) {
    const img = $("boxplots");
    const nt = summary.n_trials || {};
    if (!(nt.proactive || nt.reactive)) {
      img.hidden = true;
      $("boxplots-empty").textContent = "No completed trials yet.";
      $("boxplots-empty").hidden = false;
      return;
    }
    $("boxplots-empty").textContent = "Rendering the box plots…";
    $("boxplots-empty").hidden = false;
    try {
      const res = await api(`/api/summary/boxplots.png${sessionQuery()}`, { raw: true });
      const blob = await res.blob();
      if (img.dataset.url) URL.revokeObjectURL(img.dataset.url);
      const url = URL.createObjectURL(blob);
      img.dataset.url = url;
      img.src = url;
      img.hidden = false;
      $("boxplots-empty").hidden = true;
    } catch (err) {
      $("boxplots-empty").textContent = "The box plots could not be drawn.";
      showError(describe(err, "Loading the box plots"));
    }
  }

  async function download(path, btn) {
    const sid = $("results-session").value;
    const url = sid && !path.includes("participants.csv") ? `${path}?session_id=${sid}` : path;
    btn.disabled = true;
    try {
      const res = await api(url, { raw: true });
      const blob = await res.blob();
      const disp = res.headers.get("Content-Disposition") || "";
      const m = /filename="?([^";]+)"?/.exec(disp);
      const name = m ? m[1] : path.split("/").pop();
      const a = document.createElement("a");
      a.href = URL.createObjectURL(blob);
      a.download = name;
      document.body.append(a);
      a.click();
      setTimeout(() => { URL.revokeObjectURL(a.href); a.remove(); }, 1000);
      toast(`Downloaded ${name}.`);
    } catch (err) {
      showError(describe(err, "The download"));
    } finally {
      btn.disabled = false;
    }
  }

  // ------------------------------------------------------------------ navigation

  function selectView(view) {
    state.view = view;
    for (const tab of document.querySelectorAll(".tab")) {
      tab.setAttribute("aria-selected", tab.dataset.view === view ? "true" : "false");
    }
    for (const v of ["live", "study", "results"]) $(`view-${v}`).hidden = v !== view;
    if (view === "results") refreshResults();
    if (view === "study") refreshStudy().catch((err) => showError(describe(err, "Loading the study records")));
    if (view === "live" && state.latest) {
      state.lastPlanKey = "";
      state.dirty = true;
    }
  }

  // ------------------------------------------------------------------ wiring

  function init() {
    $("login-form").addEventListener("submit", (ev) => {
      ev.preventDefault();
      const token = $("login-token").value.trim();
      if (!token) {
        $("login-error").textContent = "Enter the operator token.";
        return;
      }
      signIn(token);
    });
    $("logout-button").addEventListener("click", () => signOut("Signed out."));
    $("alert-close").addEventListener("click", clearError);
    $("estop-button").addEventListener("click", estop);
    $("reset-button").addEventListener("click", reset);
    $("participant-form").addEventListener("submit", createParticipant);
    $("session-form").addEventListener("submit", createSession);
    $("trial-form").addEventListener("submit", startTrial);
    $("trial-stop").addEventListener("click", stopTrial);
    $("trial-stop-live").addEventListener("click", stopTrial);
    $("trial-participant").addEventListener("change", () => suggestOrder());
    $("trials-refresh").addEventListener("click", () => refreshTrials().catch((err) => showError(describe(err, "Loading the trials"))));
    $("results-refresh").addEventListener("click", refreshResults);
    $("results-session").addEventListener("change", refreshResults);
    for (const tab of document.querySelectorAll(".tab")) {
      tab.addEventListener("click", () => selectView(tab.dataset.view));
    }
    for (const btn of document.querySelectorAll("[data-download]")) {
      btn.addEventListener("click", () => download(btn.dataset.download, btn));
    }
    window.addEventListener("resize", () => { state.lastPlanKey = ""; state.dirty = true; });
    requestAnimationFrame(render);
    if (state.token) signIn(state.token);
    else showLogin("");
  }

  init();
})();
