// wreckmap live preview: follows /events (server-sent events) and draws what arrives.
// No library and no network beyond this server: the boat has no internet.
"use strict";

const WINDOW_S = 10; // seconds of IMU shown in the plots

const imu = { t: [], gyro: [], accel: [] };
let frames = 0;
let lastData = 0;

function el(id) { return document.getElementById(id); }

function onFrame(info) {
  const id = "cam-" + info.session.replace(/\W/g, "_") + "-" + info.camera;
  let img = document.getElementById(id);
  if (!img) {
    const fig = document.createElement("figure");
    img = document.createElement("img");
    img.id = id;
    img.alt = info.camera;
    img.addEventListener("load", () => {
      frames += 1;
      document.body.dataset.frames = String(frames);
      el("frames").textContent = "frames: " + frames;
      // Tell the server a frame was shown (its /state reports it: a check that the page works).
      fetch("/ack?frames=" + frames).catch(() => {});
    });
    const cap = document.createElement("figcaption");
    cap.id = id + "-cap";
    fig.append(img, cap);
    el("cameras").append(fig);
  }
  img.src = "/frame/" + info.session + "/" + info.camera + ".jpg?seq=" + info.seq;
  const lagMs = (Date.now() * 1e6 - info.receive_ns) / 1e6;
  el(id + "-cap").textContent = info.camera + " " + info.width + "×" + info.height + ", " + lagMs.toFixed(0) + " ms old";
  el("session").textContent = info.session;
}

function onImu(s) {
  for (let i = 0; i < s.t_ns.length; i++) {
    imu.t.push(s.t_ns[i] / 1e9);
    imu.gyro.push(s.gyro_rad_s[i]);
    imu.accel.push(s.accel_m_s2[i]);
  }
  const newest = imu.t[imu.t.length - 1];
  while (imu.t.length && imu.t[0] < newest - WINDOW_S) {
    imu.t.shift(); imu.gyro.shift(); imu.accel.shift();
  }
  plot(el("gyro"), imu.t, imu.gyro, "gyro rad/s");
  plot(el("accel"), imu.t, imu.accel, "accel m/s²");
  el("imu-text").textContent = s.stream + ": " + s.rate_hz + " Hz, |a| mean " + s.accel_norm_mean_m_s2 + " m/s²";
}

// A small line plot of three channels (x red, y green, z blue) on a canvas.
function plot(canvas, t, rows, label) {
  const ctx = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height;
  ctx.clearRect(0, 0, w, h);
  if (t.length < 2) return;
  let lo = Infinity, hi = -Infinity;
  for (const r of rows) for (const v of r) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
  if (hi - lo < 1e-6) { hi += 0.5; lo -= 0.5; }
  const t1 = t[t.length - 1], t0 = t1 - WINDOW_S;
  const x = (tt) => ((tt - t0) / WINDOW_S) * (w - 40) + 35;
  const y = (v) => h - 12 - ((v - lo) / (hi - lo)) * (h - 24);
  ctx.strokeStyle = "#999"; ctx.beginPath(); ctx.moveTo(35, y(0)); ctx.lineTo(w, y(0)); ctx.stroke();
  const colours = ["#c00", "#080", "#00c"];
  for (let c = 0; c < 3; c++) {
    ctx.strokeStyle = colours[c]; ctx.beginPath();
    for (let i = 0; i < t.length; i++) {
      const px = x(t[i]), py = y(rows[i][c]);
      if (i === 0) ctx.moveTo(px, py); else ctx.lineTo(px, py);
    }
    ctx.stroke();
  }
  ctx.fillStyle = "#111"; ctx.font = "11px sans-serif";
  ctx.fillText(label, 40, 12);
  ctx.fillText(hi.toFixed(2), 0, 12); ctx.fillText(lo.toFixed(2), 0, h - 4);
}

function onDepth(d) {
  const depth = d.depth_m === null ? "–" : d.depth_m.toFixed(2) + " m";
  const temp = d.temperature_c === null ? "" : ", " + d.temperature_c.toFixed(1) + " °C";
  el("depth").textContent = d.stream + ": " + depth + temp;
}

function onHealth(hl) {
  const freeMiB = hl.disk_free_bytes / 1048576;
  const line = el("health-line");
  line.textContent = hl.file + " (" + (hl.file_bytes / 1048576).toFixed(1) + " MiB, file " + hl.files +
    "), disk free " + freeMiB.toFixed(0) + " MiB, queue " + hl.queue_items + ", up " + hl.uptime_s + " s, sources " +
    Object.entries(hl.sources).map(([k, v]) => k + " " + v).join(", ");
  line.className = freeMiB < 1024 || Object.values(hl.sources).includes("down") ? "bad" : "";
  if (hl.state === "stopped") {
    // The recorder's last word: why it stopped, and whether its files were closed.
    line.textContent = "recording stopped: " + hl.stop_reason +
      (hl.clean ? " (files closed cleanly)" : " (last file needs wreckmap-field recover)") + "; " + line.textContent;
    line.className = hl.stop_reason.startsWith("disk") || !hl.clean ? "bad" : "";
  }
  const body = el("topics").querySelector("tbody");
  body.replaceChildren();
  for (const [topic, s] of Object.entries(hl.topics)) {
    const tr = document.createElement("tr");
    for (const v of [topic, s.rate_hz.toFixed(1), s.count, s.dropped]) {
      const td = document.createElement("td"); td.textContent = String(v); tr.append(td);
    }
    if (s.dropped > 0) tr.className = "bad";
    body.append(tr);
  }
  const events = el("events");
  events.replaceChildren();
  for (const e of hl.events) { const li = document.createElement("li"); li.textContent = e; events.append(li); }
}

function connect() {
  const source = new EventSource("/events");
  const handle = (fn) => (ev) => { lastData = Date.now(); fn(JSON.parse(ev.data)); };
  source.addEventListener("frame", handle(onFrame));
  source.addEventListener("imu", handle(onImu));
  source.addEventListener("depth", handle(onDepth));
  source.addEventListener("health", handle(onHealth));
}

setInterval(() => {
  const live = Date.now() - lastData < 3000;
  el("status").textContent = live ? "live" : "no data for " + ((Date.now() - lastData) / 1000).toFixed(0) + " s";
  el("status").className = live ? "live" : "stale";
}, 1000);

connect();
