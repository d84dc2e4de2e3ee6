// zstd frames from crafted files: fzstd 0.1.1 looped forever on this 80-byte frame (a PARM section
// of a mutated paper-profile map, found by fuzz.test.mjs); build.mjs guards the loop. Run in a child
// process with a time limit, since a synchronous endless loop cannot be interrupted from inside.
import assert from "node:assert/strict";
import { spawnSync } from "node:child_process";
import { join } from "node:path";
import { test } from "node:test";
import { fixtures, python, WEB } from "./helpers.mjs";

const FRAME = "KLUv/SBcPQIAwsUQEfDrzyLFLJOAhLIPC15Vz1io8W3K84vXODa4Dx7EU9XWkuf1DN52B2dtoz2vKpnldnDUu8s9r1QyB1e27PnClFvLYQA=";

test("a crafted zstd frame whose Huffman table never ends is refused, not looped on", () => {
  const script = `import { inflate } from ${JSON.stringify(join(WEB, "dist", "internals.mjs"))};
    try { inflate(Uint8Array.from(Buffer.from("${FRAME}", "base64")), 1 << 20, "section PARM"); console.log("decoded"); }
    catch (e) { console.log(e.name); }`;
  const run = spawnSync(process.execPath, ["--input-type=module", "-e", script], { encoding: "utf8", timeout: 60_000 });
  assert.equal(run.signal, null, "the decoder looped (killed after 60 s)");
  assert.equal(run.stdout.trim(), "CorruptFileError");
});

test("libzstd in WebAssembly (zstddec) and fzstd give the same bytes on frames the Python writer's zstandard makes", async () => {
  const internals = await import("../dist/internals.mjs");
  assert.ok(await internals.ready(), "the WebAssembly zstd decoder did not load");
  // Random, repetitive and byte-plane data, small to a few MB, fast and strong levels, with the
  // content size stated (as the writer's are).
  const script = `import base64, json, random, zstandard
random.seed(5)
out = []
for n in (1, 7, 300, 4096, 65537, 3000000):
    for kind in ("random", "runs", "planes"):
        if kind == "random":
            raw = bytes(random.getrandbits(8) for _ in range(min(n, 200000))) * (n // min(n, 200000) or 1)
        elif kind == "runs":
            raw = b"".join(bytes([random.randrange(4)]) * random.randrange(1, 300) for _ in range(n // 150 + 1))[:n]
        else:
            raw = bytes((k * k) >> 9 & 255 for k in range(n))
        for level in (1, 19):
            out.append(base64.b64encode(zstandard.ZstdCompressor(level=level).compress(raw)).decode())
print(json.dumps(out))`;
  const run = spawnSync(python(), ["-c", script], { encoding: "utf8", maxBuffer: 1 << 28 });
  assert.equal(run.status, 0, run.stderr);
  const frames = JSON.parse(run.stdout).map((b) => Uint8Array.from(Buffer.from(b, "base64")));
  assert.equal(frames.length, 36);
  for (const [k, frame] of frames.entries()) {
    internals.useWasm(false);
    assert.equal(internals.nativeZstd(), null);
    const plain = internals.inflate(frame, 1 << 26, `frame ${k}`);
    internals.useWasm(true);
    assert.ok(internals.nativeZstd(), "the WebAssembly decoder is not used");
    const wasm = internals.inflate(frame, 1 << 26, `frame ${k}`);
    assert.ok(plain.length > 0 && Buffer.from(wasm).equals(Buffer.from(plain)), `frame ${k}: the decoders disagree`);
  }
});

test("where the WebAssembly zstd decoder cannot start (no fetch, no Buffer), maps decode through fzstd", () => {
  const map = join(fixtures(), "gale_default.dftpc");
  const script = `import { readFileSync } from "node:fs";
    const data = new Uint8Array(readFileSync(${JSON.stringify(map)}));
    delete globalThis.fetch;
    globalThis.Buffer = undefined;
    const { decode, ready } = await import(${JSON.stringify(join(WEB, "dist", "dftpcc.mjs"))});
    const m = decode(data);
    console.log(m.statistics.cells > 0, await ready());`;
  const run = spawnSync(process.execPath, ["--input-type=module", "-e", script], { encoding: "utf8", timeout: 60_000 });
  assert.equal(run.stderr, "");
  assert.equal(run.stdout.trim(), "true false");
});
