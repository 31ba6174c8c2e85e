import { describe, expect, it } from 'vitest';
import { formatAge, formatCount, formatKilobytesPerSecond, originLines, ratesText, statusText, vehicleLines } from './format.js';

describe('formatAge', () => {
  it.each([
    [null, 'never'],
    [0, '0.0 s ago'],
    [2.14, '2.1 s ago'],
    [-3, '0.0 s ago'],
    [59.94, '59.9 s ago'],
    [125, '2 min ago'],
    [5400, '1.5 h ago'],
  ])('%s s → %s', (seconds, text) => expect(formatAge(seconds)).toBe(text));
});

describe('statusText', () => {
  it('says when pose corrections moved the map, and while it is fused again', () => {
    const session = { id: 's', known: true, vehicle: '', renderedVoxels: 5, frames: 3, ageSeconds: 1, corrections: 2, refusing: true };
    expect(statusText({ connected: true }, session)).toBe('connected · session s · 5 voxels · 3 frames · 2 pose corrections, map being fused again · updated 1.0 s ago');
    expect(statusText({ connected: true }, { ...session, corrections: 1, refusing: false })).toContain('· 1 pose correction ·');
    expect(statusText({ connected: true }, { ...session, corrections: 0 })).not.toContain('correction');
  });
  it('names the link, session, voxels, frames and age', () => {
    const session = { id: 'e2e', known: true, vehicle: 'sim-1', renderedVoxels: 12345, frames: 1, ageSeconds: 2.1 };
    expect(statusText({ connected: true }, session)).toBe('connected · session e2e (sim-1) · 12,345 voxels · 1 frame · updated 2.1 s ago');
    expect(statusText({ connected: true }, { ...session, serverVoxels: 99999 })).toBe('connected · session e2e (sim-1) · 12,345 cells of 99,999 voxels · 1 frame · updated 2.1 s ago');
    expect(statusText({ connected: true }, { ...session, frames: 0, serverVoxels: 1198329 })).toBe('connected · session e2e (sim-1) · 12,345 cells of 1,198,329 voxels · imported map · updated 2.1 s ago');
    expect(statusText({ connected: true }, { ...session, frames: 0, serverVoxels: 1198329, isDiff: true })).toContain(' · diff of two flights · ');
    expect(statusText({ connected: true }, { ...session, frames: 0, renderedVoxels: 0, serverVoxels: 0 })).toBe('connected · session e2e (sim-1) · 0 voxels · 0 frames · updated 2.1 s ago');
    expect(statusText({ connected: false, retryInSeconds: 1.2 }, null)).toBe('disconnected, retrying in 2 s · no session yet');
    expect(statusText({ connected: true }, { id: 'x', known: false })).toBe('connected · session x not on the server (yet)');
  });

  it('groups thousands', () => {
    expect([0, 999, 1000, 1234567].map(formatCount)).toEqual(['0', '999', '1,000', '1,234,567']);
  });
});

describe('ratesText', () => {
  it('says poses/s and clouds/s apart, and the vehicles\' link apart from this page\'s', () => {
    expect(ratesText({ poses: 10, clouds: 3.24, linkBytes: 28_400, viewerBytes: 12_000 }))
      .toBe('10.0 poses/s · 3.2 clouds/s · link 28 kB/s · viewer 12 kB/s');
  });
  it('leaves out what is not measured (yet, or at all: not live)', () => {
    expect(ratesText({ viewerBytes: 512 })).toBe('viewer 0.5 kB/s');
    expect(ratesText({ poses: 0, clouds: null, linkBytes: 0 })).toBe('0.0 poses/s · link 0.0 kB/s');
    expect(ratesText({})).toBe('');
  });
  it('gives kB/s of 1000 bytes, a decimal below 10', () => {
    expect([0, 49, 9_949, 9_950, 28_499, 1_234_400, -5].map(formatKilobytesPerSecond))
      .toEqual(['0.0 kB/s', '0.0 kB/s', '9.9 kB/s', '10 kB/s', '28 kB/s', '1,234 kB/s', '0.0 kB/s']);
  });
});

describe('vehicleLines', () => {
  it('shows each vehicle spool and only the counts that are not zero', () => {
    expect(vehicleLines(undefined)).toEqual([]);
    expect(vehicleLines([{ vehicleId: 'sim-1', spoolSamples: 1, spoolBytes: 0, skippedFrames: 0, lateFrames: 0, givenUp: 0, heldBack: 0, sessionClosed: false }]))
      .toEqual(['sim-1: spool 1 sample']);
    expect(vehicleLines([{ vehicleId: 'uav-2', spoolSamples: 1234, spoolBytes: 8300, skippedFrames: 2, lateFrames: 1, givenUp: 5, heldBack: 40, sessionClosed: true }]))
      .toEqual(['uav-2: spool 1,234 samples (8.3 kB) · 2 frames skipped · 1 frame late · 5 samples given up']);
  });
  it('says where a vehicle in its own frame is with its alignment, merged by vehicle id', () => {
    const status = [
      { vehicleId: 'sim-1', spoolSamples: 0, spoolBytes: 0, skippedFrames: 0, lateFrames: 0, givenUp: 0 },
      { vehicleId: 'sim-2', spoolSamples: 3, spoolBytes: 0, skippedFrames: 0, lateFrames: 0, givenUp: 0 },
    ];
    const aligning = { vehicleId: 'sim-2', frame: 'aligning', attempts: 4, reason: 'too little overlap', transform: null, overlap: null, rmseM: null, alignedS: null };
    expect(vehicleLines(status, [aligning]))
      .toEqual(['sim-1: spool 0 samples', 'sim-2: aligning (4 tries: too little overlap) · spool 3 samples']);
    const aligned = { vehicleId: 'sim-2', frame: 'aligned', attempts: 5, reason: '', transform: [1, 2, 0, 0, 0, 0, 1], overlap: 0.62, rmseM: 0.04, alignedS: 3.1 };
    expect(vehicleLines(status, [aligned])[1]).toBe('sim-2: aligned (overlap 62 %, rmse 0.04 m) · spool 3 samples');
    // Before its first status, and before a first try.
    expect(vehicleLines([], [{ ...aligning, vehicleId: 'sim-3', attempts: 0, reason: '' }])).toEqual(['sim-3: aligning']);
    expect(vehicleLines(undefined, [{ ...aligning, attempts: 1, reason: '' }])).toEqual(['sim-2: aligning (1 try)']);
  });
});

describe('originLines', () => {
  it('says where each session of a site was placed, and which were left out', () => {
    const yaw90 = [0, 0, Math.SQRT1_2, Math.SQRT1_2];
    expect(originLines({ site: {
      sessions: [{ session: 'mon', transform: [0, 0, 0, 0, 0, 0, 1], onto: '', overlap: null, rmseM: null },
        { session: 'tue', transform: [20, 0, 0.5, ...yaw90], onto: 'mon', overlap: 0.64, rmseM: 0.031 }],
      leftOut: [{ session: 'hall', reason: 'aligns onto none' }] } })).toEqual([
      "site in mon's frame: 2 sessions",
      'tue: moved (20.00, 0.00, 0.50) m, yaw 90.0° · onto mon: overlap 64 %, rmse 0.031 m',
      'hall: left out (aligns onto none)']);
  });

  it("gives a diff's counts, an import's file, and nothing for a flight", () => {
    expect(originLines({ diff: { first: 'a', second: 'b', appeared: 1200, disappeared: 3, unchanged: 24142, unseenByFirst: 9, unseenBySecond: 0 } })).toEqual([
      'diff a → b: 1,200 appeared, 3 disappeared, 24,142 unchanged',
      'not seen by a: 9 · by b: 0 (unknown is not free)']);
    expect(originLines({ importedFrom: 'fr_campus.bt' })).toEqual(['imported from fr_campus.bt']);
    expect(originLines(null)).toEqual([]);
  });
});
