// The viewer WebSocket, protocol 2 (docs/PROTOCOL.md): parsing and validation of the server's
// text messages, and the viewer's own messages. Entry points: parseMessage(text) and the
// *Message() builders. Tiles arrive as binary messages (tile_codec.js). A message is checked
// completely before anything uses it, so a malformed one is rejected (ProtocolError naming
// the field) without touching any state.

export const kProtocolVersion = 2;

export class ProtocolError extends Error {
  constructor(message) {
    super(message);
    this.name = 'ProtocolError';
  }
}

function shown(value) {
  if (value === undefined) return 'nothing';
  const text = JSON.stringify(value);
  return text.length > 60 ? `${text.slice(0, 57)}...` : text;
}

const isFiniteNumber = (v) => typeof v === 'number' && Number.isFinite(v);
const isCount = (v) => Number.isSafeInteger(v) && v >= 0;
const isString = (v) => typeof v === 'string';

// Reads field `name` of `message`, or throws naming the message type, field and value.
function field(message, name, isValid, expected, { optional = false, fallback } = {}) {
  const value = message[name];
  if ((value === undefined || value === null) && optional) return fallback;
  if (!isValid(value)) {
    throw new ProtocolError(`${message.type} message: "${name}" must be ${expected}, got ${shown(value)}`);
  }
  return value;
}

const requireId = (m, name) => field(m, name, (v) => isString(v) && v.length > 0, 'a non-empty string');
const count = (m, name) => field(m, name, isCount, 'a count');
const optionalCount = (m, name, fallback = 0) => field(m, name, isCount, 'a count', { optional: true, fallback });

function isPoint(v) {
  return Array.isArray(v) && v.length === 3 && v.every(isFiniteNumber);
}

function isBounds(v) {
  return v === null || (typeof v === 'object' && !Array.isArray(v) && isPoint(v.min) && isPoint(v.max));
}

const bounds = (m) => field(m, 'bounds', isBounds, 'null or {"min": [x, y, z], "max": [x, y, z]}', { optional: true, fallback: null });

// [[t, x, y, z, qx, qy, qz, qw], ...]: T_map_body with a non-zero quaternion.
function poseList(message) {
  const value = message.poses;
  if (!Array.isArray(value)) {
    throw new ProtocolError(`poses message: "poses" must be an array of [t, x, y, z, qx, qy, qz, qw], got ${shown(value)}`);
  }
  value.forEach((pose, i) => {
    const valid = Array.isArray(pose) && pose.length === 8 && pose.every(isFiniteNumber) &&
      pose[4] ** 2 + pose[5] ** 2 + pose[6] ** 2 + pose[7] ** 2 > 0;
    if (!valid) {
      throw new ProtocolError(`poses message: "poses"[${i}] must be 8 finite numbers [t, x, y, z, qx, qy, qz, qw] with a non-zero quaternion, got ${shown(pose)}`);
    }
  });
  return value;
}

// Each vehicle's own counters (the status's vehicle_status; none from an older server).
function vehicleStatus(m) {
  const list = field(m, 'vehicle_status', Array.isArray, 'an array', { optional: true, fallback: [] });
  return list.map((v, i) => {
    if (typeof v !== 'object' || v === null || Array.isArray(v)) {
      throw new ProtocolError(`${m.type} message: "vehicle_status"[${i}] must be an object, got ${shown(v)}`);
    }
    const entry = { ...v, type: m.type };
    return {
      vehicleId: requireId(entry, 'vehicle_id'),
      spoolSamples: optionalCount(entry, 'spool_samples'),
      spoolBytes: optionalCount(entry, 'spool_bytes'),
      skippedFrames: optionalCount(entry, 'skipped_frames'),
      lateFrames: optionalCount(entry, 'late_frames'),
      givenUp: optionalCount(entry, 'given_up'),
      heldBack: optionalCount(entry, 'held_back'),
      sessionClosed: field(entry, 'session_closed', (b) => typeof b === 'boolean', 'true or false', { optional: true, fallback: false }),
    };
  });
}

const kVehicleFrameStates = ['aligning', 'aligned'];
const optionalNumber = (m, name, isValid, expected) => field(m, name, isValid, expected, { optional: true, fallback: null });

// The vehicles in their own frame and where the server is with aligning each into the
// session's (the status's vehicle_frames; none from an older server, or when every vehicle
// is in the session's frame).
function vehicleFrames(m) {
  const list = field(m, 'vehicle_frames', Array.isArray, 'an array', { optional: true, fallback: [] });
  return list.map((v, i) => {
    if (typeof v !== 'object' || v === null || Array.isArray(v)) {
      throw new ProtocolError(`${m.type} message: "vehicle_frames"[${i}] must be an object, got ${shown(v)}`);
    }
    const entry = { ...v, type: m.type };
    return {
      vehicleId: requireId(entry, 'vehicle_id'),
      frame: field(entry, 'frame', (f) => kVehicleFrameStates.includes(f), '"aligning" or "aligned"'),
      attempts: optionalCount(entry, 'attempts'),
      reason: field(entry, 'reason', isString, 'a string', { optional: true, fallback: '' }),
      // T_session_own: [tx, ty, tz, qx, qy, qz, qw].
      transform: optionalNumber(entry, 'transform', (t) => Array.isArray(t) && t.length === 7 && t.every(isFiniteNumber),
        '7 finite numbers [tx, ty, tz, qx, qy, qz, qw]'),
      overlap: optionalNumber(entry, 'overlap', (x) => isFiniteNumber(x) && x >= 0 && x <= 1, 'a share from 0 to 1'),
      rmseM: optionalNumber(entry, 'rmse_m', (x) => isFiniteNumber(x) && x >= 0, 'a non-negative number (metres)'),
      alignedS: optionalNumber(entry, 'aligned_s', isFiniteNumber, 'a number (seconds)'),
    };
  });
}

const isObject = (v) => typeof v === 'object' && v !== null && !Array.isArray(v);
const isTransform = (t) => Array.isArray(t) && t.length === 7 && t.every(isFiniteNumber);

// Each entry of list `name` of `m`, an object read by `read` (a message's nested list).
function objectList(m, name, read) {
  return field(m, name, Array.isArray, 'an array', { optional: true, fallback: [] }).map((v, i) => {
    if (!isObject(v)) throw new ProtocolError(`${m.type} message: "${name}"[${i}] must be an object, got ${shown(v)}`);
    return read({ ...v, type: m.type });
  });
}

// What made a session that is not a flight (the status's origin; null for a flight): a file
// imported, a diff of two sessions, or a site of sessions registered into the first's frame.
function origin(m) {
  const o = field(m, 'origin', isObject, 'an object', { optional: true, fallback: null });
  if (o === null) return null;
  const entry = { ...o, type: m.type };
  const result = {};
  if (o.imported_from !== undefined) result.importedFrom = field(entry, 'imported_from', isString, 'a string');
  if (o.diff !== undefined) {
    const d = { ...field(entry, 'diff', isObject, 'an object'), type: m.type };
    result.diff = {
      first: requireId(d, 'first'),
      second: requireId(d, 'second'),
      appeared: optionalCount(d, 'appeared'),
      disappeared: optionalCount(d, 'disappeared'),
      unchanged: optionalCount(d, 'unchanged'),
      unseenByFirst: optionalCount(d, 'unseen_by_first'),
      unseenBySecond: optionalCount(d, 'unseen_by_second'),
    };
  }
  if (o.site !== undefined) {
    const s = { ...field(entry, 'site', isObject, 'an object'), type: m.type };
    result.site = {
      sessions: objectList(s, 'sessions', (e) => ({
        session: requireId(e, 'session'),
        // T_site_session: [tx, ty, tz, qx, qy, qz, qw].
        transform: field(e, 'transform', isTransform, '7 finite numbers [tx, ty, tz, qx, qy, qz, qw]'),
        onto: field(e, 'onto', isString, 'a string', { optional: true, fallback: '' }),
        overlap: optionalNumber(e, 'overlap', (x) => isFiniteNumber(x) && x >= 0 && x <= 1, 'a share from 0 to 1'),
        rmseM: optionalNumber(e, 'rmse_m', (x) => isFiniteNumber(x) && x >= 0, 'a non-negative number (metres)'),
      })),
      leftOut: objectList(s, 'left_out', (e) => ({
        session: requireId(e, 'session'),
        reason: field(e, 'reason', isString, 'a string', { optional: true, fallback: '' }),
      })),
    };
  }
  return result;
}

// A session's status (GET /api/sessions entries, "session" messages).
function status(m) {
  return {
    id: requireId(m, 'id'),
    vehicle: field(m, 'vehicle', isString, 'a string', { optional: true, fallback: '' }),
    state: field(m, 'state', isString, 'a string', { optional: true, fallback: '' }),
    resolution: field(m, 'resolution', (v) => isFiniteNumber(v) && v > 0, 'a positive number (metres)'),
    frames: count(m, 'frames'),
    occupiedVoxels: count(m, 'occupied_voxels'),
    poses: optionalCount(m, 'poses'),
    // Clouds taken and the vehicles' link bytes, cumulative: null from a server that does not say.
    framesReceived: optionalCount(m, 'frames_received', null),
    bytesReceived: optionalCount(m, 'bytes_received', null),
    droppedFrames: optionalCount(m, 'dropped_frames'),
    backlog: optionalCount(m, 'fusion_backlog'),
    corrections: optionalCount(m, 'corrections'),
    refusing: field(m, 'refusing', (v) => typeof v === 'boolean', 'true or false', { optional: true, fallback: false }),
    bounds: bounds(m),
    vehicleStatus: vehicleStatus(m),
    vehicleFrames: vehicleFrames(m),
    origin: origin(m),
  };
}

const kParsers = {
  hello(m) {
    const protocol = field(m, 'protocol', Number.isSafeInteger, 'an integer');
    if (protocol !== kProtocolVersion) {
      throw new ProtocolError(`hello message: protocol ${protocol} is not supported (this viewer speaks ${kProtocolVersion})`);
    }
    return { type: 'hello', protocol, server: field(m, 'server', isString, 'a string', { optional: true, fallback: '' }) };
  },
  sessions(m) {
    const list = field(m, 'sessions', Array.isArray, 'an array of sessions');
    return { type: 'sessions', sessions: list.map((s) => status({ ...s, type: 'sessions' })) };
  },
  session(m) {
    return { type: 'session', ...status(m) };
  },
  session_removed(m) {
    return { type: 'session_removed', id: requireId(m, 'id') };
  },
  subscribed(m) {
    return {
      type: 'subscribed',
      session: requireId(m, 'session'),
      resolution: field(m, 'resolution', (v) => isFiniteNumber(v) && v > 0, 'a positive number (metres)'),
      version: count(m, 'version'),
      voxels: count(m, 'voxels'),
      tiles: count(m, 'tiles'),
      bounds: bounds(m),
      status: status({ ...field(m, 'status', (v) => v !== null && typeof v === 'object', 'a session status'), type: 'subscribed' }),
    };
  },
  plan(m) {
    return { type: 'plan', id: count(m, 'id'), session: requireId(m, 'session'), tiles: count(m, 'tiles'), cells: count(m, 'cells') };
  },
  view_done(m) {
    return { type: 'view_done', id: count(m, 'id'), session: requireId(m, 'session') };
  },
  map(m) {
    return {
      type: 'map',
      session: requireId(m, 'session'),
      version: count(m, 'version'),
      changedMs: field(m, 'changed_ms', (v) => isFiniteNumber(v) && v >= 0, 'a time (Unix ms)'),
      voxels: count(m, 'voxels'),
      tiles: count(m, 'tiles'),
      bounds: bounds(m),
    };
  },
  poses(m) {
    return {
      type: 'poses',
      session: requireId(m, 'session'),
      vehicle: field(m, 'vehicle', isString, 'a string', { optional: true, fallback: '' }),
      reset: field(m, 'reset', (v) => typeof v === 'boolean', 'true or false', { optional: true, fallback: false }),
      poses: poseList(m),
    };
  },
  trajectory_done(m) {
    return { type: 'trajectory_done', session: requireId(m, 'session'), poses: count(m, 'poses') };
  },
  replaying(m) {
    return { type: 'replaying', session: requireId(m, 'session'), until: field(m, 'until', isFiniteNumber, 'a time (seconds since the epoch)') };
  },
  replayed(m) {
    return {
      type: 'replayed',
      session: requireId(m, 'session'),
      until: field(m, 'until', isFiniteNumber, 'a time (seconds since the epoch)'),
      frames: count(m, 'frames'),
      voxels: count(m, 'voxels'),
      bounds: bounds(m),
    };
  },
  pong(m) {
    return { type: 'pong', t: field(m, 't', isFiniteNumber, 'a number', { optional: true, fallback: null }) };
  },
  error(m) {
    return {
      type: 'error',
      message: field(m, 'message', isString, 'a string'),
      code: field(m, 'code', isString, 'a string', { optional: true, fallback: '' }),
      session: field(m, 'session', isString, 'a string', { optional: true, fallback: '' }),
    };
  },
};

/** Parses one WebSocket text frame; returns a normalised message (camelCase fields) or throws ProtocolError. */
export function parseMessage(text) {
  let message;
  try {
    message = JSON.parse(text);
  } catch (error) {
    throw new ProtocolError(`message is not JSON (${error.message}): ${shown(String(text))}`);
  }
  if (message === null || typeof message !== 'object' || Array.isArray(message)) {
    throw new ProtocolError(`message must be a JSON object, got ${shown(message)}`);
  }
  const parse = Object.hasOwn(kParsers, message.type) ? kParsers[message.type] : null;
  if (!parse) {
    throw new ProtocolError(`unknown message type ${shown(message.type)} (expected one of ${Object.keys(kParsers).join(', ')})`);
  }
  return parse(message);
}

/** The first message on a connection; `token` may be null (none needed, or given in the URL). */
export function helloMessage(token) {
  return JSON.stringify(token ? { type: 'hello', protocol: kProtocolVersion, token } : { type: 'hello', protocol: kProtocolVersion });
}

export function subscribeMessage(session) {
  return JSON.stringify({ type: 'subscribe', session });
}

/**
 * Where the camera is: eye [x, y, z], frustum planes [[a, b, c, d], ...] (inside where
 * a x + b y + c z + d >= 0), vertical fov in degrees, viewport height in pixels, the cell
 * budget and the screen-space error in pixels; `id` comes back in plan and view_done.
 */
export function viewMessage({ id, eye, planes, fov, height, budget, error }) {
  return JSON.stringify({ type: 'view', id, eye, planes, fov, height: Math.max(1, Math.round(height)), budget, error });
}

/** The session as it was at `until` (seconds since the epoch): the time slider. */
export function replayMessage(session, until) {
  return JSON.stringify({ type: 'replay', session, until });
}

/** Tiles the page no longer holds (its cache's budget): the server sends them again when needed. */
export function dropMessage(session, keys) {
  return JSON.stringify({ type: 'drop', session, keys });
}
