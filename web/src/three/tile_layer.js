// The subscribed session's tiles drawn as boxes: one InstancedMesh per tile (a tile that
// changes is rebuilt alone; a tile that goes is disposed), each cell a box of its level's
// size, coloured by height over the map's z range, by occupancy probability, or by a diff
// session's change class (appeared, disappeared, unchanged).
// Entry point: TileLayer.sync(session) from the view's beforeRender.

import * as THREE from 'three';
import { changeColour, rampColour } from '../core/colour_ramp.js';
import { TILE_BITS, cellCoordinates } from '../core/tile_codec.js';

const kBoxFill = 0.92; // a box fills this fraction of its cell, so neighbours stay tellable apart
const kTileVoxels = 1 << TILE_BITS;

// The ramp sampled once, converted to three's linear working colour space.
const kRampLinear = (() => {
  const size = 256;
  const table = new Float32Array(size * 3);
  const colour = new THREE.Color();
  for (let i = 0; i < size; i += 1) {
    colour.setRGB(...rampColour(i / (size - 1)), THREE.SRGBColorSpace);
    table.set([colour.r, colour.g, colour.b], i * 3);
  }
  return table;
})();
const kRampSteps = kRampLinear.length / 3 - 1;

// A change class's colour in the linear working space, for each tile value.
const kChangeLinear = (() => {
  const table = new Float32Array(256 * 3);
  const colour = new THREE.Color();
  for (let v = 0; v < 256; v += 1) {
    colour.setRGB(...changeColour(v), THREE.SRGBColorSpace);
    table.set([colour.r, colour.g, colour.b], v * 3);
  }
  return table;
})();

export class TileLayer {
  constructor(scene) {
    this.scene = scene;
    this.geometry = new THREE.BoxGeometry(1, 1, 1);
    this.material = new THREE.MeshLambertMaterial({ color: 0xffffff });
    this.drawn = new Map(); // tile key text → {mesh, revision, box}
    this.sessionId = null;
    this.colourBy = 'height'; // or 'probability', 'change'
    this.zRange = null; // [zMin, zMax] the height ramp spans, metres
    this.count = 0; // boxes drawn
    this.bounds = new THREE.Box3(); // of the drawn boxes, metres; empty when none
  }

  get heightRange() {
    return this.colourBy === 'height' ? this.zRange : null;
  }

  setColourBy(mode) {
    if (mode === this.colourBy) return;
    this.colourBy = mode;
    this.clear(); // recoloured on the next sync
  }

  clear() {
    for (const { mesh } of this.drawn.values()) this.drop(mesh);
    this.drawn.clear();
    this.count = 0;
    this.bounds.makeEmpty();
  }

  drop(mesh) {
    this.scene.remove(mesh);
    mesh.dispose(); // frees the instance buffers; geometry and material are shared
  }

  /** Brings the meshes up to date with `session` (a SessionState or null). */
  sync(session) {
    if ((session?.id ?? null) !== this.sessionId) {
      this.clear();
      this.sessionId = session?.id ?? null;
    }
    if (!session || session.resolution === null) {
      this.clear();
      return;
    }
    // The ramp spans the map's heights as the server reports them; when they change, every
    // tile is recoloured.
    const b = session.bounds;
    const zRange = b ? [b.min[2], b.max[2]] : null;
    if (this.colourBy === 'height' && JSON.stringify(zRange) !== JSON.stringify(this.zRange)) {
      this.clear();
    }
    this.zRange = zRange;
    let changed = false;
    for (const [text, entry] of this.drawn) {
      if (!session.tiles.has(text)) {
        this.drop(entry.mesh);
        this.drawn.delete(text);
        changed = true;
      }
    }
    for (const [text, tile] of session.tiles) {
      const drawn = this.drawn.get(text);
      if (drawn?.revision === tile.revision) continue;
      if (drawn) this.drop(drawn.mesh);
      this.drawn.set(text, this.build(tile, session.resolution));
      changed = true;
    }
    if (!changed) return;
    this.count = 0;
    this.bounds.makeEmpty();
    for (const { mesh, box } of this.drawn.values()) {
      this.count += mesh.count;
      this.bounds.union(box);
    }
  }

  build(tile, resolution) {
    const n = tile.codes.length;
    const mesh = new THREE.InstancedMesh(this.geometry, this.material, n);
    mesh.instanceColor = new THREE.InstancedBufferAttribute(new Float32Array(n * 3), 3);
    const cell = resolution * 2 ** tile.level;
    const size = cell * kBoxFill;
    const origin = tile.key.map((k) => k * kTileVoxels * resolution);
    const matrices = mesh.instanceMatrix.array;
    const colours = mesh.instanceColor.array;
    const [zMin, zMax] = this.zRange ?? [0, 0];
    const box = new THREE.Box3();
    const lo = [Infinity, Infinity, Infinity];
    const hi = [-Infinity, -Infinity, -Infinity];
    for (let i = 0; i < n; i += 1) {
      const c = cellCoordinates(tile.codes[i]);
      const x = origin[0] + (c[0] + 0.5) * cell;
      const y = origin[1] + (c[1] + 0.5) * cell;
      const z = origin[2] + (c[2] + 0.5) * cell;
      // Column-major scale + translation: a box of edge `size` centred on the cell's centre.
      matrices.set([size, 0, 0, 0, 0, size, 0, 0, 0, 0, size, 0, x, y, z, 1], i * 16);
      if (this.colourBy === 'change') {
        const v = tile.values[i];
        colours.set(kChangeLinear.subarray(v * 3, v * 3 + 3), i * 3);
      } else {
        const t = this.colourBy === 'probability' ? tile.values[i] / 255
          : zMax > zMin ? Math.min(1, Math.max(0, (z - zMin) / (zMax - zMin))) : 0.5;
        const step = Math.round(t * kRampSteps);
        colours.set(kRampLinear.subarray(step * 3, step * 3 + 3), i * 3);
      }
      lo[0] = Math.min(lo[0], x); lo[1] = Math.min(lo[1], y); lo[2] = Math.min(lo[2], z);
      hi[0] = Math.max(hi[0], x); hi[1] = Math.max(hi[1], y); hi[2] = Math.max(hi[2], z);
    }
    if (n > 0) box.set(new THREE.Vector3(...lo).subScalar(cell / 2), new THREE.Vector3(...hi).addScalar(cell / 2));
    mesh.boundingBox = box.clone();
    mesh.boundingSphere = box.getBoundingSphere(new THREE.Sphere());
    this.scene.add(mesh);
    return { mesh, revision: tile.revision, box };
  }
}
