// The viewer page in a real headless browser (Debian's chromium driven by puppeteer-core, software
// WebGL): maps written by the Python codec from ../shared/data, served by `dftpcc view` itself.
// Screenshots stay in DFTPCC_VIEWER_ARTIFACTS (default a fresh temporary folder, printed) to be looked at.
import { spawn, spawnSync } from "node:child_process";
import { copyFileSync, existsSync, mkdirSync, mkdtempSync, readdirSync, readFileSync, renameSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";
import { after, before, describe, test } from "node:test";
import assert from "node:assert/strict";
import puppeteer from "puppeteer-core";
import { ROOT, WEB, python } from "./helpers.mjs";

const CHROMIUM = process.env.CHROMIUM ?? "/usr/bin/chromium";
const FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
  "--disable-sync", "--no-first-run", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"];
const ENV = { ...process.env, PYTHONPATH: join(ROOT, "src"), PYTHONWARNINGS: "ignore" };

let work;
let artifacts;
let fx;
let browser;
const servers = [];

function f32(path) {
  const b = readFileSync(path);
  return new Float32Array(b.buffer.slice(b.byteOffset, b.byteOffset + b.byteLength));
}

/** `dftpcc view MAP --port 0 ...`: resolves to {url, proc} once it prints its address. */
function view(map, ...args) {
  const proc = spawn(python(), ["-m", "dftpcc", "view", map, "--port", "0", ...args], { env: ENV, stdio: ["ignore", "pipe", "pipe"] });
  servers.push(proc);
  return new Promise((resolve, reject) => {
    let out = "";
    let err = "";
    proc.stdout.on("data", (d) => {
      out += d;
      const m = /(http:\/\/127\.0\.0\.1:\d+\/)/.exec(out);
      if (m) resolve({ url: m[1], proc });
    });
    proc.stderr.on("data", (d) => { err += d; });
    proc.on("exit", (code) => reject(new Error(`dftpcc view exited ${code}: ${err}`)));
  });
}

/** A page of the viewer, its console errors and uncaught exceptions collected. */
async function open(url, { until = "done" } = {}) {
  const page = await browser.newPage();
  await page.setViewport({ width: 1000, height: 700 });
  const problems = [];
  page.on("pageerror", (e) => problems.push(`pageerror: ${e.message}`));
  page.on("console", (m) => { if (m.type() === "error") problems.push(`console: ${m.text()}`); });
  await page.goto(url);
  await page.waitForFunction((s) => window.viewer && (window.viewer.status === s || window.viewer.status === "error"),
    { timeout: 120_000, polling: 100 }, until);
  return { page, problems };
}

async function shot(page, name) {
  const path = join(artifacts, `${name}.png`);
  await page.screenshot({ path });
  return path;
}

/** Pixel statistics of the WebGL canvas, read back in the page (preserveDrawingBuffer keeps it). */
function pixels(page) {
  return page.evaluate(() => {
    const src = document.querySelector("#scene canvas");
    const c = document.createElement("canvas");
    c.width = src.width;
    c.height = src.height;
    const ctx = c.getContext("2d");
    ctx.drawImage(src, 0, 0);
    const { data } = ctx.getImageData(0, 0, c.width, c.height);
    const bg = [0x1b, 0x1f, 0x24];
    const differs = (k) => Math.abs(data[k] - bg[0]) + Math.abs(data[k + 1] - bg[1]) + Math.abs(data[k + 2] - bg[2]) > 12;
    let off = 0;
    let centre = 0;
    let centreN = 0;
    const colours = new Set();
    for (let y = 0; y < c.height; y++) {
      for (let x = 0; x < c.width; x++) {
        const k = 4 * (y * c.width + x);
        const d = differs(k);
        off += d;
        colours.add((data[k] >> 3) << 10 | (data[k + 1] >> 3) << 5 | (data[k + 2] >> 3));
        if (Math.abs(x - c.width / 2) < c.width / 10 && Math.abs(y - c.height / 2) < c.height / 10) {
          centre += d;
          centreN++;
        }
      }
    }
    return { covered: off / (c.width * c.height), centre: centre / centreN, colours: colours.size };
  });
}

/** Energy of second differences along rows: what a low-pass removes first. */
function roughness(h, rows, cols) {
  let sum = 0;
  let n = 0;
  for (let r = 0; r < rows; r++) {
    for (let c = 1; c + 1 < cols; c++) {
      const k = r * cols + c;
      const d = h[k + 1] - 2 * h[k] + h[k - 1];
      if (!Number.isNaN(d)) {
        sum += d * d;
        n++;
      }
    }
  }
  return sum / n;
}

function assertSameMap(got, ref, label) {
  assert.equal(got.length, ref.length, `${label}: cells`);
  let worst = 0;
  for (let k = 0; k < ref.length; k++) {
    const a = got[k];
    const b = ref[k];
    assert.equal(a === null || Number.isNaN(a), Number.isNaN(b), `${label}: empty cell ${k} differs`);
    if (!Number.isNaN(b)) worst = Math.max(worst, Math.abs(a - b) / Math.max(1, Math.abs(b)));
  }
  // Both are float32 of the same float64 decode, up to the decoders' last bits.
  assert.ok(worst < 4e-7, `${label}: heights differ by ${worst} relative`);
}

before(async () => {
  assert.ok(existsSync(CHROMIUM), `${CHROMIUM} is missing: apt-get install chromium (or set CHROMIUM)`);
  work = mkdtempSync(join(tmpdir(), "dftpcc-viewer-test-"));
  artifacts = process.env.DFTPCC_VIEWER_ARTIFACTS ?? join(work, "screenshots");
  mkdirSync(artifacts, { recursive: true });
  console.log(`viewer screenshots: ${artifacts}`);
  fx = join(work, "fixtures");
  const run = spawnSync(python(), [join(WEB, "test", "viewer_fixtures.py"), fx], { stdio: ["ignore", "inherit", "inherit"], env: ENV });
  assert.equal(run.status, 0, "viewer_fixtures.py failed");
  browser = await puppeteer.launch({ executablePath: CHROMIUM, headless: true, pipe: true,
    args: [...FLAGS, `--user-data-dir=${join(work, "profile")}`] });
});

after(async () => {
  await browser?.close();
  for (const p of servers) p.kill("SIGINT");
});

describe("viewer page", () => {
  test("shows the terrain of an untiled map where the camera looks", async () => {
    const { url } = await view(join(fx, "gale.dftpc"));
    const { page, problems } = await open(url);
    assert.equal(await page.evaluate(() => window.viewer.status), "done");
    await shot(page, "gale");
    const px = await pixels(page);
    // A blank page is one colour; terrain covers much of the window, all of its centre, in many colours.
    assert.ok(px.covered > 0.15, `terrain covers ${px.covered} of the window`);
    assert.ok(px.centre > 0.95, `terrain covers ${px.centre} of the centre`);
    assert.ok(px.colours > 200, `${px.colours} colours`);
    assert.deepEqual(problems, []);
    await page.close();
  });

  test("header figures equal dftpcc info --json", async () => {
    const { url } = await view(join(fx, "gale.dftpc"));
    const { page } = await open(url);
    const rows = await page.evaluate(() => Object.fromEntries([...document.querySelectorAll("#header tr")].map((tr) => [tr.dataset.key, tr.dataset.value])));
    const info = JSON.parse(readFileSync(join(fx, "gale.info.json"), "utf8"));
    const m = JSON.parse(readFileSync(join(fx, "manifest.json"), "utf8")).gale;
    assert.equal(Number(rows.bytes), info.bytes);
    assert.equal(Number(rows.rows), info.grid.rows);
    assert.equal(Number(rows.cols), info.grid.cols);
    assert.equal(Number(rows.resolution_m), info.grid.resolution_m);
    assert.deepEqual(rows.origin.split(" ").map(Number), info.grid.origin);
    assert.equal(Number(rows.cutoff), info.params.cutoff);
    assert.equal(Number(rows.step), info.params.step);
    assert.equal(Number(rows.dem_max_error_m), info.stats.dem_max_error_m);
    assert.equal(Number(rows.dem_rmse_m), info.stats.dem_rmse_m);
    assert.equal(Number(rows.target_max_error), info.params.target_max_error);
    assert.equal(rows.crs, info.crs);
    const ext = rows.extent.split(" ").map(Number);
    m.bounds.forEach((b, i) => assert.ok(Math.abs(ext[i] - b) < 1e-6, `extent ${ext} against ${m.bounds}`));
    const shown = await page.$eval("#panel", (e) => e.textContent);
    assert.match(shown, /max error\s*330 mm/);
    assert.match(shown, /Mars2000 Equidistant Cylindrical/);
    await page.close();
  });

  test("the height under the cursor is the Python decoder's", async () => {
    const { url } = await view(join(fx, "gale.dftpc"));
    const { page } = await open(url);
    const ref = f32(join(fx, "gale.ref.f32"));
    const { cols } = JSON.parse(readFileSync(join(fx, "manifest.json"), "utf8")).gale;
    const seen = new Set();
    for (const [x, y] of [[500, 350], [430, 300], [600, 420]]) {
      await page.mouse.move(x, y);
      await page.waitForFunction((x0, y0) => { const d = document.getElementById("cursor").dataset; return d.row !== undefined && window.viewer.cellAt(x0, y0)?.row === Number(d.row); },
        { timeout: 10_000 }, x, y);
      const d = await page.$eval("#cursor", (e) => ({ ...e.dataset, text: e.textContent }));
      const want = ref[Number(d.row) * cols + Number(d.col)];
      assert.ok(!Number.isNaN(want), `cell ${d.row}, ${d.col} is empty in the Python decode`);
      assert.equal(Number(d.height), want, `height at row ${d.row}, col ${d.col}: page ${d.height}, Python ${want}`);
      assert.match(d.text, /^height -4,4\d\d\.\d+ m at x /);
      // The cell's centre at the Python height projects back under the cursor (cells are ~2.5 px here).
      const [sx, sy] = await page.evaluate((r, c, h) => window.viewer.screenOf(r, c, h), Number(d.row), Number(d.col), want);
      assert.ok(Math.hypot(sx - x, sy - y) < 5, `cell ${d.row}, ${d.col} lands at ${sx}, ${sy}, the cursor is at ${x}, ${y}`);
      seen.add(`${d.row},${d.col}`);
    }
    assert.equal(seen.size, 3, "three points, three cells");
    await shot(page, "gale-cursor");
    await page.close();
  });

  test("a progressive load shows a coarser map first, then the whole decode", async () => {
    const map = join(fx, "gale.dftpc");
    const size = readFileSync(map).length;
    const { url } = await view(map);
    // About 12 slices of the file, a tenth of a second apart.
    const { page, problems } = await open(`${url}?rate=${Math.ceil(size / 1.2)}`, { until: "partial" });
    await shot(page, "gale-coarse");
    await page.waitForFunction(() => window.viewer.status === "done", { timeout: 60_000, polling: 100 });
    const got = await page.evaluate(() => ({ stages: window.viewer.stages, coarse: Array.from(window.viewer.coarse ?? []), final: Array.from(window.viewer.final) }));
    const { rows, cols } = JSON.parse(readFileSync(join(fx, "manifest.json"), "utf8")).gale;
    assert.ok(got.stages.length >= 3, `${got.stages.length} stages`);
    assert.ok(got.stages[0].partial && got.stages[0].bytesRead < size, `first stage from ${got.stages[0].bytesRead} of ${size} bytes`);
    assert.equal(got.stages.at(-1).partial, false);
    assert.equal(got.stages.at(-1).bytesRead, size);
    const coarse = got.coarse.map((v) => (v === null ? NaN : v));
    const final = got.final.map((v) => (v === null ? NaN : v));
    const [r0, r1] = [roughness(coarse, rows, cols), roughness(final, rows, cols)];
    assert.ok(r0 < 0.5 * r1, `first stage roughness ${r0} against final ${r1}`);
    assertSameMap(final, f32(join(fx, "gale.ref.f32")), "final progressive stage");
    assert.deepEqual(problems, []);
    await page.close();
  });

  test("a tiled map appears tile by tile and ends as the whole decode", async () => {
    const { url } = await view(join(fx, "davos_tiled.dftpc"));
    const { page, problems } = await open(url);
    const got = await page.evaluate(() => ({ stages: window.viewer.stages, final: Array.from(window.viewer.final) }));
    const info = JSON.parse(readFileSync(join(fx, "davos_tiled.info.json"), "utf8"));
    assert.equal(got.stages.length, info.tiles.occupied);
    assert.ok(got.stages.every((s) => s.tile !== undefined && s.width <= info.tiles.size && s.height <= info.tiles.size));
    assertSameMap(got.final.map((v) => (v === null ? NaN : v)), f32(join(fx, "davos_tiled.ref.f32")), "tiled map");
    await shot(page, "davos-tiled");
    const px = await pixels(page);
    assert.ok(px.covered > 0.15 && px.centre > 0.95, JSON.stringify(px));
    assert.deepEqual(problems, []);
    await page.close();
  });

  test("a geographic map with empty cells: cells hidden, degrees shown as degrees", async () => {
    const { url } = await view(join(fx, "korolev.dftpc"));
    const { page, problems } = await open(url);
    const final = await page.evaluate(() => Array.from(window.viewer.final));
    const ref = f32(join(fx, "korolev.ref.f32"));
    assert.ok(ref.filter(Number.isNaN).length > 0.1 * ref.length, "the fixture has empty cells");
    assertSameMap(final.map((v) => (v === null ? NaN : v)), ref, "korolev");
    assert.match(await page.$eval('#header tr[data-key="resolution_m"]', (e) => e.textContent), /0\.00781\d*° × 0\.00780\d*° of longitude × latitude/);
    // Drawn in metres on Mars's sphere (3,396 km): 6.7 degrees of longitude at 73 N, 2.7 of latitude.
    const [w, h] = await page.evaluate(() => window.viewer.sceneSize);
    assert.ok(w > 110e3 && w < 125e3 && h > 155e3 && h < 168e3, `scene of ${w} x ${h} m`);
    const px = await pixels(page);
    assert.ok(px.covered > 0.15 && px.centre > 0.95, JSON.stringify(px));
    await shot(page, "korolev");
    assert.deepEqual(problems, []);
    await page.close();
  });

  test("the error view colours decoded minus original within the stated maximum error", async () => {
    const m = JSON.parse(readFileSync(join(fx, "manifest.json"), "utf8")).gale;
    const info = JSON.parse(readFileSync(join(fx, "gale.info.json"), "utf8"));
    const { url } = await view(join(fx, "gale.dftpc"), "--original", m.source);
    const { page, problems } = await open(url);
    await page.waitForFunction(() => window.viewer.diffMax !== null, { timeout: 30_000 });
    const before = await pixels(page);
    await page.click('input[value="error"]');
    await page.waitForFunction(() => document.getElementById("legend-title").textContent.includes("original"));
    const most = await page.evaluate(() => window.viewer.diffMax);
    // Both sides are float32 in the page: two roundings of heights of this size.
    const ulps = 2 * 2 ** -23 * Math.max(...f32(join(fx, "gale.ref.f32")).filter((v) => !Number.isNaN(v)).map(Math.abs));
    assert.ok(most > 0 && most <= info.stats.dem_max_error_m + ulps, `max |decoded - original| ${most}, stated ${info.stats.dem_max_error_m} (+${ulps})`);
    await shot(page, "gale-error");
    const after = await pixels(page);
    assert.ok(after.centre > 0.95);
    assert.notDeepEqual(after, before, "the colours changed");
    assert.deepEqual(problems, []);
    await page.close();
  });

  for (const name of ["damaged", "notamap"]) {
    test(`a ${name} file shows one message, no crash`, async () => {
      const { url } = await view(join(fx, `${name}.dftpc`));
      const { page, problems } = await open(url);
      const box = await page.$eval("#error", (e) => ({ text: e.textContent, shown: getComputedStyle(e).display !== "none" }));
      assert.equal(await page.evaluate(() => window.viewer.status), "error");
      assert.ok(box.shown && box.text.length > 10, JSON.stringify(box));
      assert.match(box.text, /^(CorruptFileError|UnsupportedFormatError|InvalidInputError)/);
      assert.deepEqual(problems, []);
      // Still alive: the page answers.
      assert.equal(await page.evaluate(() => 1 + 1), 2);
      await shot(page, name);
      await page.close();
    });
  }

  test("--follow reloads the map when its file changes", async () => {
    const map = join(work, "following.dftpc");
    copyFileSync(join(fx, "gale.dftpc"), map);
    const { url } = await view(map, "--follow");
    const { page } = await open(url);
    assert.equal(await page.$eval('#header tr[data-key="rows"]', (e) => e.dataset.value), "337");
    // Replaced as dftpcc writes files: a new file renamed over the old.
    copyFileSync(join(fx, "davos_tiled.dftpc"), `${map}.part`);
    renameSync(`${map}.part`, map);
    await page.waitForFunction(() => window.viewer.loads >= 2 && window.viewer.status === "done", { timeout: 60_000, polling: 200 });
    assert.equal(await page.$eval('#header tr[data-key="rows"]', (e) => e.dataset.value), "495");
    await page.close();
  });
});

describe("viewer assets", () => {
  test("the committed bundle is what web/viewer/ builds", () => {
    const out = join(work, "assets");
    const run = spawnSync(process.execPath, [join(WEB, "viewer", "build.mjs"), out], { cwd: WEB, stdio: "inherit" });
    assert.equal(run.status, 0);
    const committed = join(ROOT, "src", "dftpcc", "viewer_assets");
    assert.deepEqual(readdirSync(out).sort(), readdirSync(committed).sort());
    for (const name of readdirSync(out)) {
      assert.ok(readFileSync(join(out, name)).equals(readFileSync(join(committed, name))),
        `${name} is stale: run make viewer and commit src/dftpcc/viewer_assets/`);
    }
  });
});
