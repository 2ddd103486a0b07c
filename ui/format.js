// Numbers, vectors and times for people.
import { h } from './dom.js';

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
  const text = !isFinite(s)
    ? t
    : s < 60
      ? `${Math.max(0, Math.round(s))} s ago`
      : s < 3600
        ? `${Math.round(s / 60)} min ago`
        : s < 86400
          ? `${Math.round(s / 3600)} h ago`
          : `${Math.round(s / 86400)} d ago`;
  return h('time', { datetime: t, title: t }, text);
}
