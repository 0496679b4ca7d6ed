/* adxl355.h: Analog Devices ADXL355 3-axis accelerometer, platform-independent driver (SPI, no heap).
 *
 * Same shape as lis3dsh.h: the platform fills an adxl355_ctx_t with read/write functions on
 * register `reg`; it builds the SPI address byte with adxl355_spi_addr() = (reg << 1) | 1 for a read
 * (the ADXL355 auto-increments on multi-byte transfers). Every function returns 0 or <0.
 *
 * Data: 20-bit two's complement, left-justified in XDATA3..XDATA1 (bits 19:12, 11:4, 3:0 in [7:4]);
 * +-2 g = 256000 LSB/g = 3.9 ug/LSB. Temperature 12-bit unsigned (TEMP2[3:0]:TEMP1), nominal
 * 1885 LSB at 25 C and -9.05 LSB/C (design 3.1 identity `3.9,-9.05,1885`).
 */
#ifndef ADXL355_H
#define ADXL355_H

#include <stdint.h>
#include "fw_hal.h"

#define ADXL355_DEVID_AD   0x00u
#define ADXL355_DEVID_MST  0x01u
#define ADXL355_PARTID     0x02u
#define ADXL355_REVID      0x03u
#define ADXL355_STATUS     0x04u   /* NVM_BUSY[4] ACTIVITY[3] FIFO_OVR[2] FIFO_FULL[1] DATA_RDY[0] */
#define ADXL355_TEMP2      0x06u   /* temp[11:8] in [3:0] */
#define ADXL355_TEMP1      0x07u   /* temp[7:0] */
#define ADXL355_XDATA3     0x08u   /* .. ZDATA1 0x10 */
#define ADXL355_FILTER     0x28u   /* HPF_CORNER[6:4] ODR_LPF[3:0] */
#define ADXL355_RANGE      0x2Cu   /* I2C_HS[7] INT_POL[6] RANGE[1:0] */
#define ADXL355_POWER_CTL  0x2Du   /* DRDY_OFF[2] TEMP_OFF[1] STANDBY[0] */
#define ADXL355_RESET      0x2Fu

#define ADXL355_ID_AD      0xADu
#define ADXL355_ID_MST     0x1Du
#define ADXL355_ID_PART    0xEDu
#define ADXL355_RESET_CODE 0x52u
#define ADXL355_STATUS_DATA_RDY 0x01u
#define ADXL355_RANGE_I2C_HS    0x80u
#define ADXL355_POWER_STANDBY   0x01u
#define ADXL355_POWER_TEMP_OFF  0x02u
#define ADXL355_POWER_DRDY_OFF  0x04u

#define ADXL355_UG_PER_LSB_2G 3.9f
#define ADXL355_T_LSB_PER_C   (-9.05f)
#define ADXL355_T_LSB_AT_25C  1885.0f

typedef int32_t (*adxl355_read_ptr)(void *handle, uint8_t reg, uint8_t *buf, uint16_t len);
typedef int32_t (*adxl355_write_ptr)(void *handle, uint8_t reg, const uint8_t *buf, uint16_t len);

typedef struct adxl355_ctx {
    adxl355_read_ptr read;
    adxl355_write_ptr write;
    void *handle;
} adxl355_ctx_t;

typedef enum {
    ADXL355_ODR_4000HZ = 0, ADXL355_ODR_2000HZ = 1, ADXL355_ODR_1000HZ = 2, ADXL355_ODR_500HZ = 3,
    ADXL355_ODR_250HZ = 4, ADXL355_ODR_125HZ = 5, ADXL355_ODR_62HZ5 = 6, ADXL355_ODR_31HZ25 = 7,
    ADXL355_ODR_15HZ625 = 8, ADXL355_ODR_7HZ813 = 9, ADXL355_ODR_3HZ906 = 10
} adxl355_odr_t;

typedef enum { ADXL355_RANGE_2G = 1, ADXL355_RANGE_4G = 2, ADXL355_RANGE_8G = 3 } adxl355_range_t;

#define ADXL355_ERR_BUS  (-1)
#define ADXL355_ERR_ID   (-2)
#define ADXL355_ERR_ARG  (-3)

static inline uint8_t adxl355_spi_addr(uint8_t reg, int is_read)
{
    return (uint8_t)(((unsigned)reg << 1) | (is_read ? 1u : 0u));
}

int32_t adxl355_read_reg(const adxl355_ctx_t *ctx, uint8_t reg, uint8_t *buf, uint16_t len);
int32_t adxl355_write_reg(const adxl355_ctx_t *ctx, uint8_t reg, uint8_t value);
/* Check DEVID_AD/DEVID_MST/PARTID, soft reset, then ODR (FILTER, no high-pass), range, and
 * measurement mode with temperature and DRDY on (POWER_CTL = 0). */
int32_t adxl355_init(const adxl355_ctx_t *ctx, adxl355_odr_t odr, adxl355_range_t range);
int32_t adxl355_data_ready(const adxl355_ctx_t *ctx);
/* One burst TEMP2..ZDATA1: 20-bit sign-extended counts and the 12-bit temperature count. */
int32_t adxl355_read_sample(const adxl355_ctx_t *ctx, fw_raw_sample_t *out);
/* Decoders, exported for the tests */
int32_t adxl355_decode_axis(const uint8_t b[3]);
int32_t adxl355_decode_temp(uint8_t temp2, uint8_t temp1);
float adxl355_temp_c(int32_t count);
float adxl355_odr_hz(adxl355_odr_t odr);

#endif
