// Doc strings for people. Services write their docs in the small reStructuredText subset of
// Python docstrings: ``code``, *emphasis*, **strong**, `interpreted text` and roles such as
// :class:`Name` (both shown as code), paragraphs split by a blank line, and paths of the
// project's guides (`docs/vision.md`). parseDoc turns a doc into paragraphs of runs (no DOM, so
// node's test runner checks it); renderDoc builds elements from them with h(), never from HTML
// text: whatever a service puts in its doc shows as text.

/** Longest doc rendered; the rest is cut (a device's doc is text from the network). */
export const MAX_DOC_LENGTH = 8192;

// One inline piece: ``literal`` | :role:`text` | `text` (`text`_ a reference) | **strong** |
// *emphasis* (not inside a word) | a guide's path, docs/NAME.md with an optional #anchor.
const INLINE =
  /``(.+?)``|:[A-Za-z][\w.+-]*:`([^`]+)`|`([^`]+)`_{0,2}|\*\*(\S(?:[^*]*?\S)?)\*\*|(?<![\w*])\*(?![\s*])([^*]+?)(?<!\s)\*(?![\w*])|(?<![\w/])(docs\/[\w-]+(?:\/[\w-]+)*\.md(?:#[\w-]+)?)/g;
/** A guide's path that may become a link: docs/NAME.md[#anchor], no "..", nothing else. */
const DOC_PATH = /^docs\/[\w-]+(?:\/[\w-]+)*\.md(?:#[\w-]+)?$/;

function codeOrPath(text) {
  return DOC_PATH.test(text) ? { kind: 'path', text } : { kind: 'code', text };
}

/**
 * A doc as paragraphs of runs: [[{kind, text}, …], …], `kind` one of text, code, emphasis,
 * strong, path (a guide's path, docs/x.md). Lines of a paragraph join with a space.
 */
export function parseDoc(doc) {
  let source = String(doc ?? '');
  if (source.length > MAX_DOC_LENGTH) source = `${source.slice(0, MAX_DOC_LENGTH - 1)}…`;
  const paragraphs = source
    .replace(/\r\n?/g, '\n')
    .split(/\n[ \t]*\n/)
    .map((p) => p.trim().replace(/\s*\n\s*/g, ' '))
    .filter(Boolean);
  return paragraphs.map((text) => {
    const runs = [];
    let at = 0;
    const plain = (end) => {
      if (end > at) runs.push({ kind: 'text', text: text.slice(at, end) });
    };
    for (const m of text.matchAll(INLINE)) {
      plain(m.index);
      const [, literal, role, interpreted, strong, emphasis, path] = m;
      if (literal !== undefined) runs.push(codeOrPath(literal));
      else if (role !== undefined) runs.push(codeOrPath(role));
      else if (interpreted !== undefined) runs.push(codeOrPath(interpreted));
      else if (strong !== undefined) runs.push({ kind: 'strong', text: strong });
      else if (emphasis !== undefined) runs.push({ kind: 'emphasis', text: emphasis });
      else runs.push({ kind: 'path', text: path });
      at = m.index + m[0].length;
    }
    plain(text.length);
    return runs;
  });
}

/** The doc as plain text, its markup dropped (a tooltip): "see ``docs/x.md``" -> "see docs/x.md". */
export function plainDoc(doc) {
  return parseDoc(doc)
    .map((runs) => runs.map((run) => run.text).join(''))
    .join('\n\n');
}

/**
 * The doc as elements: a <p> per paragraph with <code>, <em> and <strong>; a guide's path is a
 * link into `docsBase` (the folder where the gateway serves the rendered guides) when one is
 * given, else code. `h` is dom.js's element builder.
 */
export function renderDoc(doc, { h, docsBase = null, className = 'doc' }) {
  const tags = { code: 'code', emphasis: 'em', strong: 'strong' };
  const paragraphs = parseDoc(doc).map((runs) =>
    h(
      'p',
      {},
      runs.map((run) => {
        if (run.kind === 'text') return run.text;
        if (run.kind === 'path') {
          const code = h('code', { class: 'doc-path' }, run.text);
          if (!docsBase) return code;
          const [file, anchor] = run.text.split('#');
          const href = `${docsBase.replace(/\/$/, '')}/${file.slice('docs/'.length)}${anchor ? `#${anchor}` : ''}`;
          return h('a', { href, target: '_blank', rel: 'noopener' }, code);
        }
        return h(tags[run.kind], {}, run.text);
      }),
    ),
  );
  return h('div', { class: className }, paragraphs);
}
