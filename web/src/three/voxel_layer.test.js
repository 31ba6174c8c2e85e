import * as THREE from 'three';
import { describe, expect, it } from 'vitest';
import { kHeightRamp } from '../core/colour_ramp.js';
import { voxelKey } from '../core/map_state.js';
import { VoxelLayer } from './voxel_layer.js';

const voxelMap = (triples) => new Map(triples.map((t) => [voxelKey(...t), t]));
const linear = (srgb) => new THREE.Color().setRGB(...srgb, THREE.SRGBColorSpace).toArray();

describe('VoxelLayer', () => {
  it('places one box per voxel at its centre, coloured by height', () => {
    const scene = new THREE.Scene();
    const layer = new VoxelLayer(scene);
    layer.setVoxels(voxelMap([[0, 0, 0], [-2, 3, 4], [1, 1, 2]]), 0.5);
    expect(layer.count).toBe(3);
    const matrix = new THREE.Matrix4();
    const position = new THREE.Vector3();
    const scale = new THREE.Vector3();
    layer.mesh.getMatrixAt(1, matrix);
    matrix.decompose(position, new THREE.Quaternion(), scale);
    expect(position.toArray()).toEqual([-0.75, 1.75, 2.25]);
    expect(scale.x).toBeCloseTo(0.46, 6); // 0.5 m cells, boxes a little smaller
    const colour = new THREE.Color();
    expect(layer.mesh.getColorAt(0, colour).toArray().map((c) => +c.toFixed(5))).toEqual(linear(kHeightRamp[0]).map((c) => +c.toFixed(5)));
    expect(layer.mesh.getColorAt(1, colour).toArray().map((c) => +c.toFixed(5))).toEqual(linear(kHeightRamp.at(-1)).map((c) => +c.toFixed(5)));
    expect(layer.heightRange).toEqual([0.25, 2.25]);
    expect(layer.bounds.min.toArray()).toEqual([-1, 0, 0]);
    expect(layer.bounds.max.toArray()).toEqual([1, 2, 2.5]);
  });

  it('doubles its capacity with a new mesh, keeping one in the scene', () => {
    const scene = new THREE.Scene();
    const layer = new VoxelLayer(scene);
    layer.setVoxels(voxelMap([[0, 0, 0]]), 0.1);
    const first = layer.mesh;
    const many = Array.from({ length: 1500 }, (_, i) => [i, 0, i % 7]);
    layer.setVoxels(voxelMap(many), 0.1);
    expect(layer.mesh).not.toBe(first);
    expect(layer.mesh.instanceMatrix.count).toBe(2048);
    expect(layer.count).toBe(1500);
    expect(scene.children.filter((c) => c.isInstancedMesh)).toEqual([layer.mesh]);
    const last = new THREE.Matrix4();
    layer.mesh.getMatrixAt(1499, last);
    expect(last.elements[12]).toBeCloseTo(149.95, 4); // float32 storage
  });

  it('draws nothing for an empty set', () => {
    const layer = new VoxelLayer(new THREE.Scene());
    layer.setVoxels(voxelMap([[1, 2, 3]]), 0.1);
    layer.setVoxels(new Map(), 0.1);
    expect(layer.count).toBe(0);
    expect(layer.heightRange).toBeNull();
    expect(layer.bounds.isEmpty()).toBe(true);
  });
});
