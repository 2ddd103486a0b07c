// End-to-end tests of the dashboard in headless Chromium: `node dashboard.mjs BASE_URL OUT_DIR`.
// The server at BASE_URL must be empty; this script fills it through the API, opens every page,
// checks what they show and saves screenshots in OUT_DIR. Exits non-zero on the first failure.
import { launchChromium } from './chromium.mjs';
import assert from 'node:assert/strict';
import { mkdirSync } from 'node:fs';
import { call, seedGridworld, seedKinematic } from './seed.mjs';

const [base, out] = process.argv.slice(2);
if (!base || !out) throw new Error('usage: node dashboard.mjs BASE_URL OUT_DIR');
mkdirSync(out, { recursive: true });

const t0 = Date.now();
const kin = await seedKinematic(base);
const grid = await seedGridworld(base);
const e = await call(base, 'GET', `/v1/experiments/${grid}`);
console.log(
  `seeded: gridworld #${grid} (${e.n_trajectories} trajectories, model v${e.model_version}), kinematic #${kin} in ${Date.now() - t0} ms`,
);

const browser = await launchChromium();
const context = await browser.newContext({ viewport: { width: 1280, height: 900 }, acceptDownloads: true });
const page = await context.newPage();
const errors = [];
page.on('pageerror', err => errors.push(String(err)));
page.on('console', msg => {
  if (msg.type() === 'error') errors.push(msg.text());
});

async function open(path) {
  await page.goto(base + path);
  await page.waitForSelector('body[data-ready="true"]', { timeout: 20000 });
  const alert = await page.locator('[role=alert]').count();
  assert.equal(alert, 0, `${path} shows an error: ${alert && (await page.locator('[role=alert]').innerText())}`);
}

/**
 * The line charts on this page draw lines, not filled polygons: every `polyline` has computed
 * `fill: none` (the series colour rules must not fill it), while each point and legend entry is
 * filled in the colour of its series' line.
 */
async function assertChartLines(what) {
  const charts = await page.locator('.chart svg').evaluateAll(svgs =>
    svgs.map(svg => {
      const lines = {};
      for (const l of svg.querySelectorAll('polyline')) lines[l.getAttribute('class')] = getComputedStyle(l);
      return {
        fills: [...svg.querySelectorAll('polyline')].map(l => getComputedStyle(l).fill),
        marks: [...svg.querySelectorAll('circle, .legend')].map(m => {
          const series = m.getAttribute('class').match(/series-\d+/)[0];
          return { series, fill: getComputedStyle(m).fill, line: lines[series]?.stroke };
        }),
      };
    }),
  );
  const fills = charts.flatMap(c => c.fills);
  assert.ok(fills.length > 0, `${what} draws line charts`);
  const filled = fills.filter(f => f !== 'none');
  assert.equal(
    filled.length,
    0,
    `${what}: ${filled.length} of ${fills.length} chart lines are filled (${[...new Set(filled)]}), not fill none`,
  );
  const marks = charts.flatMap(c => c.marks);
  assert.ok(marks.length > 0, `${what} draws points`);
  for (const m of marks) assert.equal(m.fill, m.line, `${what}: ${m.series} points and legend filled as its line`);
}

const tests = [];
const test = (name, fn) => tests.push([name, fn]);

test('the experiment list shows every experiment, newest first, and exports CSV', async () => {
  await open('/');
  const rows = page.locator('#experiments tbody tr');
  assert.equal(await rows.count(), 2);
  assert.match(await rows.nth(0).innerText(), /icy gridworld\s+icy_gridworld\s+active/);
  assert.match(await rows.nth(1).innerText(), /kinematic arm\s+kinematic/);
  await page.screenshot({ path: `${out}/experiments.png` });
  const [download] = await Promise.all([page.waitForEvent('download'), page.getByText('Export CSV').click()]);
  const csv = await (await import('node:fs/promises')).readFile(await download.path(), 'utf8');
  const lines = csv.trim().split('\n');
  assert.equal(lines[0], 'id,name,domain,strategy,iteration,trajectories,transitions,model_version,last_activity');
  assert.equal(lines.length, 3);
  assert.match(
    lines[1],
    new RegExp(`^${grid},icy gridworld,icy_gridworld,active,\\d+,${e.n_trajectories},${e.n_transitions},`),
  );
});

test('an experiment shows its settings, timeline and runs', async () => {
  await page.getByRole('link', { name: 'icy gridworld' }).click();
  await page.waitForSelector('body[data-ready="true"]');
  assert.match(await page.locator('#settings').innerText(), /icy_gridworld[\s\S]*batch size\s+4/);
  assert.match(
    await page.locator('#settings').innerText(),
    /heteroscedastic, (matern(12|32|52) kernel|kernel chosen at each fit by marginal likelihood \(auto\))/,
  );
  assert.ok((await page.locator('#timeline figure').count()) >= 6, 'model and iteration charts');
  await assertChartLines('the learning timeline');
  const statuses = await page.locator('#runs .badge').allInnerTexts();
  for (const s of ['open', 'abandoned', 'executed', 'unsolicited', 'refused', 'deviating'])
    assert.ok(statuses.includes(s), `${s} in ${statuses}`);
  await page.screenshot({ path: `${out}/experiment.png`, fullPage: true });
});

test('the runs table shows refused and deviating runs, and a logged run its source', async () => {
  const runs = await call(base, 'GET', `/v1/experiments/${grid}/runs?limit=100`);
  const refused = runs.items.filter(r => r.status === 'refused');
  assert.ok(refused.length >= 1, 'the seed was refused at least once');
  const rows = page.locator('#runs tbody tr');
  const refusedRow = rows.filter({ has: page.locator('.badge.refused') }).first();
  const text = await refusedRow.innerText();
  assert.match(text, /own-planner/, 'the newest refusal is the client whose candidate fell short');
  assert.match(text, /no plan at β -?\d[\d.]*( → -?\d[\d.]*)* \(0 extensions\)/, text);
  const kpis = await page.locator('.kpi').innerText();
  const e2 = await call(base, 'GET', `/v1/experiments/${grid}`);
  assert.equal(e2.n_refused, refused.length);
  assert.match(kpis, new RegExp(`${e2.n_refused}\\s+refused requests`));
  assert.ok((await page.locator('#timeline figure h3', { hasText: 'Refused proposal requests' }).count()) === 1);

  const deviating = runs.items.filter(r => r.deviating);
  assert.equal(deviating.length, 1, 'one deviating run: the drifter');
  const devRow = rows.filter({ has: page.locator('.badge.deviating') });
  assert.equal(await devRow.count(), 1);
  assert.match(await devRow.innerText(), /executed\s+deviating[\s\S]*drifter/);
  assert.match(
    await rows.filter({ hasText: 'logs/icy-rows.csv' }).innerText(),
    /unsolicited[\s\S]*logs\/icy-rows\.csv · episode 2 · teleop/,
  );

  await devRow.locator(`a[href$="/trajectories/${deviating[0].trajectory_id}"]`).click();
  await page.waitForSelector('body[data-ready="true"]');
  assert.match(await page.locator('h1').innerText(), /deviating/);
  assert.match(await page.locator('#deviating').innerText(), /did not execute the proposal as planned/);
  assert.equal(await page.locator('#steps tbody tr').first().locator('td .bad[title^="planned"]').count(), 1);
  await page.screenshot({ path: `${out}/deviating.png`, fullPage: true });

  const logged = runs.items.find(r => r.source);
  await open(`/ui/experiments/${grid}/trajectories/${logged.trajectory_id}`);
  assert.equal(await page.locator('#source').innerText(), 'Source: logs/icy-rows.csv · episode 2 · teleop');
  assert.equal(await page.locator('#deviating').count(), 0);
  await open(`/ui/experiments/${grid}`);
});

test('an excluded run is marked in the runs and listed with its reason', async () => {
  const listed = await call(base, 'GET', `/v1/experiments/${grid}/exclusions`);
  assert.equal(listed.total, 1);
  const x = listed.items[0];
  assert.ok(x.applied, 'the seed refit after the exclusion');
  const row = page.locator('#runs tbody tr').filter({ has: page.locator('.badge.excluded') });
  assert.equal(await row.count(), 1);
  assert.match(await row.innerText(), new RegExp(`#${x.trajectory_ids[0]} steps`));
  const text = await page.locator(`#exclusion-${x.id}`).innerText();
  assert.match(text, new RegExp(`trajectory #${x.trajectory_ids[0]} \\(1 trajectory, 1 transitions\\)`));
  assert.match(text, /the robot was bumped by a person[\s\S]*in effect[\s\S]*yes/);
  const model = await call(base, 'GET', `/v1/experiments/${grid}/model`);
  assert.deepEqual(model.exclusions, [x.id]);
});

test('a trajectory shows its steps with μ ± σ at the time and now', async () => {
  const runs = await call(base, 'GET', `/v1/experiments/${grid}/runs?limit=100`);
  const executed = runs.items.find(r => r.status === 'executed');
  await page.locator(`a[href$="/trajectories/${executed.trajectory_id}"]`).click();
  await page.waitForSelector('body[data-ready="true"]');
  assert.equal(await page.locator('#steps tbody tr').count(), executed.length);
  const first = await page.locator('#steps tbody tr').first().innerText();
  assert.match(first, /±[\s\S]*±/, 'μ ± σ at the time and now');
  assert.match(await page.locator('main').innerText(), new RegExp(`Executed proposal\\s+#${executed.proposal_id}`));
  await assertChartLines('the trajectory page');
});

test('the precondition map draws one grid per move and slides over model versions', async () => {
  await open(`/ui/experiments/${grid}/map`);
  // The version answering now (a background refit may have added one since seeding).
  await page.waitForSelector('body[data-map-ready]');
  assert.ok(+(await page.evaluate(() => document.body.dataset.mapReady)) >= e.model_version);
  const canvases = page.locator('#map-panels canvas');
  assert.equal(await canvases.count(), 4, 'one panel per discrete action');
  const colours = await canvases.first().evaluate(c => {
    const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
    const seen = new Set();
    for (let i = 0; i < d.length; i += 4 * 97) seen.add(`${d[i]},${d[i + 1]},${d[i + 2]}`);
    return seen.size;
  });
  assert.ok(colours > 5, `the map is drawn (${colours} colours)`);
  const caption = () => page.locator('#map-panels figure').first().innerText();
  const before = await caption();
  await page.locator('#map-beta').fill('-3');
  assert.notEqual(await caption(), before, 'β changes the share inside');
  await page.locator('#map-beta').fill('2');
  await page.screenshot({ path: `${out}/map.png`, fullPage: true });
  await page.locator('#map-version').fill('1');
  await page.waitForSelector('body[data-map-ready="1"]');
});

test('the kinematic experiment says which estimator fits it', async () => {
  await open(`/ui/experiments/${kin}`);
  await page.waitForSelector('body[data-ready="true"]');
  assert.match(
    await page.locator('#settings').innerText(),
    /local experts: an exact GP per region of about 50 transitions, each with its own hyperparameters/,
  );
  // Its two models of the arm, each with what its labels of the 60 transitions say.
  const rows = await page.locator('#robot-models tbody tr').allInnerTexts();
  assert.equal(rows.length, 2, rows.join(' | '));
  assert.match(rows[0], /^domain\s+built_in\s+1\s+60\s+0\s/);
  assert.match(rows[1], /^still\s+linear\s+0\.1\s+60\s+0\s/);
});

test('the kinematic map has two continuous axes and sliders for the rest', async () => {
  await open(`/ui/experiments/${kin}/map`);
  await page.waitForSelector('body[data-map-ready]');
  assert.equal(await page.locator('#map-panels canvas').count(), 1);
  assert.equal(await page.locator('.controls input[type=range]').count(), 2 + 2, 'β, version and two fixed components');
  // Axes in the state's units: each end and the middle of the grid (the unit square).
  await page.screenshot({ path: `${out}/map-kinematic.png`, fullPage: true });
  assert.deepEqual(await page.locator('.map-ticks.x span').allInnerTexts(), ['0', '0.5', '1']);
  assert.deepEqual(await page.locator('.map-ticks.y span').allInnerTexts(), ['0', '0.5', '1']);
  // The fixed action is a typical move of the training data (each component's median), not
  // the middle of the bounds.
  const m = await call(base, 'GET', `/v1/experiments/${kin}/precondition/map?x=s.x0&y=s.x1&nx=3&ny=3`);
  const median = v => {
    const w = [...v].sort((a, b) => a - b),
      k = Math.floor(w.length / 2);
    return w.length % 2 ? w[k] : (w[k - 1] + w[k]) / 2;
  };
  const want = [0, 1].map(i => median(m.training.map(t => t.a[i])));
  const slider = name => page.locator(`.controls label:text-is("${name}") + input`);
  const got = [+(await slider('a.dx0').inputValue()), +(await slider('a.dx1').inputValue())];
  for (let i = 0; i < 2; i++)
    assert.ok(Math.abs(got[i] - want[i]) <= 0.002 + 1e-9, `a[${i}]: ${got[i]} against ${want[i]}`);
  // One map per model of the robot: the further model `still` has its own.
  assert.deepEqual(await page.locator('#map-model option').allInnerTexts(), ['domain', 'still']);
  assert.equal(await page.locator('#map-panels').getAttribute('data-model'), 'domain');
  await page.locator('#map-model').selectOption('still');
  await page.waitForSelector('#map-panels[data-model="still"]');
  assert.match(await page.locator('#map-status').innerText(), /precondition of still/);
});

test('a trajectory of a proposal across models says which model each step relied on', async () => {
  const proposal = await call(base, 'POST', `/v1/experiments/${kin}/proposals`, {
    start: [0.2, 0.2],
    goal: [0.5, 0.5],
    client_id: 'two-models',
    models: ['domain', 'still'],
  });
  assert.deepEqual(proposal.models, ['still', 'domain']);
  const { states, actions } = proposal.trajectory;
  const executed = await call(base, 'POST', `/v1/experiments/${kin}/trajectories`, {
    proposal_id: proposal.id,
    transitions: actions.map((a, i) => ({ s: states[i], a, s_next: states[i + 1] })),
  });
  await open(`/ui/experiments/${kin}/trajectories/${executed.id}`);
  await page.waitForSelector('body[data-ready="true"]');
  assert.match(await page.locator('main').innerText(), /It stepped with still, domain \(cheapest first\)/);
  const heads = await page.locator('#steps thead th').allInnerTexts();
  const column = heads.indexOf('model');
  assert.ok(column > 0, heads.join(' | '));
  const cells = await page.locator(`#steps tbody tr td:nth-child(${column + 1})`).allInnerTexts();
  assert.deepEqual(cells, proposal.step_models);
});

test('diagnostics show leave-one-out calibration and the precondition rates', async () => {
  await open(`/ui/experiments/${grid}/diagnostics`);
  await page.waitForSelector('#diagnostics .kpi');
  const text = await page.locator('#diagnostics').innerText();
  assert.match(text, /inside μ ± 1σ[\s\S]*nominal 68\.3 %/);
  assert.match(text, /TPR[\s\S]*TNR/);
  await assertChartLines('the diagnostics page');
  await page.screenshot({ path: `${out}/diagnostics.png`, fullPage: true });
  // Version 1 was fitted after the first batch: every later transition is judged by it.
  await open(`/ui/experiments/${grid}/diagnostics?version=1`);
  await page.waitForSelector('#later');
  assert.match(
    await page.locator('#later').innerText(),
    /transitions posted after its training set[\s\S]*TPR[\s\S]*TNR/,
  );
});

test('an unknown experiment shows the API error', async () => {
  await page.goto(`${base}/ui/experiments/999`);
  await page.waitForSelector('body[data-ready="true"]');
  assert.match(await page.locator('[role=alert]').innerText(), /404 not_found: no experiment 999/);
  errors.length = 0; // the failed fetch is logged by the browser, as it should be
});

let failed = 0;
for (const [name, fn] of tests) {
  const started = Date.now();
  try {
    await fn();
    assert.deepEqual(errors.splice(0), [], 'no errors in the browser console');
    console.log(`ok   ${name} (${Date.now() - started} ms)`);
  } catch (err) {
    failed++;
    console.log(
      `FAIL ${name}\n     ${String(err.stack ?? err)
        .split('\n')
        .slice(0, 4)
        .join('\n     ')}`,
    );
    await page.screenshot({ path: `${out}/failure-${failed}.png`, fullPage: true }).catch(() => {});
    errors.length = 0;
  }
}
await browser.close();
console.log(`${tests.length - failed} passed, ${failed} failed; screenshots in ${out}`);
process.exit(failed ? 1 : 0);
