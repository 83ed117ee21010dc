/* The few registers of a TI Stellaris LM3S6965 (Cortex-M3, 256 KiB flash, 64 KiB SRAM) that a
 * Property Service device needs: the system control block's clock and gating, GPIO port A's
 * UART pins, UART0, SysTick and the NVIC. Addresses and bits from the LM3S6965 data sheet
 * (SPMS001) and the ARMv7-M architecture reference; no vendor headers. */
#ifndef LM3S6965_H
#define LM3S6965_H

#include <stdint.h>

#define LM3S_REG(address) (*(volatile uint32_t *)(address))

/* System control (data sheet §6): the clock tree and the peripherals' clock gates. */
#define SYSCTL_RIS LM3S_REG(0x400FE050u)
#define SYSCTL_RCC LM3S_REG(0x400FE060u)
#define SYSCTL_RCGC1 LM3S_REG(0x400FE104u)
#define SYSCTL_RCGC2 LM3S_REG(0x400FE108u)
#define SYSCTL_RIS_PLLLRIS (1u << 6) /* the PLL has locked */
#define SYSCTL_RCC_MOSCDIS (1u << 0)
#define SYSCTL_RCC_OSCSRC_MASK (3u << 4)
#define SYSCTL_RCC_XTAL_MASK (0xFu << 6)
#define SYSCTL_RCC_XTAL_8MHZ (0xEu << 6) /* the evaluation board's crystal */
#define SYSCTL_RCC_BYPASS (1u << 11)
#define SYSCTL_RCC_PWRDN (1u << 13)
#define SYSCTL_RCC_USESYSDIV (1u << 22)
#define SYSCTL_RCC_SYSDIV_MASK (0xFu << 23)
#define SYSCTL_RCC_SYSDIV(n) ((uint32_t)(n) << 23) /* the 200 MHz PLL output / (n + 1) */
#define SYSCTL_RCGC1_UART0 (1u << 0)
#define SYSCTL_RCGC2_GPIOA (1u << 0)

/* GPIO port A: PA0 is U0Rx, PA1 is U0Tx when their alternate function is on. */
#define GPIOA_AFSEL LM3S_REG(0x40004420u)
#define GPIOA_DEN LM3S_REG(0x4000451Cu)

/* UART0 (data sheet §12): a PL011-style UART with 16-byte FIFOs, interrupt 5. */
#define UART0_DR LM3S_REG(0x4000C000u)
#define UART0_FR LM3S_REG(0x4000C018u)
#define UART0_IBRD LM3S_REG(0x4000C024u)
#define UART0_FBRD LM3S_REG(0x4000C028u)
#define UART0_LCRH LM3S_REG(0x4000C02Cu)
#define UART0_CTL LM3S_REG(0x4000C030u)
#define UART0_IFLS LM3S_REG(0x4000C034u)
#define UART0_IM LM3S_REG(0x4000C038u)
#define UART0_ICR LM3S_REG(0x4000C044u)
#define UART_DR_OE (1u << 11) /* the byte after this one was lost: the receive FIFO was full */
#define UART_FR_RXFE (1u << 4)
#define UART_FR_TXFF (1u << 5)
#define UART_LCRH_FEN (1u << 4)
#define UART_LCRH_WLEN_8 (3u << 5)
#define UART_CTL_UARTEN (1u << 0)
#define UART_CTL_TXE (1u << 8)
#define UART_CTL_RXE (1u << 9)
#define UART_IFLS_RX_1_8 (0u << 3) /* interrupt once the receive FIFO holds 2 of its 16 bytes */
#define UART_IM_RXIM (1u << 4)
#define UART_IM_RTIM (1u << 6) /* receive timeout: fewer bytes than the level, then silence */
#define UART0_IRQ 5

/* SysTick (ARMv7-M B3.3): a 24-bit down-counter on the processor clock. */
#define SYST_CSR LM3S_REG(0xE000E010u)
#define SYST_RVR LM3S_REG(0xE000E014u)
#define SYST_CVR LM3S_REG(0xE000E018u)
#define SYST_CSR_ENABLE (1u << 0)
#define SYST_CSR_CLKSOURCE (1u << 2)
#define SYST_CSR_COUNTFLAG (1u << 16) /* reached 0 since the last read; reading clears it */

/* NVIC: one enable bit per external interrupt. */
#define NVIC_ISER0 LM3S_REG(0xE000E100u)

static inline void lm3s_interrupts_off(void) { __asm volatile("cpsid i" ::: "memory"); }
static inline void lm3s_interrupts_on(void) { __asm volatile("cpsie i" ::: "memory"); }

/* The system clock after lm3s_clock_50mhz(). */
#define LM3S_SYSCLK 50000000u

/* Run from the 8 MHz crystal through the PLL at 50 MHz (data sheet §6.3, "Initialization and
 * Configuration"): out of reset the chip runs on its internal oscillator, whose ±30 % no UART
 * can keep to. */
static inline void lm3s_clock_50mhz(void) {
    uint32_t rcc = SYSCTL_RCC;
    rcc = (rcc | SYSCTL_RCC_BYPASS) & ~SYSCTL_RCC_USESYSDIV;
    SYSCTL_RCC = rcc;
    rcc &= ~(SYSCTL_RCC_XTAL_MASK | SYSCTL_RCC_OSCSRC_MASK | SYSCTL_RCC_PWRDN | SYSCTL_RCC_MOSCDIS);
    rcc |= SYSCTL_RCC_XTAL_8MHZ; /* OSCSRC 0: the main oscillator */
    SYSCTL_RCC = rcc;
    rcc = (rcc & ~SYSCTL_RCC_SYSDIV_MASK) | SYSCTL_RCC_SYSDIV(3) | SYSCTL_RCC_USESYSDIV;
    SYSCTL_RCC = rcc;
    while (!(SYSCTL_RIS & SYSCTL_RIS_PLLLRIS)) {
    }
    SYSCTL_RCC = rcc & ~SYSCTL_RCC_BYPASS;
}

#endif
