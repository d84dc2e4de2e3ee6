// Every crafted damaged file of tests/corpus is refused as the Python reader refuses it: the same
// error class, and a message matching the corpus's expectation where it states one.
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { join } from "node:path";
import { test } from "node:test";
import { decode } from "../dist/dftpcc.mjs";
import { bytes, ROOT } from "./helpers.mjs";

const CORPUS = join(ROOT, "tests", "corpus");
const EXPECTED = JSON.parse(readFileSync(join(CORPUS, "expected.json"), "utf8"));

for (const [name, want] of Object.entries(EXPECTED)) {
  test(`corpus ${name}: ${want.error}${want.match ? ` /${want.match}/` : ""}`, () => {
    const data = bytes(join(CORPUS, name));
    let error = null;
    try {
      decode(data);
    } catch (e) {
      error = e;
    }
    assert.ok(error, `${name} decoded`);
    assert.equal(error.name, want.error, `${name}: ${error.message}`);
    if (want.match) assert.match(error.message, new RegExp(want.match), name);
  });
}
