// Shared by the tests: where the fixtures are (written by fixtures.py with the venv's python into a
// temporary folder, once per version of the codec and of fixtures.py), and how to read them.
import { spawnSync } from "node:child_process";
import { createHash } from "node:crypto";
import { existsSync, readdirSync, readFileSync, renameSync, rmSync, statSync } from "node:fs";
import { tmpdir } from "node:os";
import { dirname, join, resolve } from "node:path";
import { fileURLToPath } from "node:url";

export const WEB = resolve(dirname(fileURLToPath(import.meta.url)), "..");
export const ROOT = resolve(WEB, "..");

export function python() {
  return process.env.PYTHON ? resolve(ROOT, process.env.PYTHON) : join(ROOT, ".venv", "bin", "python");
}

function sources(dir, out = []) {
  for (const name of readdirSync(dir).sort()) {
    const p = join(dir, name);
    if (statSync(p).isDirectory()) sources(p, out);
    else if (name.endsWith(".py")) out.push(p);
  }
  return out;
}

/** The fixture folder (DFTPCC_WEB_FIXTURES, or one generated when the codec or fixtures.py changed since the last run). */
export function fixtures() {
  if (process.env.DFTPCC_WEB_FIXTURES) return process.env.DFTPCC_WEB_FIXTURES; // a folder written before
  const hash = createHash("sha256");
  for (const p of [join(WEB, "test", "fixtures.py"), ...sources(join(ROOT, "src", "dftpcc"))]) hash.update(readFileSync(p));
  const dir = join(tmpdir(), `dftpcc-web-fixtures-${hash.digest("hex").slice(0, 16)}`);
  if (existsSync(join(dir, "manifest.json"))) return dir;
  const work = `${dir}.${process.pid}`;
  rmSync(work, { recursive: true, force: true });
  const run = spawnSync(python(), [join(WEB, "test", "fixtures.py"), work], {
    stdio: ["ignore", "inherit", "inherit"],
    env: { ...process.env, PYTHONPATH: join(ROOT, "src"), PYTHONWARNINGS: "ignore" },
  });
  if (run.status !== 0) throw new Error(`fixtures.py failed (${python()}): status ${run.status} ${run.error ?? ""}`);
  if (!existsSync(join(dir, "manifest.json"))) renameSync(work, dir);
  return dir;
}

export function bytes(path) {
  return new Uint8Array(readFileSync(path));
}

export function f64(path) {
  const b = readFileSync(path);
  return new Float64Array(b.buffer.slice(b.byteOffset, b.byteOffset + b.byteLength));
}
