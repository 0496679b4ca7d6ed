/* startup_stm32f4.c: vector table and reset handler for STM32F405/407 (Cortex-M4F), no vendor SDK;
 * the fault handlers and the no-init block of recovery.h.
 *
 * Reset: enable the FPU (CPACR CP10/CP11 full access) before any C code can touch a float
 * register, copy .data from flash, zero .bss, then main(). NMI, HardFault, MemManage, BusFault and
 * UsageFault share Fault_Entry (store the cause, reset: recovery.h). Every other handler a target
 * does not define is a weak alias of Default_Handler (a spin: a debugger sees where it stopped). */
#include <stdint.h>
#include <stddef.h>
#include "stm32f4_regs.h"
#include "recovery.h"

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
extern uint8_t _noinit_start[], _noinit_size[];
int main(void);

void Reset_Handler(void);
void Default_Handler(void);
void Fault_Entry(void);
#define WEAK_ALIAS __attribute__((weak, alias("Default_Handler")))
#define FAULT_ALIAS __attribute__((weak, alias("Fault_Entry")))
void NMI_Handler(void) FAULT_ALIAS;
void HardFault_Handler(void) FAULT_ALIAS;
void MemManage_Handler(void) FAULT_ALIAS;
void BusFault_Handler(void) FAULT_ALIAS;
void UsageFault_Handler(void) FAULT_ALIAS;
void SVC_Handler(void) WEAK_ALIAS;
void DebugMon_Handler(void) WEAK_ALIAS;
void PendSV_Handler(void) WEAK_ALIAS;
void SysTick_Handler(void) WEAK_ALIAS;
void EXTI0_IRQHandler(void) WEAK_ALIAS;
void TIM2_IRQHandler(void) WEAK_ALIAS;
void USART1_IRQHandler(void) WEAK_ALIAS;
void USART2_IRQHandler(void) WEAK_ALIAS;

#define N_IRQ 82u   /* STM32F405/407: IRQ 0..81 */

typedef void (*vector_t)(void);

__attribute__((section(".isr_vector"), used))
const vector_t g_vectors[16u + N_IRQ] = {
    (vector_t)(uintptr_t)&_estack,
    Reset_Handler,
    NMI_Handler,
    HardFault_Handler,
    MemManage_Handler,
    BusFault_Handler,
    UsageFault_Handler,
    0, 0, 0, 0,
    SVC_Handler,
    DebugMon_Handler,
    0,
    PendSV_Handler,
    SysTick_Handler,
    Default_Handler,  /* IRQ 0 */
    Default_Handler,  /* IRQ 1 */
    Default_Handler,  /* IRQ 2 */
    Default_Handler,  /* IRQ 3 */
    Default_Handler,  /* IRQ 4 */
    Default_Handler,  /* IRQ 5 */
    EXTI0_IRQHandler,  /* IRQ 6 */
    Default_Handler,  /* IRQ 7 */
    Default_Handler,  /* IRQ 8 */
    Default_Handler,  /* IRQ 9 */
    Default_Handler,  /* IRQ 10 */
    Default_Handler,  /* IRQ 11 */
    Default_Handler,  /* IRQ 12 */
    Default_Handler,  /* IRQ 13 */
    Default_Handler,  /* IRQ 14 */
    Default_Handler,  /* IRQ 15 */
    Default_Handler,  /* IRQ 16 */
    Default_Handler,  /* IRQ 17 */
    Default_Handler,  /* IRQ 18 */
    Default_Handler,  /* IRQ 19 */
    Default_Handler,  /* IRQ 20 */
    Default_Handler,  /* IRQ 21 */
    Default_Handler,  /* IRQ 22 */
    Default_Handler,  /* IRQ 23 */
    Default_Handler,  /* IRQ 24 */
    Default_Handler,  /* IRQ 25 */
    Default_Handler,  /* IRQ 26 */
    Default_Handler,  /* IRQ 27 */
    TIM2_IRQHandler,  /* IRQ 28 */
    Default_Handler,  /* IRQ 29 */
    Default_Handler,  /* IRQ 30 */
    Default_Handler,  /* IRQ 31 */
    Default_Handler,  /* IRQ 32 */
    Default_Handler,  /* IRQ 33 */
    Default_Handler,  /* IRQ 34 */
    Default_Handler,  /* IRQ 35 */
    Default_Handler,  /* IRQ 36 */
    USART1_IRQHandler,  /* IRQ 37 */
    USART2_IRQHandler,  /* IRQ 38 */
    Default_Handler,  /* IRQ 39 */
    Default_Handler,  /* IRQ 40 */
    Default_Handler,  /* IRQ 41 */
    Default_Handler,  /* IRQ 42 */
    Default_Handler,  /* IRQ 43 */
    Default_Handler,  /* IRQ 44 */
    Default_Handler,  /* IRQ 45 */
    Default_Handler,  /* IRQ 46 */
    Default_Handler,  /* IRQ 47 */
    Default_Handler,  /* IRQ 48 */
    Default_Handler,  /* IRQ 49 */
    Default_Handler,  /* IRQ 50 */
    Default_Handler,  /* IRQ 51 */
    Default_Handler,  /* IRQ 52 */
    Default_Handler,  /* IRQ 53 */
    Default_Handler,  /* IRQ 54 */
    Default_Handler,  /* IRQ 55 */
    Default_Handler,  /* IRQ 56 */
    Default_Handler,  /* IRQ 57 */
    Default_Handler,  /* IRQ 58 */
    Default_Handler,  /* IRQ 59 */
    Default_Handler,  /* IRQ 60 */
    Default_Handler,  /* IRQ 61 */
    Default_Handler,  /* IRQ 62 */
    Default_Handler,  /* IRQ 63 */
    Default_Handler,  /* IRQ 64 */
    Default_Handler,  /* IRQ 65 */
    Default_Handler,  /* IRQ 66 */
    Default_Handler,  /* IRQ 67 */
    Default_Handler,  /* IRQ 68 */
    Default_Handler,  /* IRQ 69 */
    Default_Handler,  /* IRQ 70 */
    Default_Handler,  /* IRQ 71 */
    Default_Handler,  /* IRQ 72 */
    Default_Handler,  /* IRQ 73 */
    Default_Handler,  /* IRQ 74 */
    Default_Handler,  /* IRQ 75 */
    Default_Handler,  /* IRQ 76 */
    Default_Handler,  /* IRQ 77 */
    Default_Handler,  /* IRQ 78 */
    Default_Handler,  /* IRQ 79 */
    Default_Handler,  /* IRQ 80 */
    Default_Handler,  /* IRQ 81 */
};

__attribute__((naked, noreturn)) void Reset_Handler(void)
{
    /* FPU on first, in assembly: the compiler may use s-registers in any C function. */
    __asm volatile(
        "ldr r0, =0xE000ED88\n\t"
        "ldr r1, [r0]\n\t"
        "orr r1, r1, #(0xF << 20)\n\t"
        "str r1, [r0]\n\t"
        "dsb\n\t"
        "isb\n\t"
        "b reset_c\n\t");
}

__attribute__((used, noreturn)) void reset_c(void);
__attribute__((used, noreturn)) void reset_c(void)
{
    uint32_t *src = &_sidata;
    uint32_t *dst = &_sdata;
    while (dst < &_edata) {
        *dst++ = *src++;
    }
    for (dst = &_sbss; dst < &_ebss; dst++) {
        *dst = 0u;
    }
    (void)main();
    for (;;) {
        __asm volatile("wfi");
    }
}

void Default_Handler(void)
{
    for (;;) {
    }
}

/* ---- no-init block (recovery.h) ---- */

/* C99 static assertion: the block fits its 256-byte region (stm32f4.ld NOINIT). */
typedef char noinit_fits[(sizeof(noinit_block_t) <= 256u) ? 1 : -1];

noinit_block_t *noinit(void)
{
    return (noinit_block_t *)(void *)_noinit_start;
}

static uint32_t noinit_crc(const noinit_block_t *b)
{
    return fw_crc32(0u, (const uint8_t *)b, (uint32_t)offsetof(noinit_block_t, crc));
}

void noinit_seal(void)
{
    noinit_block_t *b = noinit();
    b->magic = NOINIT_MAGIC;
    b->crc = noinit_crc(b);
}

void boot_info_take(uint32_t hw_cause, fw_boot_info_t *out)
{
    noinit_block_t *b = noinit();
    int kept = b->magic == NOINIT_MAGIC && b->crc == noinit_crc(b);
    uint32_t cause;

    out->fault_cfsr = 0u;
    out->fault_pc = 0u;
    if (!kept || hw_cause == FW_RESET_POWER || hw_cause == FW_RESET_BROWNOUT) {
        /* power-up (or a block nobody can trust): start afresh */
        uint8_t *p = (uint8_t *)b;
        for (uint32_t i = 0; i < (uint32_t)sizeof *b; i++) {
            p[i] = 0u;
        }
        b->boots = 1u;
        cause = hw_cause != FW_RESET_UNKNOWN ? hw_cause : FW_RESET_POWER;
    } else {
        b->boots = b->boots < 0xFFFFFFFFu ? b->boots + 1u : b->boots;
        if ((hw_cause == FW_RESET_SOFTWARE || hw_cause == FW_RESET_UNKNOWN) && b->pending != 0u) {
            cause = b->pending;           /* the firmware reset itself and said why */
        } else if (hw_cause != FW_RESET_UNKNOWN) {
            cause = hw_cause;             /* the reset flags: watchdog, pin, software */
        } else {
            cause = FW_RESET_SOFTWARE;    /* QEMU: a SYSRESETREQ that stored no cause */
        }
        if (cause != FW_RESET_FAULT) {
            b->flags &= ~NOINIT_F_CSS;
        }
    }
    if (cause == FW_RESET_FAULT) {
        out->fault_cfsr = b->fault_cfsr;
        out->fault_pc = b->fault_pc;
    }
    b->pending = 0u;
    noinit_seal();
    out->cause = (uint8_t)cause;
    out->boots = b->boots;
}

void faults_enable(void)
{
    SCB_SHCSR |= (1u << 16) | (1u << 17) | (1u << 18);   /* MEMFAULTENA BUSFAULTENA USGFAULTENA */
    __asm volatile("dsb\n\tisb" ::: "memory");
}

void system_reset(uint32_t cause)
{
    noinit_block_t *b = noinit();
    b->pending = cause;
    noinit_seal();
    __asm volatile("dsb" ::: "memory");
    SCB_AIRCR = SCB_AIRCR_SYSRESETREQ;
    __asm volatile("dsb" ::: "memory");
    for (;;) {
    }
}

/* Called by Fault_Entry with the stacked frame (r0 r1 r2 r3 r12 lr pc xpsr) and IPSR, on a fresh
 * MSP. The frame pointer is checked before use: after a stack overflow it may point anywhere. */
__attribute__((used, noreturn)) void fault_record(const uint32_t *frame, uint32_t ipsr);
__attribute__((used, noreturn)) void fault_record(const uint32_t *frame, uint32_t ipsr)
{
    noinit_block_t *b = noinit();
    uintptr_t f = (uintptr_t)frame;
    uint32_t exc = ipsr & 0x1FFu;

    b->fault_cfsr = SCB_CFSR;
    b->fault_hfsr = SCB_HFSR;
    b->fault_exc = exc;
    b->fault_pc = 0u;
    if ((f & 3u) == 0u && f >= (uintptr_t)_noinit_start + (uintptr_t)_noinit_size
        && f + 32u <= (uintptr_t)&_estack) {
        b->fault_pc = frame[6];
    }
    if (exc == 2u && (RCC_CIR & RCC_CIR_CSSF)) {
        RCC_CIR = RCC_CIR_CSSC;   /* the HSE failed; the clock is already back on the HSI */
        b->flags |= NOINIT_F_CSS;
    }
    system_reset(FW_RESET_FAULT);
}

__attribute__((naked)) void Fault_Entry(void)
{
    __asm volatile(
        "tst lr, #4\n\t"
        "ite eq\n\t"
        "mrseq r0, msp\n\t"
        "mrsne r0, psp\n\t"
        "mrs r1, ipsr\n\t"
        "ldr r2, =_estack\n\t"
        "msr msp, r2\n\t"
        "b fault_record\n\t");
}
