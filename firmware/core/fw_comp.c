/* fw_comp.c: on-board compensation (float32 only: the Cortex-M4F FPU is single precision).
 *
 * martinez2022 eq. 13 per axis with the board's own temperature, dT = temp_c - 25 C:
 *     acc_c = (acc - tdb * dT) / (1 + tdsf * dT)
 * then the SFEM if stored, acc_out = A (acc_c - b), then back to counts rounded to nearest (ties to
 * even, numpy rint) and saturated to int32. Same result as drivers/sim/board_nvm.CalFirmware.
 * compensate_counts up to float32 rounding: the arithmetic is done in counts (tdb and b divided by
 * the count size once) so the raw count never goes through a g round trip.
 *
 * A version-2 record replaces all of that with its cubic SFEM (docs/design.md 3.1,
 * sensors2023 eq. 8): T clamped to [t_lo_c, t_hi_c], d = T - t_ref_c, the 12 polynomials of A(d)
 * and b(d) by Horner in float32 (3 multiply-adds each, c[3] first), out = A (raw - b counts_per_g)
 * in counts. Eq. 13 is not applied on top: the cubic model was fitted on raw readings and carries
 * the thermal drift itself. No division per sample (counts_per_g is the board's, computed once).
 */
#include "fw_board.h"

/* Inlined into both users: at -Os GCC would otherwise call it three times per sample. */
#if defined(__GNUC__)
#define COMP_INLINE static inline __attribute__((always_inline))
#else
#define COMP_INLINE static inline
#endif

COMP_INLINE int32_t round_sat(float x)
{
    if (!(x == x)) return 0;                                 /* NaN */
    if (x >= 2147483648.0f) return INT32_MAX;
    if (x < -2147483648.0f) return INT32_MIN;
    if (x < 8388608.0f && x > -8388608.0f) {                 /* below 2^23: round half to even */
        float r = x >= 0.0f ? (x + 8388608.0f) - 8388608.0f : (x - 8388608.0f) + 8388608.0f;
        return (int32_t)r;
    }
    return (int32_t)x;                                       /* already an integer */
}

float fw_temp_c(const fw_identity_t *id, int32_t temp_count)
{
    return 25.0f + ((float)temp_count - id->t_lsb_at_25c) / id->t_lsb_per_c;
}

void fw_compensate(const fw_cal_t *cal, float ug_per_lsb, const int32_t raw[3], float temp_c, int32_t out[3])
{
    const float lsb_g = ug_per_lsb * 1e-6f;
    const float dt = temp_c - 25.0f;
    float v[3];
    for (int i = 0; i < 3; i++) {
        float tdb_counts = cal->thermal[i] * 1e-3f / lsb_g;
        float tdsf = cal->thermal[3 + i] * 1e-6f;
        v[i] = ((float)raw[i] - tdb_counts * dt) / (1.0f + tdsf * dt);
    }
    if (cal->has_sfem) {
        float w[3];
        for (int i = 0; i < 3; i++) w[i] = v[i] - cal->sfem[9 + i] / lsb_g;
        for (int i = 0; i < 3; i++)
            v[i] = cal->sfem[3 * i] * w[0] + cal->sfem[3 * i + 1] * w[1] + cal->sfem[3 * i + 2] * w[2];
    }
    for (int i = 0; i < 3; i++) out[i] = round_sat(v[i]);
}

void fw_compensate_cubic_f32(const fw_cubic_t *cu, float counts_per_g, const int32_t raw[3], float temp_c, float out[3])
{
    float t = temp_c;
    if (!(t >= cu->t_lo_c)) t = cu->t_lo_c;                 /* NaN too: the low end */
    if (t > cu->t_hi_c) t = cu->t_hi_c;
    const float d = t - cu->t_ref_c;
    float m[12];
    for (int j = 0; j < 12; j++)
        m[j] = ((cu->c[3][j] * d + cu->c[2][j]) * d + cu->c[1][j]) * d + cu->c[0][j];
    float w[3];
    for (int i = 0; i < 3; i++) w[i] = (float)raw[i] - m[9 + i] * counts_per_g;
    for (int i = 0; i < 3; i++) out[i] = m[3 * i] * w[0] + m[3 * i + 1] * w[1] + m[3 * i + 2] * w[2];
}

void fw_compensate_cubic(const fw_cubic_t *cu, float counts_per_g, const int32_t raw[3], float temp_c, int32_t out[3])
{
    float v[3];
    fw_compensate_cubic_f32(cu, counts_per_g, raw, temp_c, v);
    for (int i = 0; i < 3; i++) out[i] = round_sat(v[i]);
}
