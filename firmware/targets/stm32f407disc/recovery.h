/* recovery.h: what an STM32F4 board keeps across a reset, and how it resets itself (issue 42).
 * Implemented in startup_stm32f4.c (linked into the Discovery and the QEMU image alike).
 *
 * The no-init block (the first 256 bytes of SRAM, stm32f4.ld) holds, under a magic and a CRC-32:
 *   boots        starts since power-up (1 after a power-on or brown-out)
 *   pending      the cause the firmware stored just before it reset itself (fault handler,
 *                software watchdog, clock failure); 0 when it did not
 *   fault_*      CFSR, HFSR, the stacked PC and the exception number of the last fault
 *   flags/strap  the QEMU board's identity strap, streaming flag and ODR (it comes back streaming
 *                after a watchdog or fault reset); the Clock Security System's HSE failure
 * A power-on leaves SRAM random: the CRC tells a kept block from garbage.
 *
 * Fault handlers: HardFault, MemManage, BusFault, UsageFault and NMI share one entry: take the
 * stacked frame (MSP or PSP by EXC_RETURN), move MSP back to the top of RAM (a stack overflow
 * must not fault again inside the handler), store CFSR/HFSR/PC/exception, reset by SCB AIRCR
 * SYSRESETREQ. NMI first checks RCC_CIR.CSSF (HSE failure, Clock Security System): then the
 * block says so (NOINIT_F_CSS) and the next start reports it. */
#ifndef RECOVERY_H
#define RECOVERY_H

#include <stdint.h>
#include "fw_board.h"

#define NOINIT_MAGIC 0x4E524331u   /* "NRC1" */

#define NOINIT_F_STRAP     1u      /* strap holds the identity the bridge gave (QEMU) */
#define NOINIT_F_STREAMING 2u      /* the station had the board streaming */
#define NOINIT_F_CSS       4u      /* the last reset was the HSE failing (Clock Security System NMI) */

typedef struct noinit_block {
    uint32_t magic;
    uint32_t boots;
    uint32_t pending;       /* fw_reset_cause_t stored before a reset the firmware made itself */
    uint32_t fault_cfsr;
    uint32_t fault_hfsr;
    uint32_t fault_pc;
    uint32_t fault_exc;     /* exception number: 2 NMI, 3 HardFault, 4 MemManage, 5 BusFault, 6 UsageFault */
    uint32_t flags;         /* NOINIT_F_* */
    float odr_hz;           /* the output rate the station set (QEMU resume) */
    fw_identity_t strap;    /* QEMU: the bridge's identity strap */
    uint32_t crc;           /* CRC-32 (zlib) of every byte above */
} noinit_block_t;

/* The block itself (at _noinit_start); its CRC is only checked by boot_info_take. */
noinit_block_t *noinit(void);
/* Recompute the CRC after a change (every writer calls it). */
void noinit_seal(void);

/* Once at start, before anything else writes the block. hw_cause is what the reset flags say
 * (RCC_CSR on silicon; FW_RESET_UNKNOWN on QEMU, which has none). Power-on or brown-out, or no
 * valid block: boots = 1, the block starts afresh (cause power when the flags say nothing). Else
 * boots + 1 and the cause is the flags' (watchdog, pin) or, for a software reset, the one the
 * firmware stored (fault, watchdog) or `software`. pending is cleared; fault_* stay readable. */
void boot_info_take(uint32_t hw_cause, fw_boot_info_t *out);

/* MemManage, BusFault and UsageFault get their own handlers (SHCSR) instead of HardFault. */
void faults_enable(void);
/* Store the cause in the block and reset (SCB AIRCR SYSRESETREQ). */
__attribute__((noreturn)) void system_reset(uint32_t cause);

/* Cortex-M4 system control block registers used for faults and reset. */
#define SCB_AIRCR   (*(volatile uint32_t *)0xE000ED0Cu)
#define SCB_SHCSR   (*(volatile uint32_t *)0xE000ED24u)
#define SCB_CFSR    (*(volatile uint32_t *)0xE000ED28u)
#define SCB_HFSR    (*(volatile uint32_t *)0xE000ED2Cu)
#define SCB_AIRCR_SYSRESETREQ (0x05FA0000u | (1u << 2))

#endif
