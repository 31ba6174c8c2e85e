import { describe, expect, it } from 'vitest';
import { TileCache } from './tile_cache.js';

const tile = (key, cells) => ({ key, level: 0, version: 1, codes: new Uint32Array(cells), values: new Uint8Array(cells) });

describe('TileCache', () => {
  it('counts bytes and evicts the tiles farthest from the camera, never the new one', () => {
    const one = TileCache.bytesOf(tile([0, 0, 0], 100)); // 100 cells: 500 bytes and the overhead
    const cache = new TileCache(3 * one);
    cache.setEye([0, 0, 0], 0.1);
    expect(cache.set('0_0_0', tile([0, 0, 0], 100))).toEqual([]);
    expect(cache.set('5_0_0', tile([5, 0, 0], 100))).toEqual([]);
    expect(cache.set('1_0_0', tile([1, 0, 0], 100))).toEqual([]);
    expect(cache.bytes).toBe(3 * one);
    expect(cache.set('9_0_0', tile([9, 0, 0], 100))).toEqual(['5_0_0']); // the new, farthest one stays
    expect([...cache.keys()].sort()).toEqual(['0_0_0', '1_0_0', '9_0_0']);
    expect(cache.set('2_0_0', tile([2, 0, 0], 200))).toEqual(['9_0_0', '1_0_0']);
    expect(cache.bytes).toBeLessThanOrEqual(3 * one);
  });

  it('replaces a tile in place and forgets deleted ones', () => {
    const cache = new TileCache();
    cache.set('a', tile([0, 0, 0], 10));
    cache.set('a', tile([0, 0, 0], 20));
    expect(cache.size).toBe(1);
    expect(cache.bytes).toBe(TileCache.bytesOf(tile([0, 0, 0], 20)));
    cache.delete('a');
    expect(cache.bytes).toBe(0);
    expect([...cache]).toEqual([]);
  });
});
