/* selfcal_harness.c: host-side driver of firmware/core/fw_selfcal.c for tests/test_firmware_selfcal.py.
 *
 * Built with fw_selfcal.c into a shared library and called through ctypes: feeds whole sample
 * arrays in one call (a Python loop over ctypes calls would be slower than the calibrator) and
 * copies out what the cross-check compares, including the per-sample gate inputs (filtered
 * gradient, filtered temperature) so that a gate decision that differs can be explained.
 */
#include <stddef.h>
#include <stdint.h>
#include "../core/fw_selfcal.h"

size_t hs_state_size(void) { return sizeof(fw_selfcal_t); }

/* Feed n samples. acc is (n, 3) row-major. grad_out/ftemp_out (per sample, after it) may be NULL.
 * saved_at receives the sample indices that saved a segment; returns how many. */
int hs_run(fw_selfcal_t *c, int n, const uint32_t *t_us, const int32_t *acc, const int32_t *temp,
           const fw_selfcal_scale_t *scale, float *grad_out, float *ftemp_out, int32_t *saved_at)
{
    int i, ns = 0;
    for (i = 0; i < n; i++) {
        if (fw_selfcal_update(c, t_us[i], &acc[3 * i], temp[i], scale))
            saved_at[ns++] = i;
        if (grad_out)
            grad_out[i] = c->grad;
        if (ftemp_out)
            ftemp_out[i] = 25.0f + (((float)c->t_ref - scale->t_lsb_at_25c) + c->ft_off) / scale->t_lsb_per_c;
    }
    return ns;
}

/* Copy the saved segments out: orient/n/t_end (n_seg each), acc (n_seg, 3), temp (n_seg). */
int hs_segments(const fw_selfcal_t *c, int32_t *orient, int32_t *n, uint32_t *t_end, float *acc, float *temp)
{
    int i, k;
    for (i = 0; i < (int)c->n_seg; i++) {
        orient[i] = c->seg[i].orientation;
        n[i] = (int32_t)c->seg[i].n;
        t_end[i] = c->seg[i].t_end_us;
        for (k = 0; k < 3; k++)
            acc[3 * i + k] = c->seg[i].acc_g[k];
        temp[i] = c->seg[i].temp_c;
    }
    return (int)c->n_seg;
}

/* Load segments (for testing fw_selfcal_result alone on the station's own segments). */
void hs_load_segments(fw_selfcal_t *c, int m, const int32_t *orient, const float *acc, const float *temp)
{
    int i, k;
    fw_selfcal_reset(c);
    for (i = 0; i < m && i < (int)FW_SELFCAL_MAX_SEGMENTS; i++) {
        c->seg[i].index = (uint16_t)i;
        c->seg[i].orientation = (uint16_t)orient[i];
        c->seg[i].n = 1000u;
        for (k = 0; k < 3; k++)
            c->seg[i].acc_g[k] = acc[3 * i + k];
        c->seg[i].temp_c = temp[i];
    }
    c->n_seg = (uint16_t)i;
}

uint32_t hs_dropped(const fw_selfcal_t *c) { return c->n_dropped; }
uint32_t hs_n_samples(const fw_selfcal_t *c) { return c->n_samples; }
