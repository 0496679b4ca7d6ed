/* fw_selfcal.h: martinez2022 section 3.3 streaming calibrator, on the board (float32, no heap).
 *
 * The same algorithm and constants as the station's station/science/streaming.py (scalar path
 * `update`) and station/science/drift_coefficients.py (`result_from_segments`): exponential filter
 * (alpha 0.05) on 3 axes and temperature, gradient in C/min filtered again (alpha 0.01), gate
 * |gradient| < 1 C/min, 500 discarded then 1000 averaged samples per segment, temperature (20 C)
 * and orientation (0.8 g on every axis) changes, then TD_i/Acc0_i per orientation and TDSF/TDB.
 * The cross-check against the station's calibrator is tests/test_firmware_selfcal.py.
 */
#ifndef FW_SELFCAL_H
#define FW_SELFCAL_H

#include <stdint.h>

#define FW_SELFCAL_MAX_SEGMENTS 32u

/* fw_selfcal_result_t.flags */
#define FW_SELFCAL_FLAG_CLAMPED_X   0x0001u  /* bit k: TDSF of axis k was positive, reported as 0 */
#define FW_SELFCAL_FLAG_NO_PAIR     0x0100u  /* < 2 orientations with a usable pair: no result */
#define FW_SELFCAL_FLAG_NO_SPREAD   0x0200u  /* orientations differ < 0.4 g on some axis: no result */
#define FW_SELFCAL_FLAG_OVERFLOW    0x0400u  /* segments completed after seg[] was full were dropped */

typedef struct fw_segment {
    uint16_t index;          /* 0.. in order of saving */
    uint16_t orientation;    /* 0.. orientation counter */
    uint32_t t_end_us;       /* board time of the last averaged sample */
    float acc_g[3];          /* raw mean of the averaged samples, g */
    float temp_c;            /* raw mean temperature, C */
    uint32_t n;              /* samples averaged */
} fw_segment_t;

typedef struct fw_selfcal_result {
    float tdb_mg_per_c[3];
    float tdsf_ppm_per_c[3];
    uint16_t n_segments;
    uint16_t flags;          /* FW_SELFCAL_FLAG_*: bit 0..2 TDSF clamped; bit 8/9 no result; bit 10 overflow */
} fw_selfcal_result_t;

/* Scaling of the raw counts (from the board's identity). */
typedef struct fw_selfcal_scale {
    float g_per_count;       /* ug_per_lsb * 1e-6 */
    float t_lsb_per_c;
    float t_lsb_at_25c;
} fw_selfcal_scale_t;

typedef struct fw_selfcal {
    /* filters: acceleration in g; temperature in counts as an offset from an integer reference
     * count (t_ref) re-centred every sample, so its float32 resolution stays ~1e-7 count */
    float facc[3];
    float ft_off;            /* filtered temperature - t_ref, counts, |ft_off| <= 0.5 */
    int32_t t_ref;           /* integer reference count of the filtered temperature */
    float grad;              /* filtered gradient, C/min */
    uint32_t t_prev_us;
    /* gate and counters */
    uint16_t n_disc;         /* stable samples discarded so far */
    uint16_t n_avg;          /* samples averaged so far */
    uint8_t init, waiting, armed;
    uint16_t orientation;    /* orientation counter */
    /* exact segment sums of the raw counts (temperature relative to its first averaged count) */
    int64_t sum_acc[3];
    int64_t sum_temp;
    int32_t k_temp;
    /* change references: the last completed segment (kept even when seg[] overflowed) */
    float last_acc[3];
    float last_temp;
    uint32_t n_samples;      /* samples fed since reset */
    uint16_t n_dropped;      /* segments completed while seg[] was full (saturates) */
    fw_segment_t seg[FW_SELFCAL_MAX_SEGMENTS];
    uint16_t n_seg;
} fw_selfcal_t;

void fw_selfcal_reset(fw_selfcal_t *c);
/* One sample: board time in us (uint32 differences wrap correctly), raw counts and their scaling.
 * Returns 1 when this sample saved a segment (then c->seg[c->n_seg - 1] is it), else 0. A segment
 * completed while seg[] is full is not saved (returns 0, counted in n_dropped, flagged in the
 * result); detection goes on as if it had been saved, so the saved ones stay the station's first. */
int fw_selfcal_update(fw_selfcal_t *c, uint32_t t_us, const int32_t acc_counts[3], int32_t temp_count,
                      const fw_selfcal_scale_t *scale);
/* TDB/TDSF from the saved segments (drift_coefficients.result_from_segments). Returns 0 with a
 * result, -1 when no orientation has two segments far enough apart in temperature (the station's
 * InsufficientData: < 2 such orientations, or their Acc0 too close; out->flags says which). */
int fw_selfcal_result(const fw_selfcal_t *c, fw_selfcal_result_t *out);

#endif
