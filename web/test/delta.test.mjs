// Deltas: a growing map's delta applied gives the file the Python writer wrote, byte for byte, and
// the map decodes as Python decodes it; crafted deltas are refused with Python's error classes.
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { join } from "node:path";
import { test } from "node:test";
import { applyDelta, decode } from "../dist/dftpcc.mjs";
import { bytes, f64, fixtures } from "./helpers.mjs";

const DIR = fixtures();
const M = JSON.parse(readFileSync(join(DIR, "manifest.json"), "utf8"));

test("a growing map's delta gives the new file byte for byte, and it decodes as in Python", () => {
  const out = applyDelta(bytes(join(DIR, "grow1.dftpc")), bytes(join(DIR, "grow.dftpcd")));
  assert.deepEqual(out, bytes(join(DIR, "grow2.dftpc")));
  const map = decode(out);
  const mask = bytes(join(DIR, "grow2.mask.u8"));
  const ref = f64(join(DIR, "grow2.ref.f64"));
  for (let k = 0; k < mask.length; k++) {
    assert.equal(map.mask[k], mask[k]);
    if (mask[k]) assert.ok(Math.abs(map.heights[k] - ref[k]) <= Math.abs(ref[k]) * 2 ** -24);
  }
});

test("a delta between two unrelated files applies too", () => {
  const out = applyDelta(bytes(join(DIR, "grow1.dftpc")), bytes(join(DIR, "cross.dftpcd")));
  assert.deepEqual(out, bytes(join(DIR, "gale_default.dftpc")));
});

for (const [name, error] of Object.entries(M.delta.refusals)) {
  test(`delta ${name}: refused with ${error}, as in Python`, () => {
    const base = bytes(join(DIR, `delta_${name}.base`));
    const delta = bytes(join(DIR, `delta_${name}.dftpcd`));
    assert.throws(() => applyDelta(base, delta), (e) => e.name === error);
  });
}
