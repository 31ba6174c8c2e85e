// Issue 42's choice of encoding, measured: a session's MCAP export (protobuf) written again by
// @mcap/core's own writer in Foxglove's three plug-in-free encodings, from the same messages:
// protobuf (as exported), JSON (Foxglove's JSON schemas: bytes as base64, times as {sec, nsec})
// and ROS 2 (CDR with the ros2msg definitions @foxglove/schemas generates, written by
// @foxglove/rosmsg2-serialization), each chunked with zstd as the export is; then each file read
// and every message decoded by its reader (protobufjs, JSON.parse, rosmsg2's MessageReader).
// Prints a table of sizes and read times (best of --repeat).
//
//   node tests/interop/mcap_encodings.mjs FILE.mcap [--repeat 3]
import { createRequire } from 'node:module';
import { readFile } from 'node:fs/promises';
import { parseArgs } from 'node:util';

import { foxgloveTypes } from './foxglove_support.mjs';

const require = createRequire(new URL('../../web/package.json', import.meta.url));
const { McapIndexedReader, McapWriter, TempBuffer } = require('@mcap/core');
const { loadDecompressHandlers } = require('@mcap/support');
const zstd = require('@foxglove/wasm-zstd');
const { foxgloveMessageSchemas, generateJsonSchema, generateRosMsgMergedSchema } = require('@foxglove/schemas/internal');
const { parse: parseRosMsg } = require('@foxglove/rosmsg');
const { MessageReader, MessageWriter } = require('@foxglove/rosmsg2-serialization');

const { values: options, positionals } = parseArgs({ allowPositionals: true, options: { repeat: { type: 'string', default: '3' } } });
if (positionals.length !== 1) {
  console.error('usage: node tests/interop/mcap_encodings.mjs FILE.mcap [--repeat N]');
  process.exit(2);
}
const decodeOptions = { longs: Number, enums: Number, bytes: Buffer, defaults: true, arrays: true };

// protobufjs' object of a Foxglove message as its JSON schema or its ROS 2 message has it.
function convert(value, ros) {
  if (value instanceof Uint8Array) {  // protobufjs' bytes (a Buffer or a view)
    return ros ? new Uint8Array(value) : Buffer.from(value.buffer, value.byteOffset, value.byteLength).toString('base64');
  }
  if (Array.isArray(value)) return value.map((v) => convert(v, ros));
  if (value !== null && typeof value === 'object') {
    const keys = Object.keys(value);
    if (keys.length === 2 && 'seconds' in value && 'nanos' in value) {  // Timestamp, Duration
      return ros ? { sec: value.seconds, nanosec: value.nanos } : { sec: value.seconds, nsec: value.nanos };
    }
    return Object.fromEntries(keys.map((k) => [k, convert(value[k], ros)]));
  }
  return value;
}

// Where what a reader decoded differs from what was written (numbers, strings, bytes, arrays):
// the path to the first difference, or null.
function difference(written, read, path = '') {
  if (written === null || written === undefined) return null;  // absent: the reader's default
  if (written instanceof Uint8Array) {
    return read instanceof Uint8Array && Buffer.compare(Buffer.from(written), Buffer.from(read)) === 0 ? null : path;
  }
  if (Array.isArray(written)) {
    if (!Array.isArray(read) || written.length !== read.length) return `${path} (length)`;
    for (let i = 0; i < written.length; ++i) {
      const d = difference(written[i], read[i], `${path}[${i}]`);
      if (d !== null) return d;
    }
    return null;
  }
  if (written !== null && typeof written === 'object') {
    for (const k of Object.keys(written)) {
      const d = difference(written[k], read?.[k], `${path}.${k}`);
      if (d !== null) return d;
    }
    return null;
  }
  return written === read || (typeof written === 'number' && Number(read) === written) ? null : `${path}: ${written} vs ${read}`;
}

function schemaOf(name) {  // "foxglove.PointCloud" -> @foxglove/schemas' PointCloud
  return foxgloveMessageSchemas[name.replace(/^foxglove\./, '')];
}

async function readAll(bytes) {
  const readable = { size: async () => BigInt(bytes.length), read: async (offset, length) => bytes.subarray(Number(offset), Number(offset + length)) };
  return McapIndexedReader.Initialize({ readable, decompressHandlers: await loadDecompressHandlers() });
}

async function writeMcap(messages, encodingOf) {
  await zstd.isLoaded;
  const chunks = [];
  const writable = { position: () => BigInt(chunks.reduce((n, c) => n + c.length, 0)), write: async (buffer) => { chunks.push(Buffer.from(buffer)); } };
  const writer = new McapWriter({ writable, chunkSize: 1024 * 1024, compressChunk: (data) => ({ compression: 'zstd', compressedData: zstd.compress(data, 3) }) });
  await writer.start({ profile: '', library: 'stereomap mcap_encodings' });
  const schemas = new Map(), channels = new Map();
  for (const m of messages) {
    const e = encodingOf(m.schema);
    if (!schemas.has(m.schema)) schemas.set(m.schema, await writer.registerSchema({ name: e.schemaName, encoding: e.schemaEncoding, data: e.schemaData }));
    if (!channels.has(m.topic)) channels.set(m.topic, await writer.registerChannel({ topic: m.topic, schemaId: schemas.get(m.schema), messageEncoding: e.messageEncoding, metadata: new Map() }));
    await writer.addMessage({ channelId: channels.get(m.topic), sequence: 0, logTime: m.logTime, publishTime: m.logTime, data: e.encode(m.object) });
  }
  await writer.end();
  return Buffer.concat(chunks);
}

async function main() {
  const types = foxgloveTypes();
  const source = await readFile(positionals[0]);
  const reader = await readAll(source);
  const messages = [];
  for await (const message of reader.readMessages()) {
    const channel = reader.channelsById.get(message.channelId);
    const schema = reader.schemasById.get(channel.schemaId).name;
    const type = types.lookupType(schema);
    messages.push({ topic: channel.topic, schema, logTime: message.logTime, raw: message.data, object: type.toObject(type.decode(message.data), decodeOptions) });
  }
  const encoder = new TextEncoder();
  const rosDefinitions = new Map();
  const rosOf = (schema) => {
    if (!rosDefinitions.has(schema)) {
      const text = generateRosMsgMergedSchema(schemaOf(schema), { rosVersion: 2 });
      const definitions = parseRosMsg(text, { ros2: true });
      rosDefinitions.set(schema, { text, writer: new MessageWriter(definitions), reader: new MessageReader(definitions) });
    }
    return rosDefinitions.get(schema);
  };
  const encodings = {
    protobuf: (schema) => ({
      schemaName: schema, schemaEncoding: 'protobuf', messageEncoding: 'protobuf',
      schemaData: reader.schemasById.get([...reader.schemasById.values()].find((s) => s.name === schema).id).data,
      encode: (object) => types.lookupType(schema).encode(types.lookupType(schema).fromObject(object)).finish(),
    }),
    json: (schema) => ({
      schemaName: schema, schemaEncoding: 'jsonschema', messageEncoding: 'json',
      schemaData: encoder.encode(JSON.stringify(generateJsonSchema(schemaOf(schema)))),
      encode: (object) => encoder.encode(JSON.stringify(convert(object, false))),
    }),
    ros2: (schema) => ({
      schemaName: schema.replace('foxglove.', 'foxglove_msgs/msg/'), schemaEncoding: 'ros2msg', messageEncoding: 'cdr',
      schemaData: encoder.encode(rosOf(schema).text),
      encode: (object) => rosOf(schema).writer.writeMessage(convert(object, true)),
    }),
  };
  const decoders = {
    protobuf: (schema, data) => types.lookupType(schema).decode(data),
    json: (_schema, data) => JSON.parse(new TextDecoder().decode(data)),
    ros2: (schema, data) => rosOf(schema.replace('foxglove_msgs/msg/', 'foxglove.')).reader.readMessage(data),
  };
  console.log(`${positionals[0]}: ${messages.length} messages, ${(source.length / 1e6).toFixed(2)} MB as exported`);
  console.log('\n| encoding | file (zstd chunks) | vs protobuf | read and decode every message (best of ' + options.repeat + ') |\n|---|---|---|---|');
  let protobufBytes = 0;
  for (const [name, encodingOf] of Object.entries(encodings)) {
    const file = await writeMcap(messages, encodingOf);
    if (name === 'protobuf') protobufBytes = file.length;
    let best = Infinity, count = 0;
    for (let r = 0; r < Number(options.repeat); ++r) {
      const start = performance.now();
      const again = await readAll(file);
      count = 0;
      for await (const message of again.readMessages()) {
        const channel = again.channelsById.get(message.channelId);
        decoders[name](again.schemasById.get(channel.schemaId).name, message.data);
        ++count;
      }
      best = Math.min(best, performance.now() - start);
    }
    if (count !== messages.length) throw new Error(`${name}: ${count} of ${messages.length} messages read back`);
    if (name === 'ros2') {  // every message as written, read back by rosmsg2's reader
      const again = await readAll(file);
      let i = 0;
      for await (const message of again.readMessages()) {
        const read = decoders.ros2(again.schemasById.get(again.channelsById.get(message.channelId).schemaId).name, message.data);
        const d = difference(convert(messages[i].object, true), read);
        if (d !== null) throw new Error(`ros2: message ${i} (${messages[i].topic}) does not read back as written: ${d}`);
        ++i;
      }
    }
    console.log(`| ${name} | ${(file.length / 1e6).toFixed(2)} MB | ${(file.length / protobufBytes).toFixed(2)}x | ${best.toFixed(0)} ms |`);
  }
}

main().catch((e) => {
  console.error(`mcap_encodings failed: ${e.stack ?? e}`);
  process.exit(1);
});
