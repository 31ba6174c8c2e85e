// The tiles a viewer holds, with their bytes counted against a budget (the page's memory for
// the map). When a tile would take the cache past its budget, the tiles farthest from the
// camera go first (never the one just stored), and their keys are handed back so that the
// server can be told (it sends them again when a view needs them). The server's view plan
// already bounds what it sends by a cell budget; this is the page's own bound. Map-like:
// get, has, set, delete, clear, size, and iteration over [key text, tile].

const kTileOverheadBytes = 96; // the entry, its arrays' headers and the Map's slot, roughly
const kTileVoxels = 64;

export class TileCache {
  /** `budgetBytes`: what the tiles' cells may take together. */
  constructor(budgetBytes = 256 * 2 ** 20) {
    this.budgetBytes = budgetBytes;
    this.bytes = 0;
    this.map = new Map(); // key text → {key: [x, y, z], level, version, codes, values, ...}
    this.eye = null; // camera position (metres) that eviction measures from
    this.resolution = 1; // metres per voxel, to place tiles
  }

  static bytesOf(tile) {
    return tile.codes.byteLength + tile.values.byteLength + kTileOverheadBytes;
  }

  get size() {
    return this.map.size;
  }

  get(text) {
    return this.map.get(text);
  }

  has(text) {
    return this.map.has(text);
  }

  keys() {
    return this.map.keys();
  }

  values() {
    return this.map.values();
  }

  [Symbol.iterator]() {
    return this.map[Symbol.iterator]();
  }

  /** Where the camera is: tiles far from it are evicted first. */
  setEye(eye, resolution) {
    this.eye = eye;
    this.resolution = resolution;
  }

  /** Stores `tile` under `text`; returns the key texts evicted to stay within the budget. */
  set(text, tile) {
    this.delete(text);
    this.map.set(text, tile);
    this.bytes += TileCache.bytesOf(tile);
    if (this.bytes <= this.budgetBytes) return [];
    const edge = kTileVoxels * this.resolution;
    const distance = ([x, y, z]) => {
      if (!this.eye) return 0;
      const centre = [x, y, z].map((k) => (k + 0.5) * edge);
      return Math.hypot(centre[0] - this.eye[0], centre[1] - this.eye[1], centre[2] - this.eye[2]);
    };
    const farthestFirst = [...this.map.entries()].filter(([key]) => key !== text)
      .sort((a, b) => distance(b[1].key) - distance(a[1].key));
    const evicted = [];
    for (const [key] of farthestFirst) {
      if (this.bytes <= this.budgetBytes) break;
      this.delete(key);
      evicted.push(key);
    }
    return evicted;
  }

  delete(text) {
    const held = this.map.get(text);
    if (!held) return false;
    this.bytes -= TileCache.bytesOf(held);
    return this.map.delete(text);
  }

  clear() {
    this.map.clear();
    this.bytes = 0;
  }
}
