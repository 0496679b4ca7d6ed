/* fw_num.h: decimal text <-> numbers without libc (no printf/strtod: newlib-nano needs neither) and
 * without double precision (the core is float32 only; nothing here links soft-float double code).
 *
 * Parsing is exact (big-integer arithmetic, no FPU): a decimal text becomes the float32 numpy's
 * float32(float(text)) returns, i.e. the correctly rounded float64 rounded again to float32 (both
 * roundings done on integers), so the board stores bit-for-bit what the station's
 * cal_record.to_f32 computes and both CRCs agree.
 * Formatting of float32 is the shortest positional decimal that parses back to the same float32
 * (numpy.format_float_positional(np.float32(v), unique=True, trim="-"), i.e. serial_frames.fmt_f32),
 * in a bounded number of instructions (one 32 x 64-bit multiplication per bound, no loops over big
 * integers: a few hundred instructions on the Cortex-M4, see targets/qemu/README.md).
 */
#ifndef FW_NUM_H
#define FW_NUM_H

#include <stdint.h>

/* Bytes fw_fmt_f32 may use: its longest text is 48 characters ("-0.000...0001", -1e-45, all 2^32
 * checked) + NUL, and it writes whole words past the text (never beyond byte 59). */
#define FW_F32_TEXT_MAX 64u

/* Python float() syntax: [ws][+-](digits[.digits]|.digits)[(e|E)[+-]digits][ws], '_' between
 * digits, "inf", "infinity", "nan" (any case). Returns 0 and sets *out to float32(float(text)),
 * or -1 when the text is not a number (*out untouched). Non-finite results are returned as such
 * (callers check with fw_f32_finite). */
int fw_parse_f32(const char *s, uint32_t len, float *out);
/* Decimal integer [+-]digits (no spaces), within int64. Returns 0 or -1. */
int fw_parse_i64(const char *s, uint32_t len, int64_t *out);

/* Decimation factor k = src_hz / dst_hz (the nearest integer, halves up) when dst_hz divides src_hz:
 * |src/dst - k| < 1e-6 + k 2^-24, 1 <= k < 2^31 - 1 (exact integer arithmetic on the float32
 * values). 0 when it does not divide, dst_hz > src_hz, either is not a positive finite number.
 * drivers/sim/serial_pty._ratio asks |src/dst - k| < 1e-6 of the float64 rate; the board sees the
 * rate rounded to float32 (relative error up to 2^-24, so src/dst moves by up to k 2^-24): the
 * k 2^-24 term accepts the float32 of every rate the simulated board accepts (`ODR,1e-3` from
 * 3.125 Hz: k = 3125, the float32 0.001 is 1.5e-4 away from 3125 in the ratio). */
uint32_t fw_rate_ratio(float src_hz, float dst_hz);

/* Each writes into out (NUL terminated) and returns the length written (no NUL). */
uint32_t fw_fmt_u32(char *out, uint32_t v);
uint32_t fw_fmt_i32(char *out, int32_t v);
uint32_t fw_fmt_hex32(char *out, uint32_t v);           /* 8 upper-case hex digits (fmt_crc) */
uint32_t fw_fmt_f32(char *out, float v);                /* out: FW_F32_TEXT_MAX bytes */

/* The shortest decimal of a finite nonzero float32 magnitude (bits without the sign):
 * returns d and sets *exp10 with |v| = d * 10^exp10, d without trailing zeros (d < 10^9).
 * Exported for the exhaustive cross-check (firmware/tools/f32_exhaustive.cc). */
uint32_t fw_f32_shortest(uint32_t mag_bits, int32_t *exp10);

/* float32 bit helpers (no type punning through pointers). */
uint32_t fw_f32_bits(float v);
float fw_bits_f32(uint32_t u);
int fw_f32_finite(float v);

#endif
