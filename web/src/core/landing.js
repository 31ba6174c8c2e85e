// What the vehicles see of the landing pad (GET /api/sessions/{id}/landing): the words for the
// status line and the T's outline in the map. Pure functions, unit-tested.

/** The pad's corners a..h in its own frame (metres, z = 0): the landing patent's T. */
export const kPadCorners = [[0, 0], [3, 0], [3, 1], [2, 1], [2, 4], [1, 4], [1, 1], [0, 1]];

/** The 8 corners [x, y, z] in the map of a pad at `pose` ({position, orientation [qx,qy,qz,qw]}). */
export function padOutline(pose) {
  const [qx, qy, qz, qw] = pose.orientation;
  const [tx, ty, tz] = pose.position;
  return kPadCorners.map(([x, y]) => {
    // v' = v + 2 w (q × v) + 2 q × (q × v), with v = (x, y, 0)
    const cx = qy * 0 - qz * y, cy = qz * x - qx * 0, cz = qx * y - qy * x;
    const dx = qy * cz - qz * cy, dy = qz * cx - qx * cz, dz = qx * cy - qy * cx;
    return [x + 2 * (qw * cx + dx) + tx, y + 2 * (qw * cy + dy) + ty, 2 * (qw * cz + dz) + tz];
  });
}

function signed(degrees) {
  const d = Math.round(degrees);
  return d > 0 ? `+${d}°` : `${d}°`;
}

/**
 * One part of the status line per vehicle that reports on the pad: "pad 18.2 m at +12°
 * (uav-1)" while it is tracked with a pose, "pad lost (uav-1): REASON", "looking for the pad
 * (uav-1)"; null when no vehicle reports. Bearing: clockwise from the vehicle's forward axis.
 */
export function landingText(vehicles) {
  if (!vehicles || vehicles.length === 0) return null;
  return vehicles.map((v) => {
    if (v.state === 'TRACKING' && v.has_pose) {
      return `pad ${v.distance_m.toFixed(1)} m at ${signed(v.bearing_deg)} (${v.vehicle_id})`;
    }
    if (v.state === 'LOST') return `pad lost (${v.vehicle_id}): ${v.reason}`;
    return `looking for the pad (${v.vehicle_id})`;
  }).join(' · ');
}
