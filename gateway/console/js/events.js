// One Server-Sent Events stream per page for every subscription (docs/http-api.md, "Server-Sent Events").
//
// Widgets subscribe to selectors "SERVICE/PATH" (`*` matches one segment: "*/location"). The
// multiplexer keeps the subscriptions in a map, opens one EventSource whose URL names them all,
// and dispatches each `value` event to the subscriptions it matches. When the set of selectors
// changes it reopens the stream, debounced, so that a burst of changes costs one reconnect.
//
// Reconnects: EventSource retries a dropped stream by itself (sending Last-Event-ID; the gateway
// answers with the snapshot marked gap). A watchdog takes over when that is not enough: a stream
// the browser gave up on (an HTTP error), or one that failed several times in a row, is reopened
// after an exponential backoff, which a completed snapshot (`sync`) resets.
//
// The gateway bounds the selectors of one Listen; the page may follow many more (a group of 50
// robots shows some 700 properties). The stream names a cover of the subscriptions
// (js/selector_cover.js: a few wildcards where many exact selectors would not fit), and the
// events the cover brings that no subscription wants are thrown away here, and counted.

import { Backoff } from './backoff.js';
import { coverSelectors, covers } from './selector_cover.js';

export const EVENTS_URL = '/api/v1/events';
/**
 * Selectors the page's stream names at most: the gateway's default `[limits] max_selectors` for
 * one Listen. A gateway configured lower says so in its error, and the page takes its word.
 */
export const MAX_SELECTORS = 64;
/** Distinct selectors the page subscribes to at most (the stream covers them with fewer). */
export const MAX_SUBSCRIPTIONS = 4096;
/** Latest events kept for subscribers that join a selector the stream already follows. */
export const MAX_CACHED = 4096;
/** Native errors in a row before the watchdog replaces EventSource's own fixed-delay retry. */
const ERRORS_BEFORE_BACKOFF = 3;
/** A stream still not open after this long is closed and opened again (after the backoff). */
const CONNECT_TIMEOUT_MS = 20000;

/** Split "SERVICE/PATH" at the first "/"; throws for a selector without one. */
export function splitSelector(selector) {
  const slash = selector.indexOf('/');
  if (slash <= 0 || slash === selector.length - 1) {
    throw new Error(`a selector is SERVICE/PATH, got ${JSON.stringify(selector)}`);
  }
  return [selector.slice(0, slash), selector.slice(slash + 1)];
}

/** Whether `pattern` (segments split on `sep`, `*` = one segment) matches `name`. */
function patternMatches(pattern, name, sep) {
  if (!pattern.includes('*')) return pattern === name;
  const want = pattern.split(sep);
  const have = name.split(sep);
  return want.length === have.length && want.every((w, i) => w === '*' || w === have[i]);
}

/** Whether the selector "SERVICE/PATH" matches an event of `service` and `path`. */
export function selectorMatches(selector, service, path) {
  const [s, p] = splitSelector(selector);
  return patternMatches(s, service, '\u0000') && patternMatches(p, path, '.');
}

/**
 * The service and property names an error message points at: quoted ('rover1') or after
 * "device" / "service" ("device rover1 at tcp://…"). The gateway's Listen errors name what failed.
 */
export function namesIn(message) {
  const names = new Set();
  const pattern = /'([A-Za-z0-9_.-]{1,256})'|`([A-Za-z0-9_.-]{1,256})`|\b(?:device|service)\s+([A-Za-z0-9_-]{1,64})/g;
  for (const m of String(message ?? '').matchAll(pattern)) names.add(m[1] ?? m[2] ?? m[3]);
  return names;
}

/**
 * The selectors an error message names: those whose whole path it names if any, else those
 * whose service or a segment of whose path it names.
 */
export function namedSelectors(message, selectors) {
  const names = namesIn(message);
  const all = [...selectors].map((selector) => [selector, ...splitSelector(selector)]);
  const exact = all.filter(([, , path]) => !path.includes('*') && names.has(path));
  // "`sensors.battery`: `sensors` has no `battery`" names the deeper one: a namespace named
  // beside a property under it is where the property was looked for, not what failed.
  const deepest = exact.filter(([, , path]) => !exact.some(([, , other]) => other.startsWith(`${path}.`)));
  if (deepest.length) return deepest.map(([selector]) => selector);
  const named = all.filter(
    ([, service, path]) => names.has(service) || path.split('.').some((seg) => seg !== '*' && names.has(seg)),
  );
  if (named.length || !names.size) return named.map(([selector]) => selector);
  // A name no selector spells: a wildcard service (*/location) reached it.
  return all.filter(([, service]) => service === '*').map(([selector]) => selector);
}

/** The stream's URL for these selectors, in a stable order. */
export function eventsUrl(selectors, base = EVENTS_URL) {
  const query = new URLSearchParams();
  for (const selector of [...selectors].sort()) query.append('sel', selector);
  return `${base}?${query}`;
}

/**
 * The page's event multiplexer. `onState(state, detail)` hears "open", "connecting" or
 * "closed" (with the seconds to the next try, when one is planned).
 */
export class EventMux {
  constructor({
    url = EVENTS_URL,
    EventSourceImpl = globalThis.EventSource,
    fetchImpl = globalThis.fetch?.bind(globalThis),
    debounceMs = 80,
    maxSelectors = MAX_SELECTORS,
    backoff = new Backoff(),
    onState = () => {},
    timers = globalThis,
    clock = () => Date.now(),
    onLimit = () => {},
  } = {}) {
    Object.assign(this, { url, EventSourceImpl, fetchImpl, debounceMs, maxSelectors, backoff, onState, timers, clock });
    /** Hears the gateway's selector limit when a stream was refused for passing it. */
    this.onLimit = onLimit;
    /** selector -> {until, backoff}: left out of the stream for a while (its service failed). */
    this._quarantine = new Map();
    this._readmitTimer = null;
    /** selector -> Set of subscriptions ({onValue, onSync, onError}). */
    this.subscriptions = new Map();
    this._wildcards = new Set(); // the subscribed selectors with a `*`: matched one by one
    this._avoided = new Map(); // exact selector -> how many asked that no wildcard covers it
    this._streamMembers = new Map(); // cover selector of the stream -> the subscriptions it carries
    this._streamWanted = new Set(); // the subscriptions the open stream carries
    this._leftOut = new Set(); // subscriptions no cover within the limit could carry
    this.received = 0; // value events the streams brought
    this.unwanted = 0; // of them, those no subscription matched (the cover's cost)
    this.state = 'closed';
    this.source = null;
    this._previous = null; // the stream being replaced, delivering until its successor opens
    this._streamSelectors = new Set(); // the selectors of the open stream
    this._latest = new Map(); // "service\0path" -> the last value event, oldest first
    this._confirmed = new Set(); // selectors of a stream that reached `sync`: known good
    this._synced = false; // the open stream's snapshot is complete
    this._reopenTimer = null;
    this._watchdog = null;
    this._errorsInRow = 0;
    this._opened = false;
  }

  /**
   * Follow `selector`; returns a function that ends this subscription. Handlers:
   * onValue({service, path, value, gap, removed, time}), onSync(), and onError({code, message},
   * {dropped}): `dropped` when the subscription has ended (else it is tried again later).
   */
  subscribe(selector, { onValue = () => {}, onSync = () => {}, onError = () => {} } = {}) {
    splitSelector(selector);
    let subs = this.subscriptions.get(selector);
    if (!subs) {
      if (this.subscriptions.size >= MAX_SUBSCRIPTIONS) {
        throw new Error(`this page follows ${MAX_SUBSCRIPTIONS} selectors already; close a view first`);
      }
      subs = new Set();
      this.subscriptions.set(selector, subs);
      if (selector.includes('*')) this._wildcards.add(selector);
      this._schedule(this.debounceMs);
    }
    const sub = { onValue, onSync, onError };
    subs.add(sub);
    if (this.source && this._streamCovers(selector)) {
      // The stream follows this selector already and sends no new snapshot for it: the latest
      // values it delivered stand in for one (after the caller has finished setting up).
      this.timers.setTimeout(() => this._replay(selector, sub), 0);
    }
    return () => this._unsubscribe(selector, sub);
  }

  _unsubscribe(selector, sub) {
    const subs = this.subscriptions.get(selector);
    if (!subs || !subs.delete(sub)) return;
    if (!subs.size) this._forget(selector);
  }

  _forget(selector) {
    this.subscriptions.delete(selector);
    this._wildcards.delete(selector);
    this._quarantine.delete(selector);
    this._leftOut.delete(selector);
    this._schedule(this.debounceMs);
  }

  /**
   * Keep `selector` (an exact one: a camera's frame) out of every wildcard the stream uses: the
   * page reads it on a route of its own. Returns the function that ends the request.
   */
  avoid(selector) {
    splitSelector(selector);
    this._avoided.set(selector, (this._avoided.get(selector) ?? 0) + 1);
    this._schedule(this.debounceMs);
    let done = false;
    return () => {
      if (done) return;
      done = true;
      const left = this._avoided.get(selector) - 1;
      if (left > 0) this._avoided.set(selector, left);
      else this._avoided.delete(selector);
    };
  }

  /** Whether the open stream carries `selector` already (one of its cover selectors matches it). */
  _streamCovers(selector) {
    if (this._streamSelectors.has(selector)) return true;
    for (const wide of this._streamSelectors) if (covers(wide, selector)) return true;
    return false;
  }

  /**
   * What the stream costs: `selectors` it names, `subscriptions` it carries, value events
   * `received`, and `unwanted` ones (matched by a cover's wildcard but by no subscription).
   */
  stats() {
    return {
      selectors: [...this._streamSelectors],
      subscriptions: this.subscriptions.size,
      leftOut: this._leftOut.size,
      received: this.received,
      unwanted: this.unwanted,
    };
  }

  /** The selectors the stream should carry now: every subscription but those left out for a while. */
  _wanted() {
    const now = this.clock();
    return new Set([...this.subscriptions.keys()].filter((s) => !(this._quarantine.get(s)?.until > now)));
  }

  /** Take the selectors whose time out is over back into the stream, and wait for the next ones. */
  _readmit() {
    this._readmitTimer = null;
    const now = this.clock();
    const later = [...this._quarantine.values()].map((q) => q.until).filter((until) => until > now);
    if (later.length) this._readmitTimer = this.timers.setTimeout(() => this._readmit(), Math.min(...later) - now);
    this._schedule(0);
  }

  /** Close the stream but keep the subscriptions (the page is hidden in the back-forward cache). */
  suspend() {
    this._clearTimers();
    this._closeSource();
    this._streamSelectors = new Set();
    this._setState('closed');
  }

  /** Open the stream again now, with every subscription (a new token, a page shown again). */
  reconnect() {
    this._closeSource();
    this._streamSelectors = new Set();
    this.backoff.reset();
    this._schedule(0);
  }

  /** Close the stream for good and forget every subscription. */
  close() {
    this._clearTimers();
    this._closeSource();
    this.subscriptions.clear();
    this._setState('closed');
  }

  // -- the stream ----------------------------------------------------------------------------

  _schedule(delayMs, detail = undefined) {
    if (this._reopenTimer !== null) this.timers.clearTimeout(this._reopenTimer);
    this._reopenTimer = this.timers.setTimeout(() => {
      this._reopenTimer = null;
      this._open();
    }, delayMs);
    if (detail !== undefined) this._setState('closed', detail);
  }

  _retryLater() {
    this._closeSource();
    const delay = this.backoff.next();
    this._schedule(delay, { retryInSeconds: Math.ceil(delay / 1000) });
  }

  _open() {
    const wanted = this._wanted();
    const { cover, members, left } = coverSelectors(wanted, this.maxSelectors, { avoid: this._avoided.keys() });
    this._noteLeftOut(left);
    const selectors = new Set(cover);
    const same =
      selectors.size === this._streamSelectors.size && [...selectors].every((s) => this._streamSelectors.has(s));
    const carried = new Set([...members.values()].flat());
    if (same && this.source && this.source.readyState !== 2) {
      this._streamMembers = members; // already following exactly these
      this._streamWanted = carried;
      return;
    }
    // Make before break: an open stream goes on delivering until its successor is open, so
    // selecting another service neither blanks the page nor shows it as disconnected.
    const previous = this.source && this.source.readyState === 1 && this._opened ? this.source : null;
    if (previous) {
      this._closePrevious();
      this._previous = previous;
      this.source = null;
    }
    this._closeSource(false);
    this._streamSelectors = selectors;
    this._streamMembers = members;
    this._streamWanted = carried;
    for (const [key, event] of this._latest) {
      // What no selector follows any more would only be stale if it came back.
      if (![...selectors].some((s) => selectorMatches(s, event.service, event.path))) this._latest.delete(key);
    }
    if (!selectors.size) {
      this._closePrevious();
      this._setState('closed');
      return;
    }
    this._synced = false;
    const url = eventsUrl(selectors, this.url);
    const source = new this.EventSourceImpl(url, { withCredentials: false });
    this.source = source;
    this._opened = false;
    this._errorsInRow = 0;
    if (!previous) this._setState('connecting');
    const current = () => source === this.source;
    const old = () => source === this._previous;
    source.addEventListener('open', () => {
      if (!current()) return;
      this._closePrevious();
      this._opened = true;
      this._errorsInRow = 0;
      this._setState('open');
    });
    source.addEventListener('value', (e) => (current() || old()) && this._onValue(e.data));
    source.addEventListener('sync', () => current() && this._onSync());
    source.addEventListener('error', (e) => {
      if (old()) {
        this._closePrevious(); // its successor is on the way
        return;
      }
      if (!current()) return;
      // The gateway's own `event: error` carries data; the browser's connection error does not.
      if (typeof e.data === 'string') this._onServerError(e.data);
      else this._onConnectionError(url);
    });
    this._watchdog = this.timers.setTimeout(() => {
      this._watchdog = null;
      if (current() && source.readyState !== 1) this._retryLater();
    }, CONNECT_TIMEOUT_MS);
  }

  /** Tell the subscriptions that the limit leaves out now (once), and forget those back in. */
  _noteLeftOut(left) {
    const now = new Set(left);
    for (const selector of now) {
      if (this._leftOut.has(selector)) continue;
      const error = {
        code: 'RESOURCE_EXHAUSTED',
        message: `the stream's limit of ${this.maxSelectors} selectors leaves ${selector} out`,
      };
      for (const sub of this.subscriptions.get(selector) ?? []) sub.onError(error, { dropped: false });
    }
    this._leftOut = now;
  }

  _closePrevious() {
    if (this._previous) {
      this._previous.close();
      this._previous = null;
    }
  }

  _closeSource(withPrevious = true) {
    if (this._watchdog !== null) {
      this.timers.clearTimeout(this._watchdog);
      this._watchdog = null;
    }
    if (this.source) {
      this.source.close();
      this.source = null;
    }
    if (withPrevious) this._closePrevious();
  }

  _clearTimers() {
    if (this._reopenTimer !== null) this.timers.clearTimeout(this._reopenTimer);
    this._reopenTimer = null;
    if (this._readmitTimer !== null) this.timers.clearTimeout(this._readmitTimer);
    this._readmitTimer = null;
  }

  _setState(state, detail = {}) {
    this.state = state;
    this.onState(state, detail);
  }

  _onValue(data) {
    let event;
    try {
      event = JSON.parse(data);
    } catch {
      return; // not ours to guess at: the gateway sends JSON
    }
    if (typeof event?.service !== 'string' || typeof event?.path !== 'string') return;
    this.dispatch(event);
  }

  _replay(selector, sub) {
    if (!this.subscriptions.get(selector)?.has(sub)) return; // gone meanwhile
    if (selector.includes('*')) {
      for (const event of this._latest.values()) {
        if (selectorMatches(selector, event.service, event.path)) sub.onValue(event);
      }
    } else {
      const [service, path] = splitSelector(selector);
      const event = this._latest.get(`${service}\u0000${path}`);
      if (event) sub.onValue(event);
    }
    // A subscription the synced stream already covers has had its snapshot: the values above.
    if (this._confirmed.has(selector) || (this._synced && this._streamCovers(selector))) sub.onSync();
  }

  _remember(event) {
    const key = `${event.service}\u0000${event.path}`;
    this._latest.delete(key);
    if (event.removed) return;
    this._latest.set(key, event);
    if (this._latest.size > MAX_CACHED) this._latest.delete(this._latest.keys().next().value);
  }

  /** Hand one value event to every subscription whose selector matches it. */
  dispatch(event) {
    this._remember(event);
    this.received += 1;
    // An exact subscription is found by its name; only the wildcard ones are matched in turn
    // (a view of a large group subscribes to hundreds of exact selectors).
    const exact = `${event.service}/${event.path}`;
    const matched = [];
    if (this.subscriptions.has(exact)) matched.push(exact);
    for (const selector of this._wildcards) {
      if (selectorMatches(selector, event.service, event.path)) matched.push(selector);
    }
    if (!matched.length) this.unwanted += 1;
    for (const selector of matched) {
      for (const sub of [...(this.subscriptions.get(selector) ?? [])]) {
        try {
          sub.onValue(event);
        } catch (e) {
          console.error('a subscriber of', selector, 'failed:', e);
        }
      }
    }
  }

  _onSync() {
    this._synced = true;
    for (const selector of this._streamWanted) {
      this._confirmed.add(selector);
      this._quarantine.delete(selector); // it works again: a later failure starts a short time out
    }
    this.backoff.reset();
    this._errorsInRow = 0;
    for (const subs of this.subscriptions.values()) for (const sub of subs) sub.onSync();
  }

  /**
   * The Listen failed (e.g. NOT_FOUND) and the stream ends. The selectors added since the last
   * good snapshot are the suspects: their subscriptions hear the error and are dropped, and the
   * rest are reopened at once. Without suspects everyone hears it and the retry backs off.
   */
  _onServerError(data) {
    let error;
    try {
      error = JSON.parse(data);
    } catch {
      error = { code: 'UNKNOWN', message: String(data).slice(0, 200) };
    }
    this._failed(error);
  }

  _failed(error) {
    this._closeSource();
    const limit = /at most (\d+) selectors/.exec(error?.message ?? '');
    if (error?.code === 'RESOURCE_EXHAUSTED' && limit && Number(limit[1]) < this.maxSelectors) {
      // The gateway allows fewer selectors than the page thought: the same subscriptions,
      // covered again with fewer (wider) selectors. Nobody's subscription failed.
      this.maxSelectors = Math.max(1, Number(limit[1]));
      this.onLimit(this.maxSelectors);
      this._schedule(0);
      return;
    }
    // The culprits: the subscriptions the error names (a Listen error names the service or the
    // property that failed), else those added since the last good snapshot.
    const carried = this._streamWanted;
    const named = namedSelectors(error?.message, carried);
    const suspects = [...carried].filter((s) => !this._confirmed.has(s));
    let culprits = named.length < carried.size ? named : [];
    if (!culprits.length) culprits = suspects;
    if (!culprits.length) {
      for (const subs of this.subscriptions.values()) for (const sub of subs) sub.onError(error, { dropped: false });
      this._retryLater();
      return;
    }
    // A service that cannot be reached now (a device unplugged) is left out for a growing while
    // and tried again; anything else (no such property, not allowed) is dropped: its
    // subscribers hear why, and the rest of the page stays live.
    const transient = ['UNAVAILABLE', 'DEADLINE_EXCEEDED'].includes(error?.code);
    const now = this.clock();
    for (const selector of culprits) {
      const subs = this.subscriptions.get(selector);
      if (transient) {
        const q = this._quarantine.get(selector) ?? {
          backoff: new Backoff({ initial: 5000, max: 60000, random: this.backoff.random }),
        };
        q.until = now + q.backoff.next();
        this._quarantine.set(selector, q);
      } else if (subs) {
        this._forget(selector);
      }
      for (const sub of subs ?? []) sub.onError(error, { dropped: !transient });
    }
    if (transient) {
      if (this._readmitTimer !== null) this.timers.clearTimeout(this._readmitTimer);
      const soonest = Math.min(...[...this._quarantine.values()].map((q) => q.until).filter((u) => u > now));
      this._readmitTimer = this.timers.setTimeout(() => this._readmit(), soonest - now);
    }
    this._schedule(0);
  }

  _onConnectionError(url) {
    this._errorsInRow += 1;
    const source = this.source;
    if (source && source.readyState === 2 && !this._opened && this.fetchImpl) {
      // The browser gave up before the stream opened: an HTTP error whose JSON says why.
      this._closeSource();
      this._diagnose(url);
      return;
    }
    if (source && source.readyState !== 2 && this._errorsInRow < ERRORS_BEFORE_BACKOFF) {
      this._setState('connecting');
      return; // EventSource retries by itself, with Last-Event-ID
    }
    this._retryLater();
  }

  async _diagnose(url) {
    const controller = new AbortController();
    let error = null;
    try {
      const response = await this.fetchImpl(url, {
        headers: { Accept: 'text/event-stream' },
        signal: controller.signal,
      });
      if (!response.ok) {
        const body = await response.json().catch(() => null);
        error = body?.error ?? { code: 'UNAVAILABLE', message: `HTTP ${response.status}` };
      }
    } catch {
      error = null; // unreachable: a plain retry
    } finally {
      controller.abort(); // never keep a second stream open
    }
    if (this.source !== null || this._reopenTimer !== null) return; // something reopened meanwhile
    // A refusal of the request as a whole (too many streams, not authenticated) is nobody's
    // selector in particular: every subscription keeps waiting through the backoff.
    if (error && !['RESOURCE_EXHAUSTED', 'UNAVAILABLE', 'UNAUTHENTICATED'].includes(error.code)) {
      this._failed(error);
    } else {
      if (error) {
        for (const subs of this.subscriptions.values()) for (const sub of subs) sub.onError(error, { dropped: false });
      }
      this._retryLater();
    }
  }
}
