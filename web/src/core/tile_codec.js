// The tile wire format (proto/tiles/FORMAT.md) in the browser: decodeTiles() reads one or
// more tiles sent back to back, checking every size before it trusts it. Compressed payloads
// (zlib) are inflated by fflate. The functions stay async so that callers need not change.

import { unzlibSync } from 'fflate';

const MAGIC = [0x53, 0x4d, 0x54, 0x4c]; // "SMTL"
const FIXED_HEADER = 49;
export const TILE_BITS = 6;
export const LEVELS = TILE_BITS + 1;

export class TileFormatError extends Error {}

// zlib (RFC 1950) by fflate, synchronously: the platform's DecompressionStream was seen to
// leave a promise pending for good in a busy headless chromium, and one stuck tile stalls every
// message after it.
function inflate(bytes, expected) {
  let out;
  try {
    out = unzlibSync(bytes, { out: new Uint8Array(expected) });
  } catch (e) {
    throw new TileFormatError(`tile payload does not inflate: ${e.message}`);
  }
  if (out.length !== expected) {
    throw new TileFormatError(`tile payload inflates to ${out.length} bytes, not ${expected}`);
  }
  return out;
}

// Cells from the level-ordered child masks (FORMAT.md, Payload 1): ascending codes.
function cellsFromMasks(raw, maskLevels, count) {
  let nodes = [0];
  let at = 0;
  for (let depth = 0; depth < maskLevels && count > 0; depth++) {
    const next = [];
    for (const node of nodes) {
      if (at >= raw.length) throw new TileFormatError('tile masks are truncated');
      const mask = raw[at++];
      if (mask === 0) throw new TileFormatError('tile has an empty child mask');
      for (let child = 0; child < 8; child++) {
        if (mask & (1 << child)) next.push(node * 8 + child);
      }
      if (next.length > count) throw new TileFormatError('tile masks hold more cells than its count');
    }
    nodes = next;
  }
  if (count > 0 && nodes.length !== count) {
    throw new TileFormatError(`tile masks hold ${nodes.length} cells, its header says ${count}`);
  }
  if (raw.length - at !== count) {
    throw new TileFormatError(`tile values: ${raw.length - at} bytes for ${count} cells`);
  }
  return { codes: count > 0 ? Uint32Array.from(nodes) : new Uint32Array(0), values: raw.slice(at) };
}

// One tile from the start of `bytes` (a Uint8Array): { header, codes, values, size }.
export async function decodeTile(bytes) {
  if (bytes.length < FIXED_HEADER) throw new TileFormatError(`a tile is at least ${FIXED_HEADER} bytes`);
  for (let i = 0; i < 4; i++) {
    if (bytes[i] !== MAGIC[i]) throw new TileFormatError('not a tile (no SMTL magic)');
  }
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  if (bytes[4] !== 1) throw new TileFormatError(`tile format ${bytes[4]} is not 1`);
  const level = bytes[5];
  if (bytes[6] !== TILE_BITS || level > TILE_BITS) throw new TileFormatError('tile size or level out of range');
  const flags = bytes[7];
  if (flags & ~1) throw new TileFormatError('unknown tile flags');
  const key = [view.getInt32(8, true), view.getInt32(12, true), view.getInt32(16, true)];
  const version = Number(view.getBigUint64(20, true));
  const count = view.getUint32(28, true);
  const resolution = view.getFloat64(32, true);
  const storedBytes = view.getUint32(40, true);
  const rawBytes = view.getUint32(44, true);
  const sessionBytes = bytes[48];
  const maskLevels = TILE_BITS - level;
  if (count > 8 ** maskLevels || !(resolution > 0) || sessionBytes === 0 || sessionBytes > 64) {
    throw new TileFormatError('tile header out of range');
  }
  if (rawBytes > count * (maskLevels + 1) || (!(flags & 1) && storedBytes !== rawBytes)) {
    throw new TileFormatError('tile payload sizes out of range');
  }
  const size = FIXED_HEADER + sessionBytes + storedBytes;
  if (bytes.length < size) throw new TileFormatError(`tile is truncated: ${bytes.length} of ${size} bytes`);
  const session = new TextDecoder().decode(bytes.subarray(FIXED_HEADER, FIXED_HEADER + sessionBytes));
  const stored = bytes.subarray(FIXED_HEADER + sessionBytes, size);
  const raw = flags & 1 ? inflate(stored, rawBytes) : stored;
  const { codes, values } = cellsFromMasks(raw, maskLevels, count);
  return { header: { session, key, level, version, resolution }, codes, values, size };
}

// Every tile in `bytes`, sent back to back.
export async function decodeTiles(bytes) {
  const tiles = [];
  for (let at = 0; at < bytes.length; ) {
    const tile = await decodeTile(bytes.subarray(at));
    tiles.push(tile);
    at += tile.size;
  }
  return tiles;
}

// A cell's coordinates inside its tile (0 .. 2^(6 - level) - 1 per axis).
export function cellCoordinates(code) {
  let x = 0;
  let y = 0;
  let z = 0;
  for (let bit = 0; bit < TILE_BITS; bit++) {
    x |= ((code >> (3 * bit)) & 1) << bit;
    y |= ((code >> (3 * bit + 1)) & 1) << bit;
    z |= ((code >> (3 * bit + 2)) & 1) << bit;
  }
  return [x, y, z];
}
