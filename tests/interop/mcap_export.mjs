// Issue 42: a session exported as MCAP (`stereomap-store export ID --mcap F`) read by Foxglove's
// own readers from npm (nobody on this project wrote them): @mcap/core's indexed reader with
// @mcap/support's decompressors and Google's Draco decoder (draco3d), every CRC checked (chunks and the attachment by the reader,
// the summary's by its footer, the data section's here); every message decoded with protobufjs
// against @foxglove/schemas' definitions (their generator's .proto, not ours); counts and
// poses equal to the journal's (the store's own TUM export of each vehicle), the map's cubes to
// the session's voxels, and the map.bt attachment to `export --format bt`.
//
//   node tests/interop/mcap_export.mjs --bin-dir build/bin --dds-config config/cyclonedds-loopback.xml --domain 111
import { spawn, spawnSync } from 'node:child_process';
import { mkdtemp, readFile, rm, writeFile } from 'node:fs/promises';
import { createRequire } from 'node:module';
import { tmpdir } from 'node:os';
import path from 'node:path';

import { compareGrid, decodeOptions, dracoDecoder, foxgloveTypes, freePort, interopTest } from './foxglove_support.mjs';

const require = createRequire(new URL('../../web/package.json', import.meta.url));
const { McapIndexedReader } = require('@mcap/core');
const { loadDecompressHandlers } = require('@mcap/support');
const { crc32 } = require('@foxglove/crc');

let dracoPoints;  // Google's own Draco decoder: a CompressedPointCloud's points

const { args, bin, env, check, failures } = interopTest('111');

function run(name, argv) {
  const result = spawnSync(bin(name), argv, { env, encoding: 'utf8', timeout: 300_000 });
  if (result.status !== 0) {
    throw new Error(`${name} ${argv.join(' ')}: exit ${result.status}\n${result.stdout}${result.stderr}`);
  }
  return result.stdout;
}

async function flySession(store, domain) {
  const port = await freePort();
  const server = spawn(bin('stereomap-server'), ['--store', store, '--http', `127.0.0.1:${port}`, '--domain', domain], { env, stdio: 'ignore' });
  try {
    for (let i = 0; i < 100; ++i) {
      try {
        const reply = await fetch(`http://127.0.0.1:${port}/healthz`);
        if (reply.ok) break;
      } catch {}
      await new Promise((r) => setTimeout(r, 100));
    }
    // Two vehicles in one session, one after the other.
    for (const vehicle of ['d1', 'd2']) {
      run('stereomap-onboard', ['--source', 'sim', '--frames', '150', '--rate', '0', '--domain', domain,
        '--session', 'flight', '--vehicle', vehicle, '--seed', vehicle === 'd1' ? '1' : '2']);
    }
    let status;
    for (let i = 0; i < 200; ++i) {
      status = await (await fetch(`http://127.0.0.1:${port}/api/sessions/flight`)).json();
      if (status.fusion_backlog === 0 && status.vehicles.length === 2) break;
      await new Promise((r) => setTimeout(r, 100));
    }
    // The same export over REST, streamed (chunked) by the running server.
    const reply = await fetch(`http://127.0.0.1:${port}/api/sessions/flight/session.mcap`);
    check(reply.status === 200 && reply.headers.get('transfer-encoding') === 'chunked' &&
      (reply.headers.get('content-disposition') ?? '').includes('flight.mcap'),
      `GET session.mcap: ${reply.status}, ${reply.headers.get('transfer-encoding')}`);
    const rest = Buffer.from(await reply.arrayBuffer());
    const missing = await fetch(`http://127.0.0.1:${port}/api/sessions/nobody/session.mcap`);
    const missingBody = await missing.json();
    check(missing.status === 404 && /nobody/.test(missingBody.error), `an unknown session: ${missing.status} ${missingBody.error}`);
    const bad = await fetch(`http://127.0.0.1:${port}/api/sessions/a%20b/session.mcap`);
    check(bad.status === 400, `a malformed id: ${bad.status}`);
    // The 2D grid of a band over REST (compared with the CLI's below).
    const band = 'zmin=0.3&zmax=1.8';
    const pgm = Buffer.from(await (await fetch(`http://127.0.0.1:${port}/api/sessions/flight/map2d.pgm?${band}`)).arrayBuffer());
    const yaml = await (await fetch(`http://127.0.0.1:${port}/api/sessions/flight/map2d.yaml?${band}`)).text();
    return { status, rest, grid: { pgm, yaml } };
  } finally {
    server.kill('SIGTERM');
    await new Promise((resolve) => server.on('exit', resolve));
  }
}

function tumPoses(text) {
  return text.trim().split('\n').filter((l) => l && !l.startsWith('#')).map((l) => l.split(/\s+/).map(Number));
}

async function main() {
  dracoPoints = await dracoDecoder();
  const dir = await mkdtemp(path.join(tmpdir(), 'stereomap-mcap-'));
  try {
    const store = path.join(dir, 'store');
    const { status, rest, grid } = await flySession(store, args.domain);
    const file = path.join(dir, 'flight.mcap');
    const printed = run('stereomap-store', ['--store', store, 'export', 'flight', '--mcap', file]);
    console.log(printed.trim());
    await writeFile(path.join(dir, 'rest.mcap'), rest);
    const tum = {};
    for (const vehicle of status.vehicles) {
      run('stereomap-store', ['--store', store, 'export', 'flight', '--format', 'tum', '--vehicle', vehicle, '--out', path.join(dir, `${vehicle}.tum`)]);
      tum[vehicle] = tumPoses(await readFile(path.join(dir, `${vehicle}.tum`), 'utf8'));
    }
    run('stereomap-store', ['--store', store, 'export', 'flight', '--format', 'bt', '--out', path.join(dir, 'map.bt')]);
    const mapBt = await readFile(path.join(dir, 'map.bt'));

    run('stereomap-store', ['--store', store, 'export', 'flight', '--format', 'grid', '--zmin', '0.3', '--zmax', '1.8', '--out', path.join(dir, 'band')]);
    const cliPgm = await readFile(path.join(dir, 'band.pgm'));
    const cliYaml = await readFile(path.join(dir, 'band.yaml'), 'utf8');
    check(Buffer.compare(cliPgm, grid.pgm) === 0 && cliYaml.replace('image: band.pgm', 'image: flight.pgm') === grid.yaml,
      `map2d.pgm and map2d.yaml over REST equal the CLI's grid (${grid.pgm.length} bytes)`);
    check(/^mode: trinary$/m.test(grid.yaml) && /^occupied_thresh: 0.65$/m.test(grid.yaml) && /^free_thresh: 0.196$/m.test(grid.yaml) && /^origin: \[/m.test(grid.yaml),
      'map2d.yaml: map_server\'s fields');
    for (const [label, exported] of [['stereomap-store export', file], ['REST', path.join(dir, 'rest.mcap')]]) {
      console.log(`-- ${label}`);
      await verify(await readFile(exported), status, tum, mapBt, async (zmin, zmax) => {
        run('stereomap-store', ['--store', store, 'export', 'flight', '--format', 'grid', '--zmin', zmin, '--zmax', zmax, '--out', path.join(dir, 'mcap-band')]);
        return { pgm: await readFile(path.join(dir, 'mcap-band.pgm')), yaml: await readFile(path.join(dir, 'mcap-band.yaml'), 'utf8') };
      });
    }
  } finally {
    await rm(dir, { recursive: true, force: true });
  }
  console.log(`${failures.length === 0 ? 'PASS' : 'FAIL'}: mcap export${failures.length ? ' — ' + failures.join('; ') : ''}`);
  process.exit(failures.length === 0 ? 0 : 1);
}

async function verify(bytes, status, tum, mapBt, gridOfBand) {
  {
    const readable = { size: async () => BigInt(bytes.length), read: async (offset, length) => bytes.subarray(Number(offset), Number(offset + length)) };
    const reader = await McapIndexedReader.Initialize({ readable, decompressHandlers: await loadDecompressHandlers() });
    check(true, `indexed: ${reader.chunkIndexes.length} chunks, ${reader.channelsById.size} channels, summary CRC checked by the reader`);
    // The data section's CRC: everything before the Data End record (13 bytes before the summary).
    const footer = bytes.length - 8 - 29;
    const summaryStart = Number(bytes.readBigUInt64LE(footer + 9));
    const dataEnd = summaryStart - 13;
    check(bytes[dataEnd] === 0x0f && reader.dataSectionCrc === crc32(bytes.subarray(0, dataEnd)),
      `data section CRC ${reader.dataSectionCrc} matches its ${dataEnd} bytes`);
    check(reader.chunkIndexes.every((c) => c.compression === 'zstd'), 'every chunk zstd');

    const types = foxgloveTypes();
    const schemaOf = new Map([...reader.channelsById.values()].map((c) => [c.id, reader.schemasById.get(c.schemaId)]));
    for (const schema of reader.schemasById.values()) {
      check(schema.encoding === 'protobuf' && schema.data.length > 0, `schema ${schema.name}: protobuf with its descriptors`);
    }
    const counts = {};
    const tf = {};
    let cubes = 0, points = 0, decodeErrors = 0;
    const trajectories = {};
    const grids = [];
    for await (const message of reader.readMessages({ validateCrcs: true })) {
      const channel = reader.channelsById.get(message.channelId);
      const schema = schemaOf.get(message.channelId);
      counts[channel.topic] = (counts[channel.topic] ?? 0) + 1;
      let decoded;
      try {
        const type = types.lookupType(schema.name);
        decoded = type.toObject(type.decode(message.data), decodeOptions);
      } catch (error) {
        ++decodeErrors;
        continue;
      }
      if (schema.name === 'foxglove.FrameTransform') {
        (tf[decoded.child_frame_id] ??= []).push(decoded);
      } else if (schema.name === 'foxglove.CompressedPointCloud') {
        const n = decoded.format === 'draco' ? dracoPoints(decoded.data) : -1;
        if (n <= 0) ++decodeErrors;
        points += n;
      } else if (schema.name === 'foxglove.PointCloud') {
        const names = decoded.fields.map((f) => `${f.name}:${f.type}@${f.offset}`).join(',');
        if (!names.startsWith('x:FLOAT32@0,y:FLOAT32@4,z:FLOAT32@8') || decoded.data.length % decoded.point_stride !== 0) ++decodeErrors;
        points += decoded.data.length / decoded.point_stride;
      } else if (schema.name === 'foxglove.SceneUpdate') {
        for (const entity of decoded.entities) cubes += entity.cubes.length;
      } else if (schema.name === 'foxglove.PosesInFrame') {
        trajectories[channel.topic] = decoded;
      } else if (schema.name === 'foxglove.Grid') {
        grids.push({ decoded, metadata: channel.metadata });
      }
    }
    check(decodeErrors === 0, `every message decodes with @foxglove/schemas' definitions (${decodeErrors} did not)`);
    check(counts['/tf'] === status.poses, `/tf: ${counts['/tf']} transforms, the session's ${status.poses} poses`);
    const clouds = status.vehicles.reduce((n, v) => n + (counts[`/vehicles/${v}/cloud`] ?? 0) + (counts[`/vehicles/${v}/cloud/points`] ?? 0), 0);
    check(clouds === status.frames, `clouds: ${clouds}, the session's ${status.frames} frames (${points} points, Draco decoded by Google's decoder)`);
    check(cubes === status.occupied_voxels, `/map: ${cubes} cubes, the session's ${status.occupied_voxels} voxels`);
    for (const vehicle of status.vehicles) {
      const sent = tf[vehicle] ?? [];
      const truth = tum[vehicle];
      let worst = sent.length === truth.length ? 0 : Infinity;
      for (let i = 0; i < Math.min(sent.length, truth.length); ++i) {
        const t = sent[i].timestamp.seconds + sent[i].timestamp.nanos * 1e-9;
        const p = sent[i].translation, q = sent[i].rotation;
        const row = truth[i];
        worst = Math.max(worst, Math.abs(t - row[0]), Math.abs(p.x - row[1]), Math.abs(p.y - row[2]), Math.abs(p.z - row[3]),
          Math.min(Math.abs(q.x - row[4]) + Math.abs(q.y - row[5]) + Math.abs(q.z - row[6]) + Math.abs(q.w - row[7]),
            Math.abs(q.x + row[4]) + Math.abs(q.y + row[5]) + Math.abs(q.z + row[6]) + Math.abs(q.w + row[7])));
      }
      check(worst < 1e-5, `${vehicle}: ${sent.length} transforms equal the journal's ${truth.length} poses (largest difference ${worst})`);
      const path = trajectories[`/vehicles/${vehicle}/trajectory`];
      check(path && path.poses.length === Math.min(truth.length, 1000), `${vehicle}: its last trajectory holds ${path?.poses.length} poses`);
    }
    // The grid, cell by cell against the CLI's map_server files of the same band.
    check(grids.length === 1, `/map2d: ${grids.length} grid`);
    if (grids.length === 1) {
      const { decoded: g, metadata } = grids[0];
      const files = await gridOfBand(metadata.get('z_min'), metadata.get('z_max'));
      const { rows, differing, same } = compareGrid(g, files);
      check(same, `/map2d: ${g.column_count} x ${rows} cells (band ${metadata.get('z_min')}..${metadata.get('z_max')} m) equal the CLI's grid cell by cell (${differing} differ)`);
    }
    const attachments = [];
    for await (const attachment of reader.readAttachments({ validateCrcs: true })) attachments.push(attachment);
    check(attachments.length === 1 && attachments[0].name === 'map.bt' && Buffer.compare(Buffer.from(attachments[0].data), mapBt) === 0,
      `map.bt attached (${attachments[0]?.data.length} bytes, CRC checked), equal to export --format bt`);
    const metadata = [];
    for await (const record of reader.readMetadata()) metadata.push(record);
    check(metadata.length === 1 && metadata[0].metadata.get('id') === 'flight', 'the session\'s metadata');
  }
}

main().catch((error) => {
  console.error(error);
  process.exit(1);
});
