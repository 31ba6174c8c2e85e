import * as THREE from 'three';
import { describe, expect, it } from 'vitest';
import { MapStore } from '../core/map_state.js';
import { TileLayer } from './tile_layer.js';

// Cell code of (x, y, z) inside a tile: Morton, x lowest.
function code(x, y, z) {
  let c = 0;
  for (let bit = 0; bit < 6; bit += 1) {
    c |= ((x >> bit) & 1) << (3 * bit) | ((y >> bit) & 1) << (3 * bit + 1) | ((z >> bit) & 1) << (3 * bit + 2);
  }
  return c;
}

function sessionWith(tiles) {
  const store = new MapStore();
  const session = store.subscribe('s');
  session.resolution = 0.5;
  session.bounds = { min: [0, 0, 0], max: [64, 64, 2] };
  for (const [key, level, cells, version = 1] of tiles) {
    store.applyTile({ header: { session: 's', key, level, version, resolution: 0.5 }, codes: Uint32Array.from(cells.map((c) => code(...c))), values: new Uint8Array(cells.length).fill(255) });
  }
  return { store, session };
}

describe('TileLayer', () => {
  it('draws each cell as a box of its level at its centre', () => {
    const scene = new THREE.Scene();
    const layer = new TileLayer(scene);
    const { session } = sessionWith([[[0, 0, 0], 0, [[0, 0, 0], [1, 2, 3]]], [[-1, 0, 0], 2, [[15, 0, 0]]]]);
    layer.sync(session);
    expect(layer.count).toBe(3);
    expect(scene.children).toHaveLength(2);
    const matrix = new THREE.Matrix4();
    const position = new THREE.Vector3();
    const scale = new THREE.Vector3();
    const coarse = layer.drawn.get('-1_0_0').mesh;
    coarse.getMatrixAt(0, matrix);
    matrix.decompose(position, new THREE.Quaternion(), scale);
    // Tile -1 starts at x = -32 m; cell 15 of 2 m cells ends at its far edge.
    expect(position.toArray()).toEqual([-1, 1, 1]);
    expect(scale.x).toBeCloseTo(2 * 0.92, 6);
    expect(layer.bounds.min.x).toBe(-2);
    expect(layer.bounds.max.toArray()).toEqual([1, 2, 2]); // the coarse cell reaches 2 m up and across
  });

  it('rebuilds only changed tiles and disposes those that go', () => {
    const scene = new THREE.Scene();
    const layer = new TileLayer(scene);
    const { store, session } = sessionWith([[[0, 0, 0], 0, [[0, 0, 0]]], [[1, 0, 0], 0, [[0, 0, 0]]]]);
    layer.sync(session);
    const kept = layer.drawn.get('0_0_0').mesh;
    let disposed = 0;
    layer.drawn.get('1_0_0').mesh.addEventListener('dispose', () => { disposed += 1; });
    store.applyTile({ header: { session: 's', key: [1, 0, 0], level: 0, version: 2, resolution: 0.5 }, codes: new Uint32Array(0), values: new Uint8Array(0) });
    layer.sync(session);
    expect(layer.drawn.get('0_0_0').mesh).toBe(kept);
    expect(disposed).toBe(1);
    expect(layer.count).toBe(1);
    expect(scene.children).toHaveLength(1);
    layer.sync(null);
    expect(scene.children).toHaveLength(0);
  });
});
