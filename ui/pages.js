// The dashboard's pages. Each renders into `root` from the JSON API only.
import { API, api } from './api.js';
import { crumbs, h } from './dom.js';
import { ago, fmt, vec } from './format.js';
import { lineChart, drawMap, colourLegend } from './charts.js';

const PAGE = 25;
const expUrl = id => `/ui/experiments/${id}`;

function pager(offset, limit, total, href) {
  const prev = offset > 0,
    next = offset + limit < total;
  return h(
    'div',
    { class: 'pager' },
    h(
      'a',
      { href: prev ? href(Math.max(0, offset - limit)) : null, 'aria-disabled': !prev, class: prev ? '' : 'muted' },
      '← newer',
    ),
    h('span', { class: 'muted' }, total ? `${offset + 1}–${Math.min(total, offset + limit)} of ${total}` : 'none yet'),
    h('a', { href: next ? href(offset + limit) : null, 'aria-disabled': !next, class: next ? '' : 'muted' }, 'older →'),
  );
}

function table(headers, rows, opts = {}) {
  return h(
    'div',
    { class: 'table-wrap' },
    h(
      'table',
      { id: opts.id },
      h(
        'thead',
        {},
        h(
          'tr',
          {},
          headers.map(([t, num]) => h('th', { class: num ? 'num' : '' }, t)),
        ),
      ),
      h('tbody', {}, rows),
    ),
  );
}

const td = (x, num) => h('td', { class: num ? 'num' : '' }, x);

// ---------------------------------------------------------------- experiments

const EXP_COLUMNS = [
  'id',
  'name',
  'domain',
  'strategy',
  'iteration',
  'trajectories',
  'transitions',
  'model_version',
  'last_activity',
];
const expRow = e => [
  e.id,
  e.name,
  e.domain.kind,
  e.learning.strategy,
  e.iteration,
  e.n_trajectories,
  e.n_transitions,
  e.model_version,
  e.last_activity,
];

function csvCell(v) {
  const s = String(v ?? '');
  return /[",\n]/.test(s) ? `"${s.replaceAll('"', '""')}"` : s;
}

async function exportCsv(button) {
  button.disabled = true;
  try {
    const rows = [EXP_COLUMNS];
    for (let offset = 0; ;) {
      const page = await api(`/v1/experiments?order=newest&offset=${offset}&limit=1000`);
      rows.push(...page.items.map(expRow));
      if (page.next === null) break;
      offset = page.next;
    }
    const blob = new Blob([rows.map(r => r.map(csvCell).join(',')).join('\n') + '\n'], { type: 'text/csv' });
    const a = h('a', { href: URL.createObjectURL(blob), download: 'experiments.csv' });
    document.body.append(a);
    a.click();
    a.remove();
  } finally {
    button.disabled = false;
  }
}

export async function experimentList(root, params) {
  crumbs([['Experiments']]);
  const offset = Math.max(0, parseInt(params.get('offset') ?? '0', 10) || 0);
  const page = await api(`/v1/experiments?order=newest&offset=${offset}&limit=${PAGE}`);
  const rows = page.items.map(e =>
    h(
      'tr',
      {},
      td(e.id, true),
      td(h('a', { href: expUrl(e.id) }, e.name || `experiment ${e.id}`)),
      td(e.domain.kind),
      td(e.learning.strategy),
      td(e.iteration, true),
      td(e.n_trajectories, true),
      td(e.n_transitions, true),
      td(e.model_version, true),
      td(ago(e.last_activity)),
    ),
  );
  const csv = h('button', { onclick: ev => exportCsv(ev.target) }, 'Export CSV');
  root.replaceChildren(
    h('h1', {}, 'Experiments'),
    h(
      'div',
      { class: 'pager' },
      pager(offset, PAGE, page.total, o => `/ui/experiments?offset=${o}`),
      csv,
    ),
    table(
      [
        ['id', 1],
        ['name'],
        ['domain'],
        ['strategy'],
        ['iteration', 1],
        ['trajectories', 1],
        ['transitions', 1],
        ['model version', 1],
        ['last activity'],
      ],
      rows,
      { id: 'experiments' },
    ),
  );
}

// ---------------------------------------------------------------- one experiment

function settingsCard(e) {
  const l = e.learning,
    m = e.mde;
  const space = sp =>
    sp.names.map((n, i) => `${n} ∈ [${fmt(sp.low[i])}, ${fmt(sp.high[i])}]`).join(', ') +
    (sp.values ? ` — values ${sp.values.map(v => vec(v)).join(' ')}` : '');
  const items = [
    ['domain', e.domain.kind],
    ['d_max', fmt(e.d_max)],
    ['seed', e.seed],
    [
      'strategy',
      l.strategy +
        (l.warmup_iterations > 0
          ? ` (active: random rollouts for the first ${l.warmup_iterations} iteration${l.warmup_iterations === 1 ? '' : 's'})`
          : ''),
    ],
    ['batch size', l.batch_size],
    ['iterations J', l.iterations],
    ['candidates × extensions', `${l.n_candidates} × ${l.max_extensions}`],
    [
      'acquisition',
      (l.acquisition === 'level_set'
        ? `level set, γ = ${fmt(l.gamma)}`
        : (l.acquisition === 'bottleneck'
            ? 'bottleneck, else '
            : l.acquisition === 'spread'
              ? 'spread (boundary σ removed over the space), ties by '
              : '') + `${l.aggregation}, c = ${fmt(l.c)}, γ = ${fmt(l.gamma)}`) +
        (l.batch_diversity ? '; a batch spreads over what is uncertain (σ in flight fantasised)' : ''),
    ],
    [
      'β schedule',
      `k1 = ${fmt(l.k1)}, k2 = ${fmt(l.k2)}; test β = ${fmt(l.test_beta)}` +
        (l.calibrate_test_beta ? ' at most (each model version certifies its own β: GET …/model, test_beta)' : '') +
        (l.local_test_margin
          ? '; test plans and judgements at each state-action’s locally calibrated β, at most the test β'
          : '') +
        (l.relax_beta ? '; a training problem with no plan at β_j is planned at lower β' : ''),
    ],
    ['preset', l.preset ?? 'paper (before presets)'],
    [
      'MDE',
      `${m.noise}, ${m.kernel === 'auto' ? 'kernel chosen at each fit by marginal likelihood (auto)' : `${m.kernel ?? 'matern52'} kernel`}, prior mean ${fmt(m.prior_mean)}, ${m.restarts} restarts, ` +
        (m.label_cap === 'auto'
          ? 'label cap chosen at each fit (auto)'
          : m.label_cap
            ? `labels capped at ${fmt(m.label_cap)} d_max`
            : 'raw labels') +
        `; ${estimatorText(m)}`,
    ],
    ['state space', space(e.state_space)],
    ['action space', space(e.action_space)],
    ['features', e.feature_names.join(', ')],
    ['created', e.created_at],
  ];
  const {
    id,
    state_space,
    action_space,
    feature_names,
    created_at,
    n_trajectories,
    n_transitions,
    iteration,
    model_version,
    last_activity,
    ...settings
  } = e;
  return h(
    'section',
    { class: 'card' },
    h('h2', {}, 'Settings'),
    h(
      'dl',
      { class: 'settings', id: 'settings' },
      items.flatMap(([k, v]) => [h('dt', {}, k), h('dd', {}, v)]),
    ),
    h('details', {}, h('summary', {}, 'All settings (JSON)'), h('pre', {}, JSON.stringify(settings, null, 2))),
  );
}

function progress(e) {
  const kpi = (label, value) => h('div', {}, h('b', {}, value), h('span', { class: 'muted' }, label));
  return h(
    'section',
    { class: 'card' },
    h('h2', {}, 'Progress'),
    h(
      'div',
      { class: 'kpi' },
      kpi('iteration', e.iteration),
      kpi('trajectories', e.n_trajectories),
      kpi('transitions', e.n_transitions),
      kpi('model version', e.model_version),
      kpi('refused requests', e.n_refused ?? 0),
      kpi('last activity', ago(e.last_activity)),
    ),
  );
}

function timelineCharts(e, t) {
  // One chart per spec [title, series name, value of a row, options (`bars` for the series, the
  // rest for the chart)], each row's value against its `x`.
  const over = (rows, xOf, xlabel, specs) => {
    const x = rows.map(xOf);
    return specs.map(([title, name, value, { bars, ...options } = {}]) =>
      lineChart({ title, x, xlabel, series: [{ name, values: rows.map(value), ...(bars && { bars }) }], ...options }),
    );
  };
  const charts = [];
  if (t.models.length) {
    charts.push(
      ...over(t.models, m => m.version, 'version', [
        ['Training transitions per model version', 'n_train', m => m.n_train],
        ['Log marginal likelihood per version', 'LML', m => m.log_marginal_likelihood],
        ['Fit seconds per version', 'seconds', m => m.fit_seconds],
      ]),
    );
  }
  if (t.iterations.length) {
    charts.push(
      ...over(t.iterations, r => r.iteration, 'iteration', [
        ['Trajectories per iteration', 'trajectories', r => r.n_trajectories, { bars: true }],
        ['Refused proposal requests per iteration', 'refused (no plan)', r => r.n_refused ?? 0, { bars: true }],
        [
          'β per iteration (learning schedule)',
          'β',
          r => r.beta,
          { refs: [{ y: e.learning.test_beta, label: 'test β' }] },
        ],
        ['Transitions within d_max per iteration', 'share', r => r.share_within_d_max, { yMin: 0, yMax: 1 }],
      ]),
    );
  }
  if (!charts.length) return h('p', { class: 'muted' }, 'No trajectories yet.');
  return h('div', { class: 'charts', id: 'timeline' }, charts);
}

function modelTable(t) {
  if (!t.models.length) return null;
  return h(
    'details',
    {},
    h('summary', {}, `Model versions (${t.models.length})`),
    table(
      [
        ['version', 1],
        ['iteration', 1],
        ['n_train', 1],
        ['trajectories', 1],
        ['noise'],
        ['label cap', 1],
        ['LML', 1],
        ['fit s', 1],
        ['fitted'],
      ],
      t.models.map(m =>
        h(
          'tr',
          {},
          td(m.version, true),
          td(m.iteration, true),
          td(m.n_train, true),
          td(m.n_trajectories, true),
          td(m.noise),
          td(m.label_cap == null ? '–' : m.label_cap === 0 ? 'raw' : `${fmt(m.label_cap)} d_max`, true),
          td(fmt(m.log_marginal_likelihood, 5), true),
          td(fmt(m.fit_seconds), true),
          td(ago(m.fitted_at)),
        ),
      ),
    ),
  );
}

/** The median of `values` (NaN for none). */
function median(values) {
  const v = [...values].sort((a, b) => a - b);
  if (!v.length) return NaN;
  const k = Math.floor(v.length / 2);
  return v.length % 2 ? v[k] : (v[k - 1] + v[k]) / 2;
}

/** The MDE settings' regressor in words (`mde.estimator`; absent before it existed: exact). */
export function estimatorText(m) {
  switch (m.estimator ?? 'exact') {
    case 'auto':
      return 'exact GP up to 3000 transitions, sparse GP beyond (auto)';
    case 'sparse':
      return `sparse GP, ${m.inducing_points} inducing points`;
    case 'local_experts':
      return `local experts: an exact GP per region of about ${m.expert_size ?? 300} transitions, each with its own hyperparameters`;
    default:
      return 'exact GP';
  }
}

/** Where a trajectory comes from, in one line: `dataset · episode 3 from step 0 · label`. */
export function sourceText(src) {
  if (!src) return null;
  const parts = [src.dataset];
  if (src.episode != null) parts.push(`episode ${src.episode}${src.first_step ? ` from step ${src.first_step}` : ''}`);
  if (src.label) parts.push(src.label);
  return parts.join(' · ');
}

/** What else a run says: a refusal's βs and extensions, a trajectory's source. */
function runDetails(r) {
  if (r.status === 'refused') {
    const betas = (r.betas_tried ?? []).map(b => fmt(b)).join(' → ');
    const why = r.refusal_reason === 'deadline_exceeded' ? 'past the planning deadline' : 'no plan';
    return h('span', { class: 'muted' }, `${why} at β ${betas} (${fmt(r.extensions)} extensions)`);
  }
  const src = sourceText(r.source);
  return src ? h('span', { class: 'source' }, src) : '';
}

function runsTable(e, page, offset) {
  const rows = page.items.map(r =>
    h(
      'tr',
      { class: r.deviating ? 'deviating' : null },
      td(ago(r.created_at)),
      td(r.proposal_id ?? '–', true),
      td(
        r.trajectory_id
          ? h('a', { href: `${expUrl(e.id)}/trajectories/${r.trajectory_id}` }, `#${r.trajectory_id} steps`)
          : '–',
      ),
      td(
        h(
          'span',
          {},
          h('span', { class: `badge ${r.status}` }, r.status),
          r.deviating ? ' ' : null,
          r.deviating
            ? h('span', { class: 'badge deviating', title: 'not the proposal as planned' }, 'deviating')
            : null,
          r.excluded_by != null ? ' ' : null,
          r.excluded_by != null
            ? h(
                'a',
                {
                  class: 'badge excluded',
                  href: `#exclusion-${r.excluded_by}`,
                  title: `left out of the model by exclusion #${r.excluded_by}`,
                },
                'excluded',
              )
            : null,
        ),
      ),
      td(r.client_id ?? '–'),
      td(r.iteration ?? '–', true),
      td(r.length, true),
      td(
        r.max_deviation === null
          ? '–'
          : h('span', { class: r.max_deviation >= e.d_max ? 'bad' : 'ok' }, fmt(r.max_deviation)),
        true,
      ),
      td(runDetails(r)),
    ),
  );
  return [
    pager(offset, PAGE, page.total, o => `${expUrl(e.id)}?offset=${o}#runs`),
    table(
      [
        ['when'],
        ['proposal', 1],
        ['trajectory'],
        ['status'],
        ['client'],
        ['iteration', 1],
        ['length', 1],
        ['max deviation', 1],
        ['details'],
      ],
      rows,
      { id: 'runs' },
    ),
  ];
}

/** What an exclusion covers, in a few words. */
function exclusionScope(x) {
  const n = x.trajectory_ids.length;
  const what = x.trajectory_id != null ? `trajectory #${x.trajectory_id}` : `stored ${x.since} to ${x.until}`;
  return `${what} (${n} ${n === 1 ? 'trajectory' : 'trajectories'}, ${x.n_transitions} transitions)`;
}

/** The exclusions: what was left out of the model, why, by whom, and whether the model agrees yet. */
function exclusionsTable(page) {
  if (page.total === 0) return [];
  const who = by => (by ? h('code', { title: 'SHA-256 of the token, first 12 hex digits' }, by) : '–');
  const rows = page.items.map(x =>
    h(
      'tr',
      { id: `exclusion-${x.id}`, class: x.status === 'restored' ? 'restored' : null },
      td(`#${x.id}`, true),
      td(exclusionScope(x)),
      td(x.reason),
      td(h('span', {}, ago(x.created_at), ' by ', who(x.created_by))),
      td(
        x.status === 'restored'
          ? h(
              'span',
              {},
              h('span', { class: 'badge restored' }, 'restored'),
              ' ',
              ago(x.restored_at),
              ' by ',
              who(x.restored_by),
            )
          : h('span', { class: 'badge excluded' }, 'in effect'),
      ),
      td(
        x.applied
          ? h('span', { class: 'ok' }, 'yes')
          : h('span', { class: 'muted', title: 'the refit it requested has not been swapped in yet' }, 'refit pending'),
      ),
    ),
  );
  const more =
    page.next != null ? [h('p', { class: 'muted' }, `the newest ${page.items.length} of ${page.total}`)] : [];
  return [
    h('h2', { id: 'exclusions-title' }, 'Left out of the model'),
    table([['exclusion', 1], ['what'], ['reason'], ['made'], ['status'], ['in the model answering']], rows, {
      id: 'exclusions',
    }),
    ...more,
  ];
}

/** Each of the robot's models with what its labels say, when the experiment has several. */
function robotModelsTable(e, labels) {
  if (!labels) return [];
  const pct = x => (x == null ? '–' : `${fmt(100 * x, 3)} %`);
  return [
    h('h2', { id: 'robot-models-title' }, "The robot's models and their labels"),
    table(
      [
        ['model'],
        ['kind'],
        ['cost per call', 1],
        ['labelled', 1],
        ['missing', 1],
        ['mean deviation', 1],
        ['largest', 1],
        [`within d_max = ${fmt(e.d_max)}`, 1],
      ],
      labels.items.map(m =>
        h(
          'tr',
          {},
          td(m.model),
          td(m.kind),
          td(fmt(m.cost), true),
          td(m.n_labelled, true),
          td(m.n_missing ? h('span', { class: 'bad' }, String(m.n_missing)) : '0', true),
          td(m.mean_deviation == null ? '–' : fmt(m.mean_deviation), true),
          td(m.max_deviation == null ? '–' : fmt(m.max_deviation), true),
          td(pct(m.share_within_d_max), true),
        ),
      ),
      { id: 'robot-models' },
    ),
  ];
}

export async function experimentPage(root, params, id) {
  const offset = Math.max(0, parseInt(params.get('offset') ?? '0', 10) || 0);
  const [e, t, runs, exclusions] = await Promise.all([
    api(`/v1/experiments/${id}`),
    api(`/v1/experiments/${id}/timeline`),
    api(`/v1/experiments/${id}/runs?offset=${offset}&limit=${PAGE}`),
    api(`/v1/experiments/${id}/exclusions?limit=${PAGE}`),
  ]);
  const labels = e.models ? await api(`/v1/experiments/${id}/labels`) : null;
  const name = e.name || `experiment ${id}`;
  crumbs([['Experiments', '/ui/experiments'], [name]]);
  root.replaceChildren(
    h('h1', {}, name, ' ', h('span', { class: 'muted' }, `#${id} · ${e.domain.kind}`)),
    h(
      'p',
      {},
      h('a', { href: `${expUrl(id)}/map` }, 'Precondition map'),
      ' · ',
      h('a', { href: `${expUrl(id)}/diagnostics` }, 'Model diagnostics'),
      ' · ',
      h('a', { href: `${API}/v1/experiments/${id}` }, 'JSON'),
    ),
    h('div', { class: 'row' }, settingsCard(e), progress(e)),
    h('h2', {}, 'Learning timeline'),
    timelineCharts(e, t),
    modelTable(t),
    ...robotModelsTable(e, labels),
    h('h2', { id: 'runs-title' }, 'Proposals, trajectories and refusals'),
    ...runsTable(e, runs, offset),
    ...exclusionsTable(exclusions),
  );
}

// ---------------------------------------------------------------- one trajectory

export async function trajectoryPage(root, params, id, tid) {
  const [e, t] = await Promise.all([api(`/v1/experiments/${id}`), api(`/v1/experiments/${id}/trajectories/${tid}`)]);
  const proposal = t.proposal_id ? await api(`/v1/experiments/${id}/proposals/${t.proposal_id}`) : null;
  const now = await api(`/v1/experiments/${id}/precondition`, { points: t.transitions.map(x => ({ s: x.s, a: x.a })) });
  const name = e.name || `experiment ${id}`;
  crumbs([['Experiments', '/ui/experiments'], [name, expUrl(id)], [`trajectory ${tid}`]]);
  const planned = proposal?.trajectory;
  const steps = t.transitions;
  // A proposal that stepped with several models says which model each step relied on.
  const stepModels = proposal?.step_models ?? null;
  const pm = i => (planned && i < planned.mu.length ? `${fmt(planned.mu[i])} ± ${fmt(planned.sigma[i])}` : '–');
  // The planned action at a step, when the executed one is not it (a deviating execution).
  const close = (x, p) =>
    x.length === p.length && x.every((v, k) => Math.abs(v - p[k]) <= 1e-6 * Math.max(1, Math.abs(p[k])));
  const offPlan = i =>
    planned && t.deviating && (i >= planned.actions.length || !close(steps[i].a, planned.actions[i]))
      ? (planned.actions[i] ?? null)
      : undefined;
  const rows = steps.map((x, i) =>
    h(
      'tr',
      {},
      td(x.step, true),
      td(vec(x.s)),
      td(
        offPlan(i) === undefined
          ? vec(x.a)
          : h('span', { class: 'bad', title: offPlan(i) ? `planned ${vec(offPlan(i))}` : 'beyond the plan' }, vec(x.a)),
      ),
      td(vec(x.s_pred)),
      td(vec(x.s_next)),
      td(h('span', { class: x.deviation >= e.d_max ? 'bad' : 'ok' }, fmt(x.deviation)), true),
      td(pm(i), true),
      ...(stepModels ? [td(stepModels[i] ?? '–')] : []),
      td(`${fmt(now.results[i].mu)} ± ${fmt(now.results[i].sigma)}`, true),
      td(now.results[i].inside ? 'inside' : 'outside'),
    ),
  );
  const idx = steps.map((_, i) => i);
  const series = [{ name: 'deviation', values: steps.map(x => x.deviation) }];
  if (planned) {
    const mu = idx.map(i => planned.mu[i] ?? NaN),
      sd = idx.map(i => planned.sigma[i] ?? NaN);
    series.push({
      name: `μ±σ (v${proposal.model_version})`,
      values: mu,
      band: [mu.map((m, i) => m - sd[i]), mu.map((m, i) => m + sd[i])],
    });
  } else {
    const mu = now.results.map(r => r.mu),
      sd = now.results.map(r => r.sigma);
    series.push({
      name: `μ±σ (v${now.model_version})`,
      values: mu,
      band: [mu.map((m, i) => m - sd[i]), mu.map((m, i) => m + sd[i])],
    });
  }
  root.replaceChildren(
    h(
      'h1',
      {},
      `Trajectory ${tid}`,
      ' ',
      h(
        'span',
        { class: 'muted' },
        `${steps.length} steps${t.partial ? ' · partial' : ''}${t.deviating ? ' · deviating' : ''}`,
      ),
    ),
    h(
      'p',
      {},
      proposal
        ? [
            'Executed proposal ',
            h('b', {}, `#${proposal.id}`),
            ` (iteration ${proposal.iteration}, β = ${fmt(proposal.beta)}${proposal.relaxed_from_beta != null ? ` relaxed from β_j = ${fmt(proposal.relaxed_from_beta)}` : ''}, ${proposal.strategy}${proposal.valued_by ? ` by ${proposal.valued_by}` : ''}, client ${proposal.client_id ?? '–'}); `,
            `μ ± σ "at the time" are the proposal's, from model version ${proposal.model_version}; "now" from version ${now.model_version}.`,
            ...(stepModels
              ? [
                  ` It stepped with ${proposal.models.join(', ')} (cheapest first): each step relied on the cheapest model whose precondition trusted it, and its μ ± σ at the time are that model's.`,
                ]
              : []),
          ]
        : `Posted without a proposal; μ ± σ are the current model's (version ${now.model_version}) — the version answering at ingest is not kept per trajectory.`,
    ),
    ...(t.deviating
      ? [
          h(
            'p',
            { id: 'deviating', class: 'bad' },
            'Deviating: the robot did not execute the proposal as planned (other actions, more steps or another start; actions off the plan are marked). Its labels are real data all the same.',
          ),
        ]
      : []),
    ...(t.source ? [h('p', { id: 'source' }, 'Source: ', h('b', {}, sourceText(t.source)))] : []),
    h(
      'div',
      { class: 'charts' },
      lineChart({
        title: 'Deviation per step',
        x: idx,
        xlabel: 'step',
        series,
        refs: [{ y: e.d_max, label: 'd_max' }],
      }),
    ),
    h('h2', {}, 'Steps'),
    table(
      [
        ['step', 1],
        ['s'],
        ['a'],
        ['predicted s′'],
        ['observed s′'],
        ['deviation', 1],
        ['μ ± σ at the time', 1],
        ...(stepModels ? [['model']] : []),
        ['μ ± σ now', 1],
        [`now (β=${fmt(now.beta)})`],
      ],
      rows,
      { id: 'steps' },
    ),
  );
}

// ---------------------------------------------------------------- precondition map

function gridMarks(e, m) {
  if (e.domain.kind !== 'icy_gridworld' || m.x.name !== 's.x' || m.y.name !== 's.y') return null;
  const nx = m.x.values.length,
    ny = m.y.values.length,
    marks = new Array(nx * ny).fill('.');
  for (let j = 0; j < ny; j++)
    for (let i = 0; i < nx; i++) marks[j * nx + i] = e.domain.map[m.y.values[j]]?.[m.x.values[i]] ?? '.';
  return marks;
}

const sameVec = (a, b) => a.length === b.length && a.every((x, i) => Math.abs(x - b[i]) < 1e-9);

export async function mapPage(root, params, id) {
  const e = await api(`/v1/experiments/${id}`);
  const name = e.name || `experiment ${id}`;
  crumbs([['Experiments', '/ui/experiments'], [name, expUrl(id)], ['precondition map']]);
  const S = e.state_space,
    A = e.action_space;
  const discrete = Array.isArray(A.values) && A.values.length > 0;
  const grid = e.domain.kind === 'icy_gridworld';
  // A custom domain's periodic state components (angles) are labelled in degrees.
  const periodic = new Set(e.domain.state?.periodic ?? []);
  const comps = S.names
    .map((n, i) => ({ name: `s.${n}`, low: S.low[i], high: S.high[i], action: false, i }))
    .concat(
      discrete ? [] : A.names.map((n, i) => ({ name: `a.${n}`, low: A.low[i], high: A.high[i], action: true, i })),
    );
  const state = {
    x: params.get('x') ?? comps[0].name,
    y: params.get('y') ?? comps[1]?.name ?? comps[0].name,
    s: S.low.map((l, i) => (grid ? Math.round((l + S.high[i]) / 2) : (l + S.high[i]) / 2)),
    a: discrete ? A.values[0] : A.low.map((l, i) => (l + A.high[i]) / 2),
    // Until the user moves a slider or picks a point, the fixed action is a typical move of the
    // training data (each component's median), not the middle of the bounds — often no move.
    typical: !discrete && !params.get('a'),
    beta: e.learning.test_beta,
    version: e.model_version,
    // Whose precondition: the domain's own model's, or one of the experiment's further models.
    model: params.get('model') ?? 'domain',
    res: 41,
    maps: [],
    span: null,
  };
  const panels = h('div', { class: 'panels', id: 'map-panels' });
  const status = h('span', { class: 'muted', id: 'map-status' });
  const legend = h('div');
  const fixed = h('div', { class: 'controls' });
  const opt = (v, sel) => h('option', { value: v, selected: v === sel }, v);
  // The choice of one axis (`x` or `y`) among the components; a change reloads the map.
  const axisSel = axis =>
    h(
      'select',
      {
        id: `map-${axis}`,
        onchange: ev => {
          state[axis] = ev.target.value;
          load();
        },
      },
      comps.map(c => opt(c.name, state[axis])),
    );
  const xSel = axisSel('x');
  const ySel = axisSel('y');
  const modelNames = ['domain', ...(e.models ?? []).map(m => m.name)];
  const modelSel =
    modelNames.length > 1
      ? h(
          'select',
          {
            id: 'map-model',
            onchange: ev => {
              state.model = ev.target.value;
              load();
            },
          },
          modelNames.map(n => opt(n, state.model)),
        )
      : null;
  const betaOut = h('output', {}, fmt(state.beta));
  const betaIn = h('input', {
    type: 'range',
    id: 'map-beta',
    min: -3,
    max: 5,
    step: 0.05,
    value: state.beta,
    oninput: ev => {
      state.beta = +ev.target.value;
      betaOut.textContent = fmt(state.beta);
      paint();
    },
  });
  const verOut = h('output', {}, `v${state.version}`);
  let timer = null;
  const verIn = h('input', {
    type: 'range',
    id: 'map-version',
    min: 0,
    max: e.model_version,
    step: 1,
    value: state.version,
    disabled: e.model_version === 0,
    oninput: ev => {
      state.version = +ev.target.value;
      verOut.textContent = `v${state.version}`;
      clearTimeout(timer);
      timer = setTimeout(load, 200);
    },
  });
  const resSel = h(
    'select',
    {
      onchange: ev => {
        state.res = +ev.target.value;
        load();
      },
      disabled: grid,
    },
    [21, 41, 81, 121].map(n => h('option', { value: n, selected: n === 41 }, n)),
  );

  function fixedControls() {
    const rows = [];
    for (const c of comps) {
      if (c.name === state.x || c.name === state.y) continue;
      const vecRef = c.action ? state.a : state.s;
      const out = h('output', {}, fmt(vecRef[c.i]));
      const step = grid && !c.action ? 1 : (c.high - c.low) / 100;
      rows.push(
        h('label', {}, c.name),
        h('input', {
          type: 'range',
          min: c.low,
          max: c.high,
          step,
          value: vecRef[c.i],
          oninput: ev => {
            state.typical = false;
            vecRef[c.i] = +ev.target.value;
            out.textContent = fmt(vecRef[c.i]);
            clearTimeout(timer);
            timer = setTimeout(load, 200);
          },
        }),
        out,
      );
    }
    fixed.replaceChildren(...rows);
  }

  /** A component's value in its units: degrees for an angle (a periodic state component). */
  function inUnits(name, v) {
    const c = comps.find(k => k.name === name);
    return c && !c.action && periodic.has(c.i) ? `${fmt((v * 180) / Math.PI)}°` : fmt(v);
  }

  /** The canvas between its axes: the grid's ends and middle in the components' units. */
  function mapAxes(m, canvas) {
    const ticks = (axis, cls) => {
      const v = axis.values,
        mid = v[Math.floor((v.length - 1) / 2)];
      return h(
        'div',
        { class: `map-ticks ${cls}`, 'data-axis': axis.name },
        ...[v[0], mid, v[v.length - 1]].map(t => h('span', {}, inUnits(axis.name, t))),
      );
    };
    return h(
      'div',
      { class: 'map-axes' },
      h('div', { class: 'map-name y' }, m.y.name),
      ticks(m.y, 'y'),
      canvas,
      h('div', {}),
      h('div', {}),
      ticks(m.x, 'x'),
      h('div', {}),
      h('div', {}),
      h('div', { class: 'map-name x' }, m.x.name),
    );
  }

  function paint() {
    if (!state.maps.length) return;
    const m0 = state.maps[0].m;
    if (state.span === null) {
      const dev = state.maps
        .flatMap(({ m }) => m.mu.map((mu, k) => Math.abs(mu + state.beta * m.sigma[k] - m.d_max)))
        .sort((a, b) => a - b);
      state.span = Math.max(m0.d_max, dev[Math.floor(dev.length * 0.9)] ?? m0.d_max);
    }
    legend.replaceChildren(colourLegend(m0.d_max, state.span));
    for (const p of state.maps) {
      const marks = gridMarks(e, p.m);
      const xc = comps.find(c => c.name === p.m.x.name),
        yc = comps.find(c => c.name === p.m.y.name);
      const get = (c, t) => (c.action ? t.a : t.s)[c.i];
      const pts = p.m.training
        .filter(t => !discrete || sameVec(t.a, p.a))
        .map((t, k) => ({
          x: get(xc, t),
          y: get(yc, t),
          deviation: t.deviation,
          t,
          jx: grid ? (((k * 7) % 9) - 4) * 1.3 : 0,
          jy: grid ? (((k * 5) % 9) - 4) * 1.3 : 0,
        }));
      const r = drawMap(p.canvas, p.m, state.beta, {
        cells: grid,
        marks,
        points: pts,
        span: state.span,
        size: grid ? 300 : 380,
        onPick: pt => {
          state.typical = false;
          state.s = [...pt.t.s];
          if (!discrete) state.a = [...pt.t.a];
          fixedControls();
          load();
        },
      });
      const inside = r.upper.filter(u => u < p.m.d_max).length;
      p.caption.textContent = `${fmt((100 * inside) / r.upper.length)} % of the grid inside · ${pts.length} training points`;
    }
  }

  async function load() {
    const actions = discrete ? A.values : [state.a];
    const side = name => {
      const c = comps.find(k => k.name === name);
      return grid && !c.action ? c.high - c.low + 1 : state.res;
    };
    status.textContent = 'loading…';
    // Ready again only when this load has drawn (a test waits for it; so may a user's script).
    delete document.body.dataset.mapReady;
    const query = a =>
      new URLSearchParams({
        x: state.x,
        y: state.y,
        s: state.s.join(','),
        a: a.join(','),
        nx: side(state.x),
        ny: side(state.y),
        version: state.version,
        ...(state.model !== 'domain' && { model: state.model }),
      });
    const maps = await Promise.all(actions.map(a => api(`/v1/experiments/${id}/precondition/map?${query(a)}`)));
    state.maps = maps.map((m, k) => {
      const canvas = h('canvas', { 'aria-label': `precondition map for action ${vec(actions[k])}` });
      const caption = h('div', { class: 'muted' });
      return { m, a: actions[k], canvas, caption };
    });
    panels.replaceChildren(
      ...state.maps.map(p =>
        h(
          'figure',
          { class: 'panel' },
          h(
            'h3',
            {},
            discrete
              ? `action ${A.names.map((n, i) => `${n}=${fmt(p.a[i])}`).join(', ')}`
              : `${p.m.y.name} against ${p.m.x.name}`,
          ),
          mapAxes(p.m, p.canvas),
          p.caption,
        ),
      ),
    );
    const m0 = maps[0];
    if (state.typical) {
      state.typical = false;
      const moves = m0.training.map(t => t.a);
      if (moves.length) {
        state.a = A.low.map((_, i) => median(moves.map(a => a[i])));
        fixedControls();
        return load();
      }
    }
    const whose = m0.model ? `, the precondition of ${m0.model}` : '';
    status.textContent = `model version ${m0.model_version} (${m0.source}, ${m0.n_train} training transitions${whose})`;
    panels.dataset.model = m0.model ?? 'domain';
    state.span = null;
    paint();
    document.body.dataset.mapReady = String(m0.model_version);
  }

  fixedControls();
  root.replaceChildren(
    h('h1', {}, 'Precondition map ', h('span', { class: 'muted' }, name)),
    h(
      'p',
      { class: 'muted' },
      `Colour: μ + βσ of the model deviation estimator; inside the precondition where it is below d_max = ${fmt(e.d_max)}. `,
      'Dots: training transitions, green where the model was right (deviation < d_max), red where not; click one to fix the other components at it.',
      grid ? ' Gridworld: each panel is the grid for one move; dark cells are obstacles, ≈ marks ice.' : '',
    ),
    h(
      'section',
      { class: 'card' },
      h(
        'div',
        { class: 'controls' },
        h('label', { for: 'map-x' }, 'x axis'),
        xSel,
        h('span'),
        h('label', { for: 'map-y' }, 'y axis'),
        ySel,
        h('span'),
        ...(modelSel ? [h('label', { for: 'map-model' }, 'model'), modelSel, h('span')] : []),
        h('label', { for: 'map-beta' }, 'β'),
        betaIn,
        betaOut,
        h('label', { for: 'map-version' }, 'model version'),
        verIn,
        verOut,
        h('label', {}, 'grid points per side'),
        resSel,
        h('span'),
      ),
      h('h3', {}, 'Other components'),
      fixed,
      status,
    ),
    legend,
    panels,
  );
  await load();
}

// ---------------------------------------------------------------- diagnostics

function laterCard(d, pct, kpi) {
  const l = d.later;
  if (!l)
    return h(
      'section',
      { class: 'card' },
      h('h2', {}, 'Later transitions'),
      h('p', { class: 'muted' }, `No transitions were posted after version ${d.model_version}'s training set yet.`),
    );
  const c1 = l.coverage.find(c => c.z === 1),
    c2 = l.coverage.find(c => c.z === 2);
  return h(
    'section',
    { class: 'card', id: 'later' },
    h('h2', {}, `The ${l.n} transitions posted after its training set (never seen by version ${d.model_version})`),
    h(
      'div',
      { class: 'kpi' },
      kpi('TPR', pct(l.tpr), `${l.true_positives} of ${l.positives} below d_max judged inside`),
      kpi('TNR', pct(l.tnr), `${l.true_negatives} of ${l.negatives} at or above d_max judged outside`),
      kpi('inside μ ± 1σ', pct(c1.observed), `nominal ${pct(c1.nominal)}`),
      kpi('inside μ ± 2σ', pct(c2.observed), `nominal ${pct(c2.nominal)}`),
    ),
  );
}

export async function diagnosticsPage(root, params, id) {
  const [e, t] = await Promise.all([api(`/v1/experiments/${id}`), api(`/v1/experiments/${id}/timeline`)]);
  const name = e.name || `experiment ${id}`;
  crumbs([['Experiments', '/ui/experiments'], [name, expUrl(id)], ['diagnostics']]);
  const out = h('div', { id: 'diagnostics' });
  const versions = t.models.map(m => m.version);
  const state = { version: +(params.get('version') ?? e.model_version), beta: e.learning.test_beta };
  const verSel = h(
    'select',
    {
      onchange: ev => {
        state.version = +ev.target.value;
        load();
      },
    },
    versions.map(v => h('option', { value: v, selected: v === state.version }, `v${v}`)),
  );
  const betaIn = h('input', {
    type: 'number',
    step: 0.1,
    value: state.beta,
    onchange: ev => {
      state.beta = +ev.target.value;
      load();
    },
  });

  async function load() {
    out.replaceChildren(h('p', { class: 'muted' }, 'computing leave-one-out predictions…'));
    const d = await api(`/v1/experiments/${id}/model/diagnostics?version=${state.version}&beta=${state.beta}`);
    const pct = x => (x === null ? '–' : `${fmt(100 * x, 3)} %`);
    const c1 = d.coverage.find(c => c.z === 1),
      c2 = d.coverage.find(c => c.z === 2);
    const kpi = (label, value, note) =>
      h(
        'div',
        {},
        h('b', {}, value),
        h('span', { class: 'muted' }, label),
        note ? h('div', { class: 'muted' }, note) : null,
      );
    const p = d.precondition;
    out.replaceChildren(
      h(
        'section',
        { class: 'card' },
        h('h2', {}, `Calibration of version ${d.model_version} (leave-one-out, ${d.n} labels)`),
        h(
          'div',
          { class: 'kpi' },
          kpi('inside μ ± 1σ', pct(c1.observed), `nominal ${pct(c1.nominal)}`),
          kpi('inside μ ± 2σ', pct(c2.observed), `nominal ${pct(c2.nominal)}`),
          kpi('RMSE', fmt(d.rmse)),
          kpi('mean log density', fmt(d.mean_log_density)),
        ),
      ),
      h(
        'section',
        { class: 'card' },
        h('h2', {}, `Precondition μ + ${fmt(p.beta)}σ < ${fmt(p.d_max)} against the labels`),
        h(
          'div',
          { class: 'kpi' },
          kpi('TPR', pct(p.tpr), `${p.true_positives} of ${p.positives} labels below d_max judged inside`),
          kpi('TNR', pct(p.tnr), `${p.true_negatives} of ${p.negatives} labels at or above d_max judged outside`),
        ),
      ),
      laterCard(d, pct, kpi),
      h(
        'div',
        { class: 'charts' },
        lineChart({
          title: 'Coverage of μ ± zσ: observed against nominal',
          x: d.coverage.map(c => c.nominal),
          xlabel: 'nominal share',
          yMin: 0,
          yMax: 1,
          diagonal: true,
          series: [{ name: 'observed', values: d.coverage.map(c => c.observed) }],
        }),
      ),
      table(
        [
          ['z', 1],
          ['nominal', 1],
          ['observed', 1],
        ],
        d.coverage.map(c => h('tr', {}, td(fmt(c.z), true), td(pct(c.nominal), true), td(pct(c.observed), true))),
      ),
    );
  }

  root.replaceChildren(
    h('h1', {}, 'Model diagnostics ', h('span', { class: 'muted' }, name)),
    h(
      'p',
      { class: 'muted' },
      'Each training label is predicted by the model conditioned on all the others (closed-form leave-one-out, same hyperparameters). ',
      'A calibrated model has about 68 % of labels inside μ ± 1σ and 95 % inside μ ± 2σ. TPR/TNR: how often "inside the precondition" agrees with the truth deviation < d_max.',
    ),
    h(
      'section',
      { class: 'card' },
      h(
        'div',
        { class: 'controls' },
        h('label', {}, 'model version'),
        verSel,
        h('span'),
        h('label', {}, 'β'),
        betaIn,
        h('span'),
      ),
    ),
    out,
  );
  if (!versions.length) {
    out.replaceChildren(h('p', { class: 'muted' }, 'No fitted model yet: the prior has no labels to check.'));
    return;
  }
  await load();
}

export async function notFound(root) {
  crumbs([['Not found']]);
  root.replaceChildren(h('h1', {}, 'Not found'), h('p', {}, h('a', { href: '/ui/experiments' }, 'Experiments')));
}
