// The value grammar of the Property Service, as the console reads and writes it.
//
// Values travel as text (services/kernel/values/grammar.py and markers.py are the reference):
//   number  0.5   -3e-2          boolean  true / false (also 1/0, on/off, yes/no)
//   vector  (1 2.5 -0.03)        list     ((1 2) (a b (c 1)))      names  (location velocity)
//   marker  <marker><location>(1 2)</location><color>(1 0 0)</color></marker>
// Parsers are strict and throw ValueFormatError with a message that says what was expected;
// this module touches no DOM, so node's test runner checks it (tests/console_js/).

/** Longest value text accepted, as the services' grammar (MAX_VALUE_LENGTH). */
export const MAX_VALUE_LENGTH = 65536;
/** Deepest nesting of lists and marker elements (MAX_LIST_DEPTH). */
export const MAX_DEPTH = 32;

export class ValueFormatError extends Error {
  constructor(message) {
    super(message);
    this.name = 'ValueFormatError';
    this.code = 'INVALID_ARGUMENT';
  }
}

const NUMBER = /^[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?$/;

function shown(text) {
  const clipped = text.length > 40 ? `${text.slice(0, 39)}…` : text;
  return JSON.stringify(clipped);
}

function fail(expected, text, why) {
  return new ValueFormatError(`expected ${expected}, got ${shown(text)}${why ? `: ${why}` : ''}`);
}

function checkLength(text, expected) {
  if (typeof text !== 'string') throw new ValueFormatError(`expected ${expected}, got a ${typeof text}`);
  if (text.length > MAX_VALUE_LENGTH) {
    throw new ValueFormatError(
      `expected ${expected}, got a value of ${text.length} characters: the limit is ${MAX_VALUE_LENGTH}`,
    );
  }
}

function toNumber(token) {
  if (!NUMBER.test(token)) return null;
  const x = Number(token);
  return Number.isFinite(x) ? x : null;
}

/** A finite decimal number: "0.5", "-3", "1e-3". */
export function parseNumber(text) {
  const expected = 'a number like "0.5"';
  checkLength(text, expected);
  const token = text.trim();
  const x = toNumber(token);
  if (x === null) {
    let why = token ? `${shown(token)} is not a number` : 'the value is empty';
    if (token.includes(',')) why += ' (use a dot as the decimal point)';
    throw fail(expected, text, why);
  }
  return x;
}

/** The shortest text that parses back to exactly x; integral values without a fraction ("2"). */
export function formatNumber(x) {
  if (typeof x !== 'number' || !Number.isFinite(x)) {
    throw new ValueFormatError(`cannot format ${String(x)}: only finite numbers are values`);
  }
  if (Object.is(x, -0)) return '0';
  return String(x);
}

/**
 * Unix seconds (value text such as "1763862603.25") as the local date and time,
 * "2026-11-23 01:50:03"; null when the text is not a finite number.
 */
export function formatTime(text) {
  const seconds = Number(String(text).trim());
  if (String(text).trim() === '' || !Number.isFinite(seconds)) return null;
  const d = new Date(seconds * 1000);
  if (Number.isNaN(d.getTime())) return null;
  const two = (n) => String(n).padStart(2, '0');
  return (
    `${d.getFullYear()}-${two(d.getMonth() + 1)}-${two(d.getDate())} ` +
    `${two(d.getHours())}:${two(d.getMinutes())}:${two(d.getSeconds())}`
  );
}

const TRUE = new Set(['true', '1', 'on', 'yes']);
const FALSE = new Set(['false', '0', 'off', 'no']);

/** true/false, 1/0, on/off, yes/no (any case). */
export function parseBool(text) {
  const expected = 'a boolean ("true" or "false")';
  checkLength(text, expected);
  const word = text.trim().toLowerCase();
  if (TRUE.has(word)) return true;
  if (FALSE.has(word)) return false;
  throw fail(expected, text, 'also accepted: 1/0, on/off, yes/no');
}

export function formatBool(b) {
  return b ? 'true' : 'false';
}

/** "(1 2.5 -3e-2)" -> [1, 2.5, -0.03]; "()" is the empty vector. */
export function parseVector(text) {
  const expected = 'a vector like "(1 2 3)"';
  checkLength(text, expected);
  const body = text.trim();
  if (!body) throw fail(expected, text, 'the value is empty');
  if (!body.startsWith('(')) throw fail(expected, text, 'the numbers must be enclosed in parentheses');
  const close = body.indexOf(')');
  if (close < 0) throw fail(expected, text, 'unclosed "("');
  const inner = body.slice(1, close);
  if (inner.includes('(') || body.indexOf('(', close) >= 0) {
    throw fail(expected, text, 'a vector holds numbers only, not nested lists');
  }
  if (close + 1 < body.length) throw fail(expected, text, 'text after the closing ")"');
  const numbers = [];
  for (const token of inner.split(/\s+/).filter(Boolean)) {
    const x = toNumber(token);
    if (x === null) {
      const why = inner.includes(',')
        ? `${shown(token)} is not a number: separate the numbers with spaces, not commas`
        : `${shown(token)} is not a number`;
      throw fail(expected, text, why);
    }
    numbers.push(x);
  }
  return numbers;
}

/** [1, 2.5] -> "(1 2.5)". */
export function formatVector(numbers) {
  return `(${Array.from(numbers, formatNumber).join(' ')})`;
}

/** "((1 2) (a b (c 1)))" -> nested arrays of atom strings (numbers stay text). */
export function parseList(text) {
  const expected = 'a list like "((1 2) (a b))"';
  checkLength(text, expected);
  const stack = [];
  let result = null;
  for (const m of text.matchAll(/[()]|[^\s()]+/g)) {
    const token = m[0];
    if (result !== null) throw fail(expected, text, `unexpected ${shown(token)} after the end of the list`);
    if (token === '(') {
      if (stack.length >= MAX_DEPTH) throw fail(expected, text, `lists nest deeper than ${MAX_DEPTH} levels`);
      stack.push([]);
    } else if (token === ')') {
      if (!stack.length) throw fail(expected, text, `unmatched ")" at position ${m.index}`);
      const done = stack.pop();
      if (stack.length) stack[stack.length - 1].push(done);
      else result = done;
    } else if (stack.length) {
      stack[stack.length - 1].push(token);
    } else {
      throw fail(expected, text, 'a list must be enclosed in parentheses');
    }
  }
  if (stack.length) throw fail(expected, text, `${stack.length} unclosed "("`);
  if (result === null) throw fail(expected, text, 'the value is empty');
  return result;
}

/** Nested arrays of words, numbers and booleans -> "((1 2) (a b))". */
export function formatList(items, depth = 1) {
  if (depth > MAX_DEPTH) throw new ValueFormatError(`cannot format a list nested deeper than ${MAX_DEPTH}`);
  const parts = Array.from(items, (item) => {
    if (Array.isArray(item)) return formatList(item, depth + 1);
    if (typeof item === 'number') return formatNumber(item);
    if (typeof item === 'boolean') return formatBool(item);
    const word = String(item);
    if (!/^[^\s()]+$/.test(word)) {
      throw new ValueFormatError(`cannot put ${shown(word)} in a list: items are words without spaces or ()`);
    }
    return word;
  });
  return `(${parts.join(' ')})`;
}

/** "(location velocity)" -> ["location", "velocity"]. */
export function parseNames(text) {
  const items = parseList(text);
  items.forEach((item, i) => {
    if (Array.isArray(item)) throw fail('a list of names like "(a b)"', text, `item ${i + 1} is a nested list`);
  });
  return items;
}

// -- markers ---------------------------------------------------------------------------------

const TAG = /^[A-Za-z_][A-Za-z0-9_-]{0,63}$/;
const ENTITIES = { amp: '&', lt: '<', gt: '>', quot: '"', apos: "'" };
const MARKER_EXAMPLE = 'a marker like "<marker><location>(1 2)</location></marker>"';

function unescapeXml(text, whole) {
  return text.replace(/&(#x[0-9A-Fa-f]+|#[0-9]+|[A-Za-z]+);|&/g, (all, name) => {
    if (name === undefined) throw fail(MARKER_EXAMPLE, whole, 'a bare "&" (write &amp;)');
    if (name.startsWith('#x')) return String.fromCodePoint(parseInt(name.slice(2), 16));
    if (name.startsWith('#')) return String.fromCodePoint(parseInt(name.slice(1), 10));
    if (!(name in ENTITIES)) throw fail(MARKER_EXAMPLE, whole, `unknown entity &${name};`);
    return ENTITIES[name];
  });
}

function escapeXml(text) {
  return text.replace(/[&<>\r]/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '\r': '&#13;' })[c]);
}

/**
 * Read one element starting at text[pos] ('<'). Returns [node, end] where node is
 * {tag, fields} for an element with children, or {tag, text} for a leaf.
 */
function readElement(text, pos, depth) {
  if (depth > MAX_DEPTH) throw fail(MARKER_EXAMPLE, text, `elements nest deeper than ${MAX_DEPTH} levels`);
  if (text.startsWith('<!', pos) || text.startsWith('<?', pos)) {
    throw fail(MARKER_EXAMPLE, text, 'declarations, comments and processing instructions are not allowed');
  }
  const open = /^<([^\s<>/]+)(\s[^<>]*?)?(\/?)>/.exec(text.slice(pos, pos + 200));
  if (!open) throw fail(MARKER_EXAMPLE, text, `expected an element at position ${pos}`);
  const tag = open[1];
  if (!TAG.test(tag)) throw fail(MARKER_EXAMPLE, text, `bad element name ${shown(tag)}`);
  if (open[2] && open[2].trim()) throw fail(MARKER_EXAMPLE, text, `<${tag}> has attributes; use child elements`);
  if (open[3]) return [{ tag, text: '' }, pos + open[0].length]; // <empty/>
  let at = pos + open[0].length;
  const fields = {};
  let children = 0;
  let leafText = '';
  for (;;) {
    const lt = text.indexOf('<', at);
    if (lt < 0) throw fail(MARKER_EXAMPLE, text, `<${tag}> is not closed`);
    leafText += text.slice(at, lt);
    if (text.startsWith('</', lt)) {
      const close = `</${tag}>`;
      if (!text.startsWith(close, lt)) throw fail(MARKER_EXAMPLE, text, `<${tag}> is closed by another tag`);
      if (children === 0) return [{ tag, text: unescapeXml(leafText, text) }, lt + close.length];
      if (leafText.trim()) throw fail(MARKER_EXAMPLE, text, `<${tag}> mixes text with child elements`);
      return [{ tag, fields }, lt + close.length];
    }
    const [child, end] = readElement(text, lt, depth + 1);
    if (child.tag in fields) throw fail(MARKER_EXAMPLE, text, `<${tag}> has more than one <${child.tag}>`);
    fields[child.tag] = child.fields ? { tag: child.tag, fields: child.fields } : child.text;
    children += 1;
    at = end;
  }
}

/**
 * "<marker><location>(1 2)</location></marker>" -> {tag: "marker", fields: {location: "(1 2)"}}.
 * A field is a string, or a nested {tag, fields} for an element with children.
 */
export function parseMarker(text) {
  checkLength(text, MARKER_EXAMPLE);
  const start = text.search(/\S/);
  if (start < 0 || text[start] !== '<') throw fail(MARKER_EXAMPLE, text, 'not an XML element');
  const [node, end] = readElement(text, start, 1);
  if (text.slice(end).trim()) throw fail(MARKER_EXAMPLE, text, 'text after the root element');
  if (node.fields) return node;
  if (node.text.trim()) throw fail(MARKER_EXAMPLE, text, 'the root element must hold fields, not text');
  return { tag: node.tag, fields: {} };
}

/** Every top-level <marker> element in a text (a marker, or a list of them); bad ones are skipped. */
export function findMarkers(text, limit = 1000) {
  const found = [];
  if (typeof text !== 'string' || text.length > MAX_VALUE_LENGTH) return found;
  let at = 0;
  while (found.length < limit) {
    const next = text.indexOf('<marker>', at);
    if (next < 0) break;
    try {
      const [node, end] = readElement(text, next, 1);
      found.push(node.fields ? node : { tag: node.tag, fields: {} });
      at = end;
    } catch {
      at = next + 1;
    }
  }
  return found;
}

/** {tag, fields} -> compact XML, text escaped. */
export function formatMarker(marker, depth = 1) {
  if (depth > MAX_DEPTH) throw new ValueFormatError(`cannot format a marker nested deeper than ${MAX_DEPTH}`);
  const tag = marker.tag ?? 'marker';
  if (!TAG.test(tag)) throw new ValueFormatError(`bad marker element name ${shown(String(tag))}`);
  const parts = [`<${tag}>`];
  for (const [name, value] of Object.entries(marker.fields ?? {})) {
    if (!TAG.test(name)) throw new ValueFormatError(`bad marker field name ${shown(name)}`);
    if (value !== null && typeof value === 'object' && !Array.isArray(value)) {
      parts.push(formatMarker({ tag: name, fields: value.fields ?? {} }, depth + 1));
    } else {
      const textValue = Array.isArray(value) ? formatVector(value) : String(value);
      parts.push(`<${name}>${escapeXml(textValue)}</${name}>`);
    }
  }
  parts.push(`</${tag}>`);
  return parts.join('');
}

/** A marker at a location: markerAt([1, 2]) -> "<marker><location>(1 2)</location></marker>". */
export function markerAt(location, fields = {}) {
  return formatMarker({ tag: 'marker', fields: { location: formatVector(location), ...fields } });
}

/** A marker typed in a form: XML as it is, or "x y [z]" (or "(x y)") as a marker at that location. */
export function markerFromInput(raw) {
  const text = String(raw).trim();
  if (!text || text.startsWith('<')) return text;
  return markerAt(parseVector(text.startsWith('(') ? text : `(${text})`));
}

/** The location of a parsed marker as numbers, or null. */
export function markerLocation(marker) {
  const text = marker?.fields?.location;
  if (typeof text !== 'string') return null;
  try {
    return parseVector(text);
  } catch {
    return null;
  }
}

/**
 * The value text a form sends for a property of data type `type`: numbers and booleans are
 * checked (and normalised), vectors checked; other types go as typed. Throws ValueFormatError.
 */
export function valueFromInput(type, raw) {
  const text = String(raw);
  switch (type) {
    case 'number':
      return formatNumber(parseNumber(text));
    case 'integer': {
      const x = parseNumber(text);
      if (!Number.isInteger(x)) throw fail('an integer like "42"', text, 'the number has a fraction');
      return formatNumber(x);
    }
    case 'boolean':
      return formatBool(parseBool(text));
    case 'vector': {
      const body = text.trim();
      // "1 2 3" is taken as "(1 2 3)": the parentheses are easy to forget in a form.
      return formatVector(parseVector(body.startsWith('(') ? body : `(${body})`));
    }
    default:
      return text;
  }
}

/** Bytes in a standard base64 text (RFC 4648, with its `=` padding). */
export function base64Size(text) {
  const t = String(text ?? '');
  const padding = t.endsWith('==') ? 2 : t.endsWith('=') ? 1 : 0;
  return Math.max(0, Math.floor((t.length * 3) / 4) - padding);
}

/**
 * The text shown for a value of the JSON API or an event: a text value as it is, a binary one
 * (`{data: BASE64, media_type}`) as "[1234 bytes, image/png]".
 */
export function shownValue(item) {
  if (item?.data === undefined || item?.data === null) return item?.value ?? '';
  return `[${base64Size(item.data)} bytes, ${item.media_type || 'application/octet-stream'}]`;
}

// -- numbers for people ----------------------------------------------------------------------
// A value text may carry every digit a double has ("1.2345678901234567"); a person reads it to
// the property's resolution. The model's `resolution`, where a service declares one, says how
// fine; else the unit's usual reading on a robot, else three decimals.

/** Decimals a robot's quantities are read to when the model declares no resolution. */
const UNIT_DECIMALS = { m: 2, 'm/s': 2, rad: 2, 'rad/s': 2, degC: 1, s: 2, Hz: 1, '%': 0 };
/** Decimals of a number whose model says nothing about its precision. */
export const DEFAULT_DECIMALS = 3;
/** Most decimals shown, whatever the model says (a double holds about 16 significant digits). */
const MAX_DECIMALS = 9;

/** Decimals a resolution implies: 0.01 -> 2, 0.5 -> 1, 0.25 -> 2, 5 -> 0; null for none. */
export function decimalsOf(resolution) {
  if (typeof resolution !== 'number' || !Number.isFinite(resolution) || resolution <= 0) return null;
  for (let d = 0; d < MAX_DECIMALS; d += 1) {
    const scaled = resolution * 10 ** d;
    if (Math.abs(scaled - Math.round(scaled)) < 1e-6) return d;
  }
  return MAX_DECIMALS;
}

/**
 * The unit of element `i` of an `n`-element value: a pose's "m, rad" is metres for x y z and
 * radians for roll pitch yaw; any other unit holds for every element.
 */
export function unitOf(prop, i = 0, n = 1) {
  const parts = String(prop?.unit ?? '').split(',').map((part) => part.trim());
  if (parts.length === 2 && n === 6) return i < 3 ? parts[0] : parts[1];
  return parts[0];
}

/** Decimals a value of `prop` (element `i` of `n`) is shown with: resolution, type, unit. */
export function decimalsFor(prop, i = 0, n = 1) {
  const declared = decimalsOf(prop?.resolution);
  if (declared !== null) return declared;
  if (prop?.type === 'integer') return 0;
  return UNIT_DECIMALS[unitOf(prop, i, n)] ?? DEFAULT_DECIMALS;
}

/** x rounded to `decimals` as value text, no trailing zeros: (0.12345, 2) -> "0.12", (0.5, 2) -> "0.5". */
export function roundedText(x, decimals) {
  return formatNumber(Number(x.toFixed(Math.min(MAX_DECIMALS, Math.max(0, decimals)))) + 0);
}

/** x as a measurement: exactly `decimals` decimals and the unit, (0.5, 2, "m/s") -> "0.50 m/s". */
export function formatMeasure(x, decimals, unit = '') {
  if (typeof x !== 'number' || !Number.isFinite(x)) return '–';
  let fixed = x.toFixed(Math.min(MAX_DECIMALS, Math.max(0, decimals)));
  if (Number(fixed) === 0) fixed = fixed.replace(/^-/, ''); // never "-0.00"
  return unit ? `${fixed} ${unit}` : fixed;
}

/**
 * A number or vector value text rounded as `prop` says it is read ("(1.2345678 2 0 0 0 0.785398)"
 * -> "(1.23 2 0 0 0 0.79)"); any other text, or one that does not parse, as it is.
 */
export function roundedValue(prop, text) {
  const source = String(text ?? '');
  try {
    if (prop?.type === 'number' || prop?.type === 'integer') {
      return roundedText(parseNumber(source), decimalsFor(prop));
    }
    if (prop?.type === 'vector') {
      const numbers = parseVector(source);
      return `(${numbers.map((x, i) => roundedText(x, decimalsFor(prop, i, numbers.length))).join(' ')})`;
    }
  } catch {
    // not a number after all: shown as the service sent it
  }
  return source;
}

/** The round number at or above x (> 0): 1, 2 or 5 times a power of ten. */
export function niceCeil(x) {
  if (!(x > 0) || !Number.isFinite(x)) return 1;
  const power = 10 ** Math.floor(Math.log10(x));
  for (const m of [1, 2, 5, 10]) {
    const nice = Number((m * power).toPrecision(12));
    if (nice >= x * (1 - 1e-12)) return nice;
  }
  return 10 * power;
}

/** A span this many times wider than the value needs is narrowed around the value. */
export const SLIDER_ZOOM_FACTOR = 5;
/** The span a slider gets with no range in the model and no value yet (0 … 1). */
const DEFAULT_SPAN = 1;

/**
 * The span a slider of `prop` draws for `value`: the model's range (minimum … maximum), unless it
 * is far wider than the value needs (a speed declared 0 … 1000 m/s so that a Set of 5 passes, at
 * 0.5 m/s), or absent: then a round span that holds the value in its lower half (0 … 1 for 0.5),
 * within the model's range. The number box beside it still takes the whole range. `step` is the
 * model's resolution, 1 for an integer, else a power of ten a hundredth of the span or finer.
 * Returns {lo, hi, step, zoomed}; `zoomed` when the span is narrower than the model's range.
 */
export function sliderSpan(prop, value) {
  const finite = (x) => typeof x === 'number' && Number.isFinite(x);
  const min = finite(prop?.minimum) ? prop.minimum : null;
  const max = finite(prop?.maximum) ? prop.maximum : null;
  const known = finite(value);
  const typical = known && value !== 0 ? niceCeil(Math.abs(value) * 2) : DEFAULT_SPAN;
  let lo;
  let hi;
  if (min !== null && max !== null && max > min && (max - min <= SLIDER_ZOOM_FACTOR * typical || !known)) {
    [lo, hi] = [min, max];
  } else {
    lo = min !== null && min >= -typical ? min : known && value < 0 ? -typical : min !== null ? -typical : 0;
    if (min !== null) lo = Math.max(lo, min);
    hi = max !== null ? Math.min(max, Math.max(typical, lo + typical)) : Math.max(typical, lo + typical);
    if (!(hi > lo)) hi = lo + typical;
  }
  const declaredStep = finite(prop?.resolution) && prop.resolution > 0 ? prop.resolution : null;
  const step = declaredStep ?? (prop?.type === 'integer' ? 1 : 10 ** Math.floor(Math.log10((hi - lo) / 100)));
  const zoomed = min === null || max === null || lo > min || hi < max;
  return { lo, hi, step, zoomed };
}
