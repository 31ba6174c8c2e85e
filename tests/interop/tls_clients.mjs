// https and wss with real clients (issue 55): a test CA made here with openssl, stereomap-server
// serving TLS itself (--tls-cert, --tls-key), a sim vehicle; then curl trusting the CA (and
// refusing the server without it, and plain http on that port), Foxglove's own client over
// wss, and headless chromium trusting the server's key opening the viewer over https until it
// renders the session's voxels (and refusing it without that trust).
// With --measure N it also times the first view (a fresh browser context's page load to the
// first rendered voxels of the stored session) over https and over plain http on a second
// server with a copy of the store, N times each, alternating, and prints its last line as
//   tls first view W ms, plain V ms (medians of N)
//
//   node tests/interop/tls_clients.mjs --bin-dir build/bin --dds-config config/cyclonedds-loopback.xml --domain 132 [--measure 5]
import { execFileSync, spawn, spawnSync } from 'node:child_process';
import { readFileSync, writeFileSync } from 'node:fs';
import { cp, mkdtemp, rm } from 'node:fs/promises';
import https from 'node:https';
import { tmpdir } from 'node:os';
import path from 'node:path';
import { parseArgs } from 'node:util';

import { FoxgloveClient, freePort, waitFor, WebSocket } from './foxglove_support.mjs';

const { values: args } = parseArgs({
  options: {
    'bin-dir': { type: 'string' },
    'dds-config': { type: 'string' },
    domain: { type: 'string', default: '132' },
    measure: { type: 'string', default: '0' },
  },
});
const bin = (name) => path.join(args['bin-dir'], name);
const env = { ...process.env, CYCLONEDDS_URI: `file://${args['dds-config']}` };
const failures = [];
const check = (ok, what) => {
  if (!ok) failures.push(what);
  console.log(`${ok ? 'ok  ' : 'FAIL'} ${what}`);
};
const kChromiumFlags = ['--headless', '--no-sandbox', '--disable-gpu', '--use-angle=swiftshader',
  '--enable-unsafe-swiftshader', '--disable-background-networking', '--disable-component-update', '--no-first-run'];

function openssl(argv, options = {}) {
  return execFileSync('openssl', argv, { stdio: ['pipe', 'pipe', 'ignore'], ...options });
}

// A CA and a certificate for 127.0.0.1 signed by it; the SPKI hash chromium is told to trust.
function makeCertificates(dir) {
  const file = (name) => path.join(dir, name);
  openssl(['req', '-x509', '-newkey', 'ec', '-pkeyopt', 'ec_paramgen_curve:P-256', '-nodes', '-keyout', file('ca.key'),
    '-out', file('ca.pem'), '-days', '2', '-subj', '/CN=stereomap test CA', '-addext', 'basicConstraints=critical,CA:TRUE',
    '-addext', 'keyUsage=critical,keyCertSign']);
  openssl(['req', '-newkey', 'ec', '-pkeyopt', 'ec_paramgen_curve:P-256', '-nodes', '-keyout', file('server.key'),
    '-out', file('server.csr'), '-subj', '/CN=127.0.0.1']);
  writeFileSync(file('server.ext'), 'subjectAltName=IP:127.0.0.1\nbasicConstraints=CA:FALSE\nextendedKeyUsage=serverAuth\n');
  openssl(['x509', '-req', '-in', file('server.csr'), '-CA', file('ca.pem'), '-CAkey', file('ca.key'), '-CAcreateserial',
    '-days', '2', '-out', file('server.pem'), '-extfile', file('server.ext')]);
  const key = openssl(['x509', '-in', file('server.pem'), '-pubkey', '-noout']);
  const der = openssl(['pkey', '-pubin', '-outform', 'der'], { input: key });
  const spki = openssl(['dgst', '-sha256', '-binary'], { input: der }).toString('base64');
  return { ca: file('ca.pem'), cert: file('server.pem'), key: file('server.key'), spki };
}

function startServer(argv) {
  const child = spawn(bin('stereomap-server'), argv, { env, stdio: ['ignore', 'pipe', 'pipe'] });
  let log = '';
  child.stdout.on('data', (d) => { log += d; });
  child.stderr.on('data', (d) => { log += d; });
  const exited = new Promise((resolve) => child.on('exit', resolve));
  return { log: () => log, stop: async () => { child.kill('SIGTERM'); await exited; } };
}

function curl(argv) {
  const run = spawnSync('curl', ['-s', '--max-time', '10', ...argv], { encoding: 'utf8' });
  return { code: run.status, body: run.stdout };
}

function fly(session, domain) {
  return new Promise((resolve) => {
    const child = spawn(bin('stereomap-onboard'), ['--source', 'sim', '--frames', '40', '--session', session,
      '--domain', domain, '--spool', 'memory', '--min-new', '0', '--link-budget', 'off', '--skip-late', 'off'],
    { env, stdio: ['ignore', 'ignore', 'pipe'] });
    let err = '';
    child.stderr.on('data', (d) => { err += d; });
    child.on('exit', (code) => resolve({ code, err }));
  });
}

async function loadChromium() {
  const modulePath = new URL('../../web/node_modules/playwright-core/index.mjs', import.meta.url);
  return (await import(modulePath.href)).chromium;
}

// Milliseconds from a fresh context's page load to the session's first rendered voxels.
async function firstView(browser, url) {
  const context = await browser.newContext({ viewport: { width: 800, height: 600 } });
  try {
    const page = await context.newPage();
    const started = performance.now();
    await page.goto(url);
    await page.waitForFunction(() => window.__stereomap && window.__stereomap.renderedVoxels() > 0,
      null, { timeout: 60_000, polling: 10 });
    return performance.now() - started;
  } finally {
    await context.close();
  }
}

const median = (values) => [...values].sort((a, b) => a - b)[Math.floor(values.length / 2)];

async function main() {
  const dir = await mkdtemp(path.join(tmpdir(), 'stereomap-tls-'));
  const servers = [];
  let browser;
  try {
    const certs = makeCertificates(dir);
    const port = await freePort();
    const base = `https://127.0.0.1:${port}`;
    const store = path.join(dir, 'store');
    servers.push(startServer(['--http', `127.0.0.1:${port}`, '--store', store, '--domain', args.domain,
      '--tls-cert', certs.cert, '--tls-key', certs.key]));
    await waitFor('the server over https', 20_000, () => curl(['--cacert', certs.ca, `${base}/healthz`]).code === 0);
    check(curl(['--cacert', certs.ca, `${base}/healthz`]).body.trim() === 'ok', 'curl trusting the test CA: GET /healthz over https');
    check(curl([`${base}/healthz`]).code === 60, 'curl without the CA refuses the server (exit 60)');
    check(curl([`http://127.0.0.1:${port}/healthz`]).code !== 0, 'plain http on the https port gets nothing');
    // The line may reach the pipe after /healthz answers (a loaded machine): wait for it.
    const says = () => servers[0].log().includes(`viewer: https://127.0.0.1:${port}/ (Foxglove: wss://`);
    await waitFor('the server\'s viewer line', 10_000, says).catch(() => {});
    check(says(), 'the server says https and wss');

    const flight = await fly('tls', args.domain);
    check(flight.code === 0, `a vehicle flew into the TLS server (exit ${flight.code})`);

    // Foxglove's own client over wss, trusting the test CA.
    const ca = readFileSync(certs.ca);
    const ws = new WebSocket(`wss://127.0.0.1:${port}/foxglove?session=tls`, [FoxgloveClient.SUPPORTED_SUBPROTOCOL], { ca });
    const client = new FoxgloveClient({ ws });
    let channels = 0;
    client.on('advertise', (list) => { channels += list.length; });
    await waitFor('Foxglove channels over wss', 20_000, () => channels > 0).catch(() => {});
    check(channels > 0, `Foxglove's client over wss: ${channels} channels advertised`);
    client.close();

    // The REST API over https from node, trusting the CA.
    const listed = await new Promise((resolve) => {
      https.get(`${base}/api/sessions`, { ca }, (res) => {
        let body = '';
        res.on('data', (d) => { body += d; });
        res.on('end', () => resolve(body));
      }).on('error', (e) => resolve(`error ${e.message}`));
    });
    check(listed.includes('"id":"tls"'), 'GET /api/sessions over https lists the flight');

    const chromium = await loadChromium();
    browser = await chromium.launch({ executablePath: '/usr/bin/chromium',
      args: [...kChromiumFlags, `--ignore-certificate-errors-spki-list=${certs.spki}`] });
    const shown = await firstView(browser, `${base}/?session=tls`).catch((e) => e);
    check(typeof shown === 'number', `chromium trusting the server's key renders the session over https and wss (${typeof shown === 'number' ? `${shown.toFixed(0)} ms` : shown.message})`);
    const untrusting = await chromium.launch({ executablePath: '/usr/bin/chromium', args: kChromiumFlags });
    const refused = await untrusting.newPage().then((page) => page.goto(`${base}/`)).then(() => 'loaded', (e) => e.message);
    await untrusting.close();
    check(/ERR_CERT/.test(refused), `chromium without that trust refuses the page (${refused.split('\n')[0]})`);

    const rounds = Number(args.measure);
    if (rounds > 0) {
      await servers[0].stop();
      servers.length = 0;
      const plainStore = path.join(dir, 'plain-store');
      await cp(store, plainStore, { recursive: true });
      const plainPort = await freePort();
      servers.push(startServer(['--http', `127.0.0.1:${port}`, '--store', store, '--domain', args.domain,
        '--tls-cert', certs.cert, '--tls-key', certs.key]));
      servers.push(startServer(['--http', `127.0.0.1:${plainPort}`, '--store', plainStore, '--domain', String(Number(args.domain) + 1)]));
      await waitFor('both servers', 20_000, () => curl(['--cacert', certs.ca, `${base}/healthz`]).code === 0 &&
        curl([`http://127.0.0.1:${plainPort}/healthz`]).code === 0);
      const tls = [];
      const plain = [];
      await firstView(browser, `${base}/?session=tls`);  // chromium's own first start
      for (let i = 0; i < rounds; ++i) {
        tls.push(await firstView(browser, `${base}/?session=tls`));
        plain.push(await firstView(browser, `http://127.0.0.1:${plainPort}/?session=tls`));
      }
      console.log(`tls ${tls.map((v) => v.toFixed(0)).join(' ')} ms; plain ${plain.map((v) => v.toFixed(0)).join(' ')} ms`);
      console.log(`tls first view ${median(tls).toFixed(0)} ms, plain ${median(plain).toFixed(0)} ms (medians of ${rounds})`);
    }
  } finally {
    await browser?.close().catch(() => {});
    for (const server of servers) await server.stop();
    await rm(dir, { recursive: true, force: true });
  }
  console.log(failures.length ? `${failures.length} failed: ${failures.join('; ')}` : 'every check passed');
  process.exit(failures.length ? 1 : 0);
}

main().catch((error) => {
  console.error(error);
  process.exit(1);
});
