// The inverse orthonormal DCT-II (a DCT-III) of length N by a complex FFT of length N (Makhoul's
// reordering), two real vectors per transform. The FFT is a Stockham autosort FFT of mixed radix
// (butterflies for 2, 3, 4 and 5, a generic one for other primes) when its largest prime factor is
// cheap enough, else Bluestein's chirp-z over such an FFT of a length with small factors. A low-pass
// spectrum keeps only the first K coefficients of each vector, so the FFT's input is nonzero on a
// band of 2K - 1 entries around 0: the generic radix runs first and skips the pairs that are all
// zeros, and Bluestein's convolution needs only N + 2K - 2 points rather than 2N - 1. For wide
// spectra (a low cutoff) this is the fast path of transform.ts's addIdct; narrow ones are cheaper
// as plain sums.

/** The largest radix that has its own butterfly. */
const SMALL_RADIX = 5;

/** The prime factors of n, largest first when one exceeds SMALL_RADIX (a generic radix runs first,
 * where the band's zeros can be skipped), then 4s, 2, 3s and 5s (the cheapest butterflies a point). */
export function factorize(n: number): number[] {
  const big: number[] = [];
  const small: number[] = [];
  let m = n;
  while (m % 4 === 0) {
    small.push(4);
    m /= 4;
  }
  for (let p = 2; p * p <= m; p++) {
    while (m % p === 0) {
      (p > SMALL_RADIX ? big : small).push(p);
      m /= p;
    }
  }
  if (m > 1) (m > SMALL_RADIX ? big : small).push(m);
  big.sort((a, b) => b - a);
  return [...big, ...small];
}

/** Rough cost of one transform (flops of the mixed-radix FFT, weighted as measured in V8: a generic
 * radix's inner loop runs slower per flop than the unrolled butterflies), for a band of `lo`. */
export function mixedCost(n: number, stages: number[], lo: number): number {
  let c = 0;
  let first = true;
  for (const R of stages) {
    if (R <= SMALL_RADIX) c += (R === 4 ? 4.25 : R === 2 ? 5 : R === 3 ? 5.5 : 6.5) * n;
    else {
      const h = (R - 1) >> 1;
      const span = n / R;
      const used = first && 2 * (lo + span) <= n ? Math.min(h, Math.ceil(lo / span)) : h;
      c += n * (8 * h * used / R + 8) * GENERIC_WEIGHT;
    }
    first = false;
  }
  return c;
}

/** A generic radix's flops run faster than the model's count says against the unrolled butterflies
 * (two outputs a round share the loads; measured in Node 22 over the shared DEMs' sides). */
const GENERIC_WEIGHT = 0.6;

/** One pass of a Stockham FFT: radix R, ns the product of the radices before it, twiddles
 * w^(jm r n / (ns R)) for jm < ns, r = 1 .. R-1 (w = e^{-2 pi i / n}). */
interface Stage {
  R: number;
  ns: number;
  twr: Float64Array;
  twi: Float64Array;
  /** Generic radix: cos and sin of 2 pi a b / R for a, b in 1 .. (R-1)/2, row-major. */
  cos: Float64Array;
  sin: Float64Array;
  /** The same for rows a, a + 1 (a odd) interleaved: cos(a, b), sin(a, b), cos(a + 1, b), sin(a + 1, b). */
  quad: Float64Array;
}

/** Forward complex DFT (e^{-2 pi i j k / n}, unnormalised) of a length with factors of at most
 * MAX_RADIX, out of place between two pairs of buffers. */
export class MixedFft {
  readonly n: number;
  readonly stages: Stage[];
  private readonly br: Float64Array;
  private readonly bi: Float64Array;
  private readonly vr: Float64Array; // a generic radix's inputs
  private readonly vi: Float64Array;
  private readonly pr: Float64Array; // their sums and differences in pairs b, R - b
  private readonly pi: Float64Array;
  private readonly mr: Float64Array;
  private readonly mi: Float64Array;
  private readonly pm: Float64Array; // pr, pi, mr, mi interleaved (from b = 1)

  constructor(n: number, radices: number[]) {
    this.n = n;
    this.stages = [];
    let ns = 1;
    for (const R of radices) {
      const step = n / (ns * R);
      const twr = new Float64Array(ns * (R - 1));
      const twi = new Float64Array(ns * (R - 1));
      for (let jm = 0; jm < ns; jm++) {
        for (let r = 1; r < R; r++) {
          // The angle of the least residue, so that every power is as exact.
          const k = (jm * r * step) % n;
          twr[jm * (R - 1) + r - 1] = Math.cos((2 * Math.PI * k) / n);
          twi[jm * (R - 1) + r - 1] = -Math.sin((2 * Math.PI * k) / n);
        }
      }
      let cos = new Float64Array(0);
      let sin = new Float64Array(0);
      if (R > SMALL_RADIX) {
        const h = (R - 1) >> 1;
        cos = new Float64Array(h * h);
        sin = new Float64Array(h * h);
        for (let a = 1; a <= h; a++) {
          for (let b = 1; b <= h; b++) {
            const m = (a * b) % R;
            cos[(a - 1) * h + b - 1] = Math.cos((2 * Math.PI * m) / R);
            sin[(a - 1) * h + b - 1] = Math.sin((2 * Math.PI * m) / R);
          }
        }
      }
      const hh = (R - 1) >> 1;
      const quad = new Float64Array(R > SMALL_RADIX ? 4 * hh * hh : 0);
      for (let a = 1; a < hh; a += 2) {
        for (let b = 1; b <= hh; b++) {
          const q = 4 * ((a - 1) / 2 * hh + b - 1);
          quad[q] = cos[(a - 1) * hh + b - 1];
          quad[q + 1] = sin[(a - 1) * hh + b - 1];
          quad[q + 2] = cos[a * hh + b - 1];
          quad[q + 3] = sin[a * hh + b - 1];
        }
      }
      this.stages.push({ R, ns, twr, twi, cos, sin, quad });
      ns *= R;
    }
    this.br = new Float64Array(n);
    this.bi = new Float64Array(n);
    const most = Math.max(1, ...radices);
    this.vr = new Float64Array(most);
    this.vi = new Float64Array(most);
    this.pr = new Float64Array(most);
    this.pi = new Float64Array(most);
    this.mr = new Float64Array(most);
    this.mi = new Float64Array(most);
    this.pm = new Float64Array(4 * most);
  }

  /** In place on (re, im). The input is zero outside indices [0, lo) and (n - lo, n): a generic
   * first radix skips those (lo >= n / 2 for a dense input). */
  forward(re: Float64Array, im: Float64Array, lo: number): void {
    let xr = re;
    let xi = im;
    let yr = this.br;
    let yi = this.bi;
    for (let s = 0; s < this.stages.length; s++) {
      const st = this.stages[s];
      if (st.R === 4) this.radix4(st, xr, xi, yr, yi);
      else if (st.R === 2) this.radix2(st, xr, xi, yr, yi);
      else if (st.R === 3) this.radix3(st, xr, xi, yr, yi);
      else if (st.R === 5) this.radix5(st, xr, xi, yr, yi);
      else this.generic(st, xr, xi, yr, yi, s === 0 ? lo : this.n);
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

  private radix4(st: Stage, xr: Float64Array, xi: Float64Array, yr: Float64Array, yi: Float64Array): void {
    const { ns, twr, twi } = st;
    const m = this.n / 4;
    const blocks = m / ns;
    for (let q = 0, j = 0; q < blocks; q++) {
      const ob = q * ns * 4;
      for (let jm = 0; jm < ns; jm++, j++) {
        const ar = xr[j], ai = xi[j];
        let br = xr[j + m], bi = xi[j + m];
        let cr = xr[j + 2 * m], ci = xi[j + 2 * m];
        let dr = xr[j + 3 * m], di = xi[j + 3 * m];
        if (jm) {
          const t = 3 * jm;
          let c = twr[t], s = twi[t];
          const bt = br * c - bi * s; bi = br * s + bi * c; br = bt;
          c = twr[t + 1]; s = twi[t + 1];
          const ct = cr * c - ci * s; ci = cr * s + ci * c; cr = ct;
          c = twr[t + 2]; s = twi[t + 2];
          const dt = dr * c - di * s; di = dr * s + di * c; dr = dt;
        }
        const s0r = ar + cr, s0i = ai + ci, d0r = ar - cr, d0i = ai - ci;
        const s1r = br + dr, s1i = bi + di, d1r = br - dr, d1i = bi - di;
        const o = ob + jm;
        yr[o] = s0r + s1r; yi[o] = s0i + s1i;
        yr[o + ns] = d0r + d1i; yi[o + ns] = d0i - d1r; // d0 - i d1
        yr[o + 2 * ns] = s0r - s1r; yi[o + 2 * ns] = s0i - s1i;
        yr[o + 3 * ns] = d0r - d1i; yi[o + 3 * ns] = d0i + d1r; // d0 + i d1
      }
    }
  }

  private radix2(st: Stage, xr: Float64Array, xi: Float64Array, yr: Float64Array, yi: Float64Array): void {
    const { ns, twr, twi } = st;
    const m = this.n / 2;
    const blocks = m / ns;
    for (let q = 0, j = 0; q < blocks; q++) {
      const ob = q * ns * 2;
      for (let jm = 0; jm < ns; jm++, j++) {
        let br = xr[j + m], bi = xi[j + m];
        if (jm) {
          const c = twr[jm], s = twi[jm];
          const bt = br * c - bi * s; bi = br * s + bi * c; br = bt;
        }
        const ar = xr[j], ai = xi[j];
        const o = ob + jm;
        yr[o] = ar + br; yi[o] = ai + bi;
        yr[o + ns] = ar - br; yi[o + ns] = ai - bi;
      }
    }
  }

  private radix3(st: Stage, xr: Float64Array, xi: Float64Array, yr: Float64Array, yi: Float64Array): void {
    const { ns, twr, twi } = st;
    const m = this.n / 3;
    const blocks = m / ns;
    const h = Math.sqrt(3) / 2;
    for (let q = 0, j = 0; q < blocks; q++) {
      const ob = q * ns * 3;
      for (let jm = 0; jm < ns; jm++, j++) {
        let br = xr[j + m], bi = xi[j + m];
        let cr = xr[j + 2 * m], ci = xi[j + 2 * m];
        if (jm) {
          const t = 2 * jm;
          let c = twr[t], s = twi[t];
          const bt = br * c - bi * s; bi = br * s + bi * c; br = bt;
          c = twr[t + 1]; s = twi[t + 1];
          const ct = cr * c - ci * s; ci = cr * s + ci * c; cr = ct;
        }
        const ar = xr[j], ai = xi[j];
        const sr = br + cr, si = bi + ci;
        const mr = ar - 0.5 * sr, mi = ai - 0.5 * si;
        const qr = h * (bi - ci), qi = -h * (br - cr); // -i sin(2pi/3) (b - c)
        const o = ob + jm;
        yr[o] = ar + sr; yi[o] = ai + si;
        yr[o + ns] = mr + qr; yi[o + ns] = mi + qi;
        yr[o + 2 * ns] = mr - qr; yi[o + 2 * ns] = mi - qi;
      }
    }
  }

  private radix5(st: Stage, xr: Float64Array, xi: Float64Array, yr: Float64Array, yi: Float64Array): void {
    const { ns, twr, twi } = st;
    const m = this.n / 5;
    const blocks = m / ns;
    const c1 = Math.cos((2 * Math.PI) / 5), c2 = Math.cos((4 * Math.PI) / 5);
    const s1 = Math.sin((2 * Math.PI) / 5), s2 = Math.sin((4 * Math.PI) / 5);
    for (let q = 0, j = 0; q < blocks; q++) {
      const ob = q * ns * 5;
      for (let jm = 0; jm < ns; jm++, j++) {
        let br = xr[j + m], bi = xi[j + m];
        let cr = xr[j + 2 * m], ci = xi[j + 2 * m];
        let dr = xr[j + 3 * m], di = xi[j + 3 * m];
        let er = xr[j + 4 * m], ei = xi[j + 4 * m];
        if (jm) {
          const t = 4 * jm;
          let c = twr[t], s = twi[t];
          const bt = br * c - bi * s; bi = br * s + bi * c; br = bt;
          c = twr[t + 1]; s = twi[t + 1];
          const ct = cr * c - ci * s; ci = cr * s + ci * c; cr = ct;
          c = twr[t + 2]; s = twi[t + 2];
          const dt = dr * c - di * s; di = dr * s + di * c; dr = dt;
          c = twr[t + 3]; s = twi[t + 3];
          const et = er * c - ei * s; ei = er * s + ei * c; er = et;
        }
        const ar = xr[j], ai = xi[j];
        const t1r = br + er, t1i = bi + ei, t3r = br - er, t3i = bi - ei;
        const t2r = cr + dr, t2i = ci + di, t4r = cr - dr, t4i = ci - di;
        const b1r = ar + c1 * t1r + c2 * t2r, b1i = ai + c1 * t1i + c2 * t2i;
        const b2r = ar + c2 * t1r + c1 * t2r, b2i = ai + c2 * t1i + c1 * t2i;
        // -i z for z = s1 t3 + s2 t4 (outputs 1 and 4) and z = s2 t3 - s1 t4 (outputs 2 and 3)
        const u1r = s1 * t3i + s2 * t4i, u1i = -(s1 * t3r + s2 * t4r);
        const u2r = s2 * t3i - s1 * t4i, u2i = -(s2 * t3r - s1 * t4r);
        const o = ob + jm;
        yr[o] = ar + t1r + t2r; yi[o] = ai + t1i + t2i;
        yr[o + ns] = b1r + u1r; yi[o + ns] = b1i + u1i;
        yr[o + 2 * ns] = b2r + u2r; yi[o + 2 * ns] = b2i + u2i;
        yr[o + 3 * ns] = b2r - u2r; yi[o + 3 * ns] = b2i - u2i;
        yr[o + 4 * ns] = b1r - u1r; yi[o + 4 * ns] = b1i - u1i;
      }
    }
  }

  /** An odd prime radix: twiddled inputs, then their length-R DFT with the symmetric pairs b, R - b
   * sharing each cosine and sine (a quarter of the products of the plain sum). As the first stage
   * (ns = 1) with an input zero outside [0, lo) and (n - lo, n), the pairs beyond lo are zeros. */
  private generic(st: Stage, xr: Float64Array, xi: Float64Array, yr: Float64Array, yi: Float64Array, lo: number): void {
    const { R, ns, twr, twi, cos, sin, quad } = st;
    const { n, vr, vi, pr, pi, mr, mi, pm } = this;
    const m = n / R;
    const blocks = m / ns;
    const h = (R - 1) >> 1;
    const pruned = ns === 1 && 2 * (lo + m) <= n;
    for (let q = 0, j = 0; q < blocks; q++) {
      const ob = q * ns * R;
      for (let jm = 0; jm < ns; jm++, j++) {
        // Pairs b with b m <= lo - 1 + j hold the nonzero inputs (j + b m < lo, or n - b m + j > n - lo).
        const used = pruned ? Math.min(h, Math.floor((lo - 1 + j) / m)) : h;
        if (jm) {
          const t = (R - 1) * jm;
          vr[0] = xr[j];
          vi[0] = xi[j];
          for (let r = 1; r < R; r++) {
            const x = xr[j + r * m], y = xi[j + r * m];
            const c = twr[t + r - 1], s = twi[t + r - 1];
            vr[r] = x * c - y * s;
            vi[r] = x * s + y * c;
          }
        } else {
          vr[0] = xr[j];
          vi[0] = xi[j];
          for (let b = 1; b <= used; b++) {
            vr[b] = xr[j + b * m]; vi[b] = xi[j + b * m];
            vr[R - b] = xr[j + (R - b) * m]; vi[R - b] = xi[j + (R - b) * m];
          }
        }
        let s0r = vr[0], s0i = vi[0];
        for (let b = 1; b <= used; b++) {
          const xr = vr[b] + vr[R - b], xi = vi[b] + vi[R - b];
          const zr = vr[b] - vr[R - b], zi = vi[b] - vi[R - b];
          pr[b] = xr; pi[b] = xi; mr[b] = zr; mi[b] = zi;
          const q = 4 * (b - 1);
          pm[q] = xr; pm[q + 1] = xi; pm[q + 2] = zr; pm[q + 3] = zi;
          s0r += xr; s0i += xi;
        }
        const o = ob + jm;
        yr[o] = s0r; yi[o] = s0i;
        const v0r = vr[0], v0i = vi[0];
        // Two outputs a, a + 1 a round: each load of the pairs serves both.
        let a = 1;
        for (; a < h; a += 2) {
          let ar = v0r, ai = v0i, br = 0, bi = 0;
          let cr = v0r, ci = v0i, dr = 0, di = 0;
          // Both rows' cosines and sines, and the pairs' sums and differences, four in a row.
          for (let b = 0, q = 4 * ((a - 1) >> 1) * h; b < 4 * used; b += 4, q += 4) {
            const xr = pm[b], xi = pm[b + 1], zr = pm[b + 2], zi = pm[b + 3];
            const c = quad[q], sn = quad[q + 1];
            const c2 = quad[q + 2], sn2 = quad[q + 3];
            ar += xr * c; ai += xi * c;
            br += zr * sn; bi += zi * sn;
            cr += xr * c2; ci += xi * c2;
            dr += zr * sn2; di += zi * sn2;
          }
          // y[a] = A - i B, y[R - a] = A + i B  (w = e^{-2 pi i / R})
          yr[o + a * ns] = ar + bi; yi[o + a * ns] = ai - br;
          yr[o + (R - a) * ns] = ar - bi; yi[o + (R - a) * ns] = ai + br;
          yr[o + (a + 1) * ns] = cr + di; yi[o + (a + 1) * ns] = ci - dr;
          yr[o + (R - a - 1) * ns] = cr - di; yi[o + (R - a - 1) * ns] = ci + dr;
        }
        if (a === h) {
          let ar = v0r, ai = v0i, br = 0, bi = 0;
          const row = (a - 1) * h - 1;
          for (let b = 1; b <= used; b++) {
            const c = cos[row + b], sn = sin[row + b];
            ar += pr[b] * c; ai += pi[b] * c;
            br += mr[b] * sn; bi += mi[b] * sn;
          }
          yr[o + a * ns] = ar + bi; yi[o + a * ns] = ai - br;
          yr[o + (R - a) * ns] = ar - bi; yi[o + (R - a) * ns] = ai + br;
        }
      }
    }
  }
}

const smooth = new Map<number, number>();

/** The length with small factors (2, 3, 5) at least n whose FFT costs least. */
function smoothAtLeast(n: number): number {
  let p = smooth.get(n);
  if (p === undefined) {
    p = searchSmooth(n);
    if (smooth.size > 256) smooth.clear();
    smooth.set(n, p);
  }
  return p;
}

function searchSmooth(n: number): number {
  let best = 0;
  let bestCost = Infinity;
  for (let p2 = 1; p2 < 2 * n; p2 *= 2) {
    for (let p3 = p2; p3 < 2 * n; p3 *= 3) {
      for (let p5 = p3; p5 < 2 * n; p5 *= 5) {
        if (p5 < n) continue;
        const c = mixedCost(p5, factorize(p5), p5);
        if (c < bestCost) {
          bestCost = c;
          best = p5;
        }
      }
    }
  }
  return best;
}

/** Forward DFT of length n by Bluestein's chirp-z: a linear convolution by an FFT of length P with
 * small factors. An input nonzero on a band of indices k in [-(lo - 1), lo - 1] (mod n) convolves
 * only those B = 2 lo - 1 entries, so that P >= n + B - 1 rather than 2 n - 1. */
export class BluesteinFft {
  readonly n: number;
  readonly P: number;
  readonly shift: number; // the band's first index is -shift
  readonly band: number;
  readonly fft: MixedFft;
  readonly cr: Float64Array; // e^{-i pi k^2 / n}, k = 0 .. n - 1
  readonly ci: Float64Array;
  readonly kr: Float64Array; // FFT of the conjugate chirp, over P
  readonly ki: Float64Array;
  private readonly ar: Float64Array;
  private readonly ai: Float64Array;

  constructor(n: number, lo: number) {
    this.n = n;
    const full = 2 * lo - 1 >= n;
    this.shift = full ? 0 : lo - 1;
    this.band = full ? n : 2 * lo - 1;
    const B = this.band;
    this.P = smoothAtLeast(n + B - 1);
    const P = this.P;
    this.fft = new MixedFft(P, factorize(P));
    this.cr = new Float64Array(n);
    this.ci = new Float64Array(n);
    for (let k = 0; k < n; k++) {
      const phase = (Math.PI * ((k * k) % (2 * n))) / n; // k^2 mod 2n keeps the phase exact
      this.cr[k] = Math.cos(phase);
      this.ci[k] = -Math.sin(phase);
    }
    // kernel[e] = e^{+i pi d^2 / n} for d = e - (B - 1 - shift), e = 0 .. n + B - 2, transformed and
    // over P (the inverse FFT's normalisation).
    this.kr = new Float64Array(P);
    this.ki = new Float64Array(P);
    const t = B - 1 - this.shift;
    for (let e = 0; e <= n + B - 2; e++) {
      const d = e - t;
      const phase = (Math.PI * ((d * d) % (2 * n))) / n;
      this.kr[e] = Math.cos(phase) / P;
      this.ki[e] = Math.sin(phase) / P;
    }
    this.fft.forward(this.kr, this.ki, P);
    this.ar = new Float64Array(P);
    this.ai = new Float64Array(P);
  }

  forward(re: Float64Array, im: Float64Array): void {
    const { n, P, shift, band, cr, ci, kr, ki, ar, ai } = this;
    ar.fill(0);
    ai.fill(0);
    // a[k + shift] = x[k mod n] e^{-i pi k^2 / n} over the band.
    for (let q = 0; q < band; q++) {
      const k = q - shift;
      const i = k < 0 ? k + n : k;
      const c = k < 0 ? -k : k;
      const x = re[i], y = im[i];
      ar[q] = x * cr[c] - y * ci[c];
      ai[q] = x * ci[c] + y * cr[c];
    }
    this.fft.forward(ar, ai, P);
    // The inverse FFT of the product as the conjugate of the forward FFT of its conjugate.
    for (let k = 0; k < P; k++) {
      const x = ar[k], y = ai[k];
      ar[k] = x * kr[k] - y * ki[k];
      ai[k] = -(x * ki[k] + y * kr[k]);
    }
    this.fft.forward(ar, ai, P);
    const at = band - 1;
    for (let m = 0; m < n; m++) {
      const x = ar[m + at], y = -ai[m + at];
      re[m] = x * cr[m] - y * ci[m];
      im[m] = x * ci[m] + y * cr[m];
    }
  }

  static cost(n: number, lo: number): number {
    const P = smoothAtLeast(n + Math.min(2 * lo - 1, n) - 1);
    return 2 * mixedCost(P, factorize(P), P) + 8 * P + 12 * n;
  }
}

/** Forward DFT of length n for inputs on a band of half-width lo: the mixed-radix FFT or Bluestein's,
 * whichever costs less for that band. */
export class Fft {
  readonly n: number;
  private readonly stages: number[];
  private readonly mixed: MixedFft | null;
  private readonly chirps = new Map<number, BluesteinFft>();

  constructor(n: number) {
    this.n = n;
    this.stages = factorize(n);
    this.mixed = this.stages.every((R) => R <= MAX_MIXED_RADIX) ? new MixedFft(n, this.stages) : null;
  }

  /** Mixed radix for this band, or Bluestein's. */
  pick(lo: number): MixedFft | BluesteinFft {
    const mixed = this.mixed && mixedCost(this.n, this.stages, lo) <= BluesteinFft.cost(this.n, lo);
    if (mixed) return this.mixed!;
    // Bands rounded up to a sixteenth of n: a few kernels per length, not one per band.
    const q = Math.max(1, Math.ceil(this.n / 16));
    const key = Math.min(Math.ceil(this.n / 2), Math.ceil(lo / q) * q);
    let b = this.chirps.get(key);
    if (!b) {
      if (this.chirps.size >= 17) this.chirps.clear();
      b = new BluesteinFft(this.n, key);
      this.chirps.set(key, b);
    }
    return b;
  }

  forward(re: Float64Array, im: Float64Array, lo: number): void {
    const f = this.pick(lo);
    if (f instanceof MixedFft) f.forward(re, im, lo);
    else f.forward(re, im);
  }

  cost(lo: number): number {
    const b = BluesteinFft.cost(this.n, lo);
    return this.mixed ? Math.min(mixedCost(this.n, this.stages, lo), b) : b;
  }
}

/** Radices above this go through Bluestein's FFT whatever the band (a generic radix costs R flops a
 * point; the tables of R^2 / 4 entries grow too). */
const MAX_MIXED_RADIX = 257;

/** Orthonormal DCT-III (scipy's idct(type=2, norm="ortho")) of length n, two real vectors at once. */
export class Dct3 {
  readonly n: number;
  readonly fft: Fft;
  // e^{i pi k / 2n} with the DCT's scale for X[k] (A) and for X[n - k] (B, never the DC term), over n.
  readonly car: Float64Array;
  readonly sar: Float64Array;
  readonly cb: Float64Array;
  readonly sb: Float64Array;
  private readonly re: Float64Array;
  private readonly im: Float64Array;

  constructor(n: number) {
    this.n = n;
    this.fft = new Fft(n);
    this.car = new Float64Array(n);
    this.sar = new Float64Array(n);
    this.cb = new Float64Array(n);
    this.sb = new Float64Array(n);
    const s0 = Math.sqrt(n) / n;
    const sk = Math.sqrt(n / 2) / n;
    for (let k = 0; k < n; k++) {
      const c = Math.cos((Math.PI * k) / (2 * n));
      const s = Math.sin((Math.PI * k) / (2 * n));
      const f = k === 0 ? s0 : sk;
      this.car[k] = c * f;
      this.sar[k] = s * f;
      this.cb[k] = c * sk;
      this.sb[k] = s * sk;
    }
    this.re = new Float64Array(n);
    this.im = new Float64Array(n);
  }

  /** Flops of one call for vectors of at most klen coefficients. */
  cost(klen: number): number {
    return this.fft.cost(Math.min(klen, this.n)) + 10 * this.n;
  }

  /**
   * out[o + (at - c0) * os] += DCT-III(x)[at] for at in [c0, c0 + w), for one or two vectors: x1 is
   * inp[i1 + k * is] for k < klen (zeros beyond), its output at offset o1; x2 likewise at i2 and o2
   * when i2 >= 0.
   */
  run(inp: Float64Array, i1: number, i2: number, is: number, klen: number,
    out: Float64Array, o1: number, o2: number, os: number, c0: number, w: number): void {
    const { n, car, sar, cb, sb, re, im } = this;
    const two = i2 >= 0;
    const K = Math.min(klen, n);
    // W = conj(V1 + i V2), V = e^{i pi k / 2n} (X[k] - i X[n-k]): nonzero on k < K and k > n - K, so
    // that the forward FFT computes the inverse one.
    // Only the entries between the two ends of the band are zeros; the ends are set below.
    if (2 * K - 1 < n) {
      re.fill(0, K, n - K + 1);
      im.fill(0, K, n - K + 1);
    } else {
      re.fill(0);
      im.fill(0);
    }
    for (let k = 0; k < K; k++) {
      const a1 = inp[i1 + k * is];
      const a2 = two ? inp[i2 + k * is] : 0;
      re[k] = a1 * car[k] - a2 * sar[k];
      im[k] = -(a1 * sar[k] + a2 * car[k]);
    }
    if (2 * K - 1 < n) {
      // The two ends apart: the upper one is set, not added to.
      for (let j = 1; j < K; j++) {
        const k = n - j;
        const b1 = inp[i1 + j * is];
        const b2 = two ? inp[i2 + j * is] : 0;
        re[k] = b1 * sb[k] + b2 * cb[k];
        im[k] = b1 * cb[k] - b2 * sb[k];
      }
    } else {
      for (let j = 1; j < K; j++) {
        // X[n - k] with n - k = j: at k = n - j.
        const k = n - j;
        const b1 = inp[i1 + j * is];
        const b2 = two ? inp[i2 + j * is] : 0;
        // v1 = (b1 s, -b1 c), v2 = (b2 s, -b2 c): re += v1r - v2i, im -= v1i + v2r.
        re[k] += b1 * sb[k] + b2 * cb[k];
        im[k] -= -b1 * cb[k] + b2 * sb[k];
      }
    }
    this.fft.forward(re, im, K);
    // Cell 2m is entry m, cell 2(n - 1 - m) + 1 entry m: the even cells, then the odd ones.
    const end = c0 + w;
    const step = 2 * os;
    const even = c0 + (c0 & 1);
    const odd = c0 + 1 - (c0 & 1);
    if (two && os === 1 && c0 === 0 && w === n && (n & 1) === 0) {
      // The whole of contiguous vectors: cells 2i and 2i + 1 from entries i and n - 1 - i, in one sweep.
      for (let i = 0, p1 = o1, p2 = o2, q = n - 1; i < n / 2; i++, p1 += 2, p2 += 2, q--) {
        out[p1] += re[i];
        out[p2] -= im[i];
        out[p1 + 1] += re[q];
        out[p2 + 1] -= im[q];
      }
    } else if (two) {
      for (let at = even, m = even >> 1, p = (even - c0) * os; at < end; at += 2, m++, p += step) {
        out[o1 + p] += re[m];
        out[o2 + p] -= im[m];
      }
      for (let at = odd, m = n - 1 - ((odd - 1) >> 1), p = (odd - c0) * os; at < end; at += 2, m--, p += step) {
        out[o1 + p] += re[m];
        out[o2 + p] -= im[m];
      }
    } else {
      for (let at = even, m = even >> 1, p = o1 + (even - c0) * os; at < end; at += 2, m++, p += step) out[p] += re[m];
      for (let at = odd, m = n - 1 - ((odd - 1) >> 1), p = o1 + (odd - c0) * os; at < end; at += 2, m--, p += step) out[p] += re[m];
    }
  }
}
