import { describe, expect, it } from 'vitest';
import { ProtocolError, helloMessage, parseMessage, viewMessage } from './protocol.js';

const status = { id: 's1', vehicle: 'uav', state: 'live', resolution: 0.1, frames: 3, occupied_voxels: 40, poses: 2, bounds: null };

describe('parseMessage', () => {
  it('reads the messages of protocol 2', () => {
    expect(parseMessage('{"type":"hello","protocol":2,"server":"stereomap"}').protocol).toBe(2);
    const list = parseMessage(JSON.stringify({ type: 'sessions', sessions: [status] }));
    expect(list.sessions[0]).toMatchObject({ id: 's1', occupiedVoxels: 40, state: 'live', corrections: 0, refusing: false });
    const corrected = parseMessage(JSON.stringify({ type: 'session', ...status, corrections: 3, refusing: true }));
    expect(corrected).toMatchObject({ corrections: 3, refusing: true });
    expect(list.sessions[0]).toMatchObject({ poses: 2, framesReceived: null, bytesReceived: null }); // not said: unknown
    const counted = parseMessage(JSON.stringify({ type: 'session', ...status, frames_received: 4, bytes_received: 5_000_000_000 }));
    expect(counted).toMatchObject({ poses: 2, framesReceived: 4, bytesReceived: 5_000_000_000 });
    expect(() => parseMessage(JSON.stringify({ type: 'session', ...status, bytes_received: -1 }))).toThrow(/"bytes_received"/);
    expect(() => parseMessage(JSON.stringify({ type: 'session', ...status, refusing: 'yes' }))).toThrow(/"refusing"/);
    const subscribed = parseMessage(JSON.stringify({ type: 'subscribed', session: 's1', resolution: 0.1, version: 4, voxels: 40, tiles: 2,
      bounds: { min: [0, 0, 0], max: [1, 1, 1] }, status }));
    expect(subscribed.status.frames).toBe(3);
    expect(parseMessage('{"type":"map","session":"s1","version":9,"changed_ms":5,"voxels":41,"tiles":2,"bounds":null}').changedMs).toBe(5);
    expect(parseMessage('{"type":"poses","session":"s1","vehicle":"uav","poses":[[1,0,0,0,0,0,0,1]]}').poses).toHaveLength(1);
    expect(parseMessage('{"type":"view_done","id":3,"session":"s1"}').id).toBe(3);
    // Each vehicle's own counters; none from a server that does not send them.
    expect(list.sessions[0].vehicleStatus).toEqual([]);
    const counters = parseMessage(JSON.stringify({ type: 'session', ...status, vehicle_status: [
      { vehicle_id: 'uav-1', spool_samples: 12, spool_bytes: 900, skipped_frames: 2, late_frames: 0, given_up: 1, held_back: 0,
        session_closed: true, received_s: 1.7e9 }] }));
    expect(counters.vehicleStatus).toEqual([{ vehicleId: 'uav-1', spoolSamples: 12, spoolBytes: 900, skippedFrames: 2,
      lateFrames: 0, givenUp: 1, heldBack: 0, sessionClosed: true }]);
    expect(() => parseMessage(JSON.stringify({ type: 'session', ...status, vehicle_status: [{ vehicle_id: '' }] }))).toThrow(/vehicle_id/);
    expect(() => parseMessage(JSON.stringify({ type: 'session', ...status, vehicle_status: [{ vehicle_id: 'a', spool_samples: -3 }] }))).toThrow(/spool_samples/);
    expect(() => parseMessage(JSON.stringify({ type: 'session', ...status, vehicle_status: [7] }))).toThrow(/vehicle_status/);
    // Vehicles in their own frame and their alignment; none from an older server.
    expect(list.sessions[0].vehicleFrames).toEqual([]);
    const frames = parseMessage(JSON.stringify({ type: 'session', ...status, vehicle_frames: [
      { vehicle_id: 'sim-2', frame: 'aligned', attempts: 4, reason: '', transform: [1, 2, 3, 0, 0, 0, 1], overlap: 0.62, rmse_m: 0.04, aligned_s: 3.1 },
      { vehicle_id: 'sim-3', frame: 'aligning' }] }));
    expect(frames.vehicleFrames).toEqual([
      { vehicleId: 'sim-2', frame: 'aligned', attempts: 4, reason: '', transform: [1, 2, 3, 0, 0, 0, 1], overlap: 0.62, rmseM: 0.04, alignedS: 3.1 },
      { vehicleId: 'sim-3', frame: 'aligning', attempts: 0, reason: '', transform: null, overlap: null, rmseM: null, alignedS: null }]);
    expect(() => parseMessage(JSON.stringify({ type: 'session', ...status, vehicle_frames: [{ vehicle_id: 'a', frame: 'lost' }] }))).toThrow(/"frame" must be "aligning" or "aligned"/);
    expect(() => parseMessage(JSON.stringify({ type: 'session', ...status, vehicle_frames: [{ vehicle_id: 'a', frame: 'aligned', transform: [1, 2] }] }))).toThrow(/transform/);
    // What made a session that is not a flight: a site, a diff, an import; null for a flight.
    expect(list.sessions[0].origin).toBe(null);
    const site = parseMessage(JSON.stringify({ type: 'session', ...status, origin: { site: {
      sessions: [{ session: 'mon', transform: [0, 0, 0, 0, 0, 0, 1] },
        { session: 'tue', onto: 'mon', transform: [20, 0, 0, 0, 0, 0.7071068, 0.7071068], overlap: 0.64, rmse_m: 0.031 }],
      left_out: [{ session: 'hall', reason: 'aligns onto none' }] } } }));
    expect(site.origin.site.sessions[1]).toEqual({ session: 'tue', onto: 'mon', transform: [20, 0, 0, 0, 0, 0.7071068, 0.7071068], overlap: 0.64, rmseM: 0.031 });
    expect(site.origin.site.leftOut).toEqual([{ session: 'hall', reason: 'aligns onto none' }]);
    const diff = parseMessage(JSON.stringify({ type: 'session', ...status, origin: { diff: { first: 'a', second: 'b', appeared: 3, disappeared: 1, unchanged: 9, unseen_by_first: 2, unseen_by_second: 0 } } }));
    expect(diff.origin.diff).toEqual({ first: 'a', second: 'b', appeared: 3, disappeared: 1, unchanged: 9, unseenByFirst: 2, unseenBySecond: 0 });
    expect(() => parseMessage(JSON.stringify({ type: 'session', ...status, origin: [] }))).toThrow(/"origin" must be an object/);
    expect(() => parseMessage(JSON.stringify({ type: 'session', ...status, origin: { site: { sessions: [{ session: 'x', transform: [1] }] } } }))).toThrow(/transform/);
    expect(() => parseMessage(JSON.stringify({ type: 'session', ...status, origin: { diff: { first: '', second: 'b' } } }))).toThrow(/first/);
  });

  it('rejects what it cannot trust, naming the field', () => {
    expect(() => parseMessage('{"type":"hello","protocol":1}')).toThrow(/protocol 1 is not supported/);
    expect(() => parseMessage('{"type":"voxels"}')).toThrow(/unknown message type/);
    expect(() => parseMessage('nope')).toThrow(ProtocolError);
    expect(() => parseMessage('{"type":"poses","session":"s","poses":[[1,0,0,0,0,0,0,0]]}')).toThrow(/non-zero quaternion/);
    expect(() => parseMessage('{"type":"map","session":"s","version":-1,"changed_ms":0,"voxels":0,"tiles":0}')).toThrow(/"version"/);
  });
});

describe('viewer messages', () => {
  it('say hello with the protocol and, when given, the token', () => {
    expect(JSON.parse(helloMessage(null))).toEqual({ type: 'hello', protocol: 2 });
    expect(JSON.parse(helloMessage('t'))).toEqual({ type: 'hello', protocol: 2, token: 't' });
  });
  it('round the viewport height', () => {
    expect(JSON.parse(viewMessage({ id: 1, eye: [0, 0, 1], planes: [], fov: 50, height: 799.6, budget: 10, error: 2 })).height).toBe(800);
  });
});
