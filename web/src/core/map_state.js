// The viewer's copy of every session the server reports: occupied voxels, trajectory and
// status, built from parsed protocol messages. Entry point: MapStore.apply(message).
// Renderers read a SessionState and use its revisions to redraw only what changed.

import { ProtocolError } from './protocol.js';

// Revisions are unique across all SessionStates, so a renderer never mistakes a session that
// was re-created (after a reconnect) for the one it drew before.
let lastRevision = 0;
const newRevision = () => ++lastRevision;

/** Map key of the voxel with integer indices (ix, iy, iz). */
export function voxelKey(ix, iy, iz) {
  return `${ix},${iy},${iz}`;
}

export class SessionState {
  constructor(id) {
    this.id = id;
    this.vehicle = '';
    this.resolution = null; // metres per voxel edge
    this.frames = 0; // as reported by the server's session messages
    this.serverVoxels = 0; // occupied_voxels reported by the server
    this.bounds = null; // {min, max} in metres, as reported by the server
    this.voxels = new Map(); // voxelKey → [ix, iy, iz]
    this.voxelVersion = null; // version of the last applied voxels message
    this.voxelRevision = newRevision(); // renewed on every change of `voxels`
    this.poses = []; // [t, x, y, z, qx, qy, qz, qw], T_map_body
    this.poseEpoch = newRevision(); // renewed when `poses` is replaced rather than appended to
    this.lastMessageMs = null; // wall-clock time of the last message about this session
  }

  applyVoxels({ resolution, version, reset, add, remove }) {
    // A delta is relative to the previous version: an older or repeated one would corrupt the set.
    if (!reset && this.voxelVersion !== null && version <= this.voxelVersion) {
      throw new ProtocolError(`voxels message for session "${this.id}": version ${version} is not newer than version ${this.voxelVersion} already applied; ignored`);
    }
    if (reset) this.voxels.clear();
    for (let i = 0; i < remove.length; i += 3) this.voxels.delete(voxelKey(remove[i], remove[i + 1], remove[i + 2]));
    for (let i = 0; i < add.length; i += 3) {
      this.voxels.set(voxelKey(add[i], add[i + 1], add[i + 2]), [add[i], add[i + 1], add[i + 2]]);
    }
    this.resolution = resolution;
    this.voxelVersion = version;
    this.voxelRevision = newRevision();
  }

  applyPoses({ vehicle, reset, poses }) {
    if (reset) {
      this.poses = [];
      this.poseEpoch = newRevision();
    }
    for (const pose of poses) this.poses.push(pose); // not push(...poses): long lists overflow the stack
    if (vehicle) this.vehicle = vehicle;
  }

  applyStatus({ vehicle, resolution, frames, occupiedVoxels, bounds }) {
    Object.assign(this, { vehicle, resolution, frames, serverVoxels: occupiedVoxels, bounds });
  }
}

export class MapStore {
  constructor() {
    this.sessions = new Map(); // id → SessionState, in order of first appearance
    this.latestSessionId = null; // the session whose latest message arrived most recently
  }

  session(id) {
    let state = this.sessions.get(id);
    if (!state) {
      state = new SessionState(id);
      this.sessions.set(id, state);
    }
    return state;
  }

  /**
   * Applies one message from parseMessage(); returns the SessionState it changed, or null.
   * Throws ProtocolError, leaving the state untouched, for a message that contradicts it.
   */
  apply(message, nowMs = Date.now()) {
    if (message.type === 'hello') {
      // A (re)connected server sends every session afresh; drop sessions it may no longer have.
      this.sessions.clear();
      this.latestSessionId = null;
      return null;
    }
    if (message.type === 'error') return null;
    if (message.type === 'session_removed') {
      // Closed into the store or deleted: the server no longer holds it.
      this.sessions.delete(message.id);
      if (this.latestSessionId === message.id) this.latestSessionId = [...this.sessions.keys()].at(-1) ?? null;
      return null;
    }
    const id = message.type === 'session' ? message.id : message.session;
    const state = this.session(id);
    if (message.type === 'voxels') state.applyVoxels(message);
    else if (message.type === 'poses') state.applyPoses(message);
    else state.applyStatus(message);
    state.lastMessageMs = nowMs;
    this.latestSessionId = id;
    return state;
  }
}
