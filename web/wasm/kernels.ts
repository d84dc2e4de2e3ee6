// AssemblyScript: the hot loops of the inverse DCT (src/dct.ts) and of the finishing pass
// (src/decode.ts finishWindow) in WebAssembly SIMD, two transforms a call in the two lanes of an
// f64x2 (four real vectors: each lane a complex FFT of two, as Dct3.run pairs them). Each kernel does
// the TypeScript one's operations in its order, lane by lane (no fused multiply-add), so that both
// paths give the same bits; the tables (twiddles, chirps, constants) are computed by the TypeScript
// plans and copied here by src/wasm.ts, which also owns the memory (no allocator in this module).
// A lane array holds element k of both lanes at p + 16 k; a table holds f64 scalars at p + 8 k.

// @ts-ignore: decorator
@inline function ld(p: usize, k: i32): v128 { return v128.load(p + (<usize>k << 4)); }
// @ts-ignore: decorator
@inline function st(p: usize, k: i32, v: v128): void { v128.store(p + (<usize>k << 4), v); }
// @ts-ignore: decorator
@inline function sp(p: usize, k: i32): v128 { return v128.load64_splat(p + (<usize>k << 3)); }
// @ts-ignore: decorator
@inline function add(a: v128, b: v128): v128 { return f64x2.add(a, b); }
// @ts-ignore: decorator
@inline function sub(a: v128, b: v128): v128 { return f64x2.sub(a, b); }
// @ts-ignore: decorator
@inline function mul(a: v128, b: v128): v128 { return f64x2.mul(a, b); }
// @ts-ignore: decorator
@inline function neg(a: v128): v128 { return f64x2.neg(a); }
// @ts-ignore: decorator
@inline function word(p: usize, k: i32): i32 { return load<i32>(p + (<usize>k << 2)); }

/** Constants computed by JavaScript's Math (set by src/wasm.ts): sqrt(3) / 2, then cos(2 pi / 5),
 * cos(4 pi / 5), sin(2 pi / 5), sin(4 pi / 5). */
let consts: usize = 0;

export function setConstants(p: usize): void {
  consts = p;
}

function radix4(n: i32, ns: i32, twr: usize, twi: usize, xr: usize, xi: usize, yr: usize, yi: usize): void {
  const m = n >> 2;
  const blocks = m / ns;
  let j = 0;
  for (let q = 0; q < blocks; q++) {
    const ob = q * ns * 4;
    for (let jm = 0; jm < ns; jm++, j++) {
      const ar = ld(xr, j), ai = ld(xi, j);
      let br = ld(xr, j + m), bi = ld(xi, j + m);
      let cr = ld(xr, j + 2 * m), ci = ld(xi, j + 2 * m);
      let dr = ld(xr, j + 3 * m), di = ld(xi, j + 3 * m);
      if (jm) {
        const t = 3 * jm;
        let c = sp(twr, t), s = sp(twi, t);
        const bt = sub(mul(br, c), mul(bi, s)); bi = add(mul(br, s), mul(bi, c)); br = bt;
        c = sp(twr, t + 1); s = sp(twi, t + 1);
        const ct = sub(mul(cr, c), mul(ci, s)); ci = add(mul(cr, s), mul(ci, c)); cr = ct;
        c = sp(twr, t + 2); s = sp(twi, t + 2);
        const dt = sub(mul(dr, c), mul(di, s)); di = add(mul(dr, s), mul(di, c)); dr = dt;
      }
      const s0r = add(ar, cr), s0i = add(ai, ci), d0r = sub(ar, cr), d0i = sub(ai, ci);
      const s1r = add(br, dr), s1i = add(bi, di), d1r = sub(br, dr), d1i = sub(bi, di);
      const o = ob + jm;
      st(yr, o, add(s0r, s1r)); st(yi, o, add(s0i, s1i));
      st(yr, o + ns, add(d0r, d1i)); st(yi, o + ns, sub(d0i, d1r));
      st(yr, o + 2 * ns, sub(s0r, s1r)); st(yi, o + 2 * ns, sub(s0i, s1i));
      st(yr, o + 3 * ns, sub(d0r, d1i)); st(yi, o + 3 * ns, add(d0i, d1r));
    }
  }
}

function radix2(n: i32, ns: i32, twr: usize, twi: usize, xr: usize, xi: usize, yr: usize, yi: usize): void {
  const m = n >> 1;
  const blocks = m / ns;
  let j = 0;
  for (let q = 0; q < blocks; q++) {
    const ob = q * ns * 2;
    for (let jm = 0; jm < ns; jm++, j++) {
      let br = ld(xr, j + m), bi = ld(xi, j + m);
      if (jm) {
        const c = sp(twr, jm), s = sp(twi, jm);
        const bt = sub(mul(br, c), mul(bi, s)); bi = add(mul(br, s), mul(bi, c)); br = bt;
      }
      const ar = ld(xr, j), ai = ld(xi, j);
      const o = ob + jm;
      st(yr, o, add(ar, br)); st(yi, o, add(ai, bi));
      st(yr, o + ns, sub(ar, br)); st(yi, o + ns, sub(ai, bi));
    }
  }
}

function radix3(n: i32, ns: i32, twr: usize, twi: usize, xr: usize, xi: usize, yr: usize, yi: usize): void {
  const m = n / 3;
  const blocks = m / ns;
  const h = sp(consts, 0);
  const mh = neg(h);
  const half = f64x2.splat(0.5);
  let j = 0;
  for (let q = 0; q < blocks; q++) {
    const ob = q * ns * 3;
    for (let jm = 0; jm < ns; jm++, j++) {
      let br = ld(xr, j + m), bi = ld(xi, j + m);
      let cr = ld(xr, j + 2 * m), ci = ld(xi, j + 2 * m);
      if (jm) {
        const t = 2 * jm;
        let c = sp(twr, t), s = sp(twi, t);
        const bt = sub(mul(br, c), mul(bi, s)); bi = add(mul(br, s), mul(bi, c)); br = bt;
        c = sp(twr, t + 1); s = sp(twi, t + 1);
        const ct = sub(mul(cr, c), mul(ci, s)); ci = add(mul(cr, s), mul(ci, c)); cr = ct;
      }
      const ar = ld(xr, j), ai = ld(xi, j);
      const sr = add(br, cr), si = add(bi, ci);
      const mr = sub(ar, mul(half, sr)), mi = sub(ai, mul(half, si));
      const qr = mul(h, sub(bi, ci)), qi = mul(mh, sub(br, cr));
      const o = ob + jm;
      st(yr, o, add(ar, sr)); st(yi, o, add(ai, si));
      st(yr, o + ns, add(mr, qr)); st(yi, o + ns, add(mi, qi));
      st(yr, o + 2 * ns, sub(mr, qr)); st(yi, o + 2 * ns, sub(mi, qi));
    }
  }
}

function radix5(n: i32, ns: i32, twr: usize, twi: usize, xr: usize, xi: usize, yr: usize, yi: usize): void {
  const m = n / 5;
  const blocks = m / ns;
  const c1 = sp(consts, 1), c2 = sp(consts, 2), s1 = sp(consts, 3), s2 = sp(consts, 4);
  let j = 0;
  for (let q = 0; q < blocks; q++) {
    const ob = q * ns * 5;
    for (let jm = 0; jm < ns; jm++, j++) {
      let br = ld(xr, j + m), bi = ld(xi, j + m);
      let cr = ld(xr, j + 2 * m), ci = ld(xi, j + 2 * m);
      let dr = ld(xr, j + 3 * m), di = ld(xi, j + 3 * m);
      let er = ld(xr, j + 4 * m), ei = ld(xi, j + 4 * m);
      if (jm) {
        const t = 4 * jm;
        let c = sp(twr, t), s = sp(twi, t);
        const bt = sub(mul(br, c), mul(bi, s)); bi = add(mul(br, s), mul(bi, c)); br = bt;
        c = sp(twr, t + 1); s = sp(twi, t + 1);
        const ct = sub(mul(cr, c), mul(ci, s)); ci = add(mul(cr, s), mul(ci, c)); cr = ct;
        c = sp(twr, t + 2); s = sp(twi, t + 2);
        const dt = sub(mul(dr, c), mul(di, s)); di = add(mul(dr, s), mul(di, c)); dr = dt;
        c = sp(twr, t + 3); s = sp(twi, t + 3);
        const et = sub(mul(er, c), mul(ei, s)); ei = add(mul(er, s), mul(ei, c)); er = et;
      }
      const ar = ld(xr, j), ai = ld(xi, j);
      const t1r = add(br, er), t1i = add(bi, ei), t3r = sub(br, er), t3i = sub(bi, ei);
      const t2r = add(cr, dr), t2i = add(ci, di), t4r = sub(cr, dr), t4i = sub(ci, di);
      const b1r = add(add(ar, mul(c1, t1r)), mul(c2, t2r)), b1i = add(add(ai, mul(c1, t1i)), mul(c2, t2i));
      const b2r = add(add(ar, mul(c2, t1r)), mul(c1, t2r)), b2i = add(add(ai, mul(c2, t1i)), mul(c1, t2i));
      const u1r = add(mul(s1, t3i), mul(s2, t4i)), u1i = neg(add(mul(s1, t3r), mul(s2, t4r)));
      const u2r = sub(mul(s2, t3i), mul(s1, t4i)), u2i = neg(sub(mul(s2, t3r), mul(s1, t4r)));
      const o = ob + jm;
      st(yr, o, add(add(ar, t1r), t2r)); st(yi, o, add(add(ai, t1i), t2i));
      st(yr, o + ns, add(b1r, u1r)); st(yi, o + ns, add(b1i, u1i));
      st(yr, o + 2 * ns, add(b2r, u2r)); st(yi, o + 2 * ns, add(b2i, u2i));
      st(yr, o + 3 * ns, sub(b2r, u2r)); st(yi, o + 3 * ns, sub(b2i, u2i));
      st(yr, o + 4 * ns, sub(b1r, u1r)); st(yi, o + 4 * ns, sub(b1i, u1i));
    }
  }
}

/** An odd prime radix (MixedFft.generic): scr holds the scratch lane arrays vr, vi, pr, pi, mr, mi
 * (R entries each) and pm (4 R) at words 4 .. 10 of the plan. */
function generic(n: i32, R: i32, ns: i32, twr: usize, twi: usize, cos: usize, sin: usize, quad: usize,
  xr: usize, xi: usize, yr: usize, yi: usize, lo: i32, plan: usize): void {
  const vr = <usize>word(plan, 4), vi = <usize>word(plan, 5);
  const pr = <usize>word(plan, 6), pi = <usize>word(plan, 7);
  const mr = <usize>word(plan, 8), mi = <usize>word(plan, 9);
  const pm = <usize>word(plan, 10);
  const m = n / R;
  const blocks = m / ns;
  const h = (R - 1) >> 1;
  const pruned = ns == 1 && 2 * (lo + m) <= n;
  const zero = f64x2.splat(0);
  let j = 0;
  for (let q = 0; q < blocks; q++) {
    const ob = q * ns * R;
    for (let jm = 0; jm < ns; jm++, j++) {
      const used = pruned ? min(h, (lo - 1 + j) / m) : h;
      if (jm) {
        const t = (R - 1) * jm;
        st(vr, 0, ld(xr, j));
        st(vi, 0, ld(xi, j));
        for (let r = 1; r < R; r++) {
          const x = ld(xr, j + r * m), y = ld(xi, j + r * m);
          const c = sp(twr, t + r - 1), s = sp(twi, t + r - 1);
          st(vr, r, sub(mul(x, c), mul(y, s)));
          st(vi, r, add(mul(x, s), mul(y, c)));
        }
      } else {
        st(vr, 0, ld(xr, j));
        st(vi, 0, ld(xi, j));
        for (let b = 1; b <= used; b++) {
          st(vr, b, ld(xr, j + b * m)); st(vi, b, ld(xi, j + b * m));
          st(vr, R - b, ld(xr, j + (R - b) * m)); st(vi, R - b, ld(xi, j + (R - b) * m));
        }
      }
      let s0r = ld(vr, 0), s0i = ld(vi, 0);
      for (let b = 1; b <= used; b++) {
        const sr = add(ld(vr, b), ld(vr, R - b)), si = add(ld(vi, b), ld(vi, R - b));
        const zr = sub(ld(vr, b), ld(vr, R - b)), zi = sub(ld(vi, b), ld(vi, R - b));
        st(pr, b, sr); st(pi, b, si); st(mr, b, zr); st(mi, b, zi);
        const k = 4 * (b - 1);
        st(pm, k, sr); st(pm, k + 1, si); st(pm, k + 2, zr); st(pm, k + 3, zi);
        s0r = add(s0r, sr); s0i = add(s0i, si);
      }
      const o = ob + jm;
      st(yr, o, s0r); st(yi, o, s0i);
      const v0r = ld(vr, 0), v0i = ld(vi, 0);
      let a = 1;
      for (; a < h; a += 2) {
        let ar = v0r, ai = v0i, br = zero, bi = zero;
        let cr = v0r, ci = v0i, dr = zero, di = zero;
        for (let b = 0, k = 4 * ((a - 1) >> 1) * h; b < 4 * used; b += 4, k += 4) {
          const xr = ld(pm, b), xi = ld(pm, b + 1), zr = ld(pm, b + 2), zi = ld(pm, b + 3);
          const c = sp(quad, k), sn = sp(quad, k + 1);
          const c2 = sp(quad, k + 2), sn2 = sp(quad, k + 3);
          ar = add(ar, mul(xr, c)); ai = add(ai, mul(xi, c));
          br = add(br, mul(zr, sn)); bi = add(bi, mul(zi, sn));
          cr = add(cr, mul(xr, c2)); ci = add(ci, mul(xi, c2));
          dr = add(dr, mul(zr, sn2)); di = add(di, mul(zi, sn2));
        }
        st(yr, o + a * ns, add(ar, bi)); st(yi, o + a * ns, sub(ai, br));
        st(yr, o + (R - a) * ns, sub(ar, bi)); st(yi, o + (R - a) * ns, add(ai, br));
        st(yr, o + (a + 1) * ns, add(cr, di)); st(yi, o + (a + 1) * ns, sub(ci, dr));
        st(yr, o + (R - a - 1) * ns, sub(cr, di)); st(yi, o + (R - a - 1) * ns, add(ci, dr));
      }
      if (a == h) {
        let ar = v0r, ai = v0i, br = zero, bi = zero;
        const row = (a - 1) * h - 1;
        for (let b = 1; b <= used; b++) {
          const c = sp(cos, row + b), sn = sp(sin, row + b);
          ar = add(ar, mul(ld(pr, b), c)); ai = add(ai, mul(ld(pi, b), c));
          br = add(br, mul(ld(mr, b), sn)); bi = add(bi, mul(ld(mi, b), sn));
        }
        st(yr, o + a * ns, add(ar, bi)); st(yi, o + a * ns, sub(ai, br));
        st(yr, o + (R - a) * ns, sub(ar, bi)); st(yi, o + (R - a) * ns, add(ai, br));
      }
    }
  }
}

/**
 * MixedFft.forward on lane arrays (re, im) of the plan's length, in place. The plan's words: n,
 * stages, br, bi (lane buffers), vr, vi, pr, pi, mr, mi, pm (a generic radix's scratch), unused;
 * then per stage R, ns, twr, twi, cos, sin, quad, unused.
 */
export function mixedForward(plan: usize, re: usize, im: usize, lo: i32): void {
  const n = word(plan, 0);
  const stages = word(plan, 1);
  let xr = re, xi = im;
  let yr = <usize>word(plan, 2), yi = <usize>word(plan, 3);
  for (let s = 0; s < stages; s++) {
    const p = plan + 48 + 32 * <usize>s;
    const R = word(p, 0), ns = word(p, 1);
    const twr = <usize>word(p, 2), twi = <usize>word(p, 3);
    if (R == 4) radix4(n, ns, twr, twi, xr, xi, yr, yi);
    else if (R == 2) radix2(n, ns, twr, twi, xr, xi, yr, yi);
    else if (R == 3) radix3(n, ns, twr, twi, xr, xi, yr, yi);
    else if (R == 5) radix5(n, ns, twr, twi, xr, xi, yr, yi);
    else generic(n, R, ns, twr, twi, <usize>word(p, 4), <usize>word(p, 5), <usize>word(p, 6), xr, xi, yr, yi, s == 0 ? lo : n, plan);
    const tr = xr; xr = yr; yr = tr;
    const ti = xi; xi = yi; yi = ti;
  }
  if (xr != re) {
    memory.copy(re, xr, <usize>n << 4);
    memory.copy(im, xi, <usize>n << 4);
  }
}

/** BluesteinFft.forward on lane arrays. The plan's words: n, P, shift, band, cr, ci, kr, ki (tables),
 * ar, ai (lane buffers of P), the MixedFft plan of length P. */
export function bluesteinForward(plan: usize, re: usize, im: usize): void {
  const n = word(plan, 0), P = word(plan, 1), shift = word(plan, 2), band = word(plan, 3);
  const cr = <usize>word(plan, 4), ci = <usize>word(plan, 5), kr = <usize>word(plan, 6), ki = <usize>word(plan, 7);
  const ar = <usize>word(plan, 8), ai = <usize>word(plan, 9), fft = <usize>word(plan, 10);
  memory.fill(ar, 0, <usize>P << 4);
  memory.fill(ai, 0, <usize>P << 4);
  for (let q = 0; q < band; q++) {
    const k = q - shift;
    const i = k < 0 ? k + n : k;
    const c = k < 0 ? -k : k;
    const x = ld(re, i), y = ld(im, i);
    const a = sp(cr, c), b = sp(ci, c);
    st(ar, q, sub(mul(x, a), mul(y, b)));
    st(ai, q, add(mul(x, b), mul(y, a)));
  }
  mixedForward(fft, ar, ai, P);
  for (let k = 0; k < P; k++) {
    const x = ld(ar, k), y = ld(ai, k);
    const a = sp(kr, k), b = sp(ki, k);
    st(ar, k, sub(mul(x, a), mul(y, b)));
    st(ai, k, neg(add(mul(x, b), mul(y, a))));
  }
  mixedForward(fft, ar, ai, P);
  const at = band - 1;
  for (let m = 0; m < n; m++) {
    const x = ld(ar, m + at), y = neg(ld(ai, m + at));
    const a = sp(cr, m), b = sp(ci, m);
    st(re, m, sub(mul(x, a), mul(y, b)));
    st(im, m, add(mul(x, b), mul(y, a)));
  }
}

// @ts-ignore: decorator
@inline function at(p: usize, i: i32, off: i32): f64 {
  return i < 0 ? 0.0 : load<f64>(p + (<usize>(i + off) << 3));
}

// @ts-ignore: decorator
@inline function lanes(p: usize, i: i32, j: i32, off: i32): v128 {
  return f64x2.replace_lane(f64x2.splat(at(p, i, off)), 1, at(p, j, off));
}

/**
 * Dct3.run for four vectors: lane 0 pairs the vectors at element offsets i0, i1 of inp (element
 * stride is), lane 1 those at i2, i3 (-1: a vector of zeros); their outputs go to o0 .. o3 of out
 * (element stride os; -1: not written). K: the coefficients read (min(klen, n)). fft: a MixedFft
 * plan (bluestein 0, pruned to the band lo = K) or a BluesteinFft plan (bluestein 1). The Dct3
 * plan's words: n, car, sar, cb, sb (tables), re, im (lane buffers).
 */
// One cell of dctGroup's fused finishing pass, as finish() does it: its height from the transform's
// output h and the plane at (row, col), NaN where the mask is empty, stored at cell k and returned.
// With a residual layer (res: its grid of q 2 e (1 - 1e-6), f64 a cell; 0: none) as decode.ts sums
// it: the plane first when `plane` is 1, then the residual, then z0 as finishWindow adds it without
// a plane (z0 + (0 + 0 row) + 0 col).
@inline function finishCell(k: i32, h: f64, row: f64, col: f64, z0: f64, a: f64, b: f64, c: f64, mask: usize,
                            hts: usize, f32: i32, res: usize, plane: i32): f64 {
  let z = NaN;
  if (load<u8>(mask + <usize>k)) {
    if (res) {
      let x = h;
      if (plane) x = x + ((a + c * row) + b * col);
      x = x + load<f64>(res + (<usize>k << 3));
      z = x + ((z0 + (0.0 + 0.0 * row)) + 0.0 * col);
    } else {
      z = h + ((z0 + (a + c * row)) + b * col);
    }
  }
  if (f32) store<f32>(hts + (<usize>k << 2), <f32>z);
  else store<f64>(hts + (<usize>k << 3), z);
  return z;
}

export function dctGroup(dct: usize, bluestein: i32, fft: usize, inp: usize, i0: i32, i1: i32, i2: i32, i3: i32,
  is: i32, K: i32, out: usize, o0: i32, o1: i32, o2: i32, o3: i32, os: i32, c0: i32, w: i32, fin: usize): void {
  const n = word(dct, 0);
  const car = <usize>word(dct, 1), sar = <usize>word(dct, 2), cb = <usize>word(dct, 3), sb = <usize>word(dct, 4);
  const re = <usize>word(dct, 5), im = <usize>word(dct, 6);
  const narrow = 2 * K - 1 < n;
  if (narrow) {
    memory.fill(re + (<usize>K << 4), 0, <usize>(n - 2 * K + 1) << 4);
    memory.fill(im + (<usize>K << 4), 0, <usize>(n - 2 * K + 1) << 4);
  } else {
    memory.fill(re, 0, <usize>n << 4);
    memory.fill(im, 0, <usize>n << 4);
  }
  // Four adjacent vectors (columns of a row-major array): two loads a row, lanes shuffled.
  const adjacent = i0 >= 0 && i1 == i0 + 1 && i2 == i0 + 2 && i3 == i0 + 3;
  for (let k = 0; k < K; k++) {
    let a1: v128, a2: v128;
    if (adjacent) {
      const p = inp + (<usize>(i0 + k * is) << 3);
      const x = v128.load(p), y = v128.load(p, 16);
      a1 = i64x2.shuffle(x, y, 0, 2);
      a2 = i64x2.shuffle(x, y, 1, 3);
    } else {
      a1 = lanes(inp, i0, i2, k * is);
      a2 = lanes(inp, i1, i3, k * is);
    }
    const c = sp(car, k), s = sp(sar, k);
    st(re, k, sub(mul(a1, c), mul(a2, s)));
    st(im, k, neg(add(mul(a1, s), mul(a2, c))));
  }
  if (narrow) {
    for (let j = 1; j < K; j++) {
      const k = n - j;
      let b1: v128, b2: v128;
      if (adjacent) {
        const p = inp + (<usize>(i0 + j * is) << 3);
        const x = v128.load(p), y = v128.load(p, 16);
        b1 = i64x2.shuffle(x, y, 0, 2);
        b2 = i64x2.shuffle(x, y, 1, 3);
      } else {
        b1 = lanes(inp, i0, i2, j * is);
        b2 = lanes(inp, i1, i3, j * is);
      }
      const c = sp(cb, k), s = sp(sb, k);
      st(re, k, add(mul(b1, s), mul(b2, c)));
      st(im, k, sub(mul(b1, c), mul(b2, s)));
    }
  } else {
    for (let j = 1; j < K; j++) {
      const k = n - j;
      const b1 = lanes(inp, i0, i2, j * is), b2 = lanes(inp, i1, i3, j * is);
      const c = sp(cb, k), s = sp(sb, k);
      st(re, k, add(ld(re, k), add(mul(b1, s), mul(b2, c))));
      st(im, k, sub(ld(im, k), add(mul(neg(b1), c), mul(b2, s))));
    }
  }
  if (bluestein) bluesteinForward(fft, re, im);
  else mixedForward(fft, re, im, K);
  // Cell 2m is entry m, cell 2(n - 1 - m) + 1 entry m.
  const end = c0 + w;
  if (fin) {
    // The finishing pass on the outputs as they come (each cell once, out as zeros: 0 + x, as the
    // TypeScript path adds x to a grid of zeros), then finish()'s operations.
    const z0 = load<f64>(fin), a = load<f64>(fin, 8), b = load<f64>(fin, 16), c = load<f64>(fin, 24);
    let lo = load<f64>(fin, 32), hi = load<f64>(fin, 40);
    const mask = <usize>load<i32>(fin, 48), hts = <usize>load<i32>(fin, 52), f32 = load<i32>(fin, 56);
    const cols = load<i32>(fin, 60), down = load<i32>(fin, 68);
    const res = <usize>load<i32>(fin, 72), plane = load<i32>(fin, 76);
    let cells = load<i32>(fin, 64);
    const r0 = o0 >= 0 ? o0 / cols : 0, q0 = o0 >= 0 ? o0 - r0 * cols : 0;
    const r1 = o1 >= 0 ? o1 / cols : 0, q1 = o1 >= 0 ? o1 - r1 * cols : 0;
    const r2 = o2 >= 0 ? o2 / cols : 0, q2 = o2 >= 0 ? o2 - r2 * cols : 0;
    const r3 = o3 >= 0 ? o3 / cols : 0, q3 = o3 >= 0 ? o3 - r3 * cols : 0;
    if (!res && o0 >= 0 && o1 >= 0 && o2 >= 0 && o3 >= 0) {
      // All four outputs: the pairs' lanes as they are, outputs o0 and o2 (0 + re) in A, o1 and o3
      // (0 - im) in B; rows and columns as exact f64 integers stepped by the cell (down: the rows).
      const zero = f64x2.splat(0), one = f64x2.splat(1);
      const z0v = f64x2.splat(z0), av = f64x2.splat(a), bv = f64x2.splat(b), cv = f64x2.splat(c);
      const inf = f64x2.splat(Infinity), minf = f64x2.splat(-Infinity), nan = f64x2.splat(NaN);
      const dr = down ? one : zero, dq = down ? zero : one;
      let rA = f64x2.replace_lane(f64x2.splat(<f64>r0), 1, <f64>r2), qA = f64x2.replace_lane(f64x2.splat(<f64>q0), 1, <f64>q2);
      let rB = f64x2.replace_lane(f64x2.splat(<f64>r1), 1, <f64>r3), qB = f64x2.replace_lane(f64x2.splat(<f64>q1), 1, <f64>q3);
      let loV = inf, hiV = minf;
      for (let cell = c0, p = 0; cell < end; cell++, p += os) {
        const m = cell & 1 ? n - 1 - ((cell - 1) >> 1) : cell >> 1;
        const zA = add(add(zero, ld(re, m)), add(add(z0v, add(av, mul(cv, rA))), mul(bv, qA)));
        const zB = add(sub(zero, ld(im, m)), add(add(z0v, add(av, mul(cv, rB))), mul(bv, qB)));
        const k0 = o0 + p, k1 = o1 + p, k2 = o2 + p, k3 = o3 + p;
        const m0 = load<u8>(mask + <usize>k0), m1 = load<u8>(mask + <usize>k1);
        const m2 = load<u8>(mask + <usize>k2), m3 = load<u8>(mask + <usize>k3);
        const sA = i64x2.replace_lane(i64x2.splat(m0 ? -1 : 0), 1, m2 ? -1 : 0);
        const sB = i64x2.replace_lane(i64x2.splat(m1 ? -1 : 0), 1, m3 ? -1 : 0);
        cells += <i32>(m0 != 0) + <i32>(m1 != 0) + <i32>(m2 != 0) + <i32>(m3 != 0);
        loV = f64x2.min(f64x2.min(loV, v128.bitselect(zA, inf, sA)), v128.bitselect(zB, inf, sB));
        hiV = f64x2.max(f64x2.max(hiV, v128.bitselect(zA, minf, sA)), v128.bitselect(zB, minf, sB));
        const vA = v128.bitselect(zA, nan, sA), vB = v128.bitselect(zB, nan, sB);
        if (f32) {
          const fA = f32x4.demote_f64x2_zero(vA), fB = f32x4.demote_f64x2_zero(vB);
          v128.store32_lane(hts + (<usize>k0 << 2), fA, 0);
          v128.store32_lane(hts + (<usize>k2 << 2), fA, 1);
          v128.store32_lane(hts + (<usize>k1 << 2), fB, 0);
          v128.store32_lane(hts + (<usize>k3 << 2), fB, 1);
        } else {
          v128.store64_lane(hts + (<usize>k0 << 3), vA, 0);
          v128.store64_lane(hts + (<usize>k2 << 3), vA, 1);
          v128.store64_lane(hts + (<usize>k1 << 3), vB, 0);
          v128.store64_lane(hts + (<usize>k3 << 3), vB, 1);
        }
        rA = add(rA, dr); qA = add(qA, dq);
        rB = add(rB, dr); qB = add(qB, dq);
      }
      lo = min(lo, min(f64x2.extract_lane(loV, 0), f64x2.extract_lane(loV, 1)));
      hi = max(hi, max(f64x2.extract_lane(hiV, 0), f64x2.extract_lane(hiV, 1)));
      store<f64>(fin, lo, 32);
      store<f64>(fin, hi, 40);
      store<i32>(fin, cells, 64);
      return;
    }
    for (let cell = c0, p = 0; cell < end; cell++, p += os) {
      const m = cell & 1 ? n - 1 - ((cell - 1) >> 1) : cell >> 1;
      const r = ld(re, m), i = ld(im, m);
      const d = cell - c0;
      if (o0 >= 0) {
        const k = o0 + p;
        const z = finishCell(k, 0.0 + f64x2.extract_lane(r, 0), <f64>(down ? r0 + d : r0), <f64>(down ? q0 : q0 + d),
                             z0, a, b, c, mask, hts, f32, res, plane);
        if (load<u8>(mask + <usize>k)) {
          lo = min(lo, z);
          hi = max(hi, z);
          cells++;
        }
      }
      if (o1 >= 0) {
        const k = o1 + p;
        const z = finishCell(k, 0.0 - f64x2.extract_lane(i, 0), <f64>(down ? r1 + d : r1), <f64>(down ? q1 : q1 + d),
                             z0, a, b, c, mask, hts, f32, res, plane);
        if (load<u8>(mask + <usize>k)) {
          lo = min(lo, z);
          hi = max(hi, z);
          cells++;
        }
      }
      if (o2 >= 0) {
        const k = o2 + p;
        const z = finishCell(k, 0.0 + f64x2.extract_lane(r, 1), <f64>(down ? r2 + d : r2), <f64>(down ? q2 : q2 + d),
                             z0, a, b, c, mask, hts, f32, res, plane);
        if (load<u8>(mask + <usize>k)) {
          lo = min(lo, z);
          hi = max(hi, z);
          cells++;
        }
      }
      if (o3 >= 0) {
        const k = o3 + p;
        const z = finishCell(k, 0.0 - f64x2.extract_lane(i, 1), <f64>(down ? r3 + d : r3), <f64>(down ? q3 : q3 + d),
                             z0, a, b, c, mask, hts, f32, res, plane);
        if (load<u8>(mask + <usize>k)) {
          lo = min(lo, z);
          hi = max(hi, z);
          cells++;
        }
      }
    }
    store<f64>(fin, lo, 32);
    store<f64>(fin, hi, 40);
    store<i32>(fin, cells, 64);
    return;
  }
  if (o0 >= 0 && o1 == o0 + 1 && o2 == o0 + 2 && o3 == o0 + 3) {
    // Four adjacent outputs: out += re, out -= im as adding the negation (the same in IEEE arithmetic).
    for (let cell = c0, p = 0; cell < end; cell++, p += os) {
      const m = cell & 1 ? n - 1 - ((cell - 1) >> 1) : cell >> 1;
      const r = ld(re, m), i = neg(ld(im, m));
      const a = out + (<usize>(o0 + p) << 3);
      v128.store(a, add(v128.load(a), i64x2.shuffle(r, i, 0, 2)));
      v128.store(a, add(v128.load(a, 16), i64x2.shuffle(r, i, 1, 3)), 16);
    }
    return;
  }
  if (o0 >= 0 && o1 >= 0 && o2 >= 0 && o3 >= 0) {
    for (let cell = c0, p = 0; cell < end; cell++, p += os) {
      const m = cell & 1 ? n - 1 - ((cell - 1) >> 1) : cell >> 1;
      const r = ld(re, m), i = ld(im, m);
      const a0 = out + (<usize>(o0 + p) << 3), a1 = out + (<usize>(o1 + p) << 3);
      const a2 = out + (<usize>(o2 + p) << 3), a3 = out + (<usize>(o3 + p) << 3);
      store<f64>(a0, load<f64>(a0) + f64x2.extract_lane(r, 0));
      store<f64>(a1, load<f64>(a1) - f64x2.extract_lane(i, 0));
      store<f64>(a2, load<f64>(a2) + f64x2.extract_lane(r, 1));
      store<f64>(a3, load<f64>(a3) - f64x2.extract_lane(i, 1));
    }
    return;
  }
  for (let cell = c0, p = 0; cell < end; cell++, p += os) {
    const m = cell & 1 ? n - 1 - ((cell - 1) >> 1) : cell >> 1;
    const r = ld(re, m), i = ld(im, m);
    if (o0 >= 0) { const a = out + (<usize>(o0 + p) << 3); store<f64>(a, load<f64>(a) + f64x2.extract_lane(r, 0)); }
    if (o1 >= 0) { const a = out + (<usize>(o1 + p) << 3); store<f64>(a, load<f64>(a) - f64x2.extract_lane(i, 0)); }
    if (o2 >= 0) { const a = out + (<usize>(o2 + p) << 3); store<f64>(a, load<f64>(a) + f64x2.extract_lane(r, 1)); }
    if (o3 >= 0) { const a = out + (<usize>(o3 + p) << 3); store<f64>(a, load<f64>(a) - f64x2.extract_lane(i, 1)); }
  }
}

/**
 * The fused finishing pass of a vector of zeros (one the inverse skips): cells o + p os, p < w, as
 * dctGroup's fin. fin's layout: z0, a, b, c (f64 at bytes 0 .. 24), the least and greatest heights
 * so far (f64 at 32, 40), then i32s: the mask (48), the heights (52), 1 for f32 heights (56), the
 * grid's columns (60), the cells set so far (64), 1 when the vectors run down the columns (68), a
 * residual layer's grid or 0 (72, see finishCell), 1 to add the plane before it (76).
 */
export function finishZeros(fin: usize, o: i32, os: i32, w: i32): void {
  const z0 = load<f64>(fin), a = load<f64>(fin, 8), b = load<f64>(fin, 16), c = load<f64>(fin, 24);
  let lo = load<f64>(fin, 32), hi = load<f64>(fin, 40);
  const mask = <usize>load<i32>(fin, 48), hts = <usize>load<i32>(fin, 52), f32 = load<i32>(fin, 56);
  const cols = load<i32>(fin, 60);
  const res = <usize>load<i32>(fin, 72), plane = load<i32>(fin, 76);
  let cells = load<i32>(fin, 64);
  for (let p = 0; p < w; p++) {
    const k = o + p * os;
    const r = k / cols, q = k - r * cols;
    const z = finishCell(k, 0.0, <f64>r, <f64>q, z0, a, b, c, mask, hts, f32, res, plane);
    if (load<u8>(mask + <usize>k)) {
      lo = min(lo, z);
      hi = max(hi, z);
      cells++;
    }
  }
  store<f64>(fin, lo, 32);
  store<f64>(fin, hi, 40);
  store<i32>(fin, cells, 64);
}

/**
 * finishWindow's pass over rows [wr0, wr1) and columns [wc0, wc1) of the grid h (f64, cols a row)
 * and mask (u8): heights (f64, or f32 when f32 is 1) at out, window-major, z = h + (z0 + (a + c r) +
 * b q) where the mask is set, NaN elsewhere. Returns the cells set; their least and greatest heights
 * go to res (two f64), NaN when a height is NaN.
 */
export function finish(h: usize, mask: usize, out: usize, cols: i32, wr0: i32, wr1: i32, wc0: i32, wc1: i32,
  z0: f64, a: f64, b: f64, c: f64, f32: i32, res: usize): i32 {
  const W = wc1 - wc0;
  const inf = f64x2.splat(Infinity), minf = f64x2.splat(-Infinity), nan = f64x2.splat(NaN);
  const bv = f64x2.splat(b);
  const two = f64x2.splat(2);
  let lo = inf, hi = minf;
  let slo = Infinity, shi = -Infinity;
  let cells = 0;
  for (let r = wr0; r < wr1; r++) {
    const row = z0 + (a + c * <f64>r);
    const rowv = f64x2.splat(row);
    const k0 = r * cols;
    const t0 = (r - wr0) * W - wc0;
    let q = wc0;
    let qv = f64x2.replace_lane(f64x2.splat(<f64>q), 1, <f64>(q + 1));
    for (; q + 1 < wc1; q += 2) {
      const k = k0 + q;
      const z = add(v128.load(h + (<usize>k << 3)), add(rowv, mul(bv, qv)));
      const m0 = load<u8>(mask + <usize>k), m1 = load<u8>(mask + <usize>k + 1);
      const sel = i64x2.replace_lane(i64x2.splat(m0 ? -1 : 0), 1, m1 ? -1 : 0);
      cells += <i32>(m0 != 0) + <i32>(m1 != 0);
      lo = f64x2.min(lo, v128.bitselect(z, inf, sel));
      hi = f64x2.max(hi, v128.bitselect(z, minf, sel));
      const v = v128.bitselect(z, nan, sel);
      const t = t0 + q;
      if (f32) v128.store64_lane(out + (<usize>t << 2), f32x4.demote_f64x2_zero(v), 0);
      else v128.store(out + (<usize>t << 3), v);
      qv = add(qv, two);
    }
    for (; q < wc1; q++) {
      const k = k0 + q;
      const t = t0 + q;
      let z = NaN;
      if (load<u8>(mask + <usize>k)) {
        z = load<f64>(h + (<usize>k << 3)) + (row + b * <f64>q);
        slo = min(slo, z);
        shi = max(shi, z);
        cells++;
      }
      if (f32) store<f32>(out + (<usize>t << 2), <f32>z);
      else store<f64>(out + (<usize>t << 3), z);
    }
  }
  store<f64>(res, min(slo, min(f64x2.extract_lane(lo, 0), f64x2.extract_lane(lo, 1))));
  store<f64>(res + 8, max(shi, max(f64x2.extract_lane(hi, 0), f64x2.extract_lane(hi, 1))));
  return cells;
}

/** The start of the memory src/wasm.ts manages. */
export function heapBase(): usize {
  return __heap_base;
}

/**
 * idctAxis's plain sums (transform.ts): for each of nvec vectors, out[o + c oes] += x_k basis[k w +
 * c] for each nonzero coefficient x_k = inp[i + k ies], k < klen, and c < w, in that order (vector v
 * reads at ioff + v ivs and writes at ooff + v ovs; element offsets). Two cells a step when the
 * outputs are contiguous, two vectors a step when the vectors are adjacent (a lane whose
 * coefficient is zero adds a zero product, which leaves a sum as it is but for a zero's sign).
 */
export function sumsAxis(inp: usize, ioff: i32, ivs: i32, ies: i32, nvec: i32, klen: i32, basis: usize,
  out: usize, ooff: i32, ovs: i32, oes: i32, w: i32): void {
  if (oes == 1) {
    for (let v = 0; v < nvec; v++) {
      const i0 = ioff + v * ivs;
      const o = out + (<usize>(ooff + v * ovs) << 3);
      for (let k = 0; k < klen; k++) {
        const x = load<f64>(inp + (<usize>(i0 + k * ies) << 3));
        if (x == 0) continue;
        const xv = f64x2.splat(x);
        const b = basis + (<usize>(k * w) << 3);
        let c = 0;
        for (; c + 1 < w; c += 2) {
          const p = o + (<usize>c << 3);
          v128.store(p, add(v128.load(p), mul(xv, v128.load(b + (<usize>c << 3)))));
        }
        for (; c < w; c++) {
          const p = o + (<usize>c << 3);
          store<f64>(p, load<f64>(p) + x * load<f64>(b + (<usize>c << 3)));
        }
      }
    }
    return;
  }
  let v = 0;
  if (ovs == 1) {
    for (; v + 1 < nvec; v += 2) {
      const i0 = ioff + v * ivs, i1 = i0 + ivs;
      const o = out + (<usize>(ooff + v) << 3);
      for (let k = 0; k < klen; k++) {
        const x0 = load<f64>(inp + (<usize>(i0 + k * ies) << 3)), x1 = load<f64>(inp + (<usize>(i1 + k * ies) << 3));
        if (x0 == 0 && x1 == 0) continue;
        const xv = f64x2.replace_lane(f64x2.splat(x0), 1, x1);
        const b = basis + (<usize>(k * w) << 3);
        for (let c = 0; c < w; c++) {
          const p = o + (<usize>(c * oes) << 3);
          v128.store(p, add(v128.load(p), mul(xv, v128.load64_splat(b + (<usize>c << 3)))));
        }
      }
    }
  }
  for (; v < nvec; v++) {
    const i0 = ioff + v * ivs;
    const o = out + (<usize>(ooff + v * ovs) << 3);
    for (let k = 0; k < klen; k++) {
      const x = load<f64>(inp + (<usize>(i0 + k * ies) << 3));
      if (x == 0) continue;
      const b = basis + (<usize>(k * w) << 3);
      for (let c = 0; c < w; c++) {
        const p = o + (<usize>(c * oes) << 3);
        store<f64>(p, load<f64>(p) + x * load<f64>(b + (<usize>c << 3)));
      }
    }
  }
}

/** The symbol of a table model (cdf: n + 1 i32, strictly increasing; slots: its slot table or 0)
 * whose interval holds ``quantile``: the largest s with cdf[s] <= quantile, searched within the
 * quantile's slot. Pure (no decoder state): ansGroups and ansSymbol both step their ANS state around it. */
// @ts-ignore: decorator
@inline function symbolAt(cdf: usize, slots: usize, n: i32, slotShift: i32, quantile: i32): i32 {
  let a = 0, b = n - 1;
  if (slots) {
    const s = slots + (<usize>(quantile >>> slotShift) << 2);
    a = load<i32>(s);
    b = load<i32>(s, 4);
  }
  while (a < b) {
    const m = (a + b + 1) >> 1;
    if (load<i32>(cdf + (<usize>m << 2)) <= quantile) a = m;
    else b = m - 1;
  }
  return a;
}

/**
 * The ANS decoder of src/ans.ts (AnsDecoder, decodeGroup) for one chunk of COEF kind 3 (or RESD
 * kind 5): the stack coder's state is a u64 here, not two halves in doubles (the same integers).
 * words: the chunk's nwords u32 words (little-endian, read from the last; the JavaScript side has
 * checked that the last is nonzero). groups: ngroups descriptors of four i32 (the cumulative table's
 * offset, its slot table's offset or 0 (quantiles in slots of 2**slotShift), the model's symbols n, the group's values), decoded one
 * group after the other; value k of the chunk (in group order) goes to the f64 out[at[k]], as its
 * symbol - maxAbs. A symbol is the largest s with cdf[s] <= the quantile (cdf strictly increasing:
 * the slots' narrowing finds the same one as a search of the whole table).
 */
export function ansGroups(words: usize, nwords: i32, groups: usize, ngroups: i32, at: usize, out: usize, maxAbs: i32,
  slotShift: i32): void {
  let pos = nwords;
  let state: u64 = 0;
  if (pos > 0) {
    state = <u64>load<u32>(words + (<usize>--pos << 2));
    if (pos > 0) state = (state << 32) | <u64>load<u32>(words + (<usize>--pos << 2));
  }
  const off = <f64>maxAbs;
  let k = 0;
  for (let g = 0; g < ngroups; g++) {
    const d = groups + (<usize>g << 4);
    const cdf = <usize>load<i32>(d);
    const slots = <usize>load<i32>(d, 4);
    const n = load<i32>(d, 8);
    const end = k + load<i32>(d, 12);
    for (; k < end; k++) {
      const quantile = <i32>(<u32>state & 0xffffff);
      const a = symbolAt(cdf, slots, n, slotShift, quantile);
      const lo = load<i32>(cdf + (<usize>a << 2));
      const hi = load<i32>(cdf + (<usize>a << 2), 4);
      state = (state >> 24) * <u64>(hi - lo) + <u64>(quantile - lo);
      if ((state >> 32) == 0 && pos > 0) state = (state << 32) | <u64>load<u32>(words + (<usize>--pos << 2));
      store<f64>(out + (<usize>load<i32>(at + (<usize>k << 2)) << 3), <f64>a - off);
    }
  }
}

// --- the residual layer (src/residual.ts, src/mask.ts, src/decode.ts) ------------------------------

/** A stack ANS decoder's state and position (ansGroups' u64 state), shared by the two kernels below
 * that decode symbol by symbol; ansStart sets them from a chunk's words (the JavaScript side has
 * checked that the last word is nonzero). ansGroups keeps its state in locals of its own (the symbol
 * search, symbolAt, is shared): its loop through these globals decoded the 2 m mosaic 0.86-1.00x as
 * fast (web/bench/ab.mjs, 3 runs). */
let ansState: u64 = 0;
let ansPos: i32 = 0;
let ansWords: usize = 0;

// @ts-ignore: decorator
@inline function ansStart(words: usize, nwords: i32): void {
  ansWords = words;
  ansPos = nwords;
  ansState = 0;
  if (ansPos > 0) {
    ansState = <u64>load<u32>(words + (<usize>--ansPos << 2));
    if (ansPos > 0) ansState = (ansState << 32) | <u64>load<u32>(words + (<usize>--ansPos << 2));
  }
}

/** state = (state >> 24) * probability + remainder, and a word refilled below 2**32 (AnsDecoder.advance). */
// @ts-ignore: decorator
@inline function ansAdvance(remainder: i32, probability: i32): void {
  let s = (ansState >> 24) * <u64>probability + <u64>remainder;
  if ((s >> 32) == 0 && ansPos > 0) s = (s << 32) | <u64>load<u32>(ansWords + (<usize>--ansPos << 2));
  ansState = s;
}

/** The next symbol of a table model (cdf: n + 1 i32; slots: its slot table or 0), AnsDecoder.decode. */
// @ts-ignore: decorator
@inline function ansSymbol(cdf: usize, slots: usize, n: i32, slotShift: i32): i32 {
  const quantile = <i32>(<u32>ansState & 0xffffff);
  const a = symbolAt(cdf, slots, n, slotShift, quantile);
  const lo = load<i32>(cdf + (<usize>a << 2));
  ansAdvance(quantile - lo, load<i32>(cdf + (<usize>a << 2), 4) - lo);
  return a;
}

/** One bit of a Bernoulli model whose cumulative table is [0, left1, 2**24] (AnsDecoder.decodeBit). */
// @ts-ignore: decorator
@inline function ansBit(left1: i32): i32 {
  const quantile = <i32>(<u32>ansState & 0xffffff);
  if (quantile < left1) {
    ansAdvance(quantile, left1);
    return 0;
  }
  ansAdvance(quantile - left1, 0x1000000 - left1);
  return 1;
}

/**
 * contextMask (src/mask.ts, MASK kinds 2 and 3) after its seed lines: lines (u8, n lines of w cells,
 * the seed lines in place) gets every other line, step t = first .. L - 1 decoding line t of each
 * stripe (of nStripes; only stripe 0 at t = 0) from the chunk's words, with the models of contexts
 * 0 and 255 first, then each cell's own, the counts updated as mask.ts does (float64 operations in
 * its order: the same left1 to the bit). scratch: 2 w + 16 bytes (two padded lines), then 2 nStripes w
 * bytes from the next 16-aligned offset (contexts, bits), 16-aligned; tables: 6144 bytes (zeroed here).
 */
export function contextMask(lines: usize, n: i32, w: i32, L: i32, nStripes: i32, first: i32, words: usize, nwords: i32,
  scratch: usize, tables: usize): void {
  ansStart(words, nwords);
  const n1 = tables, nn = tables + 2048, left1 = tables + 4096;
  memory.fill(tables, 0, 6144);
  const padA = scratch, padB = scratch + <usize>(w + 8);
  const ctx = scratch + ((<usize>(2 * w + 16) + 15) & ~15);
  const bits = ctx + <usize>nStripes * <usize>w;
  memory.fill(padA, 0, <usize>(2 * w + 16));
  for (let t = first; t < L; t++) {
    let lineCount = 0;
    const most = t ? nStripes : 1;
    while (lineCount < most && lineCount * L + t < n) lineCount++;
    const m = lineCount * w;
    for (let q = 0; q < lineCount; q++) {
      const i = q * L + t;
      const base = ctx + <usize>(q * w);
      if (t == 0) {
        memory.fill(base, 0, <usize>w);
        continue;
      }
      memory.copy(padA + 2, lines + <usize>(i - 1) * <usize>w, <usize>w);
      memory.copy(padB + 2, lines + <usize>(t >= 2 ? i - 2 : i - 1) * <usize>w, <usize>w);
      let a = <i32>load<u8>(padA) | (<i32>load<u8>(padA, 1) << 1) | (<i32>load<u8>(padA, 2) << 2) | (<i32>load<u8>(padA, 3) << 3)
        | (<i32>load<u8>(padA, 4) << 4);
      let b = <i32>load<u8>(padB, 1) | (<i32>load<u8>(padB, 2) << 1) | (<i32>load<u8>(padB, 3) << 2);
      for (let j = 0; j < w; j++) {
        store<u8>(base + <usize>j, a | (b << 5));
        a = (a >> 1) | (<i32>load<u8>(padA + <usize>(j + 5)) << 4);
        b = (b >> 1) | (<i32>load<u8>(padB + <usize>(j + 4)) << 2);
      }
    }
    for (let c = 0; c < 256; c++) {
      const p = (load<f64>(n1 + (<usize>c << 3)) + (<f64>popcnt<i32>(c) + 0.5) / 9) / (load<f64>(nn + (<usize>c << 3)) + 1);
      // bernoulliLeft1(p): constriction's perfect=False quantization.
      const q = 1 - p;
      const scale = <f64>(0x1000000 - 2) / (q + p);
      store<i32>(left1 + (<usize>c << 2), <i32>floor(q * scale) + 1);
    }
    for (let pass = 0; pass < 2; pass++) {
      const c = pass ? 255 : 0;
      const l = load<i32>(left1 + (<usize>c << 2));
      let cells = 0, ones = 0;
      for (let k = 0; k < m; k++) {
        if (<i32>load<u8>(ctx + <usize>k) == c) {
          const bit = ansBit(l);
          store<u8>(bits + <usize>k, bit);
          ones += bit;
          cells++;
        }
      }
      store<f64>(nn + (<usize>c << 3), load<f64>(nn + (<usize>c << 3)) + <f64>cells);
      store<f64>(n1 + (<usize>c << 3), load<f64>(n1 + (<usize>c << 3)) + <f64>ones);
    }
    for (let k = 0; k < m; k++) {
      const c = <i32>load<u8>(ctx + <usize>k);
      if (c != 0 && c != 255) {
        const bit = ansBit(load<i32>(left1 + (<usize>c << 2)));
        store<u8>(bits + <usize>k, bit);
        const o = <usize>c << 3;
        store<f64>(nn + o, load<f64>(nn + o) + 1);
        store<f64>(n1 + o, load<f64>(n1 + o) + <f64>bit);
      }
    }
    for (let q = 0; q < lineCount; q++) memory.copy(lines + <usize>(q * L + t) * <usize>w, bits + <usize>(q * w), <usize>w);
  }
}

/** The wavefront ring's slot (k mod 5) of neighbour (up, left) of (r, c), cell k = 2 r + c, by
 * format.md's rules 1-4 (residual.ts nb): its row in the high half, -1 at rule 1's (0, 0). Every
 * neighbour lies in one of the four wavefronts before k, so five wavefronts of values are all a
 * decode reads (a wavefront's cells are rows apart in the grid: one page each). */
// @ts-ignore: decorator
@inline function nbRow(r: i32, c: i32, up: i32, left: i32, cols: i32): i32 {
  if (r == 0 && c == 0) return -1;
  let rr = 0, cc = 0;
  if (up && r == 0) cc = c - 1;
  else if (!up && c == 0) rr = r - 1;
  else {
    rr = max(r - up, 0);
    cc = min(max(c - left, 0), cols - 1);
  }
  return (rr << 3) | ((2 * rr + cc) % 5);
}

/** The value of ring `g` (five wavefronts of `rows` i32) at nbRow's answer x. */
// @ts-ignore: decorator
@inline function ringAt(g: usize, x: i32, rows: i32): i32 {
  return x < 0 ? 0 : load<i32>(g + (<usize>((x & 7) * rows + (x >> 3)) << 2));
}

// @ts-ignore: decorator
@inline function vi(g: usize, k: i32): i32 { return load<i32>(g + (<usize>k << 2)); }

/**
 * RESD kind 5 (src/residual.ts predicted) after its header: the values V (i32 grid, rows x cols) of
 * every cell, wavefront by wavefront, each wavefront's errors decoded class by class from the
 * chunk's words, then its values predicted in exact integers, P = (sum a_k x_k + 2**15) >> 16 (i64:
 * |a| < 2**24 and |x| < 2**31, seven products below 2**58). The neighbours are read from rings of the
 * last five wavefronts' values and errors (ring: 2 x 5 x rows i32; wavefront k's cell of row r at
 * (k mod 5) rows + r). weights: 7 i32; classes: 64 descriptors of four i32 (the cumulative table's
 * offset, its slot table's or 0, the symbols n (0: code 0, not coded), max_abs). line, order: i32
 * scratch of `most` (the longest wavefront), lineClass u8 of most, starts 65 i32. out: the values of
 * the rebuilt cells in row-major order (f64). Returns 0, or 1 when a value reaches 2**31 in magnitude
 * (the caller refuses the chunk).
 */
export function predicted(words: usize, nwords: i32, weights: usize, classes: usize, mask: usize, rows: i32, cols: i32,
  V: usize, ring: usize, line: usize, lineClass: usize, order: usize, starts: usize, out: usize, slotShift: i32): i32 {
  ansStart(words, nwords);
  const cells = <usize>rows * <usize>cols;
  const RV = ring, RE = ring + (<usize>(5 * rows) << 2);
  memory.fill(ring, 0, <usize>(10 * rows) << 2);
  const a0 = <i64>load<i32>(weights), a1 = <i64>load<i32>(weights, 4), a2 = <i64>load<i32>(weights, 8),
    a3 = <i64>load<i32>(weights, 12), a4 = <i64>load<i32>(weights, 16), a5 = <i64>load<i32>(weights, 20),
    a6 = <i64>load<i32>(weights, 24);
  const NONE = 255;
  const last = 2 * (rows - 1) + cols;
  const slot = <usize>rows << 2;
  for (let k = 0; k < last; k++) {
    // The wavefronts k, k - 1 .. k - 4 in the rings (only the interior, k >= 6, reads them directly).
    const s0 = <usize>(k % 5) * slot, s1 = <usize>((k + 4) % 5) * slot, s2 = <usize>((k + 3) % 5) * slot;
    const s3 = <usize>((k + 2) % 5) * slot, s4 = <usize>((k + 1) % 5) * slot;
    let n = 0;
    memory.fill(starts, 0, 65 * 4);
    const lo = k - cols + 1;
    const rFirst = lo <= 0 ? 0 : (lo + 1) >> 1;
    for (let r = rFirst; r < rows && 2 * r <= k; r++) {
      const c = k - 2 * r;
      const cell = r * cols + c;
      store<i32>(line + (<usize>n << 2), r);
      const ro = <usize>r << 2;
      store<i32>(RE + s0 + ro, 0);
      if (!load<u8>(mask + <usize>cell)) {
        store<u8>(lineClass + <usize>(n++), NONE);
        continue;
      }
      let act = 0;
      if (r >= 2 && c >= 2 && c < cols - 1) {
        act = 2 * abs(load<i32>(RE + s1 + ro)) + 2 * abs(load<i32>(RE + s2 + ro - 4)) + abs(load<i32>(RE + s3 + ro - 4))
          + abs(load<i32>(RE + s1 + ro - 4)) + abs(load<i32>(RE + s2 + ro)) + abs(load<i32>(RE + s4 + ro - 8));
      } else {
        act = 2 * abs(ringAt(RE, nbRow(r, c, 0, 1, cols), rows)) + 2 * abs(ringAt(RE, nbRow(r, c, 1, 0, cols), rows))
          + abs(ringAt(RE, nbRow(r, c, 1, 1, cols), rows)) + abs(ringAt(RE, nbRow(r, c, 1, -1, cols), rows))
          + abs(ringAt(RE, nbRow(r, c, 0, 2, cols), rows)) + abs(ringAt(RE, nbRow(r, c, 2, 0, cols), rows));
      }
      let cls = 0;
      if (act > 0) {
        const bits = 32 - clz<i32>(act);
        const s = bits >= 2 ? (act >>> (bits - 2)) & 1 : 0;
        cls = min(63, 2 * bits - 1 + s);
      }
      store<u8>(lineClass + <usize>(n++), cls);
      const sp = starts + (<usize>(cls + 1) << 2);
      store<i32>(sp, load<i32>(sp) + 1);
    }
    for (let cls = 0; cls < 64; cls++) {
      const sp = starts + (<usize>(cls + 1) << 2);
      store<i32>(sp, load<i32>(sp) + load<i32>(sp - 4));
    }
    for (let i = 0; i < n; i++) {
      const cls = <i32>load<u8>(lineClass + <usize>i);
      if (cls != NONE) {
        const sp = starts + (<usize>cls << 2);
        const at = load<i32>(sp);
        store<i32>(order + (<usize>at << 2), vi(line, i));
        store<i32>(sp, at + 1);
      }
    }
    // starts[cls] is now the end of class cls; it began where class cls - 1 ended.
    for (let cls = 0, from = 0; cls < 64; cls++) {
      const to = load<i32>(starts + (<usize>cls << 2));
      const d = classes + (<usize>cls << 4);
      const m = load<i32>(d, 8);
      if (m) {
        const cdf = <usize>load<i32>(d), slots = <usize>load<i32>(d, 4), w = load<i32>(d, 12);
        for (let i = from; i < to; i++) store<i32>(RE + s0 + (<usize>vi(order, i) << 2), ansSymbol(cdf, slots, m, slotShift) - w);
      }
      from = to;
    }
    for (let i = 0; i < n; i++) {
      const r = vi(line, i);
      const c = k - 2 * r;
      const ro = <usize>r << 2;
      let v: i64;
      if (<i32>load<u8>(lineClass + <usize>i) != NONE) {
        let S: i64;
        if (r >= 2 && c >= 2 && c < cols - 1) {
          S = a0 * <i64>load<i32>(RV + s1 + ro) + a1 * <i64>load<i32>(RV + s2 + ro - 4) + a2 * <i64>load<i32>(RV + s3 + ro - 4)
            + a3 * <i64>load<i32>(RV + s1 + ro - 4) + a4 * <i64>load<i32>(RV + s2 + ro) + a5 * <i64>load<i32>(RV + s4 + ro - 8)
            + a6 * <i64>load<i32>(RV + s3 + ro - 8);
        } else {
          S = a0 * <i64>ringAt(RV, nbRow(r, c, 0, 1, cols), rows) + a1 * <i64>ringAt(RV, nbRow(r, c, 1, 0, cols), rows)
            + a2 * <i64>ringAt(RV, nbRow(r, c, 1, 1, cols), rows) + a3 * <i64>ringAt(RV, nbRow(r, c, 1, -1, cols), rows)
            + a4 * <i64>ringAt(RV, nbRow(r, c, 0, 2, cols), rows) + a5 * <i64>ringAt(RV, nbRow(r, c, 2, 0, cols), rows)
            + a6 * <i64>ringAt(RV, nbRow(r, c, 2, -1, cols), rows);
        }
        v = ((S + 32768) >> 16) + <i64>load<i32>(RE + s0 + ro);
        if (v >= 0x80000000 || v <= -0x80000000) return 1;
      } else {
        v = <i64>ringAt(RV, nbRow(r, c, 0, 1, cols), rows);
      }
      store<i32>(RV + s0 + ro, <i32>v);
      store<i32>(V + (<usize>(r * cols + c) << 2), <i32>v);
    }
  }
  let o = out;
  for (let k: usize = 0; k < cells; k++) {
    if (load<u8>(mask + k)) {
      store<f64>(o, <f64>load<i32>(V + (k << 2)));
      o += 8;
    }
  }
  return 0;
}

/**
 * decodeWhole's residual step on the grid h (f64, rows x cols), in place on the rebuilt cells: the
 * plane first when `plane` is 1 (h += (a + c r) + b q, addPlane), then h += q_i 2 e (1 - 1e-6) with q_i
 * the residual's integer of the cell, as decode.ts sums them (a zero too: -0 + 0 is 0). q: one f64 per
 * rebuilt cell in row-major order; or, when picture is not 0 (a sparse layer: u8 a cell of the grid,
 * 1 where the integer is not 0), one per set cell of the picture, the others 0.
 */
export function addResidual(h: usize, mask: usize, q: usize, picture: usize, rows: i32, cols: i32, plane: i32, a: f64,
  b: f64, c: f64, e: f64): void {
  let i: usize = q;
  for (let r = 0; r < rows; r++) {
    const row = a + c * <f64>r;
    const k0 = r * cols;
    for (let cc = 0; cc < cols; cc++) {
      const k = k0 + cc;
      if (!load<u8>(mask + <usize>k)) continue;
      const p = h + (<usize>k << 3);
      let z = load<f64>(p);
      if (plane) z = z + (row + b * <f64>cc);
      let v = 0.0;
      if (!picture || load<u8>(picture + <usize>k)) {
        v = load<f64>(i);
        i += 8;
      }
      store<f64>(p, z + v * 2 * e * (1 - 1e-6));
    }
  }
}

/**
 * The grid res (f64, rows x cols) of a residual layer's terms q 2 e (1 - 1e-6) at the rebuilt cells
 * (decode.ts's operations; a zero's term too), for the fused finishing pass (finishCell). q and
 * picture as addResidual reads them.
 */
export function residualGrid(res: usize, mask: usize, q: usize, picture: usize, cells: i32, e: f64): void {
  let i: usize = q;
  for (let k = 0; k < cells; k++) {
    if (!load<u8>(mask + <usize>k)) continue;
    let v = 0.0;
    if (!picture || load<u8>(picture + <usize>k)) {
      v = load<f64>(i);
      i += 8;
    }
    store<f64>(res + (<usize>k << 3), v * 2 * e * (1 - 1e-6));
  }
}
