// The `statechart` widget: a state machine's diagram (`M.diagram`, an SVG with the states of
// `M.state` marked), shown live, with the machine's start, stop and event controls beside it.
//
// `M.diagram` changes with every stable configuration, and the service view follows it on the
// page's one event stream, so `update` gets each new SVG. The SVG text is never parsed into the
// page: it is the source of an <img> as a data: URL, and an image runs no script and loads
// nothing (a browser renders an SVG image in its static, secure mode).

/** Longest SVG text shown: the longest property value (65,536 characters). */
export const MAX_SVG_LENGTH = 65536;

/** The SVG text as a data: URL for an <img>; null when there is nothing to show. */
export function svgDataUrl(text) {
  if (typeof text !== 'string') return null;
  const body = text.trim();
  if (!body || body.length > MAX_SVG_LENGTH || !/^(<\?xml[^>]*>\s*)?<svg[\s>]/.test(body)) return null;
  return `data:image/svg+xml;charset=utf-8,${encodeURIComponent(body)}`;
}

/** The machine a `M.diagram` path belongs to (`patrol.diagram` -> `patrol`); null for any other path. */
export function machineOf(path) {
  const match = /^(.+)\.diagram$/.exec(path ?? '');
  return match ? match[1] : null;
}

/** The active state ids marked in the SVG text (`data-state` of each group with class `active`). */
export function activeStates(text) {
  const found = [];
  const tags = String(text ?? '').match(/<g\b[^>]*>/g) ?? [];
  for (const tag of tags) {
    const cls = /\bclass="([^"]*)"/.exec(tag)?.[1] ?? '';
    const id = /\bdata-state="([^"]*)"/.exec(tag)?.[1];
    if (id && cls.split(/\s+/).includes('active')) found.push(id);
  }
  return found;
}

/**
 * The widget factory: `statechartWidget(prop, ctx)` -> {element, update, hidesValue}.
 * Controls (for `M.diagram` of a state machine service): Start, Stop, and an event name with Send,
 * each a Set of `M.start`, `M.stop`, `M.events` through `ctx.setPath`.
 */
export function statechartWidget(prop, ctx) {
  const { h } = ctx;
  const machine = machineOf(ctx.path);
  const image = h('img', {
    class: 'statechart-image',
    alt: `statechart of ${machine ?? ctx.path}`,
    hidden: true,
  });
  const empty = h('span', { class: 'muted statechart-empty' }, 'no chart loaded');
  const active = h('output', { class: 'statechart-active', 'aria-live': 'polite' });
  const children = [image, empty, active];
  if (machine !== null && typeof ctx.setPath === 'function') {
    const eventName = h('input', {
      type: 'text',
      class: 'statechart-event',
      'aria-label': `event for ${machine}`,
      placeholder: 'event',
      spellcheck: 'false',
    });
    const send = () => {
      const name = eventName.value.trim();
      if (name) ctx.setPath(`${machine}.events`, name);
    };
    eventName.addEventListener('keydown', (e) => {
      if (e.key === 'Enter') send();
    });
    children.push(
      h(
        'div',
        { class: 'statechart-controls' },
        h('button', { type: 'button', dataset: { action: 'start' }, onclick: () => ctx.setPath(`${machine}.start`, '') }, 'Start'),
        h('button', { type: 'button', dataset: { action: 'stop' }, onclick: () => ctx.setPath(`${machine}.stop`, '') }, 'Stop'),
        eventName,
        h('button', { type: 'button', dataset: { action: 'send' }, onclick: send }, 'Send'),
      ),
    );
  }
  return {
    element: h('div', { class: 'statechart' }, ...children),
    // The SVG replaces the value text the frame would show (a page of markup).
    hidesValue: true,
    update(text) {
      const url = svgDataUrl(text);
      image.hidden = url === null;
      empty.hidden = url !== null;
      if (url === null) image.removeAttribute('src');
      else image.setAttribute('src', url);
      const states = activeStates(text);
      active.textContent = states.length ? `active: ${states.join(' ')}` : '';
    },
  };
}
