/* The example device's property table and behaviour (see thermostat.h). */
#include <string.h>

#include "thermostat.h"

static ps_fixed temp, setpoint;
#if PS_WITH_VECTORS
static ps_fixed location[6];
#endif
static int8_t step;
#if PS_WITH_BYTES
/* The last HISTORY readings of temp in tenths of a degree, a ring whose oldest is at `oldest`. */
#define HISTORY 8 /* a power of two: the ring wraps with a mask */
static int16_t history[HISTORY];
static uint8_t oldest;
#endif
static char label[16];

static const char name_temp[] PS_FLASH = "temp";
static const char name_setpoint[] PS_FLASH = "setpoint";
#if PS_WITH_VECTORS
static const char name_location[] PS_FLASH = "location";
#endif
static const char name_label[] PS_FLASH = "label";
#if PS_WITH_ACTIONS
static const char name_probe[] PS_FLASH = "probe";
#endif
#if PS_WITH_BYTES
static const char name_history[] PS_FLASH = "history";
#endif
#if PS_WITH_MODEL /* the model's words: without it the build drops them (PS_DOC) */
static const char degc[] PS_FLASH = "degC";
static const char doc_temp[] PS_FLASH = "board temperature";
static const char doc_setpoint[] PS_FLASH = "temperature to hold";
static const char doc_probe[] PS_FLASH = "in or out: plug or unplug the probe";
static const char gui_gauge[] PS_FLASH = "gauge";
static const char gui_pose[] PS_FLASH = "pose";
static const char doc_history[] PS_FLASH = "last 8 temps, int16 big-endian, 0.1 degC";
static const char octets[] PS_FLASH = "application/octet-stream";
#endif

static const ps_meta temp_meta PS_FLASH = {PS_DOC(degc), PS_DOC(doc_temp), PS_DOC(gui_gauge), -400, 1250, 1};
static const ps_meta setpoint_meta PS_FLASH = {PS_DOC(degc), PS_DOC(doc_setpoint), 0, 50, 350, 1};
#if PS_WITH_MODEL
static const ps_meta location_meta PS_FLASH = {0, 0, gui_pose, 0, 0, 0};
static const ps_meta probe_meta PS_FLASH = {0, doc_probe, 0, 0, 0, 0};
static const ps_meta history_meta PS_FLASH = {0, doc_history, 0, 0, 0, 0};
#define THERMOSTAT_META(meta) (&(meta))
#else
#define THERMOSTAT_META(meta) 0
#endif

#if PS_WITH_BYTES
/* The history's bytes, one at a time as the core asks for them: nothing is copied. */
static int16_t history_byte(ps_device *dev, uint8_t index, uint16_t position) {
    (void)dev;
    (void)index;
    if (position >= 2 * HISTORY) return -1;
    uint16_t reading = (uint16_t)history[(oldest + position / 2) & (HISTORY - 1)];
    return (int16_t)(position & 1 ? reading & 0xFF : reading >> 8);
}
static const ps_bytes_source history_source PS_FLASH = {history_byte, PS_DOC(octets)};
#endif

#if PS_WITH_ACTIONS
static uint8_t probe(ps_device *dev, uint8_t index, const char *argument) {
    (void)index;
    if (strcmp(argument, "out") == 0) ps_gone(dev, THERMOSTAT_TEMP);
    else if (strcmp(argument, "in") == 0) ps_back(dev, THERMOSTAT_TEMP);
    else return PS_INVALID_ARGUMENT;
    return PS_OK;
}
#endif

static const ps_property table[] PS_FLASH = {
    PS_NUMBER_PROPERTY(name_temp, temp, 1, PS_READ, &temp_meta),
    PS_NUMBER_PROPERTY(name_setpoint, setpoint, 1, PS_READ_WRITE, &setpoint_meta),
#if PS_WITH_VECTORS
    PS_VECTOR_PROPERTY(name_location, location, 2, PS_READ_WRITE, THERMOSTAT_META(location_meta)),
#endif
    PS_TEXT_PROPERTY(name_label, label, PS_READ_WRITE, 0),
#if PS_WITH_ACTIONS
    PS_ACTION_PROPERTY(name_probe, probe, THERMOSTAT_META(probe_meta)),
#endif
#if PS_WITH_BYTES
    PS_BYTES_PROPERTY(name_history, history_source, THERMOSTAT_META(history_meta)),
#endif
};

static const char device_name[] PS_FLASH = "thermo1";
static const char device_type[] PS_FLASH = "sensor";

/* Everything but the sink is known at build time: set in the image, not by code. */
static ps_config config = {device_name, device_type, table, sizeof table / sizeof table[0], 0, 0, 0};

void example_start(ps_device *dev, ps_put_fn put, void *context) {
    memset(dev, 0, sizeof *dev);
    temp = 215;
    setpoint = 200;
    step = 1;
    strcpy(label, "bench");
#if PS_WITH_VECTORS
    memset(location, 0, sizeof location);
#endif
#if PS_WITH_BYTES
    for (uint8_t i = 0; i < HISTORY; i++) history[i] = (int16_t)temp;
    oldest = 0;
#endif
    config.put = put;
    config.context = context;
    ps_begin(dev, &config);
}

void example_tick(ps_device *dev) {
    /* a sawtooth of 0.1 degC steps within 1 degC of the setpoint */
    if (temp >= setpoint + 10) step = -1;
    else if (temp <= setpoint - 10) step = 1;
    temp += step;
    ps_changed(dev, THERMOSTAT_TEMP);
#if PS_WITH_BYTES
    history[oldest] = (int16_t)temp; /* the oldest goes, the newest comes last */
    oldest = (oldest + 1) & (HISTORY - 1);
    ps_changed(dev, THERMOSTAT_HISTORY);
#endif
}
