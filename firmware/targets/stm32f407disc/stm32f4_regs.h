/* stm32f4_regs.h: the STM32F405/407 registers this firmware touches (RM0090), written from the
 * reference manual; no vendor SDK. Shared by the Discovery target and the QEMU netduinoplus2
 * (STM32F405) target. */
#ifndef STM32F4_REGS_H
#define STM32F4_REGS_H

#include <stdint.h>

#define REG32(addr) (*(volatile uint32_t *)(uintptr_t)(addr))

/* ---- Cortex-M4 core ---- */
#define SCB_VTOR      REG32(0xE000ED08u)
#define SCB_SCR       REG32(0xE000ED10u)
#define SCB_CPACR     REG32(0xE000ED88u)
#define SYST_CSR      REG32(0xE000E010u)   /* ENABLE[0] TICKINT[1] CLKSOURCE[2] COUNTFLAG[16] */
#define SYST_RVR      REG32(0xE000E014u)
#define SYST_CVR      REG32(0xE000E018u)
#define SYST_CSR_ENABLE    (1u << 0)
#define SYST_CSR_TICKINT   (1u << 1)
#define SYST_CSR_CLKSOURCE (1u << 2)   /* 1: the CPU clock; 0: the external reference (HCLK / 8 on STM32F4) */
#define NVIC_SHPR3    REG32(0xE000ED20u)   /* PRI_14 PendSV [23:16], PRI_15 SysTick [31:24] */
#define NVIC_ISER(n)  REG32(0xE000E100u + 4u * (n))
#define NVIC_ICER(n)  REG32(0xE000E180u + 4u * (n))
#define NVIC_IPR8(n)  (*(volatile uint8_t *)(uintptr_t)(0xE000E400u + (n)))

static inline void nvic_enable(unsigned irq, uint8_t prio)
{
    NVIC_IPR8(irq) = (uint8_t)(prio << 4);
    NVIC_ISER(irq >> 5) = 1u << (irq & 31u);
}

/* ---- RCC ---- */
#define RCC_BASE      0x40023800u
#define RCC_CR        REG32(RCC_BASE + 0x00u)   /* HSEON[16] HSERDY[17] PLLON[24] PLLRDY[25] */
#define RCC_PLLCFGR   REG32(RCC_BASE + 0x04u)   /* PLLM[5:0] PLLN[14:6] PLLP[17:16] PLLSRC[22] PLLQ[27:24] */
#define RCC_CFGR      REG32(RCC_BASE + 0x08u)   /* SW[1:0] SWS[3:2] HPRE[7:4] PPRE1[12:10] PPRE2[15:13] */
#define RCC_CIR       REG32(RCC_BASE + 0x0Cu)   /* CSSF[7] CSSC[23] */
#define RCC_CSR       REG32(RCC_BASE + 0x74u)   /* LSION[0] LSIRDY[1] RMVF[24] BORRSTF[25] PINRSTF[26] PORRSTF[27] SFTRSTF[28] IWDGRSTF[29] WWDGRSTF[30] LPWRRSTF[31] */
#define RCC_AHB1ENR   REG32(RCC_BASE + 0x30u)
#define RCC_APB1ENR   REG32(RCC_BASE + 0x40u)
#define RCC_APB2ENR   REG32(RCC_BASE + 0x44u)
#define RCC_CR_HSEON      (1u << 16)
#define RCC_CR_HSERDY     (1u << 17)
#define RCC_CR_PLLON      (1u << 24)
#define RCC_CR_PLLRDY     (1u << 25)
#define RCC_CR_CSSON      (1u << 19)
#define RCC_CIR_CSSF      (1u << 7)
#define RCC_CIR_CSSC      (1u << 23)
#define RCC_CSR_LSION     (1u << 0)
#define RCC_CSR_LSIRDY    (1u << 1)
#define RCC_CSR_RMVF      (1u << 24)
#define RCC_CSR_BORRSTF   (1u << 25)
#define RCC_CSR_PINRSTF   (1u << 26)
#define RCC_CSR_PORRSTF   (1u << 27)
#define RCC_CSR_SFTRSTF   (1u << 28)
#define RCC_CSR_IWDGRSTF  (1u << 29)
#define RCC_CSR_WWDGRSTF  (1u << 30)
#define RCC_CSR_LPWRRSTF  (1u << 31)
#define RCC_PLLCFGR_SRC_HSE (1u << 22)
#define RCC_CFGR_SW_PLL   2u
#define RCC_CFGR_SWS_MASK (3u << 2)
#define RCC_CFGR_SWS_PLL  (2u << 2)
#define RCC_AHB1ENR_GPIOA (1u << 0)
#define RCC_AHB1ENR_GPIOE (1u << 4)
#define RCC_APB1ENR_TIM2  (1u << 0)
#define RCC_APB1ENR_USART2 (1u << 17)
#define RCC_APB1ENR_PWR   (1u << 28)
#define RCC_APB2ENR_USART1 (1u << 4)
#define RCC_APB2ENR_SPI1  (1u << 12)
#define RCC_APB2ENR_SYSCFG (1u << 14)

#define PWR_CR        REG32(0x40007000u)   /* PVDE[4] PLS[7:5] VOS[14] */
#define PWR_CSR       REG32(0x40007004u)   /* PVDO[2] */
#define PWR_CR_VOS    (1u << 14)
#define PWR_CR_PVDE   (1u << 4)
#define PWR_CR_PLS(n) ((uint32_t)(n) << 5)  /* PLS 5: the 2.7 V level (RM0090 5.4.1) */
#define PWR_CR_PLS_MASK (7u << 5)
#define PWR_CSR_PVDO  (1u << 2)             /* 1: VDD below the PVD threshold */

/* ---- IWDG (independent watchdog, LSI ~32 kHz) ---- */
#define IWDG_KR       REG32(0x40003000u)
#define IWDG_PR       REG32(0x40003004u)
#define IWDG_RLR      REG32(0x40003008u)
#define IWDG_SR       REG32(0x4000300Cu)   /* PVU[0] RVU[1] */
#define IWDG_KEY_FEED   0xAAAAu
#define IWDG_KEY_ACCESS 0x5555u
#define IWDG_KEY_START  0xCCCCu

/* ---- Flash interface ---- */
#define FLASH_BASE_R  0x40023C00u
#define FLASH_ACR     REG32(FLASH_BASE_R + 0x00u)   /* LATENCY[2:0] PRFTEN[8] ICEN[9] DCEN[10] ICRST[11] DCRST[12] */
#define FLASH_KEYR    REG32(FLASH_BASE_R + 0x04u)
#define FLASH_SR      REG32(FLASH_BASE_R + 0x0Cu)   /* EOP[0] OPERR[1] WRPERR[4] PGAERR[5] PGPERR[6] PGSERR[7] BSY[16] */
#define FLASH_CR      REG32(FLASH_BASE_R + 0x10u)   /* PG[0] SER[1] SNB[6:3] PSIZE[9:8] STRT[16] LOCK[31] */
#define FLASH_OPTKEYR REG32(FLASH_BASE_R + 0x08u)
#define FLASH_OPTCR   REG32(FLASH_BASE_R + 0x14u)   /* OPTLOCK[0] OPTSTRT[1] BOR_LEV[3:2] USER[7:5] RDP[15:8] nWRP[27:16] */
#define FLASH_OPTKEY1     0x08192A3Bu
#define FLASH_OPTKEY2     0x4C5D6E7Fu
#define FLASH_OPTCR_OPTLOCK (1u << 0)
#define FLASH_OPTCR_OPTSTRT (1u << 1)
#define FLASH_OPTCR_BOR_MASK (3u << 2)
#define FLASH_OPTCR_BOR_LEV3 (0u << 2)   /* 00: BOR level 3, 2.7 V; 11 (factory): BOR off */
#define FLASH_ACR_LATENCY_5WS 5u
#define FLASH_ACR_PRFTEN  (1u << 8)
#define FLASH_ACR_ICEN    (1u << 9)
#define FLASH_ACR_DCEN    (1u << 10)
#define FLASH_ACR_ICRST   (1u << 11)
#define FLASH_ACR_DCRST   (1u << 12)
#define FLASH_KEY1        0x45670123u
#define FLASH_KEY2        0xCDEF89ABu
#define FLASH_SR_EOP      (1u << 0)
#define FLASH_SR_OPERR    (1u << 1)
#define FLASH_SR_WRPERR   (1u << 4)
#define FLASH_SR_PGAERR   (1u << 5)
#define FLASH_SR_PGPERR   (1u << 6)
#define FLASH_SR_PGSERR   (1u << 7)
#define FLASH_SR_BSY      (1u << 16)
#define FLASH_SR_ERRORS   (FLASH_SR_OPERR | FLASH_SR_WRPERR | FLASH_SR_PGAERR | FLASH_SR_PGPERR | FLASH_SR_PGSERR)
#define FLASH_CR_PG       (1u << 0)
#define FLASH_CR_SER      (1u << 1)
#define FLASH_CR_SNB(n)   ((uint32_t)(n) << 3)
#define FLASH_CR_PSIZE_X32 (2u << 8)
#define FLASH_CR_STRT     (1u << 16)
#define FLASH_CR_LOCK     (1u << 31)

/* 96-bit unique device ID */
#define UID_BASE      0x1FFF7A10u

/* ---- GPIO ---- */
#define GPIOA_BASE    0x40020000u
#define GPIOE_BASE    0x40021000u
#define GPIO_MODER(b)   REG32((b) + 0x00u)
#define GPIO_OTYPER(b)  REG32((b) + 0x04u)
#define GPIO_OSPEEDR(b) REG32((b) + 0x08u)
#define GPIO_PUPDR(b)   REG32((b) + 0x0Cu)
#define GPIO_IDR(b)     REG32((b) + 0x10u)
#define GPIO_ODR(b)     REG32((b) + 0x14u)
#define GPIO_BSRR(b)    REG32((b) + 0x18u)
#define GPIO_AFRL(b)    REG32((b) + 0x20u)
#define GPIO_AFRH(b)    REG32((b) + 0x24u)

/* ---- SYSCFG / EXTI ---- */
#define SYSCFG_EXTICR1 REG32(0x40013808u)
#define EXTI_IMR      REG32(0x40013C00u)
#define EXTI_RTSR     REG32(0x40013C08u)
#define EXTI_FTSR     REG32(0x40013C0Cu)
#define EXTI_PR       REG32(0x40013C14u)

/* ---- USART (stm32f2xx_usart in QEMU) ---- */
#define USART1_BASE   0x40011000u
#define USART2_BASE   0x40004400u
#define USART_SR(b)   REG32((b) + 0x00u)   /* RXNE[5] TC[6] TXE[7] ORE[3] */
#define USART_DR(b)   REG32((b) + 0x04u)
#define USART_BRR(b)  REG32((b) + 0x08u)
#define USART_CR1(b)  REG32((b) + 0x0Cu)   /* RE[2] TE[3] RXNEIE[5] TXEIE[7] UE[13] */
#define USART_CR2(b)  REG32((b) + 0x10u)
#define USART_CR3(b)  REG32((b) + 0x14u)
#define USART_SR_ORE  (1u << 3)
#define USART_SR_RXNE (1u << 5)
#define USART_SR_TC   (1u << 6)
#define USART_SR_TXE  (1u << 7)
#define USART_CR1_RE  (1u << 2)
#define USART_CR1_TE  (1u << 3)
#define USART_CR1_RXNEIE (1u << 5)
#define USART_CR1_TXEIE (1u << 7)
#define USART_CR1_UE  (1u << 13)

/* ---- SPI ---- */
#define SPI1_BASE     0x40013000u
#define SPI_CR1(b)    REG32((b) + 0x00u)   /* CPHA[0] CPOL[1] MSTR[2] BR[5:3] SPE[6] SSI[8] SSM[9] */
#define SPI_SR(b)     REG32((b) + 0x08u)   /* RXNE[0] TXE[1] BSY[7] */
#define SPI_DR(b)     REG32((b) + 0x0Cu)
#define SPI_SR_RXNE   (1u << 0)
#define SPI_SR_TXE    (1u << 1)
#define SPI_SR_BSY    (1u << 7)

/* ---- TIM2 (32-bit) ---- */
#define TIM2_BASE     0x40000000u
#define TIM_CR1(b)    REG32((b) + 0x00u)
#define TIM_DIER(b)   REG32((b) + 0x0Cu)
#define TIM_SR(b)     REG32((b) + 0x10u)
#define TIM_EGR(b)    REG32((b) + 0x14u)
#define TIM_CNT(b)    REG32((b) + 0x24u)
#define TIM_PSC(b)    REG32((b) + 0x28u)
#define TIM_ARR(b)    REG32((b) + 0x2Cu)

/* IRQ numbers (STM32F405/407 vector table) */
#define IRQ_EXTI0     6u
#define IRQ_TIM2      28u
#define IRQ_USART1    37u
#define IRQ_USART2    38u

static inline void irq_disable(void) { __asm volatile("cpsid i" ::: "memory"); }
static inline void irq_enable(void) { __asm volatile("cpsie i" ::: "memory"); }
static inline void cpu_wfi(void) { __asm volatile("dsb\n\twfi\n\tisb" ::: "memory"); }

#endif
