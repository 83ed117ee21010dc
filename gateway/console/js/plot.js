// The `plot` widget: a number (or each element of a vector, such as a robot's `location`) over the
// last minute, one line per element. It opens with the minute the gateway kept of the property
// (its history, `GET …/properties/{path}/history?since=60s`, docs/recording.md) and follows the
// property's events from then on. A gateway that keeps no history of it (no `[history]`
// selector names it) leaves the plot to start with the first value it sees.

import { formatNumber, parseVector } from './values.js';

/** The window a plot shows, milliseconds: the last minute. */
export const PLOT_WINDOW_MS = 60000;
/** Points a line keeps at most (a value every 100 ms for a minute). */
export const PLOT_POINTS = 600;
/** What the history asks for: the plot's window, and no more points than a line keeps. */
export const HISTORY_SINCE = '60s';
/** The elements of a 6-vector location, named as the pose widget names them. */
const POSE_AXES = ['x', 'y', 'z', 'roll', 'pitch', 'yaw'];
const WIDTH = 240;
const HEIGHT = 60;

/** The numbers a value text holds: one for a number, each element for a vector; [] for neither. */
export function plotNumbers(text) {
  const trimmed = String(text).trim();
  if (trimmed.startsWith('(')) {
    try {
      return parseVector(trimmed).map(Number);
    } catch {
      return [];
    }
  }
  const x = Number(trimmed);
  return trimmed && Number.isFinite(x) ? [x] : [];
}

/**
 * Points of each element over time: add(timeMs, numbers), then lines(nowMs) gives, for each
 * element, its SVG polyline points over the window before nowMs, on one vertical scale.
 */
export class PlotSeries {
  constructor({ windowMs = PLOT_WINDOW_MS, maxPoints = PLOT_POINTS } = {}) {
    this.windowMs = windowMs;
    this.maxPoints = maxPoints;
    /** One array of [timeMs, y] a vector element, oldest first. */
    this.series = [];
  }

  add(timeMs, numbers) {
    numbers.forEach((y, i) => {
      if (!Number.isFinite(y)) return;
      const points = (this.series[i] ??= []);
      // History and live events may overlap by a value: a point no newer than the last is dropped.
      if (points.length && points[points.length - 1][0] >= timeMs) return;
      points.push([timeMs, y]);
      if (points.length > this.maxPoints) points.shift();
    });
  }

  /** Put the points of `older` (the history) before this one's (live values that came first). */
  takeOlder(older) {
    older.series.forEach((points, i) => {
      const mine = this.series[i] ?? [];
      const first = mine.length ? mine[0][0] : Infinity;
      this.series[i] = [...points.filter(([t]) => t < first), ...mine].slice(-this.maxPoints);
    });
  }

  /** Drop what fell out of the window before `nowMs`; the range of what is left. */
  trim(nowMs) {
    const oldest = nowMs - this.windowMs;
    let lo = Infinity;
    let hi = -Infinity;
    for (const points of this.series) {
      while (points.length > 1 && points[0][0] < oldest) points.shift();
      for (const [, y] of points) {
        lo = Math.min(lo, y);
        hi = Math.max(hi, y);
      }
    }
    return { lo, hi };
  }

  /**
   * Each element's polyline points, and the range drawn: this series' own, or `range` ({lo, hi})
   * when it shares a scale with other signals of the same unit.
   */
  lines(nowMs, range = null) {
    const own = this.trim(nowMs);
    const { lo, hi } = range ?? own;
    const span = hi - lo || 1;
    const start = nowMs - this.windowMs;
    const lines = this.series.map((points) =>
      points
        .map(([t, y]) => {
          const x = Math.max(0, ((t - start) / this.windowMs) * WIDTH);
          return `${x.toFixed(1)},${(HEIGHT - 4 - ((y - lo) / span) * (HEIGHT - 8)).toFixed(1)}`;
        })
        .join(' '),
    );
    return { lines, lo, hi };
  }

  get count() {
    return this.series.reduce((n, points) => n + points.length, 0);
  }
}

function shown(x) {
  return Number.isFinite(x) ? formatNumber(Number(x.toFixed(3))) : '–';
}

/** Signals one plot draws at most: the property it opened on and two more. */
export const MAX_SIGNALS = 3;

/**
 * The vertical range each signal is drawn on: signals of one unit share a scale (two speeds
 * compare), a signal of another unit keeps its own (a temperature beside a speed).
 * `signals` is [{unit, lo, hi}]; an empty one has lo Infinity, hi -Infinity.
 */
export function sharedRanges(signals) {
  const byUnit = new Map();
  for (const { unit, lo, hi } of signals) {
    const key = unit ?? '';
    const known = byUnit.get(key) ?? { lo: Infinity, hi: -Infinity };
    byUnit.set(key, { lo: Math.min(known.lo, lo), hi: Math.max(known.hi, hi) });
  }
  return signals.map(({ unit }) => byUnit.get(unit ?? ''));
}

/** Whether `prop` may join an open plot as a further signal: a readable number. */
export function addableSignal(prop) {
  return ['number', 'integer'].includes(prop?.type) && ['read', 'read-write'].includes(prop?.access);
}

/** The kept events of a history answer as a PlotSeries, and how many of them were drawn. */
function seriesOfHistory(answer) {
  const kept = new PlotSeries();
  let drawn = 0;
  for (const event of answer?.events ?? []) {
    if (event.removed || typeof event.value !== 'string') continue;
    const numbers = plotNumbers(event.value);
    if (!numbers.length) continue;
    kept.add(event.time * 1000, numbers);
    drawn += 1;
  }
  return { kept, drawn };
}

/**
 * The widget factory: `plotWidget(prop, ctx)` -> {element, update, dispose}. `ctx.history(since)`
 * reads the property's kept values (resolves to the route's answer; rejects when there are none).
 * The chart says how many points came from the history (`data-history-points`) once it asked.
 *
 * With `ctx.model()` (the service's model), `ctx.historyOf(path, since)` and
 * `ctx.subscribe(path, handlers)` (the page's event stream), the operator can add up to two more
 * numbers of the service (`select[data-action=add-signal]`): each is a line of its own colour
 * with its legend entry (`[data-signal=PATH]`, its range and unit), opened with its last minute
 * from the history and followed live; a signal in another unit is drawn on its own scale.
 */
export function plotWidget(prop, ctx, { now = () => Date.now() } = {}) {
  const chart = ctx.svg('svg', {
    class: 'plot',
    viewBox: `0 0 ${WIDTH} ${HEIGHT}`,
    preserveAspectRatio: 'none',
    role: 'img',
    'aria-label': `${prop.name} over the last minute`,
  });
  const legend = ctx.h('small', { class: 'plot-legend' });
  const range = ctx.h('small', { class: 'plot-range' });
  const signalKeys = ctx.h('div', { class: 'plot-signals' });
  const names = prop.type === 'vector' && (prop.length === 6 || prop.length === undefined) ? POSE_AXES : [];
  // The property the plot opened on, then the ones the operator added: {prop, series, lines, key, stop}.
  const signals = [{ prop, series: new PlotSeries(), lines: [], key: null, stop: null }];
  // The first signal's own legend entry, shown once another joins (a vector's elements have theirs).
  const firstKey = ctx.h(
    'span',
    { class: 'plot-signal-key plot-signal-key-0', dataset: { signal: prop.name }, hidden: true },
    ctx.h('span', { class: 'plot-signal-name' }, prop.name),
    ctx.h('span', { class: 'plot-signal-range' }),
  );
  signalKeys.append(firstKey);
  let timer = null;
  let disposed = false;

  const unitText = (p) => (p.unit ? ` ${p.unit}` : '');
  const draw = () => {
    const at = now();
    const ownRanges = signals.map((s) => ({ unit: s.prop.unit ?? '', ...s.series.trim(at) }));
    const scales = sharedRanges(ownRanges);
    signals.forEach((signal, k) => {
      const drawn = signal.series.lines(at, signals.length > 1 ? scales[k] : null);
      drawn.lines.forEach((points, i) => {
        if (!signal.lines[i]) {
          const attrs =
            k === 0
              ? { class: `plot-line plot-line-${i % 6}`, points: '', dataset: { element: String(i) } }
              : { class: `plot-line plot-signal plot-signal-${k}`, points: '', dataset: { signal: signal.prop.name } };
          signal.lines[i] = ctx.svg('polyline', attrs);
          chart.append(signal.lines[i]);
          if (k === 0 && drawn.lines.length > 1) {
            legend.append(ctx.h('span', { class: `plot-key plot-key-${i % 6}` }, names[i] ?? String(i)));
          }
        }
        signal.lines[i].setAttribute('points', points);
      });
      if (signal.key) {
        const own = ownRanges[k];
        signal.key.querySelector('.plot-signal-range').textContent = signal.series.count
          ? ` ${shown(own.lo)} … ${shown(own.hi)}${unitText(signal.prop)}`
          : ' no values yet';
      }
    });
    const first = ownRanges[0];
    firstKey.hidden = signals.length < 2 || signals[0].lines.length > 1;
    firstKey.lastChild.textContent = signals[0].series.count ? ` ${shown(first.lo)} … ${shown(first.hi)}${unitText(prop)}` : '';
    range.textContent = signals[0].series.count
      ? `${shown(first.lo)} … ${shown(first.hi)}${unitText(prop)} · last minute`
      : 'no values yet';
  };

  const openWithHistory = (signal, read) => {
    read(HISTORY_SINCE)
      .then((answer) => {
        if (disposed) return;
        const { kept, drawn } = seriesOfHistory(answer);
        signal.series.takeOlder(kept);
        if (signal === signals[0]) chart.dataset.historyPoints = String(drawn);
        else signal.key.dataset.historyPoints = String(drawn);
        draw();
      })
      .catch(() => {
        // No history of it here: the line starts with the first live value.
        if (signal === signals[0]) chart.dataset.historyPoints = '0';
        else if (signal.key) signal.key.dataset.historyPoints = '0';
      });
  };

  // -- further signals --------------------------------------------------------------------------
  const canAdd = Boolean(ctx.model && ctx.subscribe);
  const picker = canAdd
    ? ctx.h('select', { class: 'plot-add', 'aria-label': `add a signal to the plot of ${prop.name}`, dataset: { action: 'add-signal' } })
    : null;
  let offered = []; // the numbers the picker offers now
  const fillPicker = async () => {
    let model;
    try {
      model = await ctx.model();
    } catch {
      picker.hidden = true;
      return;
    }
    if (disposed) return;
    const taken = new Set(signals.map((s) => s.prop.name));
    offered = (model?.properties ?? []).filter((p) => addableSignal(p) && !taken.has(p.name));
    picker.replaceChildren(
      ctx.h('option', { value: '' }, offered.length ? '+ signal…' : 'no other numbers'),
      ...offered.map((p) => ctx.h('option', { value: p.name }, p.name)),
    );
    picker.disabled = !offered.length;
    picker.hidden = signals.length >= MAX_SIGNALS;
  };
  const removeSignal = (signal) => {
    signal.stop?.();
    for (const line of signal.lines) line.remove();
    signal.key.remove();
    signals.splice(signals.indexOf(signal), 1);
    // The colours follow the places: the second signal keeps the second colour.
    signals.forEach((s, k) => {
      if (k === 0) return;
      for (const line of s.lines) line.setAttribute('class', `plot-line plot-signal plot-signal-${k}`);
      s.key.className = `plot-signal-key plot-signal-key-${k}`;
    });
    fillPicker();
    draw();
  };
  const addSignal = (added) => {
    if (signals.length >= MAX_SIGNALS || signals.some((s) => s.prop.name === added.name)) return;
    const k = signals.length;
    const signal = { prop: added, series: new PlotSeries(), lines: [], key: null, stop: null };
    signal.key = ctx.h(
      'span',
      { class: `plot-signal-key plot-signal-key-${k}`, dataset: { signal: added.name } },
      ctx.h('span', { class: 'plot-signal-name' }, added.name),
      ctx.h('span', { class: 'plot-signal-range' }, ' no values yet'),
      ctx.h(
        'button',
        {
          type: 'button',
          class: 'plot-remove',
          title: `take ${added.name} off the plot`,
          'aria-label': `take ${added.name} off the plot`,
          dataset: { action: 'remove-signal' },
          onclick: () => removeSignal(signal),
        },
        '×',
      ),
    );
    signalKeys.append(signal.key);
    signals.push(signal);
    try {
      signal.stop = ctx.subscribe(added.name, {
        onValue(event) {
          if (event.removed) return;
          const numbers = plotNumbers(event.value);
          if (!numbers.length) return;
          signal.series.add(typeof event.time === 'number' ? event.time * 1000 : now(), numbers);
          draw();
        },
      });
    } catch (e) {
      ctx.showError?.({ code: 'RESOURCE_EXHAUSTED', message: e.message });
    }
    if (ctx.historyOf) openWithHistory(signal, (since) => ctx.historyOf(added.name, since));
    fillPicker();
    draw();
  };
  if (picker) {
    picker.addEventListener('change', () => {
      const chosen = offered.find((p) => p.name === picker.value);
      picker.value = '';
      if (chosen) addSignal(chosen);
    });
    fillPicker();
  }

  if (ctx.history) openWithHistory(signals[0], ctx.history);
  // The window moves on while the property stands still.
  timer = setInterval(draw, 1000);
  draw();
  return {
    element: ctx.h(
      'div',
      { class: 'plot-box' },
      chart,
      legend,
      range,
      canAdd ? ctx.h('div', { class: 'plot-more' }, signalKeys, picker) : null,
    ),
    update(text, event = {}) {
      const numbers = plotNumbers(text);
      if (!numbers.length) return;
      signals[0].series.add(typeof event.time === 'number' ? event.time * 1000 : now(), numbers);
      draw();
    },
    dispose() {
      disposed = true;
      if (timer !== null) clearInterval(timer);
      timer = null;
      for (const signal of signals) signal.stop?.();
    },
  };
}
