import { describe, expect, it } from 'vitest';
import { ProtocolError, parseMessage } from './protocol.js';

const voxels = (fields) => JSON.stringify({ type: 'voxels', session: 'demo', resolution: 0.1, version: 1, ...fields });

describe('parseMessage', () => {
  it('normalises a session message', () => {
    const text = JSON.stringify({ type: 'session', id: 'demo', vehicle: 'sim-1', resolution: 0.1, frames: 12,
      occupied_voxels: 1234, bounds: { min: [0, -1, 0], max: [2, 3, 1.5] } });
    expect(parseMessage(text)).toEqual({ type: 'session', id: 'demo', vehicle: 'sim-1', resolution: 0.1,
      frames: 12, occupiedVoxels: 1234, bounds: { min: [0, -1, 0], max: [2, 3, 1.5] } });
  });

  it('treats absent reset/add/remove in a voxels message as no change', () => {
    expect(parseMessage(voxels({}))).toMatchObject({ reset: false, add: [], remove: [] });
  });

  it.each([
    ['bad JSON', '{"type": "voxels",', /not JSON/],
    ['a non-object', '[1, 2, 3]', /must be a JSON object/],
    ['an unknown type', '{"type": "teleport"}', /unknown message type "teleport"/],
    ['a missing type', '{"id": "demo"}', /unknown message type nothing/],
    ['a non-array add', voxels({ add: '1,2,3' }), /"add" must be an array/],
    ['add not a multiple of 3', voxels({ add: [1, 2, 3, 4] }), /"add" must hold whole .* got 4 numbers/],
    ['a fractional index', voxels({ remove: [1, 2.5, 3] }), /"remove"\[1\] must be an integer/],
    ['a negative version', voxels({ version: -1 }), /"version" must be a non-negative integer, got -1/],
    ['a zero resolution', voxels({ resolution: 0 }), /"resolution" must be a positive number/],
    ['a non-boolean reset', voxels({ reset: 'yes' }), /"reset" must be true or false, got "yes"/],
    ['a short pose', JSON.stringify({ type: 'poses', session: 'a', poses: [[0, 1, 2, 3, 0, 0, 0]] }), /"poses"\[0\] must be 8 finite numbers/],
    ['a zero quaternion', JSON.stringify({ type: 'poses', session: 'a', poses: [[0, 1, 2, 3, 0, 0, 0, 0]] }), /non-zero quaternion/],
    ['bad bounds', JSON.stringify({ type: 'session', id: 'a', vehicle: 'v', resolution: 0.1, frames: 0, occupied_voxels: 0, bounds: { min: [0, 0] } }), /"bounds" must be null or/],
    ['another protocol version', '{"type": "hello", "protocol": 2}', /protocol 2 is not supported/],
  ])('rejects %s', (_, text, reason) => {
    expect(() => parseMessage(text)).toThrow(ProtocolError);
    expect(() => parseMessage(text)).toThrow(reason);
  });
});
