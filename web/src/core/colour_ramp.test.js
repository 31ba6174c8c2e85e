import { describe, expect, it } from 'vitest';
import { kHeightRamp, rampColour, rampCssGradient } from './colour_ramp.js';

describe('rampColour', () => {
  it('hits the end stops, clamps and interpolates', () => {
    expect(rampColour(0)).toEqual(kHeightRamp[0]);
    expect(rampColour(1)).toEqual(kHeightRamp.at(-1));
    expect(rampColour(-5)).toEqual(kHeightRamp[0]);
    expect(rampColour(NaN)).toEqual(kHeightRamp[0]);
    const step = 1 / (kHeightRamp.length - 1);
    const mid = rampColour(step / 2);
    mid.forEach((c, i) => expect(c).toBeCloseTo((kHeightRamp[0][i] + kHeightRamp[1][i]) / 2, 12));
  });

  it('gives the legend one CSS stop per ramp stop', () => {
    expect(rampCssGradient().match(/rgb\(/g)).toHaveLength(kHeightRamp.length);
    expect(rampCssGradient()).toMatch(/^linear-gradient\(to top, rgb\(46, 64, 191\) 0%/);
  });
});
