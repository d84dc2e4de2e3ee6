// Decode speed of the JavaScript decoder against the Python decoder, same run, on the shared DEMs
// (make bench-web; ARGS: --repeats N, --cutoff C). Each DEM is compressed by the Python codec at
// its defaults (and once with a maximum-error target, whose residual layer is decoded too), then
// decoded by both; the table gives million cells (rows x cols) per second of CPU time (a shared
// machine's other work does not count), medians of N decodes.
// Both run on one core (taskset -c 0 when it exists), so the figures compare like with like.
import { spawnSync } from "node:child_process";
import { mkdtempSync, readdirSync, readFileSync, rmSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";
import { decode } from "../dist/dftpcc.mjs";
import { python, ROOT } from "../test/helpers.mjs";

const args = process.argv.slice(2);
const opt = (name, dflt) => (args.includes(name) ? args[args.indexOf(name) + 1] : dflt);
const REPEATS = Number(opt("--repeats", 7));
const DEMS = join(ROOT, "..", "shared", "data", "dems");
const env = { ...process.env, PYTHONPATH: join(ROOT, "src"), PYTHONWARNINGS: "ignore", OMP_NUM_THREADS: "1" };
const pinned = spawnSync("taskset", ["-c", "0", "true"]).status === 0;
const run = (cmd, a) => {
  const r = spawnSync(pinned ? "taskset" : cmd, pinned ? ["-c", "0", cmd, ...a] : a, { env, encoding: "utf8", maxBuffer: 1 << 26 });
  if (r.status !== 0) throw new Error(`${cmd} ${a.join(" ")}: ${r.stderr}`);
  return r.stdout;
};

const dir = mkdtempSync(join(tmpdir(), "dftpcc-bench-web-"));
try {
  for (const name of readdirSync(DEMS).filter((n) => n.endsWith(".tif")).sort()) {
    const stem = name.replace(/\.tif$/, "");
    run(python(), ["-m", "dftpcc", "compress", "-q", "--no-warnings", join(DEMS, name), join(dir, `${stem}.dftpc`)]);
    run(python(), ["-m", "dftpcc", "compress", "-q", "--no-warnings", "--target-max-error", "1", join(DEMS, name),
      join(dir, `${stem}.maxerr1m.dftpc`)]);
  }
  const py = JSON.parse(run(python(), [join(ROOT, "web", "bench", "py_decode.py"), dir, String(REPEATS)]));
  // The JS side in this same process, pinned like the Python one when taskset exists.
  if (pinned) spawnSync("taskset", ["-p", "-c", "0", String(process.pid)]);
  const rows = [];
  for (const file of readdirSync(dir).filter((n) => n.endsWith(".dftpc")).sort()) {
    const stem = file.replace(/\.dftpc$/, "");
    const data = new Uint8Array(readFileSync(join(dir, file)));
    const cpu = () => {
      const u = process.cpuUsage();
      return (u.user + u.system) / 1000;
    };
    const first = cpu();
    const map = decode(data);
    const cold = cpu() - first;
    const times = [];
    for (let k = 0; k < REPEATS; k++) {
      const t0 = cpu();
      decode(data);
      times.push(cpu() - t0);
    }
    times.sort((a, b) => a - b);
    const js = times[Math.floor(times.length / 2)] / 1000;
    const cells = map.width * map.height;
    rows.push({ stem, bytes: data.length, cells, cold: cold / 1000, js, py: py[stem].seconds });
  }
  console.log(`| map | bytes | cells | JS first decode (CPU s) | JS (M cells/s) | Python (M cells/s) | JS / Python |`);
  console.log(`|---|---:|---:|---:|---:|---:|---:|`);
  for (const r of rows) {
    console.log(`| ${r.stem} | ${r.bytes} | ${r.cells} | ${r.cold.toFixed(3)} | ${(r.cells / r.js / 1e6).toFixed(2)} | `
      + `${(r.cells / r.py / 1e6).toFixed(2)} | ${(r.py / r.js).toFixed(2)} |`);
  }
  console.log(`\nCPU time, medians of ${REPEATS} decodes after one warm-up each, ${pinned ? "both pinned to core 0 (taskset)" : "not pinned"}; node ${process.version}`);
} finally {
  rmSync(dir, { recursive: true, force: true });
}
