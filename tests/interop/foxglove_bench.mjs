// The Foxglove figures of issue 42 (run by stereomap-bench-interop, which prints them): N
// FoxgloveClients (@foxglove/ws-protocol over `ws`) on a live session while a sim vehicle flies
// in real time, each subscribed to the map, the transforms, the path and the clouds: the lag of
// each live map message (from the change of its tile, the message's log time, to the client
// holding it decoded); then, on fr_campus.bt (1.2 M voxels) opened from the store, the time from
// a new client's connect to its first map message and to the whole map, and its bytes.
// Prints one JSON line last.
//
//   node tests/interop/foxglove_bench.mjs --bin-dir build/bin --dds-config config/cyclonedds-loopback.xml --domain 114 --viewers 10 --seconds 60
import { spawn } from 'node:child_process';
import { existsSync } from 'node:fs';
import { mkdtemp, rm } from 'node:fs/promises';
import { tmpdir } from 'node:os';
import path from 'node:path';
import { parseArgs } from 'node:util';

import { connect, foxgloveTypes, freePort, startServer, tileCount, waitFor } from './foxglove_support.mjs';

const { values: args } = parseArgs({
  options: {
    'bin-dir': { type: 'string' },
    'dds-config': { type: 'string' },
    'campus': { type: 'string', default: new URL('../../../shared/data/octomap_samples/fr_campus.bt', import.meta.url).pathname },
    domain: { type: 'string', default: '114' },
    viewers: { type: 'string', default: '10' },
    seconds: { type: 'string', default: '60' },
  },
});
const bin = (name) => path.join(args['bin-dir'], name);
const env = { ...process.env, CYCLONEDDS_URI: `file://${args['dds-config']}` };
const percentile = (values, p) => {
  const sorted = [...values].sort((x, y) => x - y);
  return sorted.length ? sorted[Math.min(sorted.length - 1, Math.floor(p * sorted.length))] : NaN;
};

async function main() {
  const types = foxgloveTypes();
  const sceneUpdate = types.lookupType('foxglove.SceneUpdate');
  const dir = await mkdtemp(path.join(tmpdir(), 'stereomap-foxglove-bench-'));
  const store = path.join(dir, 'store');
  const campus = existsSync(args.campus);
  if (campus) {
    const importer = spawn(bin('stereomap-store'), ['--store', store, 'import', args.campus, '--session', 'campus'], { env, stdio: 'ignore' });
    await new Promise((resolve) => importer.on('exit', resolve));
  }
  const port = await freePort();
  const server = await startServer(bin('stereomap-server'), ['--store', store, '--http', `127.0.0.1:${port}`, '--domain', args.domain], env);
  const result = { viewers: Number(args.viewers), seconds: Number(args.seconds) };
  try {
    const frames = Math.round(Number(args.seconds) * 10);
    const vehicle = spawn(bin('stereomap-onboard'), ['--source', 'sim', '--frames', String(frames), '--rate', '10', '--domain', args.domain,
      '--session', 'live', '--vehicle', 'd1'], { env, stdio: 'ignore' });
    const landed = new Promise((resolve) => vehicle.on('exit', resolve));
    const clients = [];
    for (let i = 0; i < result.viewers; ++i) clients.push(await connect(`ws://127.0.0.1:${port}/foxglove?session=live`));
    const topics = ['/map', '/tf', '/vehicles/d1/trajectory', '/vehicles/d1/cloud'];
    await waitFor('the live session\'s channels', 30_000, () => clients.every((c) => topics.every((t) => c.channels.has(t))));
    const lags = [];
    let messages = 0, bytes = 0;
    const subscribed = BigInt(Date.now()) * 1_000_000n;
    for (const c of clients) {
      c.onMessage((topic, _schema, data, timestamp) => {
        ++messages;
        bytes += data.length;
        if (topic !== '/map') return;
        sceneUpdate.decode(data);  // held decoded
        if (timestamp > subscribed) lags.push(Date.now() - Number(timestamp / 1_000_000n));
      });
      for (const t of topics) c.subscribe(t);
    }
    const code = await landed;
    if (code !== 0) throw new Error(`the vehicle exited ${code}`);
    for (const c of clients) c.client.close();
    result.live = { map_messages: lags.length, messages, mb: bytes / 1e6, lag_p50_ms: percentile(lags, 0.5), lag_p95_ms: percentile(lags, 0.95), lag_max_ms: Math.max(...lags) };

    if (campus) {
      const opened = await fetch(`http://127.0.0.1:${port}/api/sessions/campus/open`, { method: 'POST' });
      if (opened.status !== 200) throw new Error(`opening the campus: ${opened.status}`);
      const status = await (await fetch(`http://127.0.0.1:${port}/api/sessions/campus`)).json();
      status.tiles = await tileCount(`http://127.0.0.1:${port}`, 'campus');
      const runs = [];
      for (let run = 0; run < 3; ++run) {
        const start = performance.now();
        const c = await connect(`ws://127.0.0.1:${port}/foxglove?session=campus`);
        await waitFor('the campus map channel', 10_000, () => c.channels.has('/map'));
        const timing = { first_ms: null, all_ms: null, bytes: 0, cubes: 0, entities: 0 };
        const tiles = new Set();
        c.onMessage((topic, _schema, data) => {
          if (topic !== '/map') return;
          const m = sceneUpdate.decode(data);
          timing.first_ms ??= performance.now() - start;
          timing.bytes += data.length;
          for (const e of m.entities) {
            timing.cubes += e.cubes.length;
            tiles.add(e.id.split('/')[1]);
          }
          timing.entities += m.entities.length;
          if (tiles.size === status.tiles) timing.all_ms ??= performance.now() - start;
        });
        c.subscribe('/map');
        await waitFor('the whole campus map', 120_000, () => timing.all_ms !== null);
        c.client.close();
        runs.push(timing);
      }
      result.campus = { voxels: status.occupied_voxels, tiles: status.tiles, runs };
    }
  } finally {
    await server.stop();
    await rm(dir, { recursive: true, force: true });
  }
  console.log(JSON.stringify(result));
}

main().catch((e) => {
  console.error(`foxglove bench failed: ${e.stack ?? e}`);
  process.exit(1);
});
