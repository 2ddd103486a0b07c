// Measures the dashboard at scale: `node first-paint.mjs BASE_URL`. On an empty server it first
// creates 99 small experiments and one with 50,000 transitions (500 trajectories of 100), all
// through the API; then it opens each page 5 times in headless Chromium and prints the median
// first contentful paint and the median time until the page's data is drawn.
import { launchChromium } from './chromium.mjs';
import { call, randomWalk, rng, unitSquare } from './seed.mjs';

const [base] = process.argv.slice(2);
if (!base) throw new Error('usage: node first-paint.mjs BASE_URL');

async function seed() {
  const rand = rng(11);
  const started = Date.now();
  for (let k = 0; k < 99; k++) {
    const e = await call(base, 'POST', '/v1/experiments', {
      name: `small ${k}`,
      seed: k,
      learning: { batch_size: 100 },
    });
    const transitions = [0, 1, 2].map(x => ({ s: [x, 0], a: [1, 0], s_next: [x + 1, 0] }));
    await call(base, 'POST', `/v1/experiments/${e.id}/trajectories`, { transitions });
  }
  const big = await call(base, 'POST', '/v1/experiments', {
    name: 'fifty thousand',
    seed: 1,
    domain: unitSquare(0.05),
    // No refit: an exact GP on 50,000 points is out of reach (O(n³)); the pages are measured.
    learning: { batch_size: 10000 },
  });
  for (let k = 0; k < 500; k++) {
    const transitions = randomWalk(rand, 100, 0.1, () => 0.9);
    await call(base, 'POST', `/v1/experiments/${big.id}/trajectories`, { transitions });
  }
  console.log(`seeded 100 experiments and 50,000 transitions in ${((Date.now() - started) / 1000).toFixed(1)} s`);
}

const list = await call(base, 'GET', '/v1/experiments?limit=1');
if (list.total === 0) await seed();
const all = await call(base, 'GET', '/v1/experiments?order=newest&limit=1000');
const big = all.items.reduce((a, b) => (b.n_transitions > a.n_transitions ? b : a));
const traj = (await call(base, 'GET', `/v1/experiments/${big.id}/runs?limit=1`)).items[0].trajectory_id;
console.log(`${all.total} experiments; the largest, #${big.id}, has ${big.n_transitions} transitions`);

const browser = await launchChromium();
const page = await browser.newPage({ viewport: { width: 1280, height: 900 } });
const median = xs => xs.slice().sort((a, b) => a - b)[Math.floor(xs.length / 2)];
const rows = [];
for (const [what, path] of [
  ['experiment list (100)', '/'],
  ['experiment page (50,000 transitions)', `/ui/experiments/${big.id}`],
  ['trajectory page (100 steps)', `/ui/experiments/${big.id}/trajectories/${traj}`],
  ['precondition map (41 × 41)', `/ui/experiments/${big.id}/map`],
]) {
  const fcp = [],
    ready = [];
  for (let k = 0; k < 5; k++) {
    await page.goto(base + path);
    await page.waitForSelector('body[data-ready="true"]', { timeout: 30000 });
    const [f, r] = await page.evaluate(() => [
      performance.getEntriesByName('first-contentful-paint')[0]?.startTime ?? NaN,
      performance.getEntriesByName('dashboard-ready')[0]?.startTime ?? NaN,
    ]);
    fcp.push(f);
    ready.push(r);
  }
  rows.push(`| ${what} | ${median(fcp).toFixed(0)} ms | ${median(ready).toFixed(0)} ms |`);
}
await browser.close();
console.log('| page | first contentful paint | data drawn |\n|---|---|---|\n' + rows.join('\n'));
