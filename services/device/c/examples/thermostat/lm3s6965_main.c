/* The example device on a TI Stellaris LM3S6965 (Cortex-M3, 50 MHz): UART0 at 115200 baud, a
 * 128-byte receive ring filled by the UART's interrupt (stated as rxbuf=128 in the greeting),
 * SysTick counting 10 ms for the 0.5 s tick. Start-up, vector table and linker script are in
 * boards/lm3s6965/. QEMU's lm3s6965evb machine runs the same image with UART0 on a host pty.
 * Sending is polled, as on the AVR: while a reply goes out the ring keeps receiving. */
#include "lm3s6965.h"
#include "thermostat.h"

#define BAUD 115200u
#define RING 128 /* a power of two, at least PS_MAXLINE: a whole request fits */
#define TICKS_PER_STEP 50 /* 10 ms SysTick periods in the thermostat's 0.5 s */

static volatile uint8_t ring[RING];
/* Bit i set: bytes were lost just before ring[i] (the ring was full, or the UART's own FIFO
 * overran). Every loss is marked where it happened, however many come before the main loop
 * catches up, so each damaged line is answered ERR 15 and no two lines are read as one. */
static volatile uint8_t after_loss[RING / 8];
static volatile uint8_t head, count, losing;

/* The UART's receive interrupt (and receive timeout: fewer bytes than the FIFO level, then a
 * pause): everything in the FIFO into the ring. */
void lm3s_uart0_isr(void) {
    UART0_ICR = UART_IM_RXIM | UART_IM_RTIM;
    while (!(UART0_FR & UART_FR_RXFE)) {
        uint32_t data = UART0_DR;
        if (count == RING) {
            losing = 1;
            continue;
        }
        uint8_t slot = (uint8_t)(head + count) & (RING - 1);
        uint8_t bit = (uint8_t)(1u << (slot & 7));
        ring[slot] = (uint8_t)data;
        if (losing || (data & UART_DR_OE)) after_loss[slot >> 3] |= bit;
        else after_loss[slot >> 3] &= (uint8_t)~bit;
        losing = 0;
        count++;
    }
}

static void put_byte(void *context, uint8_t byte) {
    (void)context;
    while (UART0_FR & UART_FR_TXFF) {
    }
    UART0_DR = byte;
}

static ps_device dev;

int main(void) {
    lm3s_clock_50mhz();
    SYSCTL_RCGC1 |= SYSCTL_RCGC1_UART0;
    SYSCTL_RCGC2 |= SYSCTL_RCGC2_GPIOA;
    GPIOA_AFSEL |= 0x3u; /* PA0 U0Rx, PA1 U0Tx */
    GPIOA_DEN |= 0x3u;
    UART0_CTL = 0;
    /* The divisor in 1/64ths: 50 MHz / (16 * 115200) = 27.13 -> 27 + 8/64 */
    uint32_t sixty_fourths = (4u * LM3S_SYSCLK + BAUD / 2) / BAUD;
    UART0_IBRD = sixty_fourths >> 6;
    UART0_FBRD = sixty_fourths & 63u;
    UART0_LCRH = UART_LCRH_WLEN_8 | UART_LCRH_FEN; /* 8N1, FIFOs on (writing LCRH latches the divisor) */
    UART0_IFLS = UART_IFLS_RX_1_8;
    UART0_IM = UART_IM_RXIM | UART_IM_RTIM;
    UART0_CTL = UART_CTL_UARTEN | UART_CTL_TXE | UART_CTL_RXE;
    NVIC_ISER0 = 1u << UART0_IRQ;
    SYST_RVR = LM3S_SYSCLK / 100u - 1u; /* 10 ms */
    SYST_CVR = 0;
    SYST_CSR = SYST_CSR_CLKSOURCE | SYST_CSR_ENABLE;
    uint8_t ticks = 0;
    lm3s_interrupts_on();
    thermostat_start(&dev, put_byte, 0); /* after reset: the greeting (docs/line-protocol.md §4) */
    for (;;) {
        if (count) {
            lm3s_interrupts_off();
            uint8_t byte = ring[head];
            uint8_t lost = after_loss[head >> 3] & (1u << (head & 7));
            head = (uint8_t)(head + 1) & (RING - 1);
            count--;
            lm3s_interrupts_on();
            if (lost) ps_lost(&dev); /* the line being read lost bytes before this one */
            ps_feed(&dev, &byte, 1);
        }
        if ((SYST_CSR & SYST_CSR_COUNTFLAG) && ++ticks == TICKS_PER_STEP) {
            ticks = 0;
            thermostat_tick(&dev);
        }
        ps_poll(&dev);
    }
}
