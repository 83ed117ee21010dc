/* Run AVR firmware in simavr with USART0 on a host pseudo-terminal (simavr's uart_pty part).
 *
 *   simavr_uart FIRMWARE.elf [MCU [HZ]]     (default atmega328p at 16 MHz)
 *
 * Prints "serial port /dev/pts/N" once the firmware runs: give the gateway
 * serial:///dev/pts/N. SIGUSR1 resets the MCU (the firmware starts again and greets);
 * SIGTERM and SIGINT end the run.
 *
 * RAM use: before the firmware starts, every SRAM byte is painted with 0xA5; at the end the
 * harness prints the longest run of bytes still painted ("untouched SRAM: N bytes"): the gap
 * between the end of .bss and the deepest the stack ever went. 2048 - N is the most RAM the
 * firmware used at once, static data and stack together. */
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "sim_avr.h"
#include "sim_elf.h"
#include "uart_pty.h"

#define PAINT 0xA5

static volatile sig_atomic_t reset_requested, stop_requested;

static void print_untouched(const avr_t *avr, uint16_t sram_start) {
    unsigned best = 0, best_at = 0, run = 0;
    for (unsigned a = sram_start; a <= avr->ramend; a++) {
        run = avr->data[a] == PAINT ? run + 1 : 0;
        if (run > best) {
            best = run;
            best_at = a + 1 - run;
        }
    }
    printf("untouched SRAM: %u bytes (0x%04X-0x%04X of 0x%04X-0x%04X)\n", best, best_at, best_at + best - 1,
           sram_start, avr->ramend);
    fflush(stdout);
}

static void on_signal(int sig) {
    if (sig == SIGUSR1) reset_requested = 1;
    else stop_requested = 1;
}

int main(int argc, char **argv) {
    if (argc < 2) {
        fprintf(stderr, "usage: simavr_uart FIRMWARE.elf [MCU [HZ]]\n");
        return 2;
    }
    elf_firmware_t firmware;
    memset(&firmware, 0, sizeof firmware);
    if (elf_read_firmware(argv[1], &firmware) != 0) {
        fprintf(stderr, "simavr_uart: cannot read %s\n", argv[1]);
        return 1;
    }
    if (argc > 2) snprintf(firmware.mmcu, sizeof firmware.mmcu, "%s", argv[2]);
    else if (!firmware.mmcu[0]) strcpy(firmware.mmcu, "atmega328p");
    if (argc > 3) firmware.frequency = (uint32_t)strtoul(argv[3], 0, 10);
    else if (!firmware.frequency) firmware.frequency = 16000000;

    avr_t *avr = avr_make_mcu_by_name(firmware.mmcu);
    if (!avr) {
        fprintf(stderr, "simavr_uart: unknown MCU %s\n", firmware.mmcu);
        return 1;
    }
    avr_init(avr);
    avr->log = LOG_ERROR;
    avr_load_firmware(avr, &firmware);
    const uint16_t sram_start = 0x100; /* after the registers and I/O space of an ATmega328P */
    memset(avr->data + sram_start, PAINT, avr->ramend + 1 - sram_start);

    static uart_pty_t uart;
    uart_pty_init(avr, &uart);
    uart_pty_connect(&uart, '0');
    printf("serial port %s\n", uart.port[0].slavename);
    fflush(stdout);

    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGUSR1, &sa, 0);
    sigaction(SIGTERM, &sa, 0);
    sigaction(SIGINT, &sa, 0);

    int state = cpu_Running;
    while (!stop_requested && state != cpu_Done && state != cpu_Crashed) {
        if (reset_requested) {
            reset_requested = 0;
            avr_reset(avr);
        }
        state = avr_run(avr);
    }
    print_untouched(avr, sram_start);
    /* No uart_pty_stop: it signals simavr's pty thread and joins it, which can wait for ever when
     * the signal comes while that thread is outside its select(); ending the process ends it. */
    if (state == cpu_Crashed) {
        fprintf(stderr, "simavr_uart: the firmware crashed\n");
        return 1;
    }
    return 0;
}
