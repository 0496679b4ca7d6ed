/* adxl355.c: Analog Devices ADXL355 driver (see adxl355.h). */
#include "adxl355.h"

int32_t adxl355_read_reg(const adxl355_ctx_t *ctx, uint8_t reg, uint8_t *buf, uint16_t len)
{
    if (ctx == 0 || ctx->read == 0 || buf == 0 || len == 0u) {
        return ADXL355_ERR_ARG;
    }
    return ctx->read(ctx->handle, reg, buf, len) == 0 ? 0 : ADXL355_ERR_BUS;
}

int32_t adxl355_write_reg(const adxl355_ctx_t *ctx, uint8_t reg, uint8_t value)
{
    if (ctx == 0 || ctx->write == 0) {
        return ADXL355_ERR_ARG;
    }
    return ctx->write(ctx->handle, reg, &value, 1u) == 0 ? 0 : ADXL355_ERR_BUS;
}

static int32_t check_id(const adxl355_ctx_t *ctx)
{
    uint8_t id[3] = {0, 0, 0};
    int32_t rc = adxl355_read_reg(ctx, ADXL355_DEVID_AD, id, 3u);
    if (rc != 0) {
        return rc;
    }
    if (id[0] != ADXL355_ID_AD || id[1] != ADXL355_ID_MST || id[2] != ADXL355_ID_PART) {
        return ADXL355_ERR_ID;
    }
    return 0;
}

int32_t adxl355_init(const adxl355_ctx_t *ctx, adxl355_odr_t odr, adxl355_range_t range)
{
    int32_t rc;

    if ((unsigned)odr > (unsigned)ADXL355_ODR_3HZ906 || (int)range < (int)ADXL355_RANGE_2G
        || (int)range > (int)ADXL355_RANGE_8G) {
        return ADXL355_ERR_ARG;
    }
    rc = check_id(ctx);
    if (rc == 0) {
        rc = adxl355_write_reg(ctx, ADXL355_RESET, ADXL355_RESET_CODE);
    }
    if (rc == 0) {
        rc = check_id(ctx);   /* the part answers again after its reset */
    }
    if (rc == 0) {
        rc = adxl355_write_reg(ctx, ADXL355_FILTER, (uint8_t)odr);   /* HPF off */
    }
    if (rc == 0) {
        /* keep I2C_HS (reset value), INT_POL 0, range */
        rc = adxl355_write_reg(ctx, ADXL355_RANGE, (uint8_t)(ADXL355_RANGE_I2C_HS | (unsigned)range));
    }
    if (rc == 0) {
        rc = adxl355_write_reg(ctx, ADXL355_POWER_CTL, 0u);   /* measure, temperature on, DRDY on */
    }
    return rc;
}

int32_t adxl355_data_ready(const adxl355_ctx_t *ctx)
{
    uint8_t st = 0;
    int32_t rc = adxl355_read_reg(ctx, ADXL355_STATUS, &st, 1u);
    if (rc != 0) {
        return rc;
    }
    return (st & ADXL355_STATUS_DATA_RDY) ? 1 : 0;
}

int32_t adxl355_decode_axis(const uint8_t b[3])
{
    uint32_t u = ((uint32_t)b[0] << 12) | ((uint32_t)b[1] << 4) | ((uint32_t)b[2] >> 4);
    /* sign-extend bit 19 without relying on implementation-defined right shifts */
    return (int32_t)(u ^ 0x80000u) - (int32_t)0x80000;
}

int32_t adxl355_decode_temp(uint8_t temp2, uint8_t temp1)
{
    return (int32_t)((((uint32_t)temp2 & 0x0Fu) << 8) | (uint32_t)temp1);
}

int32_t adxl355_read_sample(const adxl355_ctx_t *ctx, fw_raw_sample_t *out)
{
    uint8_t raw[11];   /* TEMP2 TEMP1 X3 X2 X1 Y3 Y2 Y1 Z3 Z2 Z1 */
    int32_t rc;
    unsigned i;

    if (out == 0) {
        return ADXL355_ERR_ARG;
    }
    rc = adxl355_read_reg(ctx, ADXL355_TEMP2, raw, (uint16_t)sizeof raw);
    if (rc != 0) {
        return rc;
    }
    out->temp = adxl355_decode_temp(raw[0], raw[1]);
    for (i = 0; i < 3u; i++) {
        out->acc[i] = adxl355_decode_axis(&raw[2u + 3u * i]);
    }
    return 0;
}

float adxl355_temp_c(int32_t count)
{
    return 25.0f + ((float)count - ADXL355_T_LSB_AT_25C) / ADXL355_T_LSB_PER_C;
}

float adxl355_odr_hz(adxl355_odr_t odr)
{
    static const float hz[11] = {4000.0f, 2000.0f, 1000.0f, 500.0f, 250.0f, 125.0f, 62.5f, 31.25f,
                                 15.625f, 7.813f, 3.906f};
    return ((unsigned)odr < 11u) ? hz[(unsigned)odr] : 0.0f;
}
