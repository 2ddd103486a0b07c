// DOM building: elements from data (text always as text) and the page's breadcrumbs.

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

/** Sets the breadcrumbs: `[[text, href], …, [text]]`. */
export function crumbs(items) {
  const nav = document.getElementById('crumbs');
  nav.replaceChildren(...items.map(([text, href]) => (href ? h('a', { href }, text) : h('span', {}, text))));
  document.title = items
    .map(i => i[0])
    .reverse()
    .concat('precond')
    .join(' · ');
}
