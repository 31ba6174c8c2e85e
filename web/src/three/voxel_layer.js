// Occupied voxels drawn as one InstancedMesh of unit boxes, scaled to the map resolution and
// coloured by height. Entry point: VoxelLayer.setVoxels(); the mesh is re-created with doubled
// capacity when the set outgrows it (instance buffers cannot be resized in place).

import * as THREE from 'three';
import { rampColour } from '../core/colour_ramp.js';

const kInitialCapacity = 1024;
const kBoxFill = 0.92; // a box fills this fraction of its cell, so neighbours stay tellable apart

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

export class VoxelLayer {
  constructor(scene) {
    this.scene = scene;
    this.geometry = new THREE.BoxGeometry(1, 1, 1);
    this.material = new THREE.MeshLambertMaterial({ color: 0xffffff });
    this.mesh = null;
    this.bounds = new THREE.Box3(); // of the drawn boxes, metres; empty when none
    this.heightRange = null; // [zMin, zMax] of voxel centres that the ramp spans, metres
  }

  get count() {
    return this.mesh ? this.mesh.count : 0;
  }

  ensureCapacity(count) {
    const capacity = this.mesh ? this.mesh.instanceMatrix.count : 0;
    if (count <= capacity) return;
    let grown = capacity || kInitialCapacity;
    while (grown < count) grown *= 2;
    if (this.mesh) {
      this.scene.remove(this.mesh);
      this.mesh.dispose(); // frees the instance buffers; geometry and material are reused
    }
    this.mesh = new THREE.InstancedMesh(this.geometry, this.material, grown);
    this.mesh.instanceMatrix.setUsage(THREE.DynamicDrawUsage);
    this.mesh.instanceColor = new THREE.InstancedBufferAttribute(new Float32Array(grown * 3), 3);
    this.mesh.instanceColor.setUsage(THREE.DynamicDrawUsage);
    this.mesh.frustumCulled = false; // instances are written directly, so three's bounding sphere would be stale
    this.scene.add(this.mesh);
  }

  /** Draws `voxels` (a Map whose values are [ix, iy, iz]) as boxes of `resolution` metres. */
  setVoxels(voxels, resolution) {
    const count = voxels.size;
    this.ensureCapacity(count);
    this.bounds.makeEmpty();
    this.heightRange = null;
    if (!this.mesh) return;
    this.mesh.count = count;
    if (count === 0) return;

    // First pass: index bounds, which the height ramp and the camera framing need.
    const lo = [Infinity, Infinity, Infinity];
    const hi = [-Infinity, -Infinity, -Infinity];
    for (const index of voxels.values()) {
      for (let axis = 0; axis < 3; axis += 1) {
        lo[axis] = Math.min(lo[axis], index[axis]);
        hi[axis] = Math.max(hi[axis], index[axis]);
      }
    }
    this.bounds.min.fromArray(lo).multiplyScalar(resolution);
    this.bounds.max.fromArray(hi).addScalar(1).multiplyScalar(resolution);
    this.heightRange = [(lo[2] + 0.5) * resolution, (hi[2] + 0.5) * resolution];

    const matrices = this.mesh.instanceMatrix.array;
    const colours = this.mesh.instanceColor.array;
    const size = resolution * kBoxFill;
    const rampSteps = kRampLinear.length / 3 - 1;
    const zSpan = hi[2] - lo[2];
    let i = 0;
    for (const [ix, iy, iz] of voxels.values()) {
      // Column-major scale + translation: a box of edge `size` centred on the voxel's centre.
      matrices.set([size, 0, 0, 0, 0, size, 0, 0, 0, 0, size, 0,
        (ix + 0.5) * resolution, (iy + 0.5) * resolution, (iz + 0.5) * resolution, 1], i * 16);
      const step = zSpan > 0 ? Math.round(((iz - lo[2]) / zSpan) * rampSteps) : Math.round(rampSteps / 2);
      colours.set(kRampLinear.subarray(step * 3, step * 3 + 3), i * 3);
      i += 1;
    }

    for (const attribute of [this.mesh.instanceMatrix, this.mesh.instanceColor]) {
      attribute.clearUpdateRanges();
      attribute.addUpdateRange(0, count * attribute.itemSize); // upload only what is drawn
      attribute.needsUpdate = true;
    }
  }
}
