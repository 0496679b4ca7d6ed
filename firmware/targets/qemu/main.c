/* main.c: the emulated board on `qemu-system-arm -M netduinoplus2` (STM32F405).
 *
 *   USART1 (serial0) = station link (run with -serial pty: the station opens the pty like a CDC port)
 *   USART2 (serial1) = sensor bridge (a socket chardev; the world simulator plays the sensor)
 *   NVM              = ARM semihosting file nvm.bin in QEMU's working directory (two slots)
 *
 * Both USARTs receive by RXNE interrupt into ring buffers; the idle loop sleeps with WFI, so an
 * idle board costs ~0 % of a host core. A full ring masks its RXNEIE (QEMU then stops taking bytes
 * from the chardev: lossless back-pressure) until the main loop has drained it.
 * The core is initialised only after the bridge's `$B` identity strap; then `$READY*HH` goes back
 * on the bridge. Each `$S` sample is handed to fw_sample() with the bridge's t_us (the simulated
 * sensor's data-ready time). */
#include <string.h>
#include "stm32f4_regs.h"
#include "fw_board.h"
#include "fw_bridge.h"
#include "semihost.h"


#define STATION_USART USART1_BASE
#define BRIDGE_USART  USART2_BASE

typedef struct ring {
    volatile uint32_t head, tail;   /* head: ISR writes, tail: main reads */
    uint8_t buf[512];
} ring_t;

#define RING_MASK 511u

static ring_t g_station_rx, g_bridge_rx;
static fw_board_t g_board;
static fw_hal_t g_hal;
static fw_linebuf_t g_bridge_line;
static uint32_t g_bridge_bad;
static uint8_t g_ready;

static void usart_write(uint32_t base, const uint8_t *buf, uint32_t len)
{
    uint32_t i;
    for (i = 0; i < len; i++) {
        while ((USART_SR(base) & USART_SR_TXE) == 0u) {
        }
        USART_DR(base) = buf[i];
    }
}

static void station_write(void *ctx, const uint8_t *buf, uint32_t len)
{
    (void)ctx;
    usart_write(STATION_USART, buf, len);
}

static int nvm_read(void *ctx, uint32_t slot, uint8_t *buf, uint32_t len)
{
    (void)ctx;
    return sh_nvm_read(slot, buf, len);
}

static int nvm_write(void *ctx, uint32_t slot, const uint8_t *buf, uint32_t len)
{
    (void)ctx;
    return sh_nvm_write(slot, buf, len);
}

static void usart_isr(uint32_t base, ring_t *r)
{
    while (USART_SR(base) & USART_SR_RXNE) {
        uint32_t head = r->head;
        if (head - r->tail >= sizeof r->buf) {
            USART_CR1(base) &= ~USART_CR1_RXNEIE;   /* full: leave the byte in DR, back-pressure */
            return;
        }
        r->buf[head & RING_MASK] = (uint8_t)USART_DR(base);
        r->head = head + 1u;
    }
}

void USART1_IRQHandler(void)
{
    usart_isr(STATION_USART, &g_station_rx);
}

void USART2_IRQHandler(void)
{
    usart_isr(BRIDGE_USART, &g_bridge_rx);
}

static uint32_t ring_read(ring_t *r, uint32_t base, uint8_t *out, uint32_t cap)
{
    uint32_t n = 0, tail = r->tail, head = r->head;
    while (tail != head && n < cap) {
        out[n++] = r->buf[tail & RING_MASK];
        tail++;
    }
    r->tail = tail;
    if (n > 0u && (USART_CR1(base) & USART_CR1_RXNEIE) == 0u) {
        USART_CR1(base) |= USART_CR1_RXNEIE;   /* room again: take bytes (a pending RXNE fires now) */
    }
    return n;
}

static void usart_init(uint32_t base)
{
    USART_BRR(base) = 0x2D9u;   /* 115200 at 84 MHz APB2 (ignored by QEMU) */
    USART_CR2(base) = 0u;
    USART_CR3(base) = 0u;
    USART_CR1(base) = USART_CR1_UE | USART_CR1_TE | USART_CR1_RE | USART_CR1_RXNEIE;
}

/* One bridge byte: the core's line accumulator and bridge parser (core/fw_bridge.h). A repeated
 * `$B` (the simulator resends it until it sees `$READY`) is answered again, never re-initialises. */
static void bridge_byte(uint8_t c)
{
    const uint8_t *line;
    uint32_t len;
    fw_identity_t id;
    fw_raw_sample_t s;
    uint8_t out[16];
    int r = fw_linebuf_push(&g_bridge_line, c, &line, &len);

    if (r == 0) {
        return;
    }
    if (r < 0) {
        g_bridge_bad++;
        return;
    }
    switch (fw_bridge_line(line, len, &id, &s)) {
    case FW_BRIDGE_IDENTITY:
        if (!g_ready) {
            fw_board_init(&g_board, &g_hal, &id, 0u);
            g_ready = 1u;
        }
        usart_write(BRIDGE_USART, out, fw_bridge_ready(out, sizeof out));
        break;
    case FW_BRIDGE_SAMPLE:
        if (g_ready) {
            fw_sample(&g_board, &s);
        }
        break;
    default:
        g_bridge_bad++;
        break;
    }
}

int main(void)
{
    uint8_t chunk[64];
    uint32_t n, i;

    g_hal.ctx = 0;
    g_hal.uart_write = station_write;
    g_hal.can_send = 0;
    g_hal.nvm_read = nvm_read;
    g_hal.nvm_write = nvm_write;

    RCC_APB2ENR |= RCC_APB2ENR_USART1;   /* an unimplemented RCC in QEMU; right on silicon */
    RCC_APB1ENR |= RCC_APB1ENR_USART2;
    usart_init(STATION_USART);
    usart_init(BRIDGE_USART);
    SCB_SCR = 0u;                          /* WFI = sleep (not deep sleep), no sleep-on-exit */
    nvic_enable(IRQ_USART1, 2u);
    nvic_enable(IRQ_USART2, 1u);

    for (;;) {
        while ((n = ring_read(&g_bridge_rx, BRIDGE_USART, chunk, sizeof chunk)) > 0u) {
            for (i = 0; i < n; i++) {
                bridge_byte(chunk[i]);
            }
        }
        if (g_ready) {
            n = ring_read(&g_station_rx, STATION_USART, chunk, sizeof chunk);
            if (n > 0u) {
                fw_uart_rx(&g_board, chunk, n);
            }
        }
        irq_disable();
        if (g_bridge_rx.head == g_bridge_rx.tail && (!g_ready || g_station_rx.head == g_station_rx.tail)) {
            cpu_wfi();   /* a pending interrupt wakes the core even with PRIMASK set */
        }
        irq_enable();
    }
}
