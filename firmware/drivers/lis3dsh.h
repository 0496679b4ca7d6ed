/* lis3dsh.h: ST LIS3DSH 3-axis accelerometer, platform-independent driver (SPI, no heap).
 *
 * In the style of ST's MEMS drivers: the platform fills a lis3dsh_ctx_t with read/write functions
 * that move `len` bytes from/to register `reg` (the platform builds the SPI address byte with
 * lis3dsh_spi_addr(): bit 7 = read; multi-byte transfers auto-increment once ADD_INC is set in
 * CTRL_REG6, which lis3dsh_init() does). Every function returns 0 on success, <0 on an error.
 *
 * Scaling (design 3.1, identity `60,1,0`): +-2 g full scale = 60 ug/LSB (0.06 mg/digit),
 * temperature OUT_T 8-bit two's complement, 1 LSB/C, 0 = 25 C.
 */
#ifndef LIS3DSH_H
#define LIS3DSH_H

#include <stdint.h>
#include "fw_hal.h"

/* Registers */
#define LIS3DSH_OUT_T        0x0Cu
#define LIS3DSH_WHO_AM_I     0x0Fu
#define LIS3DSH_CTRL_REG4    0x20u   /* ODR[7:4] BDU[3] ZEN[2] YEN[1] XEN[0] */
#define LIS3DSH_CTRL_REG3    0x23u   /* DR_EN[7] IEA[6] IEL[5] INT2_EN[4] INT1_EN[3] VFILT[2] STRT[0] */
#define LIS3DSH_CTRL_REG5    0x24u   /* BW[7:6] FSCALE[5:3] ST[2:1] SIM[0] */
#define LIS3DSH_CTRL_REG6    0x25u   /* BOOT[7] FIFO_EN[6] WTM_EN[5] ADD_INC[4] ... */
#define LIS3DSH_STATUS       0x27u   /* ZYXOR[7] .. ZYXDA[3] ZDA[2] YDA[1] XDA[0] */
#define LIS3DSH_OUT_X_L      0x28u   /* .. OUT_Z_H 0x2D */
#define LIS3DSH_FIFO_CTRL    0x2Eu   /* FMODE[7:5] WTMP[4:0] */
#define LIS3DSH_FIFO_SRC     0x2Fu   /* WTM[7] OVRN_FIFO[6] EMPTY[5] FSS[4:0] */

#define LIS3DSH_ID           0x3Fu
#define LIS3DSH_SPI_READ     0x80u

#define LIS3DSH_CTRL4_BDU    0x08u
#define LIS3DSH_CTRL4_XYZEN  0x07u
#define LIS3DSH_CTRL3_DR_EN  0x80u
#define LIS3DSH_CTRL3_IEA    0x40u   /* interrupt active high */
#define LIS3DSH_CTRL3_INT1_EN 0x08u
#define LIS3DSH_CTRL6_ADD_INC 0x10u
#define LIS3DSH_CTRL6_FIFO_EN 0x40u
#define LIS3DSH_CTRL6_WTM_EN  0x20u
#define LIS3DSH_CTRL6_P1_WTM  0x04u   /* FIFO watermark on INT1 */
#define LIS3DSH_FIFO_MODE_STREAM 0x40u   /* FMODE 010: the oldest sample is overwritten when full */
#define LIS3DSH_FIFO_SRC_WTM  0x80u
#define LIS3DSH_FIFO_SRC_OVRN 0x40u
#define LIS3DSH_FIFO_SRC_EMPTY 0x20u
#define LIS3DSH_FIFO_DEPTH    32u
#define LIS3DSH_STATUS_ZYXDA 0x08u

/* Scaling constants of the identity frame at +-2 g */
#define LIS3DSH_UG_PER_LSB_2G 60.0f
#define LIS3DSH_T_LSB_PER_C   1.0f
#define LIS3DSH_T_LSB_AT_25C  0.0f

typedef int32_t (*lis3dsh_read_ptr)(void *handle, uint8_t reg, uint8_t *buf, uint16_t len);
typedef int32_t (*lis3dsh_write_ptr)(void *handle, uint8_t reg, const uint8_t *buf, uint16_t len);

typedef struct lis3dsh_ctx {
    lis3dsh_read_ptr read;
    lis3dsh_write_ptr write;
    void *handle;           /* the platform's bus handle (SPI + chip select) */
} lis3dsh_ctx_t;

typedef enum {
    LIS3DSH_ODR_3HZ125 = 1, LIS3DSH_ODR_6HZ25 = 2, LIS3DSH_ODR_12HZ5 = 3, LIS3DSH_ODR_25HZ = 4,
    LIS3DSH_ODR_50HZ = 5, LIS3DSH_ODR_100HZ = 6, LIS3DSH_ODR_400HZ = 7, LIS3DSH_ODR_800HZ = 8,
    LIS3DSH_ODR_1600HZ = 9
} lis3dsh_odr_t;

typedef enum {
    LIS3DSH_FS_2G = 0, LIS3DSH_FS_4G = 1, LIS3DSH_FS_6G = 2, LIS3DSH_FS_8G = 3, LIS3DSH_FS_16G = 4
} lis3dsh_fs_t;

#define LIS3DSH_ERR_BUS   (-1)
#define LIS3DSH_ERR_ID    (-2)
#define LIS3DSH_ERR_ARG   (-3)

/* SPI address byte of a transfer (the platform's read/write put it first on MOSI). */
static inline uint8_t lis3dsh_spi_addr(uint8_t reg, int is_read)
{
    return (uint8_t)((reg & 0x7Fu) | (is_read ? LIS3DSH_SPI_READ : 0u));
}

int32_t lis3dsh_read_reg(const lis3dsh_ctx_t *ctx, uint8_t reg, uint8_t *buf, uint16_t len);
int32_t lis3dsh_write_reg(const lis3dsh_ctx_t *ctx, uint8_t reg, uint8_t value);
int32_t lis3dsh_who_am_i(const lis3dsh_ctx_t *ctx, uint8_t *id);
/* Check WHO_AM_I, then ADD_INC, full scale, ODR with BDU and XYZ enabled, DRDY on INT1 (active
 * high, pulsed). Returns LIS3DSH_ERR_ID when the part does not answer 0x3F. */
int32_t lis3dsh_init(const lis3dsh_ctx_t *ctx, lis3dsh_odr_t odr, lis3dsh_fs_t fs);
/* 1 when a new XYZ set is ready (STATUS.ZYXDA), 0 when not, <0 on a bus error. */
int32_t lis3dsh_data_ready(const lis3dsh_ctx_t *ctx);
/* Read X/Y/Z (16-bit two's complement) and OUT_T (8-bit) into counts; t_us is left to the caller. */
int32_t lis3dsh_read_sample(const lis3dsh_ctx_t *ctx, fw_raw_sample_t *out);
/* FIFO in stream mode with a watermark of wtm samples (1..31) on INT1 instead of data-ready: the
 * part keeps the newest 32 samples, INT1 rises when wtm are stored (the wtm-th sample's data-ready)
 * and stays high while at least wtm are. Call after lis3dsh_init. */
int32_t lis3dsh_fifo_stream(const lis3dsh_ctx_t *ctx, uint8_t wtm);
/* FIFO_SRC: *count = samples stored (0..32), *src = the raw register (OVRN: samples were lost). */
int32_t lis3dsh_fifo_status(const lis3dsh_ctx_t *ctx, uint32_t *count, uint8_t *src);
/* Read n stored samples, oldest first (one 6-byte burst X_L..Z_H each pops one), and OUT_T once
 * (the temperature is not in the FIFO; every sample of the batch gets it). t_us is left to the caller. */
int32_t lis3dsh_fifo_read(const lis3dsh_ctx_t *ctx, fw_raw_sample_t *out, uint32_t n);
/* The data-ready time of sample k (0 = oldest) of a batch whose watermark edge came at t_wtm_us:
 * the edge is the wtm-th sample's data-ready, the others one output period apart
 * (t_wtm_us + (k - (wtm - 1)) * period_us, modulo 2^32 like the board clock). */
uint32_t lis3dsh_fifo_t_us(uint32_t t_wtm_us, uint32_t wtm, uint32_t k, uint32_t period_us);
/* Output data rate in Hz of a code (0 for an invalid code). */
float lis3dsh_odr_hz(lis3dsh_odr_t odr);
/* Temperature in C of an OUT_T count: 25 + count (1 LSB/C). */
float lis3dsh_temp_c(int32_t count);
/* ug/LSB of a full-scale setting (0.06/0.12/0.18/0.24/0.73 mg/digit). */
float lis3dsh_ug_per_lsb(lis3dsh_fs_t fs);

#endif
