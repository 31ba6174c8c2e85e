// The stereomap viewer page: speaks protocol 2 on the server's /ws (docs/PROTOCOL.md). It
// lists the sessions, subscribes to the chosen one (by default the live session heard from
// most recently), tells the server where the camera is (the server then sends the tiles that
// matter most, coarse first) and draws at most once per animation frame. Exposes
// window.__stereomap for the end-to-end test.

import { changeCssGradient, rampCssGradient } from './core/colour_ramp.js';
import { originLines, ratesText, statusText, vehicleLines } from './core/format.js';
import { landingText, padOutline } from './core/landing.js';
import { MapStore, tileKeyText } from './core/map_state.js';
import { ProtocolError, dropMessage, helloMessage, parseMessage, replayMessage, subscribeMessage, viewMessage } from './core/protocol.js';
import { RateMeter } from './core/rate_meter.js';
import { TileFormatError, decodeTile } from './core/tile_codec.js';
import { MapView } from './three/map_view.js';

const kRetryFirstMs = 500; // reconnect backoff doubles from here ...
const kRetryMaxMs = 10_000; // ... up to this
const kStatusRefreshMs = 500;
const kViewEveryMs = 250; // camera moves are reported at most this often
const kReplayAfterMs = 300; // the slider asks for a replay once it rests this long

const params = new URLSearchParams(location.search);
const kBudget = Number(params.get('budget')) || 1_000_000; // cells drawn at most
const kErrorPx = Number(params.get('error')) || 2; // how large a cell may look before a finer level is due
const kCacheBytes = (Number(params.get('cache')) || 256) * 2 ** 20; // the page's memory for tiles

const elements = Object.fromEntries(['view', 'status', 'vehicles', 'session-select', 'fit-button', 'colour-select', 'legend',
  'legend-bar', 'legend-max', 'legend-mid', 'legend-min', 'legend-title', 'follow-check', 'measure-button', 'measure-result',
  'timeline', 'time-slider', 'time-label', 'live-button']
  .map((id) => [id, document.getElementById(id)]));

const store = new MapStore(kCacheBytes);
// `bytes`: what this page's connections received, in all.
const link = { socket: null, connected: false, failures: 0, retryAtMs: null, bytes: 0,
  received: 0, applied: 0, lastMessageMs: null, routedFor: null };
// Rates for the status line: the live session's (`sessionId`) poses and clouds taken and its
// vehicles' link bytes, from its statuses' counts; this page's connection from link.bytes.
const meters = { sessionId: null, poses: new RateMeter(), clouds: new RateMeter(), linkBytes: new RateMeter(),
  viewerBytes: new RateMeter() };
let pinnedSessionId = params.get('session'); // null: follow the latest
let dataChanged = false; // messages arrived since the view was last synchronised
let viewId = 0;
let viewTimer = null;
let subscribeError = '';
let replayTimer = null;
let pendingReplay = null; // the time the slider was moved to, until its replay arrives

const view = new MapView(elements.view, syncView, scheduleView);

function displayedSessionId() {
  return pinnedSessionId ?? store.latestSessionId;
}

function send(text) {
  if (link.connected) link.socket.send(text);
}

// Subscribes to the session to show when it is not the one subscribed to. In a cluster
// (behind its proxy) a session another server serves (its status names that `server`) needs
// a connection routed there: /ws?session=ID reaches its owner, so the page connects again.
function followChoice(again = false) {
  const id = displayedSessionId();
  if (!link.connected || id === null || (store.subscribed?.id === id && !again)) return;
  if (store.statuses.get(id)?.server && link.routedFor !== id) {
    link.failures = 0;
    link.socket.close();
    return;
  }
  subscribeError = '';
  store.subscribe(id);
  send(subscribeMessage(id));
  dataChanged = true;
  view.requestRender();
}

function sendView() {
  viewTimer = null;
  if (!link.connected || !store.subscribed) return;
  viewId += 1;
  const camera = view.cameraState();
  store.subscribed.tiles.setEye(camera.eye, store.subscribed.resolution ?? 1);
  send(viewMessage({ id: viewId, ...camera, budget: kBudget, error: kErrorPx }));
}

function scheduleView() {
  if (viewTimer === null) viewTimer = setTimeout(sendView, kViewEveryMs);
}

// Runs right before a frame is drawn, so a burst of messages costs one update.
function syncView() {
  if (!dataChanged) return;
  dataChanged = false;
  view.show(store.subscribed);
  updateLegend();
  updateSessionList();
  updateTimeline();
  updateStatus();
}

const formatClock = (seconds) => new Date(seconds * 1000).toISOString().slice(11, 19);

// The slider spans the subscribed session's flight; hidden when it has no poses (an imported map).
function updateTimeline() {
  const session = store.subscribed;
  const range = session?.timeRange ?? null;
  elements.timeline.hidden = range === null;
  if (range === null) return;
  const slider = elements['time-slider'];
  const chosen = pendingReplay ?? session.replayUntil; // the slider's time, or null: now
  Object.assign(slider, { min: range[0], max: range[1] });
  if (pendingReplay === null) slider.value = chosen ?? range[1];
  const shown = Number(slider.value);
  elements['time-label'].textContent = chosen === null
    ? `now (${formatClock(range[1])} UTC)`
    : `${formatClock(shown)} UTC, +${(shown - range[0]).toFixed(1)} s`;
  elements['live-button'].disabled = session.replayUntil === null;
}

// The session shown, when it is live and shown as it is now (not a replay); else null.
function liveSession() {
  const session = store.subscribed;
  const live = session?.id === displayedSessionId() && session.status?.state === 'live' && session.replayUntil === null;
  return live ? session : null;
}

function updateStatus() {
  const id = displayedSessionId();
  const session = store.subscribed?.id === id ? store.subscribed : null;
  const retryInSeconds = link.retryAtMs === null ? 0 : (link.retryAtMs - Date.now()) / 1000;
  let text = statusText({ connected: link.connected, retryInSeconds }, id === null ? null : {
    id,
    known: store.statuses.has(id),
    vehicle: session?.vehicle ?? '',
    renderedVoxels: view.renderedVoxels,
    serverVoxels: session?.serverVoxels ?? 0,
    frames: session?.frames ?? 0,
    ageSeconds: session?.lastMessageMs ? (Date.now() - session.lastMessageMs) / 1000 : null,
    corrections: session?.status?.corrections ?? 0,
    refusing: session?.status?.refusing ?? false,
    isDiff: Boolean(session?.status?.origin?.diff),
  });
  const live = liveSession() !== null;
  const rates = ratesText({
    poses: live ? meters.poses.perSecond : null,
    clouds: live ? meters.clouds.perSecond : null,
    linkBytes: live ? meters.linkBytes.perSecond : null,
    viewerBytes: link.connected ? meters.viewerBytes.perSecond : null,
  });
  if (rates) text += ` · ${rates}`;
  // Lag: from the server's change of the map to its tiles here (the same clock only on one host).
  if (live && store.lastLatency !== null) text += ` · lag ${Math.max(0, store.lastLatency).toFixed(0)} ms`;
  if (session?.replayUntil != null) text += ` · replay at ${formatClock(session.replayUntil)} UTC`;
  if (subscribeError) text += ` · ${subscribeError}`;
  const pad = landing.sessionId === id ? landingText(landing.vehicles) : null;
  if (pad) text += ` · ${pad}`;
  elements.status.textContent = text;
  elements.status.classList.toggle('offline', !link.connected);
  const vehicles = [...originLines(session?.status?.origin),
    ...vehicleLines(session?.status?.vehicleStatus, session?.status?.vehicleFrames)];
  elements.vehicles.textContent = vehicles.join('\n');
  elements.vehicles.hidden = vehicles.length === 0;
}

function updateLegend() {
  const range = view.heightRange;
  const mode = view.tiles.colourBy;
  elements.legend.hidden = mode === 'height' && range === null;
  elements['legend-title'].textContent = { probability: 'occupancy P', change: 'change' }[mode] ?? 'height z';
  elements['legend-bar'].style.background = mode === 'change' ? changeCssGradient() : rampCssGradient();
  elements['legend-mid'].textContent = mode === 'change' ? 'disappeared' : '';
  if (mode === 'probability') {
    elements['legend-min'].textContent = '0.5';
    elements['legend-max'].textContent = '1.0';
  } else if (mode === 'change') {
    elements['legend-min'].textContent = 'unchanged';
    elements['legend-max'].textContent = 'appeared';
  } else if (range) {
    elements['legend-min'].textContent = `${range[0].toFixed(1)} m`;
    elements['legend-max'].textContent = `${range[1].toFixed(1)} m`;
  }
}

let shownSessionList = '';
function updateSessionList() {
  const statuses = [...store.statuses.values()];
  const ids = statuses.map((s) => s.id);
  if (pinnedSessionId !== null && !ids.includes(pinnedSessionId)) ids.push(pinnedSessionId);
  const latest = store.latestSessionId;
  const label = (id) => {
    const s = store.statuses.get(id);
    return s ? `${id}${s.vehicle ? ` (${s.vehicle})` : ''} · ${s.state || '?'}` : id;
  };
  const listed = JSON.stringify([ids.map(label), latest, pinnedSessionId]);
  if (listed === shownSessionList) return;
  shownSessionList = listed;
  const option = (value, text) => Object.assign(document.createElement('option'), { value, textContent: text });
  elements['session-select'].replaceChildren(
    option('', latest === null ? 'follow latest' : `follow latest (${latest})`),
    ...ids.map((id) => option(id, label(id))),
  );
  elements['session-select'].value = pinnedSessionId ?? '';
}

function receiveText(text) {
  const message = parseMessage(text);
  if (message.type === 'error') {
    console.warn(`stereomap server: ${message.message}`);
    if (message.session && message.session === store.subscribed?.id) subscribeError = message.message;
  }
  store.apply(message);
  if (message.type === 'replayed' && message.until === pendingReplay && replayTimer === null) pendingReplay = null;
  if (message.type === 'subscribed' && message.session === store.subscribed?.id) {
    if (view.shownId !== message.session) view.fitBounds(message.bounds); // not when coming back from a replay
    sendView();
  }
  followChoice();
}

async function receive(data) {
  link.applied += 1;
  try {
    if (typeof data === 'string') {
      receiveText(data);
    } else {
      store.applyTile(await decodeTile(new Uint8Array(data)));
      const mine = store.subscribed;
      if (mine?.evicted.length > 0) send(dropMessage(mine.id, mine.evicted.splice(0)));
    }
  } catch (error) {
    if (!(error instanceof ProtocolError) && !(error instanceof TileFormatError)) throw error;
    console.error(`stereomap: ignored a server message: ${error.message}`);
  }
  dataChanged = true;
  view.requestRender();
}

function connect() {
  const scheme = location.protocol === 'https:' ? 'wss' : 'ws';
  const token = params.get('token');
  // The session to show travels in the URL: a cluster's proxy routes the connection to the
  // server that serves it (a single server ignores it).
  // A token goes in the URL too (as ?token=): a cluster's proxy must present it to look the
  // session's server up before the hello can.
  const id = displayedSessionId();
  link.routedFor = id;
  const query = new URLSearchParams();
  if (id !== null) query.set('session', id);
  if (token) query.set('token', token);
  const search = query.toString();
  const socket = new WebSocket(`${scheme}://${location.host}/ws${search ? `?${search}` : ''}`);
  socket.binaryType = 'arraybuffer';
  link.socket = socket;
  // Tiles decode asynchronously; one chain keeps every message in the order it came.
  let inbox = Promise.resolve();
  socket.onopen = () => {
    Object.assign(link, { connected: true, failures: 0, retryAtMs: null });
    socket.send(helloMessage(token));
    store.subscribed = null; // a new connection subscribes afresh (the server may have restarted)
    updateStatus();
  };
  socket.onmessage = (event) => {
    link.received += 1;
    link.lastMessageMs = Date.now();
    link.bytes += typeof event.data === 'string' ? event.data.length : event.data.byteLength;
    // A failure nobody foresaw is reported and the chain goes on with the next message.
    inbox = inbox.then(() => receive(event.data)).catch((error) => console.error(`stereomap: ${error.stack ?? error}`));
  };
  // Also called when connecting failed; the error event carries nothing more useful.
  socket.onclose = (event) => {
    if (event.reason) console.warn(`stereomap: the server closed the connection: ${event.reason}`);
    // At once after closing it to reach another server (followChoice), else backing off.
    const delayMs = link.failures === 0 && event.wasClean ? 0 : Math.min(kRetryMaxMs, kRetryFirstMs * 2 ** link.failures);
    Object.assign(link, { connected: false, failures: link.failures + 1, retryAtMs: Date.now() + delayMs });
    setTimeout(connect, delayMs);
    updateStatus();
  };
}

elements['session-select'].addEventListener('change', (event) => {
  pinnedSessionId = event.target.value || null;
  const url = new URL(location.href);
  if (pinnedSessionId === null) url.searchParams.delete('session');
  else url.searchParams.set('session', pinnedSessionId);
  history.replaceState(null, '', url);
  followChoice();
  dataChanged = true;
  view.requestRender();
});
elements['colour-select'].addEventListener('change', (event) => {
  view.tiles.setColourBy(event.target.value);
  dataChanged = true;
  view.requestRender();
});
elements['time-slider'].addEventListener('input', () => {
  clearTimeout(replayTimer);
  pendingReplay = Number(elements['time-slider'].value);
  updateTimeline();
  replayTimer = setTimeout(() => {
    replayTimer = null;
    if (store.subscribed) send(replayMessage(store.subscribed.id, pendingReplay));
  }, kReplayAfterMs);
});
elements['live-button'].addEventListener('click', () => {
  clearTimeout(replayTimer);
  replayTimer = null;
  pendingReplay = null;
  followChoice(true); // subscribing again shows the session as it is now
});

elements['fit-button'].addEventListener('click', () => {
  elements['follow-check'].checked = false;
  view.following = false;
  view.fit();
});
elements['follow-check'].addEventListener('change', (event) => {
  view.following = event.target.checked;
  dataChanged = true;
  view.requestRender();
});

function setMeasuring(on) {
  view.measure.on = on;
  elements['measure-button'].classList.toggle('active', on);
  elements['measure-result'].hidden = !on;
  elements['measure-result'].textContent = on ? 'measure: click a first point on the map' : '';
  if (!on) view.clearMeasure();
}
elements['measure-button'].addEventListener('click', () => setMeasuring(!view.measure.on));
// A click (not a drag of the camera) picks a point while measuring.
let pressedAt = null;
elements.view.addEventListener('pointerdown', (event) => {
  pressedAt = [event.clientX, event.clientY];
});
elements.view.addEventListener('pointerup', (event) => {
  if (!view.measure.on || !pressedAt || Math.hypot(event.clientX - pressedAt[0], event.clientY - pressedAt[1]) > 4) return;
  const point = view.pick(event);
  const out = elements['measure-result'];
  if (!point) {
    out.textContent = 'measure: no map under the pointer; click on a voxel';
    return;
  }
  const distance = view.addMeasurePoint(point);
  const at = `(${point.x.toFixed(2)}, ${point.y.toFixed(2)}, ${point.z.toFixed(2)}) m`;
  out.textContent = distance === null ? `measure: from ${at}; click a second point` : `distance ${distance.toFixed(2)} m (to ${at})`;
});

window.addEventListener('keydown', (event) => {
  const typing = event.target instanceof HTMLInputElement || event.target instanceof HTMLSelectElement;
  if (typing || event.ctrlKey || event.metaKey || event.altKey) return;
  if (event.key.toLowerCase() === 'f') view.fit();
  if (event.key.toLowerCase() === 'm') setMeasuring(!view.measure.on);
  if (event.key === 'Escape') setMeasuring(false);
});

// ?colour=height|probability|change picks the colour mode (a diff session's link says change).
if (['height', 'probability', 'change'].includes(params.get('colour'))) {
  elements['colour-select'].value = params.get('colour');
  view.tiles.setColourBy(params.get('colour'));
}
// What the session's vehicles see of the landing pad (REST, once a second): outlined in the map
// while tracked, and said on the status line.
const landing = { sessionId: null, vehicles: [] };
async function pollLanding() {
  const id = displayedSessionId();
  const live = store.subscribed?.id === id && store.subscribed?.status?.state === 'live';
  // Once for each session shown, then only while it is live; never while the link is down (a
  // fetch that finds no server is a console error, and the link's status says it already).
  if (!link.connected || (id === landing.sessionId && !live)) return;
  let vehicles = [];
  // A closed session has no vehicles, and the server answers its resources with 409 (open it
  // first): a console error for a session merely shown (a store's imported map, say).
  if (id !== null && store.statuses.get(id)?.state !== 'closed') {
    const token = new URLSearchParams(window.location.search).get('token');
    const query = token ? `?token=${encodeURIComponent(token)}` : '';
    try {
      const reply = await fetch(`/api/sessions/${encodeURIComponent(id)}/landing${query}`);
      if (reply.ok) vehicles = (await reply.json()).vehicles ?? [];
    } catch {
      return; // the server went away meanwhile: try again once the link is back
    }
  }
  Object.assign(landing, { sessionId: id, vehicles });
  view.landing.setOutlines(vehicles.filter((v) => v.state === 'TRACKING' && v.has_pose).map((v) => padOutline(v.pad_in_map)));
  view.requestRender();
}
setInterval(pollLanding, 1000);

window.__stereomap = {
  // Landing pads outlined in the map.
  landingPads: () => view.landing.count,
  get connected() {
    return link.connected;
  },
  get session() {
    return displayedSessionId();
  },
  renderedVoxels: () => view.renderedVoxels,
  // The tiles held for the session shown: [{key: "x_y_z", level, cells}].
  tiles: () => (store.subscribed?.id === displayedSessionId() ? [...store.subscribed.tiles.values()] : [])
    .map((t) => ({ key: tileKeyText(t.key), level: t.level, cells: t.codes.length })),
  trajectoryLength: () => view.trajectoryLength,
  // Messages received and taken up (decoded and applied) on this connection's page, and how
  // long ago the last one came: tells a quiet server from a page that fell behind.
  link: () => ({ received: link.received, applied: link.applied, lastMessageAgoMs: link.lastMessageMs && Date.now() - link.lastMessageMs }),
  // The time shown by a replay (seconds), or null for the session as it is.
  replayUntil: () => store.subscribed?.replayUntil ?? null,
  timeRange: () => store.subscribed?.timeRange ?? null,
  frames: () => (store.subscribed?.id === displayedSessionId() ? store.subscribed.frames : 0),
};
// The counts as they stand now go to the rates: the server sends a session's status within
// 25 ms of each live sample, so the last one received holds until another comes.
setInterval(() => {
  const nowMs = performance.now();
  meters.viewerBytes.add(link.bytes, nowMs);
  const live = liveSession();
  if ((live?.id ?? null) !== meters.sessionId) {
    for (const meter of [meters.poses, meters.clouds, meters.linkBytes]) meter.reset();
    meters.sessionId = live?.id ?? null;
  }
  if (live) {
    meters.poses.add(live.status.poses, nowMs);
    meters.clouds.add(live.status.framesReceived, nowMs);
    meters.linkBytes.add(live.status.bytesReceived, nowMs);
  }
  updateStatus();
}, kStatusRefreshMs);
updateSessionList();
updateStatus();
connect();
