// pressurepose click page: place the mat's corner markers on a camera image and save the marker
// file `pressurepose coregister` reads. Talks to viz/clicker.py's JSON API only; loads nothing
// from the internet.
//
// Pixel frame (coregister's): u right, v down, in the original image's pixels, (0, 0) = the
// centre of the top-left pixel. On screen, image point (u, v) is drawn at
//   x = offX + (u + 0.5) * scale,  y = offY + (v + 0.5) * scale   (CSS pixels in the canvas).
//
// Test hooks: document.body.dataset.ready = "1" once the image is drawn; window.clickerState
// holds the view (scale, offX, offY), the markers, the active marker, saves and any error.
"use strict";

const $ = (id) => document.getElementById(id);
const CORNERS = ["head_left", "head_right", "foot_left", "foot_right"];
const COLOURS = { head_left: "#ff4d4d", head_right: "#ffd23f", foot_left: "#3fd2ff", foot_right: "#7dff5c" };
const HIT_PX = 9;   // a press this close (CSS px) to a marker grabs it instead of placing one
const MOVE_PX = 3;  // a press that moves less than this is a click, not a drag
const st = { info: null, img: null, markers: [], undo: [], sel: -1, scale: 1, offX: 0, offY: 0,
             dpr: 1, drag: null, reproj: null, dirty: false };
window.clickerState = { ready: false, scale: 1, offX: 0, offY: 0, markers: [], active: "", saves: 0, error: "" };

function sync() {
  Object.assign(window.clickerState, { scale: st.scale, offX: st.offX, offY: st.offY, active: active(),
                                       markers: JSON.parse(JSON.stringify(st.markers)) });
}

function showError(msg) {
  $("error").textContent = msg;
  $("error").style.display = msg ? "block" : "none";
  window.clickerState.error = msg;
}

async function api(path, options) {
  const r = await fetch(path, options);
  let body = null;
  try { body = await r.json(); } catch (_) { /* not JSON */ }
  if (!r.ok) throw new Error((body && body.error) || r.statusText);
  return body;
}

const colourOf = (name) => COLOURS[name] || "#ff7cf5";
const round3 = (x) => Math.round(x * 1000) / 1000;

// --- view: fit, zoom, pan ------------------------------------------------------------------

const canvas = $("img");

function resize() {
  const r = canvas.getBoundingClientRect();
  st.dpr = window.devicePixelRatio || 1;
  canvas.width = Math.max(1, Math.round(r.width * st.dpr));
  canvas.height = Math.max(1, Math.round(r.height * st.dpr));
  draw();
}

function fit() {
  if (!st.info) return;
  const r = canvas.getBoundingClientRect(), W = st.info.width, H = st.info.height;
  st.scale = Math.min(r.width / W, r.height / H);
  st.offX = (r.width - W * st.scale) / 2;
  st.offY = (r.height - H * st.scale) / 2;
  draw();
}

function toImage(clientX, clientY) {
  const r = canvas.getBoundingClientRect();
  return [(clientX - r.left - st.offX) / st.scale - 0.5, (clientY - r.top - st.offY) / st.scale - 0.5];
}

const toScreen = (u, v) => [st.offX + (u + 0.5) * st.scale, st.offY + (v + 0.5) * st.scale];

function zoomAt(px, py, factor) {
  const fitScale = Math.min(canvas.clientWidth / st.info.width, canvas.clientHeight / st.info.height);
  const s = Math.min(64, Math.max(fitScale / 4, st.scale * factor));
  st.offX = px - (px - st.offX) * s / st.scale;  // keep the image point under the cursor still
  st.offY = py - (py - st.offY) * s / st.scale;
  st.scale = s;
  draw();
}

// --- drawing -------------------------------------------------------------------------------

function draw() {
  const g = canvas.getContext("2d");
  g.setTransform(st.dpr, 0, 0, st.dpr, 0, 0);
  g.fillStyle = "#333";
  g.fillRect(0, 0, canvas.width, canvas.height);
  if (st.img) {
    g.imageSmoothingEnabled = st.scale < 1;  // crisp pixels when zoomed in, to click precisely
    g.drawImage(st.img, st.offX, st.offY, st.info.width * st.scale, st.info.height * st.scale);
  }
  g.font = "bold 12px system-ui, sans-serif";
  st.markers.forEach((m, i) => {
    const [x, y] = toScreen(m.pixel[0], m.pixel[1]);
    const c = colourOf(m.name), sel = i === st.sel;
    for (const [w, col] of [[sel ? 5 : 3, "#000"], [sel ? 2.5 : 1.2, c]]) {
      g.strokeStyle = col; g.lineWidth = w;
      g.beginPath();
      g.moveTo(x - 12, y); g.lineTo(x - 3, y); g.moveTo(x + 3, y); g.lineTo(x + 12, y);
      g.moveTo(x, y - 12); g.lineTo(x, y - 3); g.moveTo(x, y + 3); g.lineTo(x, y + 12);
      g.stroke();
      g.beginPath(); g.arc(x, y, 7, 0, 2 * Math.PI); g.stroke();
    }
    g.lineWidth = 3; g.strokeStyle = "#000"; g.fillStyle = c;
    g.strokeText(m.name, x + 10, y - 10); g.fillText(m.name, x + 10, y - 10);
  });
  if (st.reproj) {  // where the saved pose puts the markers: far from the clicks = a bad click
    g.strokeStyle = "#ff1744"; g.lineWidth = 1.5;
    for (const [u, v] of st.reproj) {
      const [x, y] = toScreen(u, v);
      g.beginPath(); g.moveTo(x - 5, y - 5); g.lineTo(x + 5, y + 5); g.moveTo(x + 5, y - 5); g.lineTo(x - 5, y + 5); g.stroke();
    }
  }
  sync();
}

// --- markers -------------------------------------------------------------------------------

function active() {
  const r = document.querySelector("input[name=which]:checked");
  return r ? r.value : "";
}

function setActive(name) {
  const r = document.querySelector(`input[name=which][value="${name}"]`);
  if (r) r.checked = true;
  sync();
}

function edited() {
  st.dirty = true;
  st.reproj = null;
  $("result").textContent = "unsaved changes";
  listMarkers();
  draw();
}

function pushUndo() {
  st.undo.push(JSON.stringify(st.markers));
  if (st.undo.length > 500) st.undo.shift();
}

function undo() {
  if (!st.undo.length) return;
  st.markers = JSON.parse(st.undo.pop());
  st.sel = -1;
  if (active() !== "__custom__") {  // the first corner still to click (usually the one undone)
    const next = CORNERS.find((c) => !st.markers.some((x) => x.name === c));
    if (next) setActive(next);
  }
  edited();
}

function deleteSelected() {
  if (st.sel < 0) return;
  pushUndo();
  st.markers.splice(st.sel, 1);
  st.sel = -1;
  edited();
}

async function lookUpDepth(m) {
  delete m.depth_m;  // a moved marker's old depth is wrong
  if (!st.info.has_depth) return;
  try {
    const r = await api(`api/depth?u=${m.pixel[0]}&v=${m.pixel[1]}`);
    if (r.depth_m !== null) m.depth_m = r.depth_m;
  } catch (e) { showError(e.message); }
  listMarkers();
  sync();
}

function place(u, v) {
  let name = active(), xyz = null;
  if (name === "__custom__") {
    name = $("cname").value.trim();
    xyz = ["cx_m", "cy_m", "cz_m"].map((id) => Number($(id).value));
    if (!name || xyz.some((x) => !Number.isFinite(x))) {
      showError("the other marker needs a name and its mat x, y, z in metres");
      return;
    }
  }
  showError("");
  pushUndo();
  let i = st.markers.findIndex((m) => m.name === name);
  if (i < 0) { st.markers.push({ name }); i = st.markers.length - 1; }
  const m = st.markers[i];
  m.pixel = [round3(u), round3(v)];
  if (xyz) m.mat_xyz_m = xyz; else delete m.mat_xyz_m;
  st.sel = i;
  if (xyz) {  // ready for the next one: marker5 -> marker6
    $("cname").value = name.replace(/(\d*)$/, (d) => String((Number(d) || 0) + 1));
  } else {
    const next = CORNERS.find((c) => !st.markers.some((x) => x.name === c));
    if (next) setActive(next);
  }
  lookUpDepth(m);
  edited();
}

function listMarkers() {
  const t = $("markers");
  t.innerHTML = "";
  st.markers.forEach((m, i) => {
    const tr = t.insertRow();
    tr.className = i === st.sel ? "sel" : "";
    tr.dataset.name = m.name;
    const sw = `<span style="display:inline-block;width:9px;height:9px;background:${colourOf(m.name)}"></span>`;
    const d = m.depth_m !== undefined ? `${m.depth_m.toFixed(3)} m` : "";
    const xyz = m.mat_xyz_m ? ` @ (${m.mat_xyz_m.join(", ")})` : "";
    tr.innerHTML = `<td>${sw}</td><td></td><td>${m.pixel[0].toFixed(2)}</td><td>${m.pixel[1].toFixed(2)}</td>` +
                   `<td>${d}</td><td><button title="delete">&times;</button></td>`;
    tr.cells[1].textContent = m.name + xyz;  // names are the user's text
    tr.onclick = () => { st.sel = i; listMarkers(); draw(); };
    tr.querySelector("button").onclick = (e) => { e.stopPropagation(); st.sel = i; deleteSelected(); };
  });
  $("count").textContent = st.markers.length;
  for (const c of CORNERS) {
    const label = document.querySelector(`#corners label[data-name="${c}"]`);
    if (label) label.classList.toggle("done", st.markers.some((m) => m.name === c));
  }
}

// --- pointer: click places, drag moves a marker or pans, wheel zooms -------------------------

function hit(clientX, clientY) {
  const r = canvas.getBoundingClientRect();
  let best = -1, bestD = HIT_PX;
  st.markers.forEach((m, i) => {
    const [x, y] = toScreen(m.pixel[0], m.pixel[1]);
    const d = Math.hypot(x - (clientX - r.left), y - (clientY - r.top));
    if (d < bestD) { best = i; bestD = d; }
  });
  return best;
}

canvas.addEventListener("pointerdown", (e) => {
  if (!st.info) return;
  canvas.setPointerCapture(e.pointerId);
  const i = e.button === 0 ? hit(e.clientX, e.clientY) : -1;
  st.drag = { x: e.clientX, y: e.clientY, button: e.button, moved: false, i, offX: st.offX, offY: st.offY,
              before: JSON.stringify(st.markers) };
  if (i >= 0) { st.sel = i; listMarkers(); draw(); }
});

canvas.addEventListener("pointermove", (e) => {
  if (!st.info) return;
  const [u, v] = toImage(e.clientX, e.clientY);
  $("cursor").textContent = `u ${u.toFixed(2)}, v ${v.toFixed(2)}, zoom ${st.scale.toFixed(2)}`;
  const d = st.drag;
  if (!d) return;
  if (Math.hypot(e.clientX - d.x, e.clientY - d.y) >= MOVE_PX) d.moved = true;
  if (!d.moved) return;
  if (d.i >= 0) {
    st.markers[d.i].pixel = [round3(u), round3(v)];
  } else {
    st.offX = d.offX + e.clientX - d.x;
    st.offY = d.offY + e.clientY - d.y;
  }
  draw();
});

canvas.addEventListener("pointerup", (e) => {
  const d = st.drag;
  st.drag = null;
  if (!d) return;
  if (d.i >= 0 && d.moved) {
    st.undo.push(d.before);
    lookUpDepth(st.markers[d.i]);
    edited();
  } else if (d.i < 0 && !d.moved && d.button === 0) {
    const [u, v] = toImage(e.clientX, e.clientY);
    const W = st.info.width, H = st.info.height;
    if (u >= -0.5 && u <= W - 0.5 && v >= -0.5 && v <= H - 0.5) place(u, v);
  }
});

canvas.addEventListener("wheel", (e) => {
  if (!st.info) return;
  e.preventDefault();
  const r = canvas.getBoundingClientRect();
  zoomAt(e.clientX - r.left, e.clientY - r.top, Math.exp(-e.deltaY * 0.0015));
}, { passive: false });

canvas.addEventListener("contextmenu", (e) => e.preventDefault());

document.addEventListener("keydown", (e) => {
  if (e.target.tagName === "INPUT") return;
  if ((e.ctrlKey || e.metaKey) && e.key === "z") { e.preventDefault(); undo(); }
  else if (e.key === "Delete" || e.key === "Backspace") { e.preventDefault(); deleteSelected(); }
  else if (e.key === "f") fit();
  else if (e.key >= "1" && e.key <= "4") setActive(CORNERS[Number(e.key) - 1]);
});

// --- save ----------------------------------------------------------------------------------

async function save() {
  const intrinsics = {};
  for (const k of ["fx", "fy", "cx", "cy"]) {
    if ($(k).value.trim() !== "") intrinsics[k] = Number($(k).value);
  }
  const markers = st.markers.map((m) => {
    const out = { name: m.name, pixel: m.pixel };
    if (m.depth_m !== undefined) out.depth_m = m.depth_m;
    if (m.mat_xyz_m) out.mat_xyz_m = m.mat_xyz_m;
    return out;
  });
  try {
    const r = await api("api/save", { method: "POST", headers: { "Content-Type": "application/json" },
                                      body: JSON.stringify({ intrinsics, markers }) });
    showError("");
    st.markers = r.document.markers;  // with the depths the server read
    st.dirty = false;
    const res = $("result");
    res.textContent = `saved ${r.document.markers.length} markers to ${r.saved}\n`;
    if (r.pose) {
      const p = r.pose.camera_position_in_mat_m.map((x) => x.toFixed(3)).join(", ");
      res.textContent += `reprojection RMS ${r.pose.rms_px.toFixed(2)} px (red x: where the pose puts ` +
                         `each marker); camera at (${p}) m in the mat frame\n`;
      st.reproj = r.pose.reprojected;
    } else {
      res.textContent += `no pose from these markers yet: ${r.pose_error}\n`;
    }
    res.appendChild(document.createTextNode("next: "));
    const code = document.createElement("code");
    code.id = "command";
    code.textContent = r.command;
    res.appendChild(code);
    window.clickerState.saves += 1;
    listMarkers();
    draw();
  } catch (e) {
    showError(`not saved: ${e.message}`);
    $("result").textContent = `not saved: ${e.message}`;
  }
}

// --- start ---------------------------------------------------------------------------------

async function start() {
  try {
    const info = await api("api/info");
    st.info = info;
    $("what").textContent = `${info.image} (${info.width} x ${info.height}` +
      (info.has_depth ? `, depth ${info.depth_range_m[0]}-${info.depth_range_m[1]} m` : "") + `) -> ${info.out}`;
    for (const k of ["fx", "fy", "cx", "cy"]) {
      if (info.intrinsics) $(k).value = info.intrinsics[k];
    }
    const box = $("corners");
    for (const c of CORNERS) {
      const label = document.createElement("label");
      label.dataset.name = c;
      const xyz = info.corners[c].map((x) => x.toFixed(3)).join(", ");
      label.innerHTML = `<input type="radio" name="which" value="${c}"> <span style="color:${colourOf(c)};` +
                        `text-shadow:0 0 2px #000">&#9679;</span> ${c} <span class="hint">(${xyz})</span>`;
      box.appendChild(label);
    }
    document.querySelectorAll("input[name=which]").forEach((r) => { r.onchange = sync; });
    st.markers = JSON.parse(JSON.stringify(info.markers));
    setActive(CORNERS.find((c) => !st.markers.some((m) => m.name === c)) || CORNERS[0]);
    const img = new Image();
    img.src = "api/image.png";
    await img.decode();
    st.img = img;
    new ResizeObserver(() => { resize(); }).observe($("stage"));
    resize();
    fit();
    listMarkers();
    if (!info.intrinsics) $("result").textContent = "fill in the camera intrinsics before saving";
    $("undo").onclick = undo;
    $("delete").onclick = deleteSelected;
    $("fit").onclick = fit;
    $("save").onclick = save;
    window.addEventListener("beforeunload", (e) => { if (st.dirty) e.preventDefault(); });
    window.clickerState.ready = true;
    document.body.dataset.ready = "1";
  } catch (e) {
    showError(e.message);
  }
}

start();
