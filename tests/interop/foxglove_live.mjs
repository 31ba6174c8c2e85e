// Issue 42: a live session in Foxglove's own WebSocket client (@foxglove/ws-protocol's
// FoxgloveClient over `ws`, from npm; nobody on this project wrote them) while a sim vehicle
// flies: the handshake, the channels, every message decoded with protobufjs against
// @foxglove/schemas' definitions (transforms, paths, Draco clouds through Google's decoder, the
// map's entities, the 2D grid), the map's cubes equal to the session's voxels and the last
// transform to its trajectory, a client that unsubscribes sees the flow stop, a client that
// stops reading a campus map is closed as /ws closes one, hostile clients are refused, and a
// server with a token serves only upgrades that carry it.
//
//   node tests/interop/foxglove_live.mjs --bin-dir build/bin --dds-config config/cyclonedds-loopback.xml --domain 113
import { spawn } from 'node:child_process';
import { existsSync } from 'node:fs';
import { mkdtemp, rm } from 'node:fs/promises';
import { tmpdir } from 'node:os';
import path from 'node:path';

import { compareGrid, connect, decodeOptions, dracoDecoder, FoxgloveClient, foxgloveTypes, freePort, interopTest, startServer, tileCount, waitFor, WebSocket } from './foxglove_support.mjs';

const kCampusMap = new URL('../../../shared/data/octomap_samples/fr_campus.bt', import.meta.url).pathname;
const { args, bin, env, check, failures } = interopTest('113');
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

function runToEnd(name, argv) {
  const child = spawn(bin(name), argv, { env, stdio: ['ignore', 'ignore', 'pipe'] });
  let err = '';
  child.stderr.on('data', (d) => { err += d; });
  return new Promise((resolve) => child.on('exit', (code) => resolve({ code, err })));
}

// A WebSocket upgrade's answer: its HTTP status, or 'open'.
function upgradeAnswer(port, target, protocols, headers = {}) {
  return new Promise((resolve) => {
    const ws = new WebSocket(`ws://127.0.0.1:${port}${target}`, protocols, { headers });
    ws.on('unexpected-response', (_req, res) => resolve(res.statusCode));
    ws.on('open', () => {
      resolve('open');
      ws.close();
    });
    ws.on('error', () => {});
  });
}

// The last pose of the session's trajectory (TUM over REST).
async function lastPose(base, session) {
  const text = await (await fetch(`${base}/api/sessions/${session}/trajectory.tum`)).text();
  const lines = text.trim().split('\n').filter((l) => l && !l.startsWith('#'));
  return lines.at(-1).split(/\s+/).map(Number);
}

async function main() {
  const types = foxgloveTypes();
  const draco = await dracoDecoder();
  const dir = await mkdtemp(path.join(tmpdir(), 'stereomap-foxglove-'));
  const store = path.join(dir, 'store');
  const withCampus = existsSync(kCampusMap);
  if (withCampus) {
    const imported = await runToEnd('stereomap-store', ['--store', store, 'import', kCampusMap, '--session', 'campus']);
    if (imported.code !== 0) throw new Error(`stereomap-store import: ${imported.err}`);
  } else {
    console.log(`skipping the slow client's part: ${kCampusMap} is absent`);
  }
  const port = await freePort();
  const base = `http://127.0.0.1:${port}`;
  const server = await startServer(bin('stereomap-server'), ['--store', store, '--http', `127.0.0.1:${port}`, '--domain', args.domain], env);
  const vehicle = spawn(bin('stereomap-onboard'), ['--source', 'sim', '--frames', '160', '--rate', '10', '--domain', args.domain,
    '--session', 'live', '--vehicle', 'd1'], { env, stdio: 'ignore' });
  let flying = true;
  const landed = new Promise((resolve) => vehicle.on('exit', (code) => { flying = false; resolve(code); }));
  try {
    // --- A: every channel of the live session, decoded -----------------------------------
    const a = await connect(`ws://127.0.0.1:${port}/foxglove?session=live`);
    const info = await a.serverInfo;
    check(info.name.startsWith('stereomap') && Array.isArray(info.capabilities) && typeof info.sessionId === 'string',
      `serverInfo: ${info.name}, capabilities ${JSON.stringify(info.capabilities)}`);
    check(a.client !== undefined && a.ws.protocol === 'foxglove.websocket.v1', `subprotocol chosen: ${a.ws.protocol}`);
    const wanted = ['/tf', '/map', '/map2d', '/vehicles/d1/trajectory', '/vehicles/d1/cloud'];
    await waitFor('the vehicle\'s channels', 30_000, () => wanted.every((t) => a.channels.has(t)));
    for (const [topic, channel] of a.channels) {
      check(channel.encoding === 'protobuf' && channel.schemaEncoding === 'protobuf' && types.lookupType(channel.schemaName) &&
        Buffer.from(channel.schema, 'base64').length > 100, `${topic}: ${channel.schemaName}, protobuf, a descriptor set`);
    }
    const got = { tf: [], paths: [], clouds: [], grids: [], entities: new Map(), mapMessages: 0, mapBytes: 0, badDecodes: [] };
    a.onMessage((topic, schemaName, bytes, timestamp) => {
      let m;
      try {
        m = types.lookupType(schemaName).toObject(types.lookupType(schemaName).decode(bytes), decodeOptions);
      } catch (e) {
        got.badDecodes.push(`${topic}: ${e.message}`);
        return;
      }
      if (topic === '/tf') got.tf.push(m);
      else if (topic === '/vehicles/d1/trajectory') got.paths.push(m);
      else if (topic === '/vehicles/d1/cloud') got.clouds.push({ m, points: draco(m.data) });
      else if (topic === '/map2d') got.grids.push(m);
      else if (topic === '/map') {
        ++got.mapMessages;
        got.mapBytes += bytes.length;
        for (const d of m.deletions) got.entities.delete(d.id);
        for (const e of m.entities) got.entities.set(e.id, e.cubes.length);
      }
    });
    for (const topic of wanted) a.subscribe(topic);

    // --- B: unsubscribes mid-flight and sees the flow stop ---------------------------------
    const b = await connect(`ws://127.0.0.1:${port}/foxglove?session=live`, ['foxglove.sdk.v1']);
    check(b.ws.protocol === 'foxglove.sdk.v1', `a client offering foxglove.sdk.v1 only is served: ${b.ws.protocol}`);
    await waitFor('B\'s channels', 10_000, () => b.channels.has('/tf') && b.channels.has('/vehicles/d1/cloud'));
    let bMessages = 0;
    b.onMessage(() => { ++bMessages; });
    const bSubs = [b.subscribe('/tf'), b.subscribe('/vehicles/d1/cloud'), b.subscribe('/map')];
    await waitFor('B\'s first 20 messages', 10_000, () => bMessages >= 20);
    for (const id of bSubs) b.client.unsubscribe(id);
    await sleep(300);  // what was on the wire already
    const bAtUnsubscribe = bMessages, aAtUnsubscribe = got.tf.length;
    await sleep(2000);
    check(flying && got.tf.length > aAtUnsubscribe + 5 && bMessages === bAtUnsubscribe,
      `unsubscribed: B got ${bMessages - bAtUnsubscribe} messages in 2 s while A got ${got.tf.length - aAtUnsubscribe} transforms`);
    b.client.close();

    // --- the flight ends: what A holds is the session --------------------------------------
    const code = await landed;
    check(code === 0, `the vehicle flew 160 frames (exit ${code})`);
    let status;
    await waitFor('fusion to finish', 60_000, async () => {
      status = await (await fetch(`${base}/api/sessions/live`)).json();
      return status.fusion_backlog === 0;
    });
    await sleep(3500);  // a poll, a path and a grid (at most every 2 s) later
    check(got.badDecodes.length === 0, `every message decoded against @foxglove/schemas (${got.badDecodes.slice(0, 3).join('; ')})`);
    const last = got.tf.at(-1);
    const truth = await lastPose(base, 'live');
    const t = last.translation, q = last.rotation;
    const stamp = last.timestamp.seconds + last.timestamp.nanos * 1e-9;
    // TUM text rounds: stamps to the microsecond, translations to 6 decimals, rotations to 9.
    check(last.parent_frame_id === 'map' && last.child_frame_id === 'd1' && Math.abs(stamp - truth[0]) < 1e-6 &&
      Math.max(...[t.x - truth[1], t.y - truth[2], t.z - truth[3]].map(Math.abs)) <= 5.01e-7 &&
      Math.max(...[q.x - truth[4], q.y - truth[5], q.z - truth[6], q.w - truth[7]].map(Math.abs)) <= 5.01e-10,
      `${got.tf.length} transforms; the last equals the session's last pose (t ${stamp.toFixed(3)}: ${JSON.stringify([t, q])} vs ${truth.join(' ')})`);
    const lastPath = got.paths.at(-1);
    check(lastPath && lastPath.frame_id === 'map' && lastPath.poses.length >= Math.min(status.poses, 1000) - 1,
      `${got.paths.length} paths; the last has ${lastPath?.poses.length} poses (session: ${status.poses})`);
    check(got.clouds.length >= 10 && got.clouds.every((c) => c.m.format === 'draco' && c.points > 0),
      `${got.clouds.length} clouds, Draco decoded by Google's decoder (${got.clouds.at(-1)?.points} points in the last)`);
    let cubes = 0;
    for (const n of got.entities.values()) cubes += n;
    const tiles = await tileCount(base, 'live');
    const tilesShown = new Set([...got.entities.keys()].map((id) => id.split('/')[1])).size;
    check(cubes === status.occupied_voxels && tilesShown === tiles,
      `the map: ${got.entities.size} entities of ${tilesShown} tiles, ${cubes} cubes; the session: ${tiles} tiles, ${status.occupied_voxels} voxels (${got.mapMessages} SceneUpdates, ${(got.mapBytes / 1e6).toFixed(1)} MB)`);
    // The last grid, cell by cell against map_server's files of its band over REST.
    const grid = got.grids.at(-1);
    const floor = status.bounds.min[2] + status.resolution / 2;  // the lowest occupied voxel's centre
    const band = `zmin=${(floor + 0.2).toFixed(6)}&zmax=${(floor + 2).toFixed(6)}`;
    const files = {
      pgm: Buffer.from(await (await fetch(`${base}/api/sessions/live/map2d.pgm?${band}`)).arrayBuffer()),
      yaml: await (await fetch(`${base}/api/sessions/live/map2d.yaml?${band}`)).text(),
    };
    const compared = grid ? compareGrid(grid, files) : { rows: 0, differing: NaN, same: false };
    check(compared.same, `${got.grids.length} grids; the last, ${grid?.column_count} x ${compared.rows} cells of ${grid?.cell_size?.x} m, equals map2d.pgm of its band cell by cell (${compared.differing} differ)`);
    a.client.close();

    // --- a client that stops reading: closed with the reason -------------------------------
    if (withCampus) {
      const opened = await fetch(`${base}/api/sessions/campus/open`, { method: 'POST' });
      check(opened.status === 200, `POST /api/sessions/campus/open: ${opened.status}`);
      const slow = await connect(`ws://127.0.0.1:${port}/foxglove?session=campus`);
      await waitFor('the campus map channel', 10_000, () => slow.channels.has('/map'));
      let closed = null;
      slow.ws.on('close', (code, reason) => { closed = { code, reason: String(reason) }; });
      slow.subscribe('/map');
      slow.ws._socket.pause();  // reads nothing more: the campus's entities back up
      await waitFor('the server to give up on the slow client', 40_000, () => /foxglove client \d+: closing \((client stuck|client too slow)/.test(server.log()));
      slow.ws._socket.resume();
      await waitFor('the slow client to see its socket close', 20_000, () => closed !== null);
      check(true, `a client that stopped reading the campus map was closed: ${server.log().match(/foxglove client \d+: closing \(([^)]*)\)/)[1]}`);
    }

    // --- hostile clients -------------------------------------------------------------------
    const upgrade = (target, protocols) => upgradeAnswer(port, target, protocols);
    const foxglove = [FoxgloveClient.SUPPORTED_SUBPROTOCOL];
    check(await upgrade('/foxglove', []) === 404, 'an upgrade at /foxglove without Foxglove\'s subprotocol: 404');
    check(await upgrade('/foxglove', ['something.else']) === 404, 'an upgrade at /foxglove with another subprotocol: 404');
    check(await upgrade('/elsewhere', foxglove) === 404, 'Foxglove\'s subprotocol at another path: 404');
    check(await upgrade('/foxglove?session=a%2F..', foxglove) === 400, 'a session that is not an id: 400');
    check(await upgrade('/ws', []) === 'open', 'the viewer\'s /ws is still served beside it');
    const hostile = await connect(`ws://127.0.0.1:${port}/`);
    const statuses = [];
    hostile.client.on('status', (s) => statuses.push(s));
    let hostileClosed = null;
    hostile.ws.on('close', (code, reason) => { hostileClosed = { code, reason: String(reason) }; });
    hostile.ws.send('{"op": "subscribe", "subscriptions": [{"id": 1, "channelId": 99999}]}');
    hostile.ws.send(Buffer.from([1, 0, 0, 0, 0, 1, 2, 3]));
    await waitFor('two status errors', 5000, () => statuses.length >= 2);
    check(statuses.every((s) => s.level === 2), `bad messages are answered with status errors: ${statuses.map((s) => s.message).join(' | ')}`);
    for (let i = 0; i < 20; ++i) hostile.ws.send('{');
    await waitFor('the hostile client to be closed', 5000, () => hostileClosed !== null);
    check(hostileClosed.code === 1008 && /too many bad messages/.test(hostileClosed.reason), `then closed: ${hostileClosed.code} ${hostileClosed.reason}`);
    check(!/internal error/.test(server.log()), 'no internal error in the server\'s log');

    // --- a server with a token: Foxglove has no hello, so the upgrade must carry it --------
    const tokenPort = await freePort();
    const guarded = await startServer(bin('stereomap-server'), ['--store', path.join(dir, 'guarded'), '--http', `127.0.0.1:${tokenPort}`,
      '--domain', args.domain], { ...env, STEREOMAP_TOKEN: 'sesame-1234' });
    try {
      const at = (target, headers = {}) => upgradeAnswer(tokenPort, target, foxglove, headers);
      check(await at('/foxglove') === 401, 'with a token set, an upgrade without it: 401');
      check(await at('/foxglove?token=wrong') === 401, 'with a wrong token: 401');
      check(await at('/foxglove?token=sesame-1234') === 'open', 'with ?token=: served');
      check(await at('/foxglove', { Authorization: 'Bearer sesame-1234' }) === 'open', 'with Authorization: Bearer: served');
    } finally {
      await guarded.stop();
    }
  } finally {
    vehicle.kill('SIGTERM');
    await server.stop();
    await rm(dir, { recursive: true, force: true });
  }
  console.log(`${failures.length === 0 ? 'PASS' : 'FAIL'}: foxglove live${failures.length ? ' — ' + failures.join('; ') : ''}`);
  process.exit(failures.length === 0 ? 0 : 1);
}

main().catch((e) => {
  console.error(`FAIL: foxglove live: ${e.stack ?? e}`);
  process.exit(1);
});
