/* Start-up for the LM3S6965: the vector table and the reset handler, in C. The application gives
 * main() and, when it takes UART0's interrupt, lm3s_uart0_isr(); every other exception stops in
 * lm3s_fault, where a debugger finds it.
 *
 * The reset handler paints the unused SRAM between .bss and the stack with STACK_PAINT before main
 * runs: whatever is still painted later was never touched, so a RAM dump (QEMU's pmemsave) shows
 * the deepest the stack went. */
#include <stdint.h>

#include "lm3s6965.h"

#define STACK_PAINT 0xA5A5A5A5u

extern uint32_t __data_start, __data_end, __data_load, __bss_start, __bss_end, __stack_top;
int main(void);
void lm3s_reset(void);
void lm3s_fault(void);
void lm3s_uart0_isr(void) __attribute__((weak, alias("lm3s_fault")));

void lm3s_fault(void) {
    for (;;) {
    }
}

void lm3s_reset(void) {
    const uint32_t *from = &__data_load;
    for (uint32_t *to = &__data_start; to < &__data_end;) *to++ = *from++;
    for (uint32_t *to = &__bss_start; to < &__bss_end;) *to++ = 0;
    uint32_t *sp;
    __asm volatile("mov %0, sp" : "=r"(sp));
    for (uint32_t *to = &__bss_end; to < sp - 8;) *to++ = STACK_PAINT; /* 8 words: this frame */
    main();
    lm3s_fault(); /* main never returns */
}

typedef void (*lm3s_handler)(void);

/* ARMv7-M B1.5.3: word 0 the initial SP, then the exceptions 1-15, then the interrupts (16 + n). */
static const struct {
    uint32_t *initial_sp;
    lm3s_handler handlers[15 + UART0_IRQ + 1];
} vectors __attribute__((section(".vectors"), used)) = {
    &__stack_top,
    {
        lm3s_reset,
        lm3s_fault, /* NMI */
        lm3s_fault, /* HardFault */
        lm3s_fault, /* MemManage */
        lm3s_fault, /* BusFault */
        lm3s_fault, /* UsageFault */
        0, 0, 0, 0,
        lm3s_fault, /* SVCall */
        lm3s_fault, /* DebugMonitor */
        0,
        lm3s_fault, /* PendSV */
        lm3s_fault, /* SysTick: the example polls it instead */
        lm3s_fault, /* 0 GPIO A */
        lm3s_fault, /* 1 GPIO B */
        lm3s_fault, /* 2 GPIO C */
        lm3s_fault, /* 3 GPIO D */
        lm3s_fault, /* 4 GPIO E */
        lm3s_uart0_isr, /* 5 UART0 */
    },
};
