// Moving the page to another gateway's console when its own stays unreachable (docs/console.md,
// "Several gateways"). No DOM here: tested under node.
//
// The gateway refuses requests from pages of other origins and sends no CORS headers, so the
// page cannot talk to another gateway; it can only become that gateway's page, by a top-level
// navigation. Before it goes it asks, with a `no-cors` GET of the other console's icon, whether
// anything answers there at all (the answer is opaque: nothing of it is read), so that it never
// leaves a working page for a browser's error page.
//
// The page's URL carries the state: `gateways` (the other consoles, kept on every move) and
// `tried` (the consoles already left in this round, the last one being where it came from). A
// page whose stream opens ends the round (`tried` is dropped); one whose every other gateway is
// tried or silent stays where it is and says so, so dead gateways never pass the page around.

/** Gateways one page takes at most: a list is written by hand, and each costs a probe. */
export const MAX_GATEWAYS = 16;
/** How long the page's own gateway may stay unreachable before the page looks elsewhere. */
export const FAILOVER_AFTER_MS = 10000;
/** How long a probe of another gateway may take before it counts as silent. */
export const PROBE_TIMEOUT_MS = 3000;
/** What a probe asks for: a small file every console serves. */
export const PROBE_PATH = 'console/favicon.svg';

/**
 * A console address as the page compares and carries them: an absolute http(s) URL without its
 * query, fragment or credentials, ending in `/`. Throws a plain-worded Error for anything else
 * (`javascript:`, a relative path, a URL with a user name).
 */
export function consoleAddress(text) {
  let url;
  try {
    url = new URL(String(text).trim());
  } catch {
    throw new Error(`not an absolute URL: ${JSON.stringify(String(text).slice(0, 200))}`);
  }
  if (url.protocol !== 'http:' && url.protocol !== 'https:') {
    throw new Error(`only http and https consoles are taken, not ${url.protocol}`);
  }
  if (url.username || url.password) throw new Error(`a console URL carries no credentials: ${url.host}`);
  const path = url.pathname.endsWith('/') ? url.pathname : url.pathname.replace(/[^/]*$/, '');
  return `${url.origin}${path}`;
}

/**
 * The `gateways` (or `tried`) parameter: comma-separated console URLs, as addresses, without
 * repeats, at most MAX_GATEWAYS; `rejected` lists what was not taken, with why.
 */
export function parseGateways(text) {
  const gateways = [];
  const rejected = [];
  for (const item of String(text ?? '').split(',')) {
    if (!item.trim()) continue;
    try {
      const address = consoleAddress(item);
      if (gateways.includes(address)) continue;
      if (gateways.length >= MAX_GATEWAYS) {
        rejected.push(`${item.trim().slice(0, 200)}: more than ${MAX_GATEWAYS} gateways`);
        continue;
      }
      gateways.push(address);
    } catch (e) {
      rejected.push(e.message);
    }
  }
  return { gateways, rejected };
}

/** What a page's URL says: its own console address, the round of gateways, what was tried. */
export function failoverState(href) {
  const url = new URL(href);
  const own = consoleAddress(url.href);
  const listed = parseGateways(url.searchParams.get('gateways'));
  const tried = parseGateways(url.searchParams.get('tried')).gateways;
  // The round: every gateway listed, the page's own included (it may be missing from the list).
  const round = listed.gateways.includes(own) ? listed.gateways : [own, ...listed.gateways];
  return { own, round, tried, rejected: listed.rejected, from: tried.at(-1) ?? null };
}

/**
 * The gateways to try, in order: those after `own` in the round, wrapping round, neither the
 * page's own nor any already tried. Empty: the round is over.
 */
export function candidates({ own, round, tried }) {
  const start = round.indexOf(own);
  const ordered = start < 0 ? round : [...round.slice(start + 1), ...round.slice(0, start)];
  return ordered.filter((address) => address !== own && !tried.includes(address));
}

/**
 * The URL of `target`'s console for a page leaving `own`: the same gateway list, `own` added
 * to what was tried, and the same fragment (the selected service).
 */
export function moveUrl(target, { own, round, tried }, hash = '') {
  const url = new URL(target);
  url.searchParams.set('gateways', round.join(','));
  url.searchParams.set('tried', [...tried.filter((a) => a !== own), own].join(','));
  url.hash = hash;
  return url.href;
}

/** The page's URL with the round ended (`tried` dropped): its stream is open here. */
export function withRoundEnded(href) {
  const url = new URL(href);
  url.searchParams.delete('tried');
  return url.href;
}

/**
 * Watches the page's stream state and moves the page when its gateway stays unreachable.
 * `probe(address)` resolves to true when anything answers there; `move(url)` navigates;
 * `notice(text)` shows a line in the top bar; `endRound()` drops `tried` from the page's URL.
 */
export class Failover {
  constructor({
    href,
    hash = () => '',
    probe,
    move,
    notice = () => {},
    endRound = () => {},
    afterMs = FAILOVER_AFTER_MS,
    timers = globalThis,
  }) {
    Object.assign(this, { hash, probe, move, notice, endRound, afterMs, timers });
    this.state = failoverState(href);
    this._timer = null;
    this._looking = false;
    this.moved = false;
    this.stayed = false;
    if (this.state.from) this.notice(`moved here from ${this.state.from} (unreachable)`);
    if (this.state.rejected.length) this.notice(`gateways not taken: ${this.state.rejected.join('; ')}`);
  }

  /** Whether there is anywhere else to go at all (a list of gateways was given). */
  get enabled() {
    return this.state.round.length > 1;
  }

  /** Hear the stream's state ("open", "connecting", "closed"). */
  stateChanged(state) {
    if (!this.enabled || this.moved) return;
    if (state === 'open') {
      this._cancel();
      if (this.stayed) this.notice('');
      this.stayed = false;
      if (this.state.tried.length) {
        this.state = { ...this.state, tried: [] };
        this.endRound();
      }
      return;
    }
    if (this._timer === null && !this._looking) {
      this._timer = this.timers.setTimeout(() => this._look(), this.afterMs);
    }
  }

  _cancel() {
    if (this._timer !== null) this.timers.clearTimeout(this._timer);
    this._timer = null;
  }

  async _look() {
    this._timer = null;
    this._looking = true;
    try {
      for (const address of candidates(this.state)) {
        if (await this.probe(address)) {
          this.moved = true;
          this.move(moveUrl(address, this.state, this.hash()));
          return;
        }
      }
      const tried = [this.state.own, ...this.state.tried, ...candidates(this.state)];
      this.stayed = true;
      this.notice(`every gateway unreachable (tried ${tried.join(', ')}); staying here`);
    } finally {
      this._looking = false;
    }
    // Stay, and look again later: only a gateway that answers a probe is ever gone to.
    this._timer = this.timers.setTimeout(() => this._look(), this.afterMs * 3);
  }
}

/** A probe by `fetch`: true when `address` answers at all (any status), false otherwise. */
export function fetchProbe(fetchImpl = globalThis.fetch?.bind(globalThis), timeoutMs = PROBE_TIMEOUT_MS) {
  return async (address) => {
    const controller = new AbortController();
    const timer = setTimeout(() => controller.abort(), timeoutMs);
    try {
      await fetchImpl(new URL(PROBE_PATH, address).href, {
        mode: 'no-cors',
        cache: 'no-store',
        credentials: 'omit',
        signal: controller.signal,
      });
      return true;
    } catch {
      return false;
    } finally {
      clearTimeout(timer);
    }
  };
}
