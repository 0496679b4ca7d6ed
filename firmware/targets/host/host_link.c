/* host_link.c: the station link of the host target (serial frames or slcan lines). */
#include <errno.h>
#include <string.h>
#include <unistd.h>
#include "host.h"

#define OUT_MAX (1u << 20)   /* like the simulated board's USB buffer: beyond it, frames are dropped */
static uint8_t out_buf[OUT_MAX];

int host_link_pending(const host_link_t *l) { return l->out_len > 0; }

void host_link_flush(host_link_t *l)
{
    uint32_t done = 0;
    while (done < l->out_len) {
        ssize_t n = write(l->fd, out_buf + done, l->out_len - done);
        if (n > 0) { done += (uint32_t)n; continue; }
        if (n < 0 && errno == EINTR) continue;
        if (n < 0 && (errno == EIO || errno == EPIPE)) {   /* nobody listening: the bytes are lost */
            l->bytes_dropped += l->out_len - done;
            done = l->out_len;
        }
        break;   /* EAGAIN: poll for POLLOUT */
    }
    memmove(out_buf, out_buf + done, l->out_len - done);
    l->out_len -= done;
}

void host_link_write(host_link_t *l, const uint8_t *buf, uint32_t len)
{
    if (l->out_len + len > OUT_MAX) { l->bytes_dropped += len; return; }
    memcpy(out_buf + l->out_len, buf, len);
    l->out_len += len;
    if (l->out_len == len) host_link_flush(l);
}

void host_uart_write(void *ctx, const uint8_t *buf, uint32_t len) { host_link_write(&((host_ctx_t *)ctx)->link, buf, len); }

static const char HEX[] = "0123456789ABCDEF";

void host_can_send(void *ctx, uint16_t id, uint8_t dlc, const uint8_t *data)
{
    uint8_t line[32];
    uint32_t k = 0;
    line[k++] = 't';
    line[k++] = (uint8_t)HEX[(id >> 8) & 7u];
    line[k++] = (uint8_t)HEX[(id >> 4) & 15u];
    line[k++] = (uint8_t)HEX[id & 15u];
    line[k++] = (uint8_t)('0' + dlc);
    for (uint8_t i = 0; i < dlc; i++) { line[k++] = (uint8_t)HEX[data[i] >> 4]; line[k++] = (uint8_t)HEX[data[i] & 15u]; }
    line[k++] = '\r';
    host_link_write(&((host_ctx_t *)ctx)->link, line, k);
}

static int hexv(uint8_t c)
{
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    if (c >= 'a' && c <= 'f') return c - 'a' + 10;
    return -1;
}

static void slcan_line(fw_board_t *b, const uint8_t *s, uint32_t n)
{
    uint8_t data[8];
    if (n < 5 || s[0] != 't') return;   /* only standard data frames; adapter commands ignored */
    int h0 = hexv(s[1]), h1 = hexv(s[2]), h2 = hexv(s[3]), dlc = s[4] - '0';
    if (h0 < 0 || h1 < 0 || h2 < 0 || dlc < 0 || dlc > 8 || n < 5u + 2u * (uint32_t)dlc) return;
    for (int i = 0; i < dlc; i++) {
        int hi = hexv(s[5 + 2 * i]), lo = hexv(s[6 + 2 * i]);
        if (hi < 0 || lo < 0) return;
        data[i] = (uint8_t)(hi << 4 | lo);
    }
    fw_can_rx(b, (uint16_t)(h0 << 8 | h1 << 4 | h2), (uint8_t)dlc, data);
}

void host_slcan_rx(host_link_t *l, fw_board_t *b, const uint8_t *data, uint32_t len)
{
    for (uint32_t i = 0; i < len; i++) {
        uint8_t c = data[i];
        if (c == '\r' || c == '\n') {
            if (l->in_len) slcan_line(b, l->in_line, l->in_len);
            l->in_len = 0;
        } else if (l->in_len < sizeof l->in_line) {
            l->in_line[l->in_len++] = c;
        } else {
            l->in_len = 0;   /* garbage without an end: drop it */
        }
    }
}
