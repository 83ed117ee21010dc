/* Run AVR firmware in simavr with USART0 on a host pseudo-terminal (simavr's uart_pty part).
 *
 *   simavr_uart FIRMWARE.elf [MCU [HZ]]     (default atmega328p at 16 MHz)
 *
 * Prints "serial port /dev/pts/N" once the firmware runs: give the gateway
 * serial:///dev/pts/N. SIGUSR1 resets the MCU (the firmware starts again and greets);
 * SIGTERM and SIGINT end the run. */
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "sim_avr.h"
#include "sim_elf.h"
#include "uart_pty.h"

static volatile sig_atomic_t reset_requested, stop_requested;

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
    uart_pty_stop(&uart);
    if (state == cpu_Crashed) {
        fprintf(stderr, "simavr_uart: the firmware crashed\n");
        return 1;
    }
    return 0;
}
