/* fw_board.h: the board firmware's portable core (design 3.1 serial, 3.2 CAN, NVM, compensation).
 *
 * A target calls, from its main loop or interrupts (never re-entrantly):
 *   fw_board_init   once at boot: loads the NVM record, checks its CRC; a corrupt record is reported
 *                   as `E,NVM,...` (serial) and the board runs uncompensated with zero coefficients;
 *   fw_uart_rx      with bytes the station sent (serial boards);
 *   fw_can_rx       with a CAN frame the station sent (CAN boards);
 *   fw_board_idle   from the idle loop (nothing received, no sample waiting): finishes a long reply;
 *   fw_sample       with each new sensor sample (data-ready); the core decimates to the ODR, runs the
 *                   on-board streaming calibrator when on, compensates when on, and sends `D` frames
 *                   (or 0x180+N frames) while started. `seq` counts output samples taken while
 *                   started, not frames sent: a t_us gap of more than 1.5 source periods since the
 *                   previous sample counts the missed source periods (decimation phase and seq advance
 *                   for each missed output sample, no frame), and a sample that could not be framed
 *                   still advances seq (docs/design.md 3.1, firmware/README.md).
 * Long replies (`S` to $SFER, `T,<k>` to $SFTR, `C` to $CALR, `R` to $SCRR: 6 to 12 numbers) are not
 * formatted by the command: it records them (fw_reply_t) and every later fw_sample formats
 * FW_REPLY_STEP_VALUES more numbers, so no single call formats 12 floats (the per-sample budget,
 * targets/qemu/README.md); fw_board_idle, and the next command, finish it at once. The frame goes
 * out whole when complete (frames never interleave on the link), bytes as if sent at once.
 */
#ifndef FW_BOARD_H
#define FW_BOARD_H

#include <stdint.h>
#include "fw_hal.h"
#include "fw_selfcal.h"
#include "fw_boot.h"
#include "fw_frame.h"

#define FW_SERIAL_MAX 31u   /* serial number, NUL terminated (design 3.1: 1..32; CAN frames 0,1,12,13 carry 28) */
#define FW_SENSOR_MAX 15u
#define FW_FW_MAX 15u
#define FW_RX_LINE_MAX 512u   /* = the station's MAX_LINE_BYTES: a $SFTW of 12 positional floats can pass 200 */

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

/* The cubic thermal SFEM of a version-2 record (docs/design.md 3.1, sensors2023 eq. 8):
 * A(T)_ij = sum_k c[k][3i+j] d^k, b(T)_i = sum_k c[k][9+i] d^k (b in g), d = clamp(T, t_lo_c, t_hi_c)
 * - t_ref_c. Kept apart from fw_cal_t so that fw_cal_t (and fw_compensate) stay as version 1 had them. */
#define FW_CUBIC_POWERS 4u
#define FW_CUBIC_VALUES 51u      /* t_ref_c, t_lo_c, t_hi_c, c[0][0..11] .. c[3][0..11]: the $SFTC CRC order */
typedef struct fw_cubic {
    float t_ref_c, t_lo_c, t_hi_c;
    float c[FW_CUBIC_POWERS][12];   /* power k: a11..a33 row by row, b x y z (g) */
    uint32_t crc;                   /* CRC-32 of the 51 values (fw_cubic_crc) */
    uint8_t present;                /* 1: stored (the record in force is version 2) */
} fw_cubic_t;

typedef enum { FW_NVM_OK = 0, FW_NVM_EMPTY = 1, FW_NVM_CORRUPT = 2 } fw_nvm_status_t;
/* Record state as the identity (`rec_state=`) and CAN identity frame 11 (byte 2) report it. */
typedef enum { FW_REC_OK = 0, FW_REC_FALLBACK = 1, FW_REC_EMPTY = 2, FW_REC_CORRUPT = 3 } fw_rec_state_t;

/* A long reply being formatted a few numbers per call (the comment at the top). */
#define FW_REPLY_VALUES_MAX 12u
#define FW_REPLY_STEP_VALUES 4u   /* numbers formatted per fw_sample: ~4 x 200 instructions on the M4 */
typedef enum {
    FW_REPLY_TAIL_NONE = 0,       /* T,<k>,<12 values> */
    FW_REPLY_TAIL_HEX = 1,        /* ...,<crc> (S) */
    FW_REPLY_TAIL_CALR = 2,       /* ...,<crc>,<comp>,rec_ver=..,rec_gen=..,rec_slot=..,rec_state=.. (C) */
    FW_REPLY_TAIL_U32X2 = 3       /* ...,<u32>,<u32> (R: n_segments, flags) */
} fw_reply_tail_t;
typedef struct fw_reply {
    fw_tx_t tx;                          /* the body so far (kind and any prefix written at once) */
    float vals[FW_REPLY_VALUES_MAX];     /* the numbers still to format, copied when the command came */
    uint32_t tail_u32[2];                /* the tail's words (crc; comp; n_segments, flags) */
    uint8_t n_vals;                      /* numbers in vals */
    uint8_t next;                        /* next number to format */
    uint8_t tail;                        /* fw_reply_tail_t */
    uint8_t pending;                     /* 1: recorded, not sent yet */
} fw_reply_t;

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
    fw_boot_info_t boot;          /* why and how often the board started (fw_board_set_boot) */
    uint32_t sensor_reinits;      /* sensor re-initialised by the target's liveness check */
    float selfcal_skew_mg_per_c;  /* simulation fault: the on-board calibrator's TDB is off by this */
    /* issue 42: version-2 record, record state, sample counting */
    fw_cubic_t cubic;             /* the cubic SFEM in force (cubic.present = 0: version-1 record or none) */
    float sft_stage[FW_CUBIC_POWERS][12];   /* $SFTW staging */
    uint8_t sft_have;             /* bit k: power k staged since the last $SFTC */
    uint8_t nvm_bad_nonfinite;    /* bit k: slot k was CORRUPT because a value is not finite (CRCs fine) */
    uint32_t prev_t_us;           /* data-ready time of the previous source sample */
    uint32_t gap_us;              /* more than this since the previous sample: missed periods (1.5 periods) */
    uint32_t gap_lo, gap_span;    /* a gap: dt - gap_lo <= gap_span, i.e. gap_us < dt < 2^31 (armed by the first sample) */
    float src_rate_per_us;        /* source ODR in samples per microsecond (missed-period count) */
    float counts_per_g;           /* 1e6 / ug_per_lsb (the cubic SFEM's b in counts) */
    fw_reply_t reply;             /* a long reply being formatted (serial boards) */
} fw_board_t;

void fw_board_init(fw_board_t *b, const fw_hal_t *hal, const fw_identity_t *id, uint8_t can_node);
void fw_uart_rx(fw_board_t *b, const uint8_t *data, uint32_t len);
void fw_can_rx(fw_board_t *b, uint16_t id, uint8_t dlc, const uint8_t *data);
void fw_sample(fw_board_t *b, const fw_raw_sample_t *s);
/* From the target's idle loop (no station byte, no sample waiting): formats the rest of a pending
 * long reply and sends it, so a board whose sensor is silent or not sampling still answers. After
 * it nothing is pending: the target may sleep. Bounded: one 12-number reply (targets/qemu/README.md). */
void fw_board_idle(fw_board_t *b);

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
/* The version-2 cubic SFEM (counts in, counts out, float32; eq. 13 is not applied on top): T =
 * temp_c clamped to [t_lo_c, t_hi_c], d = T - t_ref_c, A(d) and b(d) by Horner, out = A (raw - b
 * counts_per_g). fw_compensate_cubic_f32 leaves the float result (cross-checks); fw_compensate_cubic
 * rounds it like fw_compensate. counts_per_g = 1e6 / ug_per_lsb. */
void fw_compensate_cubic_f32(const fw_cubic_t *cu, float counts_per_g, const int32_t raw[3], float temp_c, float out[3]);
void fw_compensate_cubic(const fw_cubic_t *cu, float counts_per_g, const int32_t raw[3], float temp_c, int32_t out[3]);
/* CRC-32 of the 51 values in the $SFTC order (t_ref_c, t_lo_c, t_hi_c, c[0][0..11] .. c[3][0..11]). */
uint32_t fw_cubic_crc(const fw_cubic_t *cu);
float fw_temp_c(const fw_identity_t *id, int32_t temp_count);

/* Added: the size of fw_board_t (ctypes allocates it), the CAN scaling of an identity (right shift
 * so that +-1.9 g fits int16 and the resulting ug per CAN count, drivers/sim/slcan_pty.can_scale). */
uint32_t fw_board_sizeof(void);
/* Layout of the core's structs for the ctypes mirrors in tests/ (core/fw_layout.c): "fw_board_t"
 * etc. give sizeof, "fw_board_t.seq" etc. offsetof; 0xFFFFFFFF for a name it does not know. A test
 * that checks its mirror against these fails on a layout change instead of reading garbage. */
uint32_t fw_layout(const char *name);
uint8_t fw_can_scale(const fw_identity_t *id, float *ug_per_can_lsb);
/* The record in force as the identity reports it: state (fw_rec_state_t), layout version (0: none). */
fw_rec_state_t fw_board_rec_state(const fw_board_t *b);
uint8_t fw_board_rec_version(const fw_board_t *b);

#endif
