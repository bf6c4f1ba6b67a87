// clvol viewer page: sends state changes over a WebSocket and shows the frames that come
// back. Frame messages are binary: uint32 LE n | n bytes JSON | PNG (clvol/viewer/server.py).
"use strict";

const PRESETS = ["cloud", "fog", "smoke", "milk", "jade", "wax", "skin"];
const $ = (id) => document.getElementById(id);
const state = {};          // the newest state the server confirmed or we sent
const clvol = window.clvol = { framesReceived: 0, errors: [], lastMeta: null, socket: null,
                               frameTimes: [] };

function log(text) {
  clvol.errors.push(text);
  const m = $("messages");
  m.textContent = (text + "\n" + m.textContent).slice(0, 2000);
}

function send(changes) {
  Object.assign(state, changes);
  if (clvol.socket && clvol.socket.readyState === WebSocket.OPEN) {
    clvol.socket.send(JSON.stringify({ type: "state", state: changes }));
  }
}

// Every slider shows its value beside it (a span made in setup()): the number the server
// receives, in the unit a user thinks in (the density slider is log10 of the scale).
const SLIDER_TEXT = {
  albedo0: (v) => v.toFixed(3), albedo1: (v) => v.toFixed(3), albedo2: (v) => v.toFixed(3),
  g: (v) => v.toFixed(2),
  density: (v) => Math.pow(10, v).toPrecision(3),
  exposure: (v) => (v >= 0 ? "+" : "") + v.toFixed(1) + " stops",
  skylevel: (v) => v.toFixed(2),
};
function showNumbers() {
  for (const [id, text] of Object.entries(SLIDER_TEXT)) {
    $(id + "_num").textContent = text(Number($(id).value));
  }
}

// The sky control: a colour (its largest channel scaled to 1) and a radiance (that channel's
// value). sky = [r, g, b] radiance, all 0 for no sky (or the environment map's scale).
function showSky(sky) {
  const m = Math.max(sky[0], sky[1], sky[2]);
  const hex = (v) => Math.round(255 * (m > 0 ? v / m : 1)).toString(16).padStart(2, "0");
  $("skycolour").value = "#" + sky.map(hex).join("");
  $("skylevel").value = m;
}
function skyValue() {
  const h = $("skycolour").value, m = Number($("skylevel").value);
  return [1, 3, 5].map((i) => (m * parseInt(h.slice(i, i + 2), 16)) / 255);
}
function sendSky() { send({ sky: skyValue() }); }

// The map menu: the maps the server offers (by file name), after "(constant colour)".
function showMaps(names) {
  const sel = $("skymap");
  while (sel.options.length > 1) sel.remove(1);
  for (const name of names) {
    const o = document.createElement("option");
    o.value = name; o.textContent = name;
    sel.appendChild(o);
  }
}

function showState(s) {
  Object.assign(state, s);
  $("method").value = s.method;
  $("resolution").value = String(s.resolution);
  $("preset").value = s.preset || "";
  s.albedo.forEach((a, i) => { $("albedo" + i).value = a; });
  $("g").value = s.g;
  showSky(s.sky);
  $("skymap").value = s.sky_map || "";
  $("density").value = Math.log10(s.density_scale);
  $("expmode").value = s.exposure === null ? "image" : s.exposure === "scene" ? "scene" : "manual";
  if (typeof s.exposure === "number") $("exposure").value = s.exposure;
  showNumbers();
}

// The medium controls follow the server when it changed the medium on its own (a preset sets
// albedo and g): otherwise the next albedo slider would send the other channels' stale values.
let syncedPreset;
function syncMedium(s) {
  if (!s || s.preset === syncedPreset) return;
  syncedPreset = s.preset;
  Object.assign(state, { albedo: s.albedo, g: s.g, preset: s.preset });
  s.albedo.forEach((a, i) => { $("albedo" + i).value = a; });
  $("g").value = s.g;
  $("preset").value = s.preset || "";
  showNumbers();
}

function onFrame(buffer) {
  const n = new DataView(buffer).getUint32(0, true);
  const meta = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, n)));
  syncMedium(meta.state);
  const png = new Blob([new Uint8Array(buffer, 4 + n)], { type: "image/png" });
  const img = $("frame");
  const old = img.src;
  img.src = URL.createObjectURL(png);
  if (old) URL.revokeObjectURL(old);
  clvol.lastMeta = meta;
  clvol.framesReceived += 1;
  document.body.dataset.frames = String(clvol.framesReceived);
  const now = performance.now();
  clvol.frameTimes.push(now);
  while (clvol.frameTimes.length > 1 && now - clvol.frameTimes[0] > 2000) clvol.frameTimes.shift();
  const span = (now - clvol.frameTimes[0]) / 1000;
  $("fps").textContent = span > 0 ? ((clvol.frameTimes.length - 1) / span).toFixed(1) : "-";
  $("framems").textContent = meta.frame_ms.toFixed(1) + " ms (" + meta.width + "\u00d7" + meta.height + ")";
  // the path tracer's samples per pixel; the stochastic source's samples per pixel block
  const perBlock = meta.method === "stochastic" || meta.method === "progressive";
  $("spplabel").textContent = perBlock ? "samples" : "spp";
  $("spp").textContent = meta.method === "pathtrace" || perBlock ? String(meta.spp) : "-";
  // the progressive source's path-traced points per block so far (its header's mean)
  const paths = meta.header["raymarch.progressive_paths_per_block"];
  const mean = paths ? String(paths).split(",")[0].replace("mean ", "") : "";
  $("paths").textContent = meta.method === "progressive" && mean ? mean + " per block" : "-";
  $("stages").textContent = Object.entries(meta.stages_ms)
    .map(([k, v]) => k + ": " + v.toFixed(1) + " ms").join("\n");
  $("effects").textContent = Object.entries(meta.effects).map(([k, v]) => k + ": " + v).join("\n");
  const w = $("warning");
  w.hidden = !meta.warning;
  w.textContent = meta.warning || "";
  if ($("expmode").value !== "manual") $("exposure").value = meta.exposure;
  showNumbers();
  nextFrame(meta);
}

// ------------------------------------------------------------------ sequence playback
// A volume sequence (hello's "frames"): a frame slider and a play button. Playing asks for the
// next frame once the frame asked for has arrived (so it never queues frames faster than the
// device renders them), at most every PLAY_MS.
const PLAY_MS = 80;
const seq = { frames: [], playing: false, last: 0 };
clvol.seq = seq;
function showFrameNumber() {
  $("frameno").textContent = seq.frames.length ? String(seq.frames[Number($("frameidx").value)]) : "";
}
function setupSequence(frames, current) {
  seq.frames = frames || [];
  $("sequence").hidden = seq.frames.length < 2;
  $("frameidx").max = String(Math.max(0, seq.frames.length - 1));
  const i = seq.frames.indexOf(current);
  $("frameidx").value = String(i >= 0 ? i : 0);
  showFrameNumber();
}
function nextFrame(meta) {
  if (!seq.playing || !meta.state || meta.state.frame !== state.frame) return;
  const wait = Math.max(0, PLAY_MS - (performance.now() - seq.last));
  setTimeout(() => {
    if (!seq.playing) return;
    const i = (Number($("frameidx").value) + 1) % seq.frames.length;
    $("frameidx").value = String(i);
    showFrameNumber();
    seq.last = performance.now();
    send({ frame: seq.frames[i] });
  }, wait);
}

function connect() {
  const ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws");
  ws.binaryType = "arraybuffer";
  clvol.socket = ws;
  ws.onmessage = (ev) => {
    if (typeof ev.data !== "string") { onFrame(ev.data); return; }
    const msg = JSON.parse(ev.data);
    if (msg.type === "hello") {
      showMaps(msg.sky_maps || []);
      showState(msg.state);
      syncedPreset = msg.state.preset;
      setupSequence(msg.frames, msg.state.frame);
    }
    else if (msg.type === "error") log("error: " + msg.message);
    else if (msg.type === "saved") log("saved " + msg.path);
  };
  ws.onclose = () => {
    // Reconnect (the server starts the new connection from the scene's state); a page whose
    // socket closed would otherwise keep dead controls until a reload.
    log("connection closed; reconnecting");
    setTimeout(connect, 1000);
  };
}

// ------------------------------------------------------------------ controls
function setup() {
  for (const id of Object.keys(SLIDER_TEXT)) {
    const span = document.createElement("span");
    span.id = id + "_num";
    span.className = "num";
    $(id).insertAdjacentElement("afterend", span);
    $(id).addEventListener("input", showNumbers);
  }
  for (const p of PRESETS) {
    const o = document.createElement("option");
    o.value = p; o.textContent = p;
    $("preset").appendChild(o);
  }
  $("method").onchange = () => send({ method: $("method").value });
  $("resolution").onchange = () => send({ resolution: Number($("resolution").value) });
  $("preset").onchange = () => send({ preset: $("preset").value || null });
  for (let i = 0; i < 3; i++) {
    $("albedo" + i).oninput = () => send({ albedo: [0, 1, 2].map((j) => Number($("albedo" + j).value)) });
  }
  $("g").oninput = () => send({ g: Number($("g").value) });
  $("skycolour").oninput = sendSky;
  $("skylevel").oninput = sendSky;
  // a map starts at scale 1 (white, radiance 1); back to a constant sky keeps the colour
  $("skymap").onchange = () => {
    const name = $("skymap").value || null;
    if (name && Math.max(...state.sky) === 0) { showSky([1, 1, 1]); showNumbers(); }
    send({ sky_map: name, sky: skyValue() });   // one message: one frame
  };
  $("density").oninput = () => send({ density_scale: Math.pow(10, Number($("density").value)) });
  $("exposure").oninput = () => { $("expmode").value = "manual"; send({ exposure: Number($("exposure").value) }); };
  // auto: chosen from each frame; from the light: clvol.image.scene_exposure (docs/scenes.md)
  $("expmode").onchange = () => {
    const mode = $("expmode").value;
    send({ exposure: mode === "image" ? null : mode === "scene" ? "scene" : Number($("exposure").value) });
  };
  $("save").onclick = () => clvol.socket.send(JSON.stringify({ type: "save" }));
  $("frameidx").oninput = () => { showFrameNumber(); send({ frame: seq.frames[Number($("frameidx").value)] }); };
  $("play").onclick = () => {
    seq.playing = !seq.playing;
    $("play").textContent = seq.playing ? "pause" : "play";
    if (seq.playing) nextFrame({ state: { frame: state.frame } });
  };

  const img = $("frame");
  let drag = null;
  img.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY, sun: e.shiftKey || $("sunmode").checked };
    img.setPointerCapture(e.pointerId);
  });
  img.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX; drag.y = e.clientY;
    const clampEl = (v, lim) => Math.max(-lim, Math.min(lim, v));
    if (drag.sun) {
      send({ sun_azimuth: state.sun_azimuth - 0.5 * dx,
             sun_elevation: clampEl(state.sun_elevation - 0.5 * dy, 90) });
    } else {
      send({ azimuth: state.azimuth - 0.5 * dx, elevation: clampEl(state.elevation + 0.5 * dy, 89) });
    }
  });
  const end = () => { drag = null; };
  img.addEventListener("pointerup", end);
  img.addEventListener("pointercancel", end);
  img.addEventListener("wheel", (e) => {
    e.preventDefault();
    const d = state.distance * Math.exp(0.001 * e.deltaY);
    send({ distance: Math.max(0.05, Math.min(100, d)) });
  }, { passive: false });
}

setup();
connect();
