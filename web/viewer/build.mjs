// Bundles the viewer page (web/viewer/) into the Python package's viewer_assets/ (package data of the
// wheel, committed so a pip user needs no Node): index.html, viewer.js (three.js, the page) and
// worker.js (the decoder in a Web Worker). `node viewer/build.mjs [outdir]` from web/.
import { build } from "esbuild";
import { copyFile, mkdir } from "node:fs/promises";
import { fileURLToPath } from "node:url";
import path from "node:path";
import { compileKernels } from "../wasm/compile.mjs";

const here = path.dirname(fileURLToPath(import.meta.url));
const out = path.resolve(process.argv[2] ?? path.join(here, "../../src/dftpcc/viewer_assets"));
await mkdir(out, { recursive: true });
await compileKernels();
const common = { bundle: true, format: "iife", target: "es2022", minify: true, legalComments: "none", keepNames: true, logLevel: "warning",
  loader: { ".wasm": "binary" } };
await build({ ...common, entryPoints: [path.join(here, "main.mjs")], outfile: path.join(out, "viewer.js") });
await build({ ...common, entryPoints: [path.join(here, "worker.mjs")], outfile: path.join(out, "worker.js") });
await copyFile(path.join(here, "index.html"), path.join(out, "index.html"));
