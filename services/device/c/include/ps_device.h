/*
 * ps_device: the device side of the Property Service line protocol (docs/line-protocol.md) in C99.
 *
 * No malloc, no floating point, static buffers. The core is sans-IO: the transport hands it the
 * bytes it received (ps_feed) and gives it a byte sink for the lines it sends (ps_config.put);
 * the core never touches a socket, a UART or a clock. On AVR every constant string and the
 * property table live in flash (PS_FLASH); on any other target the same macros are empty.
 *
 * Values are fixed-point integers: a number with `decimals` = 1 holding 215 reads "21.5".
 * Define PS_WITH_FLOAT to get ps_format_double() for authors who have floats anyway.
 */
#ifndef PS_DEVICE_H
#define PS_DEVICE_H

#include <stddef.h>
#include <stdint.h>

/* ---- limits (override with -D) ------------------------------------------------------------ */

/* The longest line the device accepts, LF included; stated as maxline= in the greeting. The
 * protocol's floor is 64 (docs/line-protocol.md §4): 64 bytes of RAM on an ATmega328P. */
#ifndef PS_MAXLINE
#define PS_MAXLINE 64
#endif
/* How many requests the device takes at once (inflight=); this core answers each line before it
 * reads the next, so 1 unless the transport buffers more. */
#ifndef PS_INFLIGHT
#define PS_INFLIGHT 1
#endif
/* The transport's receive buffer in bytes (rxbuf=); 0 leaves the field out (TCP: the kernel's). */
#ifndef PS_RXBUF
#define PS_RXBUF 0
#endif
/* The properties that can be listened to or go: one bit each in the masks. A longer table serves
 * the rest, but a LISTEN of one of them is ERR 8 and ps_gone ignores them. */
#ifndef PS_MAX_PROPERTIES
#define PS_MAX_PROPERTIES 16
#endif

/* ---- profiles: what the core is built with (each 0 or 1 with -D; docs/c-device-library.md) ---- */

/* PS_MINIMAL: Get, Set and Listen of numbers and text and nothing else; each switch below can
 * still be turned on by itself (-DPS_MINIMAL -DPS_WITH_CHECKSUM=1). */
#ifdef PS_MINIMAL
#define PS_DEFAULT_FEATURE 0
#else
#define PS_DEFAULT_FEATURE 1
#endif
/* Binary values (PS_BYTES, ps_put_base64; line protocol 1.2). */
#ifndef PS_WITH_BYTES
#define PS_WITH_BYTES PS_DEFAULT_FEATURE
#endif
/* The model with docs: properties.model, NAME.gui, and the unit, doc and gui strings of ps_meta
 * (PS_DOC: a string the build drops when the model is off). Ranges are checked either way. */
#ifndef PS_WITH_MODEL
#define PS_WITH_MODEL PS_DEFAULT_FEATURE
#endif
/* CRC-8 checksums ('$' lines, §6). Without them a '$' line is answered ERR 12. */
#ifndef PS_WITH_CHECKSUM
#define PS_WITH_CHECKSUM PS_DEFAULT_FEATURE
#endif
/* Tags ('#TAG ' echoed on the reply, §2.1). The gateway tags every request: a device behind it
 * keeps them. Without them a tagged line is answered ERR 12, untagged (a terminal, a script). */
#ifndef PS_WITH_TAGS
#define PS_WITH_TAGS 1
#endif
/* Vectors (PS_VECTOR) and their elements NAME.0.., NAME.x y z roll pitch yaw. */
#ifndef PS_WITH_VECTORS
#define PS_WITH_VECTORS PS_DEFAULT_FEATURE
#endif
/* Actions (PS_ACTION) and ps_gone/ps_back. */
#ifndef PS_WITH_ACTIONS
#define PS_WITH_ACTIONS PS_DEFAULT_FEATURE
#endif
/* The words after an ERR code ("ERR 5 no such property"); without them "ERR 5" alone (§2: the
 * message is optional). */
#ifndef PS_WITH_ERROR_TEXTS
#define PS_WITH_ERROR_TEXTS PS_DEFAULT_FEATURE
#endif

#if PS_MAXLINE < 64 || PS_MAXLINE > 1024
#error "PS_MAXLINE must be 64..1024 (docs/line-protocol.md §1, §4)"
#endif
#if PS_MAX_PROPERTIES > 32
#error "PS_MAX_PROPERTIES must be at most 32"
#endif

/* ---- strings and tables in flash ------------------------------------------------------------ */

#if defined(__AVR__)
#include <avr/pgmspace.h>
#define PS_FLASH PROGMEM
#define PS_F(text) PSTR(text)                      /* a string literal placed in flash */
#define ps_flash_byte(p) pgm_read_byte(p)          /* read one byte of a PS_FLASH object */
#define ps_flash_copy(dst, src, n) memcpy_P((dst), (src), (n))
#else
#define PS_FLASH
#define PS_F(text) (text)
#define ps_flash_byte(p) (*(const uint8_t *)(p))
#define ps_flash_copy(dst, src, n) memcpy((dst), (src), (n))
#endif

#if PS_WITH_MODEL
#define PS_DOC(flash_string) (flash_string)
#else
#define PS_DOC(flash_string) 0
#endif

/* ---- status codes: the gRPC numbers (docs/line-protocol.md §7) ---------------------------- */

enum ps_code {
    PS_OK = 0,
    PS_INVALID_ARGUMENT = 3,
    PS_DEADLINE_EXCEEDED = 4,
    PS_NOT_FOUND = 5,
    PS_RESOURCE_EXHAUSTED = 8,
    PS_FAILED_PRECONDITION = 9,
    PS_OUT_OF_RANGE = 11,
    PS_UNIMPLEMENTED = 12,
    PS_INTERNAL = 13,
    PS_UNAVAILABLE = 14,
    PS_DATA_LOSS = 15
};

/* ---- the property table a device author fills in ------------------------------------------ */

typedef int32_t ps_fixed; /* a number times 10^decimals */

enum ps_type {
    PS_NUMBER, /* data: ps_fixed*; "integer" in the model when decimals is 0 */
    PS_VECTOR, /* data: ps_fixed[size]; "(1 2.5 0)"; elements NAME.0.. or NAME.x y z roll pitch yaw */
    PS_TEXT,   /* data: char[size], NUL-terminated; the value is the rest of the line */
    PS_ACTION, /* no data: a SET calls action(dev, index, argument); a GET or LISTEN is refused */
    PS_BYTES   /* data: const ps_bytes_source* (PS_FLASH); read-only; sent as \= and base64 (1.2, §2.4) */
};

enum ps_access { PS_READ = 1, PS_WRITE = 2, PS_READ_WRITE = 3, PS_INVOKE = 4 };

/* Optional metadata; every string is a PS_FLASH string or NULL. */
typedef struct ps_meta {
    const char *unit; /* words: "degC" */
    const char *doc;  /* words, no parentheses: "board temperature" */
    const char *gui;  /* the preferred widget, answered to GET NAME.gui */
    ps_fixed minimum; /* in the property's fixed-point scale; a SET outside is ERR 3 when has_range */
    ps_fixed maximum;
    uint8_t has_range;
} ps_meta;

struct ps_device;

/* An action: argument is the SET's value, unescaped; return PS_OK or a status code. */
typedef uint8_t (*ps_action_fn)(struct ps_device *dev, uint8_t index, const char *argument);

typedef struct ps_property {
    const char *name;     /* PS_FLASH string: a path segment, or dotted segments */
    uint8_t type;         /* enum ps_type */
    uint8_t access;       /* enum ps_access */
    uint8_t decimals;     /* numbers and vectors: digits after the point, 0..6 */
    uint8_t size;         /* vectors: elements; text: bytes of the buffer, NUL included */
    void *data;           /* see enum ps_type */
    ps_action_fn action;  /* PS_ACTION only */
    const ps_meta *meta;  /* PS_FLASH or NULL */
} ps_property;

#define PS_NUMBER_PROPERTY(name, var, decimals, access, meta) \
    { (name), PS_NUMBER, (access), (decimals), 1, &(var), 0, (meta) }
#define PS_VECTOR_PROPERTY(name, array, decimals, access, meta) \
    { (name), PS_VECTOR, (access), (decimals), (uint8_t)(sizeof(array) / sizeof((array)[0])), (array), 0, (meta) }
#define PS_TEXT_PROPERTY(name, buffer, access, meta) \
    { (name), PS_TEXT, (access), 0, (uint8_t)sizeof(buffer), (buffer), 0, (meta) }
#define PS_ACTION_PROPERTY(name, fn, meta) \
    { (name), PS_ACTION, PS_INVOKE, 0, 0, 0, (fn), (meta) }

/* A byte source: the byte at `position` (0, 1, 2, ... in order) of property `index`'s binary value,
 * 0..255, or -1 after the last. The core asks for each byte once, in order, while it writes the
 * line, so a source may ignore `position` and read a UART, an SPI FIFO or flash as it goes. */
typedef int16_t (*ps_byte_fn)(struct ps_device *dev, uint8_t index, uint16_t position);

/* A binary property's data (PS_BYTES): where its bytes come from and what they are. */
typedef struct ps_bytes_source {
    ps_byte_fn read;
    const char *media_type; /* PS_FLASH: "image/jpeg", "application/octet-stream"; NULL for none */
} ps_bytes_source;

#define PS_BYTES_PROPERTY(name, source, meta) \
    { (name), PS_BYTES, PS_READ, 0, 0, (void *)&(source), 0, (meta) }

/* The byte sink: the core calls it for every byte of every line it sends, LF included. */
typedef void (*ps_put_fn)(void *context, uint8_t byte);
/* Called after a SET changed property `index` (not for actions): the author applies it. */
typedef void (*ps_on_set_fn)(struct ps_device *dev, uint8_t index);

typedef struct ps_config {
    const char *name;               /* PS_FLASH: the greeting's name= */
    const char *type;               /* PS_FLASH: the greeting's type= (sensor, light, ...) */
    const ps_property *properties;  /* PS_FLASH array */
    uint8_t count;
    ps_put_fn put;
    void *context;                  /* handed to put */
    ps_on_set_fn on_set;            /* may be NULL */
} ps_config;

/* One bit per property: as narrow as PS_MAX_PROPERTIES allows (8-bit masks are cheap on AVR). */
#if PS_MAX_PROPERTIES <= 8
typedef uint8_t ps_mask;
#elif PS_MAX_PROPERTIES <= 16
typedef uint16_t ps_mask;
#else
typedef uint32_t ps_mask;
#endif

typedef struct ps_device {
    const ps_config *config;
    ps_mask listening;  /* LISTENed properties */
    ps_mask pending;    /* changed since their last EVENT (conflated: the latest value only) */
    ps_mask absent;     /* gone (ps_gone) until ps_back */
#if PS_MAXLINE <= 256
    uint8_t length; /* bytes of the current line in `line` (one byte: a line fits in 255) */
#else
    uint16_t length; /* bytes of the current line in `line` */
#endif
    uint8_t tag_at;     /* the current request's tag: where in `line` it starts ... */
    uint8_t tag_length; /* ... and its length; 0: the reply goes untagged */
    uint8_t flags;      /* PS_FLAG_* below */
    uint8_t crc;        /* CRC-8 of the line being sent */
    char line[PS_MAXLINE];
} ps_device;

/* ---- the core's entry points ------------------------------------------------------------------ */

/* Start (or restart) a session: a new connection, a reset, power-up. Clears every subscription
 * and the checksum mode and sends the greeting (§4.4: a greeting mid-session means "started afresh"). */
void ps_begin(ps_device *dev, const ps_config *config);
/* Bytes received by the transport: every complete line is answered before ps_feed returns. */
void ps_feed(ps_device *dev, const uint8_t *bytes, size_t count);
/* The transport dropped bytes (a full receive buffer): the current line is answered ERR 15. */
void ps_lost(ps_device *dev);
/* The device changed property `index` itself: an EVENT goes out at the next ps_poll. */
void ps_changed(ps_device *dev, uint8_t index);
/* Send the EVENT lines of changed, listened properties. Call it from the main loop. */
void ps_poll(ps_device *dev);
#if PS_WITH_ACTIONS
/* Property `index` no longer exists (a tool unplugged): a listener gets GONE; GET is NOT_FOUND. */
void ps_gone(ps_device *dev, uint8_t index);
/* Property `index` exists again: a listener of `properties` gets the new list. */
void ps_back(ps_device *dev, uint8_t index);
#endif

/* ---- pieces the core is built of, public for tests and for authors ---------------------------- */

uint8_t ps_crc8(const uint8_t *bytes, size_t count);
/* Parse decimal text ("-21.5") into a fixed-point value with `decimals` digits; PS_OK or
 * PS_INVALID_ARGUMENT (not a number, too many decimals, too large). */
uint8_t ps_parse_fixed(const char *text, size_t length, uint8_t decimals, ps_fixed *out);
/* Format a fixed-point value into out (at least 13 bytes); trailing zeros of the fraction are left
 * out ("21.5", "3", "-0.05"). Returns the length. */
uint8_t ps_format_fixed(ps_fixed value, uint8_t decimals, char *out);
#if PS_WITH_BYTES
/* Write "\=" and the standard base64 of the bytes read(dev, index, 0), read(dev, index, 1), ...
 * up to the first -1 into the line being sent (through the sink, counted in its CRC), 4 characters
 * for every 3 bytes, the last group padded with '='. Two bytes of state, whatever the length (the
 * position passed to read wraps after 65535: a longer value needs a source that ignores it). The line must still fit the client's limit (1024 bytes unless the gateway's proxy option
 * maxline raises it): at most 756 bytes after "#TAG OK " (docs/line-protocol.md §2.4). */
void ps_put_base64(ps_device *dev, ps_byte_fn read, uint8_t index);
#endif
/* Undo the escapes \n \r \\ \s in place; PS_OK or PS_INVALID_ARGUMENT (any other escape, "\=" too:
 * this library takes no binary values, it only sends them). */
uint8_t ps_unescape(char *text, size_t *length);
#ifdef PS_WITH_FLOAT
/* Optional: format a double with `decimals` digits, through ps_format_fixed. */
uint8_t ps_format_double(double value, uint8_t decimals, char *out);
#endif

#define PS_FLAG_OVERFLOW 0x01 /* the current line is longer than PS_MAXLINE */
#define PS_FLAG_LOST 0x02     /* the transport dropped bytes of the current line */
#define PS_FLAG_CHECKSUM 0x04 /* a good '$' line came: every line sent carries a checksum */
#define PS_FLAG_LIST 0x08     /* someone listens to `properties` */
#define PS_FLAG_LIST_DUE 0x10 /* the `properties` list changed since its last EVENT */
#define PS_FLAG_MIRROR 0x20   /* answering a '$' line: its reply carries a checksum (§6) */

#endif
