import { describe, expect, it } from 'vitest';
import { kPadCorners, landingText, padOutline } from './landing.js';

describe('padOutline', () => {
  it('places the corners where the pose puts them', () => {
    const identity = padOutline({ position: [1, 2, 3], orientation: [0, 0, 0, 1] });
    expect(identity).toEqual(kPadCorners.map(([x, y]) => [x + 1, y + 2, 3]));
    // Turned over about x (the pad's z into a deck whose z is up): y flips.
    const over = padOutline({ position: [0, 0, 0], orientation: [1, 0, 0, 0] });
    over.forEach(([x, y, z], k) => {
      expect(x).toBeCloseTo(kPadCorners[k][0], 12);
      expect(y).toBeCloseTo(-kPadCorners[k][1], 12);
      expect(z).toBeCloseTo(0, 12);
    });
    // A quarter turn about z: (x, y) -> (-y, x).
    const s = Math.SQRT1_2;
    const turned = padOutline({ position: [0, 0, 0], orientation: [0, 0, s, s] });
    turned.forEach(([x, y], k) => {
      expect(x).toBeCloseTo(-kPadCorners[k][1], 12);
      expect(y).toBeCloseTo(kPadCorners[k][0], 12);
    });
  });
});

describe('landingText', () => {
  it('says distance and bearing while tracked, the reason when lost', () => {
    expect(landingText([])).toBeNull();
    expect(landingText([{ vehicle_id: 'uav-1', state: 'TRACKING', has_pose: true, distance_m: 18.23, bearing_deg: 12.4 }]))
      .toBe('pad 18.2 m at +12° (uav-1)');
    expect(landingText([
      { vehicle_id: 'a', state: 'LOST', has_pose: false, reason: 'the pad is leaving the image' },
      { vehicle_id: 'b', state: 'SEARCHING', has_pose: false, reason: 'no pad' },
      { vehicle_id: 'c', state: 'TRACKING', has_pose: true, distance_m: 5, bearing_deg: -90 },
    ])).toBe('pad lost (a): the pad is leaving the image · looking for the pad (b) · pad 5.0 m at -90° (c)');
  });
});
