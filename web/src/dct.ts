// The inverse orthonormal DCT-II (a DCT-III) of length N by a complex FFT of length N (Makhoul's
// reordering), two real vectors per transform; the FFT is fft.js for powers of two and Bluestein's
// chirp-z over fft.js otherwise. For wide spectra (a low cutoff) this is the fast path of
// transform.ts's addIdct; narrow ones are cheaper as plain sums.
import FFT from "fft.js";

function pow2AtLeast(n: number): number {
  let p = 2;
  while (p < n) p *= 2;
  return p;
}

/** Forward DFT of any length n, in place on (re, im). */
class AnyFFT {
  readonly n: number;
  private readonly p: number;
  private readonly fft: FFT;
  private readonly a: Float64Array;
  private readonly b: Float64Array;
  private readonly c: Float64Array; // the chirp e^{-i pi m^2 / n}, interleaved
  private readonly kernel: Float64Array; // FFT of the conjugate chirp, wrapped to p

  constructor(n: number) {
    this.n = n;
    const direct = n >= 2 && (n & (n - 1)) === 0;
    this.p = direct ? n : pow2AtLeast(2 * n - 1);
    this.fft = new FFT(this.p);
    this.a = new Float64Array(2 * this.p);
    this.b = new Float64Array(2 * this.p);
    this.c = new Float64Array(2 * n);
    this.kernel = new Float64Array(2 * this.p);
    if (direct) return;
    for (let m = 0; m < n; m++) {
      const phase = (Math.PI * ((m * m) % (2 * n))) / n; // m^2 mod 2n keeps the phase exact
      this.c[2 * m] = Math.cos(phase);
      this.c[2 * m + 1] = -Math.sin(phase);
    }
    const w = new Float64Array(2 * this.p);
    for (let m = 0; m < n; m++) {
      w[2 * m] = this.c[2 * m];
      w[2 * m + 1] = -this.c[2 * m + 1];
      if (m) {
        w[2 * (this.p - m)] = w[2 * m];
        w[2 * (this.p - m) + 1] = w[2 * m + 1];
      }
    }
    this.fft.transform(this.kernel, w);
  }

  forward(re: Float64Array, im: Float64Array): void {
    const { n, p, a, b, c } = this;
    if (p === n) {
      for (let k = 0; k < n; k++) {
        a[2 * k] = re[k];
        a[2 * k + 1] = im[k];
      }
      this.fft.transform(b, a);
      for (let k = 0; k < n; k++) {
        re[k] = b[2 * k];
        im[k] = b[2 * k + 1];
      }
      return;
    }
    a.fill(0);
    for (let m = 0; m < n; m++) {
      a[2 * m] = re[m] * c[2 * m] - im[m] * c[2 * m + 1];
      a[2 * m + 1] = re[m] * c[2 * m + 1] + im[m] * c[2 * m];
    }
    this.fft.transform(b, a);
    const kr = this.kernel;
    for (let k = 0; k < p; k++) {
      const xr = b[2 * k];
      const xi = b[2 * k + 1];
      a[2 * k] = xr * kr[2 * k] - xi * kr[2 * k + 1];
      a[2 * k + 1] = xr * kr[2 * k + 1] + xi * kr[2 * k];
    }
    this.fft.inverseTransform(b, a);
    for (let k = 0; k < n; k++) {
      const xr = b[2 * k];
      const xi = b[2 * k + 1];
      re[k] = xr * c[2 * k] - xi * c[2 * k + 1];
      im[k] = xr * c[2 * k + 1] + xi * c[2 * k];
    }
  }

  /** Flops of one transform, roughly: what addIdct weighs against plain sums. */
  static cost(n: number): number {
    const direct = n >= 2 && (n & (n - 1)) === 0;
    const p = direct ? n : pow2AtLeast(2 * n - 1);
    return (direct ? 1 : 2) * 5 * p * Math.log2(p) + 12 * p;
  }
}

/** Orthonormal DCT-III (scipy's idct(type=2, norm="ortho")) of length n, two real vectors at once. */
export class Dct3 {
  readonly n: number;
  private readonly fft: AnyFFT;
  private readonly tc: Float64Array;
  private readonly ts: Float64Array;
  private readonly re: Float64Array;
  private readonly im: Float64Array;

  constructor(n: number) {
    this.n = n;
    this.fft = new AnyFFT(n);
    this.tc = new Float64Array(n);
    this.ts = new Float64Array(n);
    for (let k = 0; k < n; k++) {
      this.tc[k] = Math.cos((Math.PI * k) / (2 * n));
      this.ts[k] = Math.sin((Math.PI * k) / (2 * n));
    }
    this.re = new Float64Array(n);
    this.im = new Float64Array(n);
  }

  static cost(n: number): number {
    return AnyFFT.cost(n) + 20 * n;
  }

  /** y1 = DCT-III(x1), y2 = DCT-III(x2); x of length <= n (zeros beyond), y of length n. */
  run(x1: Float64Array, k1: number, x2: Float64Array | null, k2: number, y1: Float64Array, y2: Float64Array | null): void {
    const { n, tc, ts, re, im } = this;
    const s0 = Math.sqrt(n);
    const sk = Math.sqrt(n / 2);
    // X[k] of the unnormalised DCT-II whose inverse is the orthonormal DCT-III of x.
    const X1 = (k: number) => (k >= k1 || k >= n ? 0 : x1[k] * (k === 0 ? s0 : sk));
    const X2 = (k: number) => (!x2 || k >= k2 || k >= n ? 0 : x2[k] * (k === 0 ? s0 : sk));
    for (let k = 0; k < n; k++) {
      const a1 = X1(k);
      const b1 = k === 0 ? 0 : X1(n - k);
      const a2 = X2(k);
      const b2 = k === 0 ? 0 : X2(n - k);
      // V = e^{i pi k / 2n} (X[k] - i X[n-k]), for both vectors packed as V1 + i V2, conjugated
      // so that the forward FFT computes the inverse one.
      const v1r = a1 * tc[k] + b1 * ts[k];
      const v1i = a1 * ts[k] - b1 * tc[k];
      const v2r = a2 * tc[k] + b2 * ts[k];
      const v2i = a2 * ts[k] - b2 * tc[k];
      re[k] = v1r - v2i;
      im[k] = -(v1i + v2r);
    }
    this.fft.forward(re, im);
    const half = Math.ceil(n / 2);
    for (let m = 0; m < n; m++) {
      const vr = re[m] / n;
      const vi = -im[m] / n;
      const at = m < half ? 2 * m : 2 * (n - 1 - m) + 1;
      y1[at] = vr;
      if (y2) y2[at] = vi;
    }
  }
}
