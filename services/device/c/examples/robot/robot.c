/* The robot example's property table and behaviour (see robot.h). */
#include <string.h>

#include "robot.h"

/* Fixed point: location in mm and mrad (3 decimals), velocity in cm/s and crad/s (2 decimals),
 * battery in tenths of a percent (1 decimal). */
static ps_fixed location[6], velocity[6], battery;
static uint8_t deadman; /* ticks left before velocity goes back to zero; 0: stopped */

static const char name_location[] PS_FLASH = "location";
static const char name_velocity[] PS_FLASH = "velocity";
static const char name_stop[] PS_FLASH = "behaviors.stop";
static const char name_battery[] PS_FLASH = "battery";
#if PS_WITH_MODEL
static const char gui_pose[] PS_FLASH = "pose";
static const char doc_velocity[] PS_FLASH = "m/s and rad/s; back to zero within 1.5 s of the last SET";
static const char doc_stop[] PS_FLASH = "stop at once";
static const char percent[] PS_FLASH = "%";
#endif

static const ps_meta location_meta PS_FLASH = {0, 0, PS_DOC(gui_pose), 0, 0, 0};
/* A vector's range holds for each element: every one of the six is -1..1. */
static const ps_meta velocity_meta PS_FLASH = {0, PS_DOC(doc_velocity), 0, -100, 100, 1};
static const ps_meta stop_meta PS_FLASH = {0, PS_DOC(doc_stop), 0, 0, 0, 0};
static const ps_meta battery_meta PS_FLASH = {PS_DOC(percent), 0, 0, 0, 1000, 1};

static void stop(ps_device *dev) {
    uint8_t moving = 0;
    for (uint8_t i = 0; i < 6; i++) moving |= velocity[i] != 0;
    memset(velocity, 0, sizeof velocity);
    deadman = 0;
    if (moving) ps_changed(dev, ROBOT_VELOCITY); /* listeners hear the robot stop */
}

static uint8_t stop_action(ps_device *dev, uint8_t index, const char *argument) {
    (void)index;
    (void)argument;
    stop(dev);
    return PS_OK;
}

/* Every SET that stored a value, the same value too: a driver that keeps sending its velocity
 * keeps the robot moving. (The core sends the SET's OK and the EVENT itself.) */
static void on_set(ps_device *dev, uint8_t index) {
    (void)dev;
    if (index == ROBOT_VELOCITY) deadman = ROBOT_DEADMAN_TICKS;
}

static const ps_property table[] PS_FLASH = {
    PS_VECTOR_PROPERTY(name_location, location, 3, PS_READ, &location_meta),
    PS_VECTOR_PROPERTY(name_velocity, velocity, 2, PS_READ_WRITE, &velocity_meta),
    PS_ACTION_PROPERTY(name_stop, stop_action, &stop_meta),
    PS_NUMBER_PROPERTY(name_battery, battery, 1, PS_READ, &battery_meta),
};

static const char device_name[] PS_FLASH = "robot1";
static const char device_type[] PS_FLASH = "robot";
static ps_config config = {device_name, device_type, table, sizeof table / sizeof table[0], 0, 0, on_set};

void example_start(ps_device *dev, ps_put_fn put, void *context) {
    memset(dev, 0, sizeof *dev);
    memset(location, 0, sizeof location);
    memset(velocity, 0, sizeof velocity);
    deadman = 0;
    battery = 1000;
    config.put = put;
    config.context = context;
    ps_begin(dev, &config);
}

void example_tick(ps_device *dev) {
    if (!deadman) return;
    if (--deadman == 0) { /* nobody said "keep going": stop */
        stop(dev);
        return;
    }
    /* cm/s x ms = 10 um: / 100 gives mm (the location's unit); the same for crad/s and mrad */
    uint8_t moving = 0;
    for (uint8_t i = 0; i < 6; i++) {
        location[i] += velocity[i] * ROBOT_TICK_MS / 100;
        moving |= velocity[i] != 0;
    }
    if (!moving) return;
    ps_changed(dev, ROBOT_LOCATION);
    if (battery > 0) {
        battery--;
        ps_changed(dev, ROBOT_BATTERY);
    }
}
