/* fw_frame.h: design 3.1 framing `$BODY*HH\n` (fw_frame/fw_unframe/fw_xor_checksum are declared in
 * fw_board.h), a line accumulator for targets and the core, comma-field splitting and a small
 * body builder for replies. No heap: every buffer is the caller's. */
#ifndef FW_FRAME_H
#define FW_FRAME_H

#include <stdint.h>

#define FW_MAX_FIELDS 16u
#define FW_TX_BODY_MAX 768u   /* longest reply body (S frame with 12 worst-case floats) */

/* Line accumulator: feed one byte; returns 1 when a line ended (newline) and line, line_len hold it
 * (without '\n'; a trailing '\r' is left to fw_unframe), -1 when a line ended that was longer than
 * cap (discarded: garbage), 0 otherwise. buf/cap/len/overflow are the caller's storage. */
int fw_line_push(uint8_t *buf, uint32_t cap, uint32_t *len, uint8_t *overflow, uint8_t byte,
                 const uint8_t **line, uint32_t *line_len);

typedef struct fw_linebuf {
    uint8_t buf[200];
    uint32_t len;
    uint8_t overflow;
} fw_linebuf_t;
static inline int fw_linebuf_push(fw_linebuf_t *lb, uint8_t byte, const uint8_t **line, uint32_t *len)
{
    return fw_line_push(lb->buf, (uint32_t)sizeof lb->buf, &lb->len, &lb->overflow, byte, line, len);
}

typedef struct fw_field { const char *p; uint32_t len; } fw_field_t;
/* Split body at ','; returns the number of fields (at most max; more -> max + 1 and the rest lost). */
uint32_t fw_split(const uint8_t *body, uint32_t len, fw_field_t *f, uint32_t max);
int fw_field_is(const fw_field_t *f, const char *text);

/* Reply body builder; overflow makes fw_tx_frame return 0 (nothing sent). On the per-sample path
 * (every D frame): numbers are formatted straight into body, fw_tx_frame copies and checksums a
 * word at a time (fw_frame.c; targets/qemu/README.md has the instruction counts). */
typedef struct fw_tx {
    char body[FW_TX_BODY_MAX];
    uint32_t len;
    uint8_t overflow;
} fw_tx_t;
void fw_tx_begin(fw_tx_t *t, const char *kind);
void fw_tx_str(fw_tx_t *t, const char *s);             /* ",s" */
void fw_tx_raw(fw_tx_t *t, const char *s, uint32_t n); /* appends n bytes, no comma */
void fw_tx_u32(fw_tx_t *t, uint32_t v);
void fw_tx_i32(fw_tx_t *t, int32_t v);
void fw_tx_f32(fw_tx_t *t, float v);
void fw_tx_hex32(fw_tx_t *t, uint32_t v);
/* `$BODY*HH\n` into out (cap >= FW_TX_BODY_MAX + 5); returns its length, 0 on overflow. */
uint32_t fw_tx_frame(const fw_tx_t *t, uint8_t *out, uint32_t cap);

#endif
