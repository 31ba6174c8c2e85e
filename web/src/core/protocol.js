// Parsing and validation of the server → viewer WebSocket messages (docs/PROTOCOL.md, v1).
// Entry point: parseMessage(text). A message is checked completely before anything uses it,
// so a malformed one is rejected (ProtocolError naming the field) without touching any state.

export const kProtocolVersion = 1;

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

// Reads field `name` of `message`, or throws naming the message type, field and value.
function field(message, name, isValid, expected, { optional = false, fallback } = {}) {
  const value = message[name];
  if (value === undefined && optional) return fallback;
  if (!isValid(value)) {
    throw new ProtocolError(`${message.type} message: "${name}" must be ${expected}, got ${shown(value)}`);
  }
  return value;
}

const requireId = (m, name) => field(m, name, (v) => typeof v === 'string' && v.length > 0, 'a non-empty string');
const requireResolution = (m) => field(m, 'resolution', (v) => isFiniteNumber(v) && v > 0, 'a positive number (metres)');
const optionalReset = (m) => field(m, 'reset', (v) => typeof v === 'boolean', 'true or false', { optional: true, fallback: false });

function isPoint(v) {
  return Array.isArray(v) && v.length === 3 && v.every(isFiniteNumber);
}

function isBounds(v) {
  return v === null || (typeof v === 'object' && !Array.isArray(v) && isPoint(v.min) && isPoint(v.max));
}

// A flat [ix, iy, iz, ...] array of integer voxel indices; absent means no change.
function voxelIndices(message, name) {
  const value = message[name];
  if (value === undefined) return [];
  if (!Array.isArray(value)) {
    throw new ProtocolError(`voxels message: "${name}" must be an array of integer triples, got ${shown(value)}`);
  }
  if (value.length % 3 !== 0) {
    throw new ProtocolError(`voxels message: "${name}" must hold whole [ix, iy, iz] triples, got ${value.length} numbers`);
  }
  const bad = value.findIndex((v) => !Number.isSafeInteger(v));
  if (bad >= 0) {
    throw new ProtocolError(`voxels message: "${name}"[${bad}] must be an integer index, got ${shown(value[bad])}`);
  }
  return value;
}

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

const kParsers = {
  hello(m) {
    const protocol = field(m, 'protocol', Number.isSafeInteger, 'an integer');
    if (protocol !== kProtocolVersion) {
      throw new ProtocolError(`hello message: protocol ${protocol} is not supported (this viewer speaks ${kProtocolVersion})`);
    }
    return { type: 'hello', protocol, server: field(m, 'server', (v) => typeof v === 'string', 'a string', { optional: true, fallback: '' }) };
  },
  session(m) {
    return {
      type: 'session',
      id: requireId(m, 'id'),
      vehicle: field(m, 'vehicle', (v) => typeof v === 'string', 'a string'),
      resolution: requireResolution(m),
      frames: field(m, 'frames', isCount, 'a count'),
      occupiedVoxels: field(m, 'occupied_voxels', isCount, 'a count'),
      bounds: field(m, 'bounds', isBounds, 'null or {"min": [x, y, z], "max": [x, y, z]}'),
    };
  },
  voxels(m) {
    return {
      type: 'voxels',
      session: requireId(m, 'session'),
      resolution: requireResolution(m),
      version: field(m, 'version', isCount, 'a non-negative integer'),
      reset: optionalReset(m),
      add: voxelIndices(m, 'add'),
      remove: voxelIndices(m, 'remove'),
    };
  },
  poses(m) {
    return {
      type: 'poses',
      session: requireId(m, 'session'),
      vehicle: field(m, 'vehicle', (v) => typeof v === 'string', 'a string', { optional: true, fallback: '' }),
      reset: optionalReset(m),
      poses: poseList(m),
    };
  },
  session_removed(m) {
    return { type: 'session_removed', id: requireId(m, 'id') };
  },
  error(m) {
    return { type: 'error', message: field(m, 'message', (v) => typeof v === 'string', 'a string') };
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
    throw new ProtocolError(`unknown message type ${shown(message.type)} (expected hello, session, session_removed, voxels, poses or error)`);
  }
  return parse(message);
}
