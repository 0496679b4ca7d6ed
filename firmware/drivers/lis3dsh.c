/* lis3dsh.c: ST LIS3DSH driver (see lis3dsh.h). */
#include "lis3dsh.h"

int32_t lis3dsh_read_reg(const lis3dsh_ctx_t *ctx, uint8_t reg, uint8_t *buf, uint16_t len)
{
    if (ctx == 0 || ctx->read == 0 || buf == 0 || len == 0u) {
        return LIS3DSH_ERR_ARG;
    }
    return ctx->read(ctx->handle, reg, buf, len) == 0 ? 0 : LIS3DSH_ERR_BUS;
}

int32_t lis3dsh_write_reg(const lis3dsh_ctx_t *ctx, uint8_t reg, uint8_t value)
{
    if (ctx == 0 || ctx->write == 0) {
        return LIS3DSH_ERR_ARG;
    }
    return ctx->write(ctx->handle, reg, &value, 1u) == 0 ? 0 : LIS3DSH_ERR_BUS;
}

int32_t lis3dsh_who_am_i(const lis3dsh_ctx_t *ctx, uint8_t *id)
{
    return lis3dsh_read_reg(ctx, LIS3DSH_WHO_AM_I, id, 1u);
}

int32_t lis3dsh_init(const lis3dsh_ctx_t *ctx, lis3dsh_odr_t odr, lis3dsh_fs_t fs)
{
    uint8_t id = 0;
    int32_t rc;

    if ((int)odr < (int)LIS3DSH_ODR_3HZ125 || (int)odr > (int)LIS3DSH_ODR_1600HZ || (int)fs > (int)LIS3DSH_FS_16G) {
        return LIS3DSH_ERR_ARG;
    }
    rc = lis3dsh_who_am_i(ctx, &id);
    if (rc != 0) {
        return rc;
    }
    if (id != LIS3DSH_ID) {
        return LIS3DSH_ERR_ID;
    }
    /* Register auto-increment first: every later multi-byte read relies on it. */
    rc = lis3dsh_write_reg(ctx, LIS3DSH_CTRL_REG6, LIS3DSH_CTRL6_ADD_INC);
    if (rc == 0) {
        /* anti-aliasing BW 800 Hz (00), full scale, no self-test, 4-wire SPI */
        rc = lis3dsh_write_reg(ctx, LIS3DSH_CTRL_REG5, (uint8_t)((unsigned)fs << 3));
    }
    if (rc == 0) {
        rc = lis3dsh_write_reg(ctx, LIS3DSH_CTRL_REG4,
                               (uint8_t)(((unsigned)odr << 4) | LIS3DSH_CTRL4_BDU | LIS3DSH_CTRL4_XYZEN));
    }
    if (rc == 0) {
        rc = lis3dsh_write_reg(ctx, LIS3DSH_CTRL_REG3,
                               (uint8_t)(LIS3DSH_CTRL3_DR_EN | LIS3DSH_CTRL3_IEA | LIS3DSH_CTRL3_INT1_EN));
    }
    return rc;
}

int32_t lis3dsh_data_ready(const lis3dsh_ctx_t *ctx)
{
    uint8_t st = 0;
    int32_t rc = lis3dsh_read_reg(ctx, LIS3DSH_STATUS, &st, 1u);
    if (rc != 0) {
        return rc;
    }
    return (st & LIS3DSH_STATUS_ZYXDA) ? 1 : 0;
}

int32_t lis3dsh_read_sample(const lis3dsh_ctx_t *ctx, fw_raw_sample_t *out)
{
    uint8_t raw[6];
    uint8_t t = 0;
    int32_t rc;
    unsigned i;

    if (out == 0) {
        return LIS3DSH_ERR_ARG;
    }
    rc = lis3dsh_read_reg(ctx, LIS3DSH_OUT_X_L, raw, 6u);
    if (rc == 0) {
        rc = lis3dsh_read_reg(ctx, LIS3DSH_OUT_T, &t, 1u);
    }
    if (rc != 0) {
        return rc;
    }
    for (i = 0; i < 3u; i++) {
        out->acc[i] = (int32_t)(int16_t)(uint16_t)((uint16_t)raw[2u * i] | ((uint16_t)raw[2u * i + 1u] << 8));
    }
    out->temp = (int32_t)(int8_t)t;
    return 0;
}

int32_t lis3dsh_fifo_stream(const lis3dsh_ctx_t *ctx, uint8_t wtm)
{
    int32_t rc;

    if (wtm == 0u || wtm >= LIS3DSH_FIFO_DEPTH) {
        return LIS3DSH_ERR_ARG;
    }
    /* bypass first: a mode change from stream straight to stream does not empty the FIFO */
    rc = lis3dsh_write_reg(ctx, LIS3DSH_FIFO_CTRL, 0u);
    if (rc == 0) {
        rc = lis3dsh_write_reg(ctx, LIS3DSH_CTRL_REG6, (uint8_t)(LIS3DSH_CTRL6_ADD_INC | LIS3DSH_CTRL6_FIFO_EN
                                                                | LIS3DSH_CTRL6_WTM_EN | LIS3DSH_CTRL6_P1_WTM));
    }
    if (rc == 0) {
        rc = lis3dsh_write_reg(ctx, LIS3DSH_FIFO_CTRL, (uint8_t)(LIS3DSH_FIFO_MODE_STREAM | wtm));
    }
    if (rc == 0) {
        /* INT1 on, active high, data-ready NOT routed (the watermark is) */
        rc = lis3dsh_write_reg(ctx, LIS3DSH_CTRL_REG3, (uint8_t)(LIS3DSH_CTRL3_IEA | LIS3DSH_CTRL3_INT1_EN));
    }
    return rc;
}

int32_t lis3dsh_fifo_status(const lis3dsh_ctx_t *ctx, uint32_t *count, uint8_t *src)
{
    uint8_t v = 0;
    int32_t rc = lis3dsh_read_reg(ctx, LIS3DSH_FIFO_SRC, &v, 1u);
    if (rc != 0) {
        return rc;
    }
    if (src != 0) {
        *src = v;
    }
    if (count != 0) {
        uint32_t fss = (uint32_t)v & 0x1Fu;
        /* FSS has 5 bits: 32 stored reads as 0 with EMPTY clear */
        *count = (v & LIS3DSH_FIFO_SRC_EMPTY) ? 0u : (fss == 0u ? LIS3DSH_FIFO_DEPTH : fss);
    }
    return 0;
}

int32_t lis3dsh_fifo_read(const lis3dsh_ctx_t *ctx, fw_raw_sample_t *out, uint32_t n)
{
    uint8_t raw[6];
    uint8_t t = 0;
    int32_t rc;
    uint32_t k;
    unsigned i;

    if (out == 0 || n > LIS3DSH_FIFO_DEPTH) {
        return LIS3DSH_ERR_ARG;
    }
    rc = n > 0u ? lis3dsh_read_reg(ctx, LIS3DSH_OUT_T, &t, 1u) : 0;
    for (k = 0; k < n && rc == 0; k++) {
        rc = lis3dsh_read_reg(ctx, LIS3DSH_OUT_X_L, raw, 6u);
        if (rc == 0) {
            for (i = 0; i < 3u; i++) {
                out[k].acc[i] = (int32_t)(int16_t)(uint16_t)((uint16_t)raw[2u * i] | ((uint16_t)raw[2u * i + 1u] << 8));
            }
            out[k].temp = (int32_t)(int8_t)t;
        }
    }
    return rc;
}

uint32_t lis3dsh_fifo_t_us(uint32_t t_wtm_us, uint32_t wtm, uint32_t k, uint32_t period_us)
{
    /* unsigned arithmetic on purpose: the board clock wraps at 2^32 */
    return t_wtm_us + k * period_us - (wtm - 1u) * period_us;
}

float lis3dsh_odr_hz(lis3dsh_odr_t odr)
{
    static const float hz[10] = {0.0f, 3.125f, 6.25f, 12.5f, 25.0f, 50.0f, 100.0f, 400.0f, 800.0f, 1600.0f};
    return ((unsigned)odr < 10u) ? hz[(unsigned)odr] : 0.0f;
}

float lis3dsh_temp_c(int32_t count)
{
    return 25.0f + ((float)count - LIS3DSH_T_LSB_AT_25C) / LIS3DSH_T_LSB_PER_C;
}

float lis3dsh_ug_per_lsb(lis3dsh_fs_t fs)
{
    static const float ug[5] = {60.0f, 120.0f, 180.0f, 240.0f, 730.0f};
    return ((unsigned)fs < 5u) ? ug[(unsigned)fs] : 0.0f;
}
