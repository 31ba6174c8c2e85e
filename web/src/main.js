// The stereomap viewer page: connects to the server's /ws, keeps every session's state, and
// draws the chosen one (by default the session heard from most recently) at most once per
// animation frame. Exposes window.__stereomap for the end-to-end test.

import { rampCssGradient } from './core/colour_ramp.js';
import { statusText } from './core/format.js';
import { MapStore } from './core/map_state.js';
import { ProtocolError, parseMessage } from './core/protocol.js';
import { MapView } from './three/map_view.js';

const kRetryFirstMs = 500; // reconnect backoff doubles from here ...
const kRetryMaxMs = 10_000; // ... up to this
const kStatusRefreshMs = 500;

const elements = Object.fromEntries(['view', 'status', 'session-select', 'fit-button', 'legend', 'legend-bar',
  'legend-max', 'legend-min'].map((id) => [id, document.getElementById(id)]));

const store = new MapStore();
const link = { connected: false, failures: 0, retryAtMs: null };
let pinnedSessionId = new URLSearchParams(location.search).get('session'); // null: follow the latest
let dataChanged = false; // messages arrived since the view was last synchronised

const view = new MapView(elements.view, syncView);

function displayedSessionId() {
  return pinnedSessionId ?? store.latestSessionId;
}

function displayedSession() {
  return store.sessions.get(displayedSessionId()) ?? null;
}

// Runs right before a frame is drawn, so a burst of messages costs one update.
function syncView() {
  if (!dataChanged) return;
  dataChanged = false;
  const session = displayedSession();
  view.show(session);
  updateLegend();
  updateSessionList();
  updateStatus();
}

function updateStatus() {
  const id = displayedSessionId();
  const session = displayedSession();
  const retryInSeconds = link.retryAtMs === null ? 0 : (link.retryAtMs - Date.now()) / 1000;
  elements.status.textContent = statusText({ connected: link.connected, retryInSeconds }, id === null ? null : {
    id,
    known: session !== null,
    vehicle: session?.vehicle ?? '',
    renderedVoxels: view.renderedVoxels,
    frames: session?.frames ?? 0,
    ageSeconds: session?.lastMessageMs ? (Date.now() - session.lastMessageMs) / 1000 : null,
  });
  elements.status.classList.toggle('offline', !link.connected);
}

function updateLegend() {
  const range = view.heightRange;
  elements.legend.hidden = range === null;
  if (range) {
    elements['legend-min'].textContent = `${range[0].toFixed(1)} m`;
    elements['legend-max'].textContent = `${range[1].toFixed(1)} m`;
  }
}

let shownSessionList = '';
function updateSessionList() {
  const ids = [...store.sessions.keys()];
  if (pinnedSessionId !== null && !ids.includes(pinnedSessionId)) ids.push(pinnedSessionId);
  const latest = store.latestSessionId;
  const listed = JSON.stringify([ids, latest, pinnedSessionId, ids.map((id) => store.sessions.get(id)?.vehicle)]);
  if (listed === shownSessionList) return;
  shownSessionList = listed;
  const option = (value, text) => Object.assign(document.createElement('option'), { value, textContent: text });
  elements['session-select'].replaceChildren(
    option('', latest === null ? 'follow latest' : `follow latest (${latest})`),
    ...ids.map((id) => {
      const vehicle = store.sessions.get(id)?.vehicle;
      return option(id, vehicle ? `${id} (${vehicle})` : id);
    }),
  );
  elements['session-select'].value = pinnedSessionId ?? '';
}

function receive(text) {
  try {
    const message = parseMessage(text);
    if (message.type === 'error') console.warn(`stereomap server: ${message.message}`);
    store.apply(message);
  } catch (error) {
    if (!(error instanceof ProtocolError)) throw error;
    console.error(`stereomap: ignored a server message: ${error.message}`);
  }
  dataChanged = true;
  view.requestRender();
}

function connect() {
  const scheme = location.protocol === 'https:' ? 'wss' : 'ws';
  // A server bound beyond loopback wants its token: pass on the page's ?token=.
  const token = new URLSearchParams(location.search).get('token');
  const query = token ? `?token=${encodeURIComponent(token)}` : '';
  const socket = new WebSocket(`${scheme}://${location.host}/ws${query}`);
  socket.onopen = () => {
    Object.assign(link, { connected: true, failures: 0, retryAtMs: null });
    updateStatus();
  };
  socket.onmessage = (event) => receive(event.data);
  // Also called when connecting failed; the error event carries nothing more useful.
  socket.onclose = () => {
    const delayMs = Math.min(kRetryMaxMs, kRetryFirstMs * 2 ** link.failures);
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
  dataChanged = true;
  view.requestRender();
});
elements['fit-button'].addEventListener('click', () => view.fit());
window.addEventListener('keydown', (event) => {
  const typing = event.target instanceof HTMLInputElement || event.target instanceof HTMLSelectElement;
  if (event.key.toLowerCase() === 'f' && !typing && !event.ctrlKey && !event.metaKey && !event.altKey) view.fit();
});

elements['legend-bar'].style.background = rampCssGradient();
window.__stereomap = {
  get connected() {
    return link.connected;
  },
  get session() {
    return displayedSessionId();
  },
  renderedVoxels: () => view.renderedVoxels,
  trajectoryLength: () => view.trajectoryLength,
  frames: () => displayedSession()?.frames ?? 0,
};
updateSessionList();
updateStatus();
setInterval(updateStatus, kStatusRefreshMs);
connect();
