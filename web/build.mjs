// Bundles src/ into dist/dftpcc.mjs (an ES module, for Node and pages) and dist/dftpcc.js (an IIFE
// exposing the global `dftpcc`, for a Web Worker or a plain <script>).
import { build } from "esbuild";

const common = { entryPoints: ["src/index.ts"], bundle: true, target: "es2022", logLevel: "warning", sourcemap: true };
await build({ ...common, format: "esm", outfile: "dist/dftpcc.mjs" });
await build({ ...common, format: "iife", globalName: "dftpcc", outfile: "dist/dftpcc.js", minify: true });
await build({ ...common, entryPoints: ["src/internals.ts"], format: "esm", outfile: "dist/internals.mjs" });
