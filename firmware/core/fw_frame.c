/* fw_frame.c: design 3.1 framing codec, line accumulator, field splitting, reply builder.
 *
 * Per-sample cost matters here (every D frame passes through the builder and fw_frame): numbers are
 * formatted straight into the body, the checksum and the copy into the output go a word at a time
 * (unaligned 32-bit loads/stores are fine on the Cortex-M4 and on hosts; memcpy of 4 bytes compiles
 * to one of each), and no libc call is made for short strings. */
#include <string.h>
#include "fw_board.h"
#include "fw_frame.h"
#include "fw_num.h"

#if defined(__GNUC__)
#define FW_INLINE static inline __attribute__((always_inline))
#else
#define FW_INLINE static inline
#endif

static const char HEX[] = "0123456789ABCDEF";

FW_INLINE uint32_t load32(const uint8_t *p) { uint32_t w; memcpy(&w, p, 4); return w; }
FW_INLINE void store32(uint8_t *p, uint32_t w) { memcpy(p, &w, 4); }

FW_INLINE uint8_t fold32(uint32_t w)
{
    w ^= w >> 16;
    w ^= w >> 8;
    return (uint8_t)w;
}

uint8_t fw_xor_checksum(const uint8_t *body, uint32_t len)
{
    uint32_t w = 0, i = 0;
    for (; i + 4u <= len; i += 4u) w ^= load32(body + i);
    uint8_t x = fold32(w);
    for (; i < len; i++) x ^= body[i];
    return x;
}

/* out[0..len) = body[0..len), returns the XOR of the bytes copied. */
FW_INLINE uint8_t copy_xor(uint8_t *out, const uint8_t *body, uint32_t len)
{
    uint32_t w = 0, i = 0;
    for (; i + 8u <= len; i += 8u) {   /* two words per turn: half the loop overhead */
        uint32_t v0 = load32(body + i), v1 = load32(body + i + 4u);
        store32(out + i, v0);
        store32(out + i + 4u, v1);
        w ^= v0 ^ v1;
    }
    if (i + 4u <= len) {
        uint32_t v = load32(body + i);
        store32(out + i, v);
        w ^= v;
        i += 4u;
    }
    uint8_t x = fold32(w);
    for (; i < len; i++) {
        out[i] = body[i];
        x ^= body[i];
    }
    return x;
}

static uint32_t frame_into(const uint8_t *body, uint32_t len, uint8_t *out, uint32_t cap)
{
    if (len > cap || cap - len < 5u) return 0;
    out[0] = '$';
    uint8_t x = copy_xor(out + 1, body, len);
    out[len + 1] = '*';
    out[len + 2] = (uint8_t)HEX[x >> 4];
    out[len + 3] = (uint8_t)HEX[x & 0xFu];
    out[len + 4] = '\n';
    return len + 5u;
}

uint32_t fw_frame(const uint8_t *body, uint32_t len, uint8_t *out, uint32_t cap)
{
    return frame_into(body, len, out, cap);
}

static int hexval(uint8_t c)   /* upper-case only, as the contract says */
{
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    return -1;
}

int32_t fw_unframe(const uint8_t *line, uint32_t len, const uint8_t **body)
{
    if (len && line[len - 1] == '\r') len--;
    if (len < 4 || line[0] != '$' || line[len - 3] != '*') return -1;
    int hi = hexval(line[len - 2]), lo = hexval(line[len - 1]);
    if (hi < 0 || lo < 0) return -1;
    uint32_t n = len - 4u;
    if (fw_xor_checksum(line + 1, n) != (uint8_t)((hi << 4) | lo)) return -1;
    *body = line + 1;
    return (int32_t)n;
}

int fw_line_push(uint8_t *buf, uint32_t cap, uint32_t *len, uint8_t *overflow, uint8_t byte,
                 const uint8_t **line, uint32_t *line_len)
{
    if (byte == '\n') {
        int was = *overflow;
        *line = buf;
        *line_len = *len;
        *len = 0;
        *overflow = 0;
        return was ? -1 : 1;
    }
    if (*overflow) return 0;
    if (*len >= cap) { *overflow = 1; *len = 0; return 0; }
    buf[(*len)++] = byte;
    return 0;
}

uint32_t fw_split(const uint8_t *body, uint32_t len, fw_field_t *f, uint32_t max)
{
    uint32_t n = 0, start = 0;
    for (uint32_t i = 0; i <= len; i++) {
        if (i == len || body[i] == ',') {
            if (n >= max) return max + 1u;
            f[n].p = (const char *)body + start;
            f[n].len = i - start;
            n++;
            start = i + 1;
        }
    }
    return n;
}

int fw_field_is(const fw_field_t *f, const char *text)
{
    uint32_t i = 0;
    for (; i < f->len; i++) {
        if (f->p[i] != text[i] || text[i] == 0) return 0;   /* text shorter, or a byte differs */
    }
    return text[i] == 0;
}

/* ---- reply builder ---- */

void fw_tx_raw(fw_tx_t *t, const char *s, uint32_t n)
{
    if (t->overflow || n > FW_TX_BODY_MAX - t->len) { t->overflow = 1; return; }
    char *p = t->body + t->len;
    t->len += n;
    if (n > 16u) { memcpy(p, s, n); return; }
    while (n--) *p++ = *s++;
}

void fw_tx_begin(fw_tx_t *t, const char *kind)
{
    t->overflow = 0;
    if (kind[0] && !kind[1]) {   /* every frame kind of design 3.1 is one letter */
        t->body[0] = kind[0];
        t->len = 1;
        return;
    }
    t->len = 0;
    fw_tx_raw(t, kind, (uint32_t)strlen(kind));
}

void fw_tx_str(fw_tx_t *t, const char *s)
{
    fw_tx_raw(t, ",", 1);
    fw_tx_raw(t, s, (uint32_t)strlen(s));
}

/* Room for ',' plus n bytes plus the formatter's NUL: then format in place (the NUL lands inside the
 * body, beyond len, and is overwritten by whatever comes next). */
FW_INLINE char *tx_room(fw_tx_t *t, uint32_t n)
{
    if (t->overflow || n + 2u > FW_TX_BODY_MAX - t->len) return NULL;
    char *p = t->body + t->len;
    *p = ',';
    return p + 1;
}

void fw_tx_u32(fw_tx_t *t, uint32_t v)
{
    char *p = tx_room(t, 10u);
    if (p) { t->len += 1u + fw_fmt_u32(p, v); return; }
    char b[12];
    fw_tx_raw(t, ",", 1);
    fw_tx_raw(t, b, fw_fmt_u32(b, v));
}

void fw_tx_i32(fw_tx_t *t, int32_t v)
{
    char *p = tx_room(t, 11u);
    if (p) { t->len += 1u + fw_fmt_i32(p, v); return; }
    char b[12];
    fw_tx_raw(t, ",", 1);
    fw_tx_raw(t, b, fw_fmt_i32(b, v));
}

void fw_tx_hex32(fw_tx_t *t, uint32_t v)
{
    char *p = tx_room(t, 8u);
    if (p) { t->len += 1u + fw_fmt_hex32(p, v); return; }
    char b[9];
    fw_tx_raw(t, ",", 1);
    fw_tx_raw(t, b, fw_fmt_hex32(b, v));
}

void fw_tx_f32(fw_tx_t *t, float v)
{
    char *p = tx_room(t, FW_F32_TEXT_MAX - 1u);
    if (p) { t->len += 1u + fw_fmt_f32(p, v); return; }
    char b[FW_F32_TEXT_MAX];
    fw_tx_raw(t, ",", 1);
    fw_tx_raw(t, b, fw_fmt_f32(b, v));
}

uint32_t fw_tx_frame(const fw_tx_t *t, uint8_t *out, uint32_t cap)
{
    if (t->overflow) return 0;
    return frame_into((const uint8_t *)t->body, t->len, out, cap);
}
