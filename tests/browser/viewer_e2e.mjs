#!/usr/bin/env node
// End-to-end test of the browser viewer: a real stereomap-server and stereomap-onboard (sim
// source) over DDS on loopback, the built viewer in headless Debian chromium. Checks that the
// page shows the live rates while the vehicle flies and ends up drawing exactly the server's
// occupied voxels, frame count and trajectory; then (with ../shared/data) the imported
// Freiburg campus map at the levels the server chose, tile by tile against
// GET /api/sessions/campus/tiles; the time slider replaying the flight to its middle and back;
// switching sessions; and a page that reconnects by itself after the server restarts.
// Screenshots sit beside --screenshot.
//
// Usage: viewer_e2e.mjs --bin-dir DIR --web-root DIR --dds-config FILE --domain N
//                       --screenshot FILE [--port P] [--frames 60]
// Without --port (or with 0) a free port is picked: the server keeps it across its restart.
// Prints "1 passed, 0 failed" and exits 0, or "0 passed, 1 failed" and exits 1; 2 on bad usage.

import { spawn } from 'node:child_process';
import { existsSync } from 'node:fs';
import { mkdtemp, mkdir, rm } from 'node:fs/promises';
import net from 'node:net';
import { tmpdir } from 'node:os';
import path from 'node:path';
import { pathToFileURL } from 'node:url';
import { parseArgs } from 'node:util';

const kOverallTimeoutMs = 300_000;
const kCampusTimeoutMs = 90_000;
const kCampusMap = new URL('../../../shared/data/octomap_samples/fr_campus.bt', import.meta.url).pathname;
const kHealthTimeoutMs = 20_000;
const kFirstVoxelsTimeoutMs = 60_000;
const kServerSettleTimeoutMs = 60_000;
const kPageCatchUpTimeoutMs = 30_000;
const kStablePolls = 3; // occupied_voxels unchanged over this many polls = fusion finished
// The voxels are drawn in the height ramp's saturated colours; the background, grid and
// trajectory are grey. Measured on a 3,015-voxel room from a mock server, auto-framed: 18.8 %
// of the view coloured; 0.04 % (the pose marker alone) when the boxes were never written.
const kMinColouredFraction = 0.01;
const kChromiumFlags = ['--headless', '--no-sandbox', '--disable-gpu', '--use-angle=swiftshader',
  '--enable-unsafe-swiftshader', '--disable-background-networking', '--disable-component-update', '--no-first-run'];

class TestFailure extends Error {}

function usage(message) {
  console.error(`viewer_e2e: ${message}\nusage: viewer_e2e.mjs --bin-dir DIR --web-root DIR --dds-config FILE --domain N --screenshot FILE [--port P] [--frames 60]`);
  process.exit(2);
}

function readOptions() {
  let values;
  try {
    ({ values } = parseArgs({
      options: Object.fromEntries(['bin-dir', 'web-root', 'dds-config', 'domain', 'port', 'screenshot', 'frames']
        .map((name) => [name, { type: 'string' }])),
    }));
  } catch (error) {
    usage(error.message);
  }
  for (const name of ['bin-dir', 'web-root', 'dds-config', 'domain', 'screenshot']) {
    if (!values[name]) usage(`--${name} is required`);
  }
  const integer = (name, fallback) => {
    const n = Number(values[name] ?? fallback);
    if (!Number.isInteger(n) || n < 0) usage(`--${name} must be a non-negative integer, got "${values[name]}"`);
    return n;
  };
  return {
    binDir: path.resolve(values['bin-dir']),
    webRoot: path.resolve(values['web-root']),
    ddsConfig: path.resolve(values['dds-config']),
    domain: integer('domain'),
    port: integer('port', 0),
    screenshot: path.resolve(values.screenshot),
    frames: integer('frames', 60),
  };
}

// A child process whose output is kept (last lines shown on failure) and whose exit is awaitable.
function start(name, command, args, env) {
  const child = spawn(command, args, { env: { ...process.env, ...env }, stdio: ['ignore', 'pipe', 'pipe'] });
  const proc = { name, child, output: [], exit: null };
  const keep = (chunk) => {
    proc.output.push(...chunk.toString().split('\n').filter(Boolean));
    proc.output.splice(0, Math.max(0, proc.output.length - 40));
  };
  child.stdout.on('data', keep);
  child.stderr.on('data', keep);
  proc.exited = new Promise((resolve) => {
    child.on('error', (error) => {
      proc.exit = { code: null, error: error.message };
      resolve(proc.exit);
    });
    child.on('exit', (code, signal) => {
      proc.exit = { code, signal };
      resolve(proc.exit);
    });
  });
  console.log(`started ${name}: ${command} ${args.join(' ')}`);
  return proc;
}

// Fails unless `proc` is still running, or (with `mayExit`) has exited with code 0.
function expectRunningOrSuccess(proc, { mayExit = false } = {}) {
  if (!proc.exit || (mayExit && proc.exit.code === 0)) return;
  const { code, signal, error } = proc.exit;
  const how = error ? `failed to start (${error})` : signal ? `was killed by ${signal}` : `exited with code ${code}`;
  throw new TestFailure(`expected ${proc.name} to ${mayExit ? 'exit with code 0' : 'keep running'}, but it ${how}`);
}

async function stop(proc) {
  if (!proc || proc.exit) return;
  proc.child.kill('SIGTERM');
  const killed = setTimeout(() => proc.child.kill('SIGKILL'), 5000);
  await proc.exited;
  clearTimeout(killed);
}

const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

/**
 * Polls `probe` (returning {ok, seen}) every `intervalMs` until ok; on timeout fails with
 * "expected <what> within N s; last seen <seen>". `check` runs before each poll and throws to
 * fail early (a process died, the page reported an error).
 */
async function waitUntil(what, timeoutMs, intervalMs, probe, check) {
  const deadline = Date.now() + timeoutMs;
  let seen = 'nothing yet';
  for (;;) {
    check();
    const result = await probe();
    if (result.ok) return result;
    seen = result.seen;
    if (Date.now() >= deadline) throw new TestFailure(`expected ${what} within ${timeoutMs / 1000} s; last seen ${seen}`);
    await sleep(intervalMs);
  }
}

async function loadChromium() {
  // Relative to this script, so any clone works once `npm ci` has run in web/.
  const modulePath = new URL('../../web/node_modules/playwright-core/index.mjs', import.meta.url);
  try {
    return (await import(modulePath.href)).chromium;
  } catch (error) {
    throw new TestFailure(`expected playwright-core at ${modulePath.pathname} (run "npm ci" in web/), but importing it failed: ${error.message}`);
  }
}

// A port nothing listens on now (the kernel's choice), so that runs side by side never meet.
function freePort() {
  return new Promise((resolve, reject) => {
    const probe = net.createServer();
    probe.once('error', reject);
    probe.listen(0, '127.0.0.1', () => {
      const { port } = probe.address();
      probe.close(() => resolve(port));
    });
  });
}

async function run(options, resources, progress) {
  const { binDir, webRoot, ddsConfig, domain, frames } = options;
  const port = options.port || (await freePort());
  const ddsEnv = { CYCLONEDDS_URI: pathToFileURL(ddsConfig).href };
  const base = `http://127.0.0.1:${port}`;
  const ddsArgs = ['--dds-config', ddsConfig, '--domain', String(domain)];

  progress.step = 'importing the campus map';
  resources.store = await mkdtemp(path.join(tmpdir(), 'stereomap-e2e-store-'));
  const withCampus = existsSync(kCampusMap);
  if (withCampus) {
    const importer = start('stereomap-store import', path.join(binDir, 'stereomap-store'),
      ['--store', resources.store, 'import', kCampusMap, '--session', 'campus'], {});
    const { code } = await importer.exited;
    if (code !== 0) throw new TestFailure(`expected stereomap-store import to exit 0, seen ${code}: ${importer.output.join(' | ')}`);
  } else {
    console.log(`skipping the campus part: ${kCampusMap} is absent`);
  }

  progress.step = 'starting the server';
  const startServer = () => {
    const proc = start('stereomap-server', path.join(binDir, 'stereomap-server'),
      ['--http', `127.0.0.1:${port}`, '--store', resources.store, ...ddsArgs, '--web-root', webRoot], ddsEnv);
    resources.procs.push(proc);
    return proc;
  };
  let server = startServer();
  const serverAlive = () => expectRunningOrSuccess(server);
  const get = async (urlPath) => {
    try {
      const response = await fetch(`${base}${urlPath}`, { signal: AbortSignal.timeout(2000) });
      return { status: response.status, body: await response.text() };
    } catch (error) {
      return { status: null, body: error.cause?.code ?? error.message };
    }
  };
  const healthy = () => waitUntil(`GET /healthz to answer 200`, kHealthTimeoutMs, 200, async () => {
    const { status, body } = await get('/healthz');
    return { ok: status === 200, seen: status === null ? `no answer (${body})` : `status ${status}` };
  }, serverAlive);
  await healthy();

  progress.step = 'opening the viewer in chromium';
  const chromium = await loadChromium();
  resources.browser = await chromium.launch({ executablePath: '/usr/bin/chromium', args: kChromiumFlags });
  const page = await resources.browser.newPage({ viewport: { width: 1280, height: 800 } });
  const pageErrors = [];
  let serverDown = false; // while the server restarts, the browser's own "connection failed" is expected
  page.on('pageerror', (error) => pageErrors.push(`uncaught: ${error.message}`));
  page.on('console', (message) => {
    if (message.type() !== 'error') return;
    if (serverDown && /WebSocket connection to .* failed/.test(message.text())) return;
    pageErrors.push(`console.error: ${message.text()}`);
  });
  const noPageErrors = () => {
    if (pageErrors.length) throw new TestFailure(`expected no page errors, seen ${pageErrors.length}:\n  ${pageErrors.join('\n  ')}`);
  };
  const pageHealthy = () => {
    serverAlive();
    noPageErrors();
  };
  // Every tile at the finest level, so that the page's count is the server's exactly.
  const response = await page.goto(`${base}/?error=0.25&budget=20000000`);
  if (response?.status() !== 200) throw new TestFailure(`expected GET / to answer 200, seen ${response?.status()}`);
  const hook = () => page.evaluate(() => {
    const s = window.__stereomap;
    return s ? { connected: s.connected, session: s.session, voxels: s.renderedVoxels(), poses: s.trajectoryLength(), frames: s.frames() } : null;
  });
  const shown = (h) => (h ? JSON.stringify(h) : 'no window.__stereomap');

  progress.step = 'running the onboard pipeline';
  const onboard = start('stereomap-onboard', path.join(binDir, 'stereomap-onboard'),
    // Every cloud (--min-new 0, no link budget), thinned to the server's 0.1 m voxels: the page
    // must show each.
    ['--source', 'sim', '--frames', String(frames), '--rate', '10', '--session', 'e2e', '--vehicle', 'sim-1',
      '--min-new', '0', '--link-budget', 'off', '--spool', 'memory', '--skip-late', 'off', ...ddsArgs], ddsEnv);
  resources.procs.push(onboard);
  const onboardHealthy = () => {
    pageHealthy();
    expectRunningOrSuccess(onboard, { mayExit: true });
  };

  const first = await waitUntil('the page to render voxels (renderedVoxels() > 0)', kFirstVoxelsTimeoutMs, 250, async () => {
    const h = await hook();
    return { ok: h !== null && h.voxels > 0, seen: shown(h), h };
  }, onboardHealthy);
  const firstPoses = first.h.poses;
  console.log(`first voxels on the page: ${first.h.voxels} voxels, trajectory ${firstPoses} poses, session ${first.h.session}`);

  progress.step = 'reading the live rates on the status line';
  // The vehicle sends at --rate 10: each rate is above 0 and, smoothed over spans of at least
  // 1 s, not far above 10 even when DDS delivers in bursts.
  const ratesPattern = /(\d+\.\d) poses\/s · (\d+\.\d) clouds\/s · link ([\d.,]+) kB\/s · viewer ([\d.,]+) kB\/s/;
  const rates = await waitUntil('the status line to show "N poses/s · N clouds/s · link N kB/s · viewer N kB/s" while the vehicle flies',
    (frames / 10) * 1000 + 60_000, 250, async () => {
      const text = await page.textContent('#status');
      const [poses, clouds, link, viewer] = (ratesPattern.exec(text) ?? []).slice(1).map((v) => Number(v.replace(/,/g, '')));
      if (poses === undefined && onboard.exit !== null) throw new TestFailure(`expected the live rates on the status line before the flight ended, seen "${text}"`);
      return { ok: poses > 0 && clouds > 0 && link > 0 && viewer > 0, seen: `"${text}"`, text, poses, clouds };
    }, onboardHealthy);
  console.log(`status line while flying: ${rates.text}`);
  // The vehicle's own counters (VehicleStatus, once a second): its spool at least.
  progress.step = 'reading the vehicle\'s counters';
  const counters = await waitUntil('the vehicles line to show "<vehicle>: spool N samples"', 10_000, 250, async () => {
    const text = (await page.textContent('#vehicles')) ?? '';
    const hidden = await page.locator('#vehicles').isHidden();
    return { ok: !hidden && /^[\w.-]+: spool [\d,]+ samples?/.test(text), seen: `"${text}" (hidden ${hidden})`, text };
  }, onboardHealthy);
  console.log(`vehicles line while flying: ${counters.text}`);
  const liveShot = options.screenshot.replace(/\.png$/, '') + '_live.png';
  await mkdir(path.dirname(liveShot), { recursive: true });
  await page.screenshot({ path: liveShot });
  console.log(`screenshot: ${liveShot}`);
  if (!(rates.poses <= 15 && rates.clouds <= 15)) throw new TestFailure(`expected at most 15 poses/s and clouds/s from a vehicle at --rate 10, seen "${rates.text}"`);

  progress.step = 'waiting for stereomap-onboard to finish';
  // At --rate 10 the frames take frames / 10 s; the rest is start-up and DDS discovery.
  await waitUntil('stereomap-onboard to exit', (frames / 10) * 1000 + 60_000, 250,
    async () => ({ ok: onboard.exit !== null, seen: 'it still running' }), onboardHealthy);

  progress.step = 'waiting for the server to fuse every frame';
  let previousVoxels = null;
  let stable = 0;
  const settled = await waitUntil(`session "e2e" in GET /api/sessions with frames = ${frames} and occupied_voxels unchanged over ${kStablePolls} polls`,
    kServerSettleTimeoutMs, 500, async () => {
      const { status, body } = await get('/api/sessions');
      if (status !== 200) return { ok: false, seen: `GET /api/sessions status ${status}: ${body.slice(0, 200)}` };
      let session;
      try {
        session = JSON.parse(body).find((s) => s.id === 'e2e');
      } catch (error) {
        return { ok: false, seen: `GET /api/sessions body that is not JSON (${error.message}): ${body.slice(0, 200)}` };
      }
      if (!session) return { ok: false, seen: `no session "e2e" in ${body.slice(0, 200)}` };
      stable = session.occupied_voxels === previousVoxels ? stable + 1 : 1;
      previousVoxels = session.occupied_voxels;
      return { ok: session.frames === frames && stable >= kStablePolls, seen: `${JSON.stringify(session)} (unchanged over ${stable} polls)`, session };
    }, pageHealthy);
  const serverSession = settled.session;

  progress.step = 'waiting for the page to catch up';
  // The trajectory is part of the wait: frames() is the received status while the voxels and
  // the line are what was drawn, so one animation frame may separate them.
  const expected = { session: 'e2e', voxels: serverSession.occupied_voxels, frames, poses: serverSession.poses };
  const last = await waitUntil(`the page to show ${JSON.stringify(expected)} (renderedVoxels() = server occupied_voxels, ` +
    `frames() = --frames, trajectoryLength() = server poses)`, kPageCatchUpTimeoutMs, 250, async () => {
    const h = await hook();
    return { ok: h !== null && Object.keys(expected).every((k) => h[k] === expected[k]), seen: shown(h), h };
  }, pageHealthy);
  console.log(`server: ${serverSession.occupied_voxels} voxels, ${serverSession.frames} frames, ${serverSession.poses} poses; ` +
    `page: ${last.h.voxels} voxels, ${last.h.frames} frames, trajectory ${firstPoses} poses at first voxels and ${last.h.poses} at the end`);
  if (!(last.h.poses > firstPoses)) throw new TestFailure(`expected the trajectory to grow after the first voxels (> ${firstPoses} poses), seen ${last.h.poses}`);
  if (!last.h.connected) throw new TestFailure('expected the page to be connected at the end, seen connected = false');

  progress.step = 'saving the screenshot';
  await page.waitForTimeout(300); // let the status line refresh its age before the picture
  await mkdir(path.dirname(options.screenshot), { recursive: true });
  const png = await page.screenshot({ path: options.screenshot });
  console.log(`screenshot: ${options.screenshot}`);
  const coloured = await colouredFraction(page, png);
  console.log(`coloured pixels outside the overlays: ${(100 * coloured).toFixed(2)} % of the view`);
  if (coloured < kMinColouredFraction) {
    throw new TestFailure(`expected at least ${100 * kMinColouredFraction} % of the view in the voxels' colours, seen ${(100 * coloured).toFixed(2)} %`);
  }
  pageHealthy();

  progress.step = 'replaying the flight to its middle with the time slider';
  const range = await page.evaluate(() => window.__stereomap.timeRange());
  if (!range) throw new TestFailure('expected the time slider to span the e2e flight, seen no time range');
  const tum = (await get('/api/sessions/e2e/trajectory.tum')).body.trim().split('\n').map((line) => Number(line.split(' ')[0]));
  // Halfway between two poses in the middle of the flight, so that no pose sits on the edge.
  const half = Math.floor(tum.length / 2);
  const middle = (tum[half - 1] + tum[half]) / 2;
  await page.evaluate((t) => {
    const slider = document.getElementById('time-slider');
    slider.value = String(t);
    slider.dispatchEvent(new Event('input', { bubbles: true }));
  }, middle);
  const replayed = await waitUntil(`the page to show the flight as it was at ${middle.toFixed(1)} s (fewer voxels, the poses up to then)`,
    kPageCatchUpTimeoutMs, 250, async () => {
      const h = await hook();
      const until = await page.evaluate(() => window.__stereomap.replayUntil());
      if (until === null || Math.abs(until - middle) > 0.001) return { ok: false, seen: `replay at ${until}; ${shown(h)}` };
      const posesThen = half;
      return { ok: h.poses === posesThen && h.voxels > 0 && h.voxels < expected.voxels,
        seen: `replay at ${until}: ${shown(h)}, expected ${posesThen} poses and 0 < voxels < ${expected.voxels}`, h };
    }, pageHealthy);
  console.log(`replay at the middle of the flight: ${replayed.h.voxels} voxels, ${replayed.h.poses} poses`);
  const replayShot = options.screenshot.replace(/\.png$/, '') + '_replay.png';
  await page.screenshot({ path: replayShot });
  console.log(`screenshot: ${replayShot}`);
  await page.click('#live-button');
  await waitUntil(`the page to show the whole flight again after "now" (${JSON.stringify(expected)})`, kPageCatchUpTimeoutMs, 250, async () => {
    const h = await hook();
    const until = await page.evaluate(() => window.__stereomap.replayUntil());
    return { ok: until === null && Object.keys(expected).every((k) => h[k] === expected[k]), seen: `replay ${until}; ${shown(h)}` };
  }, pageHealthy);

  progress.step = 'measuring a distance with two clicks';
  await page.keyboard.press('m');
  const box = await page.locator('#view canvas').boundingBox();
  for (const [fx, fy] of [[0.45, 0.55], [0.62, 0.5]]) {
    await page.mouse.click(box.x + fx * box.width, box.y + fy * box.height);
    await page.waitForTimeout(200);
  }
  const measured = await page.locator('#measure-result').textContent();
  const metres = Number(/distance (\d+\.\d+) m/.exec(measured)?.[1]);
  if (!(metres > 0.1 && metres < 30)) throw new TestFailure(`expected "distance N m" between two voxels of the room after two clicks, seen "${measured}"`);
  console.log(`measured: ${measured}`);
  await page.keyboard.press('Escape');

  // Every tile the page holds has, at its level, exactly the cells the server's index lists,
  // and every tile of the map is held at some level.
  const tilesMatch = async (onPage, id) => {
    const { status, body } = await get(`/api/sessions/${id}/tiles`);
    if (status !== 200) return { ok: false, seen: `GET /api/sessions/${id}/tiles status ${status}` };
    const index = JSON.parse(body);
    const cells = new Map(index.tiles.map((t) => [`${t.level}/${t.key}`, t.voxels]));
    const keys = new Set(index.tiles.filter((t) => t.level === 0).map((t) => t.key));
    const held = await onPage.evaluate(() => ({ session: window.__stereomap.session, tiles: window.__stereomap.tiles(), link: window.__stereomap.link() }));
    if (held.session !== id) return { ok: false, seen: `session ${held.session}` };
    const wrong = held.tiles.filter((t) => cells.get(`${t.level}/${t.key}`) !== t.cells);
    const missing = [...keys].filter((k) => !held.tiles.some((t) => t.key === k));
    const levels = {};
    for (const t of held.tiles) levels[t.level] = (levels[t.level] ?? 0) + t.cells;
    return {
      ok: wrong.length === 0 && missing.length === 0 && held.tiles.length === keys.size,
      seen: `${held.tiles.length} of ${keys.size} tiles held, cells per level ${JSON.stringify(levels)}, ` +
        `${wrong.length} differ from the server, ${missing.length} missing; link ${JSON.stringify(held.link)}`,
      levels,
    };
  };

  if (withCampus) {
    progress.step = 'opening the imported campus map in a second page';
    const opened = await fetch(`${base}/api/sessions/campus/open`, { method: 'POST' });
    if (opened.status !== 200) throw new TestFailure(`expected POST /api/sessions/campus/open to answer 200, seen ${opened.status}`);
    const campusPage = await resources.browser.newPage({ viewport: { width: 1280, height: 800 } });
    campusPage.on('pageerror', (error) => pageErrors.push(`campus page uncaught: ${error.message}`));
    campusPage.on('console', (message) => {
      if (message.type() === 'error') pageErrors.push(`campus page console.error: ${message.text()}`);
      else if (message.type() === 'warning') console.log(`campus page warns: ${message.text()}`);
    });
    // A budget that software rendering (SwiftShader) draws in good time; still several levels.
    await campusPage.goto(`${base}/?session=campus&budget=100000`);
    const campus = await waitUntil('the campus page to hold every tile at the level the server chose, cells equal to the index',
      kCampusTimeoutMs, 1000, () => tilesMatch(campusPage, 'campus'), pageHealthy);
    console.log(`campus page: ${campus.seen}`);
    if (Object.keys(campus.levels).length < 2) throw new TestFailure(`expected the campus at several levels of detail, seen ${JSON.stringify(campus.levels)}`);
    await campusPage.waitForTimeout(500);
    const campusShot = options.screenshot.replace(/\.png$/, '') + '_campus.png';
    // Software rendering draws the 100k campus cells (and the first page's map) one frame in
    // seconds, many more while other tests load both cores: a CI run saw 30 s pass.
    await campusPage.screenshot({ path: campusShot, timeout: 120000 });
    console.log(`screenshot: ${campusShot}`);

    progress.step = 'switching the campus page to the live session and back';
    await campusPage.selectOption('#session-select', 'e2e');
    await waitUntil('the campus page to show session e2e', kPageCatchUpTimeoutMs, 250, () => tilesMatch(campusPage, 'e2e'), pageHealthy);
    await campusPage.selectOption('#session-select', 'campus');
    await waitUntil('the campus page to show the campus again', kCampusTimeoutMs, 1000, () => tilesMatch(campusPage, 'campus'), pageHealthy);
    await campusPage.close();
  }

  progress.step = 'restarting the server under the open page';
  serverDown = true;
  await stop(server);
  await waitUntil('the page to notice the server is gone', 10_000, 100, async () => {
    const h = await hook();
    return { ok: h !== null && !h.connected, seen: shown(h) };
  }, noPageErrors);
  server = startServer();
  await healthy();
  const back = await waitUntil('the page to reconnect by itself and hold the e2e map again', kPageCatchUpTimeoutMs, 250,
    async () => {
      const h = await hook();
      if (!h?.connected) return { ok: false, seen: shown(h) };
      return tilesMatch(page, 'e2e');
    }, pageHealthy);
  console.log(`after the restart: ${back.seen}`);
  serverDown = false;
  pageHealthy();

  // Last: the main page follows the newest session, and the deck's is one.
  progress.step = 'a descent onto the moving deck with the landing watch on';
  const deck = start('stereomap-onboard (deck)', path.join(binDir, 'stereomap-onboard'),
    ['--source', 'sim:deck', '--landing', 'default', '--frames', '10', '--rate', '0', '--session', 'deck',
      '--vehicle', 'uav-1', '--spool', 'memory', ...ddsArgs], ddsEnv);
  resources.procs.push(deck);
  await waitUntil('the deck descent to finish', 120_000, 250,
    async () => ({ ok: deck.exit !== null, seen: 'it still running' }), () => expectRunningOrSuccess(deck, { mayExit: true }));
  const deckPage = await resources.browser.newPage({ viewport: { width: 1280, height: 800 } });
  deckPage.on('pageerror', (error) => pageErrors.push(`deck page uncaught: ${error.message}`));
  await deckPage.goto(`${base}/?session=deck`);
  const padSeen = await waitUntil('the deck page to outline the pad and say where it is', kPageCatchUpTimeoutMs, 250, async () => {
    const pads = await deckPage.evaluate(() => window.__stereomap?.landingPads() ?? 0);
    const status = await deckPage.textContent('#status');
    return { ok: pads === 1 && /pad \d+\.\d m at [+-]?\d+° \(uav-1\)/.test(status), seen: `${pads} pads, status "${status}"` };
  }, pageHealthy);
  console.log(`deck page: ${padSeen.seen}`);
  const deckShot = options.screenshot.replace(/\.png$/, '') + '_landing.png';
  await deckPage.screenshot({ path: deckShot, timeout: 120000 });
  console.log(`screenshot: ${deckShot}`);
  await deckPage.close();
}

// Fraction of the screenshot's pixels, outside the overlay panels, that are clearly coloured
// (channels differ by more than 60 of 255). Decoded in the page, which has a PNG decoder.
function colouredFraction(page, png) {
  return page.evaluate(async (base64) => {
    const bitmap = await createImageBitmap(await (await fetch(`data:image/png;base64,${base64}`)).blob());
    const context = new OffscreenCanvas(bitmap.width, bitmap.height).getContext('2d');
    context.drawImage(bitmap, 0, 0);
    const { data } = context.getImageData(0, 0, bitmap.width, bitmap.height);
    const panels = [...document.querySelectorAll('.panel')].map((panel) => panel.getBoundingClientRect());
    let coloured = 0;
    for (let y = 0; y < bitmap.height; y += 1) {
      for (let x = 0; x < bitmap.width; x += 1) {
        if (panels.some((r) => x >= r.left && x < r.right && y >= r.top && y < r.bottom)) continue;
        const i = (y * bitmap.width + x) * 4;
        if (Math.max(data[i], data[i + 1], data[i + 2]) - Math.min(data[i], data[i + 1], data[i + 2]) > 60) coloured += 1;
      }
    }
    return coloured / (bitmap.width * bitmap.height);
  }, png.toString('base64'));
}

async function main() {
  const options = readOptions();
  const resources = { procs: [], browser: null, store: null };
  const progress = { step: 'starting' };
  let passed = false;
  let timer;
  try {
    const timeout = new Promise((_, reject) => {
      timer = setTimeout(() => reject(new TestFailure(`expected the test to finish within ${kOverallTimeoutMs / 1000} s; it was still ${progress.step}`)), kOverallTimeoutMs);
    });
    await Promise.race([run(options, resources, progress), timeout]);
    passed = true;
  } catch (error) {
    console.error(`FAILED while ${progress.step}: ${error instanceof TestFailure ? error.message : error.stack}`);
    for (const proc of resources.procs) console.error(`--- ${proc.name}, last output:\n  ${proc.output.join('\n  ') || '(none)'}`);
  } finally {
    clearTimeout(timer);
    await resources.browser?.close().catch((error) => console.error(`closing chromium: ${error.message}`));
    await Promise.all(resources.procs.reverse().map(stop));
    if (resources.store) await rm(resources.store, { recursive: true, force: true });
  }
  console.log(passed ? '1 passed, 0 failed' : '0 passed, 1 failed');
  process.exit(passed ? 0 : 1);
}

main();
