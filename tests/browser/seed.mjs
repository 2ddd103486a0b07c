// Fills a precond server with a small, seeded data set through its public API: the learning
// loop run for real on the icy gridworld (proposals executed in the true world), plus an
// abandoned, an open, an unsolicited partial, a deviating and a refused run and a logged
// trajectory with its source, and a kinematic experiment.

/** A seeded PRNG (mulberry32). */
export function rng(seed) {
  let a = seed >>> 0;
  return () => {
    a = (a + 0x6d2b79f5) >>> 0;
    let t = a;
    t = Math.imul(t ^ (t >>> 15), t | 1);
    t ^= t + Math.imul(t ^ (t >>> 7), t | 61);
    return ((t ^ (t >>> 14)) >>> 0) / 4294967296;
  };
}

/** The kinematic domain on the unit square, with actions of at most `step` per component. */
export function unitSquare(step) {
  return {
    kind: 'kinematic',
    state_low: [0, 0],
    state_high: [1, 1],
    action_low: [-step, -step],
    action_high: [step, step],
  };
}

/**
 * A random walk of `steps` transitions in the unit square from a random start: each action
 * uniform in ±`span`/2 per component, moving the state by `gain(s)` times the action, clamped.
 */
export function randomWalk(rand, steps, span, gain) {
  let s = [rand(), rand()];
  const transitions = [];
  for (let t = 0; t < steps; t++) {
    const a = [(rand() - 0.5) * span, (rand() - 0.5) * span];
    const g = gain(s);
    const next = s.map((v, i) => Math.min(1, Math.max(0, v + g * a[i])));
    transitions.push({ s, a, s_next: next });
    s = next;
  }
  return transitions;
}

export async function call(base, method, path, body) {
  const r = await fetch(base + path, {
    method,
    headers: { 'content-type': 'application/json' },
    body: body === undefined ? undefined : JSON.stringify(body),
  });
  const json = await r.json().catch(() => null);
  if (!r.ok) throw new Error(`${method} ${path}: ${r.status} ${JSON.stringify(json)}`);
  return json;
}

/** The icy gridworld's true dynamics on `map`: x-moves reversed on ice; blocked moves stay. */
export function trueStep(map, [x, y], [dx, dy]) {
  const cell = (cx, cy) => map[cy]?.[cx];
  if (cell(x, y) === '~' && dx !== 0) dx = -dx;
  const [nx, ny] = [x + dx, y + dy];
  const c = cell(nx, ny);
  return c === undefined || c === '#' ? [x, y] : [nx, ny];
}

function freeCell(map, rand) {
  for (;;) {
    const y = Math.floor(rand() * map.length),
      x = Math.floor(rand() * map[0].length);
    if (map[y][x] !== '#') return [x, y];
  }
}

/** Runs `n` learning-loop rounds on a new gridworld experiment; returns its id. */
export async function seedGridworld(base, { name = 'icy gridworld', n = 12, seed = 7 } = {}) {
  const rand = rng(seed);
  const e = await call(base, 'POST', '/v1/experiments', {
    name,
    seed,
    mde: { restarts: 0 },
    learning: { batch_size: 4, iterations: 6, n_candidates: 4, max_extensions: 1500 },
  });
  const map = e.domain.map;
  for (let k = 0; k < n; k++) {
    const start = freeCell(map, rand);
    let goal = freeCell(map, rand);
    while (goal[0] === start[0] && goal[1] === start[1]) goal = freeCell(map, rand);
    let p;
    try {
      p = await call(base, 'POST', `/v1/experiments/${e.id}/proposals`, { start, goal, client_id: `robot-${k % 3}` });
    } catch (err) {
      if (String(err).includes('no_plan')) continue;
      throw err;
    }
    let s = start;
    const transitions = p.trajectory.actions.map(a => {
      const next = trueStep(map, s, a);
      const t = { s, a, s_next: next };
      s = next;
      return t;
    });
    await call(base, 'POST', `/v1/experiments/${e.id}/trajectories`, { proposal_id: p.id, transitions });
  }
  // Every move from every free cell of two rows crossing the ice, posted without a proposal.
  const logged = [];
  for (const y of [2, 3])
    for (let x = 0; x < map[0].length; x++)
      for (const a of [
        [1, 0],
        [-1, 0],
        [0, 1],
        [0, -1],
      ]) {
        logged.push({ s: [x, y], a, s_next: trueStep(map, [x, y], a) });
      }
  await call(base, 'POST', `/v1/experiments/${e.id}/trajectories`, {
    transitions: logged,
    source: { dataset: 'logs/icy-rows.csv', episode: 2, label: 'teleop' },
  });
  // A robot that slipped: its first move is not the one proposed (a deviating execution).
  const drift = await call(base, 'POST', `/v1/experiments/${e.id}/proposals`, {
    start: [0, 0],
    goal: [3, 0],
    client_id: 'drifter',
  });
  let at = [0, 0];
  const slipped = drift.trajectory.actions.map((a, i) => {
    const act = i === 0 ? (a[1] === 1 ? [1, 0] : [0, 1]) : a;
    const next = trueStep(map, at, act);
    const t = { s: at, a: act, s_next: next };
    at = next;
    return t;
  });
  await call(base, 'POST', `/v1/experiments/${e.id}/trajectories`, { proposal_id: drift.id, transitions: slipped });
  // A request refused: the client's only candidate stops short of its goal.
  await call(base, 'POST', `/v1/experiments/${e.id}/proposals`, {
    start: [0, 0],
    goal: [5, 5],
    client_id: 'own-planner',
    candidates: [
      {
        states: [
          [0, 0],
          [1, 0],
        ],
        actions: [[1, 0]],
      },
    ],
  }).then(
    () => {
      throw new Error('the short candidate was not refused');
    },
    err => {
      if (!String(err).includes('no_plan')) throw err;
    },
  );
  const bumped = await call(base, 'POST', `/v1/experiments/${e.id}/trajectories`, {
    partial: true,
    transitions: [{ s: [0, 0], a: [1, 0], s_next: [1, 0] }],
  });
  // The operator left this run out of the model (the refit below is fitted without it).
  await call(base, 'POST', `/v1/experiments/${e.id}/exclusions`, {
    trajectory_id: bumped.id,
    reason: 'the robot was bumped by a person',
  });
  const quit = await call(base, 'POST', `/v1/experiments/${e.id}/proposals`, {
    start: [0, 0],
    goal: [0, 4],
    client_id: 'quitter',
  });
  await call(base, 'POST', `/v1/experiments/${e.id}/proposals/${quit.id}/abandon`, {});
  await call(base, 'POST', `/v1/experiments/${e.id}/proposals`, { start: [1, 1], goal: [4, 1], client_id: 'waiting' });
  await call(base, 'POST', `/v1/experiments/${e.id}/model/refit`, {});
  return e.id;
}

/** A kinematic experiment with a few random-walk trajectories (labels from a 10 % drag). */
export async function seedKinematic(base, { name = 'kinematic arm', seed = 3 } = {}) {
  const rand = rng(seed);
  const e = await call(base, 'POST', '/v1/experiments', {
    name,
    seed,
    domain: unitSquare(0.1),
    mde: { restarts: 0, noise: 'homoscedastic', estimator: 'local_experts', expert_size: 50 },
    learning: { batch_size: 100 },
    // A second model of the arm, which ignores the action: it labels every transition too.
    models: [
      {
        name: 'still',
        cost: 0.1,
        model: {
          kind: 'linear',
          A: [
            [1, 0],
            [0, 1],
          ],
          B: [
            [0, 0],
            [0, 0],
          ],
        },
      },
    ],
  });
  for (let k = 0; k < 4; k++) {
    const transitions = randomWalk(rand, 15, 0.2, s => (s[0] > 0.5 ? 0.5 : 0.95));
    await call(base, 'POST', `/v1/experiments/${e.id}/trajectories`, { transitions });
  }
  await call(base, 'POST', `/v1/experiments/${e.id}/model/refit`, {});
  return e.id;
}
