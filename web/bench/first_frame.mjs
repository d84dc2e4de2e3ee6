// Time to the first rendered frame of a 4 M-cell map in the viewer (headless chromium, software WebGL):
// a 2048 x 2048 mosaic of the shared DEMs (benchmarks/bench_big.py's layout), compressed by the Python
// codec, served by `dftpcc view`, opened cold N times (default 3). Prints the medians, milliseconds
// since navigation: first frame (the first decoded prefix shown), and the whole map shown.
import { spawn, spawnSync } from "node:child_process";
import { mkdtempSync, rmSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";
import puppeteer from "puppeteer-core";
import { ROOT, python } from "../test/helpers.mjs";

const SIDE = Number(process.env.SIDE ?? 2048);
const RUNS = Number(process.env.RUNS ?? 3);
const env = { ...process.env, PYTHONPATH: join(ROOT, "src"), PYTHONWARNINGS: "ignore" };
const work = mkdtempSync(join(tmpdir(), "dftpcc-first-frame-"));
const median = (v) => [...v].sort((a, b) => a - b)[Math.floor(v.length / 2)];

try {
  const tif = join(work, "mosaic.tif");
  const map = process.env.MAP ?? join(work, "mosaic.dftpc"); // MAP: a map made before, to time the page alone
  const made = process.env.MAP ? { status: 0 } : spawnSync (python(), ["-c", `import sys; from pathlib import Path; sys.path.insert(0, ${JSON.stringify(ROOT)});
from benchmarks.bench_big import build_raster
build_raster(Path(${JSON.stringify(join(ROOT, "..", "shared", "data"))}), Path(sys.argv[1]), ${SIDE})`, tif], { env, stdio: "inherit", cwd: ROOT });
  if (made.status !== 0) throw new Error("building the mosaic failed");
  const coded = process.env.MAP ? { status: 0 } : spawnSync(python(), ["-m", "dftpcc", "compress", "-q", "--no-warnings", tif, map], { env, stdio: "inherit" });
  if (coded.status !== 0) throw new Error("compressing the mosaic failed");
  const server = spawn(python(), ["-m", "dftpcc", "view", map, "--port", "0"], { env, stdio: ["ignore", "pipe", "inherit"] });
  const url = await new Promise((resolve) => {
    let out = "";
    server.stdout.on("data", (d) => {
      out += d;
      const m = /(http:\/\/127\.0\.0\.1:\d+\/)/.exec(out);
      if (m) resolve(m[1]);
    });
  });
  const browser = await puppeteer.launch({
    executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium", headless: true, pipe: true,
    args: ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
      "--disable-sync", "--no-first-run", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", `--user-data-dir=${join(work, "profile")}`],
  });
  const runs = [];
  for (let k = 0; k < RUNS; k++) {
    const page = await browser.newPage();
    await page.setViewport({ width: 1280, height: 800 });
    await page.goto(url);
    await page.waitForFunction(() => window.viewer?.status === "done" || window.viewer?.status === "error", { timeout: 600_000, polling: 100 });
    const r = await page.evaluate(() => ({ status: window.viewer.status, error: window.viewer.error, first: window.viewer.firstFrameMs,
      done: window.viewer.doneMs, stages: window.viewer.stages.map((s) => [s.bytesRead, Math.round(s.ms)]), timings: window.viewer.timings }));
    if (r.status !== "done") throw new Error(`the page failed: ${JSON.stringify(r.error)}`);
    if (k === 0) await page.screenshot({ path: join(tmpdir(), "dftpcc-first-frame.png") });
    runs.push(r);
    await page.close();
  }
  await browser.close();
  server.kill("SIGINT");
  const size = spawnSync(python(), ["-c", "import os,sys; print(os.path.getsize(sys.argv[1]))", map], { env }).stdout.toString().trim();
  console.log(`viewer, ${SIDE} x ${SIDE} mosaic (${size} bytes), ${RUNS} cold loads: first frame ${median(runs.map((r) => r.first)).toFixed(0)} ms, `
    + `whole map ${median(runs.map((r) => r.done)).toFixed(0)} ms (medians since navigation; each: ${runs.map((r) => Math.round(r.first)).join(", ")} ms; stages [bytes, decode ms] of the first: ${JSON.stringify(runs[0].stages)})`);
  console.log(`page timings of the first load (ms since navigation): ${JSON.stringify(runs[0].timings)}`);
  console.log(`screenshot of the first load: ${join(tmpdir(), "dftpcc-first-frame.png")}`);
} finally {
  rmSync(work, { recursive: true, force: true });
}
