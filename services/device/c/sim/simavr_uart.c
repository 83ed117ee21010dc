/* Run AVR firmware in simavr with USART0 on a host pseudo-terminal (simavr's uart_pty part).
 *
 *   simavr_uart [--reset-on-open MS] FIRMWARE.elf [MCU [HZ]]     (default atmega328p at 16 MHz)
 *
 * Prints "serial port /dev/pts/N" once the firmware runs: give the gateway
 * serial:///dev/pts/N. SIGUSR1 resets the MCU (the firmware starts again and greets);
 * SIGUSR2 hangs it (the firmware stops running: no reply, no event) until the next reset;
 * SIGTERM and SIGINT end the run.
 *
 * --reset-on-open MS plays an Arduino board: opening the serial port pulls DTR, which resets the
 * MCU, and a bootloader then runs for MS milliseconds, reading (and so eating) every byte that
 * arrives, before the firmware starts and greets. A pty has no DTR: the harness watches the port
 * for opens (inotify) instead.
 *
 * RAM use: before the firmware starts, every SRAM byte is painted with 0xA5; at the end the
 * harness prints the longest run of bytes still painted ("untouched SRAM: N bytes"): the gap
 * between the end of .bss and the deepest the stack ever went. 2048 - N is the most RAM the
 * firmware used at once, static data and stack together. */
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/inotify.h>
#include <time.h>
#include <unistd.h>

#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_elf.h"
#include "sim_io.h"
#include "uart_pty.h"

#define PAINT 0xA5

static volatile sig_atomic_t reset_requested, hang_requested, stop_requested;

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
    else if (sig == SIGUSR2) hang_requested = 1;
    else stop_requested = 1;
}

static long long now_ms(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (long long)ts.tv_sec * 1000 + ts.tv_nsec / 1000000;
}

/* What the bootloader eats: every byte on its way to USART0. The pty part hands bytes on only when
 * the USART says it has room (XON), which it says only while the MCU runs: say it for the
 * bootloader, then drop what came, from the pty part's queue and from the USART's own. */
static void eat_input(avr_t *avr, uart_pty_t *uart) {
    avr_raise_irq(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XON), 1);
    uart->port[0].in.read = uart->port[0].in.write; /* the reader's side: everything read */
    for (avr_io_t *io = avr->io_port; io; io = io->next) {
        if (strcmp(io->kind, "uart") == 0 && ((avr_uart_t *)io)->name == '0') {
            avr_uart_t *usart = (avr_uart_t *)io;
            usart->input.read = usart->input.write;
        }
    }
}

/* Whether the port was opened since the last look (inotify IN_OPEN events, read without waiting). */
static int port_opened(int watch) {
    char events[4096] __attribute__((aligned(__alignof__(struct inotify_event))));
    int opened = 0;
    ssize_t n;
    while ((n = read(watch, events, sizeof events)) > 0) opened = 1;
    return opened;
}

int main(int argc, char **argv) {
    long boot_ms = -1; /* --reset-on-open: the bootloader's time; -1: the port's opens do nothing */
    if (argc > 2 && strcmp(argv[1], "--reset-on-open") == 0) {
        boot_ms = atol(argv[2]);
        argv += 2;
        argc -= 2;
    }
    if (argc < 2 || boot_ms < -1) {
        fprintf(stderr, "usage: simavr_uart [--reset-on-open MS] FIRMWARE.elf [MCU [HZ]]\n");
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
    int watch = -1;
    if (boot_ms >= 0) {
        watch = inotify_init1(IN_NONBLOCK | IN_CLOEXEC);
        if (watch < 0 || inotify_add_watch(watch, uart.port[0].slavename, IN_OPEN) < 0) {
            perror("simavr_uart: inotify");
            return 1;
        }
    }
    printf("serial port %s\n", uart.port[0].slavename);
    fflush(stdout);

    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGUSR1, &sa, 0);
    sigaction(SIGUSR2, &sa, 0);
    sigaction(SIGTERM, &sa, 0);
    sigaction(SIGINT, &sa, 0);

    int state = cpu_Running, hung = 0;
    long long booting_until = 0; /* the bootloader runs (the firmware does not) until then */
    unsigned long steps = 0;
    while (!stop_requested && state != cpu_Done && state != cpu_Crashed) {
        if (reset_requested) {
            reset_requested = 0;
            hung = 0;
            avr_reset(avr);
        }
        if (hang_requested) {
            hang_requested = 0;
            hung = 1;
        }
        /* Look for an open every few thousand steps while the firmware runs (a syscall per
         * instruction would crawl), and every time round while it does not. */
        if (watch >= 0 && (booting_until || hung || ++steps % 4096 == 0) && port_opened(watch)) {
            booting_until = now_ms() + boot_ms; /* DTR: reset, and the bootloader starts */
            printf("port opened: reset, the bootloader runs for %ld ms\n", boot_ms);
            fflush(stdout);
            hung = 0;
        }
        if (booting_until) {
            /* The bootloader reads whatever comes and the firmware never sees it. */
            eat_input(avr, &uart);
            if (now_ms() < booting_until) {
                usleep(1000);
                continue;
            }
            booting_until = 0;
            avr_reset(avr); /* the bootloader hands over: the firmware starts and greets */
        }
        if (hung) {
            usleep(1000);
            continue;
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
