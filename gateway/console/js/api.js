// The gateway's HTTP/JSON API (docs/http-api.md): fetch with a time limit, JSON errors as ApiError.

export const API_BASE = '/api/v1';
/** Seconds a request may take before the console gives up on it (the gateway's call_timeout is 5 s). */
export const REQUEST_TIMEOUT_MS = 10000;

const TOKEN_KEY = 'ps_token';

/** An error answer of the gateway, or a failure to reach it: `code` is the gRPC code name. */
export class ApiError extends Error {
  constructor(code, message, status = 0) {
    super(message);
    this.name = 'ApiError';
    this.code = code;
    this.status = status;
  }

  /** As the console shows it next to a widget: "CODE: message". */
  toString() {
    return `${this.code}: ${this.message}`;
  }
}

// When an answer carries no JSON error (a proxy's own page), its HTTP status still names a code.
const CODE_OF_STATUS = {
  400: 'INVALID_ARGUMENT',
  401: 'UNAUTHENTICATED',
  403: 'PERMISSION_DENIED',
  404: 'NOT_FOUND',
  409: 'ABORTED',
  413: 'RESOURCE_EXHAUSTED',
  429: 'RESOURCE_EXHAUSTED',
  499: 'CANCELLED',
  501: 'UNIMPLEMENTED',
  503: 'UNAVAILABLE',
  504: 'DEADLINE_EXCEEDED',
};

/** The bearer token the console sends (empty: none); kept for this browser tab only. */
export function token() {
  try {
    return sessionStorage.getItem(TOKEN_KEY) ?? '';
  } catch {
    return '';
  }
}

/**
 * Use `value` as the bearer token: in the Authorization header of every request, and in the
 * `ps_token` cookie for the event stream (EventSource cannot set headers). Empty clears it.
 */
export function setToken(value) {
  const clean = String(value ?? '').trim();
  try {
    if (clean) sessionStorage.setItem(TOKEN_KEY, clean);
    else sessionStorage.removeItem(TOKEN_KEY);
  } catch {
    // Storage may be off (private mode): the cookie below still carries the token.
  }
  const secure = location.protocol === 'https:' ? '; Secure' : '';
  document.cookie = clean
    ? `${TOKEN_KEY}=${encodeURIComponent(clean)}; Path=/; SameSite=Strict${secure}`
    : `${TOKEN_KEY}=; Path=/; Max-Age=0; SameSite=Strict${secure}`;
}

/** "/api/v1/services/scout1/properties/behaviors.moveto?frame=robot". */
export function propertyUrl(service, path, parameters = {}) {
  const query = new URLSearchParams(parameters).toString();
  return (
    `${API_BASE}/services/${encodeURIComponent(service)}/properties/${encodeURIComponent(path)}` +
    (query ? `?${query}` : '')
  );
}

async function errorOf(response) {
  let body = null;
  try {
    body = await response.json();
  } catch {
    // not JSON: named by its status below
  }
  const error = body?.error;
  if (error && typeof error.code === 'string') {
    return new ApiError(error.code, String(error.message ?? ''), response.status);
  }
  const code = CODE_OF_STATUS[response.status] ?? (response.status >= 500 ? 'INTERNAL' : 'UNKNOWN');
  return new ApiError(code, `HTTP ${response.status} ${response.statusText}`.trim(), response.status);
}

/**
 * One request; resolves to the JSON answer or rejects with an ApiError. `keepalive` lets a
 * request outlive the page (the teleop's last stop on pagehide); `raw` (a Blob or bytes) is sent
 * as the body instead of JSON, with the content type `type`.
 */
export async function request(method, url, body = undefined, { keepalive = false, raw = undefined, type = undefined } = {}) {
  const headers = { Accept: 'application/json' };
  const bearer = token();
  if (bearer) headers.Authorization = `Bearer ${bearer}`;
  const init = { method, headers, keepalive, credentials: 'same-origin' };
  if (raw !== undefined) {
    // The bytes of a binary value as the body, labelled with their media type.
    headers['Content-Type'] = type ?? 'application/octet-stream';
    init.body = raw;
  } else if (body !== undefined) {
    headers['Content-Type'] = 'application/json';
    init.body = JSON.stringify(body);
  }
  if (!keepalive) init.signal = AbortSignal.timeout(REQUEST_TIMEOUT_MS);
  let response;
  try {
    response = await fetch(url, init);
  } catch (e) {
    if (e?.name === 'TimeoutError') {
      throw new ApiError('DEADLINE_EXCEEDED', `no answer within ${REQUEST_TIMEOUT_MS / 1000} s`);
    }
    throw new ApiError('UNAVAILABLE', `the gateway cannot be reached (${e?.message ?? e})`);
  }
  if (!response.ok) throw await errorOf(response);
  try {
    return await response.json();
  } catch {
    throw new ApiError('INTERNAL', `the gateway's answer to ${method} ${url} is not JSON`, response.status);
  }
}

/** {"services": [{name, type, state, address, location}]}. */
export function listServices() {
  return request('GET', `${API_BASE}/services`);
}

/** Milliseconds a model read is shared: the views that open together ask the gateway once. */
export const MODEL_SHARED_MS = 2000;
/** Services whose last model read is remembered (the oldest is forgotten beyond). */
const MODELS_KEPT = 256;
const models = new Map(); // service -> {promise, pending, at}

/**
 * The Describe model of a service: {service, type, properties: [...]}. Callers that ask while a
 * read is on its way, or within MODEL_SHARED_MS of one, share it (the service view, the map and
 * the inspector all want it when a service is opened or comes up); `fresh` always reads anew.
 */
export function describe(service, { fresh = false } = {}) {
  const known = models.get(service);
  if (known && !fresh && (known.pending || Date.now() - known.at < MODEL_SHARED_MS)) return known.promise;
  const entry = { pending: true, at: Date.now(), promise: null };
  entry.promise = request('GET', `${API_BASE}/services/${encodeURIComponent(service)}/model`).then(
    (model) => {
      entry.pending = false;
      entry.at = Date.now();
      return model;
    },
    (e) => {
      if (models.get(service) === entry) models.delete(service); // a failure is not shared later
      throw e;
    },
  );
  models.delete(service);
  models.set(service, entry);
  if (models.size > MODELS_KEPT) models.delete(models.keys().next().value);
  return entry.promise;
}

/** Get: {service, path, value}, or {service, path, values: [{path, value}]} for a wildcard path. */
export function getProperty(service, path, parameters = {}) {
  return request('GET', propertyUrl(service, path, parameters));
}

/**
 * The values the gateway kept of a property (its `[history]`, docs/recording.md): resolves to
 * {service, path, events: [{value, time, sequence, ...}], truncated}, oldest first. `since` is a
 * duration before now ("60s") or seconds since the epoch.
 */
export function getHistory(service, path, { since = '60s', limit = 0 } = {}) {
  const query = new URLSearchParams({ since: String(since) });
  if (limit) query.set('limit', String(limit));
  return request('GET', `${propertyUrl(service, path)}/history?${query}`);
}

/** Set: resolves to {service, path, value} (the reply text). */
export function setProperty(service, path, value, parameters = {}, options = {}) {
  const body = { value: String(value) };
  if (Object.keys(parameters).length) body.parameters = parameters;
  return request('PUT', propertyUrl(service, path), body, options);
}

/**
 * Set a binary property to `bytes` (a Blob, a File or a Uint8Array), sent as they are with the
 * content type `type` (the property's media type, or application/octet-stream).
 */
export function setPropertyBytes(service, path, bytes, type = 'application/octet-stream') {
  return request('PUT', propertyUrl(service, path), undefined, { raw: bytes, type });
}
