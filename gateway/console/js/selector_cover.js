// Covering many selectors with a few: the page's one event stream names its selectors in its URL,
// and the gateway allows `[limits] max_selectors` (64) in one Listen. A view of a group of 50
// robots follows some 700 properties; `swarm/robots.*.location` follows 50 of them with one
// selector. No DOM here: tested under node.
//
// A selector is SERVICE/PATH, and `*` matches one segment (a service, or one name of a dotted
// path). The cover starts from the selectors themselves and widens step by step only while it
// has more than the limit: each step puts `*` in place of one name where that makes the most
// selectors one, so the stream carries what the page shows and little else. What the page then
// receives beyond its subscriptions is thrown away by the multiplexer (and counted there).
//
// Widening rules, chosen for what a wildcard costs on the gateway and on the wire:
// * A path name becomes `*` within its service (`scout1/robots.*.location`).
// * The service becomes `*` only for a path without `*` (`*/location`): a selector such as `*/*`
//   would follow every property of every service, camera frames included.
// * No widening may cover an avoided property (a binary one the page reads on its own route).

/** Split "SERVICE/PATH" into [SERVICE, ...names of PATH]. */
function partsOf(selector) {
  const slash = selector.indexOf('/');
  return [selector.slice(0, slash), ...selector.slice(slash + 1).split('.')];
}

function selectorOf(parts) {
  return `${parts[0]}/${parts.slice(1).join('.')}`;
}

/** Whether the selector `wide` matches everything `narrow` matches (both as parts). */
export function coversParts(wide, narrow) {
  if (wide.length !== narrow.length) return false;
  return wide.every((name, i) => name === '*' || name === narrow[i]);
}

/** Whether the selector text `wide` matches everything `narrow` does. */
export function covers(wide, narrow) {
  return coversParts(partsOf(wide), partsOf(narrow));
}

function stars(parts) {
  return parts.reduce((n, name) => n + (name === '*' ? 1 : 0), 0);
}

/** The selectors one step wider than `parts` that the rules allow. */
function widenings(parts, avoided) {
  const found = [];
  for (let i = 1; i < parts.length; i += 1) {
    if (parts[i] === '*') continue;
    found.push(parts.map((name, j) => (j === i ? '*' : name)));
  }
  if (parts[0] !== '*' && stars(parts) === 0) found.push(['*', ...parts.slice(1)]);
  return found.filter((wide) => !avoided.some((a) => coversParts(wide, a)));
}

/**
 * The fewest widening steps that bring `selectors` to at most `limit`. Returns `{cover, members,
 * left}`: `cover` the selectors the stream names (sorted); `members` a Map from each of them to
 * the given selectors it stands for; `left` the given selectors no cover within the rules and the
 * limit could take (followed by nothing; empty unless the limit is very low). `avoid` lists
 * exact selectors no widening may cover.
 */
export function coverSelectors(selectors, limit, { avoid = [] } = {}) {
  const avoided = [...avoid].map(partsOf);
  // Each selector once; one that another given selector already matches rides along with it.
  const given = [...new Set(selectors)].map((s) => ({ key: s, parts: partsOf(s) }));
  const wild = given.filter((g) => g.parts.includes('*'));
  const items = new Map(); // cover selector -> {parts, members: [given selectors]}
  for (const g of given) {
    if (!wild.some((w) => w.key !== g.key && coversParts(w.parts, g.parts) && !coversParts(g.parts, w.parts))) {
      items.set(g.key, { parts: g.parts, members: [g.key] });
    }
  }
  for (const g of given) {
    if (items.has(g.key)) continue;
    const [host] = [...items].find(([, item]) => coversParts(item.parts, g.parts));
    items.get(host).members.push(g.key);
  }
  const max = Math.max(1, limit);
  while (items.size > max) {
    // Every allowed one-step widening, with the current selectors it would make one.
    const candidates = new Map();
    for (const [key, item] of items) {
      for (const wide of widenings(item.parts, avoided)) {
        const wideKey = selectorOf(wide);
        let candidate = candidates.get(wideKey);
        if (!candidate) {
          candidate = { key: wideKey, parts: wide, absorbs: new Set(items.has(wideKey) ? [wideKey] : []) };
          candidates.set(wideKey, candidate);
        }
        candidate.absorbs.add(key);
      }
    }
    const merging = [...candidates.values()].filter((c) => c.absorbs.size >= 2);
    if (!merging.length) break;
    // Most selectors made one first; then the narrowest (fewest `*`), then one within a service.
    merging.sort(
      (a, b) =>
        b.absorbs.size - a.absorbs.size ||
        stars(a.parts) - stars(b.parts) ||
        (a.parts[0] === '*') - (b.parts[0] === '*') ||
        (a.key < b.key ? -1 : 1),
    );
    // Every merge as large as the best, while it is needed and its selectors are still there.
    const size = merging[0].absorbs.size;
    for (const candidate of merging) {
      if (candidate.absorbs.size < size || items.size <= max) break;
      if (![...candidate.absorbs].every((key) => items.has(key))) continue;
      // Whatever else the new selector matches (a narrower one already there) joins it too.
      const members = [];
      for (const [key, item] of items) {
        if (candidate.absorbs.has(key) || coversParts(candidate.parts, item.parts)) {
          members.push(...item.members);
          items.delete(key);
        }
      }
      items.set(candidate.key, { parts: candidate.parts, members });
    }
  }
  let kept = [...items];
  const left = [];
  if (kept.length > max) {
    // Nothing more can be made one: the selectors that stand for the most stay.
    kept.sort((a, b) => b[1].members.length - a[1].members.length || (a[0] < b[0] ? -1 : 1));
    for (const [, item] of kept.slice(max)) left.push(...item.members);
    kept = kept.slice(0, max);
  }
  kept.sort((a, b) => (a[0] < b[0] ? -1 : 1));
  return {
    cover: kept.map(([key]) => key),
    members: new Map(kept.map(([key, item]) => [key, item.members])),
    left,
  };
}
