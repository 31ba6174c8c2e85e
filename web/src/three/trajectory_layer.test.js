import * as THREE from 'three';
import { describe, expect, it } from 'vitest';
import { TrajectoryLayer } from './trajectory_layer.js';

// A pose at (i, 2i, 1) turned by `yaw` about z; the quaternion is left unnormalised on purpose.
const pose = (i, yaw = 0) => [i, i, 2 * i, 1, 0, 0, 2 * Math.sin(yaw / 2), 2 * Math.cos(yaw / 2)];

describe('TrajectoryLayer', () => {
  it('draws the positions and puts the marker on the last pose', () => {
    const layer = new TrajectoryLayer(new THREE.Scene());
    layer.setPoses([pose(0), pose(1), pose(2, Math.PI / 2)], 'a#1');
    expect(layer.length).toBe(3);
    expect(layer.line.geometry.drawRange.count).toBe(3);
    const position = layer.line.geometry.getAttribute('position');
    expect([position.getX(1), position.getY(1), position.getZ(1)]).toEqual([1, 2, 1]);
    expect(layer.marker.visible).toBe(true);
    expect(layer.marker.position.toArray()).toEqual([2, 4, 1]);
    // Body +x (the cone's direction) turned 90° about z points along map +y.
    const forward = new THREE.Vector3(1, 0, 0).applyQuaternion(layer.marker.quaternion);
    forward.toArray().forEach((c, i) => expect(c).toBeCloseTo([0, 1, 0][i], 12));
  });

  it('appends across buffer growth and restarts on a new epoch', () => {
    const layer = new TrajectoryLayer(new THREE.Scene());
    const poses = [pose(0), pose(1)];
    layer.setPoses(poses, 'a#1');
    for (let i = 2; i < 600; i += 1) poses.push(pose(i));
    layer.setPoses(poses, 'a#1');
    const position = layer.line.geometry.getAttribute('position');
    expect(layer.length).toBe(600);
    expect(position.count).toBe(1024);
    expect([position.getX(1), position.getY(599)]).toEqual([1, 1198]);
    expect(layer.bounds.max.toArray()).toEqual([599, 1198, 1]);
    layer.setPoses([pose(7)], 'a#2');
    expect(layer.length).toBe(1);
    expect(layer.bounds.min.toArray()).toEqual([7, 14, 1]);
    layer.setPoses([], 'b#1');
    expect(layer.length).toBe(0);
    expect(layer.marker.visible).toBe(false);
  });
});
