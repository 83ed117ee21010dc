/* The small robot example: a base that drives where it is told, for as long as it is told.
 *   location         vector (x y z roll pitch yaw), read: where the robot is, in m and rad; moves
 *                    on the timer by velocity x tick (example_tick, ROBOT_TICK_MS of motion each)
 *   velocity         vector (x y z roll pitch yaw), read-write: m/s and rad/s, each element
 *                    -1..1; a dead-man: velocity not SET again within ROBOT_DEADMAN_TICKS ticks
 *                    goes back to zero by itself (the same value SET again counts: on_set runs)
 *   behaviors.stop   action: SET behaviors.stop (any value) stops at once
 *   battery          number, read, %: drains while the robot moves
 * The ports run it: ../ports/host_main.c (TCP, a pty, a serial port), ../ports/avr_main.c (an
 * ATmega328P); docs/c-device-library.md walks through it. */
#ifndef ROBOT_H
#define ROBOT_H

#include "example.h"

enum { ROBOT_LOCATION, ROBOT_VELOCITY, ROBOT_STOP, ROBOT_BATTERY };

/* The motion one tick stands for (the AVR's timer period). */
#define ROBOT_TICK_MS 500
/* Ticks a velocity holds without a new SET: 3 x 0.5 s on the AVR. */
#define ROBOT_DEADMAN_TICKS 3

#endif
