/* What an example device gives the ports (host_main.c: POSIX; avr_main.c: ATmega328P): its start
 * and its timer. Each example (thermostat/, robot/) defines both; a port is linked with one. */
#ifndef EXAMPLE_H
#define EXAMPLE_H

#include "ps_device.h"

/* Power-up or reset: every value to its default, then the greeting through put. */
void example_start(ps_device *dev, ps_put_fn put, void *context);
/* The timer (every 0.5 s on the AVR, --period on the host): the device changes what it changes. */
void example_tick(ps_device *dev);

#endif
