/* main.c: STM32F407 Discovery (STM32F407VGT6) target of the board firmware.
 *
 *   clock    168 MHz SYSCLK from the 8 MHz HSE crystal via the main PLL (M 8, N 336, P 2, Q 7),
 *            AHB 168, APB1 42 (timers 84), APB2 84 MHz; flash 5 wait states, prefetch + caches;
 *            Clock Security System on (an HSE failure is an NMI: the cause is stored, the board
 *            resets, and comes back on the HSI saying `E,CLOCK,...`)
 *   time     TIM2 (32-bit) at 1 MHz = the board's microsecond clock (wraps after 71.6 min, like
 *            the protocol's uint32 t_us); SysTick every 10 ms wakes the loop (liveness, watchdog)
 *   station  USART2 on PA2 (TX) / PA3 (RX), 115200 8N1, to a USB-serial adapter (RX by RXNE
 *            interrupt into a ring, TX by TXE interrupt from a ring)
 *   sensor   on-board LIS3DSH on SPI1 (PA5 SCK, PA6 MISO, PA7 MOSI, CS PE3), mode 3, 5.25 MHz,
 *            100 Hz, +-2 g, FIFO in stream mode with a watermark of 10 on INT1 = PE0 -> EXTI0
 *            (rising edge timestamped with TIM2); each sample's data-ready time is reconstructed
 *            from the watermark time and the ODR
 *   NVM      flash sectors 2 and 3 (16 KB each, 0x08008000 / 0x0800C000), one record slot each,
 *            kept free of code by the linker script (flash_nvm.c); refused below 2.7 V (PVD)
 *   serial   "F4" + the 96-bit unique ID in hex (fw_serial_from_uid)
 *   recovery IWDG (~2 s) fed only when the loop made progress; fault handlers store CFSR/HFSR/PC
 *            in the no-init block and reset (recovery.h); reset cause from RCC_CSR + that block;
 *            BOR level 3 (2.7 V) in the option bytes; every hardware wait bounded */
#include <string.h>
#include "stm32f4_regs.h"
#include "fw_board.h"
#include "fw_health.h"
#include "lis3dsh.h"
#include "flash_nvm.h"
#include "recovery.h"

#ifndef FW_VERSION_STRING
#define FW_VERSION_STRING "fw-c-1.0"
#endif

#define HSE_HZ      8000000u
#define APB1_HZ     42000000u
#define STATION_BAUD 115200u
#define SENSOR_ODR  LIS3DSH_ODR_100HZ
#define SENSOR_FS   LIS3DSH_FS_2G
#define FIFO_WTM    10u           /* samples per watermark interrupt: 100 ms at 100 Hz */
#define TICK_MS     10u           /* SysTick: the loop's liveness/watchdog cadence */
#define SPI_TIMEOUT_US 200u       /* one byte at 5.25 MHz takes 1.5 us */
#define TX_TIMEOUT_US  20000u     /* the TX ring frees a byte every 87 us: 20 ms without one is a stuck USART */
#define CLOCK_SPINS 2000000u      /* HSE/PLL/switch waits, counted (TIM2 is not running yet): >100 ms at 16 MHz */

/* ---- rings ---- */
#define RX_RING 256u
#define TX_RING 1024u
static volatile uint32_t g_rx_head, g_rx_tail, g_tx_head, g_tx_tail;
static uint8_t g_rx_buf[RX_RING], g_tx_buf[TX_RING];
static volatile uint32_t g_rx_overruns, g_tx_dropped;

static volatile uint32_t g_wtm_count;    /* EXTI0 edges (FIFO watermark) */
static volatile uint32_t g_wtm_t_us;     /* TIM2 at the latest edge */
static volatile uint32_t g_ticks;        /* SysTick */

static fw_board_t g_board;
static fw_hal_t g_hal;
static lis3dsh_ctx_t g_sensor;
static fw_health_t g_health;
static uint32_t g_sysclk_hz = 16000000u;
static uint8_t g_clock_fault;            /* 1: no HSE at start, 2: PLL did not lock */
static uint32_t g_spi_errors;

/* ---- clock ---- */
static int spin_until(volatile uint32_t *reg, uint32_t mask, uint32_t want)
{
    uint32_t spin;
    for (spin = 0; spin < CLOCK_SPINS; spin++) {
        if ((*reg & mask) == want) {
            return 0;
        }
    }
    return -1;
}

static void clock_init(void)
{
    RCC_APB1ENR |= RCC_APB1ENR_PWR;
    PWR_CR |= PWR_CR_VOS;                          /* regulator scale 1: needed for 168 MHz */
    RCC_CR |= RCC_CR_HSEON;
    if (spin_until(&RCC_CR, RCC_CR_HSERDY, RCC_CR_HSERDY) != 0) {
        RCC_CR &= ~RCC_CR_HSEON;
        g_clock_fault = 1u;                        /* no crystal: stay on the 16 MHz HSI, and say so */
        return;
    }
    FLASH_ACR = FLASH_ACR_LATENCY_5WS | FLASH_ACR_PRFTEN | FLASH_ACR_ICEN | FLASH_ACR_DCEN;
    if (spin_until(&FLASH_ACR, 7u, FLASH_ACR_LATENCY_5WS) != 0) {
        g_clock_fault = 2u;
        return;
    }
    /* AHB /1, APB1 /4 (42 MHz), APB2 /2 (84 MHz) */
    RCC_CFGR = (RCC_CFGR & ~((0xFu << 4) | (7u << 10) | (7u << 13))) | (5u << 10) | (4u << 13);
    RCC_PLLCFGR = (HSE_HZ / 1000000u) | (336u << 6) | (0u << 16) | RCC_PLLCFGR_SRC_HSE | (7u << 24);
    RCC_CR |= RCC_CR_PLLON;
    if (spin_until(&RCC_CR, RCC_CR_PLLRDY, RCC_CR_PLLRDY) != 0) {
        RCC_CR &= ~RCC_CR_PLLON;
        RCC_CFGR &= ~((7u << 10) | (7u << 13));    /* back to undivided buses on the HSI */
        g_clock_fault = 2u;
        return;
    }
    RCC_CFGR = (RCC_CFGR & ~3u) | RCC_CFGR_SW_PLL;
    if (spin_until(&RCC_CFGR, RCC_CFGR_SWS_MASK, RCC_CFGR_SWS_PLL) != 0) {
        RCC_CFGR &= ~3u;
        g_clock_fault = 2u;
        return;
    }
    RCC_CR |= RCC_CR_CSSON;                        /* HSE failure -> NMI (recovery.h), clock -> HSI */
    g_sysclk_hz = 168000000u;
}

static uint32_t apb1_hz(void)
{
    return g_sysclk_hz == 168000000u ? APB1_HZ : g_sysclk_hz;
}

/* ---- TIM2: microseconds; SysTick: the loop's tick ---- */
static void timer_init(void)
{
    RCC_APB1ENR |= RCC_APB1ENR_TIM2;
    /* APB1 prescaler != 1 doubles the timer clock: 84 MHz at 168 MHz SYSCLK */
    TIM_PSC(TIM2_BASE) = (g_sysclk_hz == 168000000u ? 2u * APB1_HZ : g_sysclk_hz) / 1000000u - 1u;
    TIM_ARR(TIM2_BASE) = 0xFFFFFFFFu;
    TIM_EGR(TIM2_BASE) = 1u;   /* UG: load the prescaler */
    TIM_CNT(TIM2_BASE) = 0u;
    TIM_CR1(TIM2_BASE) = 1u;   /* CEN */

    SYST_RVR = g_sysclk_hz / 1000u * TICK_MS - 1u;   /* 1.68 M at 168 MHz: fits 24 bits */
    SYST_CVR = 0u;
    NVIC_SHPR3 = (NVIC_SHPR3 & 0x00FFFFFFu) | (3u << 28);
    SYST_CSR = SYST_CSR_CLKSOURCE | SYST_CSR_TICKINT | SYST_CSR_ENABLE;
}

void SysTick_Handler(void)
{
    g_ticks++;   /* only wakes the loop from WFI */
}

static uint32_t micros(void)
{
    return TIM_CNT(TIM2_BASE);
}

/* ---- independent watchdog: LSI ~32 kHz / 64 = 500 Hz, reload 999: ~2 s (1.4-3.8 s over the LSI's
 * 17-47 kHz), longer than the longest legitimate stall (a 16 KB sector erase, 500 ms max) ---- */
static void iwdg_init(void)
{
    uint32_t t0;
    IWDG_KR = IWDG_KEY_START;
    IWDG_KR = IWDG_KEY_ACCESS;
    IWDG_PR = 4u;            /* /64 */
    IWDG_RLR = 999u;
    t0 = micros();
    while ((IWDG_SR & 3u) != 0u && micros() - t0 < 100000u) {
        /* PVU/RVU: the values cross into the LSI domain (a few LSI periods) */
    }
    IWDG_KR = IWDG_KEY_FEED;
}

static void iwdg_feed(void)
{
    IWDG_KR = IWDG_KEY_FEED;
}

/* ---- reset cause (RCC_CSR; cleared with RMVF so the next reset's flags are its own) ---- */
static uint32_t reset_flags_cause(void)
{
    uint32_t csr = RCC_CSR, cause;
    /* an internal reset also drives NRST, so PINRSTF comes with every other flag: test it last */
    if (csr & RCC_CSR_PORRSTF) cause = FW_RESET_POWER;
    else if (csr & RCC_CSR_BORRSTF) cause = FW_RESET_BROWNOUT;
    else if (csr & (RCC_CSR_IWDGRSTF | RCC_CSR_WWDGRSTF)) cause = FW_RESET_WATCHDOG;
    else if (csr & RCC_CSR_SFTRSTF) cause = FW_RESET_SOFTWARE;   /* the no-init block says fault or not */
    else if (csr & RCC_CSR_LPWRRSTF) cause = FW_RESET_UNKNOWN;
    else if (csr & RCC_CSR_PINRSTF) cause = FW_RESET_PIN;
    else cause = FW_RESET_UNKNOWN;
    RCC_CSR |= RCC_CSR_RMVF;
    return cause;
}

/* ---- supply: PVD at 2.7 V (NVM writes are refused below it), BOR level 3 in the option bytes ---- */
static void pvd_init(void)
{
    PWR_CR = (PWR_CR & ~PWR_CR_PLS_MASK) | PWR_CR_PLS(5u) | PWR_CR_PVDE;
}

/* BOR level 3 (reset below ~2.7 V, the bottom of the x32 flash programming range) is programmed
 * once, only when the option bytes say otherwise (factory: BOR off) and the PVD says the supply is
 * above 2.7 V now (a board running below it would otherwise hold itself in reset). The other option
 * bits (RDP, WRP, USER) are written back unchanged. Returns 1 if it programmed, 0 if not needed,
 * <0 when it could not. */
static int bor_level3(void)
{
    uint32_t t0;
    if ((FLASH_OPTCR & FLASH_OPTCR_BOR_MASK) == FLASH_OPTCR_BOR_LEV3) {
        return 0;
    }
    if (PWR_CSR & PWR_CSR_PVDO) {
        return -1;
    }
    t0 = micros();
    while (FLASH_SR & FLASH_SR_BSY) {
        if (micros() - t0 > 100000u) {
            return -2;
        }
    }
    FLASH_OPTKEYR = FLASH_OPTKEY1;
    FLASH_OPTKEYR = FLASH_OPTKEY2;
    FLASH_OPTCR = (FLASH_OPTCR & ~FLASH_OPTCR_BOR_MASK) | FLASH_OPTCR_BOR_LEV3;
    FLASH_OPTCR |= FLASH_OPTCR_OPTSTRT;
    t0 = micros();
    while (FLASH_SR & FLASH_SR_BSY) {
        if (micros() - t0 > 1000000u) {
            FLASH_OPTCR |= FLASH_OPTCR_OPTLOCK;
            return -2;
        }
    }
    FLASH_OPTCR |= FLASH_OPTCR_OPTLOCK;
    return (FLASH_OPTCR & FLASH_OPTCR_BOR_MASK) == FLASH_OPTCR_BOR_LEV3 ? 1 : -3;
}

/* ---- GPIO helpers ---- */
static void gpio_mode(uint32_t base, unsigned pin, uint32_t mode)
{
    GPIO_MODER(base) = (GPIO_MODER(base) & ~(3u << (2u * pin))) | (mode << (2u * pin));
}

static void gpio_af(uint32_t base, unsigned pin, uint32_t af)
{
    gpio_mode(base, pin, 2u);
    GPIO_OSPEEDR(base) |= 2u << (2u * pin);   /* high speed */
    if (pin < 8u) {
        GPIO_AFRL(base) = (GPIO_AFRL(base) & ~(0xFu << (4u * pin))) | (af << (4u * pin));
    } else {
        GPIO_AFRH(base) = (GPIO_AFRH(base) & ~(0xFu << (4u * (pin - 8u)))) | (af << (4u * (pin - 8u)));
    }
}

/* ---- USART2 station link ---- */
static void station_init(void)
{
    RCC_APB1ENR |= RCC_APB1ENR_USART2;
    gpio_af(GPIOA_BASE, 2u, 7u);
    gpio_af(GPIOA_BASE, 3u, 7u);
    GPIO_PUPDR(GPIOA_BASE) = (GPIO_PUPDR(GPIOA_BASE) & ~(3u << 6)) | (1u << 6);   /* RX pull-up */
    USART_BRR(USART2_BASE) = (apb1_hz() + STATION_BAUD / 2u) / STATION_BAUD;       /* 0x16D at 42 MHz */
    USART_CR2(USART2_BASE) = 0u;   /* 1 stop bit */
    USART_CR3(USART2_BASE) = 0u;
    USART_CR1(USART2_BASE) = USART_CR1_UE | USART_CR1_TE | USART_CR1_RE | USART_CR1_RXNEIE;   /* 8N1 */
    nvic_enable(IRQ_USART2, 2u);
}

void USART2_IRQHandler(void)
{
    uint32_t sr = USART_SR(USART2_BASE);
    if (sr & (USART_SR_RXNE | USART_SR_ORE)) {
        uint8_t c = (uint8_t)USART_DR(USART2_BASE);   /* SR then DR read also clears ORE */
        if (sr & USART_SR_ORE) {
            g_rx_overruns++;
        }
        if (g_rx_head - g_rx_tail < RX_RING) {
            g_rx_buf[g_rx_head % RX_RING] = c;
            g_rx_head++;
        } else {
            g_rx_overruns++;
        }
    }
    if ((USART_CR1(USART2_BASE) & USART_CR1_TXEIE) && (sr & USART_SR_TXE)) {
        if (g_tx_tail != g_tx_head) {
            USART_DR(USART2_BASE) = g_tx_buf[g_tx_tail % TX_RING];
            g_tx_tail++;
        } else {
            USART_CR1(USART2_BASE) &= ~USART_CR1_TXEIE;
        }
    }
}

/* Queue bytes for the TXE interrupt. A full ring waits (WFI: the interrupt frees a byte every
 * 87 us) at most TX_TIMEOUT_US per byte; a USART that never raises TXE loses the rest of the frame
 * (counted), it never hangs the loop. */
static void station_write(void *ctx, const uint8_t *buf, uint32_t len)
{
    uint32_t i, t0;
    (void)ctx;
    for (i = 0; i < len; i++) {
        t0 = micros();
        while (g_tx_head - g_tx_tail >= TX_RING) {
            if (micros() - t0 > TX_TIMEOUT_US) {
                g_tx_dropped += len - i;
                return;
            }
            cpu_wfi();
        }
        g_tx_buf[g_tx_head % TX_RING] = buf[i];
        g_tx_head++;
        irq_disable();
        USART_CR1(USART2_BASE) |= USART_CR1_TXEIE;
        irq_enable();
    }
}

static void send_error(const char *code, const char *text)
{
    uint8_t body[80], out[96];
    uint32_t n = 0, k;
    const char *parts[3] = { "E,", code, text };
    for (k = 0; k < 3u; k++) {
        const char *p = parts[k];
        while (*p && n < sizeof body - 1u) {
            body[n++] = (uint8_t)*p++;
        }
        if (k == 1u && n < sizeof body - 1u) {
            body[n++] = ',';
        }
    }
    n = fw_frame(body, n, out, sizeof out);
    station_write(0, out, n);
}

/* ---- SPI1 + LIS3DSH: every wait bounded, errors returned to the driver ---- */
static void spi_init(void)
{
    RCC_APB2ENR |= RCC_APB2ENR_SPI1;
    gpio_af(GPIOA_BASE, 5u, 5u);
    gpio_af(GPIOA_BASE, 6u, 5u);
    gpio_af(GPIOA_BASE, 7u, 5u);
    GPIO_BSRR(GPIOE_BASE) = 1u << 3;          /* CS high (idle) before it becomes an output */
    gpio_mode(GPIOE_BASE, 3u, 1u);
    /* master, mode 3 (CPOL 1, CPHA 1), 84 MHz / 16 = 5.25 MHz (LIS3DSH: 10 MHz max), software NSS */
    SPI_CR1(SPI1_BASE) = (1u << 0) | (1u << 1) | (1u << 2) | (3u << 3) | (1u << 8) | (1u << 9);
    SPI_CR1(SPI1_BASE) |= 1u << 6;            /* SPE */
}

static int spi_wait(uint32_t mask, uint32_t want)
{
    uint32_t t0 = micros();
    while ((SPI_SR(SPI1_BASE) & mask) != want) {
        if (micros() - t0 > SPI_TIMEOUT_US) {
            g_spi_errors++;
            return -1;
        }
    }
    return 0;
}

static int spi_xfer(uint8_t out, uint8_t *in)
{
    if (spi_wait(SPI_SR_TXE, SPI_SR_TXE) != 0) {
        return -1;
    }
    SPI_DR(SPI1_BASE) = out;
    if (spi_wait(SPI_SR_RXNE, SPI_SR_RXNE) != 0) {
        return -1;
    }
    *in = (uint8_t)SPI_DR(SPI1_BASE);
    return 0;
}

static int spi_done(int rc)
{
    if (spi_wait(SPI_SR_BSY, 0u) != 0) {
        rc = -1;
    }
    GPIO_BSRR(GPIOE_BASE) = 1u << 3;          /* CS high, whatever happened */
    if (rc != 0) {
        (void)SPI_DR(SPI1_BASE);              /* drop a half-received byte */
    }
    return rc;
}

static int32_t lis_read(void *handle, uint8_t reg, uint8_t *buf, uint16_t len)
{
    uint16_t i;
    uint8_t dummy;
    int rc;
    (void)handle;
    GPIO_BSRR(GPIOE_BASE) = 1u << (3u + 16u); /* CS low */
    rc = spi_xfer(lis3dsh_spi_addr(reg, 1), &dummy);
    for (i = 0; i < len && rc == 0; i++) {
        rc = spi_xfer(0u, &buf[i]);
    }
    return spi_done(rc);
}

static int32_t lis_write(void *handle, uint8_t reg, const uint8_t *buf, uint16_t len)
{
    uint16_t i;
    uint8_t dummy;
    int rc;
    (void)handle;
    GPIO_BSRR(GPIOE_BASE) = 1u << (3u + 16u);
    rc = spi_xfer(lis3dsh_spi_addr(reg, 0), &dummy);
    for (i = 0; i < len && rc == 0; i++) {
        rc = spi_xfer(buf[i], &dummy);
    }
    return spi_done(rc);
}

static void int1_init(void)
{
    RCC_APB2ENR |= RCC_APB2ENR_SYSCFG;
    gpio_mode(GPIOE_BASE, 0u, 0u);            /* PE0 input: LIS3DSH INT1 (push-pull, active high) */
    SYSCFG_EXTICR1 = (SYSCFG_EXTICR1 & ~0xFu) | 4u;   /* EXTI0 <- port E */
    EXTI_RTSR |= 1u;
    EXTI_FTSR &= ~1u;
    EXTI_PR = 1u;
    EXTI_IMR |= 1u;
    nvic_enable(IRQ_EXTI0, 1u);
}

void EXTI0_IRQHandler(void)
{
    EXTI_PR = 1u;
    g_wtm_t_us = micros();
    g_wtm_count++;
}

static int sensor_start(void)
{
    int32_t rc = lis3dsh_init(&g_sensor, SENSOR_ODR, SENSOR_FS);
    if (rc == 0) {
        rc = lis3dsh_fifo_stream(&g_sensor, (uint8_t)FIFO_WTM);
    }
    return rc == 0 ? 0 : -1;
}

/* ---- NVM and identity ---- */
static int nvm_read(void *ctx, uint32_t slot, uint8_t *buf, uint32_t len)
{
    (void)ctx;
    return flash_nvm_read(slot, buf, len);
}

static int nvm_write(void *ctx, uint32_t slot, const uint8_t *buf, uint32_t len)
{
    int rc;
    (void)ctx;
    rc = flash_nvm_write(slot, buf, len);
    if (rc != FLASH_NVM_OK) {
        send_error("NVM", flash_nvm_error_text(rc));   /* why; the core then says which command failed */
    }
    return rc;
}

/* ---- samples: drain the FIFO, reconstruct each sample's data-ready time ---- */
static uint32_t g_wtm_seen, g_last_t_us, g_period_us = 10000u;
static uint8_t g_have_last;
static uint32_t g_taken_since_feed;

static void take_fifo(void)
{
    fw_raw_sample_t batch[LIS3DSH_FIFO_DEPTH];
    uint32_t n = 0, k, edge_t = 0, now;
    uint8_t src = 0;
    int fresh_edge;

    irq_disable();
    fresh_edge = g_wtm_count != g_wtm_seen;
    edge_t = g_wtm_t_us;
    g_wtm_seen = g_wtm_count;
    irq_enable();
    if (lis3dsh_fifo_status(&g_sensor, &n, &src) != 0 || n == 0u) {
        return;
    }
    if (lis3dsh_fifo_read(&g_sensor, batch, n) != 0) {
        return;
    }
    now = micros();
    for (k = 0; k < n; k++) {
        uint32_t t;
        if (src & LIS3DSH_FIFO_SRC_OVRN) {
            t = now - (n - 1u - k) * g_period_us;          /* samples were overwritten: anchor at now */
        } else if (fresh_edge && n >= FIFO_WTM) {
            t = lis3dsh_fifo_t_us(edge_t, FIFO_WTM, k, g_period_us);
        } else if (g_have_last) {
            t = g_last_t_us + (k + 1u) * g_period_us;      /* no new edge (a late read): continue the line */
        } else {
            t = now - (n - 1u - k) * g_period_us;
        }
        batch[k].t_us = t;
        fw_sample(&g_board, &batch[k]);
    }
    g_last_t_us = batch[n - 1u].t_us;
    g_have_last = 1u;
    g_taken_since_feed += n;
    fw_health_data_ready(&g_health, g_last_t_us);
}

int main(void)
{
    fw_identity_t id;
    fw_boot_info_t boot;
    uint8_t uid[12];
    uint8_t chunk[32];
    uint32_t n, i, hw_cause;
    int sensor_ok, bor;

    hw_cause = reset_flags_cause();
    boot_info_take(hw_cause, &boot);
    faults_enable();
    clock_init();
    RCC_AHB1ENR |= RCC_AHB1ENR_GPIOA | RCC_AHB1ENR_GPIOE;
    (void)RCC_AHB1ENR;   /* two cycles after the enable before the first GPIO access */
    timer_init();
    iwdg_init();
    pvd_init();
    station_init();
    spi_init();
    flash_nvm_init(micros, iwdg_feed);

    memset(&id, 0, sizeof id);
    for (i = 0; i < 12u; i++) {
        uid[i] = ((const volatile uint8_t *)(uintptr_t)UID_BASE)[i];
    }
    (void)fw_serial_from_uid(uid, id.serial);
    strncpy(id.sensor, "LIS3DSH", FW_SENSOR_MAX);
    strncpy(id.fw, FW_VERSION_STRING, FW_FW_MAX);
    id.ug_per_lsb = LIS3DSH_UG_PER_LSB_2G;
    id.t_lsb_per_c = LIS3DSH_T_LSB_PER_C;
    id.t_lsb_at_25c = LIS3DSH_T_LSB_AT_25C;
    id.odr_hz = lis3dsh_odr_hz(SENSOR_ODR);
    g_period_us = (uint32_t)(1e6f / id.odr_hz);

    g_hal.ctx = 0;
    g_hal.uart_write = station_write;
    g_hal.can_send = 0;
    g_hal.nvm_read = nvm_read;
    g_hal.nvm_write = nvm_write;

    g_sensor.read = lis_read;
    g_sensor.write = lis_write;
    g_sensor.handle = 0;
    sensor_ok = sensor_start() == 0;
    /* the FIFO raises the watermark every FIFO_WTM samples: that much silence is normal */
    fw_health_init(&g_health, FIFO_WTM * g_period_us, 0u);

    fw_board_init(&g_board, &g_hal, &id, 0u);
    fw_board_set_boot(&g_board, &boot);
    if (noinit()->flags & NOINIT_F_CSS) {
        send_error("CLOCK", g_clock_fault ? "HSE failed (clock security system): running on the 16 MHz HSI"
                                          : "HSE failed (clock security system), back after the reset");
        noinit()->flags &= ~NOINIT_F_CSS;   /* said once */
        noinit_seal();
    } else if (g_clock_fault == 1u) {
        send_error("CLOCK", "no HSE: running on the 16 MHz HSI");
    } else if (g_clock_fault == 2u) {
        send_error("CLOCK", "PLL did not lock: running on the 16 MHz HSI");
    }
    bor = bor_level3();
    if (bor < 0) {
        send_error("SUPPLY", bor == -1 ? "below 2.7 V: BOR level 3 not programmed" : "BOR level 3 not programmed");
    }
    if (!sensor_ok) {
        send_error("SENSOR", "LIS3DSH not found");
    }
    int1_init();   /* after the FIFO is set: a watermark already reached shows as INT1 high */

    for (;;) {
        int progress, health_ran;
        fw_health_verdict_t v;

        n = 0;
        while (g_rx_tail != g_rx_head && n < sizeof chunk) {
            chunk[n++] = g_rx_buf[g_rx_tail % RX_RING];
            g_rx_tail++;
        }
        if (n > 0u) {
            fw_uart_rx(&g_board, chunk, n);
        }
        /* a new watermark edge, or INT1 still high (a batch we were late for: no new edge comes) */
        if (g_wtm_count != g_wtm_seen || (GPIO_IDR(GPIOE_BASE) & 1u)) {
            take_fifo();
        }

        /* liveness: while streaming, no data-ready within 3 output periods (+ one FIFO batch) */
        v = fw_health_poll(&g_health, micros(), fw_board_period_us(&g_board), fw_board_streaming(&g_board));
        if (v == FW_HEALTH_SUSPECT) {
            uint8_t who = 0;
            fw_health_who_am_i(&g_health, lis3dsh_who_am_i(&g_sensor, &who) == 0 && who == LIS3DSH_ID);
            v = fw_health_poll(&g_health, micros(), fw_board_period_us(&g_board), 1);
        }
        if (v == FW_HEALTH_REINIT) {
            uint32_t silent_ms = fw_health_silent_ms(&g_health, micros());
            sensor_ok = sensor_start() == 0;
            g_have_last = 0u;
            fw_health_reinit_done(&g_health, micros());
            fw_board_sensor_reinit(&g_board, silent_ms);
        }
        health_ran = 1;

        /* the watchdog is fed only for progress: idle, the loop ran; streaming, it took samples
         * since the last feed, or its liveness check (just above) ran: a silent sensor is that
         * check's to handle (re-init within 3 periods), a loop stuck anywhere else starves the IWDG */
        progress = !fw_board_streaming(&g_board) || g_taken_since_feed > 0u || health_ran;
        if (progress) {
            iwdg_feed();
            g_taken_since_feed = 0u;
        }

        if (g_rx_tail == g_rx_head && g_wtm_count == g_wtm_seen) {
            fw_board_idle(&g_board);   /* nothing waits: finish a long reply (core/fw_board.h) */
        }
        irq_disable();
        if (g_rx_tail == g_rx_head && g_wtm_count == g_wtm_seen && (GPIO_IDR(GPIOE_BASE) & 1u) == 0u) {
            cpu_wfi();   /* SysTick wakes it every TICK_MS at the latest */
        }
        irq_enable();
    }
}
