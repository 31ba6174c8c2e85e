// Text of the viewer's status line. Pure functions so the wording is unit-tested.

/** "2.1 s ago", "3 min ago", "1.5 h ago"; "never" for null. */
export function formatAge(seconds) {
  if (seconds === null || seconds === undefined) return 'never';
  const s = Math.max(0, seconds); // a clock step backwards must not print a negative age
  if (s < 60) return `${s.toFixed(1)} s ago`;
  if (s < 3600) return `${Math.floor(s / 60)} min ago`;
  return `${(s / 3600).toFixed(1)} h ago`;
}

/** 1234567 → "1,234,567". */
export function formatCount(n) {
  return Math.round(n).toString().replace(/\B(?=(\d{3})+(?!\d))/g, ',');
}

/**
 * Bytes per second as kB/s, 1 kB = 1000 bytes (so that 8 × is the kbit/s of link budgets):
 * "0.4 kB/s", "9.9 kB/s", "28 kB/s", "1,234 kB/s".
 */
export function formatKilobytesPerSecond(bytesPerSecond) {
  const kB = Math.max(0, bytesPerSecond) / 1000;
  return `${kB < 9.95 ? kB.toFixed(1) : formatCount(kB)} kB/s`;
}

/**
 * The rates on the status line, each per second or null (not measured: left out).
 * `poses`, `clouds`: what a live session's vehicles sent that the server took, all vehicles
 * together; `linkBytes`: those vehicles' samples on their link into the server; `viewerBytes`:
 * what this page's connection received. "10.0 poses/s · 3.2 clouds/s · link 28 kB/s · viewer 12 kB/s".
 */
export function ratesText({ poses = null, clouds = null, linkBytes = null, viewerBytes = null }) {
  const parts = [];
  if (poses !== null) parts.push(`${poses.toFixed(1)} poses/s`);
  if (clouds !== null) parts.push(`${clouds.toFixed(1)} clouds/s`);
  if (linkBytes !== null) parts.push(`link ${formatKilobytesPerSecond(linkBytes)}`);
  if (viewerBytes !== null) parts.push(`viewer ${formatKilobytesPerSecond(viewerBytes)}`);
  return parts.join(' · ');
}

function plural(n, word) {
  return `${formatCount(n)} ${word}${n === 1 ? '' : 's'}`;
}

/**
 * The status line. `link` is {connected, retryInSeconds}; `session` is null (none chosen) or
 * {id, known, vehicle, renderedVoxels, serverVoxels, frames, ageSeconds, corrections, refusing};
 * `known` is false for a session asked for (?session=ID) that the server has not reported;
 * `corrections` counts the vehicles' pose-graph corrections the map took, `refusing` is true
 * while the server fuses the map again with the newest.
 */
export function statusText(link, session) {
  const parts = [link.connected ? 'connected'
    : link.retryInSeconds > 0 ? `disconnected, retrying in ${Math.ceil(link.retryInSeconds)} s`
    : 'connecting…'];
  if (!session) {
    parts.push('no session yet');
  } else if (!session.known) {
    parts.push(`session ${session.id} not on the server (yet)`);
  } else {
    parts.push(`session ${session.id}${session.vehicle ? ` (${session.vehicle})` : ''}`);
    // Cells drawn (coarser levels far away) against the map's voxels at the finest level.
    const { renderedVoxels: shown, serverVoxels: total } = session;
    parts.push(total > 0 && total !== shown ? `${formatCount(shown)} cells of ${plural(total, 'voxel')}` : plural(shown, 'voxel'));
    // A map with voxels and no frames came from a file (stereomap-store import) or a diff.
    const made = session.isDiff ? 'diff of two flights' : 'imported map';
    parts.push(session.frames === 0 && total > 0 ? made : plural(session.frames, 'frame'));
    if (session.corrections > 0) {
      parts.push(`${plural(session.corrections, 'pose correction')}${session.refusing ? ', map being fused again' : ''}`);
    }
    parts.push(`updated ${formatAge(session.ageSeconds)}`);
  }
  return parts.join(' · ');
}

// Where the server is with aligning a vehicle in its own frame into the session's:
// "aligning (4 tries: too little overlap)", "aligned (overlap 62 %, rmse 0.04 m)".
function frameText(f) {
  if (f.frame === 'aligned') {
    const fit = [];
    if (f.overlap != null) fit.push(`overlap ${Math.round(f.overlap * 100)} %`);
    if (f.rmseM != null) fit.push(`rmse ${f.rmseM.toFixed(2)} m`);
    return fit.length > 0 ? `aligned (${fit.join(', ')})` : 'aligned';
  }
  const tries = f.attempts > 0 ? `${f.attempts} ${f.attempts === 1 ? 'try' : 'tries'}` : '';
  const why = [tries, f.reason].filter((t) => t).join(': ');
  return why ? `aligning (${why})` : 'aligning';
}

/**
 * One line per vehicle of a session from its own counters (protocol.js: the status's
 * vehicleStatus) and, for a vehicle in its own frame, its alignment (vehicleFrames), merged
 * by vehicle id: what an operator needs to see of a vehicle they cannot reach. The frame
 * first, then the spool always and the other counts only when not zero. "sim-2: aligning
 * (4 tries: too little overlap) · spool 3 samples (8.3 kB) · 2 frames skipped". (A vehicle
 * told its session is closed sends no more status: the server keeps none.)
 */
export function vehicleLines(vehicleStatus, vehicleFrames) {
  const frames = new Map((vehicleFrames ?? []).map((f) => [f.vehicleId, f]));
  const lines = (vehicleStatus ?? []).map((v) => {
    const parts = [`spool ${plural(v.spoolSamples, 'sample')}${v.spoolBytes > 0 ? ` (${(v.spoolBytes / 1000).toFixed(1)} kB)` : ''}`];
    if (v.skippedFrames > 0) parts.push(`${plural(v.skippedFrames, 'frame')} skipped`);
    if (v.lateFrames > 0) parts.push(`${plural(v.lateFrames, 'frame')} late`);
    if (v.givenUp > 0) parts.push(`${plural(v.givenUp, 'sample')} given up`);
    const frame = frames.get(v.vehicleId);
    frames.delete(v.vehicleId);
    if (frame) parts.unshift(frameText(frame));
    return `${v.vehicleId}: ${parts.join(' · ')}`;
  });
  // Vehicles with no status of their own (yet) still show their frame.
  for (const f of frames.values()) lines.push(`${f.vehicleId}: ${frameText(f)}`);
  return lines;
}

/** Yaw in degrees of a quaternion [qx, qy, qz, qw] (rotation about z, -180..180). */
function yawDegrees([qx, qy, qz, qw]) {
  return (Math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz)) * 180) / Math.PI;
}

/**
 * What made a session that is not a flight (a parsed status origin), as panel lines: a site's
 * sessions and where each was placed ("tue: moved (20.00, 0.00, 0.00) m, yaw 90.0° · onto mon:
 * overlap 64 %, rmse 0.031 m"), those left out, a diff's counts, or the file imported. None
 * for a flight.
 */
export function originLines(origin) {
  if (!origin) return [];
  const lines = [];
  if (origin.site) {
    const [first, ...rest] = origin.site.sessions;
    if (first) lines.push(`site in ${first.session}'s frame: ${plural(origin.site.sessions.length, 'session')}`);
    for (const s of rest) {
      const [x, y, z] = s.transform;
      let line = `${s.session}: moved (${x.toFixed(2)}, ${y.toFixed(2)}, ${z.toFixed(2)}) m, yaw ${yawDegrees(s.transform.slice(3)).toFixed(1)}°`;
      if (s.onto) {
        line += ` · onto ${s.onto}`;
        if (s.overlap !== null) line += `: overlap ${(100 * s.overlap).toFixed(0)} %`;
        if (s.rmseM !== null) line += `, rmse ${s.rmseM.toFixed(3)} m`;
      }
      lines.push(line);
    }
    for (const l of origin.site.leftOut) lines.push(`${l.session}: left out${l.reason ? ` (${l.reason})` : ''}`);
  }
  if (origin.diff) {
    const d = origin.diff;
    lines.push(`diff ${d.first} → ${d.second}: ${formatCount(d.appeared)} appeared, ${formatCount(d.disappeared)} disappeared, ${formatCount(d.unchanged)} unchanged`);
    lines.push(`not seen by ${d.first}: ${formatCount(d.unseenByFirst)} · by ${d.second}: ${formatCount(d.unseenBySecond)} (unknown is not free)`);
  }
  if (origin.importedFrom) lines.push(`imported from ${origin.importedFrom}`);
  return lines;
}
