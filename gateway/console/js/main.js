// The console's entry point: builds the views, wires them to the page's one event stream, and
// exposes window.PropertyConsole (the widget extension point; docs/console.md).

import * as api from './api.js';
import './builtin_widgets.js';
import { EventMux } from './events.js';
import { Failover, fetchProbe, withRoundEnded } from './failover.js';
import { GamepadDriver } from './gamepad.js';
import { Inspector } from './inspector.js';
import { RobotMap } from './map.js';
import { ServiceList } from './service_list.js';
import { ServiceView } from './service_view.js';
import { StopAll, Teleop } from './teleop.js';
import * as values from './values.js';
import { registerWidget, widgetNames } from './widgets.js';

const $ = (selector) => {
  const el = document.querySelector(selector);
  if (!el) throw new Error(`the page lacks ${selector}`);
  return el;
};

const connection = $('#connection');
const CONNECTION_TEXT = { open: 'live', connecting: 'connecting…', closed: 'disconnected' };

// With `?gateways=URL,URL` the page moves itself to the next gateway's console when its own
// stays unreachable (js/failover.js).
const failover = new Failover({
  href: location.href,
  hash: () => location.hash,
  probe: fetchProbe(),
  move: (url) => location.assign(url),
  notice: (text) => {
    const el = $('#failover');
    el.textContent = text;
    el.hidden = !text;
  },
  endRound: () => history.replaceState(history.state, '', withRoundEnded(location.href)),
});

const mux = new EventMux({
  // The gateway allows fewer selectors per Listen than the page asked for: lay the view out again.
  onLimit: () => setTimeout(() => selected() && view.show(selected()), 0),
  onState(state, detail) {
    connection.dataset.state = state;
    const retry = detail?.retryInSeconds ? ` · retry in ${detail.retryInSeconds} s` : '';
    connection.querySelector('.connection-text').textContent = `${CONNECTION_TEXT[state] ?? state}${retry}`;
    failover.stateChanged(state);
    list.connectionChanged(state);
  },
});

function status(text, isError = false) {
  const el = $('#status');
  el.textContent = text;
  el.classList.toggle('error-text', isError);
}

let selectedName = null;
// A page opened as /#scout1 selects scout1 once the list holds it.
let pendingSelect = decodeURIComponent(location.hash.slice(1)) || null;
const selected = () => (selectedName ? list.byName(selectedName) : null);

const list = new ServiceList($('#services'), {
  mux,
  status: (text) => status(text, Boolean(text)),
  onSelect: (name) => select(name),
  onChange: (services) => {
    map.servicesChanged(services);
    if (pendingSelect && services.some((s) => s.name === pendingSelect)) {
      const name = pendingSelect;
      pendingSelect = null;
      select(name);
    }
    if (selectedName && !services.some((s) => s.name === selectedName)) {
      select(null, { push: false }); // it left: its view and its subscriptions go
    } else {
      view.updateState(selected());
      map.drawAll();
      inspector.suggestPaths(); // its service may have come up
    }
    fillDatalist(services);
  },
  locationOf: (name) => map.poses.get(name) ?? null,
  // The selected service's badge says unknown too while the gateway cannot be reached; its
  // view is built anew when the list says it is up again (onChange).
  onReachable: (reachable) => !reachable && selected() && view.updateState({ ...selected(), state: 'unknown' }),
});

const view = new ServiceView($('#service-view'), { mux });

const map = new RobotMap($('#map'), {
  mux,
  services: () => list.services,
  selected: () => selectedName,
  onSelect: (name) => select(name),
  formation: () => ({ formation: $('#formation').value, spacing: $('#spacing').value.trim() }),
  status: (text, isError = false) => {
    const el = $('#map-status');
    el.textContent = text;
    el.classList.toggle('error-text', isError);
  },
  onPose: (name) => list.moved(name),
  backgroundSelect: $('#map-background'),
});

const teleop = new Teleop(
  {
    root: $('#teleop'),
    joystick: $('#joystick'),
    knob: $('#joystick .knob'),
    status: $('#teleop-status'),
    speed: $('#teleop-speed'),
    turn: $('#teleop-turn'),
    mode: $('#teleop-mode'),
    stop: $('#teleop-stop'),
    target: $('#teleop-target'),
  },
  { selected, poseOf: (name) => map.poses.get(name) ?? null, onDrive: (name) => map.forgetTarget(name) },
);

// A gamepad drives through the teleop, with its own dead-man (js/gamepad.js).
new GamepadDriver({
  drive: (stick) => teleop.gamepad(stick),
  onPad: (text) => {
    const el = $('#teleop-gamepad');
    el.textContent = text;
    el.hidden = !text;
  },
});
// Stop all: every robot and group the list holds, after the operator confirmed it.
new StopAll(
  { button: $('#teleop-stop-all'), status: $('#teleop-stop-all-status') },
  { services: () => list.services, teleop },
);

const inspector = new Inspector(
  {
    service: $('#inspector-service'),
    path: $('#inspector-path'),
    value: $('#inspector-value'),
    params: $('#inspector-params'),
    get: $('#inspector-get'),
    set: $('#inspector-set'),
    listen: $('#inspector-listen'),
    output: $('#inspector-output'),
    log: $('#inspector-log'),
    paths: $('#inspector-paths'),
  },
  // A service listed as not up is not asked for its model (it cannot answer).
  { mux, isUp: (name) => (list.byName(name)?.state ?? 'up') === 'up' },
);

/**
 * Select `name` (null: nothing). The URL's fragment follows: a new history entry for the
 * operator's choice (`push`), so that back and forward go through the selections.
 */
function select(name, { push = true } = {}) {
  if (name === selectedName) return;
  selectedName = name;
  list.select(name);
  map.drawAll();
  const service = selected();
  view.show(service);
  teleop.selectionChanged();
  $('#formation-box').hidden = service?.type !== 'group';
  const movable = service?.type === 'mobile_robot' || service?.type === 'group';
  $('#map-target').textContent = movable ? `${service.name} (${service.type === 'group' ? 'group' : 'robot'})` : 'a robot or group you select';
  if (service) inspector.use(service.name);
  const url = new URL(location.href);
  if (name) url.hash = encodeURIComponent(name);
  else url.hash = '';
  if (url.href === location.href) return; // selected from the URL itself
  if (push) history.pushState(null, '', url);
  else history.replaceState(null, '', url);
}

/** The service the URL's fragment names (`#scout1`), or null. */
function hashService() {
  try {
    return decodeURIComponent(location.hash.slice(1)) || null;
  } catch {
    return null; // a malformed escape names nothing
  }
}

// A fragment typed into the address bar, or back and forward through the selections, selects
// the service it names (once the list holds it).
window.addEventListener('hashchange', () => {
  const name = hashService();
  if (name && !list.byName(name)) {
    pendingSelect = name;
    return;
  }
  pendingSelect = null;
  select(name);
});

function fillDatalist(services) {
  $('#inspector-services').replaceChildren(
    ...services.map((s) => Object.assign(document.createElement('option'), { value: s.name })),
  );
}

// -- header controls --------------------------------------------------------------------------

$('#group-by').addEventListener('change', (e) => list.setGrouping(e.target.value));
$('#map-fit').addEventListener('click', () => map.fit());
$('#token-form').addEventListener('submit', (e) => {
  e.preventDefault();
  api.setToken($('#token').value);
  $('#token').value = '';
  $('#token-state').textContent = api.token() ? 'token set' : 'no token';
  mux.reconnect(); // the stream carries the token in its cookie: open it again
  list.refresh();
  if (selected()) view.show(selected());
});
$('#token-state').textContent = api.token() ? 'token set' : 'no token';

// Views can be folded away (the inspector starts folded on a small screen).
for (const button of document.querySelectorAll('[data-fold]')) {
  button.addEventListener('click', () => {
    const panel = document.getElementById(button.dataset.fold);
    const folded = panel.classList.toggle('folded');
    button.setAttribute('aria-expanded', String(!folded));
  });
}

// A page kept in the back-forward cache holds no stream; shown again, it follows everything anew.
window.addEventListener('pagehide', () => mux.suspend());
window.addEventListener('pageshow', (e) => {
  if (e.persisted) {
    mux.reconnect();
    list.refresh();
  }
});

// -- the extension point ------------------------------------------------------------------------

window.PropertyConsole = Object.freeze({
  /** registerWidget(gui, factory): the widget for every property whose `.gui` is `gui`. */
  registerWidget(gui, factory) {
    registerWidget(gui, factory);
    // Properties already shown get the new widget when their view is built again.
    if (selected()) view.show(selected());
  },
  widgetNames,
  /** subscribe("SERVICE/PATH", {onValue, onSync, onError}) on the page's one stream. */
  subscribe: (selector, handlers) => mux.subscribe(selector, handlers),
  api: Object.freeze({ ...api }),
  values: Object.freeze({ ...values }),
  select,
  selected: () => selectedName,
  /** What the page's one stream costs: its selectors, and the events it threw away (docs/console.md). */
  streamStats: () => mux.stats(),
});

list.start();
map.start();
map.draw();
view.show(null);
teleop.selectionChanged();
