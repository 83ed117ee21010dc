/* Value pieces of ps_device: CRC-8 (docs/line-protocol.md §5), fixed-point numbers, escapes (§2). */
#include <string.h>

#include "ps_device.h"

uint8_t ps_crc8(const uint8_t *bytes, size_t count) {
    uint8_t crc = 0;
    while (count--) {
        crc ^= *bytes++;
        for (uint8_t bit = 0; bit < 8; bit++)
            crc = (crc & 0x80) ? (uint8_t)((crc << 1) ^ 0x07) : (uint8_t)(crc << 1);
    }
    return crc;
}

/* *value * 10 + digit, or 0 when that would pass 2^31 - 1: compared, not divided (AVR has no
 * divide instruction, and a 32-bit division per digit is a library call). */
static uint8_t push_digit(uint32_t *value, uint8_t digit) {
    if (*value > 214748364UL || (*value == 214748364UL && digit > 7)) return 0;
    *value = ((*value << 2) + *value) * 2 + digit; /* times 10 without the multiplication routine */
    return 1;
}

uint8_t ps_parse_fixed(const char *text, size_t length, uint8_t decimals, ps_fixed *out) {
    const char *end = text + length;
    uint8_t negative = 0, seen_digit = 0, point = 0, fraction = 0;
    uint32_t value = 0;
    if (text < end && (*text == '-' || *text == '+')) negative = *text++ == '-';
    for (; text < end; text++) {
        uint8_t digit = (uint8_t)(*text - '0');
        if (*text == '.' && !point) {
            point = 1;
            continue;
        }
        if (digit > 9) return PS_INVALID_ARGUMENT;
        seen_digit = 1;
        if (point) {
            /* Digits past the device's precision must be zeros: "21.50" is 21.5, "21.25" is refused
             * with one decimal rather than silently rounded. */
            if (fraction == decimals) {
                if (digit) return PS_INVALID_ARGUMENT;
                continue;
            }
            fraction++;
        }
        if (!push_digit(&value, digit)) return PS_INVALID_ARGUMENT;
    }
    if (!seen_digit) return PS_INVALID_ARGUMENT;
    for (; fraction < decimals; fraction++)
        if (!push_digit(&value, 0)) return PS_INVALID_ARGUMENT;
    *out = negative ? -(ps_fixed)value : (ps_fixed)value;
    return PS_OK;
}

/* *value / 10 in place, the remainder returned: 32 steps of shift and subtract, the long division
 * done by hand. On the AVR that is smaller than the library's 32-bit division routine, and the
 * only division the core needs. */
static uint8_t divide_by_ten(uint32_t *value) {
    uint32_t quotient = *value;
    uint8_t remainder = 0;
    for (uint8_t bit = 0; bit < 32; bit++) {
        remainder = (uint8_t)(remainder << 1 | (uint8_t)(quotient >> 31));
        quotient <<= 1;
        if (remainder >= 10) {
            remainder -= 10;
            quotient |= 1;
        }
    }
    *value = quotient;
    return remainder;
}

uint8_t ps_format_fixed(ps_fixed value, uint8_t decimals, char *out) {
    char digits[11]; /* least significant first; 2^31 has 10 digits, one more for "0.x" */
    uint8_t n = 0, length = 0, skip = 0;
    uint32_t u = value < 0 ? 0u - (uint32_t)value : (uint32_t)value;
    do digits[n++] = (char)('0' + divide_by_ten(&u));
    while ((u || n <= decimals) && n < sizeof digits);
    while (skip < decimals && digits[skip] == '0') skip++; /* no trailing zeros: "21.5", "3" */
    if (value < 0) out[length++] = '-';
    while (n > skip) {
        out[length++] = digits[--n];
        if (n == decimals && n > skip) out[length++] = '.';
    }
    out[length] = 0;
    return length;
}

uint8_t ps_unescape(char *text, size_t *length) {
    const char *from = text, *end = text + *length;
    char *to = text;
    while (from < end) {
        char c = *from++;
        if (c == '\\') {
            if (from == end) return PS_INVALID_ARGUMENT;
            c = *from++;
            if (c == 'n') c = '\n';
            else if (c == 'r') c = '\r';
            else if (c == 's') c = ' ';
            else if (c != '\\') return PS_INVALID_ARGUMENT;
        }
        *to++ = c;
    }
    *to = 0;
    *length = (size_t)(to - text);
    return PS_OK;
}

#ifdef PS_WITH_FLOAT
uint8_t ps_format_double(double value, uint8_t decimals, char *out) {
    double scaled = value;
    for (uint8_t i = 0; i < decimals; i++) scaled *= 10;
    scaled += scaled < 0 ? -0.5 : 0.5;
    if (scaled > 2147483647.0 || scaled < -2147483647.0) {
        memcpy(out, "nan", 4); /* out of the fixed-point range: not a number this device sends */
        return 3;
    }
    return ps_format_fixed((ps_fixed)scaled, decimals, out);
}
#endif
