// Two builds' decode times in one headless Chromium page, interleaved decode by decode, so that a
// shared machine's load falls on both alike: `node bench/ab.mjs A_DIST B_DIST MAP.dftpc ...
// [--repeats N] [--warmup W]` prints, per map, each build's median main-thread CPU milliseconds and
// B's speed over A's (make bench-web compares a build with the Python decoder; this compares two
// builds, such as a commit and its parent, where their difference is smaller than the run-to-run noise).
import { existsSync, mkdtempSync, readFileSync, rmSync } from "node:fs";
import { createServer } from "node:http";
import { tmpdir } from "node:os";
import { basename, join, resolve } from "node:path";
import puppeteer from "puppeteer-core";

const args = process.argv.slice(2);
const opt = (name, dflt) => (args.includes(name) ? Number(args.splice(args.indexOf(name), 2)[1]) : dflt);
const REPEATS = opt("--repeats", 21);
const WARMUP = opt("--warmup", 5);
const [A, B, ...maps] = args.map((p) => resolve(p));
const median = (v) => [...v].sort((a, b) => a - b)[Math.floor(v.length / 2)];

const server = createServer((req, res) => {
  const [, which, name] = req.url.split("/");
  const path = which === "a" ? join(A, name) : which === "b" ? join(B, name) : which === "map" ? maps[Number(name)] : null;
  if (!path || !existsSync(path)) {
    res.writeHead(which === "" ? 200 : 404, { "content-type": "text/html" });
    res.end(which === "" ? "<!doctype html><title>ab</title>" : "");
    return;
  }
  res.writeHead(200, { "content-type": path.endsWith(".mjs") ? "text/javascript" : "application/octet-stream" });
  res.end(readFileSync(path));
});
await new Promise((r) => server.listen(0, "127.0.0.1", r));
const profile = mkdtempSync(join(tmpdir(), "dftpcc-ab-"));
const browser = await puppeteer.launch({
  executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium", headless: true, pipe: true,
  args: ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", `--user-data-dir=${profile}`],
});
try {
  const page = await browser.newPage();
  await page.goto(`http://127.0.0.1:${server.address().port}/`);
  const cdp = await page.createCDPSession();
  await cdp.send("Performance.enable", { timeDomain: "threadTicks" });
  const ticks = async () => (await cdp.send("Performance.getMetrics")).metrics.find((m) => m.name === "TaskDuration").value;
  await page.evaluate(async () => {
    const load = async (p) => {
      const m = await import(p);
      if (m.ready) await m.ready();
      return m.decode;
    };
    Object.assign(window, { decodeA: await load("/a/dftpcc.mjs"), decodeB: await load("/b/dftpcc.mjs") });
  });
  console.log(`| map | A ms | B ms | B speed / A |\n|---|---:|---:|---:|`);
  for (const [k, map] of maps.entries()) {
    await page.evaluate(async (k) => {
      window.data = new Uint8Array(await (await fetch(`/map/${k}`)).arrayBuffer());
    }, k);
    const t = { a: [], b: [] };
    for (let r = 0; r < WARMUP + REPEATS; r++) {
      for (const w of r % 2 ? ["b", "a"] : ["a", "b"]) {
        const t0 = await ticks();
        await page.evaluate((w) => void window[w === "a" ? "decodeA" : "decodeB"](window.data), w);
        if (r >= WARMUP) t[w].push(1000 * ((await ticks()) - t0));
      }
    }
    const [a, b] = [median(t.a), median(t.b)];
    console.log(`| ${basename(map)} | ${a.toFixed(2)} | ${b.toFixed(2)} | ${(a / b).toFixed(2)} |`);
  }
  console.log(`\nMedians of ${REPEATS} decodes each after ${WARMUP} warm-ups, interleaved; main-thread CPU time (DevTools thread ticks). ${await browser.version()}. A: ${A}. B: ${B}.`);
} finally {
  await browser.close();
  server.close();
  rmSync(profile, { recursive: true, force: true });
}
