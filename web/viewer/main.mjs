// The page of `dftpcc view`: fetches the map as a stream, decodes each prefix that has arrived in a
// Web Worker (an untiled map refines as bytes arrive; a tiled one appears tile by tile once whole) and
// shows it as three.js terrain: empty cells hidden, colour by height (or by decoded minus original)
// with a colour bar, hillshade, orbit controls, the header's figures and the height under the cursor.
// window.viewer holds what the page decoded and showed, for the browser tests and for a curious user.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

// Meshes beyond this many vertices take every s-th cell (the cursor still reads the decoded cell): about
// a vertex per pixel of a laptop's window, and the software renderer of a headless test draws 4 M-cell
// maps in under a second with it.
const MAX_VERTICES = 600_000;
// A tiled map redraws as its tiles decode, at most once in this many milliseconds.
const TILE_SHOW_MS = 250;
const HEIGHT_STOPS = [[0, [0.17, 0.31, 0.56]], [0.22, [0.16, 0.56, 0.52]], [0.45, [0.47, 0.72, 0.33]],
  [0.7, [0.83, 0.68, 0.36]], [0.88, [0.62, 0.45, 0.33]], [1, [0.96, 0.95, 0.93]]];
const ERROR_STOPS = [[0, [0.15, 0.3, 0.75]], [0.5, [0.95, 0.95, 0.95]], [1, [0.8, 0.15, 0.12]]];
// Sun from the north-west, 45 degrees up: the cartographers' hillshade.
const SUN = (() => {
  const az = (315 * Math.PI) / 180;
  const alt = Math.PI / 4;
  return [Math.sin(az) * Math.cos(alt), Math.cos(az) * Math.cos(alt), Math.sin(alt)];
})();

const $ = (id) => document.getElementById(id);
const state = {
  status: "loading", error: null, header: null, stages: [], loads: 0, frames: 0, firstFrameMs: null,
  started: performance.now(), timings: {}, etag: null, colour: "height", original: null, diffMax: null,
};
window.viewer = state;
state.timings.script = Math.round(performance.now());

// --- the worker --------------------------------------------------------------------------------------
const worker = new Worker("worker.js");
let nextId = 0;
const pending = new Map();
worker.onmessage = (event) => {
  const { id } = event.data;
  const done = pending.get(id);
  pending.delete(id);
  if (event.data.error) {
    const err = new Error(event.data.error.message);
    err.name = event.data.error.name;
    done.reject(err);
  } else done.resolve(event.data);
};
worker.onerror = (event) => fail({ name: "Error", message: `the decoder stopped: ${event.message}` });
function ask(message) {
  const id = nextId++;
  return new Promise((resolve, reject) => {
    pending.set(id, { resolve, reject });
    worker.postMessage({ id, ...message });
  });
}

// --- the scene ---------------------------------------------------------------------------------------
const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
renderer.setSize(window.innerWidth, window.innerHeight);
renderer.setClearColor(0x1b1f24);
$("scene").appendChild(renderer.domElement);
const scene = new THREE.Scene();
const camera = new THREE.PerspectiveCamera(45, window.innerWidth / window.innerHeight, 0.1, 1e7);
const controls = new OrbitControls(camera, renderer.domElement);
controls.addEventListener("change", render);
const material = new THREE.MeshBasicMaterial({ vertexColors: true, side: THREE.DoubleSide });
let mesh = null;
let view = null; // the grid now shown: {rows, cols, res, dy, heights, stride, exag, zmin, zmax, ...}

const mark = (name) => { state.timings[name] ??= Math.round(performance.now()); };

function render() {
  renderer.render(scene, camera);
  if (mesh) {
    renderer.getContext().finish();
    mark("rendered");
  }
  state.frames++;
  // Since the page's navigation began (performance's time origin): what a user waits for.
  if (mesh && state.firstFrameMs === null) state.firstFrameMs = performance.now();
}
window.addEventListener("resize", () => {
  camera.aspect = window.innerWidth / window.innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(window.innerWidth, window.innerHeight);
  render();
});

function palette(stops, t, out, k) {
  t = Math.min(1, Math.max(0, t));
  let i = 1;
  while (i < stops.length - 1 && stops[i][0] < t) i++;
  const [t0, c0] = stops[i - 1];
  const [t1, c1] = stops[i];
  const f = (t - t0) / (t1 - t0);
  for (let c = 0; c < 3; c++) out[k + c] = c0[c] + f * (c1[c] - c0[c]);
}

function finiteRange(values) {
  let lo = Infinity;
  let hi = -Infinity;
  for (let k = 0; k < values.length; k++) {
    const v = values[k]; // NaN fails both tests
    if (v < lo) lo = v;
    if (v > hi) hi = v;
  }
  return [lo, hi];
}

/** The terrain of a whole grid of heights (NaN where empty), in metres about its centre. */
function show(rows, cols, heights, geometry) {
  // The scene is in metres: a geographic grid's degrees become metres on its body's sphere.
  const [sx, sy] = metresPerUnit(geometry, state.header?.crs);
  const res = geometry.resolution * sx;
  const dy = (geometry.dy || geometry.resolution) * sy;
  mark("show");
  const [zmin, zmax] = finiteRange(heights);
  if (!Number.isFinite(zmin)) return;
  const first = !view || view.rows !== rows || view.cols !== cols;
  const stride = Math.max(1, Math.ceil(Math.sqrt((rows * cols) / MAX_VERTICES)));
  const exag = first ? exaggeration(rows * dy, cols * res, zmax - zmin) : view.exag;
  const zc = first ? (zmin + zmax) / 2 : view.zc;
  view = { rows, cols, res, dy, heights, stride, exag, zc, zmin, zmax, geometry };
  state.sceneSize = [cols * res, rows * dy];
  const nx = Math.ceil(cols / stride);
  const ny = Math.ceil(rows / stride);
  const pos = new Float32Array(nx * ny * 3);
  const valid = new Uint8Array(nx * ny);
  for (let i = 0; i < ny; i++) {
    for (let j = 0; j < nx; j++) {
      const r = i * stride;
      const c = j * stride;
      const h = heights[r * cols + c];
      const k = i * nx + j;
      valid[k] = Number.isNaN(h) ? 0 : 1;
      pos[3 * k] = (c + 0.5) * res - (cols * res) / 2;
      pos[3 * k + 1] = valid[k] ? (h - zc) * exag : 0;
      pos[3 * k + 2] = (rows * dy) / 2 - (r + 0.5) * dy;
    }
  }
  // Empty cells hidden: a quad with an empty corner keeps the triangle of its three others, if any.
  const index = nx * ny > 65535 ? new Uint32Array(6 * nx * ny) : new Uint16Array(6 * nx * ny);
  let m = 0;
  for (let i = 0; i + 1 < ny; i++) {
    for (let j = 0; j + 1 < nx; j++) {
      const a = i * nx + j;
      const b = a + 1;
      const c = a + nx;
      const d = c + 1;
      const n = valid[a] + valid[b] + valid[c] + valid[d];
      if (n === 4) {
        index[m++] = a; index[m++] = b; index[m++] = d;
        index[m++] = a; index[m++] = d; index[m++] = c;
      } else if (n === 3) {
        if (valid[a]) index[m++] = a;
        if (valid[b]) index[m++] = b;
        if (valid[d]) index[m++] = d;
        if (valid[c]) index[m++] = c;
      }
    }
  }
  view.nx = nx;
  view.ny = ny;
  view.valid = valid;
  mark("triangles");
  const g = new THREE.BufferGeometry();
  g.setAttribute("position", new THREE.BufferAttribute(pos, 3));
  g.setIndex(new THREE.BufferAttribute(index.slice(0, m), 1));
  g.setAttribute("color", new THREE.BufferAttribute(new Float32Array(nx * ny * 3), 3));
  g.computeBoundingSphere();
  g.computeBoundingBox();
  if (mesh) {
    mesh.geometry.dispose();
    mesh.geometry = g;
  } else {
    mesh = new THREE.Mesh(g, material);
    scene.add(mesh);
  }
  mark("geometry");
  paint();
  mark("painted");
  if (first) frame();
  render();
}

function exaggeration(height, width, relief) {
  // Flat fields read as a flat sheet: lift them until their relief is a tenth of the map's width.
  const wanted = (0.1 * Math.max(width, height)) / Math.max(relief, 1e-9);
  return wanted > 1.5 ? Math.min(20, Number(wanted.toPrecision(1))) : 1;
}

function frame() {
  const ext = Math.max(view.cols * view.res, view.rows * view.dy);
  camera.near = ext / 2000;
  camera.far = ext * 20;
  camera.position.set(0, ext * 0.85, ext * 1.05);
  camera.updateProjectionMatrix();
  controls.target.set(0, 0, 0);
  controls.update();
}

/** Vertex colours: height (or decoded minus original) times the hillshade. */
function paint() {
  const { nx, ny, stride, cols, rows, res, dy, heights, exag, valid } = view;
  const colours = mesh.geometry.getAttribute("color").array;
  const diff = state.colour === "error" && state.diff ? state.diff : null;
  const lim = diff ? Math.max(state.diffScale, 1e-12) : 0;
  const su = stride * res;
  const sv = stride * dy;
  // Slope from the neighbours on each side, one-sided at an empty neighbour, flat where both are.
  const slope = (i0, j0, i1, j1, h, step) => {
    const a = i1 >= 0 && j1 >= 0 && i1 < ny && j1 < nx && valid[i1 * nx + j1] ? heights[i1 * stride * cols + j1 * stride] : NaN;
    const b = i0 >= 0 && j0 >= 0 && i0 < ny && j0 < nx && valid[i0 * nx + j0] ? heights[i0 * stride * cols + j0 * stride] : NaN;
    if (a === a && b === b) return (a - b) / (2 * step);
    if (a === a) return (a - h) / step;
    if (b === b) return (h - b) / step;
    return 0;
  };
  for (let i = 0; i < ny; i++) {
    for (let j = 0; j < nx; j++) {
      const k = i * nx + j;
      if (!valid[k]) continue;
      const h = heights[i * stride * cols + j * stride];
      const du = slope(i, j - 1, i, j + 1, h, su) * exag;
      const dv = slope(i - 1, j, i + 1, j, h, sv) * exag;
      const norm = Math.hypot(du, dv, 1);
      const shade = Math.max(0, (-du * SUN[0] - dv * SUN[1] + SUN[2]) / norm);
      if (diff) {
        const e = diff[i * stride * cols + j * stride];
        if (Number.isNaN(e)) colours.fill(0.45, 3 * k, 3 * k + 3);
        else palette(ERROR_STOPS, 0.5 + e / (2 * lim), colours, 3 * k);
      } else palette(HEIGHT_STOPS, (h - view.zmin) / Math.max(view.zmax - view.zmin, 1e-12), colours, 3 * k);
      const light = 0.35 + 0.65 * shade;
      for (let c = 0; c < 3; c++) colours[3 * k + c] *= light;
    }
  }
  mesh.geometry.getAttribute("color").needsUpdate = true;
  legend(diff);
  void rows;
}

function legend(diff) {
  const bar = $("bar");
  const ctx = bar.getContext("2d");
  const img = ctx.createImageData(1, bar.height);
  const rgb = [0, 0, 0];
  for (let y = 0; y < bar.height; y++) {
    palette(diff ? ERROR_STOPS : HEIGHT_STOPS, 1 - y / (bar.height - 1), rgb, 0);
    img.data.set([...rgb.map((v) => Math.round(v * 255)), 255], 4 * y);
  }
  ctx.putImageData(img, 0, 0);
  $("legend-title").textContent = diff ? "decoded − original" : "height";
  $("legend-max").textContent = diff ? `+${metres(state.diffScale)}` : metres(view.zmax);
  $("legend-min").textContent = diff ? `−${metres(state.diffScale)}` : metres(view.zmin);
  $("legend").hidden = false;
}

// --- figures -----------------------------------------------------------------------------------------
function metres(v) {
  const a = Math.abs(v);
  if (a !== 0 && a < 1) return `${(v * 1000).toPrecision(3)} mm`;
  return `${v.toLocaleString("en", { maximumFractionDigits: a < 100 ? 3 : 1 })} m`;
}

/** The semi-major axis (metres) of a geographic CRS, or null for a projected or local one. */
function geographicRadius(crs) {
  const wkt = typeof crs?.wkt === "string" ? crs.wkt.trim() : "";
  if (!/^(GEOGCS|GEOGCRS|GEODCRS)\[/.test(wkt)) return null;
  const m = /(?:SPHEROID|ELLIPSOID)\["[^"]*",\s*([0-9.eE+]+)/.exec(wkt);
  return m ? Number(m[1]) : 6378137;
}

/** Metres per horizontal unit along x and y (1, 1 unless the grid is in degrees). */
function metresPerUnit(g, crs) {
  const radius = geographicRadius(crs);
  if (!radius) return [1, 1];
  const perDegree = (radius * Math.PI) / 180;
  const latitude = g.y0 + (g.rows * (g.dy || g.resolution)) / 2;
  return [perDegree * Math.cos((latitude * Math.PI) / 180), perDegree];
}

function extentOf(g) {
  const dy = g.dy || g.resolution;
  const us = [0, g.cols * g.resolution];
  const vs = [0, g.rows * dy];
  const [c, s] = [Math.cos(g.angle), Math.sin(g.angle)];
  const xs = [];
  const ys = [];
  for (const u of us) for (const v of vs) {
    xs.push(g.angle === 0 ? g.x0 + u : g.x0 + c * u - s * v);
    ys.push(g.angle === 0 ? g.y0 + v : g.y0 + s * u + c * v);
  }
  return [Math.min(...xs), Math.min(...ys), Math.max(...xs), Math.max(...ys)];
}

function crsText(crs) {
  const wkt = typeof crs?.wkt === "string" ? crs.wkt : null;
  if (wkt) return { label: (/^\w+\["([^"]*)"/.exec(wkt) ?? [null, wkt])[1], value: wkt };
  const keys = Object.keys(crs ?? {});
  return keys.length ? { label: JSON.stringify(crs), value: JSON.stringify(crs) } : { label: "none", value: "" };
}

function cellText(g, crs) {
  const unit = geographicRadius(crs) ? (v) => `${Number(v.toPrecision(4))}°` : metres;
  const text = g.dy && g.dy !== g.resolution ? `${unit(g.resolution)} × ${unit(g.dy)}` : unit(g.resolution);
  return geographicRadius(crs) ? `${text} of longitude × latitude` : text;
}

function showHeader(header, bytes) {
  const g = header.geometry;
  const p = header.params;
  const s = header.stats;
  const ext = extentOf(g);
  const crs = crsText(header.crs);
  const rows = [
    ["bytes", "file", `${bytes.toLocaleString("en")} bytes, format ${header.version}${header.tiled ? `, ${header.tiles.ty} × ${header.tiles.tx} tiles` : ""}`, bytes],
    ["rows", "grid", `${g.rows.toLocaleString("en")} × ${g.cols.toLocaleString("en")} cells`, g.rows],
    ["cols", null, null, g.cols],
    ["resolution_m", "cell size", cellText(g, header.crs), g.resolution],
    ["origin", "origin", `${g.x0}, ${g.y0}; angle ${g.angle.toPrecision(4)} rad`, `${g.x0} ${g.y0}`],
    ["extent", "extent", `x ${ext[0].toFixed(2)} … ${ext[2].toFixed(2)}, y ${ext[1].toFixed(2)} … ${ext[3].toFixed(2)}`, ext.join(" ")],
    ["crs", "CRS", crs.label, crs.value],
    ["cutoff", "cutoff", `${p.cutoff}${p.storage === "quantized" ? `, step ${metres(p.step)}` : ""} (${p.profile ?? ""} ${p.transform})`, p.cutoff],
    ["step", null, null, p.step],
    ["dem_max_error_m", "max error", metres(s.dem_max_error_m), s.dem_max_error_m],
    ["dem_rmse_m", "RMSE", metres(s.dem_rmse_m), s.dem_rmse_m],
    ["target_max_error", "target", p.target_max_error > 0 ? `max error ${metres(p.target_max_error)}` : p.target_rmse > 0 ? `RMSE ${metres(p.target_rmse)}` : "none", p.target_max_error],
  ];
  const table = $("header");
  table.replaceChildren();
  for (const [key, label, text, value] of rows) {
    const tr = document.createElement("tr");
    tr.dataset.key = key;
    tr.dataset.value = String(value);
    if (label === null) tr.hidden = true;
    const a = document.createElement("td");
    a.textContent = label ?? key;
    const b = document.createElement("td");
    b.textContent = text ?? "";
    if (key === "crs") {
      b.className = "crs";
      b.title = crs.value;
    }
    tr.append(a, b);
    table.append(tr);
  }
}

function addRow(key, label, text, value) {
  let tr = document.querySelector(`#header tr[data-key="${key}"]`);
  if (!tr) {
    tr = document.createElement("tr");
    tr.dataset.key = key;
    tr.append(document.createElement("td"), document.createElement("td"));
    $("header").append(tr);
  }
  tr.dataset.value = String(value);
  tr.children[0].textContent = label;
  tr.children[1].textContent = text;
}

function status(text) {
  $("status").textContent = text;
}

function fail(err) {
  state.status = "error";
  state.error = { name: err.name, message: err.message };
  const box = $("error");
  box.textContent = `${err.name === "Error" ? "" : `${err.name}: `}${err.message}`;
  box.style.display = "block";
  status("could not show the map");
}

// --- the cursor --------------------------------------------------------------------------------------
const ray = new THREE.Raycaster();
/** The decoded cell under a point of the window (CSS pixels), or null. */
function cellAt(x, y) {
  if (!mesh || !view) return null;
  const rect = renderer.domElement.getBoundingClientRect();
  const ndc = new THREE.Vector2(((x - rect.left) / rect.width) * 2 - 1, -((y - rect.top) / rect.height) * 2 + 1);
  ray.setFromCamera(ndc, camera);
  const hit = ray.intersectObject(mesh)[0];
  if (!hit) return null;
  const { rows, cols, res, dy, heights, geometry: g } = view;
  const col = Math.floor((hit.point.x + (cols * res) / 2) / res);
  const row = Math.floor(((rows * dy) / 2 - hit.point.z) / dy);
  if (row < 0 || col < 0 || row >= rows || col >= cols) return null;
  const height = heights[row * cols + col];
  if (Number.isNaN(height)) return null;
  const u = (col + 0.5) * g.resolution;
  const v = (row + 0.5) * (g.dy || g.resolution);
  const [c, s] = [Math.cos(g.angle), Math.sin(g.angle)];
  const error = state.diff ? state.diff[row * cols + col] : NaN;
  return { row, col, height, x: g.x0 + c * u - s * v, y: g.y0 + s * u + c * v, error };
}
state.cellAt = cellAt;
/** Where the centre of a cell at a height lands in the window (CSS pixels): the inverse of cellAt. */
state.screenOf = (row, col, height) => {
  const { rows, cols, res, dy, zc, exag } = view;
  const p = new THREE.Vector3((col + 0.5) * res - (cols * res) / 2, (height - zc) * exag, (rows * dy) / 2 - (row + 0.5) * dy).project(camera);
  const rect = renderer.domElement.getBoundingClientRect();
  return [rect.left + ((p.x + 1) / 2) * rect.width, rect.top + ((1 - p.y) / 2) * rect.height];
};
let hoverQueued = null;
renderer.domElement.addEventListener("pointermove", (event) => {
  const first = hoverQueued === null;
  hoverQueued = [event.clientX, event.clientY];
  if (first) requestAnimationFrame(() => {
    const cell = cellAt(...hoverQueued);
    hoverQueued = null;
    const box = $("cursor");
    if (!cell) {
      box.textContent = "";
      delete box.dataset.row;
      return;
    }
    Object.assign(box.dataset, { row: cell.row, col: cell.col, height: cell.height });
    box.textContent = `height ${metres(cell.height)} at x ${cell.x.toFixed(2)}, y ${cell.y.toFixed(2)} (row ${cell.row}, col ${cell.col})`
      + (Number.isNaN(cell.error) ? "" : `; decoded − original ${metres(cell.error)}`);
  });
});

// --- loading -----------------------------------------------------------------------------------------
function fullGrid(g) {
  return new Float32Array(g.rows * g.cols).fill(NaN);
}

function record(map, extra) {
  state.stages.push({ bytesRead: map.bytesRead, partial: map.partial, width: map.width, height: map.height,
    row0: map.row0, col0: map.col0, cells: map.statistics.cells, ms: extra.ms, ...extra });
}

async function fetchMap() {
  const res = await fetch(`map.dftpc${location.search}`, { cache: "no-store" });
  if (!res.ok) throw new Error(`the server has no map: ${(await res.text()).trim()}`);
  return res;
}

async function load() {
  state.loads++;
  state.status = "loading";
  state.stages = [];
  state.coarse = null;
  state.diff = null;
  state.diffMax = null;
  state.started = performance.now();
  const mapRes = fetchMap(); // both at once: the map's first bytes need not wait for its name
  const metaRes = await fetch("map.json", { cache: "no-store" });
  if (!metaRes.ok) throw new Error(`the server has no map: ${(await metaRes.text()).trim()}`);
  const meta = await metaRes.json();
  state.etag = meta.etag;
  document.title = `${meta.name} — dftpcc view`;
  $("name").textContent = meta.name;
  mark("meta");
  const res = await mapRes;
  const total = Number(res.headers.get("Content-Length")) || meta.bytes;
  let buf = new Uint8Array(total);
  let got = 0;
  let tiled = null;
  let busy = null;
  let decodedUpTo = 0;
  // The newest prefix goes to the worker whenever it is idle: stages follow the link's pace.
  const refine = () => {
    if (busy || tiled === true || got === decodedUpTo || got >= total) return;
    const n = got;
    decodedUpTo = n;
    busy = (async () => {
      try {
        if (tiled === null) {
          const { header } = await ask({ op: "header", bytes: buf.slice(0, n), fileSize: total });
          tiled = header.tiled;
          state.header = header;
          showHeader(header, total);
          if (tiled) return;
        }
        const { map, ms } = await ask({ op: "decode", bytes: buf.slice(0, n), fileSize: total });
        if (state.status === "error") return;
        record(map, { ms });
        state.coarse ??= map.heights;
        state.status = "partial";
        show(map.height, map.width, map.heights, map.header.geometry);
        status(`${(100 * n / total).toFixed(0)} % of ${total.toLocaleString("en")} bytes: a coarser map (${map.statistics.cells.toLocaleString("en")} cells${map.stride ? `, sampled every ${map.stride} cells` : ""})`);
      } catch {
        // A prefix too short for its header or first coefficients: the next one may do.
      } finally {
        busy = null;
        refine();
      }
    })();
  };
  const reader = res.body.getReader();
  for (;;) {
    const { done, value } = await reader.read();
    if (done) break;
    if (got + value.length > buf.length) {
      const grown = new Uint8Array(Math.max(2 * buf.length, got + value.length));
      grown.set(buf.subarray(0, got));
      buf = grown;
    }
    buf.set(value, got);
    got += value.length;
    refine();
  }
  mark("fetched");
  while (busy) await busy;
  const bytes = buf.subarray(0, got);
  const { header } = await ask({ op: "header", bytes });
  state.header = header;
  showHeader(header, got);
  if (!header.tiled) {
    const { map, ms } = await ask({ op: "decode", bytes });
    record(map, { ms });
    show(map.height, map.width, map.heights, header.geometry);
  } else {
    // Tile by tile, each shown as it decodes.
    const g = header.geometry;
    const t = header.tiles;
    const heights = fullGrid(g);
    const occupied = [...t.cells.keys()].filter((k) => t.cells[k] > 0);
    let shown = 0;
    let lastShown = -Infinity;
    for (const k of occupied) {
      const i = Math.floor(k / t.tx);
      const j = k % t.tx;
      const win = { rows: [i * t.size, Math.min(g.rows, (i + 1) * t.size)], cols: [j * t.size, Math.min(g.cols, (j + 1) * t.size)] };
      const { map, ms } = await ask({ op: "decode", bytes, window: win });
      record(map, { ms, tile: k });
      for (let r = 0; r < map.height; r++) {
        heights.set(map.heights.subarray(r * map.width, (r + 1) * map.width), (map.row0 + r) * g.cols + map.col0);
      }
      shown++;
      status(`tile ${shown} of ${occupied.length}`);
      // A mesh of the whole grid per tile would cost more than the tiles of a large map: a few a second.
      if (shown === occupied.length || performance.now() - lastShown > TILE_SHOW_MS) {
        show(g.rows, g.cols, heights, g);
        lastShown = performance.now();
        await new Promise((resolve) => setTimeout(resolve, 0));
      }
    }
  }
  state.final = view.heights;
  state.doneMs ??= performance.now();
  state.status = "done";
  const ms = header.tiled ? state.stages.reduce((sum, s) => sum + s.ms, 0) : state.stages.at(-1).ms;
  status(`${got.toLocaleString("en")} bytes decoded in ${ms.toFixed(0)} ms (${state.stages.length} stage${state.stages.length > 1 ? "s" : ""})`);
  if (meta.original) await compare(header);
}

async function compare(header) {
  const g = header.geometry;
  const res = await fetch("original.f32", { cache: "no-store" });
  if (!res.ok) throw new Error(`the server has no original: ${(await res.text()).trim()}`);
  const original = new Float32Array(await res.arrayBuffer());
  if (original.length !== g.rows * g.cols) throw new Error(`the original gridded to ${original.length} cells, the map has ${g.rows * g.cols}`);
  const diff = new Float32Array(original.length);
  let most = 0;
  for (let k = 0; k < diff.length; k++) {
    diff[k] = view.heights[k] - original[k];
    if (Math.abs(diff[k]) > most) most = Math.abs(diff[k]);
  }
  state.diff = diff;
  state.diffMax = most;
  // The colour bar spans the 99th percentile of |error|: a few worst cells would leave the rest white.
  const sizes = Float32Array.from(diff.filter((v) => !Number.isNaN(v)), Math.abs).sort();
  state.diffScale = sizes.length ? sizes[Math.floor(0.99 * (sizes.length - 1))] : 0;
  addRow("error_vs_original", "vs original", `max |decoded − original| ${metres(most)}; colours to ±${metres(state.diffScale)} (99 %)`, most);
  $("colourby").hidden = false;
}

for (const input of document.querySelectorAll('input[name="colour"]')) {
  input.addEventListener("change", () => {
    state.colour = input.value;
    if (mesh) {
      paint();
      render();
    }
  });
}

function follow() {
  setInterval(async () => {
    if (state.status === "loading" || state.status === "partial") return;
    try {
      const meta = await (await fetch("map.json", { cache: "no-store" })).json();
      if (meta.etag !== state.etag) {
        $("error").style.display = "none";
        state.error = null;
        await load();
      }
    } catch (err) {
      fail(err);
    }
  }, 1000);
}

(async () => {
  try {
    await load();
  } catch (err) {
    fail(err);
  }
  try {
    const meta = await (await fetch("map.json", { cache: "no-store" })).json();
    if (meta.follow) follow();
  } catch {
    // the server is gone: nothing to follow
  }
})();
