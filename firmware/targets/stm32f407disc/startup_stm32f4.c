/* startup_stm32f4.c: vector table and reset handler for STM32F405/407 (Cortex-M4F), no vendor SDK.
 *
 * Reset: enable the FPU (CPACR CP10/CP11 full access) before any C code can touch a float
 * register, copy .data from flash, zero .bss, then main(). Every handler a target does not define
 * is a weak alias of Default_Handler (a spin: a debugger sees where it stopped). */
#include <stdint.h>

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
int main(void);

void Reset_Handler(void);
void Default_Handler(void);
#define WEAK_ALIAS __attribute__((weak, alias("Default_Handler")))
void NMI_Handler(void) WEAK_ALIAS;
void HardFault_Handler(void) WEAK_ALIAS;
void MemManage_Handler(void) WEAK_ALIAS;
void BusFault_Handler(void) WEAK_ALIAS;
void UsageFault_Handler(void) WEAK_ALIAS;
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
