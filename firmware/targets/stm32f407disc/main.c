/* main.c: STM32F407 Discovery (STM32F407VGT6) target of the board firmware.
 *
 *   clock    168 MHz SYSCLK from the 8 MHz HSE crystal via the main PLL (M 8, N 336, P 2, Q 7),
 *            AHB 168, APB1 42 (timers 84), APB2 84 MHz; flash 5 wait states, prefetch + caches
 *   time     TIM2 (32-bit) at 1 MHz = the board's microsecond clock (wraps after 71.6 min, like
 *            the protocol's uint32 t_us)
 *   station  USART2 on PA2 (TX) / PA3 (RX), 115200 8N1, to a USB-serial adapter (RX by RXNE
 *            interrupt into a ring, TX by TXE interrupt from a ring)
 *   sensor   on-board LIS3DSH on SPI1 (PA5 SCK, PA6 MISO, PA7 MOSI, CS PE3), mode 3, 5.25 MHz,
 *            100 Hz, +-2 g, DRDY on INT1 = PE0 -> EXTI0 (rising edge, timestamped with TIM2)
 *   NVM      flash sectors 2 and 3 (16 KB each, 0x08008000 / 0x0800C000), one record slot each,
 *            kept free of code by the linker script (flash.c)
 *   serial   "F4-" + 8 hex digits of a FNV-1a hash of the 96-bit unique ID */
#include <string.h>
#include "stm32f4_regs.h"
#include "fw_board.h"
#include "lis3dsh.h"
#include "flash_nvm.h"

#ifndef FW_VERSION_STRING
#define FW_VERSION_STRING "fw-c-1.0"
#endif

#define HSE_HZ      8000000u
#define APB1_HZ     42000000u
#define STATION_BAUD 115200u
#define SENSOR_ODR  LIS3DSH_ODR_100HZ
#define SENSOR_FS   LIS3DSH_FS_2G

/* ---- rings ---- */
#define RX_RING 256u
#define TX_RING 1024u
static volatile uint32_t g_rx_head, g_rx_tail, g_tx_head, g_tx_tail;
static uint8_t g_rx_buf[RX_RING], g_tx_buf[TX_RING];
static volatile uint32_t g_rx_overruns;

static volatile uint32_t g_drdy_count;   /* EXTI0 edges */
static volatile uint32_t g_drdy_t_us;    /* TIM2 at the latest edge */

static fw_board_t g_board;
static fw_hal_t g_hal;
static lis3dsh_ctx_t g_sensor;
static uint32_t g_sysclk_hz = 16000000u;

/* ---- clock ---- */
static void clock_init(void)
{
    uint32_t spin;

    RCC_APB1ENR |= RCC_APB1ENR_PWR;
    PWR_CR |= PWR_CR_VOS;                          /* regulator scale 1: needed for 168 MHz */
    RCC_CR |= RCC_CR_HSEON;
    for (spin = 0; spin < 1000000u && (RCC_CR & RCC_CR_HSERDY) == 0u; spin++) {
    }
    if ((RCC_CR & RCC_CR_HSERDY) == 0u) {
        return;                                    /* no crystal: stay on the 16 MHz HSI */
    }
    FLASH_ACR = FLASH_ACR_LATENCY_5WS | FLASH_ACR_PRFTEN | FLASH_ACR_ICEN | FLASH_ACR_DCEN;
    while ((FLASH_ACR & 7u) != FLASH_ACR_LATENCY_5WS) {
    }
    /* AHB /1, APB1 /4 (42 MHz), APB2 /2 (84 MHz) */
    RCC_CFGR = (RCC_CFGR & ~((0xFu << 4) | (7u << 10) | (7u << 13))) | (5u << 10) | (4u << 13);
    RCC_PLLCFGR = (HSE_HZ / 1000000u) | (336u << 6) | (0u << 16) | RCC_PLLCFGR_SRC_HSE | (7u << 24);
    RCC_CR |= RCC_CR_PLLON;
    while ((RCC_CR & RCC_CR_PLLRDY) == 0u) {
    }
    RCC_CFGR = (RCC_CFGR & ~3u) | RCC_CFGR_SW_PLL;
    while ((RCC_CFGR & RCC_CFGR_SWS_MASK) != RCC_CFGR_SWS_PLL) {
    }
    g_sysclk_hz = 168000000u;
}

static uint32_t apb1_hz(void)
{
    return g_sysclk_hz == 168000000u ? APB1_HZ : g_sysclk_hz;
}

/* ---- TIM2: microseconds ---- */
static void timer_init(void)
{
    RCC_APB1ENR |= RCC_APB1ENR_TIM2;
    /* APB1 prescaler != 1 doubles the timer clock: 84 MHz at 168 MHz SYSCLK */
    TIM_PSC(TIM2_BASE) = (g_sysclk_hz == 168000000u ? 2u * APB1_HZ : g_sysclk_hz) / 1000000u - 1u;
    TIM_ARR(TIM2_BASE) = 0xFFFFFFFFu;
    TIM_EGR(TIM2_BASE) = 1u;   /* UG: load the prescaler */
    TIM_CNT(TIM2_BASE) = 0u;
    TIM_CR1(TIM2_BASE) = 1u;   /* CEN */
}

static inline uint32_t micros(void)
{
    return TIM_CNT(TIM2_BASE);
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

static void station_write(void *ctx, const uint8_t *buf, uint32_t len)
{
    uint32_t i;
    (void)ctx;
    for (i = 0; i < len; i++) {
        while (g_tx_head - g_tx_tail >= TX_RING) {
            cpu_wfi();   /* ring full: the TXE interrupt frees a byte every 87 us */
        }
        g_tx_buf[g_tx_head % TX_RING] = buf[i];
        g_tx_head++;
        irq_disable();
        USART_CR1(USART2_BASE) |= USART_CR1_TXEIE;
        irq_enable();
    }
}

/* ---- SPI1 + LIS3DSH ---- */
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

static uint8_t spi_xfer(uint8_t out)
{
    while ((SPI_SR(SPI1_BASE) & SPI_SR_TXE) == 0u) {
    }
    SPI_DR(SPI1_BASE) = out;
    while ((SPI_SR(SPI1_BASE) & SPI_SR_RXNE) == 0u) {
    }
    return (uint8_t)SPI_DR(SPI1_BASE);
}

static void spi_done(void)
{
    while (SPI_SR(SPI1_BASE) & SPI_SR_BSY) {
    }
    GPIO_BSRR(GPIOE_BASE) = 1u << 3;          /* CS high */
}

static int32_t lis_read(void *handle, uint8_t reg, uint8_t *buf, uint16_t len)
{
    uint16_t i;
    (void)handle;
    GPIO_BSRR(GPIOE_BASE) = 1u << (3u + 16u); /* CS low */
    (void)spi_xfer(lis3dsh_spi_addr(reg, 1));
    for (i = 0; i < len; i++) {
        buf[i] = spi_xfer(0u);
    }
    spi_done();
    return 0;
}

static int32_t lis_write(void *handle, uint8_t reg, const uint8_t *buf, uint16_t len)
{
    uint16_t i;
    (void)handle;
    GPIO_BSRR(GPIOE_BASE) = 1u << (3u + 16u);
    (void)spi_xfer(lis3dsh_spi_addr(reg, 0));
    for (i = 0; i < len; i++) {
        (void)spi_xfer(buf[i]);
    }
    spi_done();
    return 0;
}

static void drdy_init(void)
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
    g_drdy_t_us = micros();
    g_drdy_count++;
}

/* ---- NVM and identity ---- */
static int nvm_read(void *ctx, uint32_t slot, uint8_t *buf, uint32_t len)
{
    (void)ctx;
    return flash_nvm_read(slot, buf, len);
}

static int nvm_write(void *ctx, uint32_t slot, const uint8_t *buf, uint32_t len)
{
    (void)ctx;
    return flash_nvm_write(slot, buf, len);
}

static void serial_from_uid(char *out)
{
    static const char hex[] = "0123456789ABCDEF";
    const volatile uint8_t *uid = (const volatile uint8_t *)(uintptr_t)UID_BASE;
    uint32_t h = 2166136261u;                 /* FNV-1a 32 over the 12 UID bytes */
    unsigned i;
    for (i = 0; i < 12u; i++) {
        h = (h ^ uid[i]) * 16777619u;
    }
    out[0] = 'F';
    out[1] = '4';
    out[2] = '-';
    for (i = 0; i < 8u; i++) {
        out[3u + i] = hex[(h >> (28u - 4u * i)) & 0xFu];
    }
    out[11] = '\0';
}

static void send_error(const char *body)
{
    uint8_t out[64];
    uint32_t n = fw_frame((const uint8_t *)body, (uint32_t)strlen(body), out, sizeof out);
    station_write(0, out, n);
}

int main(void)
{
    fw_identity_t id;
    fw_raw_sample_t s;
    uint8_t chunk[32];
    uint32_t seen = 0, n;
    int sensor_ok;

    clock_init();
    RCC_AHB1ENR |= RCC_AHB1ENR_GPIOA | RCC_AHB1ENR_GPIOE;
    (void)RCC_AHB1ENR;   /* two cycles after the enable before the first GPIO access */
    timer_init();
    station_init();
    spi_init();

    memset(&id, 0, sizeof id);
    serial_from_uid(id.serial);
    strncpy(id.sensor, "LIS3DSH", FW_SENSOR_MAX);
    strncpy(id.fw, FW_VERSION_STRING, FW_FW_MAX);
    id.ug_per_lsb = LIS3DSH_UG_PER_LSB_2G;
    id.t_lsb_per_c = LIS3DSH_T_LSB_PER_C;
    id.t_lsb_at_25c = LIS3DSH_T_LSB_AT_25C;
    id.odr_hz = lis3dsh_odr_hz(SENSOR_ODR);

    g_hal.ctx = 0;
    g_hal.uart_write = station_write;
    g_hal.can_send = 0;
    g_hal.nvm_read = nvm_read;
    g_hal.nvm_write = nvm_write;

    g_sensor.read = lis_read;
    g_sensor.write = lis_write;
    g_sensor.handle = 0;
    sensor_ok = (lis3dsh_init(&g_sensor, SENSOR_ODR, SENSOR_FS) == 0);

    fw_board_init(&g_board, &g_hal, &id, 0u);
    if (!sensor_ok) {
        send_error("E,SENSOR,LIS3DSH not found");
    } else {
        drdy_init();
        (void)lis3dsh_read_sample(&g_sensor, &s);   /* a pending sample would hold INT1 high: no edge */
    }

    for (;;) {
        n = 0;
        while (g_rx_tail != g_rx_head && n < sizeof chunk) {
            chunk[n++] = g_rx_buf[g_rx_tail % RX_RING];
            g_rx_tail++;
        }
        if (n > 0u) {
            fw_uart_rx(&g_board, chunk, n);
        }
        /* a new edge, or INT1 still high (a sample we were too late for: no new edge would come) */
        if (sensor_ok && (g_drdy_count != seen || (GPIO_IDR(GPIOE_BASE) & 1u))) {
            uint32_t t_us;
            irq_disable();
            t_us = (g_drdy_count != seen) ? g_drdy_t_us : micros();
            seen = g_drdy_count;
            irq_enable();
            if (lis3dsh_read_sample(&g_sensor, &s) == 0) {
                s.t_us = t_us;
                fw_sample(&g_board, &s);
            }
            continue;
        }
        irq_disable();
        if (g_rx_tail == g_rx_head && g_drdy_count == seen) {
            cpu_wfi();
        }
        irq_enable();
    }
}
