// The cluster page: every gateway of a cluster as a card (address, version, health, state, devices
// owned, load, lease), who owns each device and since when, and the admin's drain, undrain and
// rebalance. Everything is the registry's: `cluster` (JSON, followed live), `services.*.owner` and
// `services.*.owner_since` (followed live), and the actions `cluster.drain`, `cluster.undrain`,
// `cluster.rebalance` (docs/scale-out.md, "Operating a cluster").

import { setProperty } from './api.js';
import { h, clear } from './dom.js';
import { EventMux } from './events.js';

/** Devices listed in the table at most; the rest are counted (the registry may hold thousands). */
export const MAX_ROWS = 500;
const CONNECTION_TEXT = { open: 'live', connecting: 'connecting…', closed: 'disconnected' };

const $ = (selector) => {
  const el = document.querySelector(selector);
  if (!el) throw new Error(`the page lacks ${selector}`);
  return el;
};

/** The state word a member shows: draining, read-only or serving. */
export function memberState(member) {
  if (member.draining) return 'draining';
  if (member.read_only) return 'read-only';
  return 'serving';
}

/** "in 3.2 s", "3.2 s ago" or "-" for a lease expiry (unix seconds) seen at `now` (unix seconds). */
export function leaseText(expires, now) {
  if (!expires) return '-';
  const left = expires - now;
  return left >= 0 ? `in ${left.toFixed(1)} s` : `${(-left).toFixed(1)} s ago`;
}

function status(text, isError = false) {
  const el = $('#status');
  el.textContent = text;
  el.classList.toggle('error-text', isError);
}

async function act(action, gateway = '') {
  try {
    const answer = await setProperty('registry', `cluster.${action}`, gateway);
    status('');
    $('#cluster-summary').dataset.lastAction = `${action} ${gateway}`.trim();
    return answer;
  } catch (err) {
    status(`${action} ${gateway}: ${err.message}`, true);
    return null;
  }
}

function drawMembers(view) {
  const members = view.members ?? [];
  const most = Math.max(1, ...members.map((m) => m.owned ?? 0));
  const now = Date.now() / 1000;
  const policy = view.rebalance ?? {};
  $('#cluster-summary').textContent =
    `seen by ${view.gateway} · ${view.services ?? 0} services, ${view.unowned ?? 0} without an owner · ` +
    `rebalance ${policy.policy ? 'by policy' : 'when asked'} (spread ${policy.spread}, batch ${policy.batch})`;
  clear($('#members')).append(
    ...members.map((m) => {
      const state = memberState(m);
      const drain = m.draining
        ? h('button', { type: 'button', dataset: { action: 'undrain' }, onclick: () => act('undrain', m.id) }, 'Undrain')
        : h('button', { type: 'button', dataset: { action: 'drain' }, onclick: () => act('drain', m.id) }, 'Drain');
      return h(
        'article',
        { class: `member state-${state} health-${m.health}`, dataset: { member: m.id, state, health: m.health } },
        h('header', { class: 'member-head' },
          h('span', { class: 'dot', title: m.health }),
          h('strong', {}, m.id),
          m.id === view.gateway ? h('span', { class: 'muted', title: 'the gateway this page is served by' }, 'here') : null,
          h('span', { class: `badge ${state}` }, state),
        ),
        h('div', { class: 'owned', dataset: { owned: String(m.owned ?? 0) } },
          h('span', { class: 'owned-count' }, `${m.owned ?? 0}`),
          h('span', { class: 'muted' }, ' devices'),
          h('div', { class: 'bar' }, h('div', { class: 'fill', style: `width: ${(100 * (m.owned ?? 0)) / most}%` })),
        ),
        h('dl', {},
          h('dt', {}, 'address'), h('dd', {}, m.address),
          h('dt', {}, 'version'), h('dd', {}, m.version || '-'),
          h('dt', {}, 'health'), h('dd', {}, m.health),
          h('dt', {}, 'load'), h('dd', {}, `${m.calls_per_s ?? 0} calls/s · ${m.listens ?? 0} Listens`),
          h('dt', {}, 'lease'),
          h('dd', { dataset: { leaseExpires: String(m.lease_expires ?? 0) } }, leaseText(m.lease_expires, now)),
          m.read_only ? [h('dt', {}, 'read-only'), h('dd', { class: 'error-text' }, m.read_only)] : null,
          m.draining && m.drained_by ? [h('dt', {}, 'drained by'), h('dd', {}, m.drained_by)] : null,
          m.last_move
            ? [h('dt', {}, 'last move'), h('dd', {}, `${m.last_move.devices} devices in ${m.last_move.seconds} s (${m.last_move.why})`)]
            : null,
        ),
        h('footer', {}, drain),
      );
    }),
  );
}

const owners = new Map(); // device -> owner id
const since = new Map(); // device -> unix seconds

function drawDevices() {
  const names = [...owners.keys()].filter((name) => owners.get(name)).sort();
  const shown = names.slice(0, MAX_ROWS);
  $('#devices-summary').textContent =
    names.length > shown.length ? `${shown.length} of ${names.length} shown` : `${names.length}`;
  clear($('#devices tbody')).append(
    ...shown.map((name) => {
      const at = since.get(name);
      const when = at ? new Date(at * 1000).toLocaleTimeString([], { hour12: false }) : '-';
      return h('tr', { dataset: { device: name, owner: owners.get(name) } },
        h('td', {}, name), h('td', {}, owners.get(name)), h('td', {}, when));
    }),
  );
}

let devicesPending = false;
function devicesChanged() {
  // A move changes many owners at once: one redraw for the burst.
  if (devicesPending) return;
  devicesPending = true;
  setTimeout(() => {
    devicesPending = false;
    drawDevices();
  }, 100);
}

const mux = new EventMux({
  onState(state, detail) {
    const connection = $('#connection');
    connection.dataset.state = state;
    const retry = detail?.retryInSeconds ? ` · retry in ${detail.retryInSeconds} s` : '';
    connection.querySelector('.connection-text').textContent = `${CONNECTION_TEXT[state] ?? state}${retry}`;
  },
});

function deviceOf(path, leaf) {
  const match = /^services\.(.+)\.([a-z_]+)$/.exec(path);
  return match && match[2] === leaf ? match[1] : null;
}

// The leases count down between two views: their text is written again every second.
setInterval(() => {
  const now = Date.now() / 1000;
  for (const el of document.querySelectorAll('#members [data-lease-expires]')) {
    el.textContent = leaseText(Number(el.dataset.leaseExpires), now);
  }
}, 1000);

mux.subscribe('registry/cluster', {
  onValue({ value, removed }) {
    if (removed || !value) return;
    try {
      drawMembers(JSON.parse(value));
    } catch (err) {
      status(`the cluster view could not be read: ${err.message}`, true);
    }
  },
  onError({ message }) {
    status(`this gateway is not in a cluster, or the view is refused: ${message}`, true);
  },
});
mux.subscribe('registry/services.*.owner', {
  onValue({ path, value, removed }) {
    const name = deviceOf(path, 'owner');
    if (!name) return;
    if (removed) owners.delete(name);
    else owners.set(name, value);
    devicesChanged();
  },
});
mux.subscribe('registry/services.*.owner_since', {
  onValue({ path, value, removed }) {
    const name = deviceOf(path, 'owner_since');
    if (!name) return;
    if (removed) since.delete(name);
    else since.set(name, Number(value));
    devicesChanged();
  },
});

$('#rebalance').addEventListener('click', () => act('rebalance'));
