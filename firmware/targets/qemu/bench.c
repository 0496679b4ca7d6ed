/* bench.c: instructions per sample of the core on the Cortex-M4 (QEMU netduinoplus2, -icount shift=0).
 *
 * Runs BENCH_N synthetic LIS3DSH samples (100 Hz, a thermal ramp 25 -> 50 -> 25 C with plateaus,
 * 1 g on z, thermal drift and noise in the counts) through fw_sample() four times:
 *   A  not streaming, compensation off, calibrator off (decimation and bookkeeping only)
 *   B  streaming (D frames out), compensation off, calibrator off
 *   C  streaming, compensation on (thermal + SFEM stored via $CALW/$SFEW), calibrator off
 *   D  streaming, compensation on, calibrator on        <- the figure
 * The calibrator is switched by the core's own `$SCAL,<0|1>` command.
 * The D frames go to a real sink: the USART1 data register (byte by byte, TXE polled; QEMU's
 * stm32f2xx_usart transmits synchronously, so TXE is always set and no wait is counted).
 *
 * Clock: with -icount shift=0 QEMU advances its virtual clock by exactly 1 ns per guest instruction.
 * QEMU's STM32F405 TIM2 counts the virtual clock at 1 GHz (PSC 0), so one TIM2 tick = one
 * instruction. This is checked at run time: a loop of a known instruction count (subs/bne, 2 per
 * iteration) is timed at two lengths; the slope must be 1.000 tick/instruction, the intercept is the
 * cost of the two timer reads, subtracted from every sample. SysTick (CLKSOURCE = CPU clock, 168 MHz
 * in QEMU's model) is read as a cross-check (0.168 ticks/instruction).
 * Output via semihosting (SYS_WRITE0), then SYS_EXIT. */
#include <string.h>
#include "stm32f4_regs.h"
#include "fw_board.h"
#include "semihost.h"

#ifndef BENCH_N
#define BENCH_N 20000
#endif
#define ODR_HZ 100u
#define PAPER_US_PER_SAMPLE 267u   /* martinez2022, per sample */

static fw_board_t g_board;
static fw_hal_t g_hal;
static uint8_t g_nvm[FW_NVM_SLOTS][FW_NVM_SLOT_BYTES];
static uint32_t g_uart_bytes;

static void uart_sink(void *ctx, const uint8_t *buf, uint32_t len)
{
    uint32_t i;
    (void)ctx;
    for (i = 0; i < len; i++) {
        while ((USART_SR(USART1_BASE) & USART_SR_TXE) == 0u) {
        }
        USART_DR(USART1_BASE) = buf[i];
    }
    g_uart_bytes += len;
}

static int nvm_read(void *ctx, uint32_t slot, uint8_t *buf, uint32_t len)
{
    (void)ctx;
    if (slot >= FW_NVM_SLOTS || len > FW_NVM_SLOT_BYTES) {
        return -1;
    }
    memcpy(buf, g_nvm[slot], len);
    return 0;
}

static int nvm_write(void *ctx, uint32_t slot, const uint8_t *buf, uint32_t len)
{
    (void)ctx;
    if (slot >= FW_NVM_SLOTS || len > FW_NVM_SLOT_BYTES) {
        return -1;
    }
    memset(g_nvm[slot], 0xFF, sizeof g_nvm[slot]);
    memcpy(g_nvm[slot], buf, len);
    return 0;
}

/* ---- text output ---- */
static char g_line[400];
static uint32_t g_pos;

static void out_s(const char *s)
{
    while (*s && g_pos + 1u < sizeof g_line) {
        g_line[g_pos++] = *s++;
    }
    g_line[g_pos] = '\0';
}

static void out_u(uint32_t v)
{
    char t[11];
    int n = 0;
    do {
        t[n++] = (char)('0' + v % 10u);
        v /= 10u;
    } while (v);
    while (n && g_pos + 1u < sizeof g_line) {
        g_line[g_pos++] = t[--n];
    }
    g_line[g_pos] = '\0';
}

/* v / div with 'dec' decimals, rounded */
static void out_fix(uint32_t v, uint32_t div, unsigned dec)
{
    uint32_t scale = 1u, q, r;
    unsigned i;
    for (i = 0; i < dec; i++) {
        scale *= 10u;
    }
    q = (uint32_t)(((uint64_t)v * scale + div / 2u) / div);
    out_u(q / scale);
    if (dec) {
        char t[12];
        out_s(".");
        r = q % scale;
        for (i = 0; i < dec; i++) {
            t[dec - 1u - i] = (char)('0' + r % 10u);
            r /= 10u;
        }
        t[dec] = '\0';
        out_s(t);
    }
}

static void out_end(void)
{
    out_s("\n");
    sh_puts(g_line);
    g_pos = 0;
    g_line[0] = '\0';
}

static void cmd(const char *body)
{
    uint8_t out[200];
    uint32_t n = fw_frame((const uint8_t *)body, (uint32_t)strlen(body), out, sizeof out);
    fw_uart_rx(&g_board, out, n);
}

/* ---- clocks ---- */
static inline uint32_t tim2(void)
{
    return TIM_CNT(TIM2_BASE);
}

__attribute__((noinline)) static void spin(uint32_t iterations)
{
    /* exactly 2 instructions per iteration */
    __asm volatile(
        "1: subs %0, %0, #1\n\t"
        "bne 1b\n\t"
        : "+r"(iterations)
        :
        : "cc");
}

static uint32_t time_spin(uint32_t k, uint32_t *systick)
{
    uint32_t t0, t1, s0, s1;
    s0 = SYST_CVR;
    t0 = tim2();
    spin(k);
    t1 = tim2();
    s1 = SYST_CVR;
    *systick = (s0 - s1) & 0xFFFFFFu;   /* counts down; k chosen so it does not wrap twice */
    return t1 - t0;
}

/* ---- synthetic sensor ---- */
static uint32_t g_rng = 12345u;

static int32_t noise(int32_t amp)
{
    g_rng = g_rng * 1664525u + 1013904223u;
    return (int32_t)((g_rng >> 16) % (uint32_t)(2 * amp + 1)) - amp;
}

/* temperature in C (x100) of sample i: plateau 25, ramp to 45, plateau 45, ramp to 25 */
static int32_t temp_c100(uint32_t i)
{
    uint32_t q = BENCH_N / 4u, ph = i / q, k = i % q;
    switch (ph) {
    case 0u: return 2500;
    case 1u: return 2500 + (int32_t)(2500u * k / q);
    case 2u: return 5000;
    default: return 5000 - (int32_t)(2500u * k / q);
    }
}

static void make_sample(uint32_t i, fw_raw_sample_t *s)
{
    int32_t tc100 = temp_c100(i), dt100 = tc100 - 2500;
    s->t_us = i * (1000000u / ODR_HZ);
    /* 1 g on z = 16667 counts at 60 ug/LSB; drift ~0.1 mg/C = 1.67 counts/C on every axis */
    s->acc[0] = 35 + dt100 * 167 / 10000 + noise(15);
    s->acc[1] = -48 + dt100 * 167 / 10000 + noise(15);
    s->acc[2] = 16667 + dt100 * 250 / 10000 + noise(15);
    s->temp = (tc100 + 50) / 100 - 25;   /* OUT_T: 1 LSB/C, 0 = 25 C */
}

typedef struct run {
    uint64_t ticks;
    uint32_t min, max;
    uint32_t bytes;
} run_t;

static uint32_t g_overhead;

static void run_once(run_t *r)
{
    fw_raw_sample_t s;
    uint32_t i, t0, t1, d;
    r->ticks = 0;
    r->min = 0xFFFFFFFFu;
    r->max = 0;
    g_uart_bytes = 0;
    g_rng = 12345u;
    fw_selfcal_reset(&g_board.selfcal);
    for (i = 0; i < BENCH_N; i++) {
        make_sample(i, &s);
        t0 = tim2();
        fw_sample(&g_board, &s);
        t1 = tim2();
        d = t1 - t0 - g_overhead;
        r->ticks += d;
        if (d < r->min) {
            r->min = d;
        }
        if (d > r->max) {
            r->max = d;
        }
    }
    r->bytes = g_uart_bytes;
}

static uint32_t per_sample(const run_t *r)
{
    return (uint32_t)((r->ticks + BENCH_N / 2u) / BENCH_N);
}

int main(void)
{
    fw_identity_t id;
    run_t a, b, c, d;
    uint32_t k1 = 100000u, k2 = 300000u, c1, c2, st1, st2, slope_milli, t0, t1, ipS;

    /* TIM2: 32-bit up-counter at the timer input clock (1 GHz virtual in QEMU), PSC 0 */
    TIM_PSC(TIM2_BASE) = 0u;
    TIM_ARR(TIM2_BASE) = 0xFFFFFFFFu;
    TIM_EGR(TIM2_BASE) = 1u;
    TIM_CR1(TIM2_BASE) = 1u;
    SYST_RVR = 0xFFFFFFu;
    SYST_CVR = 0u;
    SYST_CSR = 5u;   /* enable, CPU clock, no interrupt */
    USART_CR1(USART1_BASE) = USART_CR1_UE | USART_CR1_TE;

    /* calibration: the slope of ticks vs instructions, and the cost of the timer reads */
    c1 = time_spin(k1, &st1);
    c2 = time_spin(k2, &st2);
    slope_milli = (uint32_t)(((uint64_t)(c2 - c1) * 1000u + (k2 - k1)) / (2u * (k2 - k1)));
    t0 = tim2();
    t1 = tim2();
    g_overhead = t1 - t0;

    memset(&id, 0, sizeof id);
    strcpy(id.serial, "BENCH-0001");
    strcpy(id.sensor, "LIS3DSH");
    strcpy(id.fw, "fw-c-bench");
    id.ug_per_lsb = 60.0f;
    id.t_lsb_per_c = 1.0f;
    id.t_lsb_at_25c = 0.0f;
    id.odr_hz = (float)ODR_HZ;
    memset(g_nvm, 0xFF, sizeof g_nvm);
    g_hal.ctx = 0;
    g_hal.uart_write = uart_sink;
    g_hal.can_send = 0;
    g_hal.nvm_read = nvm_read;
    g_hal.nvm_write = nvm_write;
    fw_board_init(&g_board, &g_hal, &id, 0u);
    cmd("CALW,0.1,-0.12,0.15,120,-80,60");
    cmd("SFEW,1.002,0.001,-0.002,0.0005,0.998,0.001,0.002,-0.001,1.001,0.003,-0.002,0.001");

    cmd("SCAL,0");
    cmd("COMP,0");
    cmd("STOP");
    run_once(&a);
    cmd("START");
    run_once(&b);
    cmd("COMP,1");
    run_once(&c);
    cmd("SCAL,1");
    run_once(&d);
    cmd("STOP");

    out_s("bench: N=");
    out_u(BENCH_N);
    out_s(" LIS3DSH samples at 100 Hz, thermal ramp 25->50->25 C; streaming on, compensation on "
          "(thermal+SFEM), streaming calibrator on; UART sink = USART1 DR");
    out_end();
    out_s("bench: clock = TIM2 under -icount shift=0: spin-loop calibration ");
    out_fix(slope_milli, 1000u, 3);
    out_s(" ticks/instruction (");
    out_u(2u * k1);
    out_s(" insns -> ");
    out_u(c1);
    out_s(", ");
    out_u(2u * k2);
    out_s(" -> ");
    out_u(c2);
    out_s("), read overhead ");
    out_u(g_overhead);
    out_s(" subtracted; SysTick cross-check ");
    out_fix(st2 - st1, 2u * (k2 - k1) / 1000u, 3);
    out_s(" ticks per 1000 insns (168 MHz => 168)");
    out_end();

    ipS = per_sample(&d);
    out_s("bench: instructions per sample: ");
    out_u(ipS);
    out_s(" (min ");
    out_u(d.min);
    out_s(", max ");
    out_u(d.max);
    out_s("; ");
    out_u(d.bytes / BENCH_N);
    out_s(" UART bytes per sample; calibrator saved ");
    out_u(g_board.selfcal.n_seg);
    out_s(" segments)");
    out_end();

    out_s("bench: us per sample at 168 MHz, CPI 1: ");
    out_fix(ipS, 168u, 2);
    out_s(" us (lower bound; flash wait states, VDIV/VSQRT 14 cycles, loads: plausibly ");
    out_fix(ipS * 13u, 1680u, 1);
    out_s("-");
    out_fix(ipS * 2u, 168u, 1);
    out_s(" us at CPI 1.3-2) vs martinez2022 ");
    out_u(PAPER_US_PER_SAMPLE);
    out_s(" us per sample");
    out_end();

    out_s("bench: split (instructions per sample): base ");
    out_u(per_sample(&a));
    out_s(", framing+UART ");
    out_u(per_sample(&b) - per_sample(&a));
    out_s(", compensation ");
    out_u(per_sample(&c) > per_sample(&b) ? per_sample(&c) - per_sample(&b) : 0u);
    out_s(", calibrator ");
    out_u(per_sample(&d) > per_sample(&c) ? per_sample(&d) - per_sample(&c) : 0u);
    out_s(", total ");
    out_u(ipS);
    out_end();
    out_s("bench: worst sample (instructions): A ");
    out_u(a.max);
    out_s(", B ");
    out_u(b.max);
    out_s(", C ");
    out_u(c.max);
    out_s(", D ");
    out_u(d.max);
    out_s(" (D's worst is a segment save of the calibrator)");
    out_end();
    sh_exit(slope_milli > 990u && slope_milli < 1010u);
}
