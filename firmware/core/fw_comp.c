/* fw_comp.c: on-board compensation (float32 only: the Cortex-M4F FPU is single precision).
 *
 * martinez2022 eq. 13 per axis with the board's own temperature, dT = temp_c - 25 C:
 *     acc_c = (acc - tdb * dT) / (1 + tdsf * dT)
 * then the SFEM if stored, acc_out = A (acc_c - b), then back to counts rounded to nearest (ties to
 * even, numpy rint) and saturated to int32. Same result as drivers/sim/board_nvm.CalFirmware.
 * compensate_counts up to float32 rounding: the arithmetic is done in counts (tdb and b divided by
 * the count size once) so the raw count never goes through a g round trip.
 */
#include "fw_board.h"

static int32_t round_sat(float x)
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
