// Decode speed of the JavaScript decoder in Node and in headless Chromium, against the Python decoder
// and the `lerc` npm decoder (Esri's LERC, WebAssembly) at equal maximum error, all in the same run
// (make bench-web; ARGS: --repeats N, --warmup W, --side S for the mosaic, --no-mosaic, --no-browser,
// --dist D for another build's dist/ folder, such as an earlier commit's, to compare in interleaved runs).
// Each shared DEM is compressed by the Python codec at its defaults (and once with a maximum-error
// target, whose residual layer is decoded too), and so is a S x S mosaic of them (4 M cells by
// default: benchmarks/bench_big.py's layout); each default file's DEM is LERC-encoded with maxZErr
// = the file's stated maximum error (bench/lerc_encode.py). The table gives million cells (rows x
// cols) per second: medians of N decodes after W warm-up decodes of the same file (the first few
// decodes in a fresh engine run before V8 has optimised the JavaScript and the WebAssembly: the
// first decode's own time is printed apart, and the viewer's first frame is timed by
// first_frame.mjs), in CPU time, so that a shared machine's
// other work does not count: Node's and Python's process time, both pinned to core 0 (taskset -c 0
// when it exists), and Chromium's page main thread (DevTools task durations in thread ticks). A second
// table times progressive prefixes of each untiled default map in Chromium (float32, as the viewer
// asks): the first 5 % and 25 % of the bytes decoded exactly and as a preview, against the whole file.
// A third says where a whole decode's time goes in Chromium, stage by stage (wall-clock milliseconds
// a decode, each stage's median over N decodes, from the build's internals.mjs; the stages of the
// map's path only).
import { spawnSync } from "node:child_process";
import { createReadStream, existsSync, mkdtempSync, readdirSync, readFileSync, rmSync, writeFileSync } from "node:fs";
import { createServer } from "node:http";
import { tmpdir } from "node:os";
import { extname, join } from "node:path";
import * as Lerc from "lerc";
import { resolve } from "node:path";
import { python, ROOT } from "../test/helpers.mjs";

const args = process.argv.slice(2);
const opt = (name, dflt) => (args.includes(name) ? args[args.indexOf(name) + 1] : dflt);
const DIST = resolve(opt("--dist", new URL("../dist", import.meta.url).pathname));
const { decode, ready } = await import(join(DIST, "dftpcc.mjs"));
// A build with the WebAssembly zstd decoder starts it asynchronously: timed once it has loaded.
if (ready) await ready();
/** Prefix lengths (fractions of a file's bytes) of the progressive table. */
const PREFIXES = [0.05, 0.25];
const REPEATS = Number(opt("--repeats", 7));
const WARMUP = Number(opt("--warmup", 5));
const SIDE = Number(opt("--side", 2048));
const WEB = join(ROOT, "web");
const DATA = join(ROOT, "..", "shared", "data");
const DEMS = join(DATA, "dems");
const env = { ...process.env, PYTHONPATH: join(ROOT, "src"), PYTHONWARNINGS: "ignore", OMP_NUM_THREADS: "1" };
const pinned = spawnSync("taskset", ["-c", "0", "true"]).status === 0;
const run = (cmd, a) => {
  const r = spawnSync(pinned ? "taskset" : cmd, pinned ? ["-c", "0", cmd, ...a] : a, { env, encoding: "utf8", maxBuffer: 1 << 26, cwd: ROOT });
  if (r.status !== 0) throw new Error(`${cmd} ${a.join(" ")}: ${r.stderr}`);
  return r.stdout;
};
const median = (v) => [...v].sort((a, b) => a - b)[Math.floor(v.length / 2)];
const cpu = () => {
  const u = process.cpuUsage();
  return (u.user + u.system) / 1000;
};

/** Median CPU seconds of `f` over REPEATS calls after WARMUP warm-up calls, and the first call's own. */
function timeCpu(f) {
  const t0 = cpu();
  const result = f();
  const cold = cpu() - t0;
  for (let k = 1; k < WARMUP; k++) f();
  const times = [];
  for (let k = 0; k < REPEATS; k++) {
    const t = cpu();
    f();
    times.push(cpu() - t);
  }
  return { result, cold: cold / 1000, seconds: median(times) / 1000 };
}

/** The same timings in headless Chromium: {name: {js, lerc}} CPU seconds of the page's main thread (medians). */
async function inChromium(dir, names) {
  const { default: puppeteer } = await import("puppeteer-core");
  const types = { ".mjs": "text/javascript", ".js": "text/javascript", ".wasm": "application/wasm", ".html": "text/html" };
  const routes = { "/dftpcc.mjs": join(DIST, "dftpcc.mjs"), "/internals.mjs": join(DIST, "internals.mjs"), "/lerc/LercDecode.es.js": join(WEB, "node_modules", "lerc", "LercDecode.es.js"),
    "/lerc/lerc-wasm.wasm": join(WEB, "node_modules", "lerc", "lerc-wasm.wasm") };
  const server = createServer((req, res) => {
    const path = req.url === "/" ? null : routes[req.url] ?? join(dir, req.url.slice(1).replace(/[^\w.-]/g, ""));
    if (req.url === "/") {
      res.writeHead(200, { "content-type": "text/html" });
      res.end("<!doctype html><title>bench</title>");
      return;
    }
    if (!path || !existsSync(path)) {
      res.writeHead(404);
      res.end();
      return;
    }
    res.writeHead(200, { "content-type": types[extname(path)] ?? "application/octet-stream" });
    createReadStream(path).pipe(res);
  });
  await new Promise((resolve) => server.listen(0, "127.0.0.1", resolve));
  const url = `http://127.0.0.1:${server.address().port}/`;
  const browser = await puppeteer.launch({
    executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium", headless: true, pipe: true,
    args: ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
      "--disable-sync", "--no-first-run", `--user-data-dir=${join(dir, "profile")}`],
  });
  try {
    const page = await browser.newPage();
    await page.goto(url);
    if (pinned) pinTree(browser.process().pid);
    // CPU time of the page's main thread, as for Node and Python: the DevTools protocol's task
    // durations measured in thread ticks (a shared machine's other work does not count).
    const cdp = await page.createCDPSession();
    await cdp.send("Performance.enable", { timeDomain: "threadTicks" });
    const taskSeconds = async () => (await cdp.send("Performance.getMetrics")).metrics.find((m) => m.name === "TaskDuration").value;
    await page.evaluate(async () => {
      const { decode, ready } = await import("/dftpcc.mjs");
      if (ready) await ready();
      const Lerc = await import("/lerc/LercDecode.es.js");
      await Lerc.load({ locateFile: (name) => `/lerc/${name}` });
      // A build before the stage timings has no stageTimes: its table is left out.
      const internals = await import("/internals.mjs");
      if (internals.ready) await internals.ready();
      Object.assign(window, { decodeDftpcc: decode, Lerc, internals: internals.stageTimes ? internals : null });
    });
    /** Median main-thread seconds of REPEATS calls after WARMUP calls, and the first call's own. */
    const timePage = async (f, arg, withFirst = false) => {
      const t00 = await taskSeconds();
      await page.evaluate(f, arg);
      const first = (await taskSeconds()) - t00;
      for (let k = 1; k < WARMUP; k++) await page.evaluate(f, arg);
      const t = [];
      for (let k = 0; k < REPEATS; k++) {
        const t0 = await taskSeconds();
        await page.evaluate(f, arg);
        t.push((await taskSeconds()) - t0);
      }
      return withFirst ? { seconds: median(t), first } : median(t);
    };
    const out = {};
    for (const name of names) {
      const hasLerc = existsSync(join(dir, `${name}.lerc`));
      await page.evaluate(async (name, hasLerc) => {
        window.data = new Uint8Array(await (await fetch(`/${name}.dftpc`)).arrayBuffer());
        window.lercBlob = hasLerc ? new Uint8Array(await (await fetch(`/${name}.lerc`)).arrayBuffer()) : null;
      }, name, hasLerc);
      const js = await timePage(() => void window.decodeDftpcc(window.data), undefined, true);
      out[name] = { js: js.seconds, first: js.first };
      // Stages of the same decodes (a separate bundle: its own warm-up), milliseconds a decode:
      // each stage's median over the decodes (wall clock: a median leaves out most of the time
      // another process took the core).
      out[name].stages = await page.evaluate((warmup, repeats) => {
        const i = window.internals;
        if (!i) return null;
        for (let k = 0; k < warmup; k++) i.decode(window.data);
        const runs = [];
        for (let k = 0; k < repeats; k++) {
          i.stageTimes(true);
          i.decode(window.data);
          runs.push(i.stageTimes(false));
        }
        const ms = {};
        for (const key of Object.keys(runs[0])) {
          const v = runs.map((r) => r[key] ?? 0).sort((a, b) => a - b);
          ms[key] = v[Math.floor(v.length / 2)];
        }
        return ms;
      }, WARMUP, REPEATS);
      if (hasLerc) out[name].lerc = await timePage(() => void window.Lerc.decode(window.lercBlob));
      if (!name.includes(".")) {
        // Progressive prefixes as the viewer's worker decodes them (an older build ignores preview).
        const decodePrefix = ([f, preview]) => {
          const n = Math.floor(f * window.data.length);
          void window.decodeDftpcc(window.data.subarray(0, n), { fileSize: window.data.length, float32: true, preview });
        };
        out[name].prefix = { whole: await timePage(() => void window.decodeDftpcc(window.data, { float32: true })) };
        for (const f of PREFIXES) {
          // A prefix shorter than the header (a small map's 5 %) has no map to time.
          const short = await page.evaluate((f) => {
            try {
              window.decodeDftpcc(window.data.subarray(0, Math.floor(f * window.data.length)), { fileSize: window.data.length });
              return false;
            } catch {
              return true;
            }
          }, f);
          out[name].prefix[f] = short ? null : { exact: await timePage(decodePrefix, [f, false]), preview: await timePage(decodePrefix, [f, true]) };
        }
      }
    }
    return { out, version: await browser.version() };
  } finally {
    await browser.close();
    server.close();
  }
}

/** Pin a process and all its descendants (Chromium's renderers) to core 0. */
function pinTree(pid) {
  const pids = [pid];
  for (let k = 0; k < pids.length; k++) {
    const children = spawnSync("ps", ["-o", "pid=", "--ppid", String(pids[k])], { encoding: "utf8" }).stdout;
    pids.push(...children.split(/\s+/).filter(Boolean).map(Number));
  }
  for (const p of pids) spawnSync("taskset", ["-a", "-p", "-c", "0", String(p)]);
}

const dir = mkdtempSync(join(tmpdir(), "dftpcc-bench-web-"));
try {
  const sources = [];
  for (const name of readdirSync(DEMS).filter((n) => n.endsWith(".tif")).sort()) sources.push([name.replace(/\.tif$/, ""), join(DEMS, name)]);
  if (!args.includes("--no-mosaic")) {
    const tif = join(dir, `mosaic_${SIDE}.tif`);
    run(python(), ["-c", `import sys; from pathlib import Path; sys.path.insert(0, ${JSON.stringify(ROOT)});
from benchmarks.bench_big import build_raster
build_raster(Path(${JSON.stringify(DATA)}), Path(sys.argv[1]), ${SIDE})`, tif]);
    sources.push([`mosaic_${SIDE}`, tif]);
  }
  for (const [stem, src] of sources) {
    run(python(), ["-m", "dftpcc", "compress", "-q", "--no-warnings", src, join(dir, `${stem}.dftpc`)]);
    writeFileSync(join(dir, `${stem}.src`), src);
    run(python(), ["-m", "dftpcc", "compress", "-q", "--no-warnings", "--target-max-error", "1", src, join(dir, `${stem}.maxerr1m.dftpc`)]);
    writeFileSync(join(dir, `${stem}.maxerr1m.src`), src);
  }
  const lercInfo = JSON.parse(run(python(), [join(WEB, "bench", "lerc_encode.py"), dir]));
  const py = JSON.parse(run(python(), [join(WEB, "bench", "py_decode.py"), dir, String(REPEATS)]));
  // The JS side in this same process, pinned like the Python one when taskset exists.
  if (pinned) spawnSync("taskset", ["-p", "-c", "0", String(process.pid)]);
  await Lerc.load();
  const names = readdirSync(dir).filter((n) => n.endsWith(".dftpc")).sort().map((n) => n.replace(/\.dftpc$/, ""));
  const rows = [];
  for (const stem of names) {
    const data = new Uint8Array(readFileSync(join(dir, `${stem}.dftpc`)));
    const js = timeCpu(() => decode(data));
    const map = js.result;
    const row = { stem, bytes: data.length, cells: map.width * map.height, cold: js.cold, js: js.seconds, py: py[stem].seconds };
    if (lercInfo[stem]) {
      const blob = new Uint8Array(readFileSync(join(dir, `${stem}.lerc`)));
      row.lercBytes = blob.length;
      row.maxError = lercInfo[stem].max_error_m;
      row.lerc = timeCpu(() => Lerc.decode(blob)).seconds;
    }
    rows.push(row);
  }
  let browser = null;
  if (!args.includes("--no-browser")) {
    browser = await inChromium(dir, names);
    for (const r of rows) Object.assign(r, { jsChromium: browser.out[r.stem].js, jsFirst: browser.out[r.stem].first, lercChromium: browser.out[r.stem].lerc });
  }
  const rate = (r, s) => (s ? (r.cells / s / 1e6).toFixed(2) : "");
  console.log("| map | cells | bytes | JS Node | JS Chromium | Python | JS Node / Python | JS Chromium / Python | JS first decode Node, Chromium | LERC bytes (same max error) | lerc Node | lerc Chromium |");
  console.log("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
  for (const r of rows) {
    console.log(`| ${r.stem} | ${r.cells} | ${r.bytes} | ${rate(r, r.js)} | ${rate(r, r.jsChromium)} | ${rate(r, r.py)} | `
      + `${(r.py / r.js).toFixed(2)} | ${r.jsChromium ? (r.py / r.jsChromium).toFixed(2) : ""} | `
      + `${rate(r, r.cold)}${r.jsFirst ? `, ${rate(r, r.jsFirst)}` : ""} | `
      + `${r.lercBytes ? `${r.lercBytes} (${r.maxError.toPrecision(3)} m)` : ""} | ${rate(r, r.lerc)} | ${rate(r, r.lercChromium)} |`);
  }
  if (browser) {
    console.log(`\n| map (Chromium, float32) | whole file | ${PREFIXES.map((f) => `${100 * f} % exact | ${100 * f} % preview`).join(" | ")} |`);
    console.log(`|---|---:|${PREFIXES.map(() => "---:|---:").join("|")}|`);
    for (const r of rows) {
      const p = browser.out[r.stem].prefix;
      if (!p) continue;
      const ms = (s) => `${(1000 * s).toFixed(1)} ms`;
      console.log(`| ${r.stem} | ${ms(p.whole)} | ${PREFIXES.map((f) => (p[f] ? `${ms(p[f].exact)} | ${ms(p[f].preview)}` : "header only | header only")).join(" | ")} |`);
    }
  }
  const staged = browser ? rows.filter((r) => browser.out[r.stem].stages) : [];
  if (staged.length) {
    const names = [...new Set(staged.flatMap((r) => Object.keys(browser.out[r.stem].stages)))];
    console.log(`\n| map (Chromium, ms a decode) | ${names.join(" | ")} |`);
    console.log(`|---|${names.map(() => "---:").join("|")}|`);
    for (const r of staged) {
      const st = browser.out[r.stem].stages;
      console.log(`| ${r.stem} | ${names.map((n) => (st[n] === undefined ? "" : st[n].toFixed(2))).join(" | ")} |`);
    }
  }
  console.log(`\nM cells per second: medians of ${REPEATS} decodes after ${WARMUP} warm-up decodes each (first decode: the first of them). Node and Python: CPU time, `
    + `${pinned ? "both pinned to core 0 (taskset)" : "not pinned"}; Chromium: CPU time of the page's main thread (DevTools task durations in thread ticks)${pinned ? ", pinned to core 0" : ""}. `
    + `node ${process.version}${browser ? `, ${browser.version}` : ""}. LERC at maxZErr = the dftpcc file's stated maximum error. `
    + `Prefixes: CPU time of the page's main thread, medians likewise. Build: ${DIST}.`);
} finally {
  rmSync(dir, { recursive: true, force: true });
}
