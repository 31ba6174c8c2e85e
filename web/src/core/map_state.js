// The viewer's picture of the server: every session's status (for the picker) and, for the
// one subscribed to, its tiles and trajectory, built from parsed protocol 2 messages and
// decoded tiles. Entry points: MapStore.apply(message) and MapStore.applyTile(tile).
// Renderers compare revisions to redraw only what changed.

import { TileCache } from './tile_cache.js';

// Revisions are unique across the page's life, so a renderer never mistakes a tile or a
// session that was re-created (after a reconnect) for the one it drew before.
let lastRevision = 0;
const newRevision = () => ++lastRevision;

/** "x_y_z", as in tile URLs. */
export function tileKeyText([x, y, z]) {
  return `${x}_${y}_${z}`;
}

export class SessionState {
  /** `cacheBytes`: the budget of the tiles held (TileCache). */
  constructor(id, cacheBytes = undefined) {
    this.id = id;
    this.status = null; // the server's latest status (protocol.js status fields)
    this.resolution = null; // metres per voxel edge
    this.bounds = null; // {min, max} of the occupied voxels, metres (server's)
    this.serverVoxels = 0; // occupied voxels at the finest level, as the server counts them
    this.tiles = new TileCache(cacheBytes); // tileKeyText → {key, level, version, codes, values, revision}
    this.evicted = []; // key texts dropped to stay within the cache's budget, to tell the server
    // Per vehicle: {poses: [[t, x, y, z, qx, qy, qz, qw], ...] (T_map_body), epoch (renewed
    // when the poses are replaced rather than appended to), updatedMs}.
    this.trajectories = new Map();
    this.lastMessageMs = null; // wall-clock time of the last message about this session
    this.lastChangeMs = 0; // when the server last changed the map (its clock, Unix ms)
    this.replayUntil = null; // shown as it was at this time (seconds), or null: as it is
    this.replayFrames = 0; // frames fused by then
    this.timeRange = null; // [first, last] pose time of the whole session (seconds), for the slider
  }

  // The whole session's time span, from its trajectories (kept while a replay shows less).
  updateTimeRange() {
    if (this.replayUntil !== null) return;
    let first = Infinity;
    let last = -Infinity;
    for (const { poses } of this.trajectories.values()) {
      if (poses.length === 0) continue;
      first = Math.min(first, poses[0][0]);
      last = Math.max(last, poses.at(-1)[0]);
    }
    this.timeRange = first <= last ? [first, last] : null;
  }

  get frames() {
    return this.replayUntil !== null ? this.replayFrames : this.status?.frames ?? 0;
  }

  get vehicle() {
    return this.status?.vehicle ?? '';
  }

  /** Occupied cells held, at whatever level each tile is. */
  get cells() {
    let n = 0;
    for (const tile of this.tiles.values()) n += tile.codes.length;
    return n;
  }

  applyTile({ header, codes, values }) {
    const text = tileKeyText(header.key);
    const held = this.tiles.get(text);
    // A tile older than the one held arrived late: keep the newer one.
    if (held && header.version < held.version) return false;
    if (codes.length === 0) {
      this.tiles.delete(text);
    } else {
      const entry = { key: header.key, level: header.level, version: header.version, codes, values, revision: newRevision() };
      for (const key of this.tiles.set(text, entry)) this.evicted.push(key);
    }
    return true;
  }

  /** Poses of every vehicle together. */
  get poseCount() {
    let n = 0;
    for (const { poses } of this.trajectories.values()) n += poses.length;
    return n;
  }

  /** The vehicle whose pose arrived last, or null. */
  get latestVehicle() {
    let latest = null;
    for (const [vehicle, { updatedMs }] of this.trajectories) {
      if (latest === null || updatedMs >= this.trajectories.get(latest).updatedMs) latest = vehicle;
    }
    return latest;
  }

  applyPoses({ vehicle, reset, poses }, nowMs = Date.now()) {
    let trajectory = this.trajectories.get(vehicle);
    if (!trajectory || reset) {
      trajectory = { poses: [], epoch: newRevision(), updatedMs: nowMs };
      this.trajectories.set(vehicle, trajectory);
    }
    for (const pose of poses) trajectory.poses.push(pose); // not push(...poses): long lists overflow the stack
    if (poses.length > 0) trajectory.updatedMs = nowMs;
    this.updateTimeRange();
  }
}

export class MapStore {
  /** `cacheBytes`: each subscribed session's tile budget (TileCache). */
  constructor(cacheBytes = undefined) {
    this.cacheBytes = cacheBytes;
    this.statuses = new Map(); // id → status, every session the server reported, in order
    this.appeared = new Map(); // id → when it was first reported (0, 1, 2, ...)
    this.subscribed = null; // the SessionState subscribed to, or null
    this.lastLatency = null; // ms from the server's map change to its tiles here (same clock only)
  }

  /**
   * The session to follow: the live one that appeared most recently (a new flight), else the
   * last loaded one (ended or opened), else the last stored one; null when there is none.
   * By appearance, not by the latest update: with several vehicles live at once their updates
   * interleave, and following the last one changed would switch sessions (and drop every
   * tile) many times a second.
   */
  get latestSessionId() {
    const all = [...this.statuses.values()].sort((a, b) => this.appeared.get(a.id) - this.appeared.get(b.id));
    const last = (states) => all.filter((s) => states.includes(s.state)).at(-1);
    return (last(['live']) ?? last(['ended', 'opened']) ?? all.at(-1))?.id ?? null;
  }

  /** Notes when a session was first reported (kept across reconnects). */
  noteAppearance(id) {
    if (!this.appeared.has(id)) this.appeared.set(id, this.appeared.size);
  }

  /** Starts over for `id` (a new subscription); its data arrives from now on. */
  subscribe(id) {
    this.subscribed = new SessionState(id, this.cacheBytes);
    const status = this.statuses.get(id);
    if (status) this.subscribed.status = status;
    return this.subscribed;
  }

  /** Applies one message from parseMessage(); returns true when something shown changed. */
  apply(message, nowMs = Date.now()) {
    const mine = this.subscribed;
    switch (message.type) {
      case 'hello':
        this.statuses.clear();
        return true;
      case 'sessions':
        this.statuses.clear();
        for (const status of message.sessions) {
          this.noteAppearance(status.id);
          this.statuses.set(status.id, status);
        }
        if (mine && this.statuses.has(mine.id)) mine.status = this.statuses.get(mine.id);
        return true;
      case 'session': {
        const { type, ...status } = message;
        this.noteAppearance(status.id);
        this.statuses.set(status.id, status);
        if (mine?.id === status.id) {
          mine.status = status;
          mine.lastMessageMs = nowMs;
        }
        return true;
      }
      case 'session_removed':
        this.statuses.delete(message.id);
        return true;
      case 'subscribed':
        if (mine?.id !== message.session) return false;
        Object.assign(mine, { resolution: message.resolution, bounds: message.bounds, serverVoxels: message.voxels, status: message.status, lastMessageMs: nowMs });
        return true;
      case 'map':
        if (mine?.id !== message.session) return false;
        Object.assign(mine, { bounds: message.bounds, serverVoxels: message.voxels, lastChangeMs: message.changedMs, lastMessageMs: nowMs });
        this.lastLatency = nowMs - message.changedMs;
        return true;
      case 'replayed':
        if (mine?.id !== message.session) return false;
        // The map and trajectories as they were then follow: start them afresh.
        mine.tiles.clear();
        mine.trajectories.clear();
        Object.assign(mine, { replayUntil: message.until, replayFrames: message.frames, bounds: message.bounds, serverVoxels: message.voxels, lastMessageMs: nowMs });
        return true;
      case 'poses':
        if (mine?.id !== message.session) return false;
        mine.applyPoses(message, nowMs);
        mine.lastMessageMs = nowMs;
        return true;
      default:
        return false;
    }
  }

  /** A decoded tile (tile_codec.js) for the subscribed session; false when not for it. */
  applyTile(tile) {
    const mine = this.subscribed;
    if (!mine || tile.header.session !== mine.id) return false;
    if (mine.resolution === null) mine.resolution = tile.header.resolution;
    return mine.applyTile(tile);
  }
}
