// Small SVG charts and the canvas precondition map; no libraries.
import { h } from './dom.js';
import { fmt } from './format.js';

const SVG = 'http://www.w3.org/2000/svg';
function s(tag, attrs = {}, ...children) {
  const el = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) if (v !== undefined && v !== null) el.setAttribute(k, v);
  for (const c of children) el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  return el;
}

function ticks(lo, hi, n = 5) {
  if (!(hi > lo)) return [lo];
  const step0 = (hi - lo) / n,
    mag = 10 ** Math.floor(Math.log10(step0));
  const step = [1, 2, 5, 10].map(k => k * mag).find(k => k >= step0);
  const out = [];
  for (let t = Math.ceil(lo / step) * step; t <= hi + step * 1e-9; t += step) out.push(Number(t.toPrecision(12)));
  return out;
}

/**
 * A line (or bar) chart: `{title, x: [...], series: [{name, values, band?: [lo[], hi[]], bars?}],
 * xlabel, ylabel, refs: [{y, label}], yMin, yMax, diagonal}`.
 */
export function lineChart(o) {
  const W = 360,
    H = 200,
    L = 46,
    R = 10,
    T = 8,
    B = 30;
  const xs = o.x;
  const all = o.series
    .flatMap(se => [...se.values, ...(se.band ? se.band.flat() : [])])
    .concat((o.refs ?? []).map(r => r.y))
    .filter(Number.isFinite);
  let yMin = o.yMin ?? Math.min(...all),
    yMax = o.yMax ?? Math.max(...all);
  if (o.series.some(se => se.bars)) yMin = Math.min(0, yMin);
  if (!(yMax > yMin)) {
    yMax = yMin + 1;
    yMin -= 1;
  }
  let xMin = Math.min(...xs),
    xMax = Math.max(...xs);
  const barPad = o.series.some(se => se.bars) ? 0.5 : 0;
  xMin -= barPad;
  xMax += barPad;
  if (!(xMax > xMin)) {
    xMax = xMin + 1;
    xMin -= 1;
  }
  const X = v => L + ((v - xMin) / (xMax - xMin)) * (W - L - R);
  const Y = v => T + (1 - (v - yMin) / (yMax - yMin)) * (H - T - B);
  const svg = s('svg', { viewBox: `0 0 ${W} ${H}`, role: 'img', 'aria-label': o.title });
  for (const t of ticks(yMin, yMax, 4)) {
    svg.append(s('line', { class: 'grid', x1: L, x2: W - R, y1: Y(t), y2: Y(t) }));
    svg.append(s('text', { x: L - 4, y: Y(t) + 3, 'text-anchor': 'end' }, fmt(t, 3)));
  }
  for (const t of ticks(xMin, xMax, 5)) {
    svg.append(s('text', { x: X(t), y: H - B + 13, 'text-anchor': 'middle' }, fmt(t, 3)));
  }
  svg.append(s('line', { class: 'axis', x1: L, x2: W - R, y1: H - B, y2: H - B }));
  svg.append(s('line', { class: 'axis', x1: L, x2: L, y1: T, y2: H - B }));
  if (o.xlabel) svg.append(s('text', { x: (L + W - R) / 2, y: H - 3, 'text-anchor': 'middle' }, o.xlabel));
  if (o.diagonal)
    svg.append(
      s('line', {
        class: 'ref',
        x1: X(Math.max(xMin, yMin)),
        y1: Y(Math.max(xMin, yMin)),
        x2: X(Math.min(xMax, yMax)),
        y2: Y(Math.min(xMax, yMax)),
      }),
    );
  for (const r of o.refs ?? []) {
    svg.append(s('line', { class: 'ref', x1: L, x2: W - R, y1: Y(r.y), y2: Y(r.y) }));
    svg.append(s('text', { x: W - R - 2, y: Y(r.y) - 3, 'text-anchor': 'end' }, r.label));
  }
  o.series.forEach((se, k) => {
    const cls = `series-${k}`;
    const pts = xs.map((x, i) => [x, se.values[i]]).filter(([, y]) => Number.isFinite(y));
    if (se.band) {
      const [lo, hi] = se.band;
      const up = xs.map((x, i) => `${X(x)},${Y(hi[i])}`),
        down = xs.map((x, i) => `${X(x)},${Y(lo[i])}`).reverse();
      svg.append(s('polygon', { class: 'band', points: up.concat(down).join(' ') }));
    }
    if (se.bars) {
      const bw = Math.max(1, (X(1) - X(0)) * 0.7);
      for (const [x, y] of pts)
        svg.append(
          s('rect', {
            class: cls,
            x: X(x) - bw / 2,
            y: Math.min(Y(y), Y(0)),
            width: bw,
            height: Math.abs(Y(0) - Y(y)),
            'fill-opacity': 0.7,
            stroke: 'none',
          }),
        );
    } else {
      svg.append(
        s('polyline', {
          class: cls,
          fill: 'none',
          'stroke-width': 1.6,
          points: pts.map(([x, y]) => `${X(x)},${Y(y)}`).join(' '),
        }),
      );
      if (pts.length <= 60)
        for (const [x, y] of pts) svg.append(s('circle', { class: cls, cx: X(x), cy: Y(y), r: 2.2 }));
    }
  });
  if (o.series.length > 1) {
    o.series.forEach((se, k) =>
      svg.append(s('text', { class: `legend series-${k}`, x: L + 6 + k * 90, y: T + 9, stroke: 'none' }, se.name)),
    );
  }
  return h('figure', { class: 'chart' }, h('h3', {}, o.title), svg);
}

// Diverging colours around d_max: inside the precondition (upper < d_max) blue-green, outside
// orange-red; the further from d_max, the darker.
function colour(upper, dMax, span) {
  const t = Math.max(-1, Math.min(1, (upper - dMax) / span));
  if (t < 0) {
    const k = -t;
    return [Math.round(235 - 190 * k), Math.round(245 - 95 * k), Math.round(235 - 120 * k)];
  }
  return [Math.round(250 - 40 * t), Math.round(235 - 175 * t), Math.round(215 - 180 * t)];
}

/** A colour legend for the map. */
export function colourLegend(dMax, span) {
  const c = h('canvas', { width: 200, height: 12 });
  const g = c.getContext('2d');
  for (let i = 0; i < 200; i++) {
    const [r, gg, b] = colour(dMax - span + (2 * span * i) / 199, dMax, span);
    g.fillStyle = `rgb(${r},${gg},${b})`;
    g.fillRect(i, 0, 1, 12);
  }
  return h(
    'div',
    { class: 'legend-bar' },
    h('span', {}, `μ+βσ ≤ ${fmt(dMax - span)}`),
    c,
    h('span', {}, `≥ ${fmt(dMax + span)} (d_max = ${fmt(dMax)} at the centre; black line: the d_max contour)`),
  );
}

/** Segments of the `level` contour of `f` (row-major `ny × nx`) by marching squares, in grid units. */
function contour(f, nx, ny, level) {
  const segs = [];
  const at = (i, j) => f[j * nx + i] - level;
  const lerp = (a, b) => a / (a - b);
  for (let j = 0; j + 1 < ny; j++)
    for (let i = 0; i + 1 < nx; i++) {
      const v = [at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)];
      const e = [];
      // Edges: bottom (0-1), right (1-2), top (2-3), left (3-0), in grid coordinates.
      if (v[0] < 0 !== v[1] < 0) e.push([i + lerp(v[0], v[1]), j]);
      if (v[1] < 0 !== v[2] < 0) e.push([i + 1, j + lerp(v[1], v[2])]);
      if (v[2] < 0 !== v[3] < 0) e.push([i + 1 - lerp(v[2], v[3]), j + 1]);
      if (v[3] < 0 !== v[0] < 0) e.push([i, j + 1 - lerp(v[3], v[0])]);
      if (e.length === 2) segs.push(e);
      else if (e.length === 4) {
        segs.push([e[0], e[1]]);
        segs.push([e[2], e[3]]);
      }
    }
  return segs;
}

/**
 * Draws one map panel on a canvas: `upper = μ + βσ` coloured around d_max, its d_max contour,
 * optional cell marks (`marks[j*nx+i]` = '#', '~'), and training points `[{x, y, deviation}]`.
 * `onPick(point)` is called when a training point is clicked.
 */
export function drawMap(canvas, m, beta, opts = {}) {
  const nx = m.x.values.length,
    ny = m.y.values.length;
  const upper = m.mu.map((mu, k) => mu + beta * m.sigma[k]);
  const size = opts.size ?? 360,
    cell = opts.cells;
  const W = (canvas.width = size),
    H = (canvas.height = Math.round(size * (opts.aspect ?? 1)));
  const g = canvas.getContext('2d');
  const [x0, x1] = [m.x.values[0], m.x.values[nx - 1]],
    [y0, y1] = [m.y.values[0], m.y.values[ny - 1]];
  // Grid point (i, j) sits at the centre of its pixel block for cell maps, on the corners otherwise.
  const px = cell ? i => ((i + 0.5) * W) / nx : i => (i * (W - 1)) / (nx - 1);
  const py = cell ? j => H - ((j + 0.5) * H) / ny : j => H - 1 - (j * (H - 1)) / (ny - 1);
  const X = x => px(((x - x0) / (x1 - x0)) * (nx - 1));
  const Y = y => py(((y - y0) / (y1 - y0)) * (ny - 1));
  const span = opts.span;
  if (cell) {
    for (let j = 0; j < ny; j++)
      for (let i = 0; i < nx; i++) {
        const [r, gg, b] = colour(upper[j * nx + i], m.d_max, span);
        g.fillStyle = `rgb(${r},${gg},${b})`;
        g.fillRect(Math.floor((i * W) / nx), Math.floor(H - ((j + 1) * H) / ny), Math.ceil(W / nx), Math.ceil(H / ny));
      }
  } else {
    // Bilinear colours: paint at grid resolution, then scale up smoothly.
    const img = new ImageData(nx, ny);
    for (let j = 0; j < ny; j++)
      for (let i = 0; i < nx; i++) {
        const [r, gg, b] = colour(upper[j * nx + i], m.d_max, span),
          o = ((ny - 1 - j) * nx + i) * 4;
        img.data.set([r, gg, b, 255], o);
      }
    const tmp = document.createElement('canvas');
    tmp.width = nx;
    tmp.height = ny;
    tmp.getContext('2d').putImageData(img, 0, 0);
    g.imageSmoothingEnabled = true;
    g.drawImage(tmp, 0, 0, W, H);
  }
  if (opts.marks) {
    g.font = `${Math.floor(Math.min(W / nx, H / ny) * 0.6)}px sans-serif`;
    g.textAlign = 'center';
    g.textBaseline = 'middle';
    for (let j = 0; j < ny; j++)
      for (let i = 0; i < nx; i++) {
        const c = opts.marks[j * nx + i];
        if (c === '#') {
          g.fillStyle = '#39404d';
          g.fillRect(
            Math.floor((i * W) / nx) + 2,
            Math.floor(H - ((j + 1) * H) / ny) + 2,
            Math.ceil(W / nx) - 4,
            Math.ceil(H / ny) - 4,
          );
        } else if (c === '~') {
          g.fillStyle = 'rgba(40,110,200,.55)';
          g.fillText('≈', px(i), py(j));
        }
      }
  }
  g.strokeStyle = '#111';
  g.lineWidth = 2;
  g.beginPath();
  for (const [[ai, aj], [bi, bj]] of contour(upper, nx, ny, m.d_max)) {
    g.moveTo(px(ai), py(aj));
    g.lineTo(px(bi), py(bj));
  }
  g.stroke();
  const pts = opts.points ?? [];
  for (const p of pts) {
    g.beginPath();
    g.arc(X(p.x) + (p.jx ?? 0), Y(p.y) + (p.jy ?? 0), 3.2, 0, 2 * Math.PI);
    g.fillStyle = p.deviation < m.d_max ? '#17803f' : '#d12d12';
    g.fill();
    g.lineWidth = 0.8;
    g.strokeStyle = '#fff';
    g.stroke();
  }
  if (opts.onPick) {
    canvas.onclick = ev => {
      const r = canvas.getBoundingClientRect(),
        cx = ((ev.clientX - r.left) * W) / r.width,
        cy = ((ev.clientY - r.top) * H) / r.height;
      let best = null,
        bd = 64;
      for (const p of pts) {
        const d = (X(p.x) - cx) ** 2 + (Y(p.y) - cy) ** 2;
        if (d < bd) {
          bd = d;
          best = p;
        }
      }
      if (best) opts.onPick(best);
    };
  }
  return { upper };
}
