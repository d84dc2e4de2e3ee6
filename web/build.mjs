// Bundles src/ into dist/dftpcc.mjs (an ES module, for Node and pages) and dist/dftpcc.js (an IIFE
// exposing the global `dftpcc`, for a Web Worker or a plain <script>).
import { readFile } from "node:fs/promises";
import { build } from "esbuild";
import { compileKernels } from "./wasm/compile.mjs";

// fzstd 0.1.1 loops forever on a crafted Huffman table (its weights' FSE loop never ends once a
// state leaves the table: the bit position turns NaN); found by web/test/fuzz.test.mjs, kept by
// web/test/zstd.test.mjs. A Huffman table has at most 255 weights, so the loop is stopped there with
// fzstd's own error. The patch is applied to the bundle, not to node_modules, and the build fails
// if fzstd's source changed.
const FZSTD_LOOP = "        for (;;) {\n            fpos -= btr1;";
const fzstdGuard = {
  name: "fzstd-guard",
  setup(b) {
    b.onLoad({ filter: /fzstd[\\/].*index\.(m?js|cjs)$/ }, async (args) => {
      const text = await readFile(args.path, "utf8");
      if (!text.includes(FZSTD_LOOP)) throw new Error(`fzstd changed: re-check the Huffman loop guard (${args.path})`);
      return { contents: text.replace(FZSTD_LOOP, "        for (;;) {\n            if (wc > 255) err(0);\n            fpos -= btr1;"), loader: "js" };
    });
  },
};

await compileKernels();
const common = { entryPoints: ["src/index.ts"], bundle: true, target: "es2022", logLevel: "warning", sourcemap: true, plugins: [fzstdGuard],
  loader: { ".wasm": "binary" } };
await build({ ...common, format: "esm", outfile: "dist/dftpcc.mjs" });
await build({ ...common, format: "iife", globalName: "dftpcc", outfile: "dist/dftpcc.js", minify: true });
await build({ ...common, entryPoints: ["src/internals.ts"], format: "esm", outfile: "dist/internals.mjs" });
