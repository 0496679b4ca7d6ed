/* fw_num.h: decimal text <-> numbers without libc (no printf/strtod: newlib-nano needs neither).
 *
 * Parsing is exact (big-integer arithmetic, no FPU): a decimal text becomes the float64 Python's
 * float() returns (correctly rounded), and the float32 numpy's float32(float(text)) returns (that
 * float64 rounded again to float32), so the board stores bit-for-bit what the station's
 * cal_record.to_f32 computes and both CRCs agree.
 * Formatting of float32 is the shortest positional decimal that parses back to the same float32
 * (numpy.format_float_positional(np.float32(v), unique=True, trim="-"), i.e. serial_frames.fmt_f32).
 */
#ifndef FW_NUM_H
#define FW_NUM_H

#include <stdint.h>

#define FW_F32_TEXT_MAX 64u   /* longest fw_fmt_f32 output + NUL (denormals: "0.000...0014") */

/* Python float() syntax: [ws][+-](digits[.digits]|.digits)[(e|E)[+-]digits][ws], '_' between
 * digits, "inf", "infinity", "nan" (any case). The float64 is exact for 1e-46 <= |x| < 1e40 (the
 * float32 range; outside it the float64 is 0 or inf: only the float32 matters to the board). Returns 0 and sets f64, f32 (either may be NULL),
 * or -1 when the text is not a number. Non-finite results are returned as such (callers check). */
int fw_parse_real(const char *s, uint32_t len, double *f64, float *f32);
/* Decimal integer [+-]digits (no spaces), within int64. Returns 0 or -1. */
int fw_parse_i64(const char *s, uint32_t len, int64_t *out);

/* Each writes into out (NUL terminated) and returns the length written (no NUL). */
uint32_t fw_fmt_u32(char *out, uint32_t v);
uint32_t fw_fmt_i32(char *out, int32_t v);
uint32_t fw_fmt_hex32(char *out, uint32_t v);           /* 8 upper-case hex digits (fmt_crc) */
uint32_t fw_fmt_f32(char *out, float v);                /* out: FW_F32_TEXT_MAX bytes */

/* float32 bit helpers (no type punning through pointers). */
uint32_t fw_f32_bits(float v);
float fw_bits_f32(uint32_t u);
int fw_f32_finite(float v);

#endif
