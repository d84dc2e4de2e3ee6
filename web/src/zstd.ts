// zstd frames by libzstd compiled to WebAssembly (the zstddec package): four to five times fzstd's
// speed on the coefficient chunks (web/bench). Its start is asynchronous (ready()), so a decode
// before it has finished, one where WebAssembly is missing or switched off (useWasm(false)), and a
// frame larger than NATIVE_MAX_BYTES (that memory never shrinks) go through fzstd: both are zstd
// decoders of the same frames (web/test/zstd.test.mjs compares them).
import { ZSTDDecoder } from "zstddec";
import { wasmEnabled } from "./wasm.js";

/** Frames declaring more bytes than this go through fzstd (whose arrays the collector takes back). */
export const NATIVE_MAX_BYTES = 64 * 2 ** 20;

let native: ZSTDDecoder | null = null;
let loading: Promise<boolean> | null = null;

/** Starts loading the WebAssembly zstd decoder (once); resolves to whether it loaded. */
export function ready(): Promise<boolean> {
  if (!loading) {
    const d = new ZSTDDecoder();
    let start: Promise<void>;
    try {
      // init() throws at once where neither fetch nor Node's Buffer exists: fzstd decodes there.
      start = typeof WebAssembly === "object" ? d.init() : Promise.reject(new Error("no WebAssembly"));
    } catch (e) {
      start = Promise.reject(e);
    }
    loading = start.then(
      () => {
        native = d;
        return true;
      },
      () => false, // a page whose policy forbids WebAssembly or data: URLs: fzstd decodes
    );
  }
  return loading;
}

/** The WebAssembly decoder when it has loaded and the kernels are switched on, else null (the first
 * call starts loading it). */
export function nativeZstd(): ZSTDDecoder | null {
  if (!loading) void ready();
  return native && wasmEnabled() ? native : null;
}
