// Decodes in a Web Worker so the page keeps turning while a large map (or the next prefix of a
// progressive one) decodes. One request at a time: {id, bytes, fileSize, window?} -> {id, map} or {id, error}.
import { decode, readHeader, ready } from "../src/index.ts";

// The WebAssembly zstd decoder loads while the first bytes are on their way (decodes before it has
// loaded use fzstd).
void ready();

self.onmessage = (event) => {
  const { id, op, bytes, fileSize, window: win } = event.data;
  try {
    if (op === "header") {
      self.postMessage({ id, header: readHeader(bytes, { fileSize }) });
      return;
    }
    const t0 = performance.now();
    // A prefix's low-passed map is sampled every few cells (options.preview): it is shown for a moment
    // only, and the whole file decodes exactly.
    const map = decode(bytes, { fileSize, window: win, float32: true, preview: true });
    const ms = performance.now() - t0;
    self.postMessage({ id, ms, map: { ...map } }, [...new Set([map.heights.buffer, map.mask.buffer])]);
  } catch (err) {
    self.postMessage({ id, error: { name: err?.name ?? "Error", message: String(err?.message ?? err) } });
  }
};
