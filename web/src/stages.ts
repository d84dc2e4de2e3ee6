// Where a decode's time goes, stage by stage (web/bench prints it): off unless asked for, so that a
// decode pays one test of a flag per stage. Wall-clock milliseconds (performance.now), summed over
// the decodes since the last reset.

let on = false;
const spent = new Map<string, number>();

/** Now, in milliseconds, when stages are being timed (0 otherwise: no clock read). */
export function mark(): number {
  return on ? performance.now() : 0;
}

/** Adds the time since `t0` (a mark) to `name`; returns a new mark. */
export function lap(name: string, t0: number): number {
  if (!on) return 0;
  const t = performance.now();
  spent.set(name, (spent.get(name) ?? 0) + t - t0);
  return t;
}

/** Starts timing stages anew (on) or stops (off); returns the milliseconds spent per stage so far. */
export function stageTimes(timing: boolean): Record<string, number> {
  const out = Object.fromEntries(spent);
  spent.clear();
  on = timing;
  return out;
}
