/* The example device: a thermostat board with six properties, transport-independent.
 *   temp      number, read, degC, changes every tick (listen to it)
 *   setpoint  number, read-write, degC, 5..35: temp swings around it
 *   location  vector (x y z roll pitch yaw), read-write: where the board sits
 *   label     text, read-write, up to 15 bytes
 *   probe     action: SET probe out unplugs the temperature probe (temp is GONE), SET probe in
 *             plugs it back
 *   history   bytes, read: the last 8 readings of temp, int16 big-endian tenths of degC (16 bytes,
 *             sent as \= and base64: line protocol 1.2)
 * The ports run it: ../ports/host_main.c on TCP, a pty or a serial port; ../ports/avr_main.c on an
 * ATmega328P's USART0. example_start sets every value to its default and greets; example_tick moves
 * temp one step (0.1 degC) and listeners get an EVENT at the next ps_poll. */
#ifndef THERMOSTAT_H
#define THERMOSTAT_H

#include "example.h"

/* The table's order; a profile without vectors, actions or binary values leaves those out. */
enum {
    THERMOSTAT_TEMP,
    THERMOSTAT_SETPOINT,
#if PS_WITH_VECTORS
    THERMOSTAT_LOCATION,
#endif
    THERMOSTAT_LABEL,
#if PS_WITH_ACTIONS
    THERMOSTAT_PROBE,
#endif
#if PS_WITH_BYTES
    THERMOSTAT_HISTORY
#endif
};

#endif
