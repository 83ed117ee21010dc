// Widgets keyed by `.gui` and by data type, and the frame every property widget sits in.
//
// A widget factory is `factory(prop, ctx)` -> `{element, update(value, event), dispose()}`:
//   prop   the property's model (name, type, access, unit, minimum, maximum, choices, length,
//          gui, doc, parameters), as GET /api/v1/services/{service}/model gives it;
//   ctx    {service, path, writable, set(text, parameters) -> Promise<reply|null>,
//           setPath(path, text, parameters) (another property of the service, the same way),
//           get(parameters) -> Promise<value|null>, showValue(text), h, svg,
//           history(since), historyOf(path, since), readPath(path), model(), subscribe(path, handlers)}
//          (a binary reply reads as "[N bytes, media/type]", values.js shownValue)
//   update is called with the value text on every change (and once with the current value).
// The frame (`[data-property=PATH]`) shows the name, unit and access, the current value text in
// `.value` and the error of a failed Set in `.error` ("CODE: message"); ctx.set fills both.
//
// The extension point is window.PropertyConsole.registerWidget(gui, factory): a factory
// registered there wins over the built-in one for that `.gui` word (docs/console.md).

import { h, svg } from './dom.js';
import { plainDoc } from './doc_text.js';
import { formatTime, roundedValue, shownValue } from './values.js';

/** `.gui` words of a text shown in a text area of several lines (a chart, a script, a note). */
export const TEXT_AREA_GUIS = new Set(['text-area', 'code']);
/** Actions that undo work (their path's last name): the console asks before it invokes them. */
export const CONFIRMED_ACTIONS = new Set(['remove', 'delete', 'stop-all', 'stop_all']);

/** Whether invoking action `prop` asks for confirmation first: by its name, or `.gui` `confirm`. */
export function needsConfirmation(prop) {
  if (prop.access !== 'action') return false;
  return prop.gui === 'confirm' || CONFIRMED_ACTIONS.has(prop.name.split('.').pop());
}

/**
 * The text shown for a value of `prop`, and its tooltip: a `.gui` `time` (Unix seconds, the
 * registry's `last_seen`) shows as a local date and time with the number in the tooltip; a number
 * or a vector rounded to the precision its model implies (values.js roundedValue: a location's
 * "(1.2345678901234567 …)" reads "(1.23 …)"), the text as sent in the tooltip.
 */
export function displayValue(prop, text) {
  if (prop.gui === 'time') {
    const time = formatTime(text);
    if (time !== null) return { text: time, title: `${text} (Unix seconds)` };
  }
  if (prop.type === 'number' || prop.type === 'integer' || prop.type === 'vector') {
    const rounded = roundedValue(prop, text);
    const unit = prop.unit ? ` ${prop.unit}` : '';
    return { text: rounded, title: `${text}${text === '' ? '' : unit}` };
  }
  return { text, title: text };
}

const GUI_NAME = /^[A-Za-z0-9_.-]{1,64}$/;
const builtins = new Map(); // gui word -> factory
const builtinTypes = new Map(); // data type -> factory
const extensions = new Map(); // gui word -> factory, from registerWidget
const builtinMedia = new Map(); // media type ("image/png") or family ("image/*") -> factory
let addressedFactory = null; // the built-in form of a property that needs parameters to be read

function checked(gui, factory) {
  if (typeof gui !== 'string' || !GUI_NAME.test(gui)) {
    throw new TypeError(`a widget's gui name is 1 to 64 letters, digits, "_", "." or "-", got ${JSON.stringify(gui)}`);
  }
  if (typeof factory !== 'function') throw new TypeError(`the widget factory for "${gui}" must be a function`);
}

/** The extension point: use `factory` for every property whose `.gui` is `gui`. */
export function registerWidget(gui, factory) {
  checked(gui, factory);
  extensions.set(gui, factory);
}

/** Built-in widgets register here (an extension of the same gui word still wins). */
export function registerBuiltin(gui, factory) {
  checked(gui, factory);
  builtins.set(gui, factory);
}

/** The built-in widget for a data type whose `.gui` names no widget. */
export function registerTypeWidget(type, factory) {
  checked(type, factory);
  builtinTypes.set(type, factory);
}

const MEDIA_TYPE = /^[a-z0-9.+-]{1,64}\/(\*|[a-z0-9.+-]{1,64})$/;

/** The built-in widget of a binary property by its media type: `image/*` (a family) or `image/png`. */
export function registerMediaWidget(mediaType, factory) {
  if (typeof mediaType !== 'string' || !MEDIA_TYPE.test(mediaType)) {
    throw new TypeError(`a media type is TYPE/SUBTYPE or TYPE/*, got ${JSON.stringify(mediaType)}`);
  }
  if (typeof factory !== 'function') throw new TypeError(`the widget factory for "${mediaType}" must be a function`);
  builtinMedia.set(mediaType, factory);
}

/** The widget registered for a media type (parameters and case ignored), else for its family. */
export function mediaWidgetFor(mediaType) {
  const essence = String(mediaType ?? '').split(';')[0].trim().toLowerCase();
  if (!essence.includes('/')) return undefined;
  return builtinMedia.get(essence) ?? builtinMedia.get(`${essence.split('/')[0]}/*`);
}

/**
 * A readable or writable property that cannot be read without a request parameter (a storage
 * service's `file` needs `name`): the page cannot follow it, only read it with parameters given.
 */
export function needsParameters(prop) {
  if (prop.access === 'action' || prop.access === 'query') return false;
  return (prop.parameters ?? []).some((p) => p.required && (p.default === null || p.default === undefined));
}

/** The built-in widget of a property that needs parameters (see needsParameters). */
export function registerAddressedWidget(factory) {
  checked('addressed', factory);
  addressedFactory = factory;
}

/** The gui words that have a widget: built in, then registered. */
export function widgetNames() {
  return [...new Set([...builtins.keys(), ...extensions.keys()])].sort();
}

/**
 * The factory for a property: a registered `.gui`, else the built-in by access, then (a binary
 * property) by its media type, then by `.gui` and by type.
 */
export function widgetFor(prop) {
  if (prop.gui && extensions.has(prop.gui)) return extensions.get(prop.gui);
  if (prop.access === 'action') return builtins.get('button');
  if (prop.access === 'query') return builtins.get('query');
  if (addressedFactory && needsParameters(prop)) return addressedFactory;
  const media = prop.type === 'bytes' ? mediaWidgetFor(prop.media_type) : undefined;
  return media ?? builtins.get(prop.gui) ?? builtinTypes.get(prop.type) ?? builtins.get('text');
}

/** Whether a property's values can be plotted: a readable number or vector. */
export function plottable(prop) {
  return ['number', 'integer', 'vector'].includes(prop.type) && ['read', 'read-write'].includes(prop.access);
}

/** Whether the page's event stream follows the property: a binary one is read its own way. */
export function followedOnStream(prop) {
  return prop.type !== 'bytes';
}

const ACCESS_SHORT = {
  read: 'read',
  write: 'write',
  'read-write': 'read/write',
  action: 'action',
  query: 'query',
  unknown: 'unknown',
};

/**
 * The frame of one property of `service` and its widget. `setProperty(service, path, text,
 * parameters)` and `getProperty(...)` are the API calls (js/api.js). Returns
 * {element, update(value, event), dispose()}.
 */
export function propertyView(
  service,
  prop,
  { setProperty, getProperty, getHistory, describe, subscribe, label = prop.name },
) {
  const writable = ['write', 'read-write', 'action', 'unknown'].includes(prop.access);
  const value = h('output', { class: 'value', 'aria-live': 'off' });
  const error = h('div', { class: 'error', role: 'alert', hidden: true });
  const unit = prop.unit ? h('span', { class: 'unit' }, prop.unit) : null;
  const frame = h(
    'div',
    {
      class: `property access-${prop.access}`,
      dataset: { property: prop.name, type: prop.type ?? '', access: prop.access ?? '', gui: prop.gui ?? '' },
    },
    h(
      'div',
      { class: 'prop-head' },
      h('span', { class: 'prop-name', title: plainDoc(prop.doc) || prop.name }, label),
      unit,
      h('span', { class: 'prop-access' }, ACCESS_SHORT[prop.access] ?? prop.access ?? ''),
    ),
  );

  const showValue = (text) => {
    const shown = displayValue(prop, text);
    value.textContent = shown.text;
    value.title = shown.title;
  };
  const showError = (e) => {
    error.textContent = `${e?.code ?? 'UNKNOWN'}: ${e?.message ?? e}`;
    error.hidden = false;
    frame.classList.add('has-error');
  };
  const clearError = () => {
    error.textContent = '';
    error.hidden = true;
    frame.classList.remove('has-error');
  };

  const ctx = {
    service,
    path: prop.name,
    writable,
    h,
    svg,
    showValue,
    showError,
    clearError,
    async set(text, parameters = {}) {
      clearError();
      frame.classList.add('busy');
      try {
        const reply = await setProperty(service, prop.name, text, parameters);
        return shownValue(reply);
      } catch (e) {
        showError(e);
        return null;
      } finally {
        frame.classList.remove('busy');
      }
    },
    /** A Set of another property of the same service (a machine's `M.start` beside `M.diagram`). */
    async setPath(path, text, parameters = {}) {
      clearError();
      frame.classList.add('busy');
      try {
        const reply = await setProperty(service, path, text, parameters);
        return shownValue(reply);
      } catch (e) {
        showError(e);
        return null;
      } finally {
        frame.classList.remove('busy');
      }
    },
    async get(parameters = {}) {
      clearError();
      try {
        const reply = await getProperty(service, prop.name, parameters);
        return shownValue(reply);
      } catch (e) {
        showError(e);
        return null;
      }
    },
    /** The kept values of the property since `since` ("60s"); rejects when the gateway keeps none. */
    history: getHistory ? (since) => getHistory(service, prop.name, { since }) : undefined,
    /** The same for another property of the service (a further signal of a plot). */
    historyOf: getHistory ? (path, since) => getHistory(service, path, { since }) : undefined,
    /** The value text of another property of the service; rejects with the error, shows nothing. */
    readPath: getProperty ? async (path) => shownValue(await getProperty(service, path)) : undefined,
    /** The service's model (shared with the views that read it at the same time). */
    model: describe ? () => describe(service) : undefined,
    /** Follow another property on the page's event stream: returns the function that ends it. */
    subscribe: subscribe ? (path, handlers) => subscribe(`${service}/${path}`, handlers) : undefined,
  };

  let widget;
  try {
    widget = widgetFor(prop)(prop, ctx);
  } catch (e) {
    // A broken extension widget costs its own property, not the page.
    console.error(`the widget for ${prop.name} (gui "${prop.gui}") failed:`, e);
    widget = { element: h('span', { class: 'muted' }, `widget "${prop.gui}" failed: ${e.message}`) };
  }
  // A widget that shows the value its own way (a statechart's SVG) hides the value text.
  if (widget.hidesValue) value.hidden = true;
  // A number or a vector can be plotted beside its own widget: the last minute, then live.
  let plot = null;
  const plotBox = h('div', { class: 'prop-plot' });
  const plotToggle = plottable(prop) && prop.gui !== 'plot'
    ? h(
        'button',
        {
          class: 'plot-toggle',
          type: 'button',
          title: 'plot the last minute, then live',
          'aria-pressed': 'false',
          dataset: { action: 'plot' },
          onclick: () => {
            if (plot) {
              plot.dispose?.();
              plot = null;
              plotBox.replaceChildren();
            } else {
              plot = builtins.get('plot')(prop, ctx);
              plotBox.replaceChildren(plot.element);
              const shownText = value.textContent;
              if (shownText) plot.update(shownText);
            }
            plotToggle.setAttribute('aria-pressed', String(Boolean(plot)));
          },
        },
        'plot',
      )
    : null;
  if (plotToggle) frame.querySelector('.prop-head').append(plotToggle);
  frame.append(h('div', { class: 'prop-body' }, value, widget.element ?? ''), plotBox, error);
  return {
    element: frame,
    update(text, event = {}) {
      showValue(text);
      frame.classList.toggle('gap', Boolean(event.gap));
      try {
        widget.update?.(text, event);
        plot?.update(text, event);
      } catch (e) {
        console.error(`the widget for ${prop.name} could not show ${JSON.stringify(text)}:`, e);
      }
    },
    removed() {
      showValue('');
      frame.classList.add('removed');
    },
    dispose() {
      widget.dispose?.();
      plot?.dispose?.();
    },
  };
}
