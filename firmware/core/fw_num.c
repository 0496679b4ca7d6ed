/* fw_num.c: exact decimal parsing and shortest float32 formatting (see fw_num.h). Integer
 * arithmetic only: no double anywhere, no libgcc soft-float. */
#include <string.h>
#include "fw_num.h"
#include "fw_num_pow10.h"

uint32_t fw_f32_bits(float v) { uint32_t u; memcpy(&u, &v, 4); return u; }
float fw_bits_f32(uint32_t u) { float v; memcpy(&v, &u, 4); return v; }
int fw_f32_finite(float v) { return (fw_f32_bits(v) & 0x7F800000u) != 0x7F800000u; }

/* ---- parsing: exact, big integers (command path only, never per sample) ---------------------- */

#define BIG_WORDS 13u          /* 416 bits: 5^149 * 2^24 and 10^86 * 2^2 both fit */
#define MAX_SIG_DIGITS 40u     /* digits kept exactly; further nonzero digits only set "sticky" */

typedef struct { uint32_t w[BIG_WORDS]; } big_t;

static void big_set(big_t *a, uint32_t v) { memset(a, 0, sizeof *a); a->w[0] = v; }

static void big_mul_add(big_t *a, uint32_t m, uint32_t add)
{
    uint64_t carry = add;
    for (uint32_t i = 0; i < BIG_WORDS; i++) {
        uint64_t t = (uint64_t)a->w[i] * m + carry;
        a->w[i] = (uint32_t)t;
        carry = t >> 32;
    }
}

static void big_pow10(big_t *a, uint32_t n)   /* a *= 10^n, 10^9 at a time */
{
    for (; n >= 9u; n -= 9u) big_mul_add(a, 1000000000u, 0);
    static const uint32_t p10[9] = { 1u, 10u, 100u, 1000u, 10000u, 100000u, 1000000u, 10000000u, 100000000u };
    if (n) big_mul_add(a, p10[n], 0);
}

static int big_cmp(const big_t *a, const big_t *b)
{
    for (uint32_t i = BIG_WORDS; i-- > 0;) {
        if (a->w[i] != b->w[i]) return a->w[i] < b->w[i] ? -1 : 1;
    }
    return 0;
}

static void big_sub(big_t *a, const big_t *b)   /* a -= b, a >= b */
{
    uint32_t borrow = 0;
    for (uint32_t i = 0; i < BIG_WORDS; i++) {
        uint64_t t = (uint64_t)a->w[i] - b->w[i] - borrow;
        a->w[i] = (uint32_t)t;
        borrow = (uint32_t)(t >> 63);
    }
}

static void big_shl1(big_t *a)
{
    for (uint32_t i = BIG_WORDS; i-- > 1;) a->w[i] = (a->w[i] << 1) | (a->w[i - 1] >> 31);
    a->w[0] <<= 1;
}

static int big_zero(const big_t *a)
{
    for (uint32_t i = 0; i < BIG_WORDS; i++) if (a->w[i]) return 0;
    return 1;
}

/* value = digits (nd decimal digits, most significant first) * 10^exp10 (+ a little if sticky).
 * Sets the float64 bits Python's float() gives and the float32 bits of float32(that float64). */
static void decimal_to_bits(const uint8_t *digits, uint32_t nd, int32_t exp10, int sticky, int neg,
                            uint64_t *b64, uint32_t *b32)
{
    uint64_t s64 = neg ? (1ull << 63) : 0;
    uint32_t s32 = neg ? 0x80000000u : 0;
    if (nd == 0) { *b64 = s64; *b32 = s32; return; }
    if ((int32_t)nd + exp10 > 40) {   /* >= 1e40: beyond float32 (the float64 is irrelevant here) */
        *b64 = s64 | 0x7FF0000000000000ull; *b32 = s32 | 0x7F800000u; return;
    }
    if ((int32_t)nd + exp10 < -46) {  /* < 1e-46 < 2^-150: float32 zero */
        *b64 = s64; *b32 = s32; return;
    }
    big_t r, d, t;
    big_set(&r, 0);
    for (uint32_t i = 0; i < nd; i++) big_mul_add(&r, 10, digits[i]);
    big_set(&d, 1);
    if (exp10 >= 0) big_pow10(&r, (uint32_t)exp10); else big_pow10(&d, (uint32_t)-exp10);
    int32_t e2 = 0;   /* value = (r/d) * 2^e2, normalised to 1 <= r/d < 2 */
    while (big_cmp(&r, &d) < 0) { big_shl1(&r); e2--; }
    for (;;) {
        t = d; big_shl1(&t);
        if (big_cmp(&r, &t) < 0) break;
        d = t; e2++;
    }
    uint64_t mant = 0;
    for (int i = 0; i < 64; i++) {
        mant <<= 1;
        if (big_cmp(&r, &d) >= 0) { big_sub(&r, &d); mant |= 1; }
        big_shl1(&r);
    }
    int st = sticky || !big_zero(&r);
    /* round to 53 bits (float64, always normal in this range), ties to even */
    uint64_t m53 = mant >> 11, rem = mant & 0x7FFu;
    if (rem > 0x400u || (rem == 0x400u && (st || (m53 & 1u)))) {
        m53++;
        if (m53 >> 53) { m53 >>= 1; e2++; }
    }
    *b64 = s64 | ((uint64_t)(e2 + 1023) << 52) | (m53 & 0xFFFFFFFFFFFFFull);
    /* then the float64 to float32 (exactly what numpy does), ties to even */
    if (e2 >= -126) {
        uint64_t m24 = m53 >> 29, r29 = m53 & 0x1FFFFFFFu;
        if (r29 > 0x10000000u || (r29 == 0x10000000u && (m24 & 1u))) {
            m24++;
            if (m24 >> 24) { m24 >>= 1; e2++; }
        }
        if (e2 > 127) { *b32 = s32 | 0x7F800000u; return; }
        *b32 = s32 | ((uint32_t)(e2 + 127) << 23) | ((uint32_t)m24 & 0x7FFFFFu);
    } else {
        int32_t sh = -97 - e2;   /* k = m53 * 2^(e2 - 52 + 149) */
        uint64_t k = 0;
        if (sh <= 54) {
            uint64_t half = 1ull << (sh - 1), low = m53 & ((1ull << sh) - 1);
            k = m53 >> sh;
            if (low > half || (low == half && (k & 1u))) k++;
        }
        *b32 = s32 | (uint32_t)k;   /* k == 2^23 is the smallest normal, bit-exact */
    }
}

static int lower(int c) { return (c >= 'A' && c <= 'Z') ? c + 32 : c; }

static int word_is(const char *s, uint32_t len, const char *w)
{
    uint32_t n = (uint32_t)strlen(w);
    if (len != n) return 0;
    for (uint32_t i = 0; i < n; i++) if (lower((unsigned char)s[i]) != w[i]) return 0;
    return 1;
}

static int is_digit(char c) { return c >= '0' && c <= '9'; }

/* Python float() text -> float64 and float32 bits; 0 or -1 (not a number). */
static int parse_bits(const char *s, uint32_t len, uint64_t *b64, uint32_t *b32)
{
    uint8_t dig[MAX_SIG_DIGITS];
    uint32_t nd = 0, i = 0;
    int neg = 0, sticky = 0, any = 0;
    int32_t exp10 = 0;
    while (len && (s[len - 1] == ' ' || s[len - 1] == '\t')) len--;
    while (i < len && (s[i] == ' ' || s[i] == '\t')) i++;
    if (i < len && (s[i] == '+' || s[i] == '-')) neg = s[i++] == '-';
    if (word_is(s + i, len - i, "inf") || word_is(s + i, len - i, "infinity")) {
        *b64 = 0x7FF0000000000000ull; *b32 = 0x7F800000u;
        goto special;
    }
    if (word_is(s + i, len - i, "nan")) {
        *b64 = 0x7FF8000000000000ull; *b32 = 0x7FC00000u;
        goto special;
    }
    for (int frac = 0; i < len; i++) {
        char c = s[i];
        if (c == '_') {   /* only between two digits */
            if (!any || i + 1 >= len || !is_digit(s[i + 1]) || !is_digit(s[i - 1])) return -1;
            continue;
        }
        if (c == '.') {
            if (frac) return -1;
            frac = 1;
            continue;
        }
        if (!is_digit(c)) break;
        any = 1;
        if (nd == 0 && c == '0') { if (frac) exp10--; continue; }
        if (nd < MAX_SIG_DIGITS) { dig[nd++] = (uint8_t)(c - '0'); if (frac) exp10--; }
        else { if (c != '0') sticky = 1; if (!frac) exp10++; }
    }
    if (!any) return -1;
    if (i < len) {
        if (s[i] != 'e' && s[i] != 'E') return -1;
        i++;
        int eneg = 0, edig = 0;
        int32_t e = 0;
        if (i < len && (s[i] == '+' || s[i] == '-')) eneg = s[i++] == '-';
        for (; i < len; i++) {
            if (s[i] == '_' && edig && i + 1 < len && is_digit(s[i + 1])) continue;
            if (!is_digit(s[i])) return -1;
            edig = 1;
            if (e < 100000) e = e * 10 + (s[i] - '0');
        }
        if (!edig) return -1;
        exp10 += eneg ? -e : e;
    }
    while (nd && dig[nd - 1] == 0) { nd--; exp10++; }   /* trailing zeros kept as exponent */
    decimal_to_bits(dig, nd, exp10, sticky, neg, b64, b32);
    return 0;
special:
    if (neg) { *b64 |= 1ull << 63; *b32 |= 0x80000000u; }
    return 0;
}

int fw_parse_f32(const char *s, uint32_t len, float *out)
{
    uint64_t b64;
    uint32_t b32;
    if (parse_bits(s, len, &b64, &b32) != 0) return -1;
    *out = fw_bits_f32(b32);
    return 0;
}

int fw_parse_i64(const char *s, uint32_t len, int64_t *out)
{
    uint32_t i = 0;
    int neg = 0;
    uint64_t v = 0;
    if (i < len && (s[i] == '+' || s[i] == '-')) neg = s[i++] == '-';
    if (i >= len) return -1;
    for (; i < len; i++) {
        if (!is_digit(s[i])) return -1;
        uint32_t dgt = (uint32_t)(s[i] - '0');
        if (v > (UINT64_C(9223372036854775808) - dgt) / 10u) return -1;
        v = v * 10u + dgt;
    }
    if (!neg && v > (uint64_t)INT64_MAX) return -1;
    *out = neg ? (int64_t)(0u - v) : (int64_t)v;
    return 0;
}

/* ---- decimation ratio ------------------------------------------------------------------------ */

/* A positive finite nonzero float32 as m * 2^e with 2^23 <= m < 2^24 (denormals normalised). */
static void unpack_pos(uint32_t bits, uint32_t *m, int32_t *e)
{
    uint32_t be = bits >> 23, fm = bits & 0x7FFFFFu;
    if (be) { *m = fm | 0x800000u; *e = (int32_t)be - 150; return; }
    *e = -149;
    while (fm < 0x800000u) { fm <<= 1; (*e)--; }
    *m = fm;
}

uint32_t fw_rate_ratio(float src_hz, float dst_hz)
{
    uint32_t sb = fw_f32_bits(src_hz), db = fw_f32_bits(dst_hz), ms, md;
    int32_t es, ed;
    /* 0, negative, inf, nan: bits - 1 wraps or lands at or above 0x7F7FFFFF */
    if (sb - 1u >= 0x7F7FFFFFu || db - 1u >= 0x7F7FFFFFu) return 0;
    /* dst > src (positive floats order like their bits). The simulator allows dst up to src * (1 + 1e-9):
     * the float32 next above src is at least 2^-24 away, so that is dst <= src here. */
    if (db > sb) return 0;
    unpack_pos(sb, &ms, &es);
    unpack_pos(db, &md, &ed);
    int32_t e = es - ed;   /* src / dst = (ms / md) * 2^e, ms / md in (1/2, 2), and >= 1: e >= 0 */
    if (e < 0 || e >= 32) return 0;   /* e >= 32: the ratio exceeds 2^31 */
    uint64_t num = (uint64_t)ms << e, quot = num / md;   /* < 2^55 / 2^23 */
    uint32_t rem = (uint32_t)(num - quot * md), dist = rem;
    if (2u * (uint64_t)rem >= md) { quot++; dist = md - rem; }   /* nearest k, halves up */
    if (quot >= 2147483647u) return 0;   /* like the float64 check k < 2147483647 */
    /* |src/dst - k| = dist / md < 1e-6 + k 2^-24, times md 1e6 2^24: (dist 1e6 - md) 2^24 < md k 1e6,
     * i.e. (a - md) 2^18 < c 15625 with a = dist 1e6 (< 2^44), c = md k (< 2^55). c >= 2^49 makes the
     * right side >= 2^62.9 > any left side (< 2^62), and keeps c 15625 below 2^64. */
    uint64_t a = (uint64_t)dist * 1000000u, c = (uint64_t)md * quot;
    if (a <= md || c >= (UINT64_C(1) << 49)) return (uint32_t)quot;
    return ((a - md) << 18) < c * 15625u ? (uint32_t)quot : 0u;
}

/* ---- formatting ---------------------------------------------------------------------------- */

/* Formatting is on the per-sample path (D frames, G frames, replies formatted between samples): no
 * loops over bytes that GCC could turn into calls to newlib-nano's byte-by-byte memset/memmove,
 * unaligned 32-bit copies (fine on the Cortex-M4 and on hosts; memcpy of 4 bytes is one load or
 * store), helpers forced inline. */
#if defined(__GNUC__)
#define FW_INLINE static inline __attribute__((always_inline))
#else
#define FW_INLINE static inline
#endif

FW_INLINE uint32_t load32(const char *p) { uint32_t w; memcpy(&w, p, 4); return w; }
FW_INLINE void store32(char *p, uint32_t w) { memcpy(p, &w, 4); }
FW_INLINE void copy12(char *dst, const char *src)
{
    uint32_t a = load32(src), b = load32(src + 4), c = load32(src + 8);
    store32(dst, a);
    store32(dst + 4, b);
    store32(dst + 8, c);
}

/* 48 '0' characters as 12 word stores (written out: a loop would become a memset call) */
FW_INLINE void zeros48(char *p)
{
    const uint32_t z = 0x30303030u;
    store32(p, z); store32(p + 4, z); store32(p + 8, z); store32(p + 12, z);
    store32(p + 16, z); store32(p + 20, z); store32(p + 24, z); store32(p + 28, z);
    store32(p + 32, z); store32(p + 36, z); store32(p + 40, z); store32(p + 44, z);
}

static const char DIGIT_PAIRS[201] =
    "00010203040506070809101112131415161718192021222324252627282930313233343536373839"
    "40414243444546474849505152535455565758596061626364656667686970717273747576777879"
    "8081828384858687888990919293949596979899";

/* The decimal digits of v written backwards from end (two at a time); returns the first digit. */
FW_INLINE char *digits_before(char *end, uint32_t v)
{
    while (v >= 100u) {
        uint32_t q = v / 100u;
        end -= 2;
        memcpy(end, DIGIT_PAIRS + 2u * (v - q * 100u), 2);
        v = q;
    }
    if (v >= 10u) {
        end -= 2;
        memcpy(end, DIGIT_PAIRS + 2u * v, 2);
    } else {
        *--end = (char)('0' + v);
    }
    return end;
}

/* scratch for digits_before: 10 digits end at tmp + 12, and 12 bytes may be read from any digit */
#define DIGIT_TMP 24u

/* Number of decimal digits of v (1..10), by a comparison tree. */
FW_INLINE uint32_t dec_len(uint32_t v)
{
    if (v < 100000u) {
        if (v < 100u) return v < 10u ? 1u : 2u;
        return v < 1000u ? 3u : (v < 10000u ? 4u : 5u);
    }
    if (v < 10000000u) return v < 1000000u ? 6u : 7u;
    return v < 100000000u ? 8u : (v < 1000000000u ? 9u : 10u);
}

/* Exactly the text and its NUL: callers size buffers for the text (12 bytes for any int32). */
static uint32_t fmt_int(char *out, uint32_t u, uint32_t neg)
{
    out[0] = '-';
    out += neg;
    uint32_t n = dec_len(u);
    digits_before(out + n, u);
    out[n] = 0;
    return n + neg;
}

uint32_t fw_fmt_u32(char *out, uint32_t v) { return fmt_int(out, v, 0u); }
uint32_t fw_fmt_i32(char *out, int32_t v) { return fmt_int(out, v < 0 ? 0u - (uint32_t)v : (uint32_t)v, v < 0 ? 1u : 0u); }

uint32_t fw_fmt_hex32(char *out, uint32_t v)
{
    static const char hex[] = "0123456789ABCDEF";
    for (uint32_t i = 0; i < 8u; i++) out[i] = hex[(v >> (28u - 4u * i)) & 0xFu];
    out[8] = 0;
    return 8;
}

/* Round to odd of x * g / 2^(64 - t), g = gh * 2^32 + gl, 1 <= t <= 4: bits [64 - t, 96) of the
 * 96-bit product, with bit 0 forced to 1 when any of its bits [32, 64 - t) is set. Bits [0, 32) are
 * left out: they hold g's round-up error (x < 2^27 < 2^32), so an exact quotient stays exact. */
FW_INLINE uint32_t mul_rto(uint32_t x, uint32_t gh, uint32_t gl, uint32_t t)
{
    uint64_t mid = (uint64_t)x * gh + (((uint64_t)x * gl) >> 32);
    uint32_t mh = (uint32_t)(mid >> 32), ml = (uint32_t)mid;
    return (mh << t) | (ml >> (32u - t)) | (uint32_t)((ml << t) != 0u);
}

/* Schubfach-style (R. Giulietti's idea, this implementation is ours): the float32 v = c * 2^q has the
 * rounding interval R = [v - 2^q / 2, v + 2^q / 2] (lower half-width 2^q / 4 at a power of two),
 * closed when c is even (the parser rounds ties to even), open when odd. With 10^k <= |R| < 10^(k+1)
 * R holds at most one multiple of 10^(k+1) and at least one of 10^k. In units of 10^k / 4:
 * vb ~ 4 v / 10^k, vbl, vbr the ends of R, each computed rounded to odd, so every comparison with a
 * multiple of 4 below is exact. Same choice as numpy's Dragon4 "unique" mode: fewest significant
 * digits, then the closest to v, then the even last digit. */
FW_INLINE uint32_t shortest(uint32_t mag, int32_t *exp10)
{
    uint32_t be = mag >> 23, fm = mag & 0x7FFFFFu;
    uint32_t c = be ? (fm | 0x800000u) : fm;
    int32_t q = be ? (int32_t)be - 150 : -149;
    uint32_t asym = (fm == 0u && be > 1u) ? 1u : 0u;
    int32_t k = (q * FW_LOG10_2_MUL + (asym ? FW_LOG10_34_ADD : 0)) >> FW_LOG10_2_SHIFT;
    int32_t n = -k;
    uint32_t t = (uint32_t)(q + ((n * FW_LOG2_10_MUL) >> FW_LOG2_10_SHIFT) + 1);
    const uint32_t *g = fw_pow10_g[n - FW_POW10_N_MIN];
    uint32_t gh = g[0], gl = g[1];
    uint32_t out = c & 1u, cb = c << 2;
    uint32_t vb = mul_rto(cb, gh, gl, t);
    uint32_t vbl = mul_rto(cb - 2u + asym, gh, gl, t) + out;   /* + out: strict when c is odd */
    uint32_t vbr = mul_rto(cb + 2u, gh, gl, t) - out;
    uint32_t s = vb >> 2, d;
    if (s >= 10u) {   /* a multiple of 10^(k+1) in R has fewer digits than s: it wins alone */
        uint32_t sp = s / 10u, u40 = sp * 40u;
        uint32_t upin = vbl <= u40, wpin = u40 + 40u <= vbr;
        if (upin != wpin) {
            d = sp + wpin;
            k++;
            goto strip;
        }
    }
    uint32_t u4 = s << 2;
    uint32_t uin = vbl <= u4, win = u4 + 4u <= vbr;
    if (uin != win) d = s + win;
    else d = s + (vb > u4 + 2u || (vb == u4 + 2u && (s & 1u)));   /* nearest, ties to even */
strip:   /* trailing zeros (a multiple of 10^(k+1), or s + 1 = 10^j): at most 8, as d < 2^28 */
    if (d % 10u == 0u) {
        d /= 10u;
        k++;
        if (d % 10000u == 0u) { d /= 10000u; k += 4; }
        if (d % 100u == 0u) { d /= 100u; k += 2; }
        if (d % 10u == 0u) { d /= 10u; k++; }
    }
    *exp10 = k;
    return d;
}

uint32_t fw_f32_shortest(uint32_t mag_bits, int32_t *exp10)
{
    return shortest(mag_bits, exp10);
}

uint32_t fw_fmt_f32(char *out, float v)
{
    uint32_t bits = fw_f32_bits(v), mag = bits & 0x7FFFFFFFu;
    char *p = out;
    if (mag > 0x7F800000u) { memcpy(out, "nan", 4); return 3; }
    if (bits >> 31) *p++ = '-';
    if (mag == 0x7F800000u) { memcpy(p, "inf", 4); return (uint32_t)(p - out) + 3u; }
    if (mag == 0u) { p[0] = '0'; p[1] = 0; return (uint32_t)(p - out) + 1u; }
    int32_t e10;
    char tmp[DIGIT_TMP];
    uint32_t d = shortest(mag, &e10);
    const char *b = digits_before(tmp + 12, d);
    int32_t nd = (int32_t)(tmp + 12 - b), point = nd + e10;   /* point: digits before the '.' */
    if (point > 0 && point < nd) {   /* dd.ddd (the usual case: no zeros to write) */
        copy12(p, b);
        p[point] = '.';
        copy12(p + point + 1, b + point);
        p += nd + 1;
    } else {
        /* 0.000ddd or ddd000: at most 44 zeros (1e-45) or 38 (3.4e38), written as 48 zeros (12
         * stores, no loop) before or after the digits. out has FW_F32_TEXT_MAX = 64 bytes: at most
         * 59 are written (sign, "0.", 44 zeros, 12-byte digit copy; or sign, 9 digits, 48 zeros). */
        if (point <= 0) {
            zeros48(p);
            p[1] = '.';
            copy12(p + 2 - point, b);
            p += 2 - point + nd;
        } else {
            copy12(p, b);
            zeros48(p + nd);
            p += point;
        }
    }
    *p = 0;
    return (uint32_t)(p - out);
}
