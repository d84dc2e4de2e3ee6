// The inverse orthonormal DCT-II (a DCT-III) of length N by a complex FFT of length N (Makhoul's
// reordering), two real vectors per transform. The FFT is fft.js for powers of two; a mixed-radix
// Stockham FFT (radices 4, 2, 3, 5 and small primes) for lengths whose prime factors are at most
// MAX_RADIX, as DEM sides mostly are (559 = 13 x 43, 495 = 3^2 x 5 x 11); Bluestein's chirp-z over
// fft.js for the others. For wide spectra (a low cutoff) this is the fast path of transform.ts's
// addIdct; narrow ones are cheaper as plain sums.
import FFT from "fft.js";

/** The radices of n, 4s first (the cheapest butterflies per point), or null when Bluestein's two
 * power-of-two FFTs cost less (a radix-p stage costs about 8 p flops a point: a large prime factor). */
function radices(n: number): number[] | null {
  const out: number[] = [];
  let m = n;
  while (m % 4 === 0) {
    out.push(4);
    m /= 4;
  }
  for (let p = 2; p * p <= m; p++) {
    while (m % p === 0) {
      out.push(p);
      m /= p;
    }
  }
  if (m > 1) out.push(m);
  return MixedFFT.cost(n, out) < bluesteinCost(n) ? out : null;
}

function bluesteinCost(n: number): number {
  const p = pow2AtLeast(2 * n - 1);
  return 2 * 5 * p * Math.log2(p) + 12 * p;
}

/** Forward complex DFT of a length whose prime factors are small: Stockham's autosort algorithm
 * (no bit reversal), one out-of-place pass per radix, twiddles from one table of the n-th roots. */
class MixedFFT {
  readonly n: number;
  private readonly stages: number[];
  private readonly wr: Float64Array; // cos(2 pi k / n)
  private readonly wi: Float64Array; // -sin(2 pi k / n)
  private readonly br: Float64Array;
  private readonly bi: Float64Array;
  private readonly vr: Float64Array; // an odd prime radix's twiddled inputs
  private readonly vi: Float64Array;
  private readonly pr: Float64Array; // their sums and differences in pairs b, R - b
  private readonly pi: Float64Array;
  private readonly mr: Float64Array;
  private readonly mi: Float64Array;
  /** Per odd prime radix R > 3: cos and sin of 2 pi a b / R for a, b in 1 .. (R-1)/2, row-major. */
  private readonly tables = new Map<number, { cos: Float64Array; sin: Float64Array }>();

  constructor(n: number, stages: number[]) {
    this.n = n;
    this.stages = stages;
    this.wr = new Float64Array(n);
    this.wi = new Float64Array(n);
    for (let k = 0; k < n; k++) {
      // Both from the angle of the least residue, so that w^k is as exact for every k.
      this.wr[k] = Math.cos((2 * Math.PI * k) / n);
      this.wi[k] = -Math.sin((2 * Math.PI * k) / n);
    }
    this.br = new Float64Array(n);
    this.bi = new Float64Array(n);
    const most = Math.max(...stages, 1);
    this.vr = new Float64Array(most);
    this.vi = new Float64Array(most);
    this.pr = new Float64Array(most);
    this.pi = new Float64Array(most);
    this.mr = new Float64Array(most);
    this.mi = new Float64Array(most);
    for (const R of stages) {
      if (R <= 4 || this.tables.has(R)) continue;
      const h = (R - 1) >> 1;
      const cos = new Float64Array(h * h);
      const sin = new Float64Array(h * h);
      for (let a = 1; a <= h; a++) {
        for (let b = 1; b <= h; b++) {
          const m = (a * b) % R; // the least residue: the angle as exact as it gets
          cos[(a - 1) * h + b - 1] = Math.cos((2 * Math.PI * m) / R);
          sin[(a - 1) * h + b - 1] = Math.sin((2 * Math.PI * m) / R);
        }
      }
      this.tables.set(R, { cos, sin });
    }
  }

  /** In place on (re, im). */
  forward(re: Float64Array, im: Float64Array): void {
    const { n, wr, wi } = this;
    let xr = re;
    let xi = im;
    let yr = this.br;
    let yi = this.bi;
    let ns = 1;
    for (const R of this.stages) {
      const span = n / R; // distance between a butterfly's inputs
      const step = n / (ns * R); // twiddle index per (j mod ns) and r
      for (let j = 0; j < span; j++) {
        const jm = j % ns;
        const out = (j - jm) * R + jm;
        const t = jm * step;
        if (R === 4) {
          const ar = xr[j], ai = xi[j];
          let br = xr[j + span], bi = xi[j + span];
          let cr = xr[j + 2 * span], ci = xi[j + 2 * span];
          let dr = xr[j + 3 * span], di = xi[j + 3 * span];
          if (t) {
            let c = wr[t], s = wi[t];
            const bt = br * c - bi * s; bi = br * s + bi * c; br = bt;
            c = wr[2 * t]; s = wi[2 * t];
            const ct = cr * c - ci * s; ci = cr * s + ci * c; cr = ct;
            c = wr[3 * t]; s = wi[3 * t];
            const dt = dr * c - di * s; di = dr * s + di * c; dr = dt;
          }
          const s0r = ar + cr, s0i = ai + ci, d0r = ar - cr, d0i = ai - ci;
          const s1r = br + dr, s1i = bi + di, d1r = br - dr, d1i = bi - di;
          yr[out] = s0r + s1r; yi[out] = s0i + s1i;
          yr[out + ns] = d0r + d1i; yi[out + ns] = d0i - d1r; // d0 - i d1
          yr[out + 2 * ns] = s0r - s1r; yi[out + 2 * ns] = s0i - s1i;
          yr[out + 3 * ns] = d0r - d1i; yi[out + 3 * ns] = d0i + d1r; // d0 + i d1
        } else if (R === 2) {
          let br = xr[j + span], bi = xi[j + span];
          if (t) {
            const c = wr[t], s = wi[t];
            const bt = br * c - bi * s; bi = br * s + bi * c; br = bt;
          }
          const ar = xr[j], ai = xi[j];
          yr[out] = ar + br; yi[out] = ai + bi;
          yr[out + ns] = ar - br; yi[out + ns] = ai - bi;
        } else if (R === 3) {
          let br = xr[j + span], bi = xi[j + span];
          let cr = xr[j + 2 * span], ci = xi[j + 2 * span];
          if (t) {
            let c = wr[t], s = wi[t];
            const bt = br * c - bi * s; bi = br * s + bi * c; br = bt;
            c = wr[2 * t]; s = wi[2 * t];
            const ct = cr * c - ci * s; ci = cr * s + ci * c; cr = ct;
          }
          const ar = xr[j], ai = xi[j];
          const sr = br + cr, si = bi + ci;
          const mr = ar - 0.5 * sr, mi = ai - 0.5 * si;
          const h = Math.sqrt(3) / 2;
          const qr = h * (bi - ci), qi = -h * (br - cr); // -i sin(2pi/3) (b - c)
          yr[out] = ar + sr; yi[out] = ai + si;
          yr[out + ns] = mr + qr; yi[out + ns] = mi + qi;
          yr[out + 2 * ns] = mr - qr; yi[out + 2 * ns] = mi - qi;
        } else {
          // An odd prime radix: twiddled inputs, then their length-R DFT with the symmetric pairs
          // b, R - b sharing each cosine and sine (a quarter of the products of the plain sum).
          const { vr, vi } = this;
          for (let r = 0; r < R; r++) {
            const x = xr[j + r * span], y = xi[j + r * span];
            const k = (t * r) % n;
            vr[r] = k ? x * wr[k] - y * wi[k] : x;
            vi[r] = k ? x * wi[k] + y * wr[k] : y;
          }
          const h = (R - 1) >> 1;
          const { pr, pi, mr, mi } = this;
          let s0r = vr[0], s0i = vi[0];
          for (let b = 1; b <= h; b++) {
            pr[b] = vr[b] + vr[R - b]; pi[b] = vi[b] + vi[R - b];
            mr[b] = vr[b] - vr[R - b]; mi[b] = vi[b] - vi[R - b];
            s0r += pr[b]; s0i += pi[b];
          }
          yr[out] = s0r; yi[out] = s0i;
          const tab = this.tables.get(R)!;
          for (let a = 1; a <= h; a++) {
            let ar = vr[0], ai = vi[0], br = 0, bi = 0;
            const row = (a - 1) * h;
            for (let b = 1; b <= h; b++) {
              const c = tab.cos[row + b - 1], sn = tab.sin[row + b - 1];
              ar += pr[b] * c; ai += pi[b] * c;
              br += mr[b] * sn; bi += mi[b] * sn;
            }
            // y[a] = A - i B, y[R - a] = A + i B  (w = e^{-2 pi i / R})
            yr[out + a * ns] = ar + bi; yi[out + a * ns] = ai - br;
            yr[out + (R - a) * ns] = ar - bi; yi[out + (R - a) * ns] = ai + br;
          }
        }
      }
      ns *= R;
      const tr = xr;
      xr = yr;
      yr = tr;
      const ti = xi;
      xi = yi;
      yi = ti;
    }
    if (xr !== re) {
      re.set(xr);
      im.set(xi);
    }
  }

  /** Flops of one transform, roughly: about 5 n log2 n for radices 2 to 5, n R for a generic R. */
  static cost(n: number, stages: number[]): number {
    let c = 0;
    for (const R of stages) c += R <= 4 ? 5 * n * Math.log2(R) : 2 * n * R + 8 * n;
    return c;
  }
}

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
  private readonly mixed: MixedFFT | null; // when n is neither a power of two nor has a large prime factor

  constructor(n: number) {
    this.n = n;
    const direct = n >= 2 && (n & (n - 1)) === 0;
    const stages = direct ? null : radices(n);
    this.mixed = stages ? new MixedFFT(n, stages) : null;
    // fft.js wants a power of two of at least 2 (unused beside the mixed-radix FFT).
    this.p = direct ? n : this.mixed ? 2 : pow2AtLeast(2 * n - 1);
    this.fft = new FFT(this.p);
    this.a = new Float64Array(2 * this.p);
    this.b = new Float64Array(2 * this.p);
    this.c = new Float64Array(this.mixed ? 0 : 2 * n);
    this.kernel = new Float64Array(2 * this.p);
    if (direct || this.mixed) return;
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
    if (this.mixed) {
      this.mixed.forward(re, im);
      return;
    }
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
    const stages = direct ? null : radices(n);
    if (stages) return MixedFFT.cost(n, stages) + 4 * n;
    if (!direct) return bluesteinCost(n);
    return 5 * n * Math.log2(n) + 12 * n;
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
