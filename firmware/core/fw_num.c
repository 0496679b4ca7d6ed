/* fw_num.c: exact decimal parsing and shortest float32 formatting (see fw_num.h). */
#include <string.h>
#include "fw_num.h"

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

static void big_pow(big_t *a, uint32_t base, uint32_t n)   /* a *= base^n */
{
    while (n--) big_mul_add(a, base, 0);
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

static uint32_t big_divmod_small(big_t *a, uint32_t d)   /* a /= d, returns remainder */
{
    uint64_t rem = 0;
    for (uint32_t i = BIG_WORDS; i-- > 0;) {
        uint64_t cur = (rem << 32) | a->w[i];
        a->w[i] = (uint32_t)(cur / d);
        rem = cur % d;
    }
    return (uint32_t)rem;
}

uint32_t fw_f32_bits(float v) { uint32_t u; memcpy(&u, &v, 4); return u; }
float fw_bits_f32(uint32_t u) { float v; memcpy(&v, &u, 4); return v; }
int fw_f32_finite(float v) { return (fw_f32_bits(v) & 0x7F800000u) != 0x7F800000u; }

static double bits_f64(uint64_t u) { double v; memcpy(&v, &u, 8); return v; }

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
    if (exp10 >= 0) big_pow(&r, 10, (uint32_t)exp10); else big_pow(&d, 10, (uint32_t)-exp10);
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

int fw_parse_real(const char *s, uint32_t len, double *f64, float *f32)
{
    uint8_t dig[MAX_SIG_DIGITS];
    uint32_t nd = 0, i = 0;
    int neg = 0, sticky = 0, any = 0;
    int32_t exp10 = 0;
    uint64_t b64;
    uint32_t b32;
    while (len && (s[len - 1] == ' ' || s[len - 1] == '\t')) len--;
    while (i < len && (s[i] == ' ' || s[i] == '\t')) i++;
    if (i < len && (s[i] == '+' || s[i] == '-')) neg = s[i++] == '-';
    if (word_is(s + i, len - i, "inf") || word_is(s + i, len - i, "infinity")) {
        b64 = 0x7FF0000000000000ull; b32 = 0x7F800000u;
        goto special;
    }
    if (word_is(s + i, len - i, "nan")) {
        b64 = 0x7FF8000000000000ull; b32 = 0x7FC00000u;
        goto special;
    }
    for (int frac = 0; i < len; i++) {
        char c = s[i];
        if (c == '_' ) {   /* only between two digits */
            if (!any || i + 1 >= len || s[i + 1] < '0' || s[i + 1] > '9' || s[i - 1] < '0' || s[i - 1] > '9') return -1;
            continue;
        }
        if (c == '.') {
            if (frac) return -1;
            frac = 1;
            continue;
        }
        if (c < '0' || c > '9') break;
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
            if (s[i] == '_' && edig && i + 1 < len && s[i + 1] >= '0' && s[i + 1] <= '9') continue;
            if (s[i] < '0' || s[i] > '9') return -1;
            edig = 1;
            if (e < 100000) e = e * 10 + (s[i] - '0');
        }
        if (!edig) return -1;
        exp10 += eneg ? -e : e;
    }
    while (nd && dig[nd - 1] == 0) { nd--; exp10++; }   /* trailing zeros kept as exponent */
    decimal_to_bits(dig, nd, exp10, sticky, neg, &b64, &b32);
    if (f64) *f64 = bits_f64(b64);
    if (f32) *f32 = fw_bits_f32(b32);
    return 0;
special:
    if (neg) { b64 |= 1ull << 63; b32 |= 0x80000000u; }
    if (f64) *f64 = bits_f64(b64);
    if (f32) *f32 = fw_bits_f32(b32);
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
        if (s[i] < '0' || s[i] > '9') return -1;
        if (v > (UINT64_C(9223372036854775808) - (uint64_t)(s[i] - '0')) / 10u) return -1;
        v = v * 10u + (uint64_t)(s[i] - '0');
    }
    if (!neg && v > (uint64_t)INT64_MAX) return -1;
    *out = neg ? (int64_t)(0u - v) : (int64_t)v;
    return 0;
}

uint32_t fw_fmt_u32(char *out, uint32_t v)
{
    char tmp[10];
    uint32_t n = 0, k = 0;
    do { tmp[n++] = (char)('0' + v % 10u); v /= 10u; } while (v);
    while (n) out[k++] = tmp[--n];
    out[k] = 0;
    return k;
}

uint32_t fw_fmt_i32(char *out, int32_t v)
{
    if (v < 0) { out[0] = '-'; return 1 + fw_fmt_u32(out + 1, 0u - (uint32_t)v); }
    return fw_fmt_u32(out, (uint32_t)v);
}

uint32_t fw_fmt_hex32(char *out, uint32_t v)
{
    static const char hex[] = "0123456789ABCDEF";
    for (int i = 0; i < 8; i++) out[i] = hex[(v >> (28 - 4 * i)) & 0xFu];
    out[8] = 0;
    return 8;
}

/* Exact decimal digits of |v| (finite, nonzero): returns nd, value = 0.d1d2.. * 10^(*point). */
static uint32_t exact_digits(uint32_t bits, uint8_t *dig, int32_t *point)
{
    uint32_t ex = (bits >> 23) & 0xFFu, m = bits & 0x7FFFFFu;
    int32_t e = ex ? (int32_t)ex - 150 : -149;
    if (ex) m |= 0x800000u;
    big_t n;
    big_set(&n, m);
    int32_t dexp = 0;
    if (e >= 0) big_pow(&n, 2, (uint32_t)e); else { big_pow(&n, 5, (uint32_t)-e); dexp = e; }
    uint8_t rev[128];
    uint32_t nr = 0;
    while (!big_zero(&n)) {
        uint32_t chunk = big_divmod_small(&n, 1000000000u);
        for (int k = 0; k < 9; k++) { rev[nr++] = (uint8_t)(chunk % 10u); chunk /= 10u; }
    }
    while (nr && rev[nr - 1] == 0) nr--;
    uint32_t nd = 0;
    for (uint32_t k = nr; k-- > 0;) dig[nd++] = rev[k];
    *point = (int32_t)nd + dexp;
    while (nd && dig[nd - 1] == 0) nd--;
    return nd;
}

uint32_t fw_fmt_f32(char *out, float v)
{
    uint32_t bits = fw_f32_bits(v), k = 0;
    int neg = (bits >> 31) != 0;
    uint32_t mag = bits & 0x7FFFFFFFu;
    if (mag > 0x7F800000u) { memcpy(out, "nan", 4); return 3; }
    if (neg) out[k++] = '-';
    if (mag == 0x7F800000u) { memcpy(out + k, "inf", 4); return k + 3; }
    if (mag == 0) { out[k++] = '0'; out[k] = 0; return k; }
    uint8_t dig[128], cand[128];
    int32_t point;
    uint32_t nd = exact_digits(mag, dig, &point), p = 1, cn = 0;
    int32_t cpoint = point;
    for (; p <= nd; p++) {   /* fewest digits, rounded to nearest (ties even), that read back */
        memcpy(cand, dig, p);
        cn = p;
        cpoint = point;
        if (p < nd) {
            int up = dig[p] > 5;
            if (dig[p] == 5) {
                int rest = 0;
                for (uint32_t j = p + 1; j < nd; j++) rest |= dig[j];
                up = rest || (cand[p - 1] & 1u);
            }
            if (up) {
                uint32_t j = p;
                while (j > 0 && cand[j - 1] == 9) cand[--j] = 0;
                if (j == 0) { cand[0] = 1; cn = 1; cpoint++; } else cand[j - 1]++;
            }
        }
        while (cn > 1 && cand[cn - 1] == 0) cn--;
        uint64_t b64;
        uint32_t b32;
        decimal_to_bits(cand, cn, cpoint - (int32_t)cn, 0, 0, &b64, &b32);
        if (b32 == mag) break;
    }
    if (cpoint <= 0) {
        out[k++] = '0'; out[k++] = '.';
        for (int32_t z = 0; z < -cpoint; z++) out[k++] = '0';
        for (uint32_t j = 0; j < cn; j++) out[k++] = (char)('0' + cand[j]);
    } else {
        for (uint32_t j = 0; j < cn || (int32_t)j < cpoint; j++) {
            if ((int32_t)j == cpoint) out[k++] = '.';
            out[k++] = (char)('0' + (j < cn ? cand[j] : 0));
        }
    }
    out[k] = 0;
    return k;
}
