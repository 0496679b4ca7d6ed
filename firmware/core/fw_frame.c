/* fw_frame.c: design 3.1 framing codec, line accumulator, field splitting, reply builder. */
#include <string.h>
#include "fw_board.h"
#include "fw_frame.h"
#include "fw_num.h"

static const char HEX[] = "0123456789ABCDEF";

uint8_t fw_xor_checksum(const uint8_t *body, uint32_t len)
{
    uint8_t x = 0;
    for (uint32_t i = 0; i < len; i++) x ^= body[i];
    return x;
}

uint32_t fw_frame(const uint8_t *body, uint32_t len, uint8_t *out, uint32_t cap)
{
    if (cap < len + 5u || len > cap) return 0;
    uint8_t x = fw_xor_checksum(body, len);
    out[0] = '$';
    memcpy(out + 1, body, len);
    out[len + 1] = '*';
    out[len + 2] = (uint8_t)HEX[x >> 4];
    out[len + 3] = (uint8_t)HEX[x & 0xFu];
    out[len + 4] = '\n';
    return len + 5u;
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
    uint32_t n = (uint32_t)strlen(text);
    return f->len == n && memcmp(f->p, text, n) == 0;
}

void fw_tx_raw(fw_tx_t *t, const char *s, uint32_t n)
{
    if (t->overflow || t->len + n > FW_TX_BODY_MAX) { t->overflow = 1; return; }
    memcpy(t->body + t->len, s, n);
    t->len += n;
}

void fw_tx_begin(fw_tx_t *t, const char *kind)
{
    t->len = 0;
    t->overflow = 0;
    fw_tx_raw(t, kind, (uint32_t)strlen(kind));
}

void fw_tx_str(fw_tx_t *t, const char *s)
{
    fw_tx_raw(t, ",", 1);
    fw_tx_raw(t, s, (uint32_t)strlen(s));
}

void fw_tx_u32(fw_tx_t *t, uint32_t v) { char b[12]; fw_tx_raw(t, ",", 1); fw_tx_raw(t, b, fw_fmt_u32(b, v)); }
void fw_tx_i32(fw_tx_t *t, int32_t v) { char b[12]; fw_tx_raw(t, ",", 1); fw_tx_raw(t, b, fw_fmt_i32(b, v)); }
void fw_tx_hex32(fw_tx_t *t, uint32_t v) { char b[9]; fw_tx_raw(t, ",", 1); fw_tx_raw(t, b, fw_fmt_hex32(b, v)); }
void fw_tx_f32(fw_tx_t *t, float v) { char b[FW_F32_TEXT_MAX]; fw_tx_raw(t, ",", 1); fw_tx_raw(t, b, fw_fmt_f32(b, v)); }

uint32_t fw_tx_frame(const fw_tx_t *t, uint8_t *out, uint32_t cap)
{
    if (t->overflow) return 0;
    return fw_frame((const uint8_t *)t->body, t->len, out, cap);
}
