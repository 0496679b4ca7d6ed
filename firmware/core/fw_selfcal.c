/* fw_selfcal.c: martinez2022 section 3.3 streaming thermal calibrator for the Cortex-M4F.
 *
 * A port of the scalar path StreamingCalibrator.update() (station/science/streaming.py) and of
 * result_from_segments() (station/science/drift_coefficients.py), with the defaults of
 * streaming_config.StreamingConfig and the station's choices: raw-mean segments, gate also while
 * averaging, signed gradient reset, gradient starting at the reset value, orientation detection
 * while logging, a non-increasing sample time contributes a zero gradient.
 *
 * Arithmetic (why it differs in form, not in algorithm, from the station's float64 code):
 * - Per sample everything is float32 (the M4F FPU is single precision; double is emulated).
 * - Segment sums are exact int64 sums of the raw counts, converted to a mean once per segment:
 *   a float32 running sum of 1000 samples near 1 g (steps of 6e-5 at 1000) would carry ~1e-6 g
 *   of rounding, over ten times the float32 step of the mean itself.
 * - The filtered temperature is kept in counts as an offset from an integer reference count,
 *   re-centred every sample (an exact operation). Near 60 C a float32 temperature has a 3.8e-6 C
 *   step, and the gradient is the difference of two consecutive filtered values times 187.5
 *   (60 / 0.32 s): the offset keeps the step at ~6e-8 count instead. Measured against the
 *   station (tests/test_firmware_selfcal.py): filtered gradient within 8e-6 C/min, against
 *   7e-5 C/min with the temperature filtered in C, which made 19 of 400 simulated runs take a
 *   gate decision near 1 C/min differently (4 ended a segment 1-21 samples apart); 0 with this.
 * - alpha is applied as a = 1 - (1 - alpha) so that a + (1 - a) == 1 exactly in float32 and the
 *   filters have unit DC gain (with 0.05f and 0.95f it would be 1 - 2.2e-7).
 * - Time is uint32 us; differences wrap correctly, and a difference of 0 or >= 2^31 us (a
 *   duplicated or backwards time stamp) is the station's "non-increasing time".
 * Overflow: a segment completed while seg[] is full is not saved but still becomes the change
 * reference (the state machine goes on exactly as the station's), is counted in n_dropped and
 * flagged by fw_selfcal_result, which uses the first FW_SELFCAL_MAX_SEGMENTS segments.
 */
#include <math.h>
#include <string.h>
#include "fw_selfcal.h"

/* StreamingConfig defaults */
#define ALPHA_ACC         0.05f   /* exponential filter on the 3 axes and the temperature */
#define ALPHA_GRAD        0.01f   /* exponential filter on the thermal gradient */
#define GRAD_LIMIT        1.0f    /* C/min: logging only while |gradient| < this */
#define DISCARD_SAMPLES   500u
#define AVERAGE_SAMPLES   1000u
#define SEGMENT_DELTA_C   20.0f   /* filtered temperature this far from the last segment: new segment */
#define ORIENT_DELTA_G    0.8f    /* every axis this far from the last segment: new orientation */
#define GRAD_RESET        10.0f   /* C/min, signed by the change's direction; also the start value */
#define T_REF_C           25.0f   /* eq. 1 reference temperature */
#define PAIR_DELTA_C      (SEGMENT_DELTA_C / 2.0f)  /* min_pair_delta_c None: segment_delta / 2 */

#define C_ACC   (1.0f - ALPHA_ACC)
#define A_ACC   (1.0f - C_ACC)
#define C_GRAD  (1.0f - ALPHA_GRAD)
#define A_GRAD  (1.0f - C_GRAD)

void fw_selfcal_reset(fw_selfcal_t *c)
{
    memset(c, 0, sizeof *c);
    c->grad = GRAD_RESET;  /* power-up: the self-heating transient is not logged */
}

/* Mean of an exact integer sum as float32, rounded once more at most: the quotient is exact
 * (|q| < 2^24 for any sensor count) and the remainder's fraction is added to it. */
static float mean_of(int64_t sum, uint32_t n)
{
    int64_t q = sum / (int64_t)n;
    int64_t r = sum - q * (int64_t)n;
    return (float)q + (float)r / (float)n;
}

/* The filtered temperature in C (only for the 20 C segment-change test, so one rounding is fine). */
static float ftemp_c(const fw_selfcal_t *c, const fw_selfcal_scale_t *s)
{
    return T_REF_C + (((float)c->t_ref - s->t_lsb_at_25c) + c->ft_off) / s->t_lsb_per_c;
}

/* Segment or orientation change: reset the gradient high, signed, and start settling. */
static void change(fw_selfcal_t *c, int orientation, int negative)
{
    if (orientation) {
        c->orientation++;
        c->armed = 0;
    }
    c->waiting = 0;
    c->grad = negative ? -GRAD_RESET : GRAD_RESET;
    c->n_disc = 0;
    c->n_avg = 0;
}

/* The averaged segment is complete: its raw means become the change references, and it is saved
 * if there is room. Returns 1 if saved. */
static int emit(fw_selfcal_t *c, uint32_t t_us, const fw_selfcal_scale_t *s)
{
    uint32_t n = c->n_avg;
    float acc[3];
    float temp;
    unsigned k;
    for (k = 0; k < 3u; k++)
        acc[k] = mean_of(c->sum_acc[k], n) * s->g_per_count;
    /* relative to the first averaged count, so the mean keeps its fraction at 12-bit counts */
    temp = T_REF_C + (((float)c->k_temp - s->t_lsb_at_25c) + mean_of(c->sum_temp, n)) / s->t_lsb_per_c;
    for (k = 0; k < 3u; k++)
        c->last_acc[k] = acc[k];
    c->last_temp = temp;
    c->armed = 1;
    c->waiting = 1;
    c->n_disc = 0;
    c->n_avg = 0;
    if (c->n_seg >= FW_SELFCAL_MAX_SEGMENTS) {
        if (c->n_dropped < UINT16_MAX)
            c->n_dropped++;
        return 0;
    }
    {
        fw_segment_t *g = &c->seg[c->n_seg];
        g->index = c->n_seg;
        g->orientation = c->orientation;
        g->t_end_us = t_us;
        for (k = 0; k < 3u; k++)
            g->acc_g[k] = acc[k];
        g->temp_c = temp;
        g->n = n;
    }
    c->n_seg++;
    return 1;
}

int fw_selfcal_update(fw_selfcal_t *c, uint32_t t_us, const int32_t acc_counts[3], int32_t temp_count,
                      const fw_selfcal_scale_t *scale)
{
    float x[3];
    unsigned k;
    for (k = 0; k < 3u; k++)
        x[k] = (float)acc_counts[k] * scale->g_per_count;
    c->n_samples++;
    if (!c->init) {
        c->init = 1;
        for (k = 0; k < 3u; k++)
            c->facc[k] = C_ACC * x[k] + A_ACC * x[k];  /* as the station: the filter starts on x0 */
        c->t_ref = temp_count;
        c->ft_off = 0.0f;
        c->t_prev_us = t_us;
    } else {
        uint32_t du = t_us - c->t_prev_us;
        float ft, g = 0.0f;
        for (k = 0; k < 3u; k++)
            c->facc[k] = c->facc[k] * C_ACC + A_ACC * x[k];
        ft = c->ft_off * C_ACC + A_ACC * (float)((int64_t)temp_count - (int64_t)c->t_ref);
        if (du != 0u && du < 0x80000000u)  /* time increased (modulo 2^32) */
            g = (ft - c->ft_off) * (60.0e6f / ((float)du * scale->t_lsb_per_c));
        c->grad = c->grad * C_GRAD + A_GRAD * g;
        {
            /* re-centre on the nearest integer r (a VCVT, no libm call): ft - r is exact for an
             * integer within 1 of ft (|ft| < 2^23), so this loses nothing */
            int32_t r = (int32_t)(ft + (ft < 0.0f ? -0.5f : 0.5f));
            c->ft_off = ft - (float)r;
            c->t_ref += r;
        }
        c->t_prev_us = t_us;
    }
    if (c->armed  /* waiting or not: orientation also detected while logging */
        && fabsf(c->facc[0] - c->last_acc[0]) > ORIENT_DELTA_G
        && fabsf(c->facc[1] - c->last_acc[1]) > ORIENT_DELTA_G
        && fabsf(c->facc[2] - c->last_acc[2]) > ORIENT_DELTA_G) {
        change(c, 1, c->grad < 0.0f);
        return 0;
    }
    if (c->waiting) {
        float ftc = ftemp_c(c, scale);
        if (fabsf(ftc - c->last_temp) > SEGMENT_DELTA_C)
            change(c, 0, ftc < c->last_temp);
        return 0;
    }
    if (!(fabsf(c->grad) < GRAD_LIMIT)) {  /* gate closed (or NaN): discard and average restart */
        c->n_disc = 0;
        c->n_avg = 0;
        return 0;
    }
    if (c->n_disc < DISCARD_SAMPLES) {
        c->n_disc++;
        return 0;
    }
    if (c->n_avg == 0u) {
        for (k = 0; k < 3u; k++)
            c->sum_acc[k] = 0;
        c->sum_temp = 0;
        c->k_temp = temp_count;
    }
    for (k = 0; k < 3u; k++)
        c->sum_acc[k] += acc_counts[k];
    c->sum_temp += temp_count - c->k_temp;
    c->n_avg++;
    if (c->n_avg >= AVERAGE_SAMPLES)
        return emit(c, t_us, scale);
    return 0;
}

/* ------------------------------------------------------------------ end of test */

#define MAX_ORIENT (FW_SELFCAL_MAX_SEGMENTS / 2u)  /* a usable orientation holds >= 2 segments */

int fw_selfcal_result(const fw_selfcal_t *c, fw_selfcal_result_t *out)
{
    /* TD_i (g/C) and Acc0_i (g) per usable orientation: 2 * 16 * 12 = 384 bytes of stack */
    float td[MAX_ORIENT][3], acc0[MAX_ORIENT][3];
    unsigned m = 0, i, k;
    memset(out, 0, sizeof *out);
    out->n_segments = c->n_seg;
    if (c->n_dropped)
        out->flags |= FW_SELFCAL_FLAG_OVERFLOW;
    /* Orientations only count up, so one orientation's segments are consecutive in seg[] and the
     * station's grouping by orientation is one pass over adjacent pairs. */
    i = 0;
    while (i < c->n_seg) {
        unsigned j = i, npair = 0;
        float std[3] = {0.0f, 0.0f, 0.0f}, sa0[3] = {0.0f, 0.0f, 0.0f};
        while (j + 1u < c->n_seg && c->seg[j + 1u].orientation == c->seg[i].orientation) {
            const fw_segment_t *s1 = &c->seg[j], *s2 = &c->seg[j + 1u];
            float dt = s2->temp_c - s1->temp_c;
            j++;
            if (fabsf(dt) < PAIR_DELTA_C)
                continue;
            for (k = 0; k < 3u; k++) {
                float d = (s2->acc_g[k] - s1->acc_g[k]) / dt;  /* eq. 3; the difference is exact */
                /* eq. 4 from the pair's mean point */
                std[k] += d;
                sa0[k] += (s1->acc_g[k] + s2->acc_g[k]) / 2.0f - d * ((s1->temp_c + s2->temp_c) / 2.0f - T_REF_C);
            }
            npair++;
        }
        if (npair > 0u && m < MAX_ORIENT) {
            for (k = 0; k < 3u; k++) {
                td[m][k] = std[k] / (float)npair;
                acc0[m][k] = sa0[k] / (float)npair;
            }
            m++;
        }
        i = j + 1u;
    }
    if (m < 2u) {
        out->flags |= FW_SELFCAL_FLAG_NO_PAIR;
        return -1;
    }
    for (k = 0; k < 3u; k++) {
        float lo = acc0[0][k], hi = acc0[0][k];
        for (i = 1; i < m; i++) {
            lo = acc0[i][k] < lo ? acc0[i][k] : lo;
            hi = acc0[i][k] > hi ? acc0[i][k] : hi;
        }
        if (hi - lo < ORIENT_DELTA_G / 2.0f) {
            out->flags |= FW_SELFCAL_FLAG_NO_SPREAD;
            return -1;
        }
    }
    for (k = 0; k < 3u; k++) {
        float tdsf, tdb;
        if (m == 2u) {
            tdsf = (td[0][k] - td[1][k]) / (acc0[0][k] - acc0[1][k]);  /* eq. 8 */
            tdb = td[0][k] - tdsf * acc0[0][k];                        /* eq. 9 */
        } else {
            /* the straight line TD = TDB + TDSF Acc0 by least squares, centred (same solution as
             * the station's normal equations, without their float32 cancellation) */
            float xm = 0.0f, ym = 0.0f, sxx = 0.0f, sxy = 0.0f;
            for (i = 0; i < m; i++) {
                xm += acc0[i][k];
                ym += td[i][k];
            }
            xm /= (float)m;
            ym /= (float)m;
            for (i = 0; i < m; i++) {
                float dx = acc0[i][k] - xm;
                sxx += dx * dx;
                sxy += dx * (td[i][k] - ym);
            }
            tdsf = sxy / sxx;
            tdb = ym - tdsf * xm;
        }
        out->tdb_mg_per_c[k] = tdb * 1e3f;  /* with the unclamped TDSF, as the paper */
        out->tdsf_ppm_per_c[k] = tdsf * 1e6f;
        if (out->tdsf_ppm_per_c[k] > 0.0f) {
            out->tdsf_ppm_per_c[k] = 0.0f;
            out->flags |= (uint16_t)(FW_SELFCAL_FLAG_CLAMPED_X << k);
        }
    }
    return 0;
}
