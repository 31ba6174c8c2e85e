// The landing pads the vehicles see: each tracked pad's T outlined in the map (bright yellow,
// drawn over the map). Entry point: LandingLayer.setOutlines().

import * as THREE from 'three';

export class LandingLayer {
  constructor(scene) {
    this.scene = scene;
    this.material = new THREE.LineBasicMaterial({ color: 0xffd400, depthTest: false });
    this.loops = [];
  }

  /** `outlines`: one array of 8 map points [x, y, z] per tracked pad (replaces the last ones). */
  setOutlines(outlines) {
    for (const loop of this.loops) {
      this.scene.remove(loop);
      loop.geometry.dispose();
    }
    this.loops = outlines.map((corners) => {
      const geometry = new THREE.BufferGeometry().setFromPoints(corners.map(([x, y, z]) => new THREE.Vector3(x, y, z)));
      const loop = new THREE.LineLoop(geometry, this.material);
      loop.renderOrder = 10; // over the map's cells
      this.scene.add(loop);
      return loop;
    });
  }

  get count() {
    return this.loops.length;
  }
}
