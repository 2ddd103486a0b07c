// The JSON API: where it is (this server, or `?api=`), the read token (`?token=`) and the client.
// Reads both from the address when first imported, before any page runs.

// The API's origin: this server by default; `?api=http://host:port` points the dashboard at
// another server (remembered in this browser; `?api=` alone forgets it).
const params = new URLSearchParams(location.search);
if (params.has('api')) {
  const api = params.get('api').replace(/\/+$/, '');
  if (api) localStorage.setItem('precond.api', api);
  else localStorage.removeItem('precond.api');
}
export const API = localStorage.getItem('precond.api') || '';

// A read token for a server started with `--token-file`: `?token=…` once (kept for this tab
// only, and taken out of the address bar so it does not stay in the history).
if (params.has('token')) {
  const token = params.get('token');
  if (token) sessionStorage.setItem('precond.token', token);
  else sessionStorage.removeItem('precond.token');
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
  const init =
    body === undefined
      ? { headers }
      : {
          method: 'POST',
          headers: { ...headers, 'content-type': 'application/json' },
          body: JSON.stringify(body),
        };
  const r = await fetch(API + path, init);
  const json = await r.json().catch(() => null);
  if (!r.ok) throw new ApiError(r.status, json);
  return json;
}
