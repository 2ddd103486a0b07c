// precond dashboard: the entry point. Routes the address to a page and shows its errors; the
// helpers are in api.js (the JSON API), dom.js (elements) and format.js (numbers and times), and
// nothing imports this module.
import { API, ApiError } from './api.js';
import { h } from './dom.js';
import * as pages from './pages.js';

// After api.js has taken any `?token=` out of the address.
const params = new URLSearchParams(location.search);

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
    root.replaceChildren(
      h(
        'div',
        { class: 'error', role: 'alert' },
        e instanceof ApiError ? `${e.status} ${e.code ?? ''}: ${e.message}` : `Error: ${e.message}`,
      ),
    );
  }
  performance.mark('dashboard-ready');
  document.body.dataset.ready = 'true';
}

main();
