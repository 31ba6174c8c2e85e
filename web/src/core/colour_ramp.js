// The height colour ramp shared by the voxels and the legend, so both always agree.
// Stops are sRGB in [0, 1], low to high (blue → teal → green → yellow → orange → red).

export const kHeightRamp = [
  [0.18, 0.25, 0.75],
  [0.1, 0.55, 0.8],
  [0.2, 0.72, 0.45],
  [0.85, 0.85, 0.25],
  [0.95, 0.55, 0.15],
  [0.85, 0.2, 0.2],
];

/** sRGB colour at t ∈ [0, 1] (clamped), linear between stops. */
export function rampColour(t) {
  const x = Math.min(1, Math.max(0, Number.isFinite(t) ? t : 0)) * (kHeightRamp.length - 1);
  const i = Math.min(Math.floor(x), kHeightRamp.length - 2);
  const f = x - i;
  return kHeightRamp[i].map((a, c) => a + (kHeightRamp[i + 1][c] - a) * f);
}

/** CSS gradient of the ramp, low values at the bottom. */
export function rampCssGradient() {
  const stops = kHeightRamp.map((rgb, i) => {
    const [r, g, b] = rgb.map((c) => Math.round(c * 255));
    return `rgb(${r}, ${g}, ${b}) ${((100 * i) / (kHeightRamp.length - 1)).toFixed(0)}%`;
  });
  return `linear-gradient(to top, ${stops.join(', ')})`;
}

// A diff session's classes (server/align/map_diff.hpp: kDiff*P), told apart by each voxel's
// tile value round(255 P): appeared 248, disappeared 217, unchanged 184. Most changed first.
export const kChangeClasses = [
  { name: 'appeared', from: 240, rgb: [0.16, 0.78, 0.24] },
  { name: 'disappeared', from: 200, rgb: [0.86, 0.16, 0.16] },
  { name: 'unchanged', from: 0, rgb: [0.6, 0.6, 0.62] },
];

/** sRGB colour of a diff session's voxel from its tile value (0-255). */
export function changeColour(value) {
  return kChangeClasses.find((c) => value >= c.from).rgb;
}

/** CSS bands of the change classes for the legend: unchanged at the bottom, appeared on top. */
export function changeCssGradient() {
  const n = kChangeClasses.length;
  const stops = [...kChangeClasses].reverse().map(({ rgb }, i) => {
    const css = `rgb(${rgb.map((c) => Math.round(c * 255)).join(', ')})`;
    return `${css} ${((100 * i) / n).toFixed(0)}%, ${css} ${((100 * (i + 1)) / n).toFixed(0)}%`;
  });
  return `linear-gradient(to top, ${stops.join(', ')})`;
}
