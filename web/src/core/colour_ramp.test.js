import { describe, expect, it } from 'vitest';
import {
  changeColour, changeCssGradient, kChangeClasses, kHeightRamp, rampColour, rampCssGradient,
} from './colour_ramp.js';

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

describe('changeColour', () => {
  it('tells the server diff classes apart by their tile values', () => {
    const rgbOf = (name) => kChangeClasses.find((c) => c.name === name).rgb;
    expect(changeColour(248)).toEqual(rgbOf('appeared')); // P 0.971
    expect(changeColour(217)).toEqual(rgbOf('disappeared')); // P 0.85
    expect(changeColour(184)).toEqual(rgbOf('unchanged')); // P 0.72
    expect(changeColour(0)).toEqual(rgbOf('unchanged'));
    expect(changeColour(255)).toEqual(rgbOf('appeared'));
  });

  it('draws the legend as hard bands, unchanged at the bottom', () => {
    const css = changeCssGradient();
    expect(css.match(/rgb\(/g)).toHaveLength(2 * kChangeClasses.length);
    expect(css).toMatch(/^linear-gradient\(to top, rgb\(153, 153, 158\) 0%, rgb\(153, 153, 158\) 33%/);
  });
});
