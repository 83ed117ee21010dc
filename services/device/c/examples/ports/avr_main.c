/* The AVR port of the example devices: an ATmega328P at 16 MHz, USART0 at 115200 baud, a 64-byte receive ring
 * filled by the RX interrupt, Timer1 ticking every 0.5 s. Sending is polled: while a line goes out
 * (a reply, an EVENT) the ring keeps receiving, so what the device can hold without reading is the
 * ring, and the greeting states it: rxbuf=64 (PS_RXBUF). A ring as long as the line buffer takes any
 * request the device accepts at all, whatever the device is doing when it comes. */
#include <avr/interrupt.h>
#include <avr/io.h>

#include "example.h"

#define BAUD 115200UL
#define RING 64 /* a power of two dividing 256: the free-running 8-bit counters wrap with it */

/* The ring: the RX interrupt writes at `tail`, the main loop reads at `head`; each counter has one
 * writer and is one byte, so neither side needs interrupts off to read the other's. */
static volatile uint8_t ring[RING];
static volatile uint8_t head, tail;
/* The ring overflowed: the byte that would have been at `lost_at` was dropped. Once the main loop
 * has fed every byte before it, the line being read is the damaged one. */
static volatile uint8_t lost, lost_at;

ISR(USART_RX_vect) {
    uint8_t byte = UDR0;
    if ((uint8_t)(tail - head) < RING) {
        ring[tail & (RING - 1)] = byte;
        tail++;
    } else if (!lost) {
        lost_at = tail;
        lost = 1;
    }
}

static void put_byte(void *context, uint8_t byte) {
    (void)context;
    while (!(UCSR0A & _BV(UDRE0))) {
    }
    UDR0 = byte;
}

static ps_device dev;

int main(void) {
    UCSR0A = _BV(U2X0);
    UBRR0 = (uint16_t)(F_CPU / (8 * BAUD) - 1);
    UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00); /* 8N1 */
    TCCR1B = _BV(WGM12) | _BV(CS12) | _BV(CS10); /* CTC, clock / 1024 */
    OCR1A = (uint16_t)(F_CPU / 1024 / 2 - 1);     /* 0.5 s */
    sei();
    example_start(&dev, put_byte, 0); /* after reset: the greeting (docs/line-protocol.md §4) */
    for (;;) {
        if (lost && head == lost_at) {
            lost = 0;
            ps_lost(&dev);
        }
        if (head != tail) {
            uint8_t byte = ring[head & (RING - 1)];
            head++;
            ps_feed(&dev, &byte, 1);
        }
        if (TIFR1 & _BV(OCF1A)) {
            TIFR1 = _BV(OCF1A);
            example_tick(&dev);
        }
        ps_poll(&dev);
    }
}
