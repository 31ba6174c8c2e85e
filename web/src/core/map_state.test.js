import { describe, expect, it } from 'vitest';
import { MapStore } from './map_state.js';
import { parseMessage } from './protocol.js';

const status = (id, state, frames = 1) => ({ id, vehicle: 'uav', state, resolution: 0.1, frames, occupied_voxels: 4, poses: 0, bounds: null });
const tile = (session, key, version, codes) => ({
  header: { session, key, level: 0, version, resolution: 0.1 },
  codes: Uint32Array.from(codes),
  values: new Uint8Array(codes.length).fill(200),
});

describe('MapStore', () => {
  it('lists sessions and follows the live one that appeared last', () => {
    const store = new MapStore();
    store.apply(parseMessage(JSON.stringify({ type: 'sessions', sessions: [status('a', 'live'), status('b', 'closed'), status('c', 'live')] })));
    expect(store.latestSessionId).toBe('c');
    // Updates of live sessions interleave (several vehicles): the followed one stays.
    for (let i = 0; i < 6; ++i) {
      store.apply(parseMessage(JSON.stringify({ type: 'session', ...status(i % 2 ? 'a' : 'c', 'live', i) })));
      expect(store.latestSessionId).toBe('c');
    }
    // A new flight is followed; when it ends, the newest live one before it.
    store.apply(parseMessage(JSON.stringify({ type: 'session', ...status('d', 'live', 1) })));
    expect(store.latestSessionId).toBe('d');
    store.apply(parseMessage(JSON.stringify({ type: 'session', ...status('d', 'ended', 2) })));
    expect(store.latestSessionId).toBe('c');
    store.apply(parseMessage('{"type":"session_removed","id":"c"}'));
    expect(store.latestSessionId).toBe('a');
    // No live session: a loaded one before a stored one, whatever the order.
    store.apply(parseMessage(JSON.stringify({ type: 'sessions', sessions: [status('e', 'ended'), status('f', 'closed')] })));
    expect(store.latestSessionId).toBe('e');
  });

  it('keeps the subscribed session\'s tiles, newest version wins, empty tiles go', () => {
    const store = new MapStore();
    const mine = store.subscribe('s');
    expect(store.applyTile(tile('other', [0, 0, 0], 1, [1]))).toBe(false);
    store.applyTile(tile('s', [0, 0, 0], 2, [1, 2, 3]));
    store.applyTile(tile('s', [1, 0, 0], 2, [5]));
    expect(mine.cells).toBe(4);
    store.applyTile(tile('s', [0, 0, 0], 1, [1])); // late and older: ignored
    expect(mine.cells).toBe(4);
    store.applyTile(tile('s', [1, 0, 0], 3, []));
    expect(mine.cells).toBe(3);
    expect([...mine.tiles.keys()]).toEqual(['0_0_0']);
  });

  it('takes poses, map markers and statuses for the subscribed session only', () => {
    const store = new MapStore();
    const mine = store.subscribe('s');
    store.apply(parseMessage('{"type":"poses","session":"s","vehicle":"uav","reset":true,"poses":[[1,0,0,0,0,0,0,1]]}'), 1000);
    store.apply(parseMessage('{"type":"poses","session":"t","vehicle":"uav","poses":[[1,0,0,0,0,0,0,1]]}'));
    expect(mine.poseCount).toBe(1);
    // Each vehicle its own trajectory.
    store.apply(parseMessage('{"type":"poses","session":"s","vehicle":"uav-2","poses":[[2,5,0,0,0,0,0,1],[3,6,0,0,0,0,0,1]]}'), 2000);
    expect(mine.trajectories.get('uav').poses).toHaveLength(1);
    expect(mine.trajectories.get('uav-2').poses).toHaveLength(2);
    expect(mine.latestVehicle).toBe('uav-2');
    store.apply(parseMessage('{"type":"map","session":"s","version":3,"changed_ms":1000,"voxels":7,"tiles":1,"bounds":null}'), 1500);
    expect(mine.serverVoxels).toBe(7);
    expect(store.lastLatency).toBe(500);
    store.apply(parseMessage(JSON.stringify({ type: 'session', ...status('s', 'live', 9) })));
    expect(mine.frames).toBe(9);
  });

  it('starts a replay afresh and keeps the whole flight\'s time span for the slider', () => {
    const store = new MapStore();
    const mine = store.subscribe('s');
    store.apply(parseMessage('{"type":"poses","session":"s","vehicle":"uav","reset":true,"poses":[[10,0,0,0,0,0,0,1],[20,1,0,0,0,0,0,1]]}'));
    store.applyTile(tile('s', [0, 0, 0], 5, [1, 2]));
    expect(mine.timeRange).toEqual([10, 20]);
    store.apply(parseMessage('{"type":"replayed","session":"s","until":15,"frames":1,"voxels":1,"bounds":null}'));
    expect(mine.replayUntil).toBe(15);
    expect(mine.frames).toBe(1);
    expect(mine.cells).toBe(0);
    store.applyTile(tile('s', [0, 0, 0], 1, [1])); // the replay's own versions start low
    store.apply(parseMessage('{"type":"poses","session":"s","vehicle":"uav","reset":true,"poses":[[10,0,0,0,0,0,0,1]]}'));
    expect(mine.cells).toBe(1);
    expect(mine.timeRange).toEqual([10, 20]);
  });

  it('hands back the tiles its cache evicts, to tell the server', () => {
    const store = new MapStore(1); // a budget of one byte: only the newest tile stays
    const mine = store.subscribe('s');
    store.applyTile(tile('s', [0, 0, 0], 1, [1]));
    store.applyTile(tile('s', [1, 0, 0], 1, [2]));
    expect([...mine.tiles.keys()]).toEqual(['1_0_0']);
    expect(mine.evicted).toEqual(['0_0_0']);
  });
});
