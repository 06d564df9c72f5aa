// pressurepose viewer page: sample list, pressure heat map, a plain-WebGL 3D view of the true
// and estimated bodies, labels and joint errors, training curves. Talks to viz/viewer.py's
// JSON API only; loads nothing from the internet.
//
// Test hooks: document.body.dataset.ready = "1" once the first sample is fully drawn (or the
// page has nothing else to draw); window.viewerState holds the current sample, the number of
// triangles drawn in the last 3D frame, the layers and any error.
"use strict";

const $ = (id) => document.getElementById(id);
const PAGE = 200;
const state = { info: null, order: "index", page: -1, items: [], pos: 0, sample: null,
                faces: null, layers: {}, loading: 0, request: 0 };
window.viewerState = { sample: -1, triangles: 0, draws: 0, layers: [], error: "" };

// --- helpers -------------------------------------------------------------------------------

function showError(msg) {
  const e = $("error");
  e.textContent = msg;
  e.style.display = msg ? "block" : "none";
  window.viewerState.error = msg;
}

async function api(path, binary) {
  const r = await fetch(path);
  if (!r.ok) {
    let msg = r.statusText;
    try { msg = (await r.json()).error; } catch (_) { /* not JSON */ }
    throw new Error(msg);
  }
  return binary ? r : r.json();
}

function fmtValue(k, v) {
  if (typeof v !== "number") return String(v);
  if (k.endsWith("_m")) return (v * 100).toFixed(2) + " cm";
  if (k.endsWith("_kg")) return v.toFixed(1) + " kg";
  if (k.endsWith("_deg")) return v.toFixed(1) + " deg";
  if (k.endsWith("_mm")) return v.toFixed(1) + " mm";
  return Number.isInteger(v) ? String(v) : v.toFixed(3);
}

const LABELS = { vpe_m: "3DVPE", v2v_m: "v2v", mpjpe_m: "MPJPE", pa_mpjpe_m: "PA-MPJPE",
                 root_pos_m: "root position err.", root_rot_deg: "root angle err.",
                 height_err_m: "height err.", mass_err_kg: "mass err.", height_m: "height", mass_kg: "mass" };

// --- colour map: dark blue -> purple -> red -> orange -> pale yellow (ours) -------------------

const STOPS = [[0, 24, 26, 48], [0.15, 70, 30, 130], [0.38, 175, 40, 110], [0.62, 238, 96, 44],
               [0.85, 250, 200, 70], [1, 255, 252, 215]];
function colour(t) {
  t = Math.min(1, Math.max(0, t));
  for (let s = 1; s < STOPS.length; s++) {
    if (t <= STOPS[s][0]) {
      const a = STOPS[s - 1], b = STOPS[s], u = (t - a[0]) / (b[0] - a[0]);
      return [0, 1, 2].map((c) => Math.round(a[c + 1] + u * (b[c + 1] - a[c + 1])));
    }
  }
  return STOPS[STOPS.length - 1].slice(1);
}

// --- pressure heat map with joints and a colour bar -----------------------------------------

const HM = { scale: 8, x0: 4, y0: 0, bar: 14 };
const texCanvas = document.createElement("canvas"); // the raw image, also the mat's texture

function drawPressure(s) {
  const c = $("pressure"), g = c.getContext("2d");
  const rows = s.rows, cols = s.cols, p = s.pressure;
  const vmax = $("autoscale").checked ? Math.max(1e-3, ...p) : state.info.mat.max_pressure_mmhg;
  texCanvas.width = cols; texCanvas.height = rows;
  const tg = texCanvas.getContext("2d"), img = tg.createImageData(cols, rows);
  for (let i = 0; i < rows * cols; i++) {
    const rgb = colour(p[i] / vmax);
    img.data.set([rgb[0], rgb[1], rgb[2], 255], 4 * i);
  }
  tg.putImageData(img, 0, 0);
  g.fillStyle = "#fff"; g.fillRect(0, 0, c.width, c.height);
  g.imageSmoothingEnabled = false;
  const W = cols * HM.scale, H = rows * HM.scale;
  g.drawImage(texCanvas, HM.x0, HM.y0, W, H);
  // joints: x along the bed -> rows, y across -> columns (mat frame, docs/conventions.md)
  const m = state.info.mat;
  const px = (j) => [HM.x0 + (j[1] / m.pitch_col_m) * HM.scale, HM.y0 + (j[0] / m.pitch_row_m) * HM.scale];
  if (s.joints_true && s.joints_est) {
    g.strokeStyle = "rgba(255,255,255,0.7)"; g.lineWidth = 1;
    s.joints_true.forEach((j, k) => {
      const a = px(j), b = px(s.joints_est[k]);
      g.beginPath(); g.moveTo(a[0], a[1]); g.lineTo(b[0], b[1]); g.stroke();
    });
  }
  for (const [joints, fill] of [[s.joints_true, "#ffffff"], [s.joints_est, "#00e5ff"]]) {
    if (!joints) continue;
    g.fillStyle = fill;
    for (const j of joints) { const a = px(j); g.beginPath(); g.arc(a[0], a[1], 2.5, 0, 2 * Math.PI); g.fill(); }
  }
  // colour bar
  const bx = HM.x0 + W + 8;
  for (let y = 0; y < H; y++) {
    const rgb = colour(1 - y / H);
    g.fillStyle = `rgb(${rgb[0]},${rgb[1]},${rgb[2]})`; g.fillRect(bx, HM.y0 + y, HM.bar, 1);
  }
  g.fillStyle = "#222"; g.font = "11px system-ui, sans-serif";
  for (let k = 0; k <= 4; k++) {
    const y = HM.y0 + H * (1 - k / 4);
    g.fillText((vmax * k / 4).toFixed(0), bx + HM.bar + 3, Math.min(H - 2, Math.max(10, y + 4)));
  }
}

// --- 3D view: plain WebGL, per-face normals, two lights, orbit camera ------------------------

const VS = `attribute vec3 aPos; attribute vec3 aNormal; attribute vec2 aUV;
uniform mat4 uMVP; uniform vec3 uOffset; varying vec3 vN; varying vec2 vUV;
void main() { vN = aNormal; vUV = aUV; gl_Position = uMVP * vec4(aPos + uOffset, 1.0); }`;
const FS = `precision mediump float; varying vec3 vN; varying vec2 vUV;
uniform vec3 uColor; uniform vec3 uLight; uniform vec3 uEye; uniform float uTextured; uniform sampler2D uTex;
void main() {
  vec3 n = normalize(vN); if (!gl_FrontFacing) n = -n;
  vec3 base = uTextured > 0.5 ? texture2D(uTex, vUV).rgb : uColor;
  float shade = 0.3 + 0.5 * max(dot(n, uLight), 0.0) + 0.3 * max(dot(n, uEye), 0.0);
  gl_FragColor = vec4(base * (uTextured > 0.5 ? 1.0 : shade), 1.0);
}`;

const view = { gl: null, prog: null, loc: {}, buffers: {}, yaw: -Math.PI / 2, pitch: 0.75, dist: 2.6,
               target: [0.9, 0.37, 0.05], matTex: null };

function initGL() {
  const canvas = $("gl");
  const gl = canvas.getContext("webgl", { preserveDrawingBuffer: true, antialias: true });
  if (!gl) throw new Error("this browser has no WebGL: the 3D view cannot be drawn");
  const shader = (type, src) => {
    const s = gl.createShader(type); gl.shaderSource(s, src); gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  };
  const prog = gl.createProgram();
  gl.attachShader(prog, shader(gl.VERTEX_SHADER, VS)); gl.attachShader(prog, shader(gl.FRAGMENT_SHADER, FS));
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
  view.gl = gl; view.prog = prog;
  for (const n of ["aPos", "aNormal", "aUV"]) view.loc[n] = gl.getAttribLocation(prog, n);
  for (const n of ["uMVP", "uOffset", "uColor", "uLight", "uEye", "uTextured", "uTex"]) view.loc[n] = gl.getUniformLocation(prog, n);
  gl.enable(gl.DEPTH_TEST);
  view.matTex = gl.createTexture();
  // orbit with the mouse, zoom with the wheel
  let drag = null;
  canvas.addEventListener("pointerdown", (e) => { drag = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
  canvas.addEventListener("pointerup", () => { drag = null; });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    view.yaw -= (e.clientX - drag[0]) * 0.01;
    view.pitch = Math.max(-1.5, Math.min(1.5, view.pitch + (e.clientY - drag[1]) * 0.01));
    drag = [e.clientX, e.clientY]; draw();
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault(); view.dist = Math.max(0.3, Math.min(12, view.dist * Math.exp(e.deltaY * 0.001))); draw();
  }, { passive: false });
}

function upload(name, positions, normals, uvs) {
  const gl = view.gl;
  const old = view.buffers[name];
  if (old) for (const b of old.bufs) gl.deleteBuffer(b);
  const bufs = [positions, normals, uvs].map((a) => {
    const b = gl.createBuffer(); gl.bindBuffer(gl.ARRAY_BUFFER, b); gl.bufferData(gl.ARRAY_BUFFER, a, gl.STATIC_DRAW); return b;
  });
  view.buffers[name] = { bufs, count: positions.length / 3 };
}

// Vertices (V*3 floats) + faces (F*3) -> one position and one face normal per corner.
function meshArrays(v, f) {
  const F = f.length / 3, pos = new Float32Array(F * 9), nrm = new Float32Array(F * 9);
  for (let t = 0; t < F; t++) {
    const a = 3 * f[3 * t], b = 3 * f[3 * t + 1], c = 3 * f[3 * t + 2];
    const ux = v[b] - v[a], uy = v[b + 1] - v[a + 1], uz = v[b + 2] - v[a + 2];
    const wx = v[c] - v[a], wy = v[c + 1] - v[a + 1], wz = v[c + 2] - v[a + 2];
    let nx = uy * wz - uz * wy, ny = uz * wx - ux * wz, nz = ux * wy - uy * wx;
    const l = Math.hypot(nx, ny, nz) || 1; nx /= l; ny /= l; nz /= l;
    for (const [k, src] of [[0, a], [1, b], [2, c]]) {
      pos.set([v[src], v[src + 1], v[src + 2]], 9 * t + 3 * k);
      nrm.set([nx, ny, nz], 9 * t + 3 * k);
    }
  }
  return [pos, nrm, new Float32Array(F * 6)];
}

function matArrays() {
  const m = state.info.mat, X = m.rows * m.pitch_row_m, Y = m.cols * m.pitch_col_m, z = -0.004;
  const pos = new Float32Array([0, 0, z, X, 0, z, X, Y, z, 0, 0, z, X, Y, z, 0, Y, z]);
  const nrm = new Float32Array(18).map((_, i) => (i % 3 === 2 ? 1 : 0));
  // texture u = column / cols (across, y), v = row / rows (along, x)
  const uv = new Float32Array([0, 0, 0, 1, 1, 1, 0, 0, 1, 1, 1, 0]);
  return [pos, nrm, uv];
}

function mat4Mul(a, b) {
  const o = new Float32Array(16);
  for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) {
    let s = 0; for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k]; o[c * 4 + r] = s;
  }
  return o;
}
function perspective(fovy, aspect, near, far) {
  const f = 1 / Math.tan(fovy / 2), nf = 1 / (near - far);
  return new Float32Array([f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * nf, -1, 0, 0, 2 * far * near * nf, 0]);
}
function normalize(v) { const l = Math.hypot(...v) || 1; return v.map((x) => x / l); }
function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
function lookAt(eye, at, up) {
  const z = normalize(eye.map((e, i) => e - at[i])), x = normalize(cross(up, z)), y = cross(z, x);
  const d = (a) => -(a[0] * eye[0] + a[1] * eye[1] + a[2] * eye[2]);
  return new Float32Array([x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0, d(x), d(y), d(z), 1]);
}

function sideOffset() { return $("side3d").checked ? 0.9 : 0; }

function draw() {
  const gl = view.gl;
  if (!gl) return;
  const canvas = gl.canvas;
  gl.viewport(0, 0, canvas.width, canvas.height);
  gl.clearColor(0.875, 0.89, 0.918, 1);
  gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
  gl.useProgram(view.prog);
  const off = sideOffset();
  const at = [view.target[0], view.target[1] + off / 2, view.target[2]];
  const cp = Math.cos(view.pitch);
  const dir = [cp * Math.cos(view.yaw), cp * Math.sin(view.yaw), Math.sin(view.pitch)];
  const eye = at.map((a, i) => a + view.dist * dir[i]);
  const mvp = mat4Mul(perspective(0.7, canvas.width / canvas.height, 0.05, 50), lookAt(eye, at, [0, 0, 1]));
  gl.uniformMatrix4fv(view.loc.uMVP, false, mvp);
  gl.uniform3fv(view.loc.uLight, normalize([0.3, -0.4, 1]));
  gl.uniform3fv(view.loc.uEye, normalize(dir));
  gl.activeTexture(gl.TEXTURE0); gl.bindTexture(gl.TEXTURE_2D, view.matTex); gl.uniform1i(view.loc.uTex, 0);
  let triangles = 0;
  const items = [];
  const showT = $("showTrue").checked, showE = $("showEst").checked;
  if (view.buffers.mat) {
    items.push(["mat", [0, 0, 0], null]);
    if (off && view.buffers.estimated && showE) items.push(["mat", [0, off, 0], null]);
  }
  if (view.buffers.true && showT) items.push(["true", [0, 0, 0], [0.56, 0.65, 0.79]]);
  if (view.buffers.estimated && showE) items.push(["estimated", [0, off, 0], [0.89, 0.34, 0.18]]);
  for (const [name, offset, col] of items) {
    const b = view.buffers[name];
    const attrs = [["aPos", 3], ["aNormal", 3], ["aUV", 2]];
    attrs.forEach(([a, n], k) => {
      gl.bindBuffer(gl.ARRAY_BUFFER, b.bufs[k]);
      gl.enableVertexAttribArray(view.loc[a]);
      gl.vertexAttribPointer(view.loc[a], n, gl.FLOAT, false, 0, 0);
    });
    gl.uniform3fv(view.loc.uOffset, offset);
    gl.uniform1f(view.loc.uTextured, col ? 0 : 1);
    gl.uniform3fv(view.loc.uColor, col || [1, 1, 1]);
    gl.drawArrays(gl.TRIANGLES, 0, b.count);
    if (name !== "mat") triangles += b.count / 3;
  }
  window.viewerState.triangles = triangles;
  window.viewerState.draws += 1;
}

function setMatTexture() {
  const gl = view.gl;
  gl.bindTexture(gl.TEXTURE_2D, view.matTex);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA, gl.RGBA, gl.UNSIGNED_BYTE, texCanvas);
  for (const [p, v] of [[gl.TEXTURE_MIN_FILTER, gl.NEAREST], [gl.TEXTURE_MAG_FILTER, gl.NEAREST],
                        [gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE], [gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE]]) gl.texParameteri(gl.TEXTURE_2D, p, v);
}

// --- sample panels -------------------------------------------------------------------------

function drawMeta(s) {
  const rows = Object.entries(s.meta).filter(([k]) => !k.startsWith("joints_"));
  $("meta").innerHTML = "";
  for (const [k, v] of rows) {
    const tr = document.createElement("tr");
    tr.innerHTML = `<td class="k"></td><td></td>`;
    tr.children[0].textContent = LABELS[k] || k; tr.children[1].textContent = fmtValue(k, v);
    $("meta").appendChild(tr);
  }
  const jt = $("joints");
  jt.innerHTML = "";
  if (!s.joint_errors_m) {
    jt.innerHTML = `<tr><td>${s.joints_est ? "no true body to compare with" : "no estimate for this sample"}</td></tr>`;
    return;
  }
  const worst = Math.max(0.1, ...s.joint_errors_m);
  s.joint_errors_m.forEach((e, k) => {
    const tr = document.createElement("tr");
    tr.innerHTML = `<td></td><td style="text-align:right"></td><td><span class="jbar"></span></td>`;
    tr.children[0].textContent = state.info.joint_names[k];
    tr.children[1].textContent = (e * 100).toFixed(1);
    tr.querySelector(".jbar").style.width = `${Math.round(120 * e / worst)}px`;
    jt.appendChild(tr);
  });
}

async function showSample(i) {
  const req = ++state.request;
  showError("");
  try {
    const s = await api(`/api/sample/${i}`);
    if (req !== state.request) return; // a newer click won
    state.sample = s;
    $("current").textContent = `#${i} of ${state.info.count}`;
    drawPressure(s); drawMeta(s);
    if (view.gl) setMatTexture();
    if (state.info.has_truth || state.info.has_estimate) {
      const r = await api(`/api/mesh/${i}`, true);
      const layers = (r.headers.get("X-Layers") || "").split(",").filter((x) => x);
      const V = Number(r.headers.get("X-Vertices"));
      const data = new Float32Array(await r.arrayBuffer());
      if (req !== state.request) return;
      if (!state.faces) state.faces = new Uint32Array(await (await api("/api/faces", true)).arrayBuffer());
      for (const name of ["true", "estimated"]) delete view.buffers[name];
      layers.forEach((name, k) => upload(name, ...meshArrays(data.subarray(3 * V * k, 3 * V * (k + 1)), state.faces)));
      if (window.viewerState.sample < 0) { // first mesh: aim at the true body (or the estimate)
        const v = data.subarray(0, 3 * V), lo = [1e9, 1e9, 1e9], hi = [-1e9, -1e9, -1e9];
        for (let k = 0; k < V; k++) for (let c = 0; c < 3; c++) { lo[c] = Math.min(lo[c], v[3 * k + c]); hi[c] = Math.max(hi[c], v[3 * k + c]); }
        view.target = lo.map((l, c) => (l + hi[c]) / 2);
      }
      window.viewerState.layers = layers;
    }
    draw();
    window.viewerState.sample = i;
    document.body.dataset.sample = String(i);
    document.body.dataset.ready = "1";
    [...$("list").children].forEach((d) => d.classList.toggle("sel", Number(d.dataset.i) === i));
  } catch (err) {
    showError(`sample ${i}: ${err.message}`);
    document.body.dataset.ready = "1";
  }
}

// --- list, paging, next / previous ---------------------------------------------------------

async function loadPage(page) {
  const r = await api(`/api/list?offset=${page * PAGE}&limit=${PAGE}&order=${state.order}`);
  state.page = page; state.items = r.items;
  const pages = Math.max(1, Math.ceil(r.total / PAGE));
  $("page").textContent = `page ${page + 1} / ${pages}`;
  const list = $("list");
  list.innerHTML = "";
  r.items.forEach((e, k) => {
    const d = document.createElement("div");
    d.dataset.i = e.i;
    const parts = [`#${e.i}`, e.partition, e.gender, e.posture, e.subject].filter((x) => x !== undefined);
    if (e.vpe_m !== undefined) parts.push(`${(e.vpe_m * 100).toFixed(1)} cm`);
    d.textContent = parts.join(" ");
    d.addEventListener("click", () => gotoPos(page * PAGE + k));
    list.appendChild(d);
  });
}

async function gotoPos(pos) {
  const n = state.info.count;
  if (n === 0) return;
  pos = ((pos % n) + n) % n;
  const page = Math.floor(pos / PAGE);
  if (page !== state.page) await loadPage(page);
  state.pos = pos;
  await showSample(state.items[pos - page * PAGE].i);
}

// --- training curves and figures -----------------------------------------------------------

function lineChart(title, series) {
  const panel = document.createElement("div");
  panel.className = "panel";
  panel.innerHTML = `<h3></h3><canvas width="420" height="220"></canvas>`;
  panel.querySelector("h3").textContent = title;
  $("curves").appendChild(panel);
  const c = panel.querySelector("canvas"), g = c.getContext("2d");
  const all = series.flatMap((s) => s.values.filter((v) => Number.isFinite(v)));
  if (!all.length) return;
  const n = Math.max(...series.map((s) => s.values.length));
  const lo = Math.min(0, ...all), hi = Math.max(...all) * 1.2 || 1;  // headroom for the legend
  const L = 44, R = 10, T = 10, B = 24, W = c.width - L - R, H = c.height - T - B;
  g.strokeStyle = "#999"; g.strokeRect(L, T, W, H);
  g.fillStyle = "#333"; g.font = "11px system-ui, sans-serif";
  for (let k = 0; k <= 4; k++) g.fillText((lo + (hi - lo) * k / 4).toPrecision(3), 2, T + H * (1 - k / 4) + 4);
  g.fillText("epoch", L + W / 2 - 14, c.height - 6);
  g.fillText("1", L, c.height - 12); g.fillText(String(n), L + W - 10, c.height - 12);
  series.forEach((s, k) => {
    g.strokeStyle = s.color; g.lineWidth = 2; g.beginPath();
    s.values.forEach((v, e) => {
      const x = L + (n > 1 ? W * e / (n - 1) : W / 2), y = T + H * (1 - (v - lo) / (hi - lo));
      if (e === 0) g.moveTo(x, y); else g.lineTo(x, y);
      if (n === 1) g.fillRect(x - 2, y - 2, 4, 4);
    });
    g.stroke();
    g.fillStyle = s.color; g.fillText(s.name, L + 8 + 110 * k, T + 14);
  });
}

function drawRun(info) {
  const rows = info.metrics;
  if (!rows.length) return;
  const col = (k) => rows.map((r) => (r[k] === undefined ? NaN : r[k]));
  lineChart("loss", [{ name: "train", values: col("loss"), color: "#2d6cdf" },
                     { name: "validation", values: col("val_loss"), color: "#e4572e" }]);
  lineChart("MPJPE (mm)", [{ name: "train", values: col("train_mpjpe_mm"), color: "#2d6cdf" },
                           { name: "validation", values: col("val_mpjpe_mm"), color: "#e4572e" }]);
}

function drawFigures(info) {
  for (const name of info.images) {
    const d = document.createElement("div");
    d.className = "panel";
    d.innerHTML = `<h3></h3><img alt="">`;
    d.querySelector("h3").textContent = name;
    d.querySelector("img").src = `/files/${name}`;
    $("figures").appendChild(d);
  }
}

// --- start ---------------------------------------------------------------------------------

async function start() {
  try {
    const info = await api("/api/info");
    state.info = info;
    $("title").textContent = `pressurepose ${info.kind}`;
    $("what").textContent = `${info.path} - ${info.count} samples${info.split ? ` (${info.split} split)` : ""}, ${info.backend} body`;
    const sum = info.summary || {};
    if (sum.vpe_m !== undefined) $("summary").textContent = `mean 3DVPE ${(sum.vpe_m * 100).toFixed(2)} cm, MPJPE ${(sum.mpjpe_m * 100).toFixed(2)} cm`;
    $("note").textContent = info.note || "";
    if (info.kind === "report") {
      for (const [k, label] of [["vpe_m", "3DVPE, worst first"], ["mpjpe_m", "MPJPE, worst first"]]) {
        const o = document.createElement("option"); o.value = k; o.textContent = label; $("order").appendChild(o);
      }
    }
    $("showEst").disabled = !info.has_estimate;
    drawRun(info);
    drawFigures(info);
    if (!info.count) {
      $("samplePanels").style.display = "none"; $("controls").style.display = "none"; $("side").style.display = "none";
      document.body.dataset.ready = "1";
      return;
    }
    if (info.has_truth || info.has_estimate) {
      initGL();
      upload("mat", ...matArrays());
    } else {  // pressure images only: no 3D view and none of its controls
      $("gl").parentElement.style.display = "none";
      for (const id of ["showTrue", "showEst", "side3d"]) $(id).parentElement.style.display = "none";
      $("resetView").style.display = "none"; document.querySelector(".legend").style.display = "none";
    }
    $("showTrue").disabled = !info.has_truth;
    $("prev").onclick = () => gotoPos(state.pos - 1);
    $("next").onclick = () => gotoPos(state.pos + 1);
    $("pgprev").onclick = () => gotoPos((state.page - 1) * PAGE);
    $("pgnext").onclick = () => gotoPos((state.page + 1) * PAGE);
    $("order").onchange = () => { state.order = $("order").value; state.page = -1; gotoPos(0); };
    $("goto").onchange = () => {
      const i = Number($("goto").value);
      if (state.order === "index") gotoPos(i); else { state.request++; showSample(i); }
    };
    for (const id of ["showTrue", "showEst", "side3d"]) $(id).onchange = draw;
    $("autoscale").onchange = () => { if (state.sample) { drawPressure(state.sample); if (view.gl) { setMatTexture(); draw(); } } };
    $("resetView").onclick = () => { view.yaw = -Math.PI / 2; view.pitch = 0.75; view.dist = 2.6; draw(); };
    document.addEventListener("keydown", (e) => {
      if (e.target.tagName === "INPUT") return;
      if (e.key === "ArrowRight") gotoPos(state.pos + 1);
      if (e.key === "ArrowLeft") gotoPos(state.pos - 1);
    });
    await gotoPos(0);
  } catch (err) {
    showError(err.message);
    document.body.dataset.ready = "1";
  }
}

start();
