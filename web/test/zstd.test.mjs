// zstd frames from crafted files: fzstd 0.1.1 looped forever on this 80-byte frame (a PARM section
// of a mutated paper-profile map, found by fuzz.test.mjs); build.mjs guards the loop. Run in a child
// process with a time limit, since a synchronous endless loop cannot be interrupted from inside.
import assert from "node:assert/strict";
import { spawnSync } from "node:child_process";
import { join } from "node:path";
import { test } from "node:test";
import { WEB } from "./helpers.mjs";

const FRAME = "KLUv/SBcPQIAwsUQEfDrzyLFLJOAhLIPC15Vz1io8W3K84vXODa4Dx7EU9XWkuf1DN52B2dtoz2vKpnldnDUu8s9r1QyB1e27PnClFvLYQA=";

test("a crafted zstd frame whose Huffman table never ends is refused, not looped on", () => {
  const script = `import { inflate } from ${JSON.stringify(join(WEB, "dist", "internals.mjs"))};
    try { inflate(Uint8Array.from(Buffer.from("${FRAME}", "base64")), 1 << 20, "section PARM"); console.log("decoded"); }
    catch (e) { console.log(e.name); }`;
  const run = spawnSync(process.execPath, ["--input-type=module", "-e", script], { encoding: "utf8", timeout: 60_000 });
  assert.equal(run.signal, null, "the decoder looped (killed after 60 s)");
  assert.equal(run.stdout.trim(), "CorruptFileError");
});
