// Compiles wasm/kernels.ts (AssemblyScript, the npm devDependency) to wasm/out/kernels.wasm, which
// build.mjs and viewer/build.mjs embed in their bundles: run by both before bundling.
import asc from "assemblyscript/asc";
import { mkdir } from "node:fs/promises";
import { fileURLToPath } from "node:url";
import path from "node:path";

const here = path.dirname(fileURLToPath(import.meta.url));

export async function compileKernels() {
  await mkdir(path.join(here, "out"), { recursive: true });
  // No runtime and no abort import: the module allocates nothing (src/wasm.ts owns its memory).
  const { error, stderr } = await asc.main([
    path.join(here, "kernels.ts"), "-O3", "--enable", "simd", "--runtime", "stub", "--use", "abort=",
    "-o", path.join(here, "out", "kernels.wasm"),
  ]);
  if (error) throw new Error(`AssemblyScript: ${error.message}\n${stderr.toString()}`);
}
