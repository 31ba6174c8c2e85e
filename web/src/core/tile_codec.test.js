import { readFileSync } from 'node:fs';
import { fileURLToPath } from 'node:url';
import { describe, expect, it } from 'vitest';
import { cellCoordinates, decodeTile, decodeTiles, TileFormatError } from './tile_codec.js';

// The golden tiles the C++ encoder writes (proto/tiles/tile_codec_test.cpp).
const fixtures = fileURLToPath(new URL('../../../proto/tiles/fixtures/', import.meta.url));
const golden = JSON.parse(readFileSync(fixtures + 'cells.json', 'utf8'));
const bytesOf = (name) => new Uint8Array(readFileSync(fixtures + name));

describe('decodeTile', () => {
  it.each(golden.map((g) => [g.file, g]))('decodes %s as the C++ encoder wrote it', async (_, g) => {
    const tile = await decodeTile(bytesOf(g.file));
    expect(tile.header).toEqual({
      session: g.session, key: g.key, level: g.level, version: g.version, resolution: g.resolution,
    });
    expect(Array.from(tile.codes)).toEqual(g.codes);
    expect(Array.from(tile.values)).toEqual(g.values);
  });

  it('reads tiles sent back to back', async () => {
    const a = bytesOf(golden[0].file);
    const b = bytesOf(golden[1].file);
    const both = new Uint8Array(a.length + b.length);
    both.set(a);
    both.set(b, a.length);
    const tiles = await decodeTiles(both);
    expect(tiles.map((t) => t.header.level)).toEqual([golden[0].level, golden[1].level]);
  });

  it('rejects every truncation and never throws anything but a TileFormatError', async () => {
    const good = bytesOf(golden[0].file);
    for (let size = 0; size < good.length; size++) {
      await expect(decodeTile(good.subarray(0, size))).rejects.toBeInstanceOf(TileFormatError);
    }
    for (let at = 0; at < good.length; at++) {
      const bad = good.slice();
      bad[at] ^= 0x5a;
      try {
        const tile = await decodeTile(bad);
        expect(tile.codes.length).toBe(tile.values.length);
      } catch (e) {
        expect(e).toBeInstanceOf(TileFormatError);
      }
    }
  });
});

describe('cellCoordinates', () => {
  it('undoes the Morton interleave (x lowest)', () => {
    expect(cellCoordinates(0b001)).toEqual([1, 0, 0]);
    expect(cellCoordinates(0b010)).toEqual([0, 1, 0]);
    expect(cellCoordinates(0b100)).toEqual([0, 0, 1]);
    expect(cellCoordinates(0b111111)).toEqual([3, 3, 3]);
  });
});
