// A `multipart/x-mixed-replace` body read as it arrives (the live image route, docs/http-api.md):
// bytes in, parts out. No DOM and no I/O, so node tests feed it bytes directly.
//
// The gateway writes each part as
//   --BOUNDARY CRLF  Content-Type: image/png CRLF  Content-Length: N CRLF  X-Sequence: S CRLF  CRLF
//   N bytes  CRLF
// and ends the body with `--BOUNDARY--`. A part without Content-Length (another server's MJPEG)
// ends where the next `CRLF--BOUNDARY` begins. Every buffer is bounded: a part over `maxPart`
// bytes or headers over `maxHeaders` bytes is an error, never a growing buffer.

/** Largest part accepted: well over the gateway's largest value (4 MiB, one gRPC message). */
export const MAX_PART_BYTES = 16 * 1024 * 1024;
/** Largest header block of one part. */
export const MAX_HEADER_BYTES = 8 * 1024;

const CRLF = [13, 10];

/** The boundary of a `multipart/...; boundary=X` content type, or null. */
export function boundaryOf(contentType) {
  const match = /;\s*boundary=(?:"([^"]{1,70})"|([^\s;]{1,70}))/i.exec(String(contentType ?? ''));
  return match ? (match[1] ?? match[2]) : null;
}

function ascii(text) {
  return Uint8Array.from(text, (c) => c.charCodeAt(0) & 0xff);
}

function indexOf(haystack, needle, from, to) {
  const last = to - needle.length;
  outer: for (let i = from; i <= last; i += 1) {
    for (let j = 0; j < needle.length; j += 1) if (haystack[i + j] !== needle[j]) continue outer;
    return i;
  }
  return -1;
}

/** An error of the body itself: the stream cannot be read further. */
export class MultipartError extends Error {
  constructor(message) {
    super(message);
    this.name = 'MultipartError';
  }
}

/**
 * Parts of one multipart body. `push(bytes)` returns the parts completed by those bytes, each
 * `{headers: {lower-case name: value}, type, body: Uint8Array}`; `done` is true once the closing
 * boundary has been read (later bytes are ignored).
 */
export class MultipartReader {
  constructor(boundary, { maxPart = MAX_PART_BYTES, maxHeaders = MAX_HEADER_BYTES } = {}) {
    if (!boundary) throw new MultipartError('a multipart body needs a boundary');
    this.dash = ascii(`--${boundary}`);
    this.delimiter = ascii(`\r\n--${boundary}`);
    this.maxPart = maxPart;
    this.maxHeaders = maxHeaders;
    this.buf = new Uint8Array(64 * 1024);
    this.start = 0;
    this.end = 0;
    this.state = 'boundary'; // boundary -> headers -> body -> boundary ...
    this.headers = null;
    this.length = null;
    this.done = false;
  }

  _append(bytes) {
    if (this.start > 0 && this.end + bytes.length > this.buf.length) {
      this.buf.copyWithin(0, this.start, this.end);
      this.end -= this.start;
      this.start = 0;
    }
    if (this.end + bytes.length > this.buf.length) {
      let size = this.buf.length;
      while (size < this.end + bytes.length) size *= 2;
      const grown = new Uint8Array(size);
      grown.set(this.buf.subarray(0, this.end));
      this.buf = grown;
    }
    this.buf.set(bytes, this.end);
    this.end += bytes.length;
  }

  /** Feed the next bytes of the body; returns the parts they complete. */
  push(bytes) {
    const parts = [];
    if (this.done) return parts;
    this._append(bytes instanceof Uint8Array ? bytes : new Uint8Array(bytes));
    for (;;) {
      const step = this._step();
      if (step === null) break;
      if (step !== true) parts.push(step);
      if (this.done) break;
    }
    return parts;
  }

  /** One step of the state machine: a part, true (progress without a part) or null (wants bytes). */
  _step() {
    const { buf, start, end } = this;
    if (this.state === 'boundary') {
      const at = indexOf(buf, this.dash, start, end);
      if (at < 0) {
        // Preamble or the CRLF before a boundary: keep only what could begin one.
        if (end - start > this.maxHeaders) this.start = end - this.dash.length;
        return null;
      }
      const after = at + this.dash.length;
      if (end - after < 2) return null;
      if (buf[after] === 45 && buf[after + 1] === 45) {
        this.done = true;
        this.start = end;
        return true;
      }
      const eol = indexOf(buf, CRLF, after, end);
      if (eol < 0) return null; // transport padding up to the line's end
      this.start = eol + 2;
      this.state = 'headers';
      return true;
    }
    if (this.state === 'headers') {
      const blank = indexOf(buf, [13, 10, 13, 10], start, end);
      const empty = end - start >= 2 && buf[start] === 13 && buf[start + 1] === 10;
      if (blank < 0 && !empty) {
        if (end - start > this.maxHeaders) throw new MultipartError(`a part's headers exceed ${this.maxHeaders} bytes`);
        return null;
      }
      const stop = empty ? start : blank;
      const text = new TextDecoder('latin1').decode(buf.subarray(start, stop));
      const headers = {};
      for (const line of text.split('\r\n')) {
        const colon = line.indexOf(':');
        if (colon > 0) headers[line.slice(0, colon).trim().toLowerCase()] = line.slice(colon + 1).trim();
      }
      this.headers = headers;
      this.length = null;
      if ('content-length' in headers) {
        const length = Number(headers['content-length']);
        if (!Number.isSafeInteger(length) || length < 0) {
          throw new MultipartError(`a part's Content-Length is not a size: ${JSON.stringify(headers['content-length'])}`);
        }
        if (length > this.maxPart) throw new MultipartError(`a part of ${length} bytes exceeds ${this.maxPart}`);
        this.length = length;
      }
      this.start = empty ? start + 2 : blank + 4;
      this.state = 'body';
      return true;
    }
    // body
    let stop;
    if (this.length !== null) {
      if (end - start < this.length) return null;
      stop = start + this.length;
    } else {
      stop = indexOf(buf, this.delimiter, start, end);
      if (stop < 0) {
        if (end - start > this.maxPart) throw new MultipartError(`a part exceeds ${this.maxPart} bytes`);
        return null;
      }
    }
    const body = buf.slice(start, stop); // a copy: the buffer is reused
    this.start = stop;
    this.state = 'boundary';
    const headers = this.headers;
    this.headers = null;
    return { headers, type: headers['content-type'] ?? 'application/octet-stream', body };
  }
}

/** "12.3 KB" for a byte count (the image widget's caption). */
export function formatSize(bytes) {
  if (bytes < 1024) return `${bytes} B`;
  if (bytes < 1024 * 1024) return `${(bytes / 1024).toFixed(1)} KB`;
  return `${(bytes / 1024 / 1024).toFixed(2)} MB`;
}

/** Whether a media type is an image a browser can show (`image/png`, `image/jpeg; q=1`). */
export function isImageType(mediaType) {
  return /^image\/[a-z0-9.+-]+\s*(;|$)/i.test(String(mediaType ?? ''));
}
