// A picture of a session as a user first sees it: opens the viewer (Debian's chromium through
// playwright-core) at URL, waits until the map has arrived (the cells drawn stop changing),
// and saves a PNG. For the README's pictures (docs/), taken by hand:
//   node tests/browser/screenshot.mjs --url 'http://127.0.0.1:8080/?session=ID' --out FILE.png
//     [--width 1280] [--height 720] [--settle-ms 3000] [--timeout-ms 60000]
import { parseArgs } from 'node:util';

const kChromiumFlags = ['--headless', '--no-sandbox', '--disable-gpu', '--use-angle=swiftshader',
  '--enable-unsafe-swiftshader', '--disable-background-networking', '--disable-component-update', '--no-first-run'];

function usage(message) {
  console.error(`screenshot: ${message}\nusage: screenshot.mjs --url URL --out FILE.png [--width 1280] [--height 720] [--settle-ms 3000] [--timeout-ms 60000]`);
  process.exit(2);
}

let values;
try {
  ({ values } = parseArgs({
    options: Object.fromEntries(['url', 'out', 'width', 'height', 'settle-ms', 'timeout-ms', 'help']
      .map((name) => [name, { type: name === 'help' ? 'boolean' : 'string' }])),
  }));
} catch (error) {
  usage(error.message);
}
if (values.help) usage('a picture of the viewer');
if (!values.url || !values.out) usage('--url and --out are required');
const number = (name, fallback) => {
  const n = Number(values[name] ?? fallback);
  if (!Number.isInteger(n) || n <= 0) usage(`--${name} must be a positive integer, got "${values[name]}"`);
  return n;
};
const width = number('width', 1280), height = number('height', 720);
const settleMs = number('settle-ms', 3000), timeoutMs = number('timeout-ms', 60000);

const modulePath = new URL('../../web/node_modules/playwright-core/index.mjs', import.meta.url);
const { chromium } = await import(modulePath.href);
const browser = await chromium.launch({ executablePath: '/usr/bin/chromium', args: kChromiumFlags });
try {
  const page = await browser.newPage({ viewport: { width, height } });
  await page.goto(values.url);
  // The map has arrived when the cells drawn have not changed for settle-ms.
  const deadline = Date.now() + timeoutMs;
  let last = -1, since = Date.now();
  for (;;) {
    const drawn = await page.evaluate(() => window.__stereomap?.renderedVoxels?.() ?? 0);
    if (drawn !== last) [last, since] = [drawn, Date.now()];
    if (drawn > 0 && Date.now() - since >= settleMs) break;
    if (Date.now() > deadline) throw new Error(`no map drawn within ${timeoutMs} ms (cells drawn: ${drawn})`);
    await new Promise((resolve) => setTimeout(resolve, 250));
  }
  await page.screenshot({ path: values.out });
  console.log(`screenshot: ${values.out} (${last} cells drawn)`);
} finally {
  await browser.close();
}
