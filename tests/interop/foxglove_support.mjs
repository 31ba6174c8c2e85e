// What the interop tests and the Foxglove benchmark share: Foxglove's schemas as protobufjs
// types (from @foxglove/schemas' own generator, not our .proto files), Google's Draco decoder,
// a server started and stopped, and a Foxglove WebSocket client (@foxglove/ws-protocol's
// FoxgloveClient over `ws`) that keeps the channels it is told of.
import { spawn } from 'node:child_process';
import { createRequire } from 'node:module';
import net from 'node:net';
import path from 'node:path';
import { parseArgs } from 'node:util';

const require = createRequire(new URL('../../web/package.json', import.meta.url));
const { foxgloveMessageSchemas, foxgloveEnumSchemas, generateProto } = require('@foxglove/schemas/internal');
const protobuf = require('protobufjs');
const draco3d = require('draco3d');
export const { FoxgloveClient } = require('@foxglove/ws-protocol');
export const WebSocket = require('ws');

// An interop test's command line (--bin-dir, --dds-config, --domain) and its checks: bin(name)
// is a binary's path, env the environment with the loopback DDS config, check(ok, what)
// prints a line and remembers a failure.
export function interopTest(defaultDomain) {
  const { values: args } = parseArgs({
    options: {
      'bin-dir': { type: 'string' },
      'dds-config': { type: 'string' },
      domain: { type: 'string', default: defaultDomain },
    },
  });
  const failures = [];
  return {
    args,
    failures,
    bin: (name) => path.join(args['bin-dir'], name),
    env: { ...process.env, CYCLONEDDS_URI: `file://${args['dds-config']}` },
    check: (ok, what) => {
      if (!ok) failures.push(what);
      console.log(`${ok ? 'ok  ' : 'FAIL'} ${what}`);
    },
  };
}

export function foxgloveTypes() {
  const root = new protobuf.Root();
  root.addJSON(protobuf.common['google/protobuf/timestamp.proto'].nested);
  root.addJSON(protobuf.common['google/protobuf/duration.proto'].nested);
  for (const [name, schema] of Object.entries(foxgloveMessageSchemas)) {
    const enums = Object.values(foxgloveEnumSchemas).filter((e) => e.parentSchemaName === name);
    protobuf.parse(generateProto(schema, enums), root, { keepCase: true });
  }
  root.resolveAll();
  return root;
}

export const decodeOptions = { longs: Number, enums: String, bytes: Buffer, defaults: true, arrays: true };

// A function from a Draco payload to its number of points (-1: it does not decode, or a
// coordinate is not finite), with Google's own decoder (WebAssembly, from npm).
export async function dracoDecoder() {
  const draco = await draco3d.createDecoderModule({});
  return (bytes) => {
    const buffer = new draco.DecoderBuffer();
    const decoder = new draco.Decoder();
    const cloud = new draco.PointCloud();
    try {
      buffer.Init(new Int8Array(bytes.buffer, bytes.byteOffset, bytes.length), bytes.length);
      if (!decoder.DecodeBufferToPointCloud(buffer, cloud).ok()) return -1;
      const positions = new draco.DracoFloat32Array();
      const attribute = decoder.GetAttribute(cloud, decoder.GetAttributeId(cloud, draco.POSITION));
      decoder.GetAttributeFloatForAllPoints(cloud, attribute, positions);
      for (let i = 0; i < positions.size(); ++i) if (!Number.isFinite(positions.GetValue(i))) return -1;
      const n = cloud.num_points();
      draco.destroy(positions);
      return n;
    } finally {
      draco.destroy(cloud);
      draco.destroy(decoder);
      draco.destroy(buffer);
    }
  };
}

export async function freePort() {
  return new Promise((resolve) => {
    const server = net.createServer();
    server.listen(0, '127.0.0.1', () => {
      const { port } = server.address();
      server.close(() => resolve(port));
    });
  });
}

// Polls `condition` (may be async) every 50 ms; throws naming `what` after `ms`.
export async function waitFor(what, ms, condition) {
  const deadline = Date.now() + ms;
  while (!(await condition())) {
    if (Date.now() > deadline) throw new Error(`timed out after ${ms} ms waiting for ${what}`);
    await new Promise((r) => setTimeout(r, 50));
  }
}

// stereomap-server with `argv` (which has --http 127.0.0.1:PORT), up once /healthz answers;
// log() is what it has logged so far.
export async function startServer(program, argv, env) {
  const child = spawn(program, argv, { env, stdio: ['ignore', 'pipe', 'pipe'] });
  let log = '';
  child.stdout.on('data', (d) => { log += d; });
  child.stderr.on('data', (d) => { log += d; });
  const exited = new Promise((resolve) => child.on('exit', resolve));
  const port = argv[argv.indexOf('--http') + 1].split(':')[1];
  await waitFor('the server\'s /healthz', 20_000, async () => {
    try {
      return (await fetch(`http://127.0.0.1:${port}/healthz`)).ok;
    } catch {
      return false;
    }
  });
  return {
    log: () => log,
    stop: async () => {
      child.kill('SIGTERM');
      await exited;
    },
  };
}

// How many tiles session `session` of the server at `base` has (its tile index's level 0).
export async function tileCount(base, session) {
  const index = await (await fetch(`${base}/api/sessions/${session}/tiles`)).json();
  return index.tiles.filter((t) => t.level === 0).length;
}

// A FoxgloveClient connected to `url`, offering `protocols`. `channels`: topic -> channel as
// advertised (unadvertised ones leave); subscribe(topic) returns the subscription id;
// onMessage(f) calls f(topic, schemaName, bytes, timestamp in ns as a BigInt, received ms).
export async function connect(url, protocols = [FoxgloveClient.SUPPORTED_SUBPROTOCOL]) {
  const ws = new WebSocket(url, protocols);
  const client = new FoxgloveClient({ ws });
  const channels = new Map();
  const byId = new Map();
  const bySubscription = new Map();
  const listeners = [];
  client.on('advertise', (list) => {
    for (const c of list) {
      channels.set(c.topic, c);
      byId.set(c.id, c);
    }
  });
  client.on('unadvertise', (ids) => {
    for (const id of ids) {
      const c = byId.get(id);
      if (c) channels.delete(c.topic);
      byId.delete(id);
    }
  });
  client.on('message', ({ subscriptionId, timestamp, data }) => {
    const received = Date.now();
    const channel = bySubscription.get(subscriptionId);
    if (!channel) return;
    const bytes = new Uint8Array(data.buffer, data.byteOffset, data.byteLength);
    for (const f of listeners) f(channel.topic, channel.schemaName, bytes, timestamp, received);
  });
  client.on('error', () => {});
  const serverInfo = new Promise((resolve) => client.on('serverInfo', resolve));
  await new Promise((resolve, reject) => {
    ws.once('open', resolve);
    ws.once('error', reject);
  });
  return {
    ws,
    client,
    channels,
    serverInfo,
    subscribe(topic) {
      const channel = channels.get(topic);
      const id = client.subscribe(channel.id);
      bySubscription.set(id, channel);
      return id;
    },
    onMessage(f) {
      listeners.push(f);
    },
  };
}

// A PGM (P5) as { width, height, pixels }.
export function parsePgm(bytes) {
  const text = bytes.subarray(0, 64).toString('latin1');
  const match = /^P5\s+(\d+)\s+(\d+)\s+255\s/.exec(text);
  if (!match) throw new Error('not a P5 PGM');
  const width = Number(match[1]), height = Number(match[2]);
  return { width, height, pixels: bytes.subarray(match[0].length) };
}

// A decoded foxglove.Grid `g` against map_server's files of the same band ({ pgm, yaml }),
// cell by cell: { rows, differing, same } (same: sizes, every cell and the origin agree).
export function compareGrid(g, files) {
  const pgm = parsePgm(files.pgm);
  const rows = g.data.length / g.row_stride;
  let differing = g.fields[0]?.name === 'occupancy' && g.fields[0]?.type === 'INT8' ? 0 : Infinity;
  for (let row = 0; row < rows && pgm.width === g.column_count && pgm.height === rows; ++row) {
    for (let column = 0; column < g.column_count; ++column) {
      const cell = Buffer.from(g.data.buffer, g.data.byteOffset, g.data.length).readInt8(row * g.row_stride + column * g.cell_stride);
      const pixel = pgm.pixels[(pgm.height - 1 - row) * pgm.width + column];
      if (pixel !== (cell === 100 ? 0 : cell === 0 ? 254 : 205)) ++differing;
    }
  }
  const origin = /origin: \[([^,]+), ([^,]+),/.exec(files.yaml);
  const same = pgm.width === g.column_count && pgm.height === rows && differing === 0 &&
    Math.abs(Number(origin[1]) - g.pose.position.x) < 1e-9 && Math.abs(Number(origin[2]) - g.pose.position.y) < 1e-9;
  return { rows, differing, same };
}
