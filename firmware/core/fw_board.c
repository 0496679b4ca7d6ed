/* fw_board.c: boot, byte/frame intake and the per-sample path shared by both links. */
#include <string.h>
#include "fw_board_internal.h"
#include "fw_nvm.h"

uint32_t fw_board_sizeof(void) { return (uint32_t)sizeof(fw_board_t); }

uint8_t fw_can_scale(const fw_identity_t *id, float *ug_per_can_lsb)
{
    uint8_t shift = 0;
    while (shift < 16u && id->ug_per_lsb * (float)(1u << shift) * 32767.0f < 1.9e6f) shift++;
    if (ug_per_can_lsb) *ug_per_can_lsb = id->ug_per_lsb * (float)(1u << shift);
    return shift;
}

void fw_send_tx(fw_board_t *b, const fw_tx_t *t)
{
    uint8_t out[FW_TX_BODY_MAX + 5u];
    uint32_t n = fw_tx_frame(t, out, (uint32_t)sizeof out);
    if (n == 0 || !b->hal->uart_write) { b->frames_dropped++; return; }
    b->hal->uart_write(b->hal->ctx, out, n);
}

void fw_send_error(fw_board_t *b, const char *code, const char *text, const char *arg, uint32_t arg_len)
{
    fw_tx_t t;
    fw_tx_begin(&t, "E");
    fw_tx_str(&t, code);
    fw_tx_str(&t, text);
    if (arg) fw_tx_raw(&t, arg, arg_len);
    fw_send_tx(b, &t);
}

uint32_t fw_odr_ratio(double src_hz, double dst_hz)
{
    if (!(dst_hz > 0.0) || dst_hz > src_hz * (1.0 + 1e-9)) return 0;
    double k = src_hz / dst_hz;
    if (!(k < 2147483647.0)) return 0;
    double r = (double)(int64_t)(k + 0.5);
    double d = k - r;
    if (d < 0.0) d = -d;
    return d < 1e-6 ? (uint32_t)r : 0;
}

void fw_set_decimation(fw_board_t *b, uint32_t k)
{
    b->decim = k;
    b->phase = 0;
    b->odr_hz = b->id.odr_hz / (float)k;
}

void fw_board_init(fw_board_t *b, const fw_hal_t *hal, const fw_identity_t *id, uint8_t can_node)
{
    memset(b, 0, sizeof *b);
    b->hal = hal;
    b->id = *id;
    b->id.serial[FW_SERIAL_MAX] = 0;
    b->id.sensor[FW_SENSOR_MAX] = 0;
    b->id.fw[FW_FW_MAX] = 0;
    b->can_node = can_node;
    fw_set_decimation(b, 1);
    b->can_shift = fw_can_scale(&b->id, &b->can_ug_per_lsb);
    fw_selfcal_reset(&b->selfcal);
    fw_nvm_boot(b);
    if (!can_node) {
        for (uint32_t k = 0; k < FW_NVM_SLOTS; k++) {
            if (b->nvm_corrupt_mask & (1u << k)) {
                char num[2] = { (char)('0' + k), 0 };
                fw_send_error(b, "NVM", "calibration record CRC mismatch in slot ", num, 1);
            }
        }
    }
}

static void serial_line(fw_board_t *b, const uint8_t *line, uint32_t len)
{
    uint32_t dollar = len;
    const uint8_t *body;
    while (dollar > 0 && line[dollar - 1] != '$') dollar--;
    if (dollar == 0) { b->rx_bad_frames++; return; }      /* no frame at all: garbage */
    dollar--;
    if (dollar > 0) b->rx_bad_frames++;                   /* garbage before the frame */
    int32_t n = fw_unframe(line + dollar, len - dollar, &body);
    if (n < 0) { b->rx_bad_frames++; return; }
    fw_serial_command(b, body, (uint32_t)n);
}

void fw_uart_rx(fw_board_t *b, const uint8_t *data, uint32_t len)
{
    if (b->can_node) return;
    for (uint32_t i = 0; i < len; i++) {
        const uint8_t *line;
        uint32_t n;
        int r = fw_line_push(b->rx_line, FW_RX_LINE_MAX, &b->rx_len, &b->rx_overflow, data[i], &line, &n);
        if (r < 0) b->rx_bad_frames++;
        else if (r > 0) serial_line(b, line, n);
    }
}

void fw_can_rx(fw_board_t *b, uint16_t id, uint8_t dlc, const uint8_t *data)
{
    if (!b->can_node || id != 0x600u + b->can_node) return;
    if (dlc > 8) dlc = 8;
    fw_can_command(b, dlc, data);
}

void fw_sample(fw_board_t *b, const fw_raw_sample_t *s)
{
    int emit = b->phase == 0;
    b->phase = b->decim > 1 ? (b->phase + 1u) % b->decim : 0;
    if (!emit) return;
    if (b->selfcal_on) {
        fw_selfcal_scale_t sc = { b->id.ug_per_lsb * 1e-6f, b->id.t_lsb_per_c, b->id.t_lsb_at_25c };
        if (fw_selfcal_update(&b->selfcal, s->t_us, s->acc, s->temp, &sc) == 1 && b->selfcal.n_seg > 0
            && !b->can_node)
            fw_serial_segment(b, &b->selfcal.seg[b->selfcal.n_seg - 1u]);
    }
    if (!b->streaming) return;
    if (b->can_node) fw_can_sample(b, s);
    else fw_serial_sample(b, s);
}
