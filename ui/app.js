// precond dashboard: routing, the API client and DOM helpers. Reads only the public JSON API.
import * as pages from './pages.js';

// The API's origin: this server by default; `?api=http://host:port` points the dashboard at
// another server (remembered in this browser; `?api=` alone forgets it).
const params = new URLSearchParams(location.search);
if (params.has('api')) {
  const api = params.get('api').replace(/\/+$/, '');
  if (api) localStorage.setItem('precond.api', api); else localStorage.removeItem('precond.api');
}
export const API = localStorage.getItem('precond.api') || '';

// A read token for a server started with `--token-file`: `?token=…` once (kept for this tab
// only, and taken out of the address bar so it does not stay in the history).
if (params.has('token')) {
  const token = params.get('token');
  if (token) sessionStorage.setItem('precond.token', token); else sessionStorage.removeItem('precond.token');
  params.delete('token');
  const rest = params.toString();
  history.replaceState(null, '', location.pathname + (rest ? `?${rest}` : '') + location.hash);
}
const TOKEN = sessionStorage.getItem('precond.token');

/** An API error with the server's `{"error": {code, message}}`. */
export class ApiError extends Error {
  constructor(status, body) {
    super(body?.error?.message ?? `HTTP ${status}`);
    this.status = status;
    this.code = body?.error?.code;
  }
}

/** GET (or POST with `body`) a JSON API path. */
export async function api(path, body) {
  const headers = TOKEN ? { authorization: `Bearer ${TOKEN}` } : {};
  const init = body === undefined ? { headers } : {
    method: 'POST', headers: { ...headers, 'content-type': 'application/json' }, body: JSON.stringify(body),
  };
  const r = await fetch(API + path, init);
  const json = await r.json().catch(() => null);
  if (!r.ok) throw new ApiError(r.status, json);
  return json;
}

/** `h('a', {href}, 'text', child…)`: an element; text is always set as text, never as HTML. */
export function h(tag, attrs = {}, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs ?? {})) {
    if (v === undefined || v === null || v === false) continue;
    if (k.startsWith('on')) el.addEventListener(k.slice(2), v);
    else if (k === 'class') el.className = v;
    else el.setAttribute(k, v === true ? '' : v);
  }
  for (const c of children.flat()) {
    if (c === undefined || c === null || c === false) continue;
    el.append(c instanceof Node ? c : String(c));
  }
  return el;
}

/** A number for people: `digits` significant digits, integers as they are. */
export function fmt(x, digits = 3) {
  if (x === null || x === undefined) return '–';
  if (typeof x !== 'number') return String(x);
  if (Number.isInteger(x) && Math.abs(x) < 1e7) return String(x);
  if (x !== 0 && (Math.abs(x) < 1e-3 || Math.abs(x) >= 1e6)) return x.toExponential(digits - 1);
  return String(Number(x.toPrecision(digits)));
}

export const vec = (v, digits = 3) => '[' + v.map(x => fmt(x, digits)).join(', ') + ']';

/** "3 min ago" for an RFC 3339 time, with the exact time as a tooltip. */
export function ago(t) {
  const s = (Date.now() - Date.parse(t)) / 1000;
  const text = !isFinite(s) ? t : s < 60 ? `${Math.max(0, Math.round(s))} s ago`
    : s < 3600 ? `${Math.round(s / 60)} min ago` : s < 86400 ? `${Math.round(s / 3600)} h ago`
    : `${Math.round(s / 86400)} d ago`;
  return h('time', { datetime: t, title: t }, text);
}

/** Sets the breadcrumbs: `[[text, href], …, [text]]`. */
export function crumbs(items) {
  const nav = document.getElementById('crumbs');
  nav.replaceChildren(...items.map(([text, href]) => href ? h('a', { href }, text) : h('span', {}, text)));
  document.title = items.map(i => i[0]).reverse().concat('precond').join(' · ');
}

function route() {
  const path = location.pathname.replace(/\/+$/, '') || '/';
  let m;
  if (path === '/' || path === '/ui' || path === '/ui/experiments') return [pages.experimentList];
  if ((m = path.match(/^\/ui\/experiments\/(\d+)$/))) return [pages.experimentPage, +m[1]];
  if ((m = path.match(/^\/ui\/experiments\/(\d+)\/trajectories\/(\d+)$/))) return [pages.trajectoryPage, +m[1], +m[2]];
  if ((m = path.match(/^\/ui\/experiments\/(\d+)\/map$/))) return [pages.mapPage, +m[1]];
  if ((m = path.match(/^\/ui\/experiments\/(\d+)\/diagnostics$/))) return [pages.diagnosticsPage, +m[1]];
  return [pages.notFound];
}

async function main() {
  const origin = document.getElementById('api-origin');
  origin.textContent = API ? `API: ${API}` : '';
  const root = document.getElementById('app');
  const [page, ...args] = route();
  try {
    await page(root, params, ...args);
  } catch (e) {
    console.error(e);
    root.replaceChildren(h('div', { class: 'error', role: 'alert' },
      e instanceof ApiError ? `${e.status} ${e.code ?? ''}: ${e.message}` : `Error: ${e.message}`));
  }
  performance.mark('dashboard-ready');
  document.body.dataset.ready = 'true';
}

main();
