/* fw_board.h: the board firmware's portable core (design 3.1 serial, 3.2 CAN, NVM, compensation).
 *
 * A target calls, from its main loop or interrupts (never re-entrantly):
 *   fw_board_init   once at boot: loads the NVM record, checks its CRC; a corrupt record is reported
 *                   as `E,NVM,...` (serial) and the board runs uncompensated with zero coefficients;
 *   fw_uart_rx      with bytes the station sent (serial boards);
 *   fw_can_rx       with a CAN frame the station sent (CAN boards);
 *   fw_sample       with each new sensor sample (data-ready); the core decimates to the ODR, runs the
 *                   on-board streaming calibrator when on, compensates when on, and sends `D` frames
 *                   (or 0x180+N frames) while started.
 */
#ifndef FW_BOARD_H
#define FW_BOARD_H

#include <stdint.h>
#include "fw_hal.h"
#include "fw_selfcal.h"

#define FW_SERIAL_MAX 15u   /* serial number, NUL terminated (CAN carries at most 14 characters) */
#define FW_SENSOR_MAX 15u
#define FW_FW_MAX 15u
#define FW_RX_LINE_MAX 200u

typedef struct fw_identity {
    char serial[FW_SERIAL_MAX + 1];
    char sensor[FW_SENSOR_MAX + 1];   /* "LIS3DSH" or "ADXL355" */
    char fw[FW_FW_MAX + 1];           /* firmware version string, e.g. "fw-c-1.0" */
    float ug_per_lsb;
    float t_lsb_per_c;
    float t_lsb_at_25c;
    float odr_hz;                     /* the sensor's own output rate (the source rate) */
} fw_identity_t;

typedef struct fw_cal {
    float thermal[6];        /* tdb x y z mg/C, tdsf x y z ppm/C */
    float sfem[12];          /* a11..a33 row by row, b x y z in g */
    uint32_t thermal_crc;    /* CRC-32 (zlib) of thermal[] as float32 little-endian */
    uint32_t sfem_crc;       /* CRC-32 of sfem[] (valid only when has_sfem) */
    uint8_t has_sfem;
    uint8_t comp;            /* on-board compensation on */
} fw_cal_t;

typedef enum { FW_NVM_OK = 0, FW_NVM_EMPTY = 1, FW_NVM_CORRUPT = 2 } fw_nvm_status_t;

typedef struct fw_board {
    const fw_hal_t *hal;
    fw_identity_t id;
    uint8_t can_node;             /* 0: serial board; 1..127: CAN node id */
    fw_cal_t cal;                 /* what is applied (a copy of the valid NVM record) */
    fw_nvm_status_t nvm_status;   /* what fw_board_init found */
    uint32_t nvm_seq;             /* generation counter of the newest valid record */
    uint8_t streaming;
    uint32_t seq;                 /* D frame sequence (wraps) */
    uint32_t decim, phase;        /* ODR = source rate / decim */
    float odr_hz;
    uint8_t can_cal_have;         /* CAN: bit k set when CAL_FIELD k arrived */
    float can_cal_fields[6];
    uint8_t rx_line[FW_RX_LINE_MAX];
    uint32_t rx_len;
    uint8_t rx_overflow;
    uint32_t rx_bad_frames;       /* checksum errors, unknown types, short lines, garbage (counted, skipped) */
    uint8_t selfcal_on;
    fw_selfcal_t selfcal;         /* the on-board martinez2022 streaming calibrator */
    /* added by the core implementation (fw_board.c and friends) */
    int8_t nvm_slot;              /* slot holding the newest valid record, -1 when none */
    uint8_t nvm_corrupt_mask;     /* bit k: slot k was neither erased nor valid at boot */
    uint8_t can_shift;            /* CAN: right shift of the counts to fit int16 (can_scale) */
    float can_ug_per_lsb;         /* CAN: ug per CAN count (after the shift) */
    uint32_t frames_dropped;      /* replies too long to frame (never expected) */
} fw_board_t;

void fw_board_init(fw_board_t *b, const fw_hal_t *hal, const fw_identity_t *id, uint8_t can_node);
void fw_uart_rx(fw_board_t *b, const uint8_t *data, uint32_t len);
void fw_can_rx(fw_board_t *b, uint16_t id, uint8_t dlc, const uint8_t *data);
void fw_sample(fw_board_t *b, const fw_raw_sample_t *s);

/* Pure helpers, exported for the cross-checks against the Python codecs (tests/ via ctypes). */
uint32_t fw_crc32(uint32_t crc, const uint8_t *buf, uint32_t len);          /* zlib's crc32(), crc=0 to start */
uint32_t fw_crc32_f32(const float *values, uint32_t n);                     /* design 3.1 CRC of float32 LE */
uint8_t fw_xor_checksum(const uint8_t *body, uint32_t len);                 /* design 3.1 HH */
/* Frame one body as `$BODY*HH\n` into out (cap bytes); returns bytes written, 0 if it does not fit. */
uint32_t fw_frame(const uint8_t *body, uint32_t len, uint8_t *out, uint32_t cap);
/* Check one received line (without '\n'): returns the body length and sets *body, or -1 if not a
 * valid `$BODY*HH` frame (bad checksum, no '$', no '*', lower-case or non-hex HH). */
int32_t fw_unframe(const uint8_t *line, uint32_t len, const uint8_t **body);
/* Eq. 13 with the board's own temperature, then the SFEM if stored: raw counts in, counts out
 * (rounded to nearest, saturated to int32). temp_c from the identity's temperature scaling. */
void fw_compensate(const fw_cal_t *cal, float ug_per_lsb, const int32_t raw[3], float temp_c, int32_t out[3]);
float fw_temp_c(const fw_identity_t *id, int32_t temp_count);

/* Added: the size of fw_board_t (ctypes allocates it), the CAN scaling of an identity (right shift
 * so that +-1.9 g fits int16 and the resulting ug per CAN count, drivers/sim/slcan_pty.can_scale). */
uint32_t fw_board_sizeof(void);
uint8_t fw_can_scale(const fw_identity_t *id, float *ug_per_can_lsb);

#endif
