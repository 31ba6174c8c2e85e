// A session's trajectory: a line through the body positions plus a marker (a cone along body +x
// with small axes) at the latest pose T_map_body. Entry point: TrajectoryLayer.setPoses().
// Appended poses are written incrementally; the buffer doubles when full.

import * as THREE from 'three';

const kInitialCapacity = 256;
const scratch = new THREE.Vector3();

export class TrajectoryLayer {
  /** `colour`: of the line (each vehicle its own). */
  constructor(scene, colour = 0xf5f5f5) {
    this.scene = scene;
    this.material = new THREE.LineBasicMaterial({ color: colour });
    this.line = new THREE.Line(new THREE.BufferGeometry(), this.material);
    this.line.frustumCulled = false; // the buffer grows in place; a cached bounding sphere would be stale
    this.drawn = 0; // poses in the line
    this.epoch = null; // SessionState.poseEpoch the line was built from
    this.bounds = new THREE.Box3(); // of the drawn positions, metres

    this.marker = new THREE.Group();
    const cone = new THREE.Mesh(new THREE.ConeGeometry(0.3, 1, 20),
      new THREE.MeshLambertMaterial({ color: 0xff3df2, emissive: 0x551050 }));
    cone.rotation.z = -Math.PI / 2; // the cone's axis is +y; point it along body +x (forward)
    cone.position.x = 0.5;
    this.marker.add(cone, new THREE.AxesHelper(0.8));
    this.marker.visible = false;
    scene.add(this.line, this.marker);
  }

  get length() {
    return this.drawn;
  }

  /** Marker size in metres, so it stays visible on maps of any extent. */
  setMarkerScale(metres) {
    this.marker.scale.setScalar(metres);
  }

  /** Draws `poses` ([t, x, y, z, qx, qy, qz, qw] each); `epoch` changes when they were replaced. */
  setPoses(poses, epoch) {
    if (epoch !== this.epoch || poses.length < this.drawn) {
      this.epoch = epoch;
      this.drawn = 0;
      this.bounds.makeEmpty();
    }
    this.ensureCapacity(poses.length);
    const position = this.line.geometry.getAttribute('position');
    const first = this.drawn;
    for (let i = first; i < poses.length; i += 1) {
      const [, x, y, z] = poses[i];
      position.setXYZ(i, x, y, z);
      this.bounds.expandByPoint(scratch.set(x, y, z));
    }
    if (poses.length > first) {
      position.addUpdateRange(first * 3, (poses.length - first) * 3); // three clears ranges once uploaded
      position.needsUpdate = true;
    }
    this.drawn = poses.length;
    this.line.geometry.setDrawRange(0, this.drawn);

    this.marker.visible = this.drawn > 0;
    if (this.drawn > 0) {
      const [, x, y, z, qx, qy, qz, qw] = poses[this.drawn - 1];
      this.marker.position.set(x, y, z);
      this.marker.quaternion.set(qx, qy, qz, qw).normalize();
    }
  }

  /** Removes the line and marker from the scene and frees their buffers. */
  dispose() {
    this.scene.remove(this.line, this.marker);
    this.line.geometry.dispose();
    this.material.dispose();
    this.marker.traverse((object) => {
      object.geometry?.dispose();
      object.material?.dispose();
    });
  }

  ensureCapacity(count) {
    const old = this.line.geometry.getAttribute('position');
    const capacity = old ? old.count : 0;
    if (count <= capacity) return;
    let grown = capacity || kInitialCapacity;
    while (grown < count) grown *= 2;
    const position = new THREE.BufferAttribute(new Float32Array(grown * 3), 3);
    position.setUsage(THREE.DynamicDrawUsage);
    if (old) position.array.set(old.array);
    // A new geometry, because WebGL buffers keep the size they were created with.
    this.line.geometry.dispose();
    this.line.geometry = new THREE.BufferGeometry().setAttribute('position', position);
  }
}
