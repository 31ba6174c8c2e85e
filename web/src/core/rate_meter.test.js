import { describe, expect, it } from 'vitest';
import { RateMeter } from './rate_meter.js';

// A count that grows by one `every` ms from t = 0 (a vehicle sending at 1000 / every Hz).
const countAt = (tMs, everyMs) => Math.floor(tMs / everyMs);

// Deterministic "random" numbers in [0, 1) (a linear congruential generator).
function lcg(seed) {
  let state = seed;
  return () => {
    state = (state * 1664525 + 1013904223) % 2 ** 32;
    return state / 2 ** 32;
  };
}

describe('RateMeter', () => {
  it('has no rate until two counts at least minSpanMs apart', () => {
    const meter = new RateMeter({ minSpanMs: 1000 });
    expect(meter.perSecond).toBeNull();
    meter.add(0, 0);
    meter.add(4, 400);
    meter.add(9, 999);
    expect(meter.perSecond).toBeNull();
    meter.add(10, 1000);
    expect(meter.perSecond).toBe(10); // over the whole second, not the last 1 ms
  });

  it('gives a steady source its exact rate, however irregularly it is read', () => {
    const meter = new RateMeter();
    const random = lcg(7);
    // A count growing linearly at 3.2 /s, read at times 10 to 900 ms apart.
    for (let t = 0; t < 20_000; t += 10 + 890 * random()) meter.add(3.2 * t / 1000, t);
    expect(meter.perSecond).toBeCloseTo(3.2, 9);
  });

  it('keeps whole-sample counts at a 3 Hz source within a tenth, read every 500 ms with jitter', () => {
    // Statuses carry integer counts: over 1 s spans a 3.33 Hz source shows 3 or 4 clouds.
    const meter = new RateMeter();
    const random = lcg(42);
    const seen = [];
    for (let t = 0; t < 60_000; t += 450 + 100 * random()) {
      meter.add(countAt(t, 300), t);
      if (t > 10_000) seen.push(meter.perSecond);
    }
    // A span of 1.0-1.1 s holds 3 or 4 counts: 2.7..4 /s unsmoothed; smoothing over 1.5 s keeps
    // each figure within 0.35 of 3.33 (measured here: 3.01-3.65), and the mean within 0.05.
    const mean = seen.reduce((a, b) => a + b, 0) / seen.length;
    expect(mean).toBeCloseTo(1000 / 300, 1);
    for (const rate of seen) expect(Math.abs(rate - 1000 / 300)).toBeLessThan(0.35);
  });

  it('falls as exp(-elapsed / timeConstantMs) after a source stops, whatever the spans', () => {
    const regular = new RateMeter({ timeConstantMs: 1500 });
    const irregular = new RateMeter({ timeConstantMs: 1500 });
    for (let t = 0; t <= 10_000; t += 500) {
      regular.add(countAt(t, 100), t); // 10 /s until t = 10 s, read every 500 ms
      irregular.add(countAt(t, 100), t);
    }
    expect(regular.perSecond).toBe(10);
    // Then nothing more: the count stays at 100, read at different times by each.
    for (const t of [11_000, 12_000, 13_000, 14_000, 15_000, 16_000]) regular.add(100, t);
    for (const t of [11_300, 13_700, 16_000]) irregular.add(100, t);
    const expected = 10 * Math.exp(-6000 / 1500);
    expect(regular.perSecond).toBeCloseTo(expected, 9);
    expect(irregular.perSecond).toBeCloseTo(expected, 9);
  });

  it('starts over when the count goes back (a restarted server) and after reset()', () => {
    const meter = new RateMeter();
    meter.add(500, 0);
    meter.add(510, 1000);
    expect(meter.perSecond).toBe(10);
    meter.add(3, 1500); // the server restarted: no negative rate, no rate at all yet
    expect(meter.perSecond).toBeNull();
    meter.add(5, 2500);
    expect(meter.perSecond).toBe(2);
    meter.reset();
    expect(meter.perSecond).toBeNull();
    meter.add(100, 3000);
    meter.add(100, 4000);
    expect(meter.perSecond).toBe(0);
  });

  it('ignores what is not a number (a field an older server does not send)', () => {
    const meter = new RateMeter();
    meter.add(0, 0);
    meter.add(undefined, 1000);
    meter.add(null, 1000);
    expect(meter.perSecond).toBeNull();
    meter.add(20, 2000);
    expect(meter.perSecond).toBe(10);
  });
});
