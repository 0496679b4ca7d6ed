/* main.c: the emulated board on `qemu-system-arm -M netduinoplus2` (STM32F405).
 *
 *   USART1 (serial0) = station link (run with -serial pty: the station opens the pty like a CDC port)
 *   USART2 (serial1) = sensor bridge (a socket chardev; the world simulator plays the sensor)
 *   NVM              = ARM semihosting file nvm.bin in QEMU's working directory (two slots)
 *   TIM2             = the board's microsecond clock (QEMU's timers count its virtual clock at
 *                      1 GHz: PSC 999), the time base of the sensor's liveness
 *   SysTick          = the watchdog (QEMU 7.2 has no IWDG) and the loop's tick: every 20 ms while
 *                      streaming, every 400 ms while not (an idle guest stays at ~0 % host CPU)
 *
 * Both USARTs receive by RXNE interrupt into ring buffers; the idle loop sleeps with WFI. A full
 * ring masks its RXNEIE (QEMU then stops taking bytes from the chardev: lossless back-pressure)
 * until the main loop has drained it.
 *
 * Start: the reset cause and boots come from the no-init block (recovery.h; first start = power,
 * QEMU keeps SRAM across its system reset). `$BOOT*HH` goes out on the bridge. A board whose block
 * holds the bridge's identity strap (it was running before a watchdog or fault reset) boots at once
 * with it, streaming again if it was, at the ODR it had; otherwise it waits for the simulator's
 * `$B` strap. Either way each `$B` is answered `$READY*HH`. Each `$S` sample is handed to
 * fw_sample() with the bridge's t_us (the simulated sensor's data-ready time).
 *
 * Recovery (issue 42): the SysTick watchdog resets (SYSRESETREQ, cause watchdog) when the loop
 * made no progress for WDT_MS (streaming: no sample taken and no liveness check run; idle: the loop
 * did not run). While streaming, no `$S` within max(3 output periods, 250 ms) of the guest's own
 * clock -> `$INIT*HH` on the bridge (the simulated sensor's re-init) and fw_board_sensor_reinit.
 * Fault injection from the bridge (`$X,...`): hardfault (an undefined instruction: UsageFault ->
 * the fault handler stores CFSR and PC and resets), hang (the loop spins: the watchdog resets),
 * selfcal_skew (fw_board_selfcal_skew). */
#include <string.h>
#include "stm32f4_regs.h"
#include "fw_board.h"
#include "fw_bridge.h"
#include "fw_health.h"
#include "recovery.h"
#include "semihost.h"


#define STATION_USART USART1_BASE
#define BRIDGE_USART  USART2_BASE

#define CPU_HZ        168000000u   /* QEMU's netduinoplus2 SYSCLK (SysTick on the CPU clock) */
#define TICK_STREAM_MS 20u
#define TICK_IDLE_MS   400u         /* on the 21 MHz reference clock (HCLK / 8): 24 bits hold 798 ms */
#define WDT_MS         1000u        /* no progress for this long: reset */
/* The bridge delivers samples in bursts (the world simulator's 50 ms ticks, longer on a loaded
 * machine): a gap shorter than this on the guest's clock is the link, not a silent sensor. */
#define SILENCE_MIN_US 250000u
#define TXE_SPINS      100000u      /* QEMU's USART transmits synchronously (TXE always set) */

typedef struct ring {
    volatile uint32_t head, tail;   /* head: ISR writes, tail: main reads */
    uint8_t buf[512];
} ring_t;

#define RING_MASK 511u

static ring_t g_station_rx, g_bridge_rx;
static fw_board_t g_board;
static fw_hal_t g_hal;
static fw_linebuf_t g_bridge_line;
static fw_health_t g_health;
static fw_boot_info_t g_boot;
static uint32_t g_bridge_bad, g_tx_timeouts;
static uint8_t g_ready;
static uint32_t g_taken_since_feed;

static volatile uint32_t g_wdt_ms;        /* ms since the loop last fed the watchdog */
static volatile uint32_t g_tick_ms = TICK_IDLE_MS;

static void usart_write(uint32_t base, const uint8_t *buf, uint32_t len)
{
    uint32_t i, spin;
    for (i = 0; i < len; i++) {
        for (spin = 0; (USART_SR(base) & USART_SR_TXE) == 0u; spin++) {
            if (spin > TXE_SPINS) {
                g_tx_timeouts++;          /* a USART that never empties loses the frame, no hang */
                return;
            }
        }
        USART_DR(base) = buf[i];
    }
}

static void station_write(void *ctx, const uint8_t *buf, uint32_t len)
{
    (void)ctx;
    usart_write(STATION_USART, buf, len);
}

static void bridge_send(uint32_t (*build)(uint8_t *, uint32_t))
{
    uint8_t out[16];
    usart_write(BRIDGE_USART, out, build(out, sizeof out));
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

/* The watchdog: QEMU 7.2's STM32F405 has no IWDG, so SysTick (a hardware timer interrupt at the
 * highest configurable priority) counts the time since the loop's last feed and resets the board
 * through SYSRESETREQ with the cause stored. Unlike the IWDG it cannot catch a hang with
 * interrupts masked (PRIMASK) or inside a higher-priority handler. */
void SysTick_Handler(void)
{
    uint32_t ms = g_wdt_ms + g_tick_ms;
    g_wdt_ms = ms;
    if (ms >= WDT_MS) {
        system_reset(FW_RESET_WATCHDOG);
    }
}

static void tick_set(uint32_t ms)
{
    if (ms == g_tick_ms && (SYST_CSR & SYST_CSR_ENABLE)) {
        return;
    }
    /* the CPU clock for short ticks, the reference clock (CPU / 8) for long ones */
    uint32_t ref = ms > 90u;
    SYST_CSR = 0u;
    g_tick_ms = ms;
    SYST_RVR = (ref ? CPU_HZ / 8u : CPU_HZ) / 1000u * ms - 1u;
    SYST_CVR = 0u;
    SYST_CSR = (ref ? 0u : SYST_CSR_CLKSOURCE) | SYST_CSR_TICKINT | SYST_CSR_ENABLE;
}

static void wdt_feed(void)
{
    g_wdt_ms = 0u;
}

static uint32_t micros(void)
{
    return TIM_CNT(TIM2_BASE);
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

/* ---- what survives a reset: the strap, streaming and the ODR (no-init block) ---- */
static void board_start(const fw_identity_t *id)
{
    fw_board_init(&g_board, &g_hal, id, 0u);
    fw_board_set_boot(&g_board, &g_boot);
    g_ready = 1u;
}

static void persist_state(void)
{
    noinit_block_t *nb = noinit();
    uint32_t flags = (nb->flags & ~NOINIT_F_STREAMING) | (fw_board_streaming(&g_board) ? NOINIT_F_STREAMING : 0u);
    if (flags != nb->flags || nb->odr_hz != g_board.odr_hz) {
        nb->flags = flags;
        nb->odr_hz = g_board.odr_hz;
        noinit_seal();
    }
}

/* The state kept across a watchdog/fault reset: the station set streaming and the ODR; set the
 * core's public fields as fw_set_decimation would (there is no core call for a resume). */
static void resume_state(const noinit_block_t *nb)
{
    if (nb->odr_hz > 0.0f && nb->odr_hz < g_board.id.odr_hz) {
        float k = g_board.id.odr_hz / nb->odr_hz;
        uint32_t decim = (uint32_t)(k + 0.5f);
        if (decim > 1u) {
            g_board.decim = decim;
            g_board.phase = 0u;
            g_board.odr_hz = g_board.id.odr_hz / (float)decim;
        }
    }
    g_board.streaming = (nb->flags & NOINIT_F_STREAMING) ? 1u : 0u;
}

/* ---- fault injection (bridge `$X`, simulation only) ---- */
__attribute__((noinline, used)) void inject_hardfault(void);
__attribute__((noinline, used)) void inject_hardfault(void)
{
    __asm volatile("udf #0" ::: "memory");   /* UsageFault UNDEFINSTR: the fault handler resets */
}

__attribute__((noinline, used)) void inject_hang(void);
__attribute__((noinline, used)) void inject_hang(void)
{
    for (;;) {
        __asm volatile("" ::: "memory");     /* interrupts on: only the watchdog gets out of here */
    }
}

/* One bridge byte: the core's line accumulator and bridge parser (core/fw_bridge.h). A repeated
 * `$B` (the simulator resends it until it sees `$READY`) is answered again, never re-initialises. */
static void bridge_byte(uint8_t c)
{
    const uint8_t *line;
    uint32_t len;
    fw_identity_t id;
    fw_raw_sample_t s;
    fw_bridge_fault_t x;
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
            noinit_block_t *nb = noinit();
            board_start(&id);
            nb->strap = id;
            nb->flags |= NOINIT_F_STRAP;
            noinit_seal();
        }
        bridge_send(fw_bridge_ready);
        break;
    case FW_BRIDGE_SAMPLE:
        if (g_ready) {
            fw_sample(&g_board, &s);
            fw_health_data_ready(&g_health, micros());
            g_taken_since_feed++;
        }
        break;
    default:
        if (fw_bridge_fault(line, len, &x) != FW_BRIDGE_FAULT) {
            g_bridge_bad++;
        } else if (x.kind == FW_FAULT_HARDFAULT) {
            inject_hardfault();
        } else if (x.kind == FW_FAULT_HANG) {
            inject_hang();
        } else if (x.kind == FW_FAULT_SELFCAL_SKEW && g_ready) {
            fw_board_selfcal_skew(&g_board, x.value);
        }
        break;
    }
}

/* While streaming: no `$S` within the deadline of the guest's clock -> re-init the sensor. The
 * bridge sensor has no WHO_AM_I register to read, so SUSPECT goes straight on to the re-init. */
static int liveness(void)
{
    fw_health_verdict_t v = fw_health_poll(&g_health, micros(), fw_board_period_us(&g_board),
                                           fw_board_streaming(&g_board));
    if (v == FW_HEALTH_SUSPECT) {
        fw_health_who_am_i(&g_health, 1);
        v = fw_health_poll(&g_health, micros(), fw_board_period_us(&g_board), 1);
    }
    if (v == FW_HEALTH_REINIT) {
        uint32_t silent_ms = fw_health_silent_ms(&g_health, micros());
        bridge_send(fw_bridge_init);
        fw_health_reinit_done(&g_health, micros());
        fw_board_sensor_reinit(&g_board, silent_ms);
    }
    return 1;
}

int main(void)
{
    uint8_t chunk[64];
    uint32_t n, i;
    noinit_block_t *nb;

    boot_info_take(FW_RESET_UNKNOWN, &g_boot);   /* QEMU has no reset flags: the block says it all */
    faults_enable();
    nb = noinit();

    g_hal.ctx = 0;
    g_hal.uart_write = station_write;
    g_hal.can_send = 0;
    g_hal.nvm_read = nvm_read;
    g_hal.nvm_write = nvm_write;

    RCC_APB2ENR |= RCC_APB2ENR_USART1;   /* an unimplemented RCC in QEMU; right on silicon */
    RCC_APB1ENR |= RCC_APB1ENR_USART2 | RCC_APB1ENR_TIM2;
    TIM_PSC(TIM2_BASE) = 999u;           /* 1 GHz / 1000 = 1 MHz */
    TIM_ARR(TIM2_BASE) = 0xFFFFFFFFu;
    TIM_EGR(TIM2_BASE) = 1u;
    TIM_CR1(TIM2_BASE) = 1u;
    usart_init(STATION_USART);
    usart_init(BRIDGE_USART);
    SCB_SCR = 0u;                          /* WFI = sleep (not deep sleep), no sleep-on-exit */
    NVIC_SHPR3 = (NVIC_SHPR3 & 0x00FFFFFFu);   /* SysTick: priority 0, above both USARTs */
    nvic_enable(IRQ_USART1, 2u);
    nvic_enable(IRQ_USART2, 1u);
    fw_health_init(&g_health, 0u, SILENCE_MIN_US);
    tick_set(TICK_IDLE_MS);

    if ((nb->flags & NOINIT_F_STRAP) && g_boot.cause != FW_RESET_POWER) {
        board_start(&nb->strap);           /* a reset, not a power-up: the board comes back by itself */
        resume_state(nb);
    }
    bridge_send(fw_bridge_boot);

    for (;;) {
        int progress, health_ran = 0;
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
            health_ran = liveness();
            persist_state();
            tick_set(fw_board_streaming(&g_board) ? TICK_STREAM_MS : TICK_IDLE_MS);
        }
        /* fed only for progress: idle, the loop ran; streaming, it took samples since the last
         * feed or ran its liveness check (a silent sensor is that check's to handle) */
        progress = !g_ready || !fw_board_streaming(&g_board) || g_taken_since_feed > 0u || health_ran;
        if (progress) {
            wdt_feed();
            g_taken_since_feed = 0u;
        }
        if (g_ready && g_bridge_rx.head == g_bridge_rx.tail && g_station_rx.head == g_station_rx.tail) {
            fw_board_idle(&g_board);   /* nothing waits: finish a long reply (core/fw_board.h) */
        }
        irq_disable();
        if (g_bridge_rx.head == g_bridge_rx.tail && (!g_ready || g_station_rx.head == g_station_rx.tail)) {
            cpu_wfi();   /* a pending interrupt wakes the core even with PRIMASK set */
        }
        irq_enable();
    }
}
