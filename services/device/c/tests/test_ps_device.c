/* The unit tests of ps_device: feed request lines, compare the exact lines sent back.
 * Build and run: make -C services/device/c test (tests/integration/test_c_device_library.py does). */
#include <stdio.h>
#include <string.h>

#include "ps_device.h"

static int checks, failures;
static char out[4096];
static size_t out_length;

#define CHECK(cond)                                                                  \
    do {                                                                             \
        checks++;                                                                    \
        if (!(cond)) {                                                               \
            failures++;                                                              \
            printf("FAIL %s:%d: %s\n", __FILE__, __LINE__, #cond);                   \
        }                                                                            \
    } while (0)

/* Send `request`, check that exactly `expected` came back (both may hold several lines). */
#define EXCHANGE(request, expected)                                                  \
    do {                                                                             \
        const char *want_ = (expected);                                              \
        send_text(request);                                                          \
        checks++;                                                                    \
        if (strcmp(out, want_) != 0) {                                               \
            failures++;                                                              \
            printf("FAIL %s:%d: sent %s\n  want %s  got  %s\n", __FILE__, __LINE__,  \
                   #request, want_, out);                                            \
        }                                                                            \
    } while (0)

static void sink(void *context, uint8_t byte) {
    (void)context;
    if (out_length + 1 < sizeof out) {
        out[out_length++] = (char)byte;
        out[out_length] = 0;
    }
}

static ps_device dev;
static ps_fixed temp = 215, setpoint = 200, pose[3] = {1000, -500, 0};
static char label[12] = "lab";
static int beeps;
static char last_argument[16];
static int sets_seen;

static uint8_t beep(ps_device *d, uint8_t index, const char *argument) {
    (void)d;
    (void)index;
    strncpy(last_argument, argument, sizeof last_argument - 1);
    if (strcmp(argument, "fail") == 0) return PS_FAILED_PRECONDITION;
    beeps++;
    return PS_OK;
}

static void on_set(ps_device *d, uint8_t index) {
    (void)d;
    (void)index;
    sets_seen++;
}

static const ps_meta temp_meta = {"degC", "board temperature", "gauge", -400, 1250, 1};
static const ps_meta setpoint_meta = {"degC", 0, 0, 50, 350, 1};
static const ps_property table[] = {
    PS_NUMBER_PROPERTY("temp", temp, 1, PS_READ, &temp_meta),
    PS_NUMBER_PROPERTY("setpoint", setpoint, 1, PS_READ_WRITE, &setpoint_meta),
    PS_VECTOR_PROPERTY("pose", pose, 3, PS_READ_WRITE, 0),
    PS_TEXT_PROPERTY("label", label, PS_READ_WRITE, 0),
    PS_ACTION_PROPERTY("beep", beep, 0),
};
static const ps_config config = {"t1", "sensor", table, 5, sink, 0, on_set};

static void reset_out(void) {
    out_length = 0;
    out[0] = 0;
}

static void send_text(const char *text) {
    reset_out();
    ps_feed(&dev, (const uint8_t *)text, strlen(text));
}

static void start(void) {
    memset(&dev, 0, sizeof dev);
    temp = 215;
    setpoint = 200;
    reset_out();
    ps_begin(&dev, &config);
}

static void test_values(void) {
    char text[16];
    ps_fixed v;
    CHECK(ps_crc8((const uint8_t *)"123456789", 9) == 0xF4);
    CHECK(ps_crc8((const uint8_t *)"GET location", 12) == 0x54);
    CHECK(ps_parse_fixed("21.5", 4, 1, &v) == PS_OK && v == 215);
    CHECK(ps_parse_fixed("-0.05", 5, 2, &v) == PS_OK && v == -5);
    CHECK(ps_parse_fixed("+3", 2, 2, &v) == PS_OK && v == 300);
    CHECK(ps_parse_fixed("21.50", 5, 1, &v) == PS_OK && v == 215);
    CHECK(ps_parse_fixed("21.25", 5, 1, &v) == PS_INVALID_ARGUMENT);
    CHECK(ps_parse_fixed("1e3", 3, 0, &v) == PS_INVALID_ARGUMENT);
    CHECK(ps_parse_fixed("", 0, 0, &v) == PS_INVALID_ARGUMENT);
    CHECK(ps_parse_fixed("-", 1, 0, &v) == PS_INVALID_ARGUMENT);
    CHECK(ps_parse_fixed(".", 1, 0, &v) == PS_INVALID_ARGUMENT);
    CHECK(ps_parse_fixed("2147483647", 10, 0, &v) == PS_OK && v == 2147483647);
    CHECK(ps_parse_fixed("2147483648", 10, 0, &v) == PS_INVALID_ARGUMENT);
    CHECK(ps_parse_fixed("2147483.648", 11, 3, &v) == PS_INVALID_ARGUMENT);
    CHECK(ps_format_fixed(215, 1, text) == 4 && strcmp(text, "21.5") == 0);
    CHECK(ps_format_fixed(300, 2, text) == 1 && strcmp(text, "3") == 0);
    CHECK(ps_format_fixed(-5, 2, text) == 5 && strcmp(text, "-0.05") == 0);
    CHECK(ps_format_fixed(0, 3, text) == 1 && strcmp(text, "0") == 0);
    CHECK(ps_format_fixed(-2147483647 - 1, 0, text) == 11 && strcmp(text, "-2147483648") == 0);
    CHECK(ps_format_fixed(1050, 2, text) == 4 && strcmp(text, "10.5") == 0);
#ifdef PS_WITH_FLOAT
    CHECK(ps_format_double(2.25, 1, text) == 3 && strcmp(text, "2.3") == 0); /* half away from zero */
    CHECK(ps_format_double(-2.25, 1, text) == 4 && strcmp(text, "-2.3") == 0);
    CHECK(ps_format_double(0.5, 0, text) == 1 && strcmp(text, "1") == 0);
    CHECK(ps_format_double(1e12, 2, text) == 3 && strcmp(text, "nan") == 0);
#endif
    char escaped[] = "a\\nb\\\\c\\sd\\r";
    size_t n = strlen(escaped);
    CHECK(ps_unescape(escaped, &n) == PS_OK && n == 8 && memcmp(escaped, "a\nb\\c d\r", 8) == 0);
    char bad[] = "a\\x";
    n = 3;
    CHECK(ps_unescape(bad, &n) == PS_INVALID_ARGUMENT);
    char trailing[] = "a\\";
    n = 2;
    CHECK(ps_unescape(trailing, &n) == PS_INVALID_ARGUMENT);
}

static void test_greeting_and_words(void) {
    start();
    CHECK(strcmp(out, "HELLO 1 name=t1 type=sensor push=1 maxline=64 inflight=1 rxbuf=32\n") == 0);
    EXCHANGE("HELLO\n", "HELLO 1 name=t1 type=sensor push=1 maxline=64 inflight=1 rxbuf=32\n");
    EXCHANGE("#h HELLO\n", "#h HELLO 1 name=t1 type=sensor push=1 maxline=64 inflight=1 rxbuf=32\n");
    EXCHANGE("HELLO 1 name=gateway type=gateway\n", ""); /* a peer's greeting: no reply */
    EXCHANGE("PING\n", "PONG\n");
    EXCHANGE("#7 PING 42 x\n", "#7 PONG 42 x\n");
    EXCHANGE("\n   \n\r\n", ""); /* blank lines are ignored */
    EXCHANGE("FROB x\n", "ERR 12 unknown word\n");
    EXCHANGE("#a FROB\n", "#a ERR 12 unknown word\n");
    EXCHANGE("OK 1\n", "ERR 3 a reply; send a request\n");
    EXCHANGE("#toolongtag GET temp\n", "ERR 3 bad tag\n");
    EXCHANGE("# GET temp\n", "ERR 3 bad tag\n");
    EXCHANGE("#x!y GET temp\n", "ERR 3 bad tag\n");
    EXCHANGE("#t\n", "ERR 3 bad tag\n"); /* a tag with no word is a bad tag (§2.1) */
    EXCHANGE("#t \n", "ERR 3 bad tag\n");
    EXCHANGE("#t GET\ttemp\n", "#t ERR 12 unknown word\n"); /* a TAB is no separator (§1) */
    EXCHANGE("#t GET temp\t\n", "#t ERR 3 bad path\n");
    EXCHANGE("GET te\rmp\n", "ERR 3 raw CR in the line; write \\r\n");
    EXCHANGE("#c CANCEL\n", "");
    EXCHANGE("#c CANCEL  \n", ""); /* trailing spaces are not a field */
    EXCHANGE("CANCEL\n", "ERR 3 CANCEL needs a tag\n");
    EXCHANGE("#c CANCEL x\n", "#c ERR 3 unexpected text after CANCEL\n"); /* §2.1: extra field */
    EXCHANGE("PONG 5\n", ""); /* the answer to a PING of the device's: nothing to answer */
    EXCHANGE("#e EVENT temp 3\n", "#e ERR 3 a reply; send a request\n");
    EXCHANGE("HELLO there\n", "ERR 3 unexpected text after HELLO\n");
}

static void test_get_and_set(void) {
    start();
    EXCHANGE("GET temp\n", "OK 21.5\n");
    EXCHANGE("get temp\r\n", "OK 21.5\n");
    EXCHANGE("  #1   GET   temp\n", "#1 OK 21.5\n");
    EXCHANGE("#2 GET nosuch\n", "#2 ERR 5 no such property\n");
    EXCHANGE("GET Temp\n", "ERR 5 no such property\n"); /* paths are case-sensitive */
    EXCHANGE("GET te..mp\n", "ERR 3 bad path\n");
    EXCHANGE("GET temp.\n", "ERR 3 bad path\n"); /* a dot only between two names */
    EXCHANGE("GET .temp\n", "ERR 3 bad path\n");
    EXCHANGE("GeT temp\n", "OK 21.5\n"); /* words in any case */
    EXCHANGE("GET temp.gui.x\n", "ERR 5 no such property\n");
    EXCHANGE("GET unit=K temp\n", "ERR 3 this device takes no parameters\n");
    EXCHANGE("GET temp extra\n", "ERR 3 unexpected text after the path\n");
    EXCHANGE("GET temp   \n", "OK 21.5\n"); /* trailing spaces are not a field */
    EXCHANGE("GET\n", "ERR 3 bad path\n");
    EXCHANGE("UNLISTEN frame=world temp\n", "OK\n"); /* §3.4: UNLISTEN ignores parameters */
    EXCHANGE("SET temp 3\n", "ERR 9 read-only\n");
    int before = sets_seen;
    EXCHANGE("SET setpoint 22.5\n", "OK 22.5\n");
    CHECK(setpoint == 225 && sets_seen == before + 1);
    EXCHANGE("SET setpoint 99\n", "ERR 3 out of range\n");
    EXCHANGE("SET setpoint 22.25\n", "ERR 3 bad value\n");
    EXCHANGE("SET setpoint abc\n", "ERR 3 bad value\n");
    EXCHANGE("SET setpoint\n", "ERR 3 bad value\n");
    CHECK(setpoint == 225 && sets_seen == before + 1);
    EXCHANGE("GET pose\n", "OK (1 -0.5 0)\n");
    EXCHANGE("GET pose.y\n", "OK -0.5\n");
    EXCHANGE("GET pose.2\n", "OK 0\n");
    EXCHANGE("GET pose.3\n", "ERR 5 no such property\n");
    EXCHANGE("GET pose.yaw\n", "ERR 5 no such property\n");
    EXCHANGE("SET pose ( 1 2  3.5 )\n", "OK (1 2 3.5)\n");
    EXCHANGE("SET pose (1 2)\n", "ERR 3 bad value\n");
    EXCHANGE("SET pose (1 2 3 4)\n", "ERR 3 bad value\n");
    EXCHANGE("SET pose (1 x 3)\n", "ERR 3 bad value\n");
    EXCHANGE("SET label tab\there\n", "OK tab\there\n"); /* inside a value a TAB is data */
    EXCHANGE("SET pose.x 7\n", "OK 7\n");
    EXCHANGE("GET pose\n", "OK (7 2 3.5)\n");
    EXCHANGE("SET label a\\nb \\\\ c\n", "OK a\\nb \\\\ c\n");
    CHECK(strcmp(label, "a\nb \\ c") == 0);
    EXCHANGE("SET label a b\n", "OK a b\n");
    EXCHANGE("SET label 0123456789ab\n", "ERR 8 text too long\n");
    EXCHANGE("SET label bad\\q\n", "ERR 3 bad escape\n");
    EXCHANGE("GET label\n", "OK a b\n");
    EXCHANGE("GET beep\n", "ERR 9 an action: SET it, reads never act\n");
    EXCHANGE("#b SET beep twice\n", "#b OK\n");
    CHECK(beeps == 1 && strcmp(last_argument, "twice") == 0);
    EXCHANGE("SET beep fail\n", "ERR 9 the action failed\n");
    EXCHANGE("LISTEN beep\n", "ERR 9 an action: SET it, reads never act\n");
    EXCHANGE("GET properties\n", "OK (temp setpoint pose label beep)\n");
    EXCHANGE("SET properties (x)\n", "ERR 9 read-only\n");
    EXCHANGE("GET temp.gui\n", "OK gauge\n");
    EXCHANGE("GET label.gui\n", "OK \n");
    EXCHANGE("GET temp.parameters\n", "OK ()\n");
    EXCHANGE("GET properties.model\n",
             "OK ((temp number read (degC) -40 125 (board temperature)) "
             "(setpoint number read-write (degC) 5 35 ()) (pose vector read-write () - - ()) "
             "(label text read-write () - - ()) (beep none action () - - ()))\n");
}

static void test_line_limits(void) {
    char line[200], mismatch_8[40];
    snprintf(mismatch_8, sizeof mismatch_8, "$ERR 8 line too long*%02X\n",
             ps_crc8((const uint8_t *)"ERR 8 line too long", 19));
    start();
    memset(line, 'x', sizeof line);
    memcpy(line, "#L SET label ", 13);
    line[198] = '\n';
    line[199] = 0;
    EXCHANGE(line, "#L ERR 8 line too long\n");
    EXCHANGE("GET temp\n", "OK 21.5\n"); /* the next line is read afresh */
    /* 63 bytes and the LF: the longest line accepted */
    memset(line, ' ', 63);
    memcpy(line + 55, "GET temp", 8);
    line[63] = '\n';
    line[64] = 0;
    EXCHANGE(line, "OK 21.5\n");
    line[0] = 'x';
    memmove(line + 1, line, 64);
    line[0] = ' ';
    line[65] = 0;
    EXCHANGE(line, "ERR 8 line too long\n");
    line[1] = '$';
    line[2] = '#';
    EXCHANGE(line, mismatch_8); /* an over-long '$' line: mirrored checksum, untagged */
    send_text("#1 GET te");
    ps_lost(&dev);
    EXCHANGE("mp\n", "ERR 15 bytes lost: the receive buffer was full\n");
    EXCHANGE("#2 GET temp\n", "#2 OK 21.5\n");
}

static void test_checksums(void) {
    char request[40], reply[40], mismatch[40];
    start();
    /* The reply to a '$' line always carries a checksum, the ERR 15 of a damaged one too (§6). */
    snprintf(mismatch, sizeof mismatch, "$ERR 15 checksum mismatch*%02X\n",
             ps_crc8((const uint8_t *)"ERR 15 checksum mismatch", 24));
    CHECK(strcmp(mismatch, "$ERR 15 checksum mismatch*C7\n") == 0); /* the spec's own example */
    EXCHANGE("$GET temp*00\n", mismatch);
    EXCHANGE("$#1 GET temp\n", mismatch);
    EXCHANGE("$\n", mismatch);
    EXCHANGE("$ab\n", mismatch); /* too short for "*HH" */
    EXCHANGE("GET temp\n", "OK 21.5\n"); /* a bad '$' line does not turn checksums on */
    EXCHANGE("$GET location*54\n", "$ERR 5 no such property*14\n");
    EXCHANGE("HELLO\n", "HELLO 1 name=t1 type=sensor push=1 maxline=64 inflight=1 rxbuf=32\n"); /* mode off */
    EXCHANGE("GET temp\n", "OK 21.5\n");
    snprintf(request, sizeof request, "$#1 GET temp*%02x\n", ps_crc8((const uint8_t *)"#1 GET temp", 11));
    snprintf(reply, sizeof reply, "$#1 OK 21.5*%02X\n", ps_crc8((const uint8_t *)"#1 OK 21.5", 10));
    EXCHANGE(request, reply);
    snprintf(reply, sizeof reply, "$OK 21.5*%02X\n", ps_crc8((const uint8_t *)"OK 21.5", 7));
    EXCHANGE("GET temp\n", reply); /* from now on every line carries one */
    EXCHANGE("$#2 GET dat?*B3\n", mismatch);
    EXCHANGE("$HELLO*35\n", "$HELLO 1 name=t1 type=sensor push=1 maxline=64 inflight=1 rxbuf=32*6B\n");
    snprintf(reply, sizeof reply, "$OK 21.5*%02X\n", ps_crc8((const uint8_t *)"OK 21.5", 7));
    EXCHANGE("GET temp\n", reply); /* $HELLO keeps the mode on */
    reset_out();
    ps_begin(&dev, &config); /* a new session starts without */
    CHECK(out[0] == 'H');
    EXCHANGE("GET temp\n", "OK 21.5\n");
}

static void test_listen(void) {
    start();
    EXCHANGE("#l LISTEN temp\n", "#l OK 21.5\n");
    reset_out();
    temp = 220;
    ps_changed(&dev, 0);
    temp = 225;
    ps_changed(&dev, 0); /* conflated: the latest value only */
    ps_changed(&dev, 2); /* nobody listens to pose */
    ps_poll(&dev);
    CHECK(strcmp(out, "EVENT temp 22.5\n") == 0);
    reset_out();
    ps_poll(&dev);
    CHECK(out[0] == 0);
    EXCHANGE("LISTEN setpoint\n", "OK 20\n");
    EXCHANGE("#s SET setpoint 21\n", "#s OK 21\nEVENT setpoint 21\n"); /* the OK first, then the EVENT */
    EXCHANGE("UNLISTEN setpoint\n", "OK\n");
    EXCHANGE("SET setpoint 22\n", "OK 22\n");
    EXCHANGE("UNLISTEN nosuch\n", "OK\n");
    EXCHANGE("LISTEN pose.x\n", "ERR 12 listen to a whole property\n");
    EXCHANGE("LISTEN properties\n", "OK (temp setpoint pose label beep)\n");
    reset_out();
    ps_gone(&dev, 0);
    ps_poll(&dev);
    CHECK(strcmp(out, "GONE temp\nEVENT properties (setpoint pose label beep)\n") == 0);
    EXCHANGE("GET temp\n", "ERR 5 no such property\n");
    EXCHANGE("LISTEN temp\n", "ERR 5 no such property\n");
    EXCHANGE("GET properties.model\n",
             "OK ((setpoint number read-write (degC) 5 35 ()) (pose vector read-write () - - ()) "
             "(label text read-write () - - ()) (beep none action () - - ()))\n");
    reset_out();
    ps_back(&dev, 0);
    ps_changed(&dev, 0); /* the GONE ended the subscription */
    ps_poll(&dev);
    CHECK(strcmp(out, "EVENT properties (temp setpoint pose label beep)\n") == 0);
    EXCHANGE("LISTEN temp\n", "OK 22.5\n");
    reset_out();
    ps_begin(&dev, &config); /* a reset: every subscription ends with the session */
    reset_out();
    ps_changed(&dev, 0);
    ps_poll(&dev);
    CHECK(out[0] == 0);
}

/* Noise: random bytes (a fixed seed) never crash the core, every line it sends is whole and
 * within bounds, and after an LF it answers a good request again (§1 resynchronisation). */
static void test_noise(void) {
    static const char alphabet[] = "GETSLINUPHOC#$*=.\\ \n\r\t01x(-)";
    uint32_t seed = 12345;
    start();
    for (int round = 0; round < 2000; round++) {
        uint8_t noise[96];
        size_t n = 1 + round % sizeof noise;
        for (size_t i = 0; i < n; i++) {
            seed = seed * 1103515245u + 12345u;
            uint8_t r = (uint8_t)(seed >> 16);
            noise[i] = (r & 1) ? (uint8_t)alphabet[(r >> 1) % (sizeof alphabet - 1)] : r;
        }
        reset_out();
        ps_feed(&dev, noise, n);
        size_t line_start = 0;
        for (size_t i = 0; i < out_length; i++)
            if (out[i] == '\n') {
                CHECK(i - line_start < 400);
                line_start = i + 1;
            }
        CHECK(line_start == out_length); /* nothing half-sent */
        if (dev.absent & 1) ps_back(&dev, 0);
        send_text("\n#z GET setpoint\n");
        CHECK(strstr(out, "#z OK ") != 0 || strstr(out, "$#z OK ") != 0);
    }
}

/* A table longer than PS_MAX_PROPERTIES: the properties past the listen masks are served, but a
 * LISTEN of one is refused (ERR 8, §3.1) instead of answered OK and never followed by an EVENT. */
static ps_fixed many[PS_MAX_PROPERTIES + 1];
static const char many_first[] = "m0", many_last[] = "mlast";
#define MANY(i) PS_NUMBER_PROPERTY(many_first, many[i], 0, PS_READ_WRITE, 0)
static const ps_property many_table[PS_MAX_PROPERTIES + 1] = {
    MANY(0), MANY(1), MANY(2), MANY(3), MANY(4), MANY(5), MANY(6), MANY(7), MANY(8), MANY(9),
    MANY(10), MANY(11), MANY(12), MANY(13), MANY(14), MANY(15),
    PS_NUMBER_PROPERTY(many_last, many[PS_MAX_PROPERTIES], 0, PS_READ_WRITE, 0),
};
static const ps_config many_config = {"t2", "sensor", many_table, PS_MAX_PROPERTIES + 1, sink, 0, 0};

static void test_more_properties_than_the_masks(void) {
    memset(&dev, 0, sizeof dev);
    reset_out();
    ps_begin(&dev, &many_config);
    EXCHANGE("#1 LISTEN mlast\n", "#1 ERR 8 subscription table full\n");
    EXCHANGE("#2 SET mlast 4\n", "#2 OK 4\n");
    EXCHANGE("#3 GET mlast\n", "#3 OK 4\n");
    reset_out();
    ps_changed(&dev, PS_MAX_PROPERTIES); /* no bit to set: nothing, and no undefined shift */
    ps_gone(&dev, PS_MAX_PROPERTIES);
    ps_poll(&dev);
    CHECK(out_length == 0);
}

/* ---- binary values (1.2, §2.4): "\=" and base64, streamed from a byte source -------------------- */

static uint8_t blob[300];
static uint16_t blob_length;
static uint16_t reads_past_the_end;

static int16_t read_blob(ps_device *d, uint8_t index, uint16_t position) {
    (void)d;
    (void)index;
    if (position < blob_length) return blob[position];
    reads_past_the_end++;
    return -1;
}

/* A source that ignores the position, as a UART or a camera FIFO would: 4 bytes, then the end. */
static uint8_t fifo_left;
static int16_t read_fifo(ps_device *d, uint8_t index, uint16_t position) {
    (void)d;
    (void)index;
    (void)position;
    return fifo_left ? (int16_t)(0xF0 | fifo_left--) : -1;
}

static const ps_bytes_source blob_source = {read_blob, "application/octet-stream"};
static const ps_bytes_source fifo_source = {read_fifo, 0};
static const ps_meta frame_meta = {0, "camera image", "image", 0, 0, 0};
static const ps_property bytes_table[] = {
    PS_BYTES_PROPERTY("blob", blob_source, 0),
    PS_BYTES_PROPERTY("fifo", fifo_source, &frame_meta),
    PS_TEXT_PROPERTY("label", label, PS_READ_WRITE, 0),
};
static const ps_config bytes_config = {"cam", "sensor", bytes_table, 3, sink, 0, 0};

/* A reference encoder written differently (bit by bit) from the library's. */
static void reference_base64(const uint8_t *bytes, size_t n, char *text) {
    static const char alphabet[] = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    size_t bits = n * 8, out_length = 0;
    for (size_t bit = 0; bit < bits; bit += 6) {
        uint8_t v = 0;
        for (size_t k = bit; k < bit + 6; k++) {
            uint8_t b = k < bits ? (uint8_t)((bytes[k / 8] >> (7 - k % 8)) & 1) : 0;
            v = (uint8_t)(v << 1 | b);
        }
        text[out_length++] = alphabet[v];
    }
    while (out_length % 4) text[out_length++] = '=';
    text[out_length] = 0;
}

static void test_binary_values(void) {
    char want[600], encoded[500];
    memset(&dev, 0, sizeof dev);
    reset_out();
    ps_begin(&dev, &bytes_config);
    /* The spec's example: the first 10 bytes of a JPEG file. */
    memcpy(blob, "\xff\xd8\xff\xe0\x00\x10JFIF", 10);
    blob_length = 10;
    EXCHANGE("#4 GET blob\n", "#4 OK \\=/9j/4AAQSkZJRg==\n");
    /* Every length from 0 to 7 (no padding, one '=', two) and all 256 byte values. */
    for (uint16_t n = 0; n <= 7; n++) {
        for (uint16_t k = 0; k < n; k++) blob[k] = (uint8_t)(0xA5 ^ (k * 37));
        blob_length = n;
        reference_base64(blob, n, encoded);
        snprintf(want, sizeof want, "OK \\=%s\n", encoded);
        EXCHANGE("GET blob\n", want);
    }
    EXCHANGE("GET blob\n", want); /* the same bytes read again give the same line */
    for (uint16_t k = 0; k < 256; k++) blob[k] = (uint8_t)k;
    blob_length = 256;
    reference_base64(blob, 256, encoded);
    snprintf(want, sizeof want, "OK \\=%s\n", encoded);
    EXCHANGE("GET blob\n", want);
    CHECK(strlen(out) == 3 + 2 + 344 + 1); /* 256 bytes are 344 characters: longer than PS_MAXLINE */
    /* Each byte is asked for once, in order, and the end once per group: a FIFO works too. */
    reads_past_the_end = 0;
    blob_length = 0;
    EXCHANGE("GET blob\n", "OK \\=\n"); /* empty bytes are still binary */
    CHECK(reads_past_the_end == 1);
    fifo_left = 4;
    EXCHANGE("GET fifo\n", "OK \\=9PPy8Q==\n"); /* F4 F3 F2 F1 */
    /* In a checksummed line the CRC covers the base64 as it streams. */
    blob[0] = 0;
    blob[1] = 1;
    blob[2] = 2;
    blob[3] = 0xFF;
    blob_length = 4;
    char request[40], reply[40];
    snprintf(request, sizeof request, "$#9 GET blob*%02X\n", ps_crc8((const uint8_t *)"#9 GET blob", 11));
    snprintf(reply, sizeof reply, "$#9 OK \\=AAEC/w==*%02X\n", ps_crc8((const uint8_t *)"#9 OK \\=AAEC/w==", 16));
    EXCHANGE(request, reply);
    reset_out();
    ps_begin(&dev, &bytes_config); /* checksum mode off again */
    /* LISTEN, then a change: the EVENT carries the new bytes. */
    EXCHANGE("#l LISTEN blob\n", "#l OK \\=AAEC/w==\n");
    blob[3] = 0xFE;
    reset_out();
    ps_changed(&dev, 0);
    ps_poll(&dev);
    CHECK(strcmp(out, "EVENT blob \\=AAEC/g==\n") == 0);
    /* The model says bytes and the media type (§3.6). */
    EXCHANGE("GET properties.model\n",
             "OK ((blob bytes read () - - () (media_type application/octet-stream)) (fifo bytes read () - - (camera "
             "image)) (label text read-write () - - ()))\n");
    EXCHANGE("GET fifo.gui\n", "OK image\n");
    /* This library sends binary values and takes none: a SET of one is read-only, and "\=" in a
     * text value is the bad escape a 1.1 device answers (§2.4). */
    EXCHANGE("#s SET blob xyz\n", "#s ERR 9 read-only\n");
    EXCHANGE("#t SET label \\=AAEC\n", "#t ERR 3 bad escape\n");
    EXCHANGE("#u SET label a\\\\=b\n", "#u OK a\\\\=b\n");
    char escaped[] = "\\=QUJD";
    size_t n = strlen(escaped);
    CHECK(ps_unescape(escaped, &n) == PS_INVALID_ARGUMENT);
}

int main(void) {
    test_values();
    test_greeting_and_words();
    test_get_and_set();
    test_line_limits();
    test_checksums();
    test_listen();
    test_noise();
    test_more_properties_than_the_masks();
    test_binary_values();
    printf("%d checks, %d failed\n", checks, failures);
    return failures ? 1 : 0;
}
