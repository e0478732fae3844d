// magctl view: the live page of a running task and the replay page of run logs (magctl/view/server.py).
// Positions arrive in metres (the run's own documents); the scene is drawn y up, in the camera field.
"use strict";

const COLORS = {robot: "#d9480f", sphere: "#1971c2", goal: "#2b8a3e", band: "rgba(43,138,62,0.18)",
                contact: "#868e96", path: "#f08c00", trail: "rgba(217,72,15,0.35)", field: "#fcfcfa"};
const CANVAS_PX = 560;
const PLOT_EVERY_MS = 250;
const pageId = Math.random().toString(36).slice(2, 10);   // names this page in the run log's control entries

const view = {mode: null, runs: [], drawn: [], info: null, socket: null, paused: false, ended: false, pageId: pageId,
              messages: 0, token: new URLSearchParams(location.search).get("token")};
window.magctlView = view;   // the page's own data: the tests read what was drawn where from here

function $(id) { return document.getElementById(id); }
function um(m) { return m == null ? "—" : (m * 1e6).toFixed(1); }
function say(text) { $("message").textContent = text; }

// --- the scene ---------------------------------------------------------------------------------------------
function transformOf(scene, canvas) {
  const margin = 10;
  const [w, h] = scene.field_m;
  const scale = Math.min((canvas.width - 2 * margin) / w, (canvas.height - 2 * margin) / h);
  return {scale: scale, ox: margin, oy: canvas.height - margin};   // canvas px = (ox + x·scale, oy − y·scale)
}

function toCanvas(t, x, y) { return [t.ox + x * t.scale, t.oy - y * t.scale]; }

function drawRobot(ctx, t, scene, pos, heading, outline) {
  ctx.save();
  ctx.setTransform(t.scale, 0, 0, -t.scale, t.ox, t.oy);
  ctx.translate(pos[0], pos[1]);
  ctx.rotate(heading);
  ctx.beginPath();   // the run's own outline (magctl.plant.outline), its concave front face ahead (paper Fig 1)
  scene.robot.outline_m.forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
  ctx.closePath();
  ctx.restore();
  if (outline) {   // over the camera frame: the tracked outline, the robot itself seen through it
    ctx.strokeStyle = COLORS.robot; ctx.lineWidth = 2; ctx.stroke(); ctx.lineWidth = 1;
  } else {
    ctx.fillStyle = COLORS.robot; ctx.fill();
  }
}

function circle(ctx, t, c, radius, style, fill, dash) {
  const [x, y] = toCanvas(t, c[0], c[1]);
  ctx.beginPath();
  ctx.arc(x, y, radius * t.scale, 0, 2 * Math.PI);
  ctx.setLineDash(dash || []);
  if (fill) { ctx.fillStyle = style; ctx.fill(); } else { ctx.strokeStyle = style; ctx.stroke(); }
  ctx.setLineDash([]);
}

function drawScene(k, event, status) {
  const run = view.runs[k], scene = run.scene, canvas = run.canvas, ctx = canvas.getContext("2d");
  if (!scene || !event) return;
  const t = transformOf(scene, canvas), obs = event.obs, out = event.outputs || {};
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.fillStyle = "#dee2e6";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  const [x0, y0] = toCanvas(t, 0, scene.field_m[1]);
  ctx.fillStyle = COLORS.field;
  ctx.fillRect(x0, y0, scene.field_m[0] * t.scale, scene.field_m[1] * t.scale);
  const image = run.image;
  if (image) {   // the camera frame mapped onto the glass by the rig's pixel calibration (pixel centres at j, i)
    const [a, b, c, d, e, f] = image.affine, s = t.scale;
    ctx.save();
    ctx.setTransform(s * a, -s * d, s * b, -s * e, t.ox + s * c, t.oy - s * f);
    ctx.drawImage(image.bitmap, -0.5, -0.5);
    ctx.restore();
  }
  ctx.lineWidth = 1;
  if (scene.goal_m) {
    if (scene.eps_m) circle(ctx, t, scene.goal_m, scene.eps_m, COLORS.band, true);
    circle(ctx, t, scene.goal_m, scene.sphere_radius_m, COLORS.goal, false, [4, 3]);
  }
  if (scene.contact_m) for (const s of obs.spheres_est_m) circle(ctx, t, s, scene.contact_m, COLORS.contact, false, [2, 4]);
  run.trail.push(obs.robot_est_m);
  if (run.trail.length > 600) run.trail.shift();
  ctx.strokeStyle = COLORS.trail;
  ctx.beginPath();
  run.trail.forEach((p, i) => { const [x, y] = toCanvas(t, p[0], p[1]); if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y); });
  ctx.stroke();
  const passes = (run.passes || []).filter(p => p.seq <= event.seq);
  passes.forEach((p, i) => {   // the motion lines pushed along so far; the newest bold
    const [ax, ay] = toCanvas(t, p.start_m[0], p.start_m[1]), [bx, by] = toCanvas(t, p.end_m[0], p.end_m[1]);
    ctx.strokeStyle = i === passes.length - 1 ? COLORS.path : "rgba(240,140,0,0.35)";
    ctx.lineWidth = i === passes.length - 1 ? 3 : 1.5;
    ctx.beginPath(); ctx.moveTo(ax, ay); ctx.lineTo(bx, by); ctx.stroke();
  });
  ctx.lineWidth = 1;
  if (Array.isArray(out.target) && out.target[0] != null) {   // the servo's target: the next waypoint
    const [ax, ay] = toCanvas(t, obs.robot_est_m[0], obs.robot_est_m[1]);
    const [bx, by] = toCanvas(t, out.target[0], out.target[1]);
    ctx.strokeStyle = COLORS.path; ctx.setLineDash([6, 4]); ctx.lineWidth = 2;
    ctx.beginPath(); ctx.moveTo(ax, ay); ctx.lineTo(bx, by); ctx.stroke();
    ctx.setLineDash([]); ctx.lineWidth = 1;
    ctx.strokeRect(bx - 4, by - 4, 8, 8);
  }
  drawRobot(ctx, t, scene, obs.robot_est_m, obs.heading_est_rad, !!image);
  ctx.lineWidth = image ? 2 : 1;
  obs.spheres_est_m.forEach(s => circle(ctx, t, s, scene.sphere_radius_m, COLORS.sphere, !image));
  ctx.lineWidth = 1;
  ctx.fillStyle = "#222";
  ctx.font = "12px system-ui";
  ctx.fillText(`t ${obs.t_s.toFixed(2)} s   frame ${obs.frame}   seq ${event.seq}` +
               (event.paused ? "   PAUSED" : "") + (obs.lost ? "   TRACKING LOST" : ""), 14, 18);
  ctx.fillText("1 mm", 14, canvas.height - 16);
  ctx.fillRect(14, canvas.height - 12, 1e-3 * t.scale, 3);
  view.drawn[k] = {seq: event.seq, t_s: obs.t_s, transform: t, camera: image ? image.count : 0,
                   robot_px: toCanvas(t, obs.robot_est_m[0], obs.robot_est_m[1]),
                   spheres_px: obs.spheres_est_m.map(s => toCanvas(t, s[0], s[1])),
                   colors: {robot: COLORS.robot, sphere: COLORS.sphere}};
  showNumbers(k, event, status);
}

function showNumbers(k, event, status) {
  const run = view.runs[k], scene = run.scene, out = event.outputs || {}, cmd = event.cmd || {};
  const phase = out.phase != null ? (scene.phases[String(out.phase)] || out.phase) : "—";
  const st = out.status != null ? (scene.statuses[String(out.status)] || out.status) : "—";
  let err = null;
  if (scene.goal_m && event.obs.spheres_est_m.length) {
    err = Math.min(...event.obs.spheres_est_m.map(s => Math.hypot(s[0] - scene.goal_m[0], s[1] - scene.goal_m[1])));
  }
  const rows = [
    ["task", `${scene.task} (seed ${scene.seed})`], ["status", st], ["phase", phase],
    ["attempt", out.attempt != null ? out.attempt : "—"],
    ["sphere–goal", err == null ? "—" : `${um(err)} µm (ε ${um(scene.eps_m)} µm)`],
    ["robot", `${um(event.obs.robot_est_m[0])}, ${um(event.obs.robot_est_m[1])} µm`],
    ["field", cmd.b_osc_T == null ? "—" : `static ${(Math.hypot(...cmd.b_static_T) * 1e3).toFixed(2)} mT, ` +
      `osc ${(cmd.b_osc_T * 1e3).toFixed(2)} mT at ${cmd.freq_Hz.toFixed(1)} Hz`],
    ["tracking", event.obs.lost ? "<span class=lost>lost</span>" : "ok"],
  ];
  if (status) rows.push(["rig", `${status.state}${status.paused ? " (paused)" : ""}; ticks ${status.ticks}, ` +
                         `overruns ${status.overruns}, slow steps ${status.slow_steps}` +
                         (status.watchdog_trips != null ? `, watchdog trips ${status.watchdog_trips}` : "")]);
  run.numbers.innerHTML = rows.map(([a, b]) => `<tr><td>${a}</td><td data-key="${a}">${b}</td></tr>`).join("");
}

// --- plots (plotly.js) ---------------------------------------------------------------------------------------
const plotState = {last: 0, history: []};

function plotAll() {
  const errorTraces = [], commandTraces = [], currentTraces = [];
  let eps = null, limits = [], names = [];
  view.runs.forEach((run, k) => {
    const tag = view.runs.length > 1 ? ` (${run.name})` : "";
    eps = eps || run.scene.eps_m;
    limits = run.scene.coil_limit_A; names = run.scene.coil_names;
    errorTraces.push({x: run.attempts.map(a => a.attempt), y: run.attempts.map(a => a.error_m * 1e6),
                      mode: "lines+markers", name: "sphere–goal" + tag});
    const pts = run.points;
    commandTraces.push({x: pts.map(p => p[0]), y: pts.map(p => p[1] * 1e3), name: "B osc (mT)" + tag, mode: "lines"});
    commandTraces.push({x: pts.map(p => p[0]), y: pts.map(p => p[3] * 1e3), name: "|B static| (mT)" + tag, mode: "lines"});
    commandTraces.push({x: pts.map(p => p[0]), y: pts.map(p => p[2]), name: "f (Hz)" + tag, mode: "lines", yaxis: "y2"});
    const last = run.current;
    if (last) currentTraces.push({type: "bar", x: names, y: last.obs.currents_A, name: "current" + tag});
  });
  const shapes = eps ? [{type: "rect", xref: "paper", x0: 0, x1: 1, y0: 0, y1: eps * 1e6, fillcolor: COLORS.band,
                         line: {width: 0}}] : [];
  const small = {margin: {l: 50, r: 50, t: 30, b: 40}, showlegend: true, legend: {orientation: "h", y: -0.25}};
  const ended = Math.max(0, ...view.runs.map(r => r.attempts.length));
  const none = ended ? [] : [{text: "no attempt has ended yet", xref: "paper", yref: "paper", x: 0.5, y: 0.6,
                              showarrow: false, font: {color: "#888"}}];
  Plotly.react("plot-errors", errorTraces, {...small, title: {text: "error per attempt (band: ε)", font: {size: 13}},
               xaxis: {title: "attempt", dtick: 1, range: [0.5, Math.max(ended, 3) + 0.5]},
               yaxis: ended ? {title: "µm", rangemode: "tozero"} : {title: "µm", range: [0, 4 * (eps || 1e-5) * 1e6]},
               shapes: shapes, annotations: none}, {displayModeBar: false});
  Plotly.react("plot-commands", commandTraces, {...small, title: {text: "field commands", font: {size: 13}},
               xaxis: {title: "t (s)"}, yaxis: {title: "mT"}, yaxis2: {title: "Hz", overlaying: "y", side: "right"}},
               {displayModeBar: false});
  const limitShapes = limits.flatMap((lim, i) => [+1, -1].map(s => ({type: "line", x0: i - 0.4, x1: i + 0.4,
                                      y0: s * lim, y1: s * lim, line: {color: "#c92a2a", width: 2}})));
  Plotly.react("plot-currents", currentTraces, {...small, title: {text: "coil currents (red: ratings)", font: {size: 13}},
               yaxis: {title: "A", range: [-(Math.max(...limits, 1) * 1.1), Math.max(...limits, 1) * 1.1]},
               shapes: limitShapes}, {displayModeBar: false});
}

function maybePlot(force) {
  const now = performance.now();
  if (!force && now - plotState.last < PLOT_EVERY_MS) return;
  plotState.last = now;
  plotAll();
}

// --- the panels --------------------------------------------------------------------------------------------
function addRun(info, name) {
  const box = document.createElement("div");
  box.className = "run";
  const k = view.runs.length;
  box.innerHTML = `<h2>${name}</h2><canvas width="${CANVAS_PX}" height="${Math.round(CANVAS_PX * 0.78)}" ` +
                  `id="scene-${k}"></canvas><table id="numbers-${k}"></table>`;
  $("runs").appendChild(box);
  const run = {name: name, scene: info.scene, canvas: box.querySelector("canvas"), numbers: box.querySelector("table"),
               attempts: info.attempts || [], passes: info.passes || [], points: [], trail: [], current: null,
               info: info};
  view.runs.push(run);
  return run;
}

// --- live --------------------------------------------------------------------------------------------------
function liveSetup(info) {
  const run = addRun(info.runs[0], "live run");
  run.points = (info.runs[0].history || []).slice();
  $("pause").disabled = $("stop").disabled = !info.controls;
  if (!info.controls) say("controls are off for this run (start it with --view-controls)");
  const proto = location.protocol === "https:" ? "wss" : "ws";
  const socket = new WebSocket(`${proto}://${location.host}/ws`);
  view.socket = socket;
  socket.onmessage = (msg) => {
    const doc = JSON.parse(msg.data);
    view.messages += 1;
    if (doc.type === "control") {
      say(doc.ok ? `${doc.action} sent (by ${doc.by})` : `${doc.action} refused: ${doc.reason}`);
      return;
    }
    if (!run.scene && doc.event) return;
    if (doc.attempts) run.attempts = doc.attempts;
    if (doc.passes) run.passes = doc.passes;
    if (doc.event) {
      const e = doc.event;
      run.current = e;
      run.points.push([e.obs.t_s, (e.cmd || {}).b_osc_T || 0, (e.cmd || {}).freq_Hz || 0,
                       e.cmd ? Math.hypot(...e.cmd.b_static_T) : 0, e.obs.currents_A, e.obs.lost, !!e.paused]);
      if (run.points.length > 1800) run.points.shift();
      drawScene(0, e, doc.status);
      view.paused = !!(doc.status && doc.status.paused);
      $("pause").textContent = view.paused ? "Resume" : "Pause";
    }
    if (doc.type === "stopped") {
      view.ended = true;
      view.stop = doc.stop;
      $("pause").disabled = $("stop").disabled = true;
      say(`run ended: ${doc.stop.exit_status} — ${doc.stop.reason}`);
      maybePlot(true);
    } else {
      maybePlot(false);
    }
  };
  socket.onclose = () => { if (!view.ended) say("connection to the run closed"); };
  if (info.runs[0].camera) cameraLoop(run, 0);
  const send = (action) => socket.send(JSON.stringify({action: action, page: pageId, token: view.token}));
  $("stop").onclick = () => send("stop");
  $("pause").onclick = () => send(view.paused ? "resume" : "pause");
}

async function cameraLoop(run, misses) {   // the rig's camera frame, a few times a second, while the run goes
  if (view.ended || misses > 5) return;
  let next = 200;
  try {
    const r = await fetch(`/api/camera.png?n=${run.imageCount || 0}`, {cache: "no-store"});
    if (r.status === 200) {
      const affine = r.headers.get("X-Magctl-Affine").split(",").map(Number);
      const bitmap = await createImageBitmap(await r.blob());
      run.imageCount = (run.imageCount || 0) + 1;
      run.image = {bitmap: bitmap, affine: affine, count: run.imageCount};
      misses = 0;
    } else {
      misses += 1;    // no frame (yet): a simulated plant has none; give up after a few
      next = 1000;
    }
  } catch (err) {
    misses += 1;
    next = 1000;
  }
  setTimeout(() => cameraLoop(run, misses), next);
}

// --- replay ------------------------------------------------------------------------------------------------
const replay = {t: 0, playing: false, speed: 1, lastTick: 0, chunks: new Map(), CHUNK: 1000};

async function fetchJSON(url) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${url}: ${r.status}`);
  return r.json();
}

async function chunk(k, c) {
  const key = `${k}:${c}`;
  if (!replay.chunks.has(key)) {
    replay.chunks.set(key, fetchJSON(`/api/frames?run=${k}&start=${c * replay.CHUNK}&count=${replay.CHUNK}`)
      .then(d => d.events));
  }
  return replay.chunks.get(key);
}

function frameIndexAt(run, t) {   // the last frame at or before run time t (s since its first frame)
  const times = run.times, target = run.info.t0_s + t;
  let lo = 0, hi = times.length - 1;
  if (target <= times[0]) return 0;
  while (lo < hi) { const mid = (lo + hi + 1) >> 1; if (times[mid] <= target) lo = mid; else hi = mid - 1; }
  return lo;
}

async function showAt(t) {
  replay.t = t;
  $("timeline").value = t;
  $("clock").textContent = `${t.toFixed(2)} s`;
  await Promise.all(view.runs.map(async (run, k) => {
    const i = frameIndexAt(run, t);
    const events = await chunk(k, Math.floor(i / replay.CHUNK));
    const e = events[i % replay.CHUNK];
    run.current = e;
    run.index = i;
    run.trail = run.trailPoints.filter(p => p[0] <= i).map(p => p[1]);
    drawScene(k, e, null);
  }));
  plotCursor();
}

function plotCursor() {
  maybePlot(true);
  const shapes = [{type: "line", xref: "x", yref: "paper", x0: replay.t + (view.runs[0] ? view.runs[0].info.t0_s : 0),
                   x1: replay.t + (view.runs[0] ? view.runs[0].info.t0_s : 0), y0: 0, y1: 1, line: {color: "#555", dash: "dot"}}];
  Plotly.relayout("plot-commands", {shapes: shapes});
}

async function replaySetup(info) {
  $("replay-bar").hidden = false;
  let duration = 0;
  for (const [k, r] of info.runs.entries()) {
    const run = addRun(r, r.name + (r.note ? " — crashed" : r.stop ? ` — ${r.stop.exit_status}` : ""));
    const series = await fetchJSON(`/api/series?run=${k}`);
    run.points = series.points;
    run.times = await fetchJSON(`/api/times?run=${k}`);
    duration = Math.max(duration, r.t1_s - r.t0_s);
  }
  // the trail: the robot's path at the frames the series sampled
  for (const [k, run] of view.runs.entries()) {
    const pos = await fetchJSON(`/api/path?run=${k}`);
    run.trailPoints = pos.index.map((i, j) => [i, pos.robot_m[j]]);
  }
  const bar = $("timeline");
  bar.max = duration;
  bar.oninput = () => { replay.playing = false; $("play").textContent = "Play"; showAt(parseFloat(bar.value)); };
  $("speed").onchange = () => { replay.speed = parseFloat($("speed").value); };
  $("play").onclick = () => {
    replay.playing = !replay.playing;
    $("play").textContent = replay.playing ? "Pause" : "Play";
    replay.lastTick = performance.now();
    if (replay.playing) requestAnimationFrame(playTick);
  };
  const jumps = $("attempt-jumps");
  view.runs.forEach((run, k) => run.attempts.forEach(a => {
    const b = document.createElement("button");
    b.textContent = view.runs.length > 1 ? `${k + 1}: attempt ${a.attempt}` : `attempt ${a.attempt}`;
    b.dataset.run = k; b.dataset.attempt = a.attempt;
    b.title = `end of attempt ${a.attempt}: sphere–goal ${um(a.error_m)} µm (frame seq ${a.seq})`;
    b.onclick = async () => {
      replay.playing = false; $("play").textContent = "Play";
      await showAt(a.t_s - run.info.t0_s);
      say(`attempt ${a.attempt}${view.runs.length > 1 ? ` of ${run.name}` : ""}: sphere–goal ${um(a.error_m)} µm at seq ${a.seq}`);
      view.shownAttempt = {run: k, attempt: a.attempt, seq: a.seq, error_um: a.error_m * 1e6};
    };
    jumps.appendChild(b);
  }));
  const notes = info.runs.filter(r => r.note).map(r => r.note);
  if (notes.length) say(notes.join("; "));
  await showAt(0);
}

async function playTick(now) {
  if (!replay.playing) return;
  const dt = (now - replay.lastTick) / 1000 * replay.speed;
  replay.lastTick = now;
  const end = parseFloat($("timeline").max);
  const t = Math.min(end, replay.t + dt);
  await showAt(t);
  if (t >= end) { replay.playing = false; $("play").textContent = "Play"; return; }
  requestAnimationFrame(playTick);
}

// --- export ------------------------------------------------------------------------------------------------
function exportPNG() {
  view.runs.forEach((run, k) => {
    const seq = view.drawn[k] ? view.drawn[k].seq : 0;
    run.canvas.toBlob(blob => {
      const a = document.createElement("a");
      a.href = URL.createObjectURL(blob);
      a.download = `magctl-${(run.scene.uid || "run").slice(0, 8)}-seq${seq}.png`;
      document.body.appendChild(a); a.click(); a.remove();
    }, "image/png");
  });
}

async function main() {
  const info = await fetchJSON("/api/info");
  view.info = info;
  view.mode = info.mode;
  $("mode").textContent = info.mode === "live" ? "live" : "replay";
  $("export").onclick = exportPNG;
  if (info.mode === "live") {
    if (!info.runs[0].scene) {   // the run has not started yet: ask again
      setTimeout(main, 200);
      return;
    }
    liveSetup(info);
  } else {
    await replaySetup(info);
  }
  view.ready = true;
}

main().catch(err => say(`error: ${err.message}`));
