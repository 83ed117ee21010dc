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

  /** Each element's polyline points, and the range drawn. */
  lines(nowMs) {
    const { lo, hi } = this.trim(nowMs);
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

/**
 * The widget factory: `plotWidget(prop, ctx)` -> {element, update, dispose}. `ctx.history(since)`
 * reads the property's kept values (resolves to the route's answer; rejects when there are none).
 * The chart says how many points came from the history (`data-history-points`) once it asked.
 */
export function plotWidget(prop, ctx, { now = () => Date.now() } = {}) {
  const plot = new PlotSeries();
  const chart = ctx.svg('svg', {
    class: 'plot',
    viewBox: `0 0 ${WIDTH} ${HEIGHT}`,
    preserveAspectRatio: 'none',
    role: 'img',
    'aria-label': `${prop.name} over the last minute`,
  });
  const legend = ctx.h('small', { class: 'plot-legend' });
  const range = ctx.h('small', { class: 'plot-range' });
  const lines = [];
  const names = prop.type === 'vector' && (prop.length === 6 || prop.length === undefined) ? POSE_AXES : [];
  let timer = null;

  const draw = () => {
    const drawn = plot.lines(now());
    drawn.lines.forEach((points, i) => {
      if (!lines[i]) {
        lines[i] = ctx.svg('polyline', { class: `plot-line plot-line-${i % 6}`, points: '', dataset: { element: String(i) } });
        chart.append(lines[i]);
        if (drawn.lines.length > 1) {
          legend.append(ctx.h('span', { class: `plot-key plot-key-${i % 6}` }, names[i] ?? String(i)));
        }
      }
      lines[i].setAttribute('points', points);
    });
    const unit = prop.unit ? ` ${prop.unit}` : '';
    range.textContent = plot.count ? `${shown(drawn.lo)} … ${shown(drawn.hi)}${unit} · last minute` : 'no values yet';
  };

  if (ctx.history) {
    ctx
      .history(HISTORY_SINCE)
      .then((answer) => {
        const kept = new PlotSeries();
        let drawnFromHistory = 0;
        for (const event of answer.events ?? []) {
          if (event.removed || typeof event.value !== 'string') continue;
          const numbers = plotNumbers(event.value);
          if (!numbers.length) continue;
          kept.add(event.time * 1000, numbers);
          drawnFromHistory += 1;
        }
        plot.takeOlder(kept);
        chart.dataset.historyPoints = String(drawnFromHistory);
        draw();
      })
      .catch(() => {
        // No history of it here: the plot starts with the first live value.
        chart.dataset.historyPoints = '0';
      });
  }
  // The window moves on while the property stands still.
  timer = setInterval(draw, 1000);
  draw();
  return {
    element: ctx.h('div', { class: 'plot-box' }, chart, legend, range),
    update(text, event = {}) {
      const numbers = plotNumbers(text);
      if (!numbers.length) return;
      plot.add(typeof event.time === 'number' ? event.time * 1000 : now(), numbers);
      draw();
    },
    dispose() {
      if (timer !== null) clearInterval(timer);
      timer = null;
    },
  };
}
