import { describe, expect, it } from 'vitest';
import { MapStore } from './map_state.js';
import { parseMessage } from './protocol.js';

function apply(store, fields, nowMs = 0) {
  return store.apply(parseMessage(JSON.stringify(fields)), nowMs);
}

const voxels = (version, fields) => ({ type: 'voxels', session: 'demo', resolution: 0.1, version, ...fields });
const pose = (t) => [t, t, 0, 1, 0, 0, 0, 1];
const keys = (store, id = 'demo') => [...store.sessions.get(id).voxels.keys()].sort();

describe('MapStore voxels', () => {
  it('applies reset, add and remove to the exact set', () => {
    const store = new MapStore();
    apply(store, voxels(1, { reset: true, add: [0, 0, 0, 1, 2, 3, -4, 5, -6] }));
    apply(store, voxels(2, { add: [7, 7, 7], remove: [1, 2, 3] }));
    apply(store, voxels(3, { remove: [9, 9, 9] })); // removing an absent voxel changes nothing
    expect(keys(store)).toEqual(['-4,5,-6', '0,0,0', '7,7,7']);
    apply(store, voxels(4, { reset: true, add: [1, 1, 1] }));
    expect(keys(store)).toEqual(['1,1,1']);
    expect(store.sessions.get('demo').voxelVersion).toBe(4);
  });

  it('keeps a duplicate add as one voxel', () => {
    const store = new MapStore();
    apply(store, voxels(1, { reset: true, add: [1, 1, 1, 1, 1, 1] }));
    expect(store.sessions.get('demo').voxels.size).toBe(1);
  });

  it('rejects a stale delta without changing the set', () => {
    const store = new MapStore();
    apply(store, voxels(5, { reset: true, add: [1, 1, 1] }));
    const revision = store.sessions.get('demo').voxelRevision;
    expect(() => apply(store, voxels(5, { remove: [1, 1, 1] }))).toThrow(/version 5 is not newer than version 5/);
    expect(keys(store)).toEqual(['1,1,1']);
    expect(store.sessions.get('demo').voxelRevision).toBe(revision);
  });

  it('is not corrupted by malformed messages', () => {
    const store = new MapStore();
    apply(store, voxels(1, { reset: true, add: [1, 1, 1, 2, 2, 2] }));
    for (const bad of [voxels(2, { remove: [1, 1] }), voxels(2, { add: 'x' }), voxels(2, { add: [3, 3, 3], remove: [2, 2, null] })]) {
      expect(() => apply(store, bad)).toThrow();
    }
    expect(keys(store)).toEqual(['1,1,1', '2,2,2']);
    apply(store, voxels(2, { remove: [2, 2, 2] })); // version 2 was never applied, so it is still accepted
    expect(keys(store)).toEqual(['1,1,1']);
  });

  it('keeps sessions apart and follows the latest message', () => {
    const store = new MapStore();
    apply(store, voxels(1, { reset: true, add: [1, 1, 1] }), 10);
    apply(store, { ...voxels(1, { reset: true, add: [2, 2, 2] }), session: 'other' }, 20);
    expect(keys(store)).toEqual(['1,1,1']);
    expect(keys(store, 'other')).toEqual(['2,2,2']);
    expect(store.latestSessionId).toBe('other');
    apply(store, voxels(2, { add: [3, 3, 3] }), 30);
    expect(store.latestSessionId).toBe('demo');
    expect(store.sessions.get('demo').lastMessageMs).toBe(30);
  });

  it('forgets sessions when a new hello arrives', () => {
    const store = new MapStore();
    apply(store, voxels(1, { reset: true, add: [1, 1, 1] }));
    apply(store, { type: 'hello', protocol: 1, server: 'stereomap 0.1.0' });
    expect(store.sessions.size).toBe(0);
    expect(store.latestSessionId).toBeNull();
  });
});

describe('MapStore poses and status', () => {
  it('appends poses and replaces them on reset', () => {
    const store = new MapStore();
    apply(store, { type: 'poses', session: 'demo', vehicle: 'sim-1', reset: true, poses: [pose(1), pose(2)] });
    apply(store, { type: 'poses', session: 'demo', vehicle: 'sim-1', poses: [pose(3)] });
    const state = store.sessions.get('demo');
    expect(state.poses.map((p) => p[0])).toEqual([1, 2, 3]);
    const epoch = state.poseEpoch;
    apply(store, { type: 'poses', session: 'demo', vehicle: 'sim-1', reset: true, poses: [pose(9)] });
    expect(state.poses.map((p) => p[0])).toEqual([9]);
    expect(state.poseEpoch).not.toBe(epoch);
  });

  it('records the session status', () => {
    const store = new MapStore();
    apply(store, { type: 'session', id: 'demo', vehicle: 'sim-1', resolution: 0.2, frames: 12, occupied_voxels: 34, bounds: null });
    expect(store.sessions.get('demo')).toMatchObject({ vehicle: 'sim-1', resolution: 0.2, frames: 12, serverVoxels: 34, bounds: null });
  });

  it('forgets a session the server removed', () => {
    const store = new MapStore();
    apply(store, { type: 'session', id: 'old', vehicle: 'v', resolution: 0.1, frames: 1, occupied_voxels: 0, bounds: null });
    apply(store, { type: 'session', id: 'new', vehicle: 'v', resolution: 0.1, frames: 1, occupied_voxels: 0, bounds: null });
    expect(apply(store, { type: 'session_removed', id: 'new' })).toBeNull();
    expect([...store.sessions.keys()]).toEqual(['old']);
    expect(store.latestSessionId).toBe('old');
    apply(store, { type: 'session_removed', id: 'unknown' });
    expect(store.sessions.size).toBe(1);
  });

  it('ignores server error replies', () => {
    const store = new MapStore();
    expect(apply(store, { type: 'error', message: 'unknown request' })).toBeNull();
    expect(store.sessions.size).toBe(0);
  });
});
