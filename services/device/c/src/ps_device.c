/*
 * The protocol core of ps_device: reads request lines, answers them through the byte sink.
 * Section numbers (§) are those of docs/line-protocol.md, version 1.2.
 */
#include <string.h>

#include "ps_device.h"

/* One copy of a function called from several places: GCC may inline a function it sees called
 * once or twice, and on AVR every copy costs flash. */
#ifdef __GNUC__
#define ONE_COPY __attribute__((noinline))
#else
#define ONE_COPY
#endif

/* Only properties below PS_MAX_PROPERTIES have a bit; the others get none (and no shift past the
 * mask's width). */
ONE_COPY /* smaller on AVR than a shift at every use */
static ps_mask bit_of(uint8_t index) {
    return index < PS_MAX_PROPERTIES ? (ps_mask)((ps_mask)1 << index) : (ps_mask)0;
}
#define BIT(i) bit_of(i)
#if PS_WITH_ACTIONS
#define ABSENT(dev, i) ((dev)->absent & BIT(i))
#else
#define ABSENT(dev, i) 0 /* nothing comes and goes: no test at all */
#endif
/* A length or position within the line: one byte wherever a line fits in 255 bytes (PS_MAXLINE
 * counts the LF), which on an 8-bit MCU halves every index's arithmetic. */
#if PS_MAXLINE <= 256
typedef uint8_t span;
#else
typedef size_t span;
#endif
/* Every refusal of the core: its code (docs/device-spec.md §7) and the words after it, one table.
 * Outside the range is ERR 3 (§3.2: INVALID_ARGUMENT, as gRPC and the gateway's own services say
 * it); its words tell it from a bad number. On the AVR a call names a refusal with one byte, and
 * the codes and words are two flash tables; without PS_WITH_ERROR_TEXTS the name is the code. */
#define PS_REFUSALS(X)                                                           \
    X(NO_PARAMETERS, PS_INVALID_ARGUMENT, "this device takes no parameters")     \
    X(BAD_PATH, PS_INVALID_ARGUMENT, "bad path")                                 \
    X(TEXT_AFTER_PATH, PS_INVALID_ARGUMENT, "unexpected text after the path")    \
    X(NOT_FOUND, PS_NOT_FOUND, "no such property")                               \
    X(BAD_ESCAPE, PS_INVALID_ARGUMENT, "bad escape")                             \
    X(READ_ONLY, PS_FAILED_PRECONDITION, "read-only")                            \
    X(TEXT_TOO_LONG, PS_RESOURCE_EXHAUSTED, "text too long")                     \
    X(OUT_OF_RANGE, PS_INVALID_ARGUMENT, "out of range")                         \
    X(BAD_VALUE, PS_INVALID_ARGUMENT, "bad value")                               \
    X(LISTEN_TO_PART, PS_UNIMPLEMENTED, "listen to a whole property")            \
    X(READ_ACTION, PS_FAILED_PRECONDITION, "an action: SET it, reads never act") \
    X(WRITE_ONLY, PS_FAILED_PRECONDITION, "write-only")                          \
    X(TABLE_FULL, PS_RESOURCE_EXHAUSTED, "subscription table full")              \
    X(BYTES_LOST, PS_DATA_LOSS, "bytes lost: the receive buffer was full")       \
    X(CHECKSUM_MISMATCH, PS_DATA_LOSS, "checksum mismatch")                      \
    X(BAD_TAG, PS_INVALID_ARGUMENT, "bad tag")                                   \
    X(LINE_TOO_LONG, PS_RESOURCE_EXHAUSTED, "line too long")                     \
    X(RAW_CR, PS_INVALID_ARGUMENT, "raw CR in the line; write \\r")              \
    X(TEXT_AFTER_HELLO, PS_INVALID_ARGUMENT, "unexpected text after HELLO")      \
    X(CANCEL_UNTAGGED, PS_INVALID_ARGUMENT, "CANCEL needs a tag")                \
    X(TEXT_AFTER_CANCEL, PS_INVALID_ARGUMENT, "unexpected text after CANCEL")    \
    X(A_REPLY, PS_INVALID_ARGUMENT, "a reply; send a request")                   \
    X(UNKNOWN_WORD, PS_UNIMPLEMENTED, "unknown word")
#if PS_WITH_ERROR_TEXTS
#define REFUSAL_NAME(name, code, words) R_##name,
#define REFUSAL_CODE(name, code, words) code,
#define REFUSAL_WORDS(name, code, words) words "\0"
static const uint8_t refusal_codes[] PS_FLASH = {PS_REFUSALS(REFUSAL_CODE)};
static const char refusal_words[] PS_FLASH = PS_REFUSALS(REFUSAL_WORDS) "the action failed";
#else
#define REFUSAL_NAME(name, code, words) R_##name = code, /* no words: the code is all there is */
#endif
/* R_ACTION_FAILED goes with the action's own code; STORED is a SET that was not refused. */
enum { PS_REFUSALS(REFUSAL_NAME) R_ACTION_FAILED, STORED = 255 };
#define TAG_MAX 8
#define PATH_MAX_LENGTH 256

/* What a path names besides a property's whole value. */
enum { WHOLE, LIST, MODEL, GUI, PARAMETERS, ELEMENT };


/* A number and a pointer kept in a PS_FLASH object, read in place. */
#if defined(__AVR__)
#define flash_fixed(p) ((ps_fixed)pgm_read_dword(p))
#define flash_pointer(p) ((__typeof__(*(p)))pgm_read_word(p)) /* a string's or a function's */
#else
#define flash_fixed(p) (*(p))
#define flash_pointer(p) (*(p))
#endif

/* ---- output: every byte goes through put(), which keeps the line's CRC ------------------------ */

#if PS_WITH_CHECKSUM
static uint8_t crc_step(uint8_t crc, uint8_t byte) {
    crc ^= byte;
    for (uint8_t bit = 0; bit < 8; bit++) crc = (crc & 0x80) ? (uint8_t)((crc << 1) ^ 0x07) : (uint8_t)(crc << 1);
    return crc;
}
#endif

static void raw(ps_device *dev, uint8_t byte) { dev->config->put(dev->config->context, byte); }

static void put(ps_device *dev, uint8_t byte) {
#if PS_WITH_CHECKSUM
    dev->crc = crc_step(dev->crc, byte);
#endif
    raw(dev, byte);
}

static void put_ram(ps_device *dev, const char *text, span length) {
    while (length--) put(dev, (uint8_t)*text++);
}

static void put_flash(ps_device *dev, const char *text) {
    for (uint8_t c; (c = ps_flash_byte(text)) != 0; text++) put(dev, c);
}

ONE_COPY static void put_number(ps_device *dev, ps_fixed value, uint8_t decimals) {
    char text[13];
    put_ram(dev, text, ps_format_fixed(value, decimals, text));
}

/* §2: a value escapes backslash, LF and CR. */
static void put_escaped(ps_device *dev, const char *text) {
    for (; *text; text++) {
        char c = *text;
        if (c == '\\' || c == '\n' || c == '\r') {
            put(dev, '\\');
            c = c == '\n' ? 'n' : c == '\r' ? 'r' : '\\';
        }
        put(dev, (uint8_t)c);
    }
}

#if PS_WITH_BYTES
/* One base64 character for a 6-bit value (RFC 4648 §4): arithmetic is smaller than a table on AVR. */
static uint8_t base64_char(uint8_t v) {
    return (uint8_t)(v < 26 ? 'A' + v : v < 52 ? 'a' + (v - 26) : v < 62 ? '0' + (v - 52) : v == 62 ? '+' : '/');
}

/* Bits go out 6 at a time as the bytes come: at most 4 bits wait between two bytes, so the state is
 * two bytes, less than the 3-byte group of the textbook encoder and the same characters (§2.4). */
void ps_put_base64(ps_device *dev, ps_byte_fn read, uint8_t index) {
    uint16_t position = 0, bits = 0; /* bits: the waiting bits, low end; `waiting` of them */
    uint8_t waiting = 0, written = 0;
    int16_t c;
    put(dev, '\\');
    put(dev, '=');
    while ((c = read(dev, index, position)) >= 0) {
        position++;
        bits = (uint16_t)(bits << 8 | (uint8_t)c);
        waiting += 8;
        while (waiting >= 6) {
            waiting -= 6;
            put(dev, base64_char((uint8_t)(bits >> waiting) & 63));
            written++;
        }
    }
    if (waiting) { /* the last bits, padded with zero bits */
        put(dev, base64_char((uint8_t)(bits << (6 - waiting)) & 63));
        written++;
    }
    while (written & 3) {
        put(dev, '=');
        written++;
    }
}
#endif

/* A reply to a tagged request carries its tag (dev->tag_at, dev->tag_length: §2.1). */
static void line_begin(ps_device *dev) {
#if PS_WITH_CHECKSUM
    if (dev->flags & (PS_FLAG_CHECKSUM | PS_FLAG_MIRROR)) raw(dev, '$');
    dev->crc = 0;
#endif
#if PS_WITH_TAGS
    if (dev->tag_length) {
        put(dev, '#');
        put_ram(dev, dev->line + dev->tag_at, dev->tag_length);
        put(dev, ' ');
    }
#endif
#if !PS_WITH_CHECKSUM && !PS_WITH_TAGS
    (void)dev; /* nothing to begin a line with */
#endif
}

static void line_end(ps_device *dev) {
#if PS_WITH_CHECKSUM
    if (dev->flags & (PS_FLAG_CHECKSUM | PS_FLAG_MIRROR)) {
        static const char hex[] PS_FLASH = "0123456789ABCDEF";
        uint8_t crc = dev->crc;
        raw(dev, '*');
        raw(dev, ps_flash_byte(&hex[crc >> 4]));
        raw(dev, ps_flash_byte(&hex[crc & 15]));
    }
#endif
    raw(dev, '\n');
}

/* The next of the NUL-separated strings in a packed flash string. */
static const char *next_string(const char *text) {
    while (ps_flash_byte(text++)) {
    }
    return text;
}

#if PS_WITH_ERROR_TEXTS || PS_WITH_MODEL
/* The n-th of the NUL-separated strings in packed. */
static const char *nth(const char *packed, uint8_t n) {
    for (; n; n--) packed = next_string(packed);
    return packed;
}
#endif

/* ERR CODE and the words of refusal (without PS_WITH_ERROR_TEXTS, "ERR 5" alone: §7). */
static void reply_error(ps_device *dev, uint8_t code, uint8_t refusal) {
    line_begin(dev);
    put_flash(dev, PS_F("ERR "));
    put_number(dev, code, 0);
#if PS_WITH_ERROR_TEXTS
    put(dev, ' ');
    put_flash(dev, nth(refusal_words, refusal));
#else
    (void)refusal;
#endif
    line_end(dev);
}

static void refuse(ps_device *dev, uint8_t refusal) {
#if PS_WITH_ERROR_TEXTS
    reply_error(dev, ps_flash_byte(&refusal_codes[refusal]), refusal);
#else
    reply_error(dev, refusal, refusal);
#endif
}

/* ---- the property table ------------------------------------------------------------------------ */

static void load(const ps_device *dev, uint8_t index, ps_property *out) {
    ps_flash_copy(out, &dev->config->properties[index], sizeof *out);
}

static uint8_t lower(uint8_t c) { return (c >= 'A' && c <= 'Z') ? (uint8_t)(c + 32) : c; }

/* The length of the flash string word when text begins with it; 0 when it does not. What follows
 * the text is a byte no word holds (the space after a field, the NUL at the end of the line), so
 * a word longer than the text never matches. */
static uint8_t match(const char *text, const char *word) {
    const char *start = word;
    for (uint8_t c; (c = ps_flash_byte(word)) != 0; word++, text++)
        if ((uint8_t)*text != c) return 0;
    return (uint8_t)(word - start);
}

#if PS_WITH_VECTORS
static const char element_names[] PS_FLASH = "x\0y\0z\0roll\0pitch\0yaw\0";

/* Element `suffix` of a vector of `size` elements: an index or x y z roll pitch yaw; 255 if none. */
static uint8_t element_of(const char *suffix, span length, uint8_t size) {
    uint16_t index = 0;
    span i = 0;
    for (; i < length && i < 3 && suffix[i] >= '0' && suffix[i] <= '9'; i++) index = (uint16_t)(index * 10 + (uint16_t)(suffix[i] - '0'));
    if (i && i == length) return index < size ? (uint8_t)index : 255;
    const char *name = element_names;
    for (uint8_t i = 0; i < 6; i++) {
        if (match(suffix, name) == length) return i < size ? i : 255;
        name = next_string(name);
    }
    return 255;
}
#endif

/* Resolve path: which property (*index) and which part of it (the return value); 255 = none. */
static uint8_t resolve(const ps_device *dev, const char *path, span length, uint8_t *index, uint8_t *element) {
    if (match(path, PS_F("properties")) == length) return LIST;
#if PS_WITH_MODEL
    if (match(path, PS_F("properties.model")) == length) return MODEL;
#endif
    for (uint8_t i = 0; i < dev->config->count; i++) {
        const ps_property *entry = &dev->config->properties[i]; /* read in place, in flash */
        uint8_t n = match(path, flash_pointer(&entry->name));
        if (!n || ABSENT(dev, i)) continue;
        *index = i;
        if (n == length) return WHOLE;
        if (path[n] != '.') continue;
        const char *suffix = path + n + 1;
        span rest = length - n - 1; /* at least 1: a path does not end with a dot */
#if PS_WITH_MODEL
        if (match(suffix, PS_F("gui")) == rest) return GUI;
        if (match(suffix, PS_F("parameters")) == rest) return PARAMETERS;
#endif
#if PS_WITH_VECTORS
        if (ps_flash_byte(&entry->type) == PS_VECTOR &&
            (*element = element_of(suffix, rest, ps_flash_byte(&entry->size))) != 255)
            return ELEMENT;
#endif
        (void)suffix;
        (void)rest;
        (void)element;
    }
    return 255;
}

static void put_value(ps_device *dev, const ps_property *p, uint8_t index) {
    (void)index;
#if PS_WITH_BYTES
    if (p->type == PS_BYTES) {
        ps_put_base64(dev, flash_pointer(&((const ps_bytes_source *)p->data)->read), index);
    } else
#endif
    if (p->type == PS_TEXT) {
        put_escaped(dev, (const char *)p->data);
    } else if (p->type == PS_NUMBER) {
        put_number(dev, *(const ps_fixed *)p->data, p->decimals);
    }
#if PS_WITH_VECTORS
    else if (p->type == PS_VECTOR) {
        put(dev, '(');
        for (uint8_t i = 0; i < p->size; i++) {
            if (i) put(dev, ' ');
            put_number(dev, ((const ps_fixed *)p->data)[i], p->decimals);
        }
        put(dev, ')');
    }
#endif
}

#if PS_WITH_MODEL
static void put_words(ps_device *dev, const char *words) {
    put(dev, '(');
    if (words) put_flash(dev, words);
    put(dev, ')');
}

/* §3 "A device that describes itself": (name type access (unit) minimum maximum (doc)). */
static void put_model_entry(ps_device *dev, const ps_property *p) {
    static const char types[] PS_FLASH = "number\0vector\0text\0none\0bytes\0integer";
    static const char access[] PS_FLASH = "read\0write\0read-write\0action"; /* PS_READ .. PS_INVOKE */
    static const ps_meta no_meta PS_FLASH = {0, 0, 0, 0, 0, 0};
    const ps_meta *meta = p->meta ? p->meta : &no_meta;
    put(dev, '(');
    put_flash(dev, p->name);
    put(dev, ' ');
    put_flash(dev, nth(types, (p->type == PS_NUMBER && p->decimals == 0) ? 5 : p->type));
    put(dev, ' ');
    put_flash(dev, nth(access, (uint8_t)(p->access - 1)));
    put(dev, ' ');
    put_words(dev, flash_pointer(&meta->unit));
    for (uint8_t bound = 0; bound < 2; bound++) {
        put(dev, ' ');
        if (ps_flash_byte(&meta->has_range))
            put_number(dev, flash_fixed(bound ? &meta->maximum : &meta->minimum), p->decimals);
        else put(dev, '-');
    }
    put(dev, ' ');
    put_words(dev, flash_pointer(&meta->doc));
#if PS_WITH_BYTES
    if (p->type == PS_BYTES) { /* §3.6: (media_type TYPE/SUBTYPE) */
        const char *media_type = flash_pointer(&((const ps_bytes_source *)p->data)->media_type);
        if (media_type) {
            put_flash(dev, PS_F(" (media_type "));
            put_flash(dev, media_type);
            put(dev, ')');
        }
    }
#endif
    put(dev, ')');
}
#endif

/* The properties present now, by name ("properties") or described (the model): one list. */
static void put_properties(ps_device *dev, uint8_t model) {
    put(dev, '(');
    uint8_t first = 1;
    for (uint8_t i = 0; i < dev->config->count; i++) {
        if (ABSENT(dev, i)) continue;
        ps_property p;
        load(dev, i, &p);
        if (!first) put(dev, ' ');
        first = 0;
#if PS_WITH_MODEL
        if (model) put_model_entry(dev, &p);
        else
#endif
            put_flash(dev, p.name);
    }
    (void)model;
    put(dev, ')');
}

/* ---- the greeting (§4) ------------------------------------------------------------------------- */

/* The flow-control fields are build-time constants: one flash string, no number formatting. */
#define PS_STRING(x) #x
#define PS_DECIMAL(x) PS_STRING(x) /* the value of macro x as text: x must be a decimal literal */
#if PS_RXBUF > 0
#define PS_RXBUF_FIELD " rxbuf=" PS_DECIMAL(PS_RXBUF)
#else
#define PS_RXBUF_FIELD ""
#endif

static void greet(ps_device *dev) {
    line_begin(dev);
    put_flash(dev, PS_F("HELLO 1 name="));
    put_flash(dev, dev->config->name);
    put_flash(dev, PS_F(" type="));
    put_flash(dev, dev->config->type);
    put_flash(dev, PS_F(" push=1 maxline=" PS_DECIMAL(PS_MAXLINE) " inflight=" PS_DECIMAL(PS_INFLIGHT) PS_RXBUF_FIELD));
    line_end(dev);
}

/* ---- requests (§3) ----------------------------------------------------------------------------- */

enum { W_GET, W_SET, W_LISTEN, W_UNLISTEN, W_PING, W_HELLO, W_CANCEL, W_PONG, W_REPLY, W_UNKNOWN };

/* The request word at text (lowered in place: words are read in any case, §2.2). */
static uint8_t word_of(char *text, span length) {
    static const char words[] PS_FLASH = "get\0set\0listen\0unlisten\0ping\0hello\0cancel\0pong\0ok\0err\0event\0gone\0";
    for (span i = 0; i < length; i++) text[i] = (char)lower((uint8_t)text[i]);
    const char *w = words;
    for (uint8_t i = 0; ps_flash_byte(w); i++) {
        if (match(text, w) == length) return i < W_REPLY ? i : W_REPLY;
        w = next_string(w);
    }
    return W_UNKNOWN;
}

/* Past the spaces at text: the line ends with a NUL, which is no space. */
static char *skip_spaces(char *text) {
    while (*text == ' ') text++;
    return text;
}

/* The end of the field that begins at text: the next space, or the end of the line. */
static char *field_end(char *text, const char *end) {
    while (text < end && *text != ' ') text++;
    return text;
}

static uint8_t is_name_char(char c) {
    return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_' || c == '-';
}

static uint8_t in_range(const ps_property *p, ps_fixed value) {
    /* the fields one by one, straight from flash: no copy on the stack */
    const ps_meta *meta = p->meta;
    return !meta || !ps_flash_byte(&meta->has_range) ||
           (value >= flash_fixed(&meta->minimum) && value <= flash_fixed(&meta->maximum));
}

#if PS_WITH_VECTORS
static uint8_t parse_vector(char *text, const char *end, const ps_property *p, ps_fixed *store) {
    uint8_t count = 0;
    text = skip_spaces(text);
    if (*text++ != '(') return R_BAD_VALUE; /* the value ends with a NUL, never '(' */
    for (;;) {
        text = skip_spaces(text);
        if (*text == ')') break;
        char *start = text;
        while (text < end && *text != ' ' && *text != ')') text++;
        ps_fixed value;
        if (count == p->size || ps_parse_fixed(start, (size_t)(text - start), p->decimals, &value) != PS_OK)
            return R_BAD_VALUE; /* an empty number too: the value ended before ')' */
        if (!in_range(p, value)) return R_OUT_OF_RANGE;
        if (store) store[count] = value;
        count++;
    }
    if (skip_spaces(text + 1) != end) return R_BAD_VALUE;
    return count == p->size ? STORED : R_BAD_VALUE;
}
#endif

/* SET of a whole number, vector or text (an element comes as a number of its own): store it or say
 * why not. */
static uint8_t store(const ps_property *p, char *value, span length) {
    if (p->type == PS_TEXT) {
        if (length >= p->size) return R_TEXT_TOO_LONG;
        memcpy(p->data, value, length + 1);
        return STORED;
    }
#if PS_WITH_VECTORS
    if (p->type == PS_VECTOR) {
        /* check everything first: a refused SET leaves the vector as it was */
        uint8_t refusal = parse_vector(value, value + length, p, 0);
        return refusal != STORED ? refusal : parse_vector(value, value + length, p, (ps_fixed *)p->data);
    }
#endif
    ps_fixed number;
    if (ps_parse_fixed(value, length, p->decimals, &number) != PS_OK) return R_BAD_VALUE;
    if (!in_range(p, number)) return R_OUT_OF_RANGE;
    *(ps_fixed *)p->data = number;
    return STORED;
}

/* GET, SET, LISTEN, UNLISTEN: rest is what follows the word, up to the line's end. */
static void answer(ps_device *dev, uint8_t word, char *rest, char *end) {
    char *path;
    for (;;) { /* NAME=VALUE fields come before the path (§2.1) */
        path = skip_spaces(rest);
        rest = field_end(path, end);
        if (!memchr(path, '=', (size_t)(rest - path))) break;
        if (word != W_UNLISTEN) { /* §3.4: UNLISTEN accepts and ignores them */
            refuse(dev, R_NO_PARAMETERS);
            return;
        }
    }
    span path_length = (span)(rest - path);
    /* names and dots, a dot only between two names (§2.1) */
    uint8_t good = path_length != 0;
#if PS_MAXLINE > PATH_MAX_LENGTH
    if (rest - path > PATH_MAX_LENGTH) good = 0;
#endif
    for (char *c = path; c < rest; c++)
        if (!is_name_char(*c) && !(*c == '.' && c > path && is_name_char(c[1]))) good = 0;
    if (!good) {
        refuse(dev, R_BAD_PATH);
        return;
    }
    char *value = end; /* SET: the rest of the line after one space (§2) */
    if (word == W_SET && rest < end) value = rest + 1;
    else if (skip_spaces(rest) != end) { /* trailing spaces are not a field */
        refuse(dev, R_TEXT_AFTER_PATH);
        return;
    }
    size_t value_length = (size_t)(end - value);
    uint8_t index = 0, element = 0;
    uint8_t part = resolve(dev, path, path_length, &index, &element);
    if (word == W_UNLISTEN) {
        if (part == LIST) dev->flags &= (uint8_t)~(PS_FLAG_LIST | PS_FLAG_LIST_DUE);
        else if (part == WHOLE) {
            dev->listening &= ~BIT(index);
            dev->pending &= ~BIT(index);
        }
        line_begin(dev);
        put_flash(dev, PS_F("OK"));
        line_end(dev);
        return;
    }
    if (part == 255) {
        refuse(dev, R_NOT_FOUND);
        return;
    }
    ps_property p;
    if (part == LIST || part == MODEL) memset(&p, 0, sizeof p);
    else load(dev, index, &p);
#if PS_WITH_VECTORS
    if (part == ELEMENT) { /* an element reads and stores as a number of its own */
        p.type = PS_NUMBER;
        p.data = (ps_fixed *)p.data + element;
    }
#endif
    uint8_t value_part = part == WHOLE || part == ELEMENT;
    if (word == W_SET) {
        if (ps_unescape(value, &value_length) != PS_OK) {
            refuse(dev, R_BAD_ESCAPE);
            return;
        }
#if PS_WITH_ACTIONS
        if (part == WHOLE && p.type == PS_ACTION) {
            uint8_t code = p.action(dev, index, value);
            if (code != PS_OK) {
                /* docs/device-spec.md §3.2: outside the range is ERR 3 (INVALID_ARGUMENT, as gRPC
                 * and the gateway's own services say it); the message tells it from a bad number */
                reply_error(dev, code == PS_OUT_OF_RANGE ? PS_INVALID_ARGUMENT : code, R_ACTION_FAILED);
                return;
            }
        } else
#endif
        {
            if (!value_part || !(p.access & PS_WRITE)) {
                refuse(dev, R_READ_ONLY);
                return;
            }
            uint8_t refusal = store(&p, value, value_length);
            if (refusal != STORED) {
                refuse(dev, refusal);
                return;
            }
            dev->pending |= dev->listening & BIT(index);
            if (dev->config->on_set) dev->config->on_set(dev, index);
        }
        /* the OK carries the value as stored, unless the property is not read (an action) */
        value_part = p.access & PS_READ;
    } else {
        /* GET and LISTEN */
        if (word == W_LISTEN && part != WHOLE && part != LIST) {
            refuse(dev, R_LISTEN_TO_PART);
            return;
        }
        if (value_part && !(p.access & PS_READ)) {
            refuse(dev, p.type == PS_ACTION ? R_READ_ACTION : R_WRITE_ONLY);
            return;
        }
        if (word == W_LISTEN) {
            if (part == LIST) {
                dev->flags |= PS_FLAG_LIST;
            } else if (!BIT(index)) { /* §3.1: no bit in the masks for this one */
                refuse(dev, R_TABLE_FULL);
                return;
            } else {
                dev->listening |= BIT(index);
            }
        }
        value_part = 1;
    }
    line_begin(dev);
    put_flash(dev, PS_F("OK"));
    if (value_part) {
        put(dev, ' ');
        if (part == LIST || part == MODEL) put_properties(dev, part == MODEL);
#if PS_WITH_MODEL
        else if (part == PARAMETERS) put_flash(dev, PS_F("()"));
        else if (part == GUI) {
            const char *gui = p.meta ? flash_pointer(&p.meta->gui) : 0;
            if (gui) put_flash(dev, gui);
        }
#endif
        else put_value(dev, &p, index);
    }
    line_end(dev);
}

static void flush_events(ps_device *dev) {
    ps_mask due = dev->pending; /* bit 0: property i, shifted down as i goes up */
    dev->pending = 0;
    for (uint8_t i = 0; due && i < dev->config->count; i++, due >>= 1) {
        if (!(due & 1)) continue;
        ps_property p;
        load(dev, i, &p);
        line_begin(dev);
#if PS_WITH_ACTIONS
        if (ABSENT(dev, i)) {
            put_flash(dev, PS_F("GONE "));
            put_flash(dev, p.name);
            dev->listening &= ~BIT(i); /* §3: the subscription ends */
        } else
#endif
        {
            put_flash(dev, PS_F("EVENT "));
            put_flash(dev, p.name);
            put(dev, ' ');
            put_value(dev, &p, i);
        }
        line_end(dev);
    }
#if PS_WITH_ACTIONS /* without ps_gone and ps_back the list never changes */
    if ((dev->flags & (PS_FLAG_LIST | PS_FLAG_LIST_DUE)) == (PS_FLAG_LIST | PS_FLAG_LIST_DUE)) {
        line_begin(dev);
        put_flash(dev, PS_F("EVENT properties "));
        put_properties(dev, 0);
        line_end(dev);
    }
    dev->flags &= (uint8_t)~PS_FLAG_LIST_DUE;
#endif
}

#if PS_WITH_CHECKSUM
static uint8_t hex_digit(char c) {
    if (c >= '0' && c <= '9') return (uint8_t)(c - '0');
    c = (char)lower((uint8_t)c);
    return (c >= 'a' && c <= 'f') ? (uint8_t)(c - 'a' + 10) : 255;
}
#endif

#if PS_WITH_CHECKSUM
/* The two hex digits at text as a byte, or -1. */
static int16_t hex_byte(const char *text) {
    uint8_t high = hex_digit(text[0]), low = hex_digit(text[1]);
    return (high | low) > 15 ? -1 : (int16_t)(high << 4 | low);
}
#endif

static void answer_line(ps_device *dev) {
    char *text = dev->line;
    char *end = text + dev->length;
    uint8_t flags = dev->flags;
    dev->flags &= (uint8_t)~(PS_FLAG_OVERFLOW | PS_FLAG_LOST);
    dev->length = 0;
    if (end > text && end[-1] == '\r') end--;
    *end = 0; /* spaces are skipped up to this end (a line is at most PS_MAXLINE - 1 bytes) */
    char *at = skip_spaces(text);
    if (at == end && !(flags & (PS_FLAG_OVERFLOW | PS_FLAG_LOST))) return; /* §1: blank: no reply */
#if PS_WITH_CHECKSUM
    if (*at == '$') dev->flags |= PS_FLAG_MIRROR; /* §6: the reply to a '$' line is checked */
#endif
    if (flags & PS_FLAG_LOST) { /* the tag may be what was lost: answer untagged */
        refuse(dev, R_BYTES_LOST);
        return;
    }
#if PS_WITH_CHECKSUM /* without: "$GET" is an unknown word, ERR 12 */
    if (!(flags & PS_FLAG_OVERFLOW) && *at == '$') {
        /* §2.1: "*HH" are the last three bytes; the CRC covers what lies between '$' and '*' */
        if (end - at < 4 || end[-3] != '*' ||
            hex_byte(end - 2) != ps_crc8((const uint8_t *)at + 1, (size_t)(end - at - 4))) {
            refuse(dev, R_CHECKSUM_MISMATCH); /* §6: untagged */
            return;
        }
        dev->flags |= PS_FLAG_CHECKSUM; /* checksum mode: only a line that checks out turns it on */
        at++;
        end -= 3;
        *end = 0;
    }
#endif
#if PS_WITH_TAGS /* without: "#1" is an unknown word, ERR 12 */
    if (*at == '#') { /* an over-long '$' line still starts with '$': its tag is not trusted */
        char *tag = ++at;
        while (is_name_char(*at)) at++; /* the NUL at the end is no name character */
        if (at == tag || at - tag > TAG_MAX || *at != ' ') {
            refuse(dev, R_BAD_TAG); /* §2.1: untagged */
            return;
        }
        dev->tag_at = (uint8_t)(tag - text);
        dev->tag_length = (uint8_t)(at - tag);
        at = skip_spaces(at);
    }
#endif
    if (flags & PS_FLAG_OVERFLOW) {
        refuse(dev, R_LINE_TOO_LONG);
        return;
    }
    if (memchr(at, '\r', (size_t)(end - at))) {
        refuse(dev, R_RAW_CR);
        return;
    }
    char *rest = field_end(at, end);
    if (rest == at) {
        dev->tag_length = 0; /* untagged */
        refuse(dev, R_BAD_TAG);
        return;
    }
    uint8_t word = word_of(at, (span)(rest - at));
    switch (word) {
    case W_PING:
        line_begin(dev);
        put_flash(dev, PS_F("PONG"));
        put_ram(dev, rest, (span)(end - rest)); /* the data as it came, its space included */
        line_end(dev);
        break;
    case W_HELLO:
        rest = skip_spaces(rest);
        if (rest == end) {
            /* §6: a plain HELLO starts afresh without checksums; $HELLO*35 keeps them */
            if (!(dev->flags & PS_FLAG_MIRROR)) dev->flags &= (uint8_t)~PS_FLAG_CHECKSUM;
            greet(dev);
        } else if (*rest < '0' || *rest > '9') { /* a greeting (a version follows) is never answered */
            refuse(dev, R_TEXT_AFTER_HELLO);
        }
        break;
    case W_PONG: /* the answer to a PING of ours: nothing to do */
        break;
    case W_CANCEL: /* every SET is answered before the next line is read: nothing is left to stop */
        if (!dev->tag_length) /* §2.1: CANCEL names the request it cancels by its tag */
            refuse(dev, R_CANCEL_UNTAGGED);
        else if (skip_spaces(rest) != end) /* §2.1: CANCEL takes nothing after the word */
            refuse(dev, R_TEXT_AFTER_CANCEL);
        break;
    case W_REPLY:
        refuse(dev, R_A_REPLY);
        break;
    case W_UNKNOWN:
        refuse(dev, R_UNKNOWN_WORD);
        break;
    default:
        answer(dev, word, rest, end);
    }
}

/* ---- entry points ------------------------------------------------------------------------------ */

void ps_begin(ps_device *dev, const ps_config *config) {
    dev->config = config;
    dev->listening = dev->pending = 0;
    dev->length = 0;
    dev->flags = 0;
    dev->tag_length = 0;
    greet(dev);
}

void ps_feed(ps_device *dev, const uint8_t *bytes, size_t count) {
    while (count--) {
        uint8_t c = *bytes++;
        if (c == '\n') {
            answer_line(dev);
            dev->tag_length = 0; /* what follows (EVENTs, the next line's errors) goes untagged */
            dev->flags &= (uint8_t)~PS_FLAG_MIRROR;
            flush_events(dev); /* §3.4: an EVENT a SET caused goes after the SET's OK */
        } else if (dev->length < PS_MAXLINE - 1) {
            dev->line[dev->length++] = (char)c; /* a line is at most PS_MAXLINE bytes, LF included */
        } else {
            dev->flags |= PS_FLAG_OVERFLOW; /* §1: drop bytes up to the LF, then ERR 8 */
        }
    }
}

void ps_lost(ps_device *dev) { dev->flags |= PS_FLAG_LOST; }

void ps_changed(ps_device *dev, uint8_t index) {
    dev->pending |= dev->listening & BIT(index);
}

void ps_poll(ps_device *dev) { flush_events(dev); }

#if PS_WITH_ACTIONS
void ps_gone(ps_device *dev, uint8_t index) {
    if (!BIT(index) || dev->absent & BIT(index)) return;
    dev->absent |= BIT(index);
    dev->pending |= dev->listening & BIT(index); /* flush_events sends GONE */
    dev->flags |= PS_FLAG_LIST_DUE;
}

void ps_back(ps_device *dev, uint8_t index) {
    if (!(dev->absent & BIT(index))) return;
    dev->absent &= ~BIT(index);
    dev->flags |= PS_FLAG_LIST_DUE;
}
#endif
