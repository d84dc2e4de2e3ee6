// The WebAssembly SIMD kernels (web/wasm/kernels.ts, compiled by the build and embedded in the
// bundle): the FFTs of the inverse DCT and the finishing pass, which run about twice to four times
// as fast as the TypeScript loops in V8 (web/bench). They do the TypeScript kernels' operations in
// their order, so both paths give the same heights; where WebAssembly or its SIMD is missing (or
// its memory cannot grow), the TypeScript path runs. This module owns the kernels' memory: a scratch
// region for one call's arrays, then the plans' tables (copied from the TypeScript plans of dct.ts),
// dropped whenever the scratch region must grow.
import bytes from "../wasm/out/kernels.wasm";
import type { BluesteinFft, Dct3, MixedFft } from "./dct.js";

interface Exports {
  memory: WebAssembly.Memory;
  heapBase(): number;
  setConstants(p: number): void;
  dctGroup(dct: number, bluestein: number, fft: number, inp: number, i0: number, i1: number, i2: number, i3: number,
    is: number, K: number, out: number, o0: number, o1: number, o2: number, o3: number, os: number, c0: number, w: number, fin: number): void;
  finishZeros(fin: number, o: number, os: number, w: number): void;
  sumsAxis(inp: number, ioff: number, ivs: number, ies: number, nvec: number, klen: number, basis: number,
    out: number, ooff: number, ovs: number, oes: number, w: number): void;
  finish(h: number, mask: number, out: number, cols: number, wr0: number, wr1: number, wc0: number, wc1: number,
    z0: number, a: number, b: number, c: number, f32: number, res: number): number;
  ansGroups(words: number, nwords: number, groups: number, ngroups: number, at: number, out: number, maxAbs: number, slotShift: number): void;
  contextMask(lines: number, n: number, w: number, L: number, nStripes: number, first: number, words: number, nwords: number,
    scratch: number, tables: number): void;
  predicted(words: number, nwords: number, weights: number, classes: number, mask: number, rows: number, cols: number,
    V: number, ring: number, line: number, lineClass: number, order: number, starts: number, out: number, slotShift: number): number;
  residualGrid(res: number, mask: number, q: number, picture: number, cells: number, e: number): void;
  addResidual(h: number, mask: number, q: number, picture: number, rows: number, cols: number, plane: number, a: number, b: number, c: number,
    e: number): void;
}

/** The kernels' memory could not grow: the caller runs the TypeScript path instead. */
export class WasmMemoryError extends Error {}

const PAGE = 65536;
/** p rounded up to a multiple of 16 (arithmetic, not bitwise: offsets pass 2**31). */
export const align16 = (p: number) => Math.ceil(p / 16) * 16;
const align = align16;

export class Kernels {
  readonly ex: Exports;
  private readonly base: number;
  private scratchEnd: number;
  private top: number;
  /** Bumped whenever the tables are dropped: a plan uploaded under another generation is stale. */
  private gen = 0;
  private readonly uploaded = new WeakMap<object, { gen: number; ptr: number }>();
  private f64 = new Float64Array(0);
  private i32 = new Int32Array(0);
  private u8 = new Uint8Array(0);

  constructor(ex: Exports) {
    this.ex = ex;
    this.base = align(ex.heapBase());
    this.scratchEnd = this.base;
    this.top = this.base;
    this.views();
  }

  private views(): void {
    const buf = this.ex.memory.buffer;
    if (this.f64.buffer !== buf) {
      this.f64 = new Float64Array(buf);
      this.i32 = new Int32Array(buf);
      this.u8 = new Uint8Array(buf);
    }
  }

  /** Float64 view of the memory (stale after any later allocation: call again). */
  view(): Float64Array {
    this.views();
    return this.f64;
  }

  bytes(): Uint8Array {
    this.views();
    return this.u8;
  }

  private ensure(end: number): void {
    const have = this.ex.memory.buffer.byteLength;
    if (end > have) {
      try {
        this.ex.memory.grow(Math.ceil((end - have) / PAGE));
      } catch {
        throw new WasmMemoryError("the WebAssembly memory cannot grow");
      }
    }
    this.views();
  }

  /** The scratch region of at least `n` bytes (16-aligned, its contents undefined); the plans'
   * tables move above it when it grows. */
  scratch(n: number): number {
    const end = align(this.base + n);
    if (end > 2 ** 32) throw new WasmMemoryError("more than 4 GiB of WebAssembly memory");
    if (end > this.scratchEnd || this.gen === 0) {
      // Grown first (a failure leaves everything as it was), with room for the constants.
      this.ensure(end + 64);
      this.scratchEnd = end;
      this.top = end;
      this.gen++;
      // The tables start anew: the constants first.
      this.ex.setConstants(this.put(new Float64Array([Math.sqrt(3) / 2, Math.cos((2 * Math.PI) / 5),
        Math.cos((4 * Math.PI) / 5), Math.sin((2 * Math.PI) / 5), Math.sin((4 * Math.PI) / 5)])));
    }
    return this.base;
  }

  /** Bytes of memory held (it never shrinks). */
  held(): number {
    return this.ex.memory.buffer.byteLength;
  }

  private alloc(n: number): number {
    const p = align(this.top);
    if (p + n > 2 ** 32) throw new WasmMemoryError("more than 4 GiB of WebAssembly memory");
    this.ensure(p + n);
    this.top = p + n;
    return p;
  }

  private put(a: Float64Array): number {
    const p = this.alloc(8 * a.length);
    this.view().set(a, p / 8);
    return p;
  }

  /** An Int32Array's copy above the scratch region (a model's table), uploaded once while it lives. */
  ints(a: Int32Array): number {
    return this.cached(a, () => {
      const p = this.alloc(4 * a.length);
      this.views();
      this.i32.set(a, p / 4);
      return p;
    });
  }

  private words(ptr: number, w: number[]): void {
    this.views();
    this.i32.set(w, ptr / 4);
  }

  private cached(key: object, make: () => number): number {
    const u = this.uploaded.get(key);
    if (u && u.gen === this.gen) return u.ptr;
    const ptr = make();
    this.uploaded.set(key, { gen: this.gen, ptr });
    return ptr;
  }

  /** A MixedFft's plan (see mixedForward in kernels.ts for its layout). */
  mixed(m: MixedFft): number {
    return this.cached(m, () => {
      const n = m.n;
      const stages = m.stages;
      const plan = this.alloc(48 + 32 * stages.length);
      const most = Math.max(1, ...stages.map((s) => s.R));
      const head = [n, stages.length, this.alloc(16 * n), this.alloc(16 * n)];
      for (let k = 0; k < 6; k++) head.push(this.alloc(16 * most));
      head.push(this.alloc(64 * most), 0);
      const words = [...head];
      for (const s of stages) words.push(s.R, s.ns, this.put(s.twr), this.put(s.twi), this.put(s.cos), this.put(s.sin), this.put(s.quad), 0);
      this.words(plan, words);
      return plan;
    });
  }

  /** A BluesteinFft's plan (bluesteinForward in kernels.ts). */
  bluestein(b: BluesteinFft): number {
    return this.cached(b, () => {
      const mixed = this.mixed(b.fft);
      const plan = this.alloc(48);
      this.words(plan, [b.n, b.P, b.shift, b.band, this.put(b.cr), this.put(b.ci), this.put(b.kr), this.put(b.ki),
        this.alloc(16 * b.P), this.alloc(16 * b.P), mixed]);
      return plan;
    });
  }

  /** A Dct3's plan (dctGroup in kernels.ts). */
  dct(d: Dct3): number {
    return this.cached(d, () => {
      const plan = this.alloc(32);
      this.words(plan, [d.n, this.put(d.car), this.put(d.sar), this.put(d.cb), this.put(d.sb), this.alloc(16 * d.n), this.alloc(16 * d.n)]);
      return plan;
    });
  }
}

let enabled = true;
let compiled: WebAssembly.Module | null | undefined;
let loaded: Kernels | null = null;

/** A memory above this is let go after a decode (a WebAssembly memory never shrinks: one large map
 * would otherwise hold its grids for the page's life); the next decode starts a fresh instance. */
const RETAIN_BYTES = 256 * 2 ** 20;

/** The kernels, or null where WebAssembly SIMD is missing (or switched off by useWasm). */
export function kernels(): Kernels | null {
  if (!enabled) return null;
  if (compiled === undefined) {
    compiled = null;
    try {
      if (typeof WebAssembly === "object" && WebAssembly.validate(bytes)) compiled = new WebAssembly.Module(bytes);
    } catch {
      compiled = null; // a page whose policy forbids WebAssembly, or a compile refused on a main thread
    }
  }
  if (compiled && !loaded) {
    try {
      loaded = new Kernels(new WebAssembly.Instance(compiled, {}).exports as unknown as Exports);
    } catch {
      compiled = null;
    }
  }
  return loaded;
}

/** Lets the kernels' memory go when it grew past RETAIN_BYTES (called after each decode). */
export function releaseKernels(): void {
  if (loaded && loaded.held() > RETAIN_BYTES) loaded = null;
}

/** Whether decodes may use WebAssembly (useWasm), for the zstd decoder (zstd.ts). */
export function wasmEnabled(): boolean {
  return enabled;
}

/** Turns the WebAssembly SIMD kernels on (the default) or off (the TypeScript path alone, as where
 * WebAssembly SIMD is missing; the tests compare both); returns whether decodes now use them. */
export function useWasm(on: boolean): boolean {
  enabled = on;
  return kernels() !== null;
}
