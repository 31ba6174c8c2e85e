// The 3D view of one session: renderer, z-up camera with orbit controls, lights, a grid on the
// z = 0 plane, the tile and trajectory layers. Entry point: MapView.requestRender() when
// data changed, MapView.show(session) from the beforeRender callback. Frames are drawn on
// demand; cameraState() is what the server needs to choose tiles (the "view" message).

import * as THREE from 'three';
import { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';
import { LandingLayer } from './landing_layer.js';
import { TrajectoryLayer } from './trajectory_layer.js';
import { TileLayer } from './tile_layer.js';

const kBackground = 0x0d1117;
const kTrajectoryColours = [0xf5f5f5, 0x7ee0ff, 0xffd166, 0xb5f277, 0xff8fa3]; // one per vehicle, in order
const kViewDirection = new THREE.Vector3(-0.55, -1, 0.75).normalize(); // from the south-west, above

export class MapView {
  /** `container` receives the canvas; `beforeRender` is called once per drawn frame. */
  constructor(container, beforeRender = () => {}, onCameraMoved = () => {}) {
    this.container = container;
    this.beforeRender = beforeRender;
    this.renderer = new THREE.WebGLRenderer({ antialias: true });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
    container.appendChild(this.renderer.domElement);

    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(kBackground);
    this.camera = new THREE.PerspectiveCamera(50, 1, 0.05, 2000);
    this.camera.up.set(0, 0, 1); // the map frame is z-up
    this.camera.position.copy(kViewDirection).multiplyScalar(12);

    const sky = new THREE.HemisphereLight(0xdfe8ff, 0x2a2622, 1.4);
    sky.position.set(0, 0, 1); // HemisphereLight's "up" is its position
    const sun = new THREE.DirectionalLight(0xffffff, 1.8);
    sun.position.set(0.4, -0.7, 1); // lights box tops brightest and the two visible sides differently
    this.scene.add(sky, sun);

    this.grid = null;
    this.setGrid(new THREE.Vector3(), 20);
    this.tiles = new TileLayer(this.scene);
    this.landing = new LandingLayer(this.scene);
    this.trajectories = new Map(); // vehicle → TrajectoryLayer
    this.markerScale = 0.3;
    this.following = false; // keep the latest vehicle at the centre of the view
    this.measure = { on: false, points: [], line: null }; // two clicked points and the line between

    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.enableDamping = true;
    this.controls.addEventListener('change', () => {
      this.requestRender();
      onCameraMoved();
    });
    // Keep the map framed while it grows, until the user moves the camera ('fit' resumes it).
    this.autoFrame = true;
    this.framedBounds = new THREE.Box3();
    this.controls.addEventListener('start', () => {
      this.autoFrame = false;
    });

    this.shownId = null; // the session the layers hold
    this.mapBounds = null; // {min, max} of the shown session's map, the server's
    this.frameRequested = false;
    new ResizeObserver(() => this.resize()).observe(container);
    this.resize();
  }

  get renderedVoxels() {
    return this.tiles.count;
  }

  get trajectoryLength() {
    let n = 0;
    for (const layer of this.trajectories.values()) n += layer.length;
    return n;
  }

  get heightRange() {
    return this.tiles.heightRange;
  }

  /**
   * Brings the layers up to date with `session` (a SessionState or null); cheap when nothing
   * changed. Meant for the beforeRender callback, so many messages cost one update per frame.
   */
  show(session) {
    const id = session ? session.id : null;
    if (id !== this.shownId) {
      this.shownId = id;
      this.autoFrame = true;
      this.framedBounds.makeEmpty();
    }
    this.tiles.sync(session);
    const wanted = session?.trajectories ?? new Map();
    for (const [vehicle, layer] of this.trajectories) {
      if (!wanted.has(vehicle)) {
        layer.dispose();
        this.trajectories.delete(vehicle);
      }
    }
    for (const [vehicle, { poses, epoch }] of wanted) {
      let layer = this.trajectories.get(vehicle);
      if (!layer) {
        layer = new TrajectoryLayer(this.scene, kTrajectoryColours[this.trajectories.size % kTrajectoryColours.length]);
        layer.setMarkerScale(this.markerScale);
        this.trajectories.set(vehicle, layer);
      }
      layer.setPoses(poses, epoch);
    }
    if (this.following && session?.latestVehicle) {
      const poses = wanted.get(session.latestVehicle).poses;
      if (poses.length > 0) this.lookAt(poses.at(-1).slice(1, 4));
    }
    this.mapBounds = session?.bounds ?? null;
    if (this.autoFrame && this.tiles.count > 0 && !this.framedBounds.containsBox(this.drawnBounds())) this.fit();
  }

  // What framing must show: the map's bounds as the server reports them (exact, and the same
  // whatever levels are drawn: coarse cells reach beyond them, and framing by what is drawn
  // would move the camera, which asks for other levels, which move the bounds...), else the
  // drawn cells; and every trajectory.
  drawnBounds() {
    const b = this.mapBounds;
    const bounds = b ? new THREE.Box3(new THREE.Vector3(...b.min), new THREE.Vector3(...b.max)) : this.tiles.bounds.clone();
    for (const layer of this.trajectories.values()) bounds.union(layer.bounds);
    return bounds;
  }

  /** Moves the camera with its target so that the target is `point` ([x, y, z]). */
  lookAt(point) {
    const delta = new THREE.Vector3(...point).sub(this.controls.target);
    if (delta.lengthSq() === 0) return;
    this.autoFrame = false;
    this.controls.target.add(delta);
    this.camera.position.add(delta);
    this.controls.update();
  }

  /**
   * The map point under the pointer (a tile cell's box), or null: `event` is a pointer event on
   * the canvas.
   */
  pick(event) {
    const rect = this.renderer.domElement.getBoundingClientRect();
    const ndc = new THREE.Vector2(((event.clientX - rect.left) / rect.width) * 2 - 1,
      -((event.clientY - rect.top) / rect.height) * 2 + 1);
    const raycaster = new THREE.Raycaster();
    raycaster.setFromCamera(ndc, this.camera);
    const meshes = [...this.tiles.drawn.values()].map((d) => d.mesh);
    const hit = raycaster.intersectObjects(meshes, false)[0];
    return hit ? hit.point : null;
  }

  /** Adds a measured point (a THREE.Vector3); returns the distance once there are two, else null. */
  addMeasurePoint(point) {
    const m = this.measure;
    if (m.points.length === 2) this.clearMeasure();
    m.points.push(point.clone());
    if (m.points.length < 2) return null;
    const geometry = new THREE.BufferGeometry().setFromPoints(m.points);
    m.line = new THREE.Line(geometry, new THREE.LineBasicMaterial({ color: 0xff3df2, depthTest: false }));
    m.line.renderOrder = 1;
    this.scene.add(m.line);
    this.requestRender();
    return m.points[0].distanceTo(m.points[1]);
  }

  clearMeasure() {
    const m = this.measure;
    if (m.line) {
      this.scene.remove(m.line);
      m.line.geometry.dispose();
      m.line.material.dispose();
    }
    m.points = [];
    m.line = null;
    this.requestRender();
  }

  /** Fits the camera to `bounds` ({min, max} in metres, the server's) before tiles arrive. */
  fitBounds(bounds) {
    if (!bounds) return;
    this.mapBounds = bounds;
    this.fit();
  }

  /** Eye, frustum planes, vertical fov (degrees) and viewport height (pixels): the "view". */
  cameraState() {
    this.camera.updateMatrixWorld();
    const frustum = new THREE.Frustum().setFromProjectionMatrix(
      new THREE.Matrix4().multiplyMatrices(this.camera.projectionMatrix, this.camera.matrixWorldInverse));
    return {
      eye: this.camera.position.toArray(),
      planes: frustum.planes.map((p) => [p.normal.x, p.normal.y, p.normal.z, p.constant]),
      fov: this.camera.fov,
      height: this.renderer.domElement.height || 800,
    };
  }

  /** Points the camera at everything drawn and keeps it framed from now on. */
  fit() {
    this.autoFrame = true;
    const bounds = this.drawnBounds();
    if (bounds.isEmpty()) return;
    // Frame some slack too, so a growing map stays in view and is not re-framed on every update.
    this.framedBounds.copy(bounds).expandByVector(bounds.getSize(new THREE.Vector3()).multiplyScalar(0.05));
    const centre = this.framedBounds.getCenter(new THREE.Vector3());
    const distance = this.distanceToSee(this.framedBounds, centre);
    this.controls.target.copy(centre);
    this.camera.position.copy(centre).addScaledVector(kViewDirection, distance);
    this.camera.near = distance / 500;
    this.camera.far = distance * 20;
    this.camera.updateProjectionMatrix();
    const radius = this.framedBounds.getBoundingSphere(new THREE.Sphere()).radius;
    this.setGrid(centre, radius * 2.5);
    this.markerScale = Math.max(radius * 0.1, 0.3);
    for (const layer of this.trajectories.values()) layer.setMarkerScale(this.markerScale);
    this.controls.update();
    this.requestRender();
  }

  // Distance from `centre` along kViewDirection at which every corner of `box` is in view:
  // a corner at (x, y) across and z towards the camera needs |x| <= (d - z) tan(half fov).
  distanceToSee(box, centre) {
    const toCamera = kViewDirection;
    const right = new THREE.Vector3().crossVectors(this.camera.up, toCamera).normalize();
    const up = new THREE.Vector3().crossVectors(toCamera, right);
    const tanY = Math.tan(THREE.MathUtils.degToRad(this.camera.fov / 2));
    const tanX = tanY * this.camera.aspect;
    let distance = 1;
    const corner = new THREE.Vector3();
    for (let i = 0; i < 8; i += 1) {
      corner.set(i & 1 ? box.max.x : box.min.x, i & 2 ? box.max.y : box.min.y, i & 4 ? box.max.z : box.min.z).sub(centre);
      const z = corner.dot(toCamera);
      distance = Math.max(distance, z + Math.abs(corner.dot(right)) / tanX, z + Math.abs(corner.dot(up)) / tanY);
    }
    return distance;
  }

  // A grid of 1 m cells (10 m when large) on z = 0 around `centre`, `size` metres across.
  setGrid(centre, size) {
    const cell = size > 200 ? 10 : 1;
    const cells = Math.max(10, Math.ceil(size / cell / 2) * 2);
    if (this.grid) {
      this.scene.remove(this.grid);
      this.grid.dispose();
    }
    this.grid = new THREE.GridHelper(cells * cell, cells, 0x3d4a5c, 0x222a35);
    this.grid.rotation.x = Math.PI / 2; // GridHelper lies in the x-z plane; the map's ground is x-y
    this.grid.position.set(Math.round(centre.x / cell) * cell, Math.round(centre.y / cell) * cell, 0);
    this.scene.add(this.grid);
  }

  resize() {
    const { clientWidth: width, clientHeight: height } = this.container;
    if (width === 0 || height === 0) return;
    this.renderer.setSize(width, height, false);
    this.camera.aspect = width / height;
    this.camera.updateProjectionMatrix();
    if (this.autoFrame && !this.framedBounds.isEmpty()) this.fit();
    this.requestRender();
  }

  requestRender() {
    if (this.frameRequested) return;
    this.frameRequested = true;
    requestAnimationFrame(() => {
      this.frameRequested = false;
      this.beforeRender();
      this.controls.update(); // while damping, this emits 'change' and so asks for the next frame
      this.renderer.render(this.scene, this.camera);
    });
  }
}
